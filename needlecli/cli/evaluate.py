"""``needle evaluate RESULTS.h5``: error tables (and plots) from a results file."""

from __future__ import annotations

from pathlib import Path

import typer

from needlecli.cli.app import app
from needlecli.cli.common import fail, setup_logging, user_errors
from needlecli.reports.evaluate import evaluate_results
from needlecli.reports.tables import TABLES, to_markdown


@app.command()
@user_errors
def evaluate(
    results: Path = typer.Argument(..., help="Results file written by needle simulate."),
    out: Path = typer.Option(None, "--out", "-o", help="Folder for tables and plots (default: beside the results)."),
    format_: str = typer.Option("md,csv,tex", "--format", "-f", help="Table formats: md, csv, tex."),
    tables: str = typer.Option(None, "--tables", "-t", help="Tables to write (default: the config's output.tables)."),
    plots: bool = typer.Option(True, "--plots/--no-plots", help="Write PNG plots of error against depth."),
    quiet: bool = typer.Option(False, "--quiet", "-q", help="Print nothing but errors."),
) -> None:
    """Compute error statistics per observer and write them as Markdown, CSV and LaTeX tables."""
    setup_logging(quiet)
    formats = [f.strip() for f in format_.split(",") if f.strip()]
    for f in formats:
        if f not in ("md", "csv", "tex"):
            fail(f"--format: unknown format {f!r}; use md, csv, tex")
    names = [t.strip() for t in tables.split(",")] if tables else None
    for t in names or []:
        if t not in TABLES:
            fail(f"--tables: unknown table {t!r}; known: {', '.join(TABLES.names())}")
    out_dir = out if out is not None else results.parent / f"{results.stem}_tables"
    written = evaluate_results(results, tables=names, out_dir=out_dir, formats=formats, plots=plots)
    if not quiet:
        for name, df in written.items():
            typer.echo(f"## {name}\n")
            typer.echo(to_markdown(df) if not df.empty else "(empty)")
            typer.echo("")
        typer.echo(f"tables: {out_dir}")
