"""Protocol and stream decoder: exact counts on a crafted stream, and fuzzing (never raises,
never yields a frame whose CRC is bad)."""

from __future__ import annotations

import numpy as np
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from softphantom.sensing.protocol import (
    DataFrame,
    InfoFrame,
    StreamDecoder,
    decode_body,
    encode_data,
    encode_info,
    encode_set_osr,
)


def _frames(n, start=0):
    rng = np.random.default_rng(start)
    return [encode_data((start + k) & 0xFFFF, 52_000 * k, 100, rng.integers(40_000, 60_000, 5)) for k in range(n)]


def test_exact_counts_on_a_crafted_stream():
    good = _frames(10)
    corrupt = bytearray(good[3]); corrupt[12] ^= 0x10                      # bad CRC
    stream = (b"\x55\xaa partial frame" + b"\x00"                          # joining mid-frame
              + good[0] + good[1] + good[2] + bytes(corrupt)               # 3 ok, 1 CRC error
              + b"line noise \x01\x02\x00"                                 # 1 malformed body
              + good[4] + good[5][:17] + good[6]                           # truncated 5 merges into 6
              + bytes(range(1, 200))                                       # 199 bytes w/o delimiter
              + b"\x00" + good[8] + good[9])                               # 7 is lost in the link
    dec = StreamDecoder()
    got = []
    for i in range(0, len(stream), 7):                                     # arbitrary chunking
        got += dec.feed(stream[i:i + 7])
    s = dec.stats
    assert [f.seq for f in got] == [0, 1, 2, 4, 8, 9]
    assert (s.frames_ok, s.sync_discards) == (6, 1)
    # rejected bodies: the flipped frame (CRC), the line noise, and 5's truncated head merged
    # with 6 (COBS or CRC, depending on its bytes)
    assert s.crc_errors >= 1 and s.crc_errors + s.malformed == 3
    assert s.overflows == 1          # the 199-byte run, dropped up to its delimiter
    assert (s.seq_gaps, s.frames_lost) == (2, 4)   # 3 (crc), then 5, 6, 7
    assert s.bytes_in == len(stream)


def test_wrap_info_and_reset():
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
    # a CRC-valid frame with an impossible field is rejected, not passed on
    dec.feed(encode_data(2, 9_200_000, 0, [0] * 5))
    assert dec.stats.malformed == 1 and dec.stats.frames_ok == 6
    # our own command echoed back on a loopback is not a board frame
    dec.feed(encode_set_osr(25))
    assert dec.stats.malformed == 2


def _valid(frame):
    body = frame[:-1] if frame.endswith(b"\x00") else frame
    return decode_body(body)       # raises if invalid: a yielded frame must re-decode cleanly


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.binary(max_size=400), st.lists(st.integers(1, 60), max_size=10))
def test_fuzz_random_bytes_never_raise(data, cuts):
    dec = StreamDecoder()
    pos = 0
    for c in cuts + [len(data)]:
        for f in dec.feed(data[pos:pos + c]):
            assert isinstance(f, (DataFrame, InfoFrame))
        pos += c
    assert dec.stats.bytes_in == len(data)


@settings(max_examples=150, deadline=None)
@given(n=st.integers(1, 8), flips=st.lists(st.tuples(st.integers(0, 10_000), st.integers(0, 7)), max_size=6),
       cut=st.integers(0, 400), seed=st.integers(0, 2**16))
def test_fuzz_bit_flips_and_truncations(n, flips, cut, seed):
    frames = _frames(n, seed)
    stream = bytearray(b"".join(frames))
    for pos, bit in flips:
        stream[pos % len(stream)] ^= 1 << bit
    stream = bytes(stream[: len(stream) - (cut % len(stream))])
    dec = StreamDecoder()
    got = dec.feed(stream) + dec.feed(b"\x00")
    originals = {f[:-1] for f in frames}
    for f in got:
        # every accepted frame is one the board actually sent (a flip that survives the CRC would
        # have to hit a 1-in-65536 collision; with ≤ 6 flips in one frame CRC-16 catches them all)
        assert encode_data(f.seq, f.t_us, f.osr, f.raw)[:-1] in originals
    s = dec.stats
    assert s.frames_ok == len(got) <= n
    if not flips and cut % len(b"".join(frames)) == 0:
        assert s.frames_ok == n and s.rejected == 0
