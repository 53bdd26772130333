"""``softphantom evaluate``: the report renders (HTML well-formed, sections, tables, every image a PNG),
tracker files as truth, and broken inputs give one line and exit code 2."""

import sys
from html.parser import HTMLParser
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from softphantom.cli import main

sys.path.insert(0, str(Path(__file__).resolve().parent))
from evaluation_synth import motion, write_motive_truth, write_run, write_snapshot  # noqa: E402

VOID = {"meta", "img", "br", "hr", "link", "input", "source", "col", "area", "base", "wbr"}


class Checker(HTMLParser):
    """Checks nesting (every non-void element closed in order) and collects ids, tables, images."""

    def __init__(self):
        super().__init__(convert_charrefs=True)
        self.stack, self.errors, self.ids, self.tables, self.imgs, self.text = [], [], set(), [], [], []

    def handle_starttag(self, tag, attrs):
        a = dict(attrs)
        if "id" in a:
            self.ids.add(a["id"])
        if tag == "table":
            self.tables.append(a.get("class"))
        if tag == "img":
            self.imgs.append(a.get("src"))
        if tag not in VOID:
            self.stack.append(tag)

    def handle_endtag(self, tag):
        if tag in VOID:
            return
        if not self.stack or self.stack[-1] != tag:
            self.errors.append(f"</{tag}> closes {self.stack[-1:] or 'nothing'}")
        else:
            self.stack.pop()

    def handle_data(self, data):
        self.text.append(data)


def parse(report: Path) -> Checker:
    c = Checker()
    c.feed(report.read_text(encoding="utf-8"))
    c.close()
    assert not c.errors and not c.stack, (c.errors, c.stack)
    return c


def assert_images(report: Path, c: Checker):
    assert c.imgs
    for src in c.imgs:
        assert "://" not in src and not src.startswith("/")  # relative, next to the report
        p = report.parent / src
        data = p.read_bytes()
        assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 2000, src


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    d = tmp_path_factory.mktemp("run")
    pe, pt = write_run(d, lag_ms=100.0, seed=5)
    return d, pe, pt


def test_report_renders_with_snapshot(run, capsys):
    d, pe, pt = run
    snap = write_snapshot(d / "peak.vtu")
    out = d / "out"
    assert main(["evaluate", "--estimate", str(pe), "--truth", str(pt), "--out", str(out), "--snapshot", str(snap)]) == 0
    printed = capsys.readouterr().out
    assert "lag" in printed and "report:" in printed and "Table I" in printed
    report = out / "report.html"
    c = parse(report)
    assert {"summary", "pose", "force", "errors", "table-i", "snapshot"} <= c.ids
    assert c.tables == ["info", "errors", "force-errors", "target-errors", "clinical"]
    assert set(c.imgs) == {"pose_6dof.png", "force.png", "snapshot_3d.png"}
    assert_images(report, c)
    text = " ".join(c.text)
    assert "coloured by |displacement_mm|" in text
    for study in ("Lagerburg", "Stone", "Podder"):
        assert study in text
    # the measured lag is stated and close to the injected 100 ms + the 250 ms later start
    import re

    m = re.search(r"([\d.]+) ms, measured", text)
    assert m and abs(float(m.group(1)) - 100.0) < 5.0


def test_report_without_snapshot_and_without_displacement(run, capsys):
    d, pe, pt = run
    out = d / "out2"
    assert main(["evaluate", "--estimate", str(pe), "--truth", str(pt), "--out", str(out), "--lag-ms", "100"]) == 0
    # an estimate without the in_envelope column (a truth, an older estimate): nothing said about it
    # (with it: test_estimates_clamped_at_the_envelope_are_counted_noted_and_shaded)
    assert "load envelope" not in capsys.readouterr().out
    c = parse(out / "report.html")
    assert "No snapshot given" in " ".join(c.text) and "snapshot_3d.png" not in c.imgs
    assert "100.0 ms, given" in " ".join(c.text)
    assert_images(out / "report.html", c)
    snap = write_snapshot(d / "plain.vtu", with_displacement=False)
    out3 = d / "out3"
    assert main(["evaluate", "--estimate", str(pe), "--truth", str(pt), "--out", str(out3), "--snapshot", str(snap)]) == 0
    c = parse(out3 / "report.html")
    assert "no 'displacement_mm' point array" in " ".join(c.text)
    assert_images(out3 / "report.html", c)


