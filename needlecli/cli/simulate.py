"""``needle simulate CONFIG``: run every Monte-Carlo insertion of an experiment and write its results."""

from __future__ import annotations

from pathlib import Path

import typer

from needlecli.cli.common import check_results_target, log, progress_bar, setup_logging, user_errors


@user_errors
def simulate(
    config: Path = typer.Argument(..., help="Experiment config (YAML)."),
    runs: int = typer.Option(None, "--runs", "-n", min=1, help="Number of Monte-Carlo runs (overrides runs.count)."),
    seed: int = typer.Option(None, "--seed", "-s", min=0, help="Seed (overrides runs.seed)."),
    out: Path = typer.Option(None, "--out", "-o", help="Results file (default: output.path or results/NAME.h5, NAME the config's name)."),
    set_: list[str] = typer.Option([], "--set", help="Override a config key: --set sensors.0.rate=2"),
    dry_run: bool = typer.Option(False, "--dry-run", help="Validate and describe; simulate nothing."),
    quiet: bool = typer.Option(False, "--quiet", "-q", help="No progress bar or log lines."),
) -> None:
    """Simulate the insertions, measure them, run the observers, write one HDF5 results file and print
    the summary table.

    Example: needle simulate configs/default.yaml --runs 10 --set sensors.0.rate=2
    """
    from needlecli.errors import shown
    from needlecli.experiments.config.load import load_config
    from needlecli.experiments.simulation.runner import default_output, run_experiment
    from needlecli.reports.evaluate import results_tables
    from needlecli.reports.tables import to_markdown

    setup_logging(quiet)
    cfg, text = load_config(config, overrides=set_, runs=runs, seed=seed)
    target = out if out is not None else default_output(cfg)
    check_results_target(cfg, target, config.parent)
    if dry_run:
        typer.echo(
            f"{config}: valid; {cfg.runs.count} run(s) of model {cfg.model.type!r}, seed {cfg.runs.seed}, "
            f"{len(cfg.sensors)} sensor(s), {len(cfg.observers)} observer(s)"
            + (f", {len(cfg.control)} controller(s) in closed loop" if cfg.control else "") + f" -> {target}"
        )
        return
    log.info("simulating %d run(s) of %s (seed %d)", cfg.runs.count, cfg.name, cfg.runs.seed)
    with progress_bar(not quiet) as bar:
        result = run_experiment(cfg, text, out=target, progress=bar, base_dir=config.parent)
    stopped = any((p.status != "ok").any() for p in result.estimates.values()) or (result.truth.status != "ok").any()
    path = result.path
    wanted = (["summary"] if cfg.observers else []) + (["status"] if stopped else [])
    tables = results_tables(result.tree, wanted, str(path)) if wanted else {}  # the file's content, in memory
    tables.pop("__errors__", None)
    del result
    for df in tables.values():
        if not df.empty:
            typer.echo((df.attrs["caption"] + "\n\n" if df.attrs.get("caption") else "") + to_markdown(df) + "\n")
    if not cfg.observers:
        typer.echo("no observers configured: truth and measurements only")
    typer.echo(f"results: {shown(path)}")
