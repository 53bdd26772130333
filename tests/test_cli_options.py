"""One definition per CLI option (softphantom.cli.options): a flag that several commands take is
declared once, with one help text; the flags that mean different things in different commands are
the listed ones. (Every command's --help exits 0 and shows each help: tests/test_cli_help.py.)"""

from __future__ import annotations

import ast
import collections
from pathlib import Path

import pytest
import typer.main

from softphantom.cli import _register, main
from softphantom.cli.app import app
from softphantom.cli.options import FLAGS_OF_SEVERAL_MEANINGS

CLI = Path(__file__).parents[1] / "softphantom" / "cli"


def _options():
    """flag → [(command path, help)] over the whole command tree."""
    _register()
    out = collections.defaultdict(list)

    def walk(cmd, path):
        for p in cmd.params:
            if type(p).__name__.endswith("Option"):
                for flag in (*p.opts, *p.secondary_opts):
                    out[flag].append((path, p.help))
        for name, sub in getattr(cmd, "commands", {}).items():
            walk(sub, f"{path} {name}".strip())

    walk(typer.main.get_command(app), "")
    return out


def test_a_flag_of_several_commands_has_one_help_text():
    helps = {flag: {h for _, h in uses} for flag, uses in _options().items()}
    drifted = {f: sorted(h) for f, h in helps.items() if len(h) > 1 and f not in FLAGS_OF_SEVERAL_MEANINGS}
    assert not drifted, f"flags declared with different help texts: {drifted}"
    stale = [f for f in FLAGS_OF_SEVERAL_MEANINGS if len(helps.get(f, ())) < 2]
    assert not stale, f"FLAGS_OF_SEVERAL_MEANINGS lists flags of one meaning: {stale}"


def test_a_shared_flag_is_declared_once_in_the_source():
    """Outside cli/options.py, a flag is declared (a typer.Option call) in one place, unless listed."""
    where = collections.defaultdict(list)
    for path in sorted(CLI.glob("*.py")):
        if path.name == "options.py":
            continue
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.Call) and ast.unparse(node.func) == "typer.Option":
                for a in node.args:
                    if isinstance(a, ast.Constant) and isinstance(a.value, str) and a.value.startswith("--"):
                        where[a.value.split("/")[0]].append(f"{path.name}:{node.lineno}")
    twice = {f: w for f, w in where.items() if len(w) > 1 and f not in FLAGS_OF_SEVERAL_MEANINGS}
    assert not twice, f"declare these once, in softphantom/cli/options.py: {twice}"


@pytest.mark.parametrize("argv, missing", [
    (["estimate", "--source", "replay:r.csv", "--out", "e.csv"], "--model"),
    (["estimate", "--model", "m", "--out", "e.csv"], "--source"),
    (["virtual", "run", "--model", "m", "--out", "o"], "--scenario"),
    (["atlas", "verify"], "--model"),
    (["calibrate", "--model", "m", "--recording", "r.csv", "--truth", "t.csv"], "--out"),
])
def test_a_shared_option_stays_required_where_it_was(argv, missing, capsys):
    assert main(argv) == 2
    assert f"Missing option '{missing}'" in capsys.readouterr().err


def test_workers_below_one_is_one_line_wherever_it_is_taken(tmp_path, capsys):
    """--workers is one option: every command refuses 0 (atlas check: below 0) before any work."""
    for argv in (["sweep", "--config", "s.toml", "--out", str(tmp_path / "o"), "--workers", "0"],
                 ["demo", "--out", str(tmp_path / "d"), "--workers", "0"],
                 ["atlas", "check", "--model", "m", "--workers", "-1"]):
        assert main(argv) == 2, argv
        err = capsys.readouterr().err.strip()
        assert err.count("\n") == 0 and "--workers must be >= " in err, err


def test_an_option_group_is_one_declaration_with_each_commands_defaults(monkeypatch):
    """virtual run, virtual serve and demo take the truth's options from one group (demo: OSR 100),
    and the command is called with the group's instance made of the parsed options."""
    import softphantom.cli.virtual as cv
    from softphantom.cli.options import TruthOptions, VirtualOptions

    _register()
    root = typer.main.get_command(app)
    defaults = {name: {p.name: p.default for p in cmd.params}
                for name, cmd in (("run", root.commands["virtual"].commands["run"]),
                                  ("serve", root.commands["virtual"].commands["serve"]),
                                  ("demo", root.commands["demo"]))}
    for name in ("run", "serve"):
        assert {f: defaults[name][f] for f in VirtualOptions.__dataclass_fields__} == {
            "seed": 0, "osr": 25, "truth_mesh_scale": 0.75, "truth_order": 2, "tube_length_m": None,
            "tube_id_mm": None, "board": "python", "mcu": "uno"}
    assert {f: defaults["demo"][f] for f in TruthOptions.__dataclass_fields__} == {
        "seed": 0, "osr": 100, "truth_mesh_scale": 0.75, "truth_order": 2}
    assert "board" not in defaults["demo"]

    got = []

    def fake_simulate(scenario, model_dir, opts):
        got.append(opts)
        raise SystemExit(3)

    monkeypatch.setattr(cv, "_simulate", fake_simulate)
    main(["virtual", "run", "--scenario", "push-on-centre", "--model", "m", "--out", "o-never", "--osr", "7",
          "--tube-id-mm", "1.5", "--mcu", "mega"])
    assert got == [VirtualOptions(osr=7, tube_id_mm=1.5, mcu="mega")]
