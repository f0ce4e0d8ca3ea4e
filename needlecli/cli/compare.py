"""``needle compare CONFIG_OR_LOG``: every applicable observer on the same insertions, one table."""

from __future__ import annotations

from pathlib import Path

import typer

from needlecli.cli.common import progress_bar, setup_logging, user_errors


@user_errors
def compare(
    source: Path = typer.Argument(..., help="Experiment config (YAML) or a log file (HDF5, needlecli-log)."),
    observers: str = typer.Option(None, "--observers", help="Only these observers (names or types, comma-separated)."),
    runs: int = typer.Option(None, "--runs", "-n", min=1, help="Runs (a config) or first trials (a log)."),
    seed: int = typer.Option(None, "--seed", "-s", min=0, help="Seed (overrides runs.seed)."),
    model: str = typer.Option(None, "--model", "-m", help="Model to replay a log with (logs only)."),
    out: Path = typer.Option(None, "--out", "-o", help="Folder for the results file and tables (default: results/NAME_compare)."),
    set_: list[str] = typer.Option([], "--set", help="Override a config key: --set sensors.0.rate=2"),
    quiet: bool = typer.Option(False, "--quiet", "-q", help="No progress bar or log lines."),
) -> None:
    """Simulate (or replay) once and run every registered observer that can run on the experiment's
    sensors on the same insertions and measurements; print the table in the form of the multi-rate UKF paper's
    appendix A and write it (compare.md, compare.csv) with the results file and the plots (each error
    against the inserted depth, compare_error_vs_depth.png). Warns when a filter does worse than the
    model alone from the same start.

    Example: needle compare configs/multirate-ukf-us3d/table1.yaml --runs 20 --observers ukf,ekf,open_loop
    """
    import logging
    import textwrap

    from needlecli.errors import shown
    from needlecli.experiments.studies.compare import compare_observers
    from needlecli.io.results import read_results
    from needlecli.metrics import compute_errors
    from needlecli.reports.compare import (
        appendix_form,
        compare_table,
        notes,
        skipped,
        terminal_form,
        truth_failed,
        with_axis_errors,
        worse_than_model,
    )
    from needlecli.reports.plots import draw_plots
    from needlecli.reports.tables import _atomic_text, to_markdown, write_table

    setup_logging(quiet)
    wanted = [o.strip() for o in observers.split(",") if o.strip()] if observers else None
    with progress_bar(not quiet) as bar:
        result = compare_observers(source, observers=wanted, runs=runs, seed=seed, model=model, overrides=set_,
                                   out_dir=out, progress=bar)
    out_dir = result.path.parent
    res = read_results(result.path)  # the tables, as every table, from the results file alone
    errors = compute_errors(res)
    df = compare_table(res, errors)
    wide = appendix_form(df, res)
    n_runs = int(res.data["truth"].data["status"].shape[0])
    caption = f"Observers on the same insertions of {res.attrs.get('name', '')} ({n_runs} runs)."
    write_table(df, out_dir / "compare", ["csv"])
    _atomic_text(out_dir / "compare.md", f"{caption}\n\n{to_markdown(wide)}\n\n{notes(res, df)}\n")
    plots = draw_plots(res, with_axis_errors(res, errors), out_dir / "compare", names=["error_vs_depth"]) if len(df) else []
    typer.echo(terminal_form(df, res) if len(df) else "(no observer could run)")
    log = logging.getLogger("needlecli")
    for w in worse_than_model(df):
        log.warning("compare: %s", w)
    if truth_failed(res):
        typer.echo(f"{truth_failed(res)} run(s) of the truth stopped early (not counted above)")
    for s in skipped(res):
        typer.echo(textwrap.fill(f"skipped: {s}", 80, subsequent_indent="  "))
    typer.echo(f"table: {shown(out_dir / 'compare.md')}, {shown(out_dir / 'compare.csv')}")
    if plots:
        typer.echo(f"plots: {', '.join(shown(p) for p in plots)}")
    typer.echo(f"results: {shown(result.path)}")
