"""The ``needle`` command. Each subcommand lives in its own module and registers itself on :data:`app`."""

from __future__ import annotations

import typer

from needlecli import __version__

app = typer.Typer(
    name="needle",
    help="Batch experiments with steerable-needle models, emulated sensors and observers.",
    no_args_is_help=True,
    pretty_exceptions_enable=False,
    add_completion=False,
)


def _version(value: bool) -> None:
    if value:
        typer.echo(f"needlecli {__version__}")
        raise typer.Exit()


@app.callback()
def main(
    version: bool = typer.Option(False, "--version", callback=_version, is_eager=True, help="Show the version."),
) -> None:
    """needle: simulate insertions, run observers, fit models, write tables in the papers' form."""


def run() -> None:
    from needlecli.cli import commands  # noqa: F401  (registers the subcommands)

    app()