def test_motive_csv_as_truth_registered_by_rest_window(run, capsys):
    d, pe, _ = run
    mot = write_motive_truth(d / "take.csv")
    out = d / "out_motive"
    assert main(["evaluate", "--estimate", str(pe), "--truth", str(mot), "--out", str(out)]) == 0
    capsys.readouterr()
    c = parse(out / "report.html")
    text = " ".join(c.text)
    assert "rest window" in text and "motive-csv" in text
    # registration by the rest window recovers the motion in the model frame (no tracker noise
    # here; the file's 6 decimals of mm and 9 of the quaternion are the limit)
    from softphantom.evaluation import evaluate, read_estimate, read_truth

    tru = read_truth(mot)
    assert tru.meta["lost_frames"] == 1 and len(tru.t) == 839
    want, _ = motion(tru.t)
    err = np.abs(tru.mm_deg() - want)
    assert err[:, :3].max() < 1e-4 and err[:, 3:].max() < 1e-5
    ev = evaluate(tru, read_estimate(pe))
    assert abs(ev.lag_ms - 100.0) < 5.0


def test_lag_says_what_it_consists_of(run, tmp_path, capsys):
    """A tracker on its own clock (the take 253 ms ahead of the run's clock, the estimate 100 ms
    late): the measured lag is 100 − 253 ms; the output and the report say that it includes the
    clock offset, which is not known; given the offset they split it into the estimator's latency;
    files on one named clock need nothing given. Signs are written once ("−148.2", never "−-")."""
    import re

    d, pe, pt = run
    mot = write_motive_truth(tmp_path / "take.csv", clock_offset_s=0.253)

    out = tmp_path / "unknown"
    assert main(["evaluate", "--estimate", str(pe), "--truth", str(mot), "--out", str(out)]) == 0
    printed = " ".join(capsys.readouterr().out.split())
    lag = float(re.search(r"lag ([−+][\d.]+) ms =", printed).group(1).replace("−", "-"))
    assert abs(lag - (100.0 - 253.0)) < 5.0
    assert "not known here" in printed and "the figure includes that offset" in printed
    assert "--clock-offset-ms" in printed and "truth clock: take_time" in printed
    text = " ".join(" ".join(parse(out / "report.html").text).split())
    assert "what the lag consists of" in text and "the figure includes that offset" in text
    for blob in (printed, text, (out / "report.html").read_text(encoding="utf-8")):
        assert "−-" not in blob and "--1" not in blob and "-−" not in blob
    from softphantom.evaluation.report import lag_caption  # the 6-DoF figure's title line

    assert "−-" not in lag_caption(SimpleNamespace(lag_ms=lag, lag=object())) and "−1" in lag_caption(
        SimpleNamespace(lag_ms=lag, lag=object()))
    # the offset given: the estimator's own latency comes out (the injected 100 ms)
    out = tmp_path / "given"
    assert main(["evaluate", "--estimate", str(pe), "--truth", str(mot), "--out", str(out),
                 "--clock-offset-ms", "253"]) == 0
    printed = " ".join(capsys.readouterr().out.split())
    m = re.search(r"the estimator's latency ([−+][\d.]+) ms − the clock offset \+253\.0 ms", printed)
    assert m and abs(float(m.group(1).replace("−", "-")) - 100.0) < 5.0, printed
    assert "latency" in " ".join(parse(out / "report.html").text)
    # a virtual run's tracker file: its virtual.json records the offset, which is then used
    run_dir = tmp_path / "virtual_run"
    run_dir.mkdir()
    (run_dir / "tracker_motive.csv").write_bytes(mot.read_bytes())
    (run_dir / "virtual.json").write_text('{"tracker": {"clock_offset_s": 0.253}}')
    assert main(["evaluate", "--estimate", str(pe), "--truth", str(run_dir / "tracker_motive.csv"),
                 "--out", str(tmp_path / "virtual_out")]) == 0
    printed = " ".join(capsys.readouterr().out.split())
    m = re.search(r"the estimator's latency ([−+][\d.]+) ms − the clock offset \+253\.0 ms \(truth clock − "
                  r"estimate clock, from virtual\.json beside the tracker file", printed)
    assert m and abs(float(m.group(1).replace("−", "-")) - 100.0) < 5.0, printed
    # both files on the scenario clock (a virtual run's truth.csv and an estimate of it): no offset
    same = tmp_path / "same"
    same.mkdir()
    pe2, pt2 = write_run(same, lag_ms=100.0, seed=5, truth_meta={"clock": "scenario (s)"},
                         estimate_meta={"source": "virtual:synthetic"})
    assert main(["evaluate", "--estimate", str(pe2), "--truth", str(pt2), "--out", str(same / "out")]) == 0
    printed = " ".join(capsys.readouterr().out.split())
    assert "= the estimator's latency (both files on the same clock: scenario (s))" in printed


