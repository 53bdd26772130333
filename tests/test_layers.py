"""The package's imports: one way only (a package imports only the layers below it, in the order of
docs/architecture.md), no cycle between modules, and reading files needs nothing of the FEM or
the estimator (the records they hold live in softphantom.records, at the bottom)."""

from __future__ import annotations

import ast
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1] / "softphantom"

LAYERS = (
    "(root)", "errors", "schema", "progress", "parallel", "pose", "records", "stream", "design", "molds", "fem",
    "sensing", "estimation", "tracking", "evaluation", "calibration", "study", "virtual", "viz", "sources",
    "cli", "__main__",
)
"""Lowest first: a package may import itself and the packages before it (docs/architecture.md)."""


def _modules() -> dict[str, Path]:
    mods = {}
    for p in ROOT.rglob("*.py"):
        parts = list(p.relative_to(ROOT.parent).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts.pop()
        mods[".".join(parts)] = p
    return mods


def _is_type_checking(node: ast.If) -> bool:
    t = node.test
    return (isinstance(t, ast.Name) and t.id == "TYPE_CHECKING") or (
        isinstance(t, ast.Attribute) and t.attr == "TYPE_CHECKING")


def _imports(tree: ast.AST, mods) -> set[str]:
    """The softphantom modules a module imports, at any depth (inside functions too: a lazy import
    is still a dependency), leaving out ``if TYPE_CHECKING:`` blocks. ``from pkg import sub`` of a
    submodule depends on that submodule."""
    out: set[str] = set()

    def visit(node):
        if isinstance(node, ast.If) and _is_type_checking(node):
            for n in node.orelse:
                visit(n)
            return
        if isinstance(node, ast.ImportFrom) and node.level == 0 and (node.module or "").split(".")[0] == "softphantom":
            subs = [a.name for a in node.names if f"{node.module}.{a.name}" in mods]
            out.update(f"{node.module}.{s}" for s in subs)
            if len(subs) < len(node.names):
                out.add(node.module)
        elif isinstance(node, ast.Import):
            out.update(a.name for a in node.names if a.name.split(".")[0] == "softphantom")
        for child in ast.iter_child_nodes(node):
            visit(child)

    visit(tree)
    return out


def _graph() -> dict[str, set[str]]:
    mods = _modules()
    return {m: _imports(ast.parse(p.read_text(), str(p)), mods) for m, p in mods.items()}


def _package(module: str) -> str:
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else "(root)"


def upward_imports(graph: dict[str, set[str]]) -> list[str]:
    """``a -> b`` for every import of a package that is not below the importer's."""
    rank = {p: i for i, p in enumerate(LAYERS)}
    bad = []
    for a, targets in graph.items():
        pa = _package(a)
        for b in sorted(targets):
            pb = _package(b)
            if pa == pb:
                continue
            if pa not in rank or pb not in rank or rank[pb] > rank[pa]:
                bad.append(f"{a} ({pa}) -> {b} ({pb})")
    return bad


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan), each sorted."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on: set[str] = set()
    found: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in graph.get(v, ()):
            if w not in graph:
                continue
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                found.append(sorted(comp))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return found


def test_every_package_is_in_a_layer():
    assert {_package(m) for m in _modules()} <= set(LAYERS)


def test_no_import_goes_up_a_layer():
    assert upward_imports(_graph()) == []


def test_no_import_cycle():
    assert cycles(_graph()) == []


def test_the_checks_catch_a_cycle_and_an_upward_import():
    g = {"softphantom.sensing.recording": {"softphantom.sensing.sources"},
         "softphantom.sensing.sources": {"softphantom.sensing.recording", "softphantom.records"},
         "softphantom.records": {"softphantom.tracking.io"}, "softphantom.tracking.io": set()}
    assert cycles(g) == [["softphantom.sensing.recording", "softphantom.sensing.sources"]]
    assert upward_imports(g) == ["softphantom.records (records) -> softphantom.tracking.io (tracking)"]
    # a lazy import inside a function counts; one under TYPE_CHECKING does not
    mods = {"softphantom.fem": None, "softphantom.pose": None}
    tree = ast.parse("from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    import softphantom.pose\n"
                     "def f():\n    from softphantom import fem\n")
    assert _imports(tree, mods) == {"softphantom.fem"}


READ_FILES = textwrap.dedent("""
    import json, os, sys, tempfile
    from softphantom.records import BIP_LAYOUT, SessionWriter
    from softphantom.stream.recording import SessionRecorder

    d = tempfile.mkdtemp()
    mcap = os.path.join(d, "s.mcap")
    with SessionRecorder(mcap, layout=None) as r:
        for i in range(20):
            r.write_tracker({"t_s": i / 100, "valid": True, "name": "bip", "position_m": [0.001 * i, 0, 0],
                             "quat_xyzw": [0, 0, 0, 1]})
    truth = os.path.join(d, "truth.csv")
    with SessionWriter(truth, ["t_s", "x_mm", "y_mm", "z_mm", "yaw_deg", "pitch_deg", "roll_deg"], {}) as w:
        w.write_rows([[0.01 * i, i, 0, 0, 0, 0, 0] for i in range(5)])
    from softphantom.records import Estimate, estimate_columns
    est = os.path.join(d, "est.csv")
    with SessionWriter(est, estimate_columns([], BIP_LAYOUT), {}) as w:
        w.write_rows([[0.01 * i] + [0.0] * (len(estimate_columns([], BIP_LAYOUT)) - 1) for i in range(5)])

    from softphantom.evaluation import read_estimate, read_truth
    from softphantom.stream import read_estimate_csv, read_recording
    from softphantom.tracking import read_track
    n = (len(read_track(mcap)), len(read_truth(truth).t), len(read_estimate(est).t), len(read_estimate_csv(est)[1]),
         len(read_recording(mcap).tracker))
    print(json.dumps({"n": n, "modules": sorted(m for m in sys.modules if m.startswith("softphantom"))}))
""")


def test_reading_tracker_and_estimate_files_loads_no_fem_or_estimator():
    import json

    out = subprocess.run([sys.executable, "-c", READ_FILES], capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
    got = json.loads(out.stdout.splitlines()[-1])
    assert got["n"] == [20, 5, 5, 5, 20]
    loaded = {_package(m) for m in got["modules"]}
    assert "tracking" in loaded and "evaluation" in loaded and "records" in loaded
    assert not loaded & {"fem", "estimation", "design", "sensing"}, sorted(loaded)


@pytest.mark.parametrize("name", ["Estimate", "Measurement", "PoseTrack", "SourceEvent"])
def test_the_records_are_defined_once(name):
    """One ``class Name`` in the package, in softphantom.records; the stages re-export it."""
    defined = [m for m, p in _modules().items() if f"\nclass {name}(" in p.read_text() or f"\nclass {name}:" in p.read_text()]
    assert defined and all(_package(m) == "records" for m in defined) and len(defined) == 1, defined
