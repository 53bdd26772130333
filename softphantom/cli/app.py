"""The shared typer application, the consoles and the one way errors are printed (no other state)."""

from __future__ import annotations

import typer
from rich.console import Console
from rich.text import Text

app = typer.Typer(
    name="softphantom",
    help="Sensorized soft organ phantoms: design, simulate, sense, estimate, evaluate.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)
# markup off: a message or a path with brackets ("[x, y, z]", "[red]") is printed as it is
console = Console(markup=False)
console_err = Console(stderr=True, markup=False)


def print_error(message: str, prefix: str = "error: ") -> None:
    """One line on stderr (``prefix`` in bold red, then ``message`` as it is: never markup)."""
    console_err.print(Text.assemble((prefix, "bold red"), str(message)), highlight=False, soft_wrap=True)


@app.command()
def version() -> None:
    """Print the softphantom version."""
    from softphantom import __version__

    console.print(f"softphantom {__version__}")


@app.callback()
def _root() -> None:
    """Sensorized soft organ phantoms: design, simulate, sense, estimate, evaluate."""
