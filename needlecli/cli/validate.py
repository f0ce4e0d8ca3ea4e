"""``needle validate CONFIG...``: check configs against the schema, do nothing else."""

from __future__ import annotations

from pathlib import Path

import typer

from needlecli.errors import NeedleError


def validate(
    configs: list[Path] = typer.Argument(..., help="Config files to check."),
    set_: list[str] = typer.Option([], "--set", help="Override a key: --set sensors.0.rate=2"),
) -> None:
    """Check experiment configs; one line per config, exit code 2 if any is invalid."""
    from needlecli.experiments.config import load_config

    bad = 0
    for path in configs:
        try:
            load_config(path, overrides=set_)
        except NeedleError as e:  # a bad config, or a replay config whose logs are missing or bad
            typer.echo(f"error: {e}", err=True)
            bad += 1
        else:
            typer.echo(f"ok: {path}")
    if bad:
        raise typer.Exit(2)
