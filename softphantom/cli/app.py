"""The shared typer application and consoles (no other state)."""

from __future__ import annotations

import typer
from rich.console import Console

app = typer.Typer(
    name="softphantom",
    help="Sensorized soft organ phantoms: design, simulate, sense, estimate, evaluate.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)
console = Console()
console_err = Console(stderr=True)


@app.command()
def version() -> None:
    """Print the softphantom version."""
    from softphantom import __version__

    console.print(f"softphantom {__version__}")


@app.callback()
def _root() -> None:
    """Sensorized soft organ phantoms: design, simulate, sense, estimate, evaluate."""
