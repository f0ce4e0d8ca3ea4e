"""``needle log ...``: make, import and inspect log files of recorded (or synthetic) insertions."""

from __future__ import annotations

from pathlib import Path

import typer

from needlecli.cli.common import user_errors

log_app = typer.Typer(help="Log files of recorded insertions: import, convert, inspect.", no_args_is_help=True)


@log_app.command("import-csv")
@user_errors
def import_csv_cmd(
    mapping: Path = typer.Argument(..., help="Mapping YAML describing the CSV exports."),
    out: Path = typer.Option(..., "--out", "-o", help="Log file to write (HDF5)."),
) -> None:
    """Import CSV exports (one file per stream: a time column and value columns) into a log."""
    from needlecli.io.atomic import check_output_file
    from needlecli.io.csv_import import import_csv
    from needlecli.io.logs import write_log

    check_output_file(out, what="the log file")
    log = import_csv(mapping)
    write_log(out, log, source=mapping)
    typer.echo(f"log: {out} ({len(log.trials)} trial(s))")


@log_app.command("from-results")
@user_errors
def from_results_cmd(
    results: Path = typer.Argument(..., help="Results file of needle simulate."),
    out: Path = typer.Option(..., "--out", "-o", help="Log file to write (HDF5)."),
    description: str = typer.Option("", help="Description stored in the log."),
    truth_every: int = typer.Option(1, "--truth-every", min=1, help="Keep the truth every k-th step (a slower tracker)."),
    prefix: str = typer.Option("run", "--prefix", help="Trial ids are <prefix><run number>."),
) -> None:
    """Turn a simulated experiment into a log (one trial per run), marked synthetic with its config."""
    from needlecli.io.atomic import check_output_file
    from needlecli.io.logs import log_from_results, write_log
    from needlecli.io.results import read_results

    check_output_file(out, what="the log file")
    log = log_from_results(read_results(results), description=description, truth_every=truth_every, prefix=prefix)
    write_log(out, log, source=results)
    typer.echo(f"log: {out} ({len(log.trials)} trial(s), synthetic)")


@log_app.command("info")
@user_errors
def info_cmd(log_file: Path = typer.Argument(..., help="Log file.")) -> None:
    """Check a log and describe its trials, streams and truth."""
    from needlecli.io.logs import read_log

    log = read_log(log_file)
    typer.echo(f"{log_file}: {len(log.trials)} trial(s); {log.attrs.get('description', '')}")
    if log.attrs.get("synthetic"):
        typer.echo(f"  synthetic: {log.attrs.get('source', '')}")
    for tr in log.trials:
        parts = [f"{n} ({len(s.t)} samples, {int((~s.valid).sum())} invalid, {s.settings.get('type')})"
                 for n, s in tr.sensors.items()]
        truth = f"truth: {tr.truth.kind}, {len(tr.truth.t)} samples" if tr.truth is not None else "no truth"
        typer.echo(f"  {tr.id}: {tr.end_time:.2f} s; inputs {', '.join(tr.inputs) or 'none'}; "
                   f"sensors {'; '.join(parts)}; {truth}")


@log_app.command("merge")
@user_errors
def merge_cmd(
    logs: list[Path] = typer.Argument(..., help="Log files to merge."),
    out: Path = typer.Option(..., "--out", "-o", help="Merged log file."),
    description: str = typer.Option("", help="Description stored in the log."),
) -> None:
    """Merge the trials of several logs into one file."""
    from needlecli.io.atomic import check_output_file
    from needlecli.io.logs import merge_logs, read_log, write_log

    check_output_file(out, what="the merged log")
    merged = merge_logs([read_log(p) for p in logs], description=description)
    write_log(out, merged, source=", ".join(str(p) for p in logs))
    typer.echo(f"log: {out} ({len(merged.trials)} trial(s))")
