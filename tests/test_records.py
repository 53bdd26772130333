"""softphantom.records: the session file (one writer, one reader, versioned; files of earlier
versions still read) and the one flat form of an estimate and of a measurement."""

from __future__ import annotations

import math
import warnings

import numpy as np
import pytest

from softphantom.cli import main
from softphantom.errors import FileFormatError
from softphantom.evaluation import read_estimate, read_truth
from softphantom.pose import Pose6
from softphantom.records import (
    FILE_VERSION,
    Estimate,
    Measurement,
    SessionWriter,
    SourceEvent,
    estimate_columns,
    estimate_row,
    estimate_to_message,
    message_to_estimate,
    read_session_file,
)
from softphantom.records.measurement import measurement_to_message
from softphantom.sensing.recording import COLUMNS, Recorder, read_recording
from softphantom.records import BIP_LAYOUT
from softphantom.stream import read_estimate_csv

# Written by the version before the format was versioned (no file_version; `nan` cells, spaces in
# the metadata line of write_table): they must read as they did.
OLD_ESTIMATE = (
    '# {"softphantom":"0.1.0","kind":"softphantom-estimate","live":false}\n'
    + ",".join(estimate_columns(["apex"], BIP_LAYOUT)) + "\n"
    + "0.5,0.1,2.0,-0.1,1.5,0.0,4.0,0.0,0.0,3.0,0.0,0.0,1.0,0.0," + ",".join(["1.0"] * 4 + ["2.0"] * 4)
    + ",12.0,optimal,4.0,0,ok,1\n"
    + "0.6," + ",".join(["nan"] * 13) + "," + ",".join(["nan"] * 8) + ",nan,none,0.0,0,event:silent: no valid frame"
    " for 0.52 s,1\n"
)
OLD_TRUTH = '# {"softphantom": "0.1.0", "kind": "virtual-truth"}\nt_s,x_mm,y_mm,z_mm,yaw_deg,pitch_deg,roll_deg\n' \
            "0.0,0.0,0.0,0.0,0.0,0.0,0.0\n0.01,0.5,1.0,0.0,2.0,0.0,0.0\n"
OLD_SENSING = (
    '# {"kind":"softphantom-sensing-recording","chain":{"v_total_mm3":[14086,14086,14058,14058]},"osr":100}\n'
    + ",".join(COLUMNS) + "\n"
    + "0.100000,0,0.099000,100,51150,51150,51150,51150,4046,0.100000,0.200000,0.300000,0.400000,"
      "1.000000,2.000000,3.000000,4.000000,0.500000,ok\n"
    + "0.200000,-1,nan,0,0,0,0,0,0,nan,nan,nan,nan,nan,nan,nan,nan,nan,event:disconnected: port failed\n"
)


def test_files_of_the_earlier_unversioned_format_still_read(tmp_path):
    est, tru, sen = tmp_path / "e.csv", tmp_path / "t.csv", tmp_path / "r.csv"
    est.write_text(OLD_ESTIMATE)
    tru.write_text(OLD_TRUTH)
    sen.write_text(OLD_SENSING)
    assert read_session_file(est).version == 0
    s = read_estimate(est)
    np.testing.assert_allclose(s.mm_deg()[0], [0.0, 4.0, 0.0, 0.0, 3.0, 0.0])
    np.testing.assert_allclose(s.targets["apex"][0], [0.0, 1e-3, 0.0])
    assert len(s.t) == 1  # the marker row has no pose
    meta, msgs = read_estimate_csv(est)
    assert meta["kind"] == "softphantom-estimate" and msgs[1]["status"].startswith("event:silent")
    e = message_to_estimate(msgs[0])
    assert e.force[1] == 2.0 and e.p_urethra == pytest.approx(1500.0) and e.qp_status == "optimal"
    assert math.isnan(message_to_estimate(msgs[1]).force[0])
    assert read_truth(tru).mm_deg()[1, 4 - 3] == pytest.approx(1.0)
    rec = read_recording(sen)
    assert len(rec) == 1 and rec.dp[0, 1] == pytest.approx(200.0) and rec.dV[0, 3] == pytest.approx(4e-9)
    assert rec.events == (SourceEvent(0.2, "disconnected", "port failed"),)


