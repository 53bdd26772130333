"""The docs' benchmark blocks (benchmarks/render_docs.py, benchmarks/_results.py): every block in
docs/ equals the results file its benchmark wrote, so a hand edit of a figure fails here."""

import importlib.util
import subprocess
import sys
from pathlib import Path

import pytest

BENCH = Path(__file__).parents[1] / "benchmarks"


def _load(name):
    spec = importlib.util.spec_from_file_location(name, BENCH / f"{name}.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


render_docs = _load("render_docs")
results = _load("_results")

PAGE = """# Page

Text before, kept | as is.

<!-- results: alpha -->
| stale | table |
<!-- /results -->

Between.

<!-- results: beta -->

old beta

<!-- /results -->
Text after.
"""


@pytest.fixture
def tree(tmp_path):
    docs, res = tmp_path / "docs", tmp_path / "results"
    docs.mkdir()
    res.mkdir()
    (res / "alpha.md").write_text("| a | b |\n| --- | --- |\n| 1 | 2 |\n\n*`benchmarks/bench_x.py`*\n")
    (res / "beta.md").write_text("new beta\n")
    (docs / "page.md").write_text(PAGE)
    return docs, res


def test_every_docs_block_equals_its_results_file():
    assert render_docs.main(["--check"]) == 0


def test_render_replaces_only_between_markers(tree):
    docs, res = tree
    out = render_docs.render(PAGE, res)
    assert out == PAGE.replace("| stale | table |", "\n| a | b |\n| --- | --- |\n| 1 | 2 |\n\n*`benchmarks/bench_x.py`*\n") \
        .replace("\nold beta\n", "\nnew beta\n")
    assert render_docs.render(out, res) == out                      # idempotent
    assert render_docs.render("no markers\n", res) == "no markers\n"


def test_a_hand_edited_block_fails_the_check_and_rendering_restores_it(tree, capsys):
    docs, res = tree
    page = docs / "page.md"
    assert render_docs.main(["--docs", str(docs), "--results", str(res)]) == 0
    rendered = page.read_text()
    assert render_docs.main(["--check", "--docs", str(docs), "--results", str(res)]) == 0
    page.write_text(rendered.replace("| 1 | 2 |", "| 1 | 3 |"))     # a figure typed in by hand
    assert render_docs.main(["--check", "--docs", str(docs), "--results", str(res)]) == 1
    assert "page.md: a results block differs" in capsys.readouterr().err
    assert "| 1 | 3 |" in page.read_text()                          # --check changes nothing
    assert render_docs.main(["--docs", str(docs), "--results", str(res)]) == 0
    assert page.read_text() == rendered


@pytest.mark.parametrize("text, words", [
    ("a\n<!-- results: gamma -->\nx\n<!-- /results -->\n", ["page.md:2", "unknown results name 'gamma'"]),
    ("<!-- results: alpha -->\nx\n", ["page.md:1", "'alpha' has no closing"]),
    ("x\n<!-- /results -->\n", ["page.md:2", "without an opening"]),
])
def test_a_bad_marker_is_one_line_exit_2_and_changes_nothing(tree, text, words):
    docs, res = tree
    (docs / "page.md").write_text(text)
    p = subprocess.run([sys.executable, str(BENCH / "render_docs.py"), "--docs", str(docs), "--results", str(res)],
                       capture_output=True, text=True)
    assert p.returncode == 2
    assert len(p.stderr.strip().splitlines()) == 1 and "Traceback" not in p.stderr
    assert all(w in p.stderr for w in words), p.stderr
    assert (docs / "page.md").read_text() == text


def test_write_table_writes_caption_table_and_provenance(tmp_path, monkeypatch):
    monkeypatch.setattr(results, "RESULTS_DIR", tmp_path)
    path = results.write_table("fem_x", ("step", "ms"), [("force", 5.4), ("tangent", results.grouped(12345.6))],
                               right=(1,), caption="Linear tets:", argv=["/any/dir/bench_fem.py", "--repeat", "3"])
    caption, table, meta = path.read_text().strip().split("\n\n")
    assert caption == "Linear tets:"
    assert table.splitlines() == ["| step | ms |", "| --- | ---: |", "| force | 5.4 |", "| tangent | 12 346 |"]
    assert meta.startswith("*`benchmarks/bench_fem.py --repeat 3`, ") and "at load " in meta and "commit " in meta
    with pytest.raises(ValueError, match="Bad-Name"):
        results.write_table("Bad-Name", ("a",), [])
