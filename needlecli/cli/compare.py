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
    sensors on the same insertions and measurements; print the table in the form of seed 003's
    appendix A and write it (compare.md, compare.csv) with the results file.

    Example: needle compare configs/seed003/table1.yaml --runs 20 --observers ukf,ekf,open_loop
    """
    import textwrap

    from needlecli.experiments.studies.compare import FOOTNOTE, appendix_form, compare_observers, compare_table, terminal_form
    from needlecli.reports.tables import _atomic_text, to_markdown, write_table

    setup_logging(quiet)
    wanted = [o.strip() for o in observers.split(",") if o.strip()] if observers else None
    with progress_bar(not quiet) as bar:
        result = compare_observers(source, observers=wanted, runs=runs, seed=seed, model=model, overrides=set_,
                                   out_dir=out, progress=bar)
    out_dir = result.path.parent
    df = compare_table(result)
    wide = appendix_form(df, result)
    skipped = [f"{c.name} ({c.type}): {c.skip}" for c in result.skipped]
    caption = f"Observers on the same insertions of {result.cfg.name} ({result.n_runs} runs)."
    write_table(df, out_dir / "compare", ["csv"])
    notes = FOOTNOTE + f"\n\nStart: {result.start}." + ("\n\nSkipped:\n" + "\n".join(f"- {s}" for s in skipped) if skipped else "")
    _atomic_text(out_dir / "compare.md", f"{caption}\n\n{to_markdown(wide)}\n\n{notes}\n")
    typer.echo(terminal_form(df, result) if len(df) else "(no observer could run)")
    if result.truth_failed:
        typer.echo(f"{result.truth_failed} run(s) of the truth stopped early (not counted above)")
    for s in skipped:
        typer.echo(textwrap.fill(f"skipped: {s}", 80, subsequent_indent="  "))
    typer.echo(f"table: {out_dir / 'compare.md'}, {out_dir / 'compare.csv'}")
    typer.echo(f"results: {result.path}")
