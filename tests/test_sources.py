"""softphantom.sources: one --source registry, one meaning per scheme (replay: replays a file at
the level it was recorded)."""

from __future__ import annotations

import numpy as np
import pytest

from softphantom.records import BIP_LAYOUT
from softphantom.cli import main
from softphantom.errors import UserError
from softphantom.records import Measurement, SessionWriter, estimate_columns
from softphantom.sensing.chain import default_chain, nominal_tare
from softphantom.sensing.recording import Recorder
from softphantom.sensing.sources import ReplaySource
from softphantom.sources import SOURCES, open_source, replay_holds
from softphantom.stream.recording import SessionRecorder
from softphantom.viz.live import EstimateReplay, SyntheticSource


@pytest.fixture()
def files(tmp_path):
    chain = default_chain()
    sensing = tmp_path / "r.csv"
    with Recorder(sensing, {"chain": chain.summary(), "tare": nominal_tare(chain).to_dict(), "osr": 100},
                  layout=chain.layout) as rec:
        for k in range(5):
            rec.write(Measurement(k / 77, k, k / 77, np.full(5, 51150), 100, np.zeros(4), np.zeros(4), 0.0))
    est = tmp_path / "e.csv"
    with SessionWriter(est, estimate_columns([], BIP_LAYOUT), {"kind": "softphantom-estimate"}) as w:
        w.write_rows([[k / 77] + [0.0] * (len(estimate_columns([], BIP_LAYOUT)) - 1) for k in range(5)])
    mcap = tmp_path / "s.mcap"
    with SessionRecorder(mcap, layout=BIP_LAYOUT) as r:
        r.write_estimate({"seq": 0, "t_s": 0.0, "force_y_N": 1.0})
    other = tmp_path / "o.csv"
    other.write_text("a,b\n1,2\n")
    return {"sensing": sensing, "estimate": est, "mcap": mcap, "other": other}


def test_replay_opens_a_file_at_the_level_it_was_recorded(files):
    assert [replay_holds(files[k]) for k in ("sensing", "estimate", "mcap", "other")] == \
        ["measurements", "estimates", "estimates", None]
    o = open_source(f"replay:{files['sensing']}")
    assert o.gives == "measurements" and isinstance(o.source, ReplaySource) and len(list(o.source)) == 5
    for k in ("estimate", "mcap"):
        o = open_source(f"replay:{files[k]}", speed=0)
        assert o.gives == "estimates" and isinstance(o.source, EstimateReplay)
    o = open_source("synthetic", duration_s=0.1)
    assert o.gives == "estimates" and isinstance(o.source, SyntheticSource)
    assert {k.scheme: k.gives for k in SOURCES.values()} == {
        "serial": "measurements", "replay": "recorded", "virtual": "measurements", "synthetic": "estimates"}


def test_a_source_of_estimates_is_refused_where_samples_are_needed(files, capsys, tmp_path, coarse_model_dir):
    for spec, msg in ((f"replay:{files['estimate']}", "holds estimates"), ("synthetic", "gives estimates"),
                      (f"replay:{files['other']}", "line 1: expected '# ' \\+ JSON metadata"), ("bogus:x", "unknown kind"),
                      ("serial:", "use serial:PORT")):
        with pytest.raises(UserError, match=msg):
            open_source(spec, want="measurements")
    assert main(["estimate", "--model", str(coarse_model_dir), "--source", f"replay:{files['mcap']}",
                 "--out", str(tmp_path / "x.csv")]) == 2
    err = capsys.readouterr().err
    assert "holds estimates" in err and err.strip().count("\n") == 0
    # live estimates a sensing recording again, which needs the model
    assert main(["live", "--source", f"replay:{files['sensing']}", "--http-port", "0"]) == 2
    assert "needs --model" in capsys.readouterr().err


def test_the_synthetic_source_refuses_a_model_of_other_names(tmp_path):
    """``synthetic`` makes up the BIP's estimates: a model directory of the BIP's names is taken
    (and not used), one of other arms or cavities is refused in one line naming both."""
    from softphantom.design.params import BIPDesign, design_from_dict, design_to_toml

    bip, other = tmp_path / "bip", tmp_path / "three"
    for d, design in ((bip, BIPDesign()), (other, design_from_dict({"arm_names": ["front_zpos", "front_zneg",
                                                                                  "back_xpos"]}))):
        d.mkdir()
        (d / "design.toml").write_text(design_to_toml(design))
    assert open_source("synthetic", bip, duration_s=0.1).gives == "estimates"
    with pytest.raises(UserError, match=r"^--source synthetic: made-up estimates of the BIP \(arms front_zpos, "
                                        r".*this model has front_zpos, front_zneg, back_xpos; urethra: use "
                                        r"--source virtual:SCENARIO to see it$"):
        open_source("synthetic", other, duration_s=0.1)
