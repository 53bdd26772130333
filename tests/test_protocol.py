"""Protocol and stream decoder: exact counts on crafted streams of both versions, one frame lost
per damaging line fault, content checks after the CRC, duplicates, and fuzzing (never raises,
never yields a frame the board did not send)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from softphantom.sensing.faults import DAMAGING, FAULT_KINDS, damage, faulty_stream
from softphantom.sensing.protocol import (
    DATA_FRAME_BYTES,
    DATA_FRAME_BYTES_V1,
    DataFrame,
    FrameError,
    InfoFrame,
    StreamDecoder,
    decode_body,
    encode_data,
    encode_get_info,
    encode_info,
    encode_set_osr,
    frame,
)


def _frames(n, start=0, version=2):
    rng = np.random.default_rng(start)
    return [encode_data((start + k) & 0xFFFF, 52_000 * k, 100, rng.integers(40_000, 60_000, 5), version=version)
            for k in range(n)]


def _feed_chunked(dec, stream, step=7):
    got = []
    for i in range(0, len(stream), step):                                  # arbitrary chunking
        got += dec.feed(stream[i:i + step])
    return got


@pytest.mark.parametrize("version", [1, 2])
def test_exact_counts_on_a_crafted_stream(version):
    good = _frames(10, version=version)
    corrupt = bytearray(good[3]); corrupt[12] ^= 0x10                      # bad CRC
    stream = (b"\x55\xaa partial frame" + b"\x00"                          # joining mid-frame
              + good[0] + good[1] + good[2] + bytes(corrupt)               # 3 ok, 1 CRC error
              + b"line noise \x01\x02\x00"                                 # 1 malformed body
              + good[4] + good[5][:17] + good[6]                           # 5 truncated: 6 survives
              + bytes(range(1, 200))                                       # 199 bytes w/o delimiter
              + b"\x00" + good[8] + good[9])                               # 7 is lost in the link
    dec = StreamDecoder()
    got = _feed_chunked(dec, stream)
    s = dec.stats
    assert [f.seq for f in got] == [0, 1, 2, 4, 6, 8, 9]
    assert (s.frames_ok, s.sync_discards, s.version) == (7, 1, version)
    assert s.crc_errors == 1 and s.overflows == 1
    # version 2: 5's head is a body of its own (malformed or CRC); version 1: it merges with 6, whose
    # whole body is recovered from the merged body's tail
    assert s.recovered == (1 if version == 1 else 0)
    assert s.crc_errors + s.malformed + s.content_errors == (2 if version == 1 else 3)
    assert (s.seq_gaps, s.frames_lost) == (3, 3)   # 3 (crc), 5 (truncated), 7 (gone)
    assert s.bytes_in == len(stream)


@pytest.mark.parametrize("version", [1, 2])
@pytest.mark.parametrize("kind", FAULT_KINDS)
def test_one_frame_lost_per_damaging_fault_none_per_harmless(version, kind):
    sf = faulty_stream(3000, 0.1, np.random.default_rng(7), version=version, kinds=(kind,))
    dec = StreamDecoder()
    got = [f.seq for f in _feed_chunked(dec, sf.data, 4096)]
    sent = {int(s) for s in sf.seqs}
    assert set(got) <= sent and len(got) == len(set(got))                 # nothing invented, no repeats
    lost = len(sent) - len(got)
    assert sf.n_faults > 200
    assert lost == (sf.n_faults if kind in DAMAGING else 0)               # 1.00 frame per damaging fault
    assert dec.stats.frames_lost == lost                                   # and the counter agrees


def test_leading_delimiter_saves_the_next_frame_byte_for_byte():
    a, b = _frames(2)
    assert a[0] == 0 and a[-1] == 0 and len(a) == DATA_FRAME_BYTES == 35
    assert len(_frames(1, version=1)[0]) == DATA_FRAME_BYTES_V1 == 34
    dec = StreamDecoder()
    # a reset mid-frame: 20 bytes of a, then b; b's own 0x00 ends a's remains
    assert [f.seq for f in dec.feed(a[:20] + b)] == [1]
    assert dec.stats.recovered == 0 and dec.stats.frames_lost == 0        # nothing before to compare


def test_both_versions_and_their_commands():
    v1 = encode_data(1, 1000, 100, [51150] * 5, version=1)
    doc = "04 01 01 01 03 e8 03 01 02 64" + " 03 ce c7 01" * 5 + " 03 50 7d 00"   # docs/protocol.md, v1
    assert v1 == bytes.fromhex(doc)
    dec = StreamDecoder()
    assert [f.seq for f in dec.feed(v1)] == [1] and dec.stats.version == 1
    assert [f.seq for f in dec.feed(encode_data(2, 53_000, 100, [51150] * 5))] == [2] and dec.stats.version == 2
    assert decode_body(v1[:-1]) == decode_body(encode_data(1, 1000, 100, [51150] * 5)[1:-1])
    assert encode_set_osr(25, version=1).hex() == "0401101903fc0800"
    assert encode_set_osr(25).hex() == "00" + "0402101903" + encode_set_osr(25)[6:].hex()
    assert encode_get_info(1)[0] != 0 and encode_get_info()[0] == 0
    with pytest.raises(Exception, match="protocol version"):
        encode_data(0, 0, 1, [0] * 5, version=3)
    with pytest.raises(FrameError, match="version 3"):
        decode_body(frame(bytes([3, 1]) + bytes(28))[1:-1])


@pytest.mark.parametrize("payload_fields, match", [
    (dict(osr=0), "osr 0 outside 1..500 .byte offset 8"),
    (dict(osr=501), "osr 501 outside"),
    (dict(osr=10, raw=[0, 0, 10_231, 0, 0]), "channel 2 above 1023·osr = 10230 .byte offset 18"),
    (dict(osr=1, raw=[0, 0, 0, 0, 2**32 - 1]), "channel 4 above"),
])
def test_content_checks_after_the_crc(payload_fields, match):
    args = dict(seq=1, t_us=0, osr=100, raw=[0] * 5) | payload_fields
    f = encode_data(**args)
    with pytest.raises(FrameError, match=match) as exc:
        decode_body(f[1:-1])
    assert exc.value.kind == "field"
    dec = StreamDecoder()
    dec.feed(encode_data(0, 0, 100, [0] * 5) + f)
    assert dec.stats.content_errors == 1 and dec.stats.frames_ok == 1 and dec.stats.crc_errors == 0
    # the boundary is accepted: 1023·osr exactly
    assert decode_body(encode_data(1, 0, 10, [10_230] * 5)[1:-1]).raw == (10_230,) * 5


def test_info_content_checks():
    with pytest.raises(FrameError, match="n_channels 4"):
        decode_body(encode_info(0, 0, n_channels=4)[1:-1])
    with pytest.raises(FrameError, match="INFO osr 0"):
        decode_body(encode_info(0, 0, osr=0)[1:-1])
    assert decode_body(encode_info(0, 0, (2, 0, 0), 5, 500)[1:-1]).osr == 500


def test_duplicates_and_stale_frames_do_not_count_as_lost():
    fr = _frames(4)
    dec = StreamDecoder()
    got = dec.feed(fr[0] + fr[1] + fr[1] + fr[1] + fr[2] + fr[3])     # 1 sent three times
    s = dec.stats
    assert [f.seq for f in got] == [0, 1, 2, 3]
    assert (s.duplicates, s.stale, s.frames_lost, s.seq_gaps, s.resets) == (2, 0, 0, 0, 0)
    # a seq repeated, or behind, on a running clock: dropped and counted, nothing lost
    dec2 = StreamDecoder()
    got = dec2.feed(fr[0] + fr[1] + encode_data(1, 52_000 + 13, 100, [0] * 5)
                    + encode_data(0, 52_000 + 26, 100, [0] * 5) + fr[2])
    assert [f.seq for f in got] == [0, 1, 2]
    assert (dec2.stats.duplicates, dec2.stats.stale, dec2.stats.frames_lost, dec2.stats.frames_ok) == (1, 1, 0, 3)
    # a late copy (its clock behind the last frame's) is a duplicate too, not a restart
    dec3 = StreamDecoder()
    got = dec3.feed(fr[0] + fr[1] + fr[2] + fr[0] + fr[3])
    assert [f.seq for f in got] == [0, 1, 2, 3] and (dec3.stats.duplicates, dec3.stats.resets) == (1, 0)


def test_wrap_info_reset_and_long_outage():
    dec = StreamDecoder()
    frames = dec.feed(encode_data(65534, 9_000_000, 100, [0] * 5) + encode_data(65535, 9_052_000, 100, [0] * 5)
                      + encode_data(0, 9_104_000, 100, [0] * 5) + encode_info(1, 9_110_000)
                      + encode_data(1, 9_156_000, 100, [0] * 5))
    assert [type(f) for f in frames] == [DataFrame] * 3 + [InfoFrame, DataFrame]
    assert dec.stats.seq_gaps == 0 and dec.stats.resets == 0         # seq wraps, INFO takes none
    # the board restarts (its clock runs backwards): a reset, not 30000 lost frames
    dec.feed(encode_info(0, 1200) + encode_data(0, 50_000, 100, [0] * 5) + encode_data(1, 102_000, 100, [0] * 5))
    assert dec.stats.resets == 1 and dec.stats.seq_gaps == 0 and dec.stats.frames_ok == 6
    # the u32 µs wrap of the board clock (every 71.6 min) is not a restart
    dec2 = StreamDecoder()
    dec2.feed(encode_data(7, 2**32 - 30_000, 100, [0] * 5) + encode_data(8, 22_000, 100, [0] * 5))
    assert dec2.stats.resets == 0 and dec2.stats.seq_gaps == 0 and dec2.stats.frames_ok == 2
    # 70 000 frames lost (seq wrapped once during the outage): the board clock tells
    p = 5 * 25 * 104
    dec3 = StreamDecoder()
    dec3.feed(encode_data(10, 0, 25, [0] * 5) + encode_data((10 + 70_001) & 0xFFFF, 70_001 * p, 25, [0] * 5))
    assert (dec3.stats.seq_gaps, dec3.stats.frames_lost) == (1, 70_000)
    # our own command echoed back on a loopback is not a board frame
    dec.feed(encode_set_osr(25))
    assert dec.stats.malformed == 1


def test_overflow_keeps_a_frame_at_the_end_of_the_run():
    fr = _frames(2, version=1)
    dec = StreamDecoder()
    got = dec.feed(fr[0] + bytes(range(1, 250)) + fr[1])             # 249 noise bytes, then frame 1
    assert [f.seq for f in got] == [0, 1] and dec.stats.overflows == 1 and dec.stats.frames_lost == 0


def _originals(frames):
    return {decode_body(f.strip(b"\x00")) for f in frames}


@settings(max_examples=150, deadline=None, derandomize=True, suppress_health_check=[HealthCheck.too_slow])
@given(st.binary(max_size=400), st.lists(st.integers(1, 60), max_size=10))
def test_fuzz_random_bytes_never_raise(data, cuts):
    dec = StreamDecoder()
    pos = 0
    for c in cuts + [len(data)]:
        for f in dec.feed(data[pos:pos + c]):
            assert isinstance(f, (DataFrame, InfoFrame))
        pos += c
    assert dec.stats.bytes_in == len(data)


@settings(max_examples=200, deadline=None, derandomize=True)
@given(n=st.integers(1, 8), flips=st.lists(st.tuples(st.integers(0, 10_000), st.integers(0, 7)), max_size=6),
       cut=st.integers(0, 400), seed=st.integers(0, 2**16), version=st.sampled_from([1, 2]))
def test_fuzz_bit_flips_and_truncations(n, flips, cut, seed, version):
    frames = _frames(n, seed, version)
    stream = bytearray(b"".join(frames))
    for pos, bit in flips:
        stream[pos % len(stream)] ^= 1 << bit
    stream = bytes(stream[: len(stream) - (cut % len(stream))])
    dec = StreamDecoder()
    got = dec.feed(stream) + dec.feed(b"\x00")
    originals = _originals(frames)
    for f in got:
        # every accepted frame is one the board actually sent (a flip that survives the CRC would
        # have to hit a 1-in-65536 collision; with ≤ 6 flips in one frame CRC-16 catches them all)
        assert f in originals
    s = dec.stats
    assert s.frames_ok == len(got) <= n
    if not flips and cut % len(b"".join(frames)) == 0:
        assert s.frames_ok == n and s.rejected == 0


@settings(max_examples=60, deadline=None, derandomize=True)
@given(seed=st.integers(0, 2**32 - 1), version=st.sampled_from([1, 2]), rate=st.floats(0.0, 0.4))
def test_fuzz_faulty_streams_lose_only_damaged_frames(seed, version, rate):
    rng = np.random.default_rng(seed)
    sf = faulty_stream(120, rate, rng, version=version)
    dec = StreamDecoder()
    got = _feed_chunked(dec, sf.data, int(rng.integers(1, 200)))
    assert [f.seq for f in got] == sorted({f.seq for f in got})          # in order, no repeats
    assert {f.seq for f in got} <= set(sf.seqs.tolist())
    assert 120 - len(got) == sf.n_damaging == dec.stats.frames_lost


def test_damage_rejects_an_unknown_kind():
    with pytest.raises(Exception, match="fault kind"):
        damage(_frames(1)[0], "teleport", np.random.default_rng(0))


@settings(max_examples=80, deadline=None, derandomize=True, suppress_health_check=[HealthCheck.too_slow])
@given(version=st.sampled_from([1, 2]), info_every=st.integers(0, 9), step=st.integers(1, 80),
       copies=st.lists(st.tuples(st.integers(0, 59), st.integers(0, 20), st.integers(1, 4)), max_size=12))
def test_fuzz_duplicated_frames_are_dropped_and_counted_never_a_restart(version, info_every, step, copies):
    """A retransmitted frame, or a doubled USB read (a run of whole frames read twice), anywhere
    after its original: dropped and counted as a duplicate; never a restart, a loss or a second sample."""
    p = 5 * 25 * 104
    msgs, is_data = [], []                           # the board's messages, an INFO now and then
    for k in range(60):
        msgs.append(encode_data(k, 1_000_000 + k * p, 25, [1000 + k] * 5, version=version))
        is_data.append(True)
        if info_every and k % info_every == 0:
            msgs.append(encode_info(k + 1, 1_000_000 + k * p + 700, osr=25, version=version))
            is_data.append(False)
    stream = bytearray()
    n_copies = n_info_copies = 0
    at = {}                                          # message index -> copies to insert after it
    for i, back, run in copies:
        i = min(i * len(msgs) // 60, len(msgs) - 1)
        first = max(0, i - back)
        last = min(i, first + run - 1)
        at.setdefault(i, []).append((first, last))
        n_copies += sum(is_data[first:last + 1])
        n_info_copies += last - first + 1 - sum(is_data[first:last + 1])
    for i, m in enumerate(msgs):
        stream += m
        for first, last in at.get(i, []):
            stream += b"".join(msgs[first:last + 1])
    dec = StreamDecoder()
    got = _feed_chunked(dec, bytes(stream), step)
    s = dec.stats
    assert [f.seq for f in got if isinstance(f, DataFrame)] == list(range(60))
    assert (s.resets, s.frames_lost, s.seq_gaps, s.rejected) == (0, 0, 0, 0)
    assert s.duplicates == n_copies and s.info_frames == len(msgs) - 60 + n_info_copies
    assert sum(isinstance(f, InfoFrame) for f in got) == len(msgs) - 60      # a copy is not handed on
