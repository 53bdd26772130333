"""Benchmark tables for the docs: each a file ``benchmarks/results/<name>.md`` that
``benchmarks/render_docs.py`` copies between ``<!-- results: <name> -->`` and ``<!-- /results -->``
in the pages, so a figure in the docs is the output of the benchmark that measures it."""

from __future__ import annotations

import datetime
import os
import platform
import re
import shlex
import subprocess
import sys
from collections.abc import Iterable, Sequence
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
RESULTS_DIR = ROOT / "benchmarks" / "results"
IMG_DIR = ROOT / "docs" / "img"
NAME = re.compile(r"[a-z0-9_]+")


def grouped(x: float, decimals: int = 0) -> str:
    """``x`` with its thousands separated by a space, as the docs write them (6 352)."""
    return f"{x:,.{decimals}f}".replace(",", " ")


def markdown_table(header: Sequence[str], rows: Iterable[Sequence[object]], right: Sequence[int] = ()) -> str:
    """A markdown table; columns whose index is in ``right`` are right-aligned."""
    rule = ["---:" if i in right else "---" for i in range(len(header))]
    lines = [header, rule, *([str(c) for c in r] for r in rows)]
    return "\n".join("| " + " | ".join(cells) + " |" for cells in lines)


def _commit() -> str:
    def git(*a: str) -> str:
        return subprocess.run(["git", *a], cwd=ROOT, capture_output=True, text=True, check=False).stdout.strip()

    sha = git("rev-parse", "--short", "HEAD") or "unknown"
    # the code measured: the package and the benchmarks, not the results they write
    code = ("softphantom", "benchmarks", ":(exclude)benchmarks/results")
    return sha + ("+modified" if git("status", "--porcelain", "--untracked-files=no", "--", *code) else "")


def provenance(argv: Sequence[str] | None = None) -> str:
    """One line: the command, the date, the machine and its load, the commit."""
    argv = sys.argv if argv is None else argv
    script = Path(argv[0])
    cmd = shlex.join([f"benchmarks/{script.name}", *argv[1:]])
    now = datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    load = os.getloadavg()[0]
    machine = f"{os.cpu_count()} cores {platform.machine()}"
    return f"*`{cmd}`, {now}, {machine} at load {load:.1f}, commit {_commit()}.*"


def write_result(name: str, markdown: str, *, caption: str = "", argv: Sequence[str] | None = None) -> Path:
    """Write ``benchmarks/results/<name>.md``: an optional caption line, the table, the provenance."""
    if not NAME.fullmatch(name):
        raise ValueError(f"result name {name!r}: lower-case letters, digits and _ only")
    RESULTS_DIR.mkdir(parents=True, exist_ok=True)
    parts = [caption.strip()] if caption.strip() else []
    parts += [markdown.strip(), provenance(argv)]
    path = RESULTS_DIR / f"{name}.md"
    path.write_text("\n\n".join(parts) + "\n", encoding="utf-8")
    print(f"wrote {path}")
    return path


def write_table(name: str, header: Sequence[str], rows: Iterable[Sequence[object]], *, right: Sequence[int] = (),
                caption: str = "", argv: Sequence[str] | None = None) -> Path:
    """``write_result`` of ``markdown_table(header, rows, right)``."""
    return write_result(name, markdown_table(header, rows, right), caption=caption, argv=argv)


def add_results_option(ap, default: str) -> None:
    """``--results-name``: the results file a run writes, for a configuration the docs show apart."""
    ap.add_argument("--results-name", default=default, metavar="NAME",
                    help=f"write the docs table to benchmarks/results/NAME.md (default {default})")