@pytest.mark.parametrize(
    "case, expect",
    [
        ("missing", "no such file"),
        ("truncated", "no CSV header line"),
        ("columns", "lacks column"),
        ("lag", "--lag-ms must be"),
        ("tracker", "cannot tell the tracker format"),
        ("snapshot", "not a readable VTU"),
    ],
)
def test_cli_broken_inputs_one_line_exit_2(run, tmp_path, capsys, case, expect):
    d, pe, pt = run
    args = {"--estimate": str(pe), "--truth": str(pt), "--out": str(tmp_path / "o")}
    if case == "missing":
        args["--estimate"] = str(tmp_path / "nope.csv")
    elif case == "truncated":
        data = pe.read_bytes()  # cut inside the header (a cut inside the rows drops the last one, with a note)
        (tmp_path / "cut.csv").write_bytes(data[: data.index(b"\n") + 5])
        args["--estimate"] = str(tmp_path / "cut.csv")
    elif case == "columns":
        (tmp_path / "e.csv").write_text('# {}\nt_s,force_y_N\n0,1\n')
        args["--estimate"] = str(tmp_path / "e.csv")
    elif case == "lag":
        args["--lag-ms"] = "soon"
    elif case == "tracker":
        (tmp_path / "t.dat").write_bytes(b"\x00\x01\x02 not a tracker file")
        args["--truth"] = str(tmp_path / "t.dat")
    elif case == "snapshot":
        (tmp_path / "s.vtu").write_text("<VTKFile> broken")
        args["--snapshot"] = str(tmp_path / "s.vtu")
    argv = ["evaluate"] + [x for kv in args.items() for x in kv]
    assert main(argv) == 2
    err = capsys.readouterr().err
    msg = " ".join(err.split())  # one message; rich wraps it at the console width
    assert msg.startswith("error: ") and expect.lower() in msg.lower(), msg
    assert "Traceback" not in err and len(msg) < 400


