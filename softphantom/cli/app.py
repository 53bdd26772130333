"""The shared typer application, the consoles, the one way errors are printed and the root options
(``-v``/``-q``: :mod:`softphantom.cli.logs`)."""

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
def _root(
    ctx: typer.Context,
    verbose: bool = typer.Option(False, "--verbose", "-v", help="Debug messages too."),
    quiet: bool = typer.Option(False, "--quiet", "-q", help="Warnings and errors only (no progress)."),
) -> None:
    """Sensorized soft organ phantoms: design, simulate, sense, estimate, evaluate."""
    from softphantom.cli.logs import close_logging, configure_from_options

    configure_from_options(verbose, quiet, console)
    ctx.call_on_close(close_logging)
