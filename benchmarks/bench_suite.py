"""The time of `make test` from a clean clone, as CI runs it.

    .venv/bin/python benchmarks/bench_suite.py [--keep]

Clones the repository's HEAD beside it (so ``../shared``, the other labs' fixtures, is found as in
the checkout) and runs ``CI=true bash .ci/run`` there: the virtualenv's install, the docs' strict
build, the numba kernels and shared models, then pytest on 2 workers. Prints and writes
(``benchmarks/results/suite.md``) the wall time of each phase, read from the run's output as it
comes, pytest's own count and time, and the CPU time of the whole run. A failing run is reported
with its exit code and writes nothing. The goal is 5 minutes in all on 2 idle cores.
"""

from __future__ import annotations

import argparse
import os
import re
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from _results import ROOT, write_table

SUMMARY = re.compile(r"=+ (?P<counts>.*?) in (?P<s>[\d.]+)s")
PREPARED = re.compile(r"prepared in (?P<s>\d+) s before the workers")


def run_suite(clone: Path) -> dict:
    """Run CI's command in ``clone``; the phases' wall times from when their first lines appear."""
    env = {**os.environ, "CI": "true"}
    env.pop("VIRTUAL_ENV", None)
    t0 = time.perf_counter()
    marks: dict[str, float] = {}
    out: list[str] = []
    proc = subprocess.Popen(["bash", ".ci/run"], cwd=clone, env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True)
    assert proc.stdout is not None
    for line in proc.stdout:
        out.append(line)
        now = time.perf_counter() - t0
        if "mkdocs build" in line:
            marks.setdefault("docs", now)
        elif "pytest -n" in line:
            marks.setdefault("pytest", now)
    rc = proc.wait()
    total = time.perf_counter() - t0
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    text = "".join(out)
    summary = SUMMARY.findall(text)
    prepared = PREPARED.search(text)
    return {"rc": rc, "total_s": total, "marks": marks, "tail": out[-15:],
            "counts": summary[-1][0] if summary else "?", "pytest_s": float(summary[-1][1]) if summary else float("nan"),
            "prepared_s": float(prepared["s"]) if prepared else float("nan"),
            "cpu_s": usage.ru_utime + usage.ru_stime}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--keep", action="store_true", help="keep the clone (its path is printed)")
    a = ap.parse_args(argv)
    clone = Path(tempfile.mkdtemp(prefix=".suite-clone-", dir=ROOT.parent))
    try:
        subprocess.run(["git", "clone", "-q", str(ROOT), str(clone)], check=True)
        commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=clone, capture_output=True,
                                text=True, check=True).stdout.strip()
        print(f"running CI=true bash .ci/run in {clone} (commit {commit}) ...", flush=True)
        r = run_suite(clone)
    finally:
        if not a.keep:
            shutil.rmtree(clone, ignore_errors=True)
    if r["rc"] != 0:
        sys.stdout.write("".join(r["tail"]))
        print(f"bench_suite: .ci/run failed with exit code {r['rc']}; nothing written", file=sys.stderr)
        return 1
    m = r["marks"]
    install = m.get("docs", float("nan"))
    docs = m.get("pytest", float("nan")) - install
    rows = [
        ("virtualenv install (`make setup`)", f"{install:.0f}"),
        ("docs' strict build (`make docs`)", f"{docs:.0f}"),
        ("numba kernels and shared models, before the workers", f"{r['prepared_s']:.0f}"),
        (f"pytest on 2 workers ({r['counts']})", f"{r['pytest_s']:.0f}"),
        ("**`make test` in all** (goal ≤ 300 s)", f"**{r['total_s']:.0f}** ({r['total_s'] / 60:.1f} min)"),
        ("CPU time of the whole run (user + system)", f"{r['cpu_s']:.0f}"),
    ]
    for label, v in rows:
        print(f"{label:60s} {v}")
    write_table("suite", ("phase", "wall s"), rows, right=(1,),
                caption=f"From a clean clone of commit {commit}:")
    return 0


if __name__ == "__main__":
    sys.exit(main())
