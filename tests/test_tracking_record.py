"""What ``softphantom track`` writes (TrackerSink): lost frames as explicit gaps, never NaN; a file is
marked complete only when it was closed after its last frame; ``read_truth`` warns on an incomplete one."""

import json
import math

import numpy as np
import pytest
from tracker_paths import written_json

from softphantom.evaluation import read_truth
from softphantom.stream.recording import read_recording
from softphantom.tracking import read_track
from softphantom.tracking.record import TrackerSink

NAN3, NAN4 = (math.nan,) * 3, (math.nan,) * 4
LOST = (3, 70, 71)  # 3 is inside the rest window (the first 0.5 s of valid samples)
N = 120


def feed(sink, n=N, lost=LOST):
    """Frame i at i/100 s: x = 0.1 m + 1 mm per frame after frame 60; lost frames as Motive sends them."""
    for i in range(n):
        ok = i not in lost
        sink.add(i / 100, (0.1 + 0.001 * max(i - 60, 0), 0.0, 0.0) if ok else NAN3, (0, 0, 0, 1) if ok else NAN4,
                 ok, frame=i + 1, latency_ms=5.0)


@pytest.mark.parametrize("suffix", [".mcap", ".csv"])
def test_lost_frames_are_gaps_counted_in_the_file(tmp_path, suffix):
    p = tmp_path / f"take{suffix}"
    with TrackerSink(p, body="bip", meta={"source": "test"}) as sink:
        feed(sink)
    data = written_json(p)
    assert data and not any(b"NaN" in d or b"nan" in d for d in data)
    if suffix == ".mcap":
        rec = read_recording(p)
        assert rec.complete and len(rec.tracker) == N
        assert [m["position_m"] for m in rec.tracker if not m["valid"]] == [None] * len(LOST)
        assert rec.metadata["complete"] == "true" and rec.metadata["frames"] == str(N)
        assert rec.metadata["frames_body_lost"] == str(len(LOST)) and rec.metadata["source"] == "test"
        tr = read_track(p)
        assert list(np.flatnonzero(~tr.valid)) == list(LOST)
    else:
        lines = p.read_text().splitlines()
        meta = json.loads(lines[0][2:])
        assert meta["complete"] is True and meta["frames"] == N and meta["frames_body_lost"] == len(LOST)
        assert len(lines) == 2 + N  # every frame has its row; a lost one has its time and empty cells
        assert [ln for ln in lines[2:] if ln.endswith(",,,,,,")] == [f"{i / 100!r},,,,,," for i in LOST]
    tru = read_truth(p)
    assert len(tru.t) == N - len(LOST) and tru.meta["lost_frames"] == len(LOST) and not tru.meta["warnings"]
    # the poses relative to rest: x rises 1 mm per frame after frame 60
    np.testing.assert_allclose(tru.mm_deg()[-1, 0], N - 1 - 60, atol=1e-9)


@pytest.mark.parametrize("suffix", [".mcap", ".csv"])
def test_a_session_that_fails_leaves_an_incomplete_file(tmp_path, suffix):
    p = tmp_path / f"take{suffix}"
    with pytest.raises(ConnectionError):
        with TrackerSink(p, body="bip") as sink:
            feed(sink)
            raise ConnectionError("the network went down")
    if suffix == ".mcap":
        assert not read_recording(p).complete
    else:
        assert json.loads(p.read_text().splitlines()[0][2:])["complete"] is False
    tru = read_truth(p)  # everything recorded is kept
    assert len(tru.t) == N - len(LOST) and tru.meta["complete"] is False
    (w,) = tru.meta["warnings"]
    assert "incomplete" in w and f"{N} frames" in w and f"body lost in {len(LOST)}" in w, w


@pytest.mark.parametrize("suffix", [".mcap", ".csv"])
def test_an_interrupted_write_leaves_an_incomplete_file(tmp_path, suffix, monkeypatch):
    """Ctrl-C that lands inside a write (the caller catches it, as ``track`` does): the frame may be
    half written, so the file is not complete."""
    p = tmp_path / f"take{suffix}"
    with TrackerSink(p, body="bip") as sink:
        feed(sink, 80)
        target = sink._rec if suffix == ".mcap" else sink._reg
        name = "write_tracker" if suffix == ".mcap" else "add"

        def interrupted(*a, **k):
            raise KeyboardInterrupt

        monkeypatch.setattr(target, name, interrupted)
        try:
            sink.add(0.8, (0.1, 0, 0), (0, 0, 0, 1), True)
        except KeyboardInterrupt:
            pass
    assert sink.complete is False
    tru = read_truth(p)  # the frames before the interrupted one are kept
    assert len(tru.t) == 80 - len(LOST) and tru.meta["complete"] is False and "incomplete" in tru.meta["warnings"][0]


def test_ctrl_c_between_frames_is_a_clean_stop(tmp_path):
    """Ctrl-C is how ``track`` is stopped: outside a write, the file is complete."""
    p = tmp_path / "take.mcap"
    with TrackerSink(p, body="bip") as sink:
        try:
            feed(sink)
            raise KeyboardInterrupt
        except KeyboardInterrupt:
            sink.end_meta["stopped_by"] = "Ctrl-C"
    rec = read_recording(p)
    assert sink.complete and rec.complete and rec.metadata["stopped_by"] == "Ctrl-C"
    assert read_truth(p).meta["warnings"] == []


def test_truth_csv_cut_at_a_row_boundary_is_caught(tmp_path):
    """A complete truth CSV copied short (cut after a whole row): its header still counts the frames."""
    p = tmp_path / "take.csv"
    with TrackerSink(p, body="bip") as sink:
        feed(sink)
    lines = p.read_text().splitlines(keepends=True)
    p.write_text("".join(lines[:-20]))
    tru = read_truth(p)
    (w,) = tru.meta["warnings"]
    assert f"{N - 20} of the {N} frames" in w, w


def test_body_never_seen(tmp_path):
    p = tmp_path / "take.csv"
    with TrackerSink(p, body="bip") as sink:
        feed(sink, 30, lost=range(30))
    meta = json.loads(p.read_text().splitlines()[0][2:])
    assert meta["complete"] is True and meta["frames_body_lost"] == 30 and meta["rest_window_s"] is None
    from softphantom.errors import FileFormatError

    with pytest.raises(FileFormatError, match="body lost in all 30 frames"):
        read_truth(p)


def test_encode_writes_non_finite_as_null():
    """The recording's JSON encoder keeps its promise (NaN → null) for any message, e.g. the live
    view's tracker feed, which passes NaN for a lost body."""
    from softphantom.stream.schema import encode

    assert json.loads(encode({"t_s": 1.0, "position_m": [math.nan, 1.0, math.inf], "ok": True})) == \
        {"t_s": 1.0, "position_m": [None, 1.0, None], "ok": True}
