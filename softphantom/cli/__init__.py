"""Command-line interface: ``softphantom <command>``.

Each stage adds its commands in its own module under ``softphantom.cli``; :func:`main` hardens the
whole command tree once (:func:`softphantom.cli.options.harden`: finite numbers, Ctrl-C → 130) and
turns every error into one line on stderr and an exit code: 2 bad input (a
:class:`~softphantom.errors.UserError` or a usage error), 3 a failed solve, 130 Ctrl-C.
"""

from __future__ import annotations

import sys

from softphantom.cli.app import app, console_err, print_error
from softphantom.cli.options import EXIT_INTERRUPTED, harden
from softphantom.errors import SoftphantomError

# Importing the command modules registers their commands on ``app``.
_COMMAND_MODULES = ("design", "molds", "fem", "sensing", "estimation", "atlas", "evaluation", "tracking", "virtual", "demo", "live",
                    "sweep", "calibration")


def _register() -> None:
    import importlib

    for name in _COMMAND_MODULES:
        try:
            importlib.import_module(f"softphantom.cli.{name}")
        except ModuleNotFoundError as exc:  # stage not built yet
            if exc.name != f"softphantom.cli.{name}":
                raise


def command():
    """The click command tree of ``app``, hardened (what :func:`main` runs; for tests too)."""
    import typer.main

    _register()
    return harden(typer.main.get_command(app))


def main(argv: list[str] | None = None) -> int:
    try:
        rv = command().main(args=argv, prog_name="softphantom", standalone_mode=False)
    except SoftphantomError as exc:
        print_error(str(exc))
        return exc.exit_code
    except KeyboardInterrupt:  # outside a command (while importing): nothing written yet
        print_error("interrupted", prefix="")
        return EXIT_INTERRUPTED
    except SystemExit as exc:
        return int(exc.code or 0)
    except Exception as exc:
        # Usage errors of the CLI framework (typer vendors click): one line, no traceback.
        if hasattr(exc, "format_message") and hasattr(exc, "exit_code"):
            if str(exc.format_message()).strip():  # (no arguments: the help was printed instead)
                print_error(_usage_line(exc))
            return int(exc.exit_code)
        if type(exc).__name__ == "Abort":
            return 1
        raise
    finally:
        console_err.file.flush()
    # non-standalone click returns typer.Exit's code (130 after Ctrl-C) or the command's value
    return rv if isinstance(rv, int) and not isinstance(rv, bool) else 0


def _usage_line(exc) -> str:
    msg = " ".join(str(exc.format_message()).split())
    cmd = getattr(getattr(exc, "ctx", None), "command_path", None)
    return f"{cmd}: {msg}" if cmd else msg


def exit_with(code: int) -> None:
    """Leave the process with ``code``. After Ctrl-C the interpreter's teardown is skipped (it took
    ~1 s with the numeric stack loaded on a busy machine, docs/robustness.md): by then every output
    was closed or removed by the command's own context managers; the standard streams are flushed."""
    if code == EXIT_INTERRUPTED:
        import os

        for stream in (sys.stdout, sys.stderr):
            try:
                stream.flush()
            except (OSError, ValueError):
                pass
        os._exit(code)
    sys.exit(code)


if __name__ == "__main__":  # pragma: no cover
    exit_with(main())


def run() -> None:
    """Console-script entry point."""
    exit_with(main())