def test_estimates_clamped_at_the_envelope_are_counted_noted_and_shaded(run, tmp_path, capsys):
    from softphantom.evaluation.files import read_table, write_table
    from softphantom.evaluation.report import shade_outside

    d, pe, pt = run
    tab = read_table(pe)
    n = len(tab.columns["t_s"])
    flag = np.ones(n)
    flag[n // 3: n // 3 + 40] = 0  # one clamped stretch of 40 samples
    flag[-5:] = 0  # and the last five
    est = write_table(tmp_path / "clamped.csv", tab.meta, {**tab.columns, "in_envelope": flag})
    out = tmp_path / "rep"
    assert main(["evaluate", "--estimate", str(est), "--truth", str(pt), "--out", str(out), "--lag-ms", "100"]) == 0
    printed = " ".join(capsys.readouterr().out.split())
    want = f"45 of {n} estimates ({45 / n:.0%}) at or beyond the estimator's load envelope"
    assert want in printed
    text = " ".join(parse(out / "report.html").text)
    assert want in text and f"45 of {n} estimates" in text
    # the shading: one span per clamped stretch
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots()
    t = np.arange(n, dtype=float)
    shade_outside(ax, t, flag > 0.5, label=True)
    assert len(ax.patches) == 2 and ax.get_legend_handles_labels()[1] == ["clamped at the envelope"]
    shade_outside(ax, t, np.ones(n, bool))
    assert len(ax.patches) == 2
    plt.close(fig)


def _hollow_tet10(path, quadratic=True):
    """A hollow ball (outer radius 30 mm, a void of 12 mm inside) of 10-node tets (or 4-node), the
    mid-edge nodes bulged 0.2 mm outward; a displacement field along +y. (mesh, corner boundary
    faces of the outer surface, of the void)."""
    import meshio
    from scipy.spatial import Delaunay

    rng = np.random.default_rng(3)
    u = rng.normal(size=(400, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    pts = np.vstack([u[:250] * 0.030, u[250:] * 0.012, u[:150] * 0.021])
    tets = Delaunay(pts).simplices
    tets = tets[np.linalg.norm(pts[tets].mean(axis=1), axis=1) > 0.012]  # the void
    cells, nodes = [("tetra", tets)], pts
    if quadratic:
        edges = [(0, 1), (1, 2), (0, 2), (0, 3), (1, 3), (2, 3)]  # VTK's mid-edge order
        mid, extra, t10 = {}, [], []
        for t in tets:
            row = list(t)
            for a, b in edges:
                key = (min(t[a], t[b]), max(t[a], t[b]))
                if key not in mid:
                    p = (pts[t[a]] + pts[t[b]]) / 2
                    mid[key] = len(pts) + len(extra)
                    extra.append(p + 2e-4 * p / np.linalg.norm(p))
                row.append(mid[key])
            t10.append(row)
        nodes = np.vstack([pts, extra])
        cells = [("tetra10", np.array(t10))]
    disp = np.zeros_like(nodes)
    disp[:, 1] = 3.0 * (nodes[:, 1] > 0)
    meshio.write(path, meshio.Mesh(nodes, cells, point_data={"displacement_mm": disp}))
    return meshio.read(path), tets, pts


def test_snapshot_of_10_node_tets_draws_the_curved_outer_surface(run, tmp_path, capsys):
    """The truth's snapshot holds 10-node tets: its outer surface is drawn, each 6-node face as 4 flat
    triangles through its mid-edge nodes; the walls of a void inside are not."""
    from softphantom.evaluation.report import surface_triangles

    mesh, tets, pts = _hollow_tet10(tmp_path / "p2.vtu")
    faces = np.sort(np.concatenate([tets[:, [0, 1, 2]], tets[:, [0, 1, 3]], tets[:, [1, 2, 3]], tets[:, [0, 2, 3]]]), 1)
    key, cnt = np.unique(faces, axis=0, return_counts=True)
    boundary = key[cnt == 1]
    outer = boundary[np.linalg.norm(pts[boundary].mean(axis=1), axis=1) > 0.02]
    assert 0 < len(outer) < len(boundary)  # the void has walls too
    tris = surface_triangles(mesh)
    assert tris.shape == (4 * len(outer), 3)
    n_corner = len(pts)
    assert (tris >= n_corner).any(axis=1).all()  # every flat triangle passes through a mid-edge node
    r = np.linalg.norm(np.asarray(mesh.points)[np.unique(tris)], axis=1)
    assert r.min() > 0.02  # nothing of the void's wall
    # through the command: the report shows the figure
    d, pe, pt = run
    out = tmp_path / "rep"
    assert main(["evaluate", "--estimate", str(pe), "--truth", str(pt), "--out", str(out),
                 "--snapshot", str(tmp_path / "p2.vtu")]) == 0
    capsys.readouterr()
    c = parse(out / "report.html")
    assert "snapshot_3d.png" in c.imgs and "nothing to draw" not in " ".join(c.text)
    assert "coloured by |displacement_mm| (max 3.00 mm)" in " ".join(c.text)
    assert_images(out / "report.html", c)
    # 6-node triangles alone (a surface file) are drawn split too; a mesh of neither says which cells it has
    import meshio

    m = meshio.Mesh(np.asarray(mesh.points), [("triangle6", np.zeros((0, 6), int))])
    t6 = np.array([[0, 1, 2, n_corner, n_corner + 1, n_corner + 2]])
    assert surface_triangles(meshio.Mesh(np.asarray(mesh.points), [("triangle6", t6)])).tolist() == \
        [[0, n_corner, n_corner + 2], [n_corner, 1, n_corner + 1], [n_corner + 2, n_corner + 1, 2],
         [n_corner, n_corner + 1, n_corner + 2]]
    assert surface_triangles(m) is None and surface_triangles(meshio.Mesh(np.zeros((2, 3)), [("line", [[0, 1]])])) is None
    lin, _, _ = _hollow_tet10(tmp_path / "p1.vtu", quadratic=False)
    assert surface_triangles(lin).shape == (len(outer), 3)


def test_target_table_has_a_header_for_each_column_and_no_blank_one(run):
    import re

    d, pe, pt = run
    out = d / "targets"
    assert main(["evaluate", "--estimate", str(pe), "--truth", str(pt), "--out", str(out), "--lag-ms", "100"]) == 0
    html = (out / "report.html").read_text(encoding="utf-8")
    table = re.search(r'<table class="target-errors">(.*?)</table>', html).group(1)
    heads = re.findall(r"<th>(.*?)</th>", table)
    assert heads[0] == "target" and all(h.strip() for h in heads), heads
    for row in re.findall(r"<tr>(.*?)</tr>", table.split("<tbody>")[1]):
        assert len(re.findall(r"<td>", row)) == len(heads)


def test_report_measures_the_lag_before_and_after_the_tube_compensation(tmp_path):
    # an estimate 5 ms late, compensated; the recording beside it holds the transducers' volumes,
    # 95 ms behind the estimator's: the report says +100 ms before compensation, +5 ms after
    from softphantom.evaluation import read_estimate, write_table
    from softphantom.evaluation.report import tube_advance_ms, tube_lag_line

    meta = {"lag_compensation": "model", "tube_tau_ms": [102.2, 101.9], "lag_noise_gain_rest": 1.3,
            "source": "virtual:synthetic"}
    pe, _ = write_run(tmp_path, lag_ms=5.0, estimate_meta=meta)
    cols = read_estimate(pe)
    t = cols.t
    arms = ("front_zpos", "back_xpos")
    est = {"t_s": t, **{n: cols.mm_deg()[:, k] for k, n in enumerate(("x_mm", "y_mm", "z_mm", "yaw_deg",
                                                                       "pitch_deg", "roll_deg"))}}
    v_now, _ = motion(t - 0.005)
    v_tube, _ = motion(t - 0.100)
    for k, a in enumerate(arms):
        est[f"dVmeas_{a}_mm3"] = 4.0 * v_now[:, 1 + 2 * k]
    write_table(pe, meta, est)
    rec = {"t_s": t, **{f"dV_{a}_mm3": 4.0 * v_tube[:, 1 + 2 * k] for k, a in enumerate(arms)}}
    est_series = read_estimate(pe)
    assert tube_advance_ms(est_series) is None  # no recording: the model's τ only
    write_table(tmp_path / "recording.csv", {"kind": "recording"}, rec)
    adv, name = tube_advance_ms(est_series)
    assert name == "recording.csv" and adv == pytest.approx(95.0, abs=3.0)
    line = tube_lag_line(est_series.meta, 5.0, (adv, name))
    assert f"lag before compensation +{5.0 + adv:.1f} ms, after +5.0 ms (measured" in line
    # against a truth that holds the cavities' volumes: each lag measured from it, the same advance
    from softphantom.evaluation import read_truth

    v_true, _ = motion(t)
    tru = {"t_s": t, **{n: v_true[:, k] for k, n in enumerate(("x_mm", "y_mm", "z_mm", "yaw_deg", "pitch_deg",
                                                                "roll_deg"))},
           **{f"dV_{a}_mm3": 4.0 * v_true[:, 1 + 2 * k] for k, a in enumerate(arms)}}
    truth = read_truth(write_table(tmp_path / "truth_dv.csv", {"kind": "virtual-truth"}, tru))
    adv_t, _ = tube_advance_ms(est_series, truth)
    assert adv_t == pytest.approx(95.0, abs=3.0)
    assert tube_advance_ms(read_estimate(write_table(tmp_path / "off.csv", {"lag_compensation": "off"}, est))) is None
