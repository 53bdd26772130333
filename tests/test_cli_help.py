"""Every command's ``--help`` shows every word of its source text: each command's first paragraph
(in its own help and in its group's list) and each option's and argument's help, whatever brackets
or other markup-like characters it holds."""

from __future__ import annotations

import re

import pytest

import typer.main

from softphantom.cli import _register, main
from softphantom.cli.app import app

_BOX = re.compile(r"[│╭╮╰╯─]")


def _norm(text: str) -> str:
    return " ".join(_BOX.sub(" ", text).split())


def _tree(cmd, path=()):
    yield path, cmd
    for name, sub in sorted(getattr(cmd, "commands", {}).items()):
        yield from _tree(sub, (*path, name))


def _text(cmd) -> str:
    import inspect

    return inspect.cleandoc(cmd.help or "").partition("\f")[0]


def _first_paragraph(cmd) -> str:
    return _text(cmd).split("\n\n")[0]


_register()
_COMMANDS = list(_tree(typer.main.get_command(app)))  # the source texts, as the modules wrote them


@pytest.mark.parametrize("path, cmd", _COMMANDS, ids=[" ".join(p) or "softphantom" for p, _ in _COMMANDS])
def test_help_shows_every_word_of_its_source(path, cmd, monkeypatch, capsys):
    monkeypatch.setenv("COLUMNS", "250")  # wide: no word folded in two
    assert main([*path, "--help"]) == 0
    shown = _norm(capsys.readouterr().out)
    missing = [f"{path or 'softphantom'}: {_text(cmd)!r}"] if _norm(_text(cmd)) not in shown else []
    for name, sub in getattr(cmd, "commands", {}).items():
        if not sub.hidden and _norm(_first_paragraph(sub)) not in shown:
            missing.append(f"{name} in the list: {_first_paragraph(sub)!r}")
    for p in cmd.params:
        help_text = getattr(p, "help", None)
        if help_text and not getattr(p, "hidden", False) and _norm(help_text) not in shown:
            missing.append(f"{p.opts[0]}: {help_text!r}")
    assert not missing, "help text lost words:\n" + "\n".join(missing)
