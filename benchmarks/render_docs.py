#!/usr/bin/env python3
"""Fill the benchmark blocks of the docs from their results files.

    .venv/bin/python benchmarks/render_docs.py            # rewrite the blocks
    .venv/bin/python benchmarks/render_docs.py --check    # exit 1 if a page's block differs

A block is the text between ``<!-- results: NAME -->`` and ``<!-- /results -->`` in a page under
docs/; it becomes the content of ``benchmarks/results/NAME.md`` (written by the benchmark that
measures it, ``benchmarks/_results.py``). Nothing outside the markers changes. A marker naming a
results file that does not exist, or an unclosed marker, is a one-line error (exit 2).
"""

from __future__ import annotations

import argparse
import re
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
OPEN = re.compile(r"^<!-- results: ([a-z0-9_]+) -->$")
CLOSE = "<!-- /results -->"


class RenderError(Exception):
    """A page's markers cannot be filled (one line naming the page and line)."""


def render(text: str, results: Path, page: str = "<page>") -> str:
    """``text`` with every block replaced by its results file's content."""
    out: list[str] = []
    lines = text.split("\n")
    i = 0
    while i < len(lines):
        m = OPEN.match(lines[i])
        if not m:
            if lines[i].strip() == CLOSE:
                raise RenderError(f"{page}:{i + 1}: {CLOSE} without an opening '<!-- results: NAME -->'")
            out.append(lines[i])
            i += 1
            continue
        name, start = m.group(1), i
        i += 1
        while i < len(lines) and lines[i].strip() != CLOSE:
            if OPEN.match(lines[i]):
                raise RenderError(f"{page}:{i + 1}: results block '{name}' (line {start + 1}) is not closed before the next one")
            i += 1
        if i == len(lines):
            raise RenderError(f"{page}:{start + 1}: results block '{name}' has no closing {CLOSE}")
        src = results / f"{name}.md"
        if not src.is_file():
            raise RenderError(f"{page}:{start + 1}: unknown results name '{name}': no file {src}")
        out += [lines[start], "", src.read_text(encoding="utf-8").strip(), "", CLOSE]
        i += 1
    return "\n".join(out)


def _short(path: Path) -> str:
    return str(path.relative_to(ROOT)) if path.is_relative_to(ROOT) else str(path)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--check", action="store_true", help="change nothing; exit 1 if a block differs from its file")
    ap.add_argument("--docs", type=Path, default=ROOT / "docs", help="the pages (default docs/)")
    ap.add_argument("--results", type=Path, default=ROOT / "benchmarks" / "results", help="the results files")
    a = ap.parse_args(argv)
    stale = []
    try:
        for page in sorted(a.docs.rglob("*.md")):
            text = page.read_text(encoding="utf-8")
            new = render(text, a.results, _short(page))
            if new == text:
                continue
            if a.check:
                stale.append(page)
            else:
                page.write_text(new, encoding="utf-8")
                print(f"rendered {_short(page)}")
    except RenderError as e:
        print(f"render_docs: {e}", file=sys.stderr)
        return 2
    for page in stale:
        print(f"render_docs: {_short(page)}: a results block differs from its file in {a.results} "
              "(edit the benchmark, not the page; then run benchmarks/render_docs.py)", file=sys.stderr)
    return 1 if stale else 0


if __name__ == "__main__":
    sys.exit(main())
