"""``needle validate CONFIG...``: check configs against the schema, do nothing else."""

from __future__ import annotations

from pathlib import Path

import typer


def validate(
    configs: list[Path] = typer.Argument(..., metavar="CONFIG...", help="Config files to check."),
    set_: list[str] = typer.Option([], "--set", help="Override a key in every config: --set sensors.0.rate=2"),
    quiet: bool = typer.Option(False, "--quiet", "-q", help="Print nothing but the problems (no ok lines, no warnings)."),
) -> None:
    """Check experiment configs: every problem of each, one line each naming the config and the key
    (with a did-you-mean for a misspelt key or name), or "ok: CONFIG"; exit code 2 if any is invalid.
    A valid config's warnings follow on stderr: a state its sensors cannot observe along the nominal
    insertion (z with a 2D probe: every estimate of it keeps the start's error).

    Example: needle validate configs/default.yaml configs/multirate-ukf-us3d/*.yaml
    """
    import logging

    from needlecli.cli.common import WARNINGS, setup_logging
    from needlecli.errors import one_line, shown
    from needlecli.experiments.config.load import checked_config
    from needlecli.experiments.simulation.observability import unobservable_states

    setup_logging(quiet, level=logging.WARNING)  # warnings (from_fit takes what a fit did not identify)
    WARNINGS.start()
    bad = 0
    try:
        for path in configs:
            cfg, problems = checked_config(path, overrides=set_)
            warnings = WARNINGS.take()  # a config's warnings: shown when it is valid, before its ok line
            for e in problems:  # a bad config, or a replay config whose logs are missing or bad
                line = one_line(str(e))
                if not line.startswith(shown(path)):  # a log's or a fit file's problem: say which config it is of
                    line = f"{shown(path)}: {line}"
                typer.echo(f"error: {line}", err=True)
            if problems:
                bad += 1
                continue
            for w in warnings:
                typer.echo(w, err=True)
            if not quiet:
                typer.echo(f"ok: {shown(path)}")
                for u in unobservable_states(cfg):
                    typer.echo(f"warning: {shown(path)}: [sensors] {u.message()}", err=True)
    finally:
        WARNINGS.stop()
    if bad:
        raise typer.Exit(2)
