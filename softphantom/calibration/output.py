"""Writing a calibration: a new model directory (the calibrated model, readable by ``estimate``,
``live`` and ``demo`` like any other) with ``calibration.json``, ``parameters.csv`` and
``report.html``; written into a temporary sibling and renamed, so ``--out`` is never half-written."""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

from softphantom.calibration.report import calibration_dict, write_parameters_csv, write_report
from softphantom.calibration.run import Calibration
from softphantom.errors import UserError


def calibrated_model(cal: Calibration):
    """The model of ``cal.model_dir`` with the fitted stiffness applied to its design."""
    from softphantom.design import load_model

    return load_model(cal.model_dir)


def write_calibration(cal: Calibration, out) -> dict[str, Path]:
    """Write everything into the new directory ``out`` (refused if it exists and is not empty)."""
    from softphantom.design import save_model

    out = Path(out)
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise UserError(f"--out {out}: exists and is not an empty directory")
    tmp = out.parent / f".{out.name}.partial-{os.getpid()}"
    try:
        if tmp.exists():
            shutil.rmtree(tmp)
        tmp.mkdir(parents=True)
        save_model(calibrated_model(cal), tmp)
        (tmp / "calibration.json").write_text(json.dumps(calibration_dict(cal), indent=2) + "\n")
        write_parameters_csv(cal, tmp / "parameters.csv")
        write_report(cal, tmp)
        if out.exists():
            out.rmdir()
        tmp.rename(out)
    except OSError as exc:
        shutil.rmtree(tmp, ignore_errors=True)
        raise UserError(f"--out {out}: cannot write ({exc.strerror or exc})") from None
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return {"model": out, "report": out / "report.html", "parameters": out / "parameters.csv",
            "calibration": out / "calibration.json"}
