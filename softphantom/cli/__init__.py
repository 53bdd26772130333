"""Command-line interface: ``softphantom <command>``.

Each stage adds its commands in its own module under ``softphantom.cli``; :func:`main` turns
:class:`~softphantom.errors.SoftphantomError` into a one-line message and an exit code.
"""

from __future__ import annotations

import sys

from softphantom.cli.app import app, console_err
from softphantom.errors import SoftphantomError

# Importing the command modules registers their commands on ``app``.
_COMMAND_MODULES = ("design", "fem", "sensing", "estimation", "evaluation", "virtual", "demo", "live")


def _register() -> None:
    import importlib

    for name in _COMMAND_MODULES:
        try:
            importlib.import_module(f"softphantom.cli.{name}")
        except ModuleNotFoundError as exc:  # stage not built yet
            if exc.name != f"softphantom.cli.{name}":
                raise


def main(argv: list[str] | None = None) -> int:
    _register()
    try:
        app(args=argv, standalone_mode=False)
    except SoftphantomError as exc:
        console_err.print(f"[bold red]error:[/] {exc}", highlight=False, soft_wrap=True)
        return exc.exit_code
    except KeyboardInterrupt:
        console_err.print("interrupted")
        return 130
    except SystemExit as exc:  # typer/click exits (e.g. --help)
        return int(exc.code or 0)
    except Exception as exc:
        # Usage errors of the CLI framework (typer vendors click): show them, no traceback.
        if hasattr(exc, "show") and hasattr(exc, "exit_code"):
            exc.show()
            return int(exc.exit_code)
        if type(exc).__name__ == "Abort":
            return 1
        raise
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())


def run() -> None:
    """Console-script entry point."""
    sys.exit(main())
