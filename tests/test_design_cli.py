"""`softphantom design`: files, report numbers, one-line errors."""

from __future__ import annotations

import re

import numpy as np
import pytest

from softphantom.cli import main
from softphantom.design import load_model


@pytest.mark.slow
def test_design_command_writes_model_report_and_png(tmp_path, capsys):
    out = tmp_path / "d"
    assert main(["design", "--out", str(out), "--mesh-size-mm", "12", "--element-order", "1"]) == 0  # the envelope table
    for f in ("model.msh", "model.vtu", "model.npz", "design.toml", "report.md", "mesh.png"):
        assert (out / f).stat().st_size > 0, f
    assert (out / "mesh.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    model = load_model(out)
    report = (out / "report.md").read_text()
    row = re.search(r"\| urethra \| ([\d.]+) \| ([\d.]+) \|", report)
    assert float(row.group(1)) == 2078.0
    assert abs(float(row.group(2)) - model.cavity_volume("urethra") * 1e9) < 0.06
    assert f"nodes: {len(model.nodes)}" in report
    assert model.design.mesh.size_mm == 12.0
    assert np.isclose(model.bulb_volume() * 1e9, float(re.search(r"\| bulb \| [\d.]+ \| ([\d.]+)", report).group(1)), atol=0.06)
    # the observability table: its rest row is observability() of the written model
    from softphantom.estimation.observability import observability

    assert "## Observability" in report and "| envelope min |" in report and "| envelope max |" in report
    rest = re.search(r"^\| rest \|(.*)\|$", report, re.M).group(1).split("|")
    obs = observability(model, loaded=False)
    assert [float(v) for v in rest[:4]] == pytest.approx(obs.rest.sv_mm3.tolist(), rel=5e-3)
    assert [float(v) for v in rest[5:8]] == pytest.approx(obs.rest.sv_force_mm3.tolist(), rel=5e-3)
    printed = capsys.readouterr().out
    assert "weakest force direction over the envelope" in printed
    # on a pipe (this capture) it says what it is doing: the meshing's start, heartbeats, its end
    printed = printed.splitlines()
    start = next(i for i, ln in enumerate(printed) if re.fullmatch(r"meshing design '\w+' …", ln))
    beats = sum(bool(re.fullmatch(r"meshing design '\w+' … [\d:]+", ln)) for ln in printed[start + 1:])
    assert re.fullmatch(r"meshing design '\w+': done in [\d.]+ s", printed[start + 1 + beats]), printed[:5]


@pytest.mark.slow
def test_a_quadratic_design_checks_observability_at_rest_by_default(tmp_path):
    """``--observability auto``: the loaded states only for linear tets (a loaded solve of the
    quadratic default costs about 25 CPU-s); ``envelope`` asks for them on any model."""
    cfg = tmp_path / "p2.toml"
    cfg.write_text("[mesh]\nelement_order = 2\n")
    out = tmp_path / "d"
    assert main(["design", "--config", str(cfg), "--out", str(out), "--mesh-size-mm", "14", "--no-png"]) == 0
    report = (out / "report.md").read_text()
    assert load_model(out).element_order == 2
    assert "| rest |" in report and "| envelope min |" not in report


def test_design_command_invalid_config_is_one_line_exit_2(tmp_path, capsys):
    cfg = tmp_path / "bad.toml"
    cfg.write_text("[arms.back_xpos]\nwall_mm = 0.4\n")
    assert main(["design", "--config", str(cfg), "--out", str(tmp_path / "o"), "--no-png"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "Traceback" not in err
    assert "arms.back_xpos.wall_mm" in err and "1 mm" in err
    assert not (tmp_path / "o").exists()
    assert main(["design", "--out", str(tmp_path / "o"), "--mesh-size-mm", "-3"]) == 2
    err = capsys.readouterr().err.strip()
    assert "mesh.size_mm" in err and "Traceback" not in err
