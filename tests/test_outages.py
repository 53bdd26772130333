"""Outages are part of the data: link events from the serial source (silent, disconnected,
reconnected, restart, resumed), marker rows in the recording and their replay, and the replay's
refusals (a header-only recording, NaN or backwards t_s)."""

from __future__ import annotations

import numpy as np
import pytest
import serial

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


def test_recording_marker_rows_round_trip_and_replay(tmp_path):
    chain = default_chain()
    ms = list(FrameSource([_frames(range(10))], chain, nominal_tare(chain)))
    path = tmp_path / "r.csv"
    with Recorder(path, {"chain": chain.summary(), "tare": nominal_tare(chain).to_dict()}) as rec:
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


def _recording(tmp_path, name, ts):
    chain = default_chain()
    ms = list(FrameSource([_frames(range(len(ts)))], chain, nominal_tare(chain)))
    path = tmp_path / name
    with Recorder(path, {"chain": chain.summary(), "tare": nominal_tare(chain).to_dict()}) as rec:
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
