"""``needle evaluate RESULTS.h5``: error tables (and plots) from a results file."""

from __future__ import annotations

from pathlib import Path

import typer

from needlecli.cli.common import fail, setup_logging, user_errors


@user_errors
def evaluate(
    results: Path = typer.Argument(..., help="Results file of needle simulate, or fit file of needle fit-em."),
    out: Path = typer.Option(None, "--out", "-o", help="Folder for tables and plots (default: RESULTS_tables/ beside the results file)."),
    format_: str = typer.Option("md,csv,tex", "--format", "-f", help="Table formats: md, csv, tex."),
    tables: str = typer.Option(None, "--tables", "-t", help="Tables to write (default: the config's output.tables)."),
    plots: bool = typer.Option(True, "--plots/--no-plots", help="Write PNG plots of error against depth."),
    baseline: Path = typer.Option(None, "--baseline", "-b", help="Check the tables against stored expectations; exit 1 on a regression."),
    write_baseline: Path = typer.Option(None, "--write-baseline", help="Store the tables as expectations (YAML)."),
    rel_tol: float = typer.Option(0.1, "--rel-tol", min=0.0, help="Relative tolerance for --write-baseline."),
    abs_tol: float = typer.Option(1e-9, "--abs-tol", min=0.0, help="Absolute tolerance floor for --write-baseline."),
    group_by: str = typer.Option(None, "--group-by", help="Fit files: metadata keys of table fit_by_design (a,b)."),
    regress: str = typer.Option(None, "--regress", help="Fit files: regressions CONSTANT:FACTOR[,...] of fit_regression."),
    quiet: bool = typer.Option(False, "--quiet", "-q", help="Print nothing but errors."),
) -> None:
    """Compute error statistics per observer and write them as Markdown, CSV and LaTeX tables, and the
    plots (PNG); a fit file of needle fit-em gives the magnetic needle EM paper's tables and figures.

    Example: needle evaluate results/default.h5 --tables summary,accuracy,consistency
    """
    from needlecli.reports.evaluate import configured_tables_of, evaluate_results, experiment_name
    from needlecli.reports.tables import TABLES, to_markdown

    setup_logging(quiet)
    formats = [f.strip() for f in format_.split(",") if f.strip()]
    for f in formats:
        if f not in ("md", "csv", "tex"):
            fail(f"--format: unknown format {f!r}; use md, csv, tex")
    names = [t.strip() for t in tables.split(",")] if tables else None
    for t in names or []:
        if t not in TABLES:
            from needlecli.errors import did_you_mean

            fail(f"--tables: unknown table {t!r}; known: {', '.join(TABLES.names())}" + did_you_mean(t, TABLES.names()))
    names = [TABLES.canonical(t) for t in names] if names else None  # a former name: the table's current name
    out_dir = out if out is not None else results.parent / f"{results.stem}_tables"
    from needlecli.errors import ConfigError, shown
    from needlecli.io.atomic import check_output_dir, check_output_file
    from needlecli.reports.baseline import compare, load_baseline, make_baseline
    from needlecli.reports.baseline import write_baseline as store

    expected = load_baseline(baseline) if baseline is not None else None
    name = experiment_name(results)
    if expected is not None and expected.results and expected.results != name:
        raise ConfigError(str(baseline), ("results",), f"is for experiment {expected.results!r}, {results} is {name!r}")
    check_output_dir(out_dir, what="the tables")
    if write_baseline is not None:
        check_output_file(write_baseline, what="the baseline")
    if expected is not None and names is None:  # compute every table the baseline names
        names = sorted({c.table for c in expected.cells} | set(configured_tables_of(results)))
    design = {"group_by": [k.strip() for k in group_by.split(",") if k.strip()] if group_by else [],
              "regress": []}
    for item in (regress.split(",") if regress else []):
        c, sep, f = item.strip().partition(":")
        if not sep or not c or not f:
            fail(f"--regress: {item.strip()!r} is not CONSTANT:FACTOR (e.g. kappa:duty_cycle)")
        design["regress"].append((c.strip(), f.strip()))
    written = evaluate_results(results, tables=names, out_dir=out_dir, formats=formats, plots=plots, design=design)
    if write_baseline is not None:
        store(write_baseline, make_baseline(written, name, rel_tol, abs_tol))
        typer.echo(f"baseline: {shown(write_baseline)}", err=quiet)
    if not quiet:
        for table, df in written.items():
            typer.echo(f"## {table}\n")
            if df.attrs.get("caption"):
                typer.echo(df.attrs["caption"] + "\n")
            typer.echo(to_markdown(df) if not df.empty else "(empty)")
            typer.echo("")
        typer.echo(f"tables: {shown(out_dir)}")
    if expected is not None:
        failures = compare(written, expected, name, source=str(baseline))
        if failures:
            typer.echo(f"REGRESSION: {len(failures)} of {len(expected.cells)} baseline cells of {baseline} fail:", err=True)
            for f in failures:
                typer.echo(f.line(), err=True)
            raise typer.Exit(1)
        typer.echo(f"baseline: all {len(expected.cells)} cells of {baseline} hold")
