"""Outages are part of the data: link events from the serial source (silent, disconnected,
reconnected, restart, resumed), marker rows in the recording and their replay, and the replay's
refusals (a header-only recording, NaN or backwards t_s)."""

from __future__ import annotations

import numpy as np
import pytest
import serial

from softphantom.records import ChannelLayout
from softphantom.cli import main
from softphantom.errors import FileFormatError
from softphantom.sensing.chain import default_chain, nominal_tare
from softphantom.sensing.protocol import encode_data
from softphantom.sensing.recording import Recorder, read_recording
from softphantom.sensing.sources import FrameSource, ReplaySource, SerialSource, SourceEvent

REST = [51150, 51150, 51150, 51150, 4046]


class Clock:
    def __init__(self):
        self.t = 100.0

    def __call__(self):
        return self.t


def _frames(seqs, t0_us=0, dt_us=13_000):
    return b"".join(encode_data(k & 0xFFFF, t0_us + dt_us * i, 25, [r // 4 for r in REST])
                    for i, k in enumerate(seqs))


def test_serial_source_reports_silence_unplug_replug_and_restart_with_times():
    clock = Clock()
    ports = []

    def opener(url, **kw):
        if len(ports) == 1:
            ports.append(None)
            raise serial.SerialException("no such device")
        p = serial.serial_for_url("loop://", **kw)
        ports.append(p)
        return p

    src = SerialSource("fake", default_chain(), opener=opener, reconnect_every_s=0.01, clock=clock)
    assert src.read(0.001) == []                                  # opens; nothing yet
    ports[0].write(_frames(range(5), 1_000_000))
    got = src.read(0.001)
    got += src.read(0.001)
    assert len(got) == 5 and src.events() == []
    clock.t += 0.6                                                # nothing for 0.6 s: silent
    src.read(0.001)
    ev = src.events()
    assert [e.kind for e in ev] == ["silent"] and ev[0].t == pytest.approx(100.6)
    ports[0].close()                                              # unplugged
    src.read(0.001)
    assert [e.kind for e in src.events()] == ["disconnected"]
    clock.t += 1.0
    src.read(0.001)                                               # the port refuses once
    clock.t += 1.0
    src.read(0.001)                                               # opens again
    ports[2].write(_frames(range(3), 50_000))                     # a new board: clock restarted
    for _ in range(3):
        got += src.read(0.001)
    kinds = [e.kind for e in src.events()]
    assert kinds == ["reconnected", "restart", "resumed"]
    src.close()
    assert src.events() == []                                     # closing is not an outage
    assert len(got) == 8


def test_a_slow_board_of_many_channels_is_not_taken_for_silent():
    """A Mega's 16 channels at OSR 500 take 0.83 s a frame (16 × 500 × 104 µs): the host waits two
    frame periods, not its 0.5 s, before it calls the link silent."""
    clock = Clock()
    arms = tuple(f"a{i}" for i in range(15))
    chain = default_chain([500e-9] * 15, layout=ChannelLayout(arms, (), ("urethra",)))
    port = []

    def opener(url, **kw):
        port.append(serial.serial_for_url("loop://", **kw))
        return port[-1]

    src = SerialSource("fake", chain, opener=opener, clock=clock)
    src.read(0.001)
    frame_s = 16 * 500 * 13 * 128 / 16e6
    for k in range(3):
        port[0].write(encode_data(k, int(k * frame_s * 1e6), 500, [51150 // 4 * 500 // 25] * 15 + [4046 * 20]))
        got = src.read(0.001) + src.read(0.001)
        assert len(got) == 1, k
        clock.t += frame_s
        src.read(0.001)
    assert src.events() == [] and src.silence_limit_s() == pytest.approx(2 * frame_s)
    clock.t += 2 * frame_s
    src.read(0.001)
    assert [e.kind for e in src.events()] == ["silent"]
    src.close()


def test_recording_marker_rows_round_trip_and_replay(tmp_path):
    chain = default_chain()
    ms = list(FrameSource([_frames(range(10))], chain, nominal_tare(chain)))
    path = tmp_path / "r.csv"
    with Recorder(path, {"chain": chain.summary(), "tare": nominal_tare(chain).to_dict()},
                  layout=chain.layout) as rec:
        for m in ms[:5]:
            rec.write(m)
        rec.write_event(SourceEvent(ms[4].t + 0.01, "disconnected", "port /dev/ttyACM0 failed, twice"))
        rec.write_event(SourceEvent(ms[5].t, "resumed", "after 8.00 s without frames"))
        for m in ms[5:]:
            rec.write(m)
    back = read_recording(path)
    assert len(back) == 10 and np.array_equal(back.seq, np.arange(10))
    assert [(e.kind, e.detail) for e in back.events] == [
        ("disconnected", "port /dev/ttyACM0 failed; twice"), ("resumed", "after 8.00 s without frames")]
    src = ReplaySource(path, batch=3)
    seen = []
    while (b := src.read()) is not None:
        seen += [("m", m.seq) for m in b] + [("e", e.kind) for e in src.events()]
    assert seen.index(("e", "disconnected")) > seen.index(("m", 4))
    assert ("e", "resumed") in seen and len([s for s in seen if s[0] == "m"]) == 10


def test_a_frozen_board_keeps_the_recording_in_time_order(tmp_path):
    """The board freezes for 1 s, then its frames of that second arrive at once, stamped with the
    times they were sampled: earlier than the host clock that noticed the silence."""
    clock = Clock()
    port = serial.serial_for_url("loop://")
    src = SerialSource("fake", default_chain(), opener=lambda url, **kw: port, clock=clock)
    chain = default_chain()
    path = tmp_path / "frozen.csv"
    with Recorder(path, {"chain": chain.summary(), "tare": nominal_tare(chain).to_dict()},
                  layout=chain.layout) as rec:
        def step(data=b"", dt=0.0):
            port.write(data)
            clock.t += dt
            batch = src.read(0.001)
            for ev in src.events():
                rec.write_event(ev, next_t=batch[0].t if batch else None)
            for m in batch:
                rec.write(m)
        step()
        for k in range(20):                                        # 77 Hz, on time
            step(_frames([k], k * 13_000), 0.013)
        for _ in range(10):                                        # frozen: 1 s without a frame
            step(dt=0.1)
        step(_frames(range(20, 97), 20 * 13_000), 0.001)          # the frozen second, all at once
        for k in range(97, 110):
            step(_frames([k], k * 13_000), 0.013)
    back = read_recording(path)
    assert [e.kind for e in back.events] == ["silent", "resumed"]
    assert np.array_equal(back.seq, np.arange(110))
    t = np.array([float(line.split(",")[0]) for line in path.read_text().splitlines()[2:]])
    assert np.all(np.diff(t) >= 0)                                 # marker rows included
    silent, resumed = back.events
    assert silent.t == pytest.approx(back.t[19]) and resumed.t == pytest.approx(back.t[20])
    assert "no valid frame for" in silent.detail and "without frames" in resumed.detail
    # killed mid-write anywhere in the marker rows and the burst after them: the complete rows read back
    import warnings

    from softphantom.sensing.recording import TruncatedRecordingWarning

    data = path.read_bytes()
    start = data.index(b"event:silent") - 60
    cut = tmp_path / "cut.csv"
    for end in range(start, start + 400, 7):
        cut.write_bytes(data[:end])
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", TruncatedRecordingWarning)
            part = read_recording(cut)
        assert np.array_equal(part.seq, np.arange(len(part))) and len(part) >= 19


def test_reader_reads_a_marker_row_later_than_the_next_sample(tmp_path):
    """A marker row stamped when the silence was noticed, after which late frames came: only the
    samples must be in time order."""
    path = _recording(tmp_path, "late_marker.csv", ["0.0", "0.1", "0.2", "0.3"])
    lines = path.read_text().splitlines()
    marker = ["0.900000", "-1", "nan", "0"] + ["0"] * 5 + ["nan"] * 9 + ["event:silent: no valid frame for 0.60 s"]
    lines.insert(4, ",".join(marker))
    path.write_text("\n".join(lines) + "\n")
    back = read_recording(path)
    assert len(back) == 4 and [e.kind for e in back.events] == ["silent"]


def _recording(tmp_path, name, ts):
    chain = default_chain()
    ms = list(FrameSource([_frames(range(len(ts)))], chain, nominal_tare(chain)))
    path = tmp_path / name
    with Recorder(path, {"chain": chain.summary(), "tare": nominal_tare(chain).to_dict()},
                  layout=chain.layout) as rec:
        for m in ms:
            rec.write(m)
    lines = path.read_text().splitlines()
    for i, t in enumerate(ts):
        cells = lines[2 + i].split(",")
        cells[0] = t
        lines[2 + i] = ",".join(cells)
    path.write_text("\n".join(lines) + "\n")
    return path


@pytest.fixture(scope="module")
def model_dir(coarse_model, tmp_path_factory):
    from softphantom.design import save_model

    d = tmp_path_factory.mktemp("outage_model")
    save_model(coarse_model, d)
    return d


def test_replay_refuses_header_only_nan_and_backwards_time(tmp_path, capsys, model_dir):
    head = _recording(tmp_path, "h.csv", [])
    with pytest.raises(FileFormatError, match="no samples to replay"):
        ReplaySource(head)
    nan = _recording(tmp_path, "n.csv", ["0.0", "nan", "0.2"])
    with pytest.raises(FileFormatError, match="line 4: t_s is nan"):
        read_recording(nan)
    back = _recording(tmp_path, "b.csv", ["0.0", "0.5", "0.2"])
    with pytest.raises(FileFormatError, match="line 5: t_s runs backwards"):
        read_recording(back)
    # through the CLI: one line, exit 2, nothing written
    for path, msg in ((head, "no samples"), (nan, "t_s is nan"), (back, "runs backwards")):
        out = tmp_path / f"e_{path.stem}.csv"
        rc = main(["estimate", "--model", str(model_dir), "--source", f"replay:{path}", "--out", str(out)])
        err = capsys.readouterr().err
        assert rc == 2 and msg in err and "Traceback" not in err and len(err.strip().splitlines()) == 1, err
        assert not out.exists()


class _BurstySource:
    """A live source handing ``burst`` samples at once (a loaded machine's reader), with link
    events at given sample indices."""

    live = True

    def __init__(self, n, burst=4, events=()):
        import collections

        from softphantom.sensing import Measurement

        self._M = Measurement
        self.n, self.k, self.burst = n, 0, burst
        self._at = dict(events)
        self._events = collections.deque()
        self.closed = False

    def read(self, timeout_s=0.1):
        import time

        if self.k >= self.n:
            return None
        time.sleep(0.002)
        out = []
        for _ in range(self.burst):
            if self.k < self.n:
                if self.k in self._at:
                    self._events.append(SourceEvent(self.k / 77.0 - 1e-4, *self._at[self.k]))
                out.append(self._M(self.k / 77.0, self.k, self.k / 77.0, np.zeros(5, int), 25, np.zeros(4),
                                   np.zeros(4), 0.0))
                self.k += 1
        return out

    def events(self):
        out = []
        while self._events:
            out.append(self._events.popleft())
        return out

    def stats(self):
        from softphantom.sensing.protocol import DecoderStats
        from softphantom.sensing.sources import SourceStats

        return SourceStats("ok", DecoderStats())

    def close(self):
        self.closed = True


class _FastEstimator:
    from softphantom.records import BIP_LAYOUT as layout

    target_names = ("apex",)

    def __init__(self):
        self.seen = []

    def step(self, m, skipped=0):
        from softphantom.estimation import Estimate
        from softphantom.pose import Pose6

        self.seen.append(m.seq)
        z = np.zeros(3)
        return Estimate(m.t, z, 0.0, Pose6(z, z), {"apex": z}, np.zeros(4), np.zeros(4), 1.0, "optimal", 1e-4,
                        skipped, m.status, layout=self.layout)


def test_live_bursts_are_all_estimated_and_events_become_marker_rows(tmp_path, monkeypatch):
    import softphantom.estimation.stream as stream_mod
    from softphantom.estimation import estimate_stream

    # no lag limit: a stall of this test's thread on a loaded machine is then no reason to drop;
    # the old latest-sample slot dropped 3 of every burst of 4 whatever the limit
    monkeypatch.setattr(stream_mod, "MAX_LAG_S", 1e9)
    from softphantom.evaluation import read_estimate
    from softphantom.evaluation.files import read_table

    src = _BurstySource(300, burst=4, events={100: ("disconnected", "port failed"),
                                             104: ("resumed", "after 8.00 s without frames")})
    est = _FastEstimator()
    seen_events = []
    s = estimate_stream(src, est, tmp_path / "e.csv", on_event=seen_events.append)
    assert s["skipped"] == 0 and est.seen == list(range(300))      # a burst is not a reason to skip
    assert s["events"] == {"disconnected": 1, "resumed": 1}
    assert [e.status for e in seen_events] == ["event:disconnected: port failed",
                                              "event:resumed: after 8.00 s without frames"]
    tab = read_table(tmp_path / "e.csv")
    status = list(tab.columns["status"])
    i = status.index("event:disconnected: port failed")
    assert status[i + 1] == "ok" and tab.columns["t_s"][i] < tab.columns["t_s"][i + 1]     # in time order
    assert np.isnan(tab.columns["force_y_N"][i]) and tab.columns["qp_status"][i] == "none"
    assert len(status) == 302 and np.all(np.diff(tab.columns["t_s"]) >= 0)
    assert read_estimate(tmp_path / "e.csv").pose.xyz.shape == (300, 3)   # evaluate skips the markers


def test_live_queue_drops_only_what_lags_and_counts_it(tmp_path):
    import time

    from softphantom.estimation import estimate_stream

    class Slow(_FastEstimator):
        def step(self, m, skipped=0):
            time.sleep(0.004)                   # 250 Hz against 77 Hz × bursts at 2 ms: falls behind
            return super().step(m, skipped)

    src = _BurstySource(2000, burst=4)
    est = Slow()
    s = estimate_stream(src, est, tmp_path / "s.csv")
    assert s["skipped"] > 0 and s["estimates"] + s["skipped"] == 2000   # every sample accounted for
    assert est.seen == sorted(est.seen) and est.seen[-1] == 1999


def test_the_board_to_estimate_path_holds_no_memory_per_sample(tmp_path):
    """The soak's path (frames → decoder → source → estimate_stream → the estimate CSV, and the
    recorder) keeps nothing per sample: the Python heap after 3 000 frames is what it was after
    600 (numpy's arrays are traced too); it grows by ~300 bytes in all."""
    import gc
    import tracemalloc

    from stub_estimators import EchoEstimator

    from softphantom.estimation import estimate_stream

    chain = default_chain()
    heap = {}

    def chunks(n, every=50):
        clock.t = 100.0
        for k in range(0, n, every):
            if k in (600, n - every):
                gc.collect()
                heap[k] = tracemalloc.get_traced_memory()[0]
            clock.t += 0.013 * every
            yield _frames(range(k, k + every), k * 13_000)

    clock = Clock()
    tracemalloc.start()
    try:
        src = FrameSource(chunks(3_000), chain, nominal_tare(chain), clock=clock)
        estimate_stream(src, EchoEstimator(), tmp_path / "e.csv", live=False)
        est_growth = heap[2_950] - heap[600]
        heap.clear()
        with Recorder(tmp_path / "r.csv", {"chain": chain.summary()}, layout=chain.layout) as rec:
            for m in FrameSource(chunks(3_000), chain, nominal_tare(chain), clock=clock):
                rec.write(m)
        rec_growth = heap[2_950] - heap[600]
    finally:
        tracemalloc.stop()
    assert est_growth < 5_000 and rec_growth < 5_000, (est_growth, rec_growth)     # 2 bytes a sample


def test_the_refresh_estimators_history_holds_constant_memory():
    """The refresh estimator keeps each refresh's linearization error and time (6 refreshes/s on
    the coarse model): the memory is allocated once, not per refresh."""
    import gc
    import tracemalloc

    from softphantom.estimation.estimator import History

    tracemalloc.start()
    try:
        errors, times = History(width=4, size=1000), History(size=1000)
        gc.collect()
        before = tracemalloc.get_traced_memory()[0]
        for k in range(5000):
            errors.append(np.full(4, k * 1e-12))
            times.append(k * 1e-3)
        gc.collect()
        grew = tracemalloc.get_traced_memory()[0] - before
    finally:
        tracemalloc.stop()
    assert grew < 2_000, grew
    assert len(errors) == 1000 and errors.values()[-1, 0] == pytest.approx(4999e-12)
    assert times[:].tolist() == pytest.approx([k * 1e-3 for k in range(4000, 5000)])
