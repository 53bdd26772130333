"""What every command gets without asking: finite numbers, Ctrl-C → exit 130, one output policy.

:func:`harden` is applied once by :func:`softphantom.cli.main` to the whole command tree, so a
command added by any module gets it:

- every numeric option rejects NaN and ±inf (a usage error, exit 2, naming the option);
- every help text is shown as written: typer renders it as rich markup, which would take
  ``[molds]`` for a style tag and drop it, so the text is escaped once here;
- Ctrl-C inside a command prints ``interrupted`` on stderr and exits 130 (the shell convention,
  so ``make`` stops); commands whose normal stop is Ctrl-C (``acquire``, ``live``, …) close their
  recording first and end with :func:`stopped`, which also exits 130.

Outputs (``--out``): :func:`staged_output` refuses an existing file or non-empty directory unless
``--overwrite`` (:func:`overwrite_option`), writes into a hidden sibling and moves the result into
place only when the command succeeds, so an error or Ctrl-C leaves no partial output and loses
nothing that was there before.
"""

from __future__ import annotations

import contextlib
import functools
import math
import os
import shutil
import signal
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any, NoReturn

import typer

from softphantom.errors import UserError

EXIT_INTERRUPTED = 130  # 128 + SIGINT


def finite_number(text: str, option: str) -> float:
    """``float(text)`` for an option parsed by hand (``--lag-ms``, ``X,Y,Z``): finite, else UserError.

    >>> finite_number("2.5", "--lag-ms")
    2.5
    >>> finite_number("nan", "--lag-ms")
    Traceback (most recent call last):
    ...
    softphantom.errors.UserError: --lag-ms: expected a finite number, got 'nan'
    """
    try:
        v = float(text)
    except (TypeError, ValueError):
        raise UserError(f"{option}: expected a number, got {text!r}") from None
    if not math.isfinite(v):
        raise UserError(f"{option}: expected a finite number, got {text!r}")
    return v


def check_choice(value: str, choices: tuple[str, ...] | list[str], option: str) -> str:
    """``value`` if it is one of ``choices``, else a UserError naming ``option`` and the choices.

    >>> check_choice("furlong", ("m", "cm", "mm"), "--length-unit")
    Traceback (most recent call last):
    ...
    softphantom.errors.UserError: --length-unit: expected m, cm or mm, got 'furlong'
    """
    if value not in choices:
        words = ", ".join(choices[:-1]) + f" or {choices[-1]}" if len(choices) > 1 else choices[0]
        raise UserError(f"{option}: expected {words}, got {value!r}")
    return value


def check_positive(value: float | None, option: str, unit: str = "", *, zero: bool = False) -> float | None:
    """``value`` (None passes) if > 0 (``zero``: >= 0), else a UserError naming ``option``.

    >>> check_positive(-1.0, "--connect-timeout-s", "s")
    Traceback (most recent call last):
    ...
    softphantom.errors.UserError: --connect-timeout-s: must be > 0 s, got -1
    """
    if value is not None and not (value >= 0 if zero else value > 0):
        raise UserError(f"{option}: must be {'>=' if zero else '>'} 0{' ' + unit if unit else ''}, got {value:g}")
    return value


# --- applied to the whole command tree ------------------------------------------------------------

def _check_finite(ctx: Any, param: Any, value: Any) -> None:
    items = value if isinstance(value, (list, tuple)) else (value,)
    for v in items:
        if isinstance(v, float) and not math.isfinite(v):
            raise typer.BadParameter(f"expected a finite number, got {v}", ctx=ctx, param=param)


def _finite_callback(callback: Any) -> Any:
    def cb(ctx: Any, param: Any, value: Any) -> Any:
        _check_finite(ctx, param, value)
        return callback(ctx, param, value) if callback is not None else value

    return cb


def _interruptible(fn: Any) -> Any:
    @functools.wraps(fn)
    def run(*args: Any, **kwargs: Any) -> Any:
        try:
            return fn(*args, **kwargs)
        except KeyboardInterrupt:
            from softphantom.cli.app import print_error

            print_error("interrupted", prefix="")
            raise typer.Exit(EXIT_INTERRUPTED) from None

    return run


def _literal(text: str | None) -> str | None:
    from rich.markup import escape

    return None if text is None else escape(text)


def harden(command: Any) -> Any:
    """Give every parameter of ``command`` (a click command or group, recursively) the finite-number
    check, every command callback the Ctrl-C → 130 handling and every help text its literal
    rendering (markup escaped). Returns ``command``."""
    if not getattr(command, "_softphantom_help_literal", False):
        command.help, command.short_help = _literal(command.help), _literal(command.short_help)
        command._softphantom_help_literal = True
    for p in getattr(command, "params", ()):
        if not getattr(p, "_softphantom_hardened", False):
            p.callback = _finite_callback(p.callback)
            if getattr(p, "help", None) is not None:
                p.help = _literal(p.help)
            p._softphantom_hardened = True
    cb = getattr(command, "callback", None)
    if cb is not None and not getattr(cb, "_softphantom_hardened", False):
        command.callback = _interruptible(cb)
        command.callback._softphantom_hardened = True
    for sub in getattr(command, "commands", {}).values():
        harden(sub)
    return command


