"""The demo (`make demo`): its wall time and its RMSE against the virtual truth, per scenario.

Runs ``softphantom demo --out DIR --overwrite`` (the default: the shipped quadratic model and its
shipped atlases, the paper's four scenarios, a finer P2 truth) and writes the table of
``DIR/summary.json`` to ``benchmarks/results/demo.md``; ``--summary DIR`` only reads a demo
already run there. ``--busy`` keeps one core busy with a spinning process while it runs (the
user's machine is never idle). Then the same for each example organ of ``examples/organs/``
(``softphantom demo --design FILE``: its generated scenarios, its own atlas built in the run) into
``benchmarks/results/demo_<file stem>.md`` (docs/organs.md); ``--design FILE`` runs that one only.

    python benchmarks/bench_demo.py [--out out/bench-demo] [--busy] [--summary DIR] [--design FILE]
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import resource
import subprocess
import sys
import time
from pathlib import Path

from _results import markdown_table, write_result

LABELS = {"needle-insertion": "needle insertion", "push-on-centre": "on-centre pushes",
          "push-off-centre": "off-centre pushes", "urethra-inflation": "urethra inflation"}


def _spin() -> None:
    while True:
        pass


def _label(r: dict) -> str:
    name = LABELS.get(r["scenario"], r["scenario"])
    for e in r["truth"]["events"]:
        if e["kind"] == "inflate" and "p_kPa" in e:  # another design's cavity
            name += f" (to {e['p_kPa']:.1f} kPa, body +{e['bulb_growth_percent']:.1f} %)"
            break
        if e["kind"] == "inflate":
            name += (f" (to {e['p_urethra_kPa']:.1f} kPa: `near_urethra` {e['near_urethra_shift_mm']:.2f} mm, "
                     f"bulb +{e['bulb_growth_percent']:.1f} %)")
    return name


def table(summary: dict) -> str:
    rows = []
    for r in summary["scenarios"]:
        dof = [f"{r['rmse'][k]:.2f} ({r['peak_truth'][k]:.1f})" for k in ("x", "y", "z", "yaw", "pitch", "roll")]
        t = r["target_rmse_mm"].values()
        a = r.get("atlas") or {}
        inside = (f"{a['in_envelope_fraction'] * 100:.0f} %" + (" (draft atlas)" if a.get("draft") else "")) if a else "–"
        f_rmse, f_peak = r["force_rmse_N"].get("|force|", float("nan")), r.get("force_peak_N", {}).get("|force|")
        rel = f" ({f_rmse / f_peak * 100:.1f} %)" if f_peak else ""
        rows.append([_label(r), *dof, f"{f_rmse:.2f}{rel}",
                     f"{min(t):.2f}–{max(t):.2f}", f"{r['lag_ms']:.0f}", inside,
                     f"{r['estimate']['rate_Hz']:.0f}", f"{r['seconds']['truth_solve']:.0f}"])
    head = ["scenario", "x mm", "y mm", "z mm", "yaw °", "pitch °", "roll °", "\\|F\\| N", "targets RMSE mm",
            "lag ms", "inside atlas", "estimator Hz", "truth solve s"]
    return markdown_table(head, rows)


ORGANS = sorted((Path(__file__).resolve().parents[1] / "examples" / "organs").glob("*.toml"))


def run_one(design: Path | None, out: Path, summary: Path | None, busy: bool) -> int:
    """One demo (the default one, ``design`` None, or that design's) run into ``out`` or read from
    ``summary``; its table into ``benchmarks/results`` (not with ``busy``)."""
    wall = None
    if summary is None:
        spin = multiprocessing.Process(target=_spin, daemon=True) if busy else None
        if spin:
            spin.start()
        before = resource.getrusage(resource.RUSAGE_CHILDREN)
        t0 = time.perf_counter()
        exe = Path(sys.executable).with_name("softphantom")
        extra = ["--design", str(design)] if design else []
        rc = subprocess.run([str(exe), "demo", "--out", str(out), "--overwrite", *extra]).returncode
        wall = time.perf_counter() - t0
        if spin:
            spin.terminate()
        if rc != 0:
            print(f"demo failed: exit {rc}", file=sys.stderr)
            return 1
        ru = resource.getrusage(resource.RUSAGE_CHILDREN)
        print(f"demo: {wall:.0f} s wall, {ru.ru_utime - before.ru_utime:.0f} s user + "
              f"{ru.ru_stime - before.ru_stime:.0f} s system" + (" (one core busy)" if busy else ""))
    d = summary or out
    s = json.loads((d / "summary.json").read_text())
    md = table(s)
    print(md)
    if busy:  # the docs' table is the idle run's
        return 0
    what = f"`softphantom demo --design {design}`" if design else "The demo"
    caption = (f"{what}: `wall_s` {s['wall_s']:.0f} s" + (f", the command {wall:.0f} s" if wall else "")
               + "; RMSE (peak \\|truth\\|; \\|F\\| also of its peak) against the virtual truth, from "
               "`summary.json`.")
    write_result(f"demo_{design.stem}" if design else "demo", md, caption=caption)
    return 0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=Path("out/bench-demo"))
    ap.add_argument("--summary", type=Path, help="a demo's output directory: read its summary.json, run nothing")
    ap.add_argument("--busy", action="store_true", help="one core kept busy by another process meanwhile")
    ap.add_argument("--design", type=Path, help="a design file: the demo of that design only (softphantom demo "
                    "--design); default: the default demo, then each of examples/organs/")
    a = ap.parse_args(argv)
    if a.design is not None or a.summary is not None:
        return run_one(a.design, a.out, a.summary, a.busy)
    for design in (None, *ORGANS):
        out = a.out if design is None else a.out.with_name(f"{a.out.name}-{design.stem}")
        if run_one(design, out, None, a.busy):
            return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
