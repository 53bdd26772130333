import json

import meshio
import numpy as np

from softphantom.cli import main


def test_simulate_writes_vtu_and_prints_results(coarse_model, tmp_path, capsys):
    from softphantom.design import save_model

    save_model(coarse_model, tmp_path / "model")
    out = tmp_path / "sim"
    rc = main(["simulate", "--model", str(tmp_path / "model"), "--force-N", "0,2,0",
               "--urethra-kPa", "5", "--out", str(out)])
    text = capsys.readouterr().out
    assert rc == 0, text
    assert "dV_back_xpos_mm3=" in text and "y_mm=" in text and "near_urethra" in text
    mesh = meshio.read(out / "deformed.vtu")
    u = mesh.point_data["displacement_mm"]
    assert u.shape == coarse_model.nodes.shape and np.all(np.isfinite(u))
    assert np.allclose(mesh.points, coarse_model.nodes + u * 1e-3)
    vm = mesh.cell_data["von_mises_kPa"][0]
    assert vm.shape == (len(coarse_model.tets),) and vm.min() >= 0 and vm.max() > 0
    res = json.loads((out / "result.json").read_text())
    assert res["pose"]["y_mm"] > 1.0  # pushed along +y
    assert res["dV_mm3"]["urethra"] > 0  # inflated
    assert set(res["target_shift_mm"]) == set(coarse_model.targets)


def test_simulate_rejects_bad_input_in_one_line(coarse_model, tmp_path, capsys):
    from softphantom.design import save_model

    save_model(coarse_model, tmp_path / "model")
    rc = main(["simulate", "--model", str(tmp_path / "model"), "--force-N", "0,5", "--out", str(tmp_path / "o")])
    assert rc == 2
    assert "--force-N" in capsys.readouterr().err
    rc = main(["simulate", "--model", str(tmp_path / "model"), "--at", "centre", "--out", str(tmp_path / "o")])
    assert rc == 2