def test_the_writer_versions_the_file_and_a_newer_version_is_refused_in_one_line(tmp_path, capsys):
    p = tmp_path / "e.csv"
    with SessionWriter(p, estimate_columns([], BIP_LAYOUT), {"softphantom": "0.1.0"}) as w:
        w.write_row([0.0] * len(estimate_columns([], BIP_LAYOUT)))
    f = read_session_file(p)
    assert f.meta["file_version"] == FILE_VERSION == f.version == 1
    newer = tmp_path / "newer.csv"
    newer.write_text(p.read_text().replace('"file_version": 1', '"file_version": 2'))
    with pytest.raises(FileFormatError, match=r"newer.csv: line 1: file_version 2 is newer than this softphantom reads \(1\)"):
        read_estimate(newer)
    assert main(["evaluate", "--estimate", str(newer), "--truth", str(p), "--out", str(tmp_path / "rep")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "file_version 2 is newer" in err and "Traceback" not in err
    bad = tmp_path / "bad.csv"
    bad.write_text('# {"file_version": "one"}\nt_s\n0\n')
    with pytest.raises(FileFormatError, match="line 1: file_version must be a whole number"):
        read_session_file(bad)


def test_a_writer_hands_every_row_to_the_os_and_replaces_the_metadata_at_close(tmp_path):
    p = tmp_path / "s.csv"
    w = SessionWriter(p, ["t_s", "x_mm"])
    with pytest.raises(RuntimeError):
        w.write_row([0.0, 1.0])                # no header yet
    w.start({"complete": False})
    w.write_rows([[0.0, 1.0], [0.01, math.nan]])
    assert p.read_text().splitlines()[2:] == ["0.0,1.0", "0.01,"]   # on disk before close
    w.close({"complete": True, "frames": 2})
    lines = p.read_text().splitlines()
    assert lines[0] == '# {"complete": true, "frames": 2, "file_version": 1}' and len(lines) == 4
    with pytest.raises(Exception, match="exists; recordings are never overwritten"):
        SessionWriter(p, ["t_s"], {}, exclusive=True)


def test_a_cut_row_is_dropped_with_a_warning_and_a_bad_row_names_its_line(tmp_path):
    p = tmp_path / "s.csv"
    p.write_text("# {}\nt_s,x_mm\n0,1\n0.1,2\n0.2,")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        f = read_session_file(p)
    assert [c for _, c in f.rows] == [["0", "1"], ["0.1", "2"]] and f.truncated
    assert "line 5 (byte 24, 4 bytes) ends without a newline" in str(caught[0].message)
    p.write_text("# {}\nt_s,x_mm\n0,1\n0.1\n")
    with pytest.raises(FileFormatError, match="line 4: 1 cells, the header has 2"):
        read_session_file(p)
    p.write_bytes(b"# {}\nt_s,x_mm\n0,\xff\n")
    with pytest.raises(FileFormatError, match="byte 16: not UTF-8"):
        read_session_file(p)


def _estimate(t=1.5):
    return Estimate(t=t, force=np.array([0.1, 2.0, -0.3]), p_urethra=1234.5,
                    pose=Pose6(np.array([1e-4, 4e-3, -2e-4]), np.radians([1.0, 3.0, -0.5])),
                    target_shift={"apex": np.array([0.0, 1e-3, 2e-4])}, volume_pred=np.arange(4) * 1e-9,
                    volume_meas=np.arange(4) * 2e-9, cond_W=12.0, qp_status="optimal", step_time=0.004,
                    skipped=2, status="ok", in_envelope=False, layout=BIP_LAYOUT)


def test_an_estimate_has_one_flat_form_a_message_is_a_row(tmp_path):
    e = _estimate()
    m = estimate_to_message(e, seq=3, t_pub_unix_s=10.0)
    cols = estimate_columns(["apex"], BIP_LAYOUT)
    assert set(m) - {"seq", "t_pub_unix_s"} == set(cols) and (m["seq"], m["t_pub_unix_s"]) == (3, 10.0)
    assert estimate_row(e, ["apex"]) == [m[c] for c in cols]
    p = tmp_path / "e.csv"
    with SessionWriter(p, cols, {}) as w:
        w.write_row(estimate_row(e, ["apex"]))
    _, msgs = read_estimate_csv(p)
    back = message_to_estimate(msgs[0])
    for a, b in ((back.force, e.force), (back.pose.xyz, e.pose.xyz), (back.pose.ypr, e.pose.ypr),
                 (back.target_shift["apex"], e.target_shift["apex"]), (back.volume_meas, e.volume_meas)):
        np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-15)
    assert (back.skipped, back.in_envelope, back.qp_status, back.p_urethra) == (2, False, "optimal", 1234.5)


def test_a_measurement_row_and_message_have_the_recording_columns(tmp_path):
    m = Measurement(0.5, 3, 0.49, np.arange(5) * 1000, 100, np.full(4, 1e3), np.full(4, 1e-9), 2e3, "rail:a,b")
    assert tuple(measurement_to_message(m, BIP_LAYOUT)) == COLUMNS
    p = tmp_path / "r.csv"
    with Recorder(p, {"chain": {"v_total_mm3": [14086] * 4}}, layout=BIP_LAYOUT) as rec:
        rec.write(m)
        rec.write_event(SourceEvent(0.6, "silent", "no frame, 0.5 s"))
    back = read_recording(p)
    assert back.raw.tolist() == [m.raw.tolist()] and back.status == ("rail:a;b",)
    # a marker takes the time of the sample before it (a later sample may have been sampled earlier)
    assert back.events == (SourceEvent(0.5, "silent", "no frame; 0.5 s"),)
