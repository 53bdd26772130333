"""``make bench`` runs ``benchmarks/bench_*.py``; research scripts live apart in
``benchmarks/research/``, and every ``benchmarks/...`` path the docs and the code name exists."""

from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
HELPERS = {"_results.py", "render_docs.py"}  # used by the benchmarks and `make bench` itself


def test_benchmarks_top_level_holds_only_what_make_bench_runs():
    stray = sorted(p.name for p in (ROOT / "benchmarks").iterdir()
                   if p.name not in HELPERS and not p.name.startswith("bench_")
                   and p.name not in ("research", "results", "__pycache__"))
    assert stray == [], f"move research scripts to benchmarks/research/: {stray}"
    assert sorted(p.name for p in (ROOT / "benchmarks" / "research").glob("diag_*"))


def test_every_named_benchmark_path_exists():
    named = re.compile(r"benchmarks/[\w./-]+\.py|benchmarks/research/[\w-]+/")
    files = [*ROOT.glob("docs/**/*.md"), ROOT / "README.md", *ROOT.glob("softphantom/**/*.py"),
             *ROOT.glob("benchmarks/**/*.py"), *ROOT.glob("tests/*.py")]
    missing = sorted({f"{f.relative_to(ROOT)}: {m}" for f in files
                      for m in named.findall(f.read_text(encoding="utf-8", errors="replace"))
                      if "bench_x" not in m and not (ROOT / m).exists()})
    assert missing == []