def stopped(message: str = "stopped (Ctrl-C)") -> NoReturn:
    """End a command that Ctrl-C stops by design, after it has closed its outputs: exit 130."""
    from softphantom.cli.app import print_error

    print_error(message, prefix="")
    raise typer.Exit(EXIT_INTERRUPTED)


# --- outputs ------------------------------------------------------------------------------------

def overwrite_option() -> Any:
    """The ``--overwrite`` flag, the same for every command with ``--out``."""
    return typer.Option(False, "--overwrite",
                        help="Replace an existing --out (a directory keeps the entries this command does not write).")


def check_output(path: Path, *, overwrite: bool, directory: bool, option: str = "--out") -> None:
    """Refuse an output that exists (a file, a non-empty directory) unless ``overwrite``, one that
    is of the other kind (a file for a directory), and a directory that holds the working one."""
    path = Path(path)
    if path.is_dir():
        if not directory:
            raise UserError(f"{option} {path}: is a directory (expected a file name)")
        if any(path.iterdir()) and not overwrite:
            raise UserError(f"{option} {path}: exists and is not empty; use --overwrite to replace its contents")
        if overwrite and Path.cwd().resolve().is_relative_to(path.resolve()):
            raise UserError(f"{option} {path}: holds the working directory; refusing to overwrite it")
    elif path.exists() or path.is_symlink():
        if directory:
            raise UserError(f"{option} {path}: exists and is not a directory")
        if not overwrite:
            raise UserError(f"{option} {path}: exists; use --overwrite to replace it")
    _check_parent(path, option)


def _check_parent(path: Path, option: str) -> None:
    """Refuse an output whose folder cannot be made (an existing file on its way) or written, before
    the command's work rather than at its end; missing folders are made when it is written."""
    parent = path.absolute().parent
    while not parent.exists() and parent != parent.parent:
        parent = parent.parent
    if not parent.is_dir():
        raise UserError(f"{option} {path}: cannot be created ({parent} is a file, not a directory)")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise UserError(f"{option} {path}: cannot be created ({parent}: permission denied)")


@contextlib.contextmanager
def _no_sigint() -> Iterator[None]:
    """Hold Ctrl-C during a few renames (re-raised after), so the move into place is never half done."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    hit: list[bool] = []
    old = signal.signal(signal.SIGINT, lambda *_: hit.append(True))
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, old)
    if hit:
        raise KeyboardInterrupt


def _remove(p: Path) -> None:
    if p.is_dir() and not p.is_symlink():
        shutil.rmtree(p, ignore_errors=True)
    else:
        with contextlib.suppress(FileNotFoundError):
            p.unlink()


def _commit(stage: Path, path: Path, directory: bool) -> None:
    with _no_sigint():
        if not directory or not path.is_dir():
            if path.exists() or path.is_symlink():
                _remove(path)  # --overwrite, checked before
            os.replace(stage, path)
            return
        # merge into an existing directory: each entry written replaces the one of that name
        aside = []
        for entry in sorted(stage.iterdir()):
            target = path / entry.name
            if target.exists() or target.is_symlink():
                old = stage.with_name(f"{stage.name}.old-{entry.name}")
                os.replace(target, old)
                aside.append(old)
            os.replace(entry, target)
        stage.rmdir()
    for old in aside:
        _remove(old)


@contextlib.contextmanager
def staged_output(path: Path, *, overwrite: bool, directory: bool, option: str = "--out") -> Iterator[Path]:
    """Yield a hidden working path next to ``path``; on success move it into place, on any error or
    Ctrl-C remove it (``path`` is then as it was). Checks ``path`` first (:func:`check_output`).

    >>> import tempfile
    >>> d = Path(tempfile.mkdtemp())
    >>> with staged_output(d / "a.txt", overwrite=False, directory=False) as tmp:
    ...     _ = tmp.write_text("one")
    >>> (d / "a.txt").read_text(), sorted(p.name for p in d.iterdir())
    ('one', ['a.txt'])
    >>> with staged_output(d / "a.txt", overwrite=False, directory=False) as tmp:
    ...     pass
    Traceback (most recent call last):
    ...
    softphantom.errors.UserError: --out ...a.txt: exists; use --overwrite to replace it
    """
    path = Path(path)
    check_output(path, overwrite=overwrite, directory=directory, option=option)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise UserError(f"{option} {path}: cannot create {path.parent} ({exc.strerror})") from None
    stage = path.with_name(f".{path.name}.partial-{os.getpid()}")
    _remove(stage)
    if directory:
        try:
            stage.mkdir()
        except OSError as exc:
            raise UserError(f"{option} {path}: cannot write in {path.parent} ({exc.strerror})") from None
    try:
        yield stage
    except BaseException:
        _remove(stage)
        raise
    try:
        _commit(stage, path, directory)
    except BaseException:
        _remove(stage)
        raise
