"""``needle import ...``: turn a public data set's own file layout into a log file."""

from __future__ import annotations

from pathlib import Path

import typer

from needlecli.cli.common import setup_logging, user_errors

import_app = typer.Typer(help="Import recorded data sets (their own file layouts) into log files.\n\n"
                              "Example: needle import ultrasteer DIR --out LOG.h5", no_args_is_help=True)


@import_app.command("ultrasteer")
@user_errors
def ultrasteer_cmd(
    data_dir: Path = typer.Argument(..., help="The data set's folder (with trials/ and resultsOrig/)."),
    out: Path = typer.Option(..., "--out", "-o", help="Log file to write (HDF5)."),
    align: bool = typer.Option(True, "--align/--no-align",
                               help="Register the tracker's rotations to its positions (one rotation per session) "
                                    "and roll the body frame so the needle bends toward -y."),
    frame: str = typer.Option("trial", "--frame",
                              help="trial: origin and axes of each trial's first tracker frame; tracker: the tracker's."),
    quiet: bool = typer.Option(False, "--quiet", "-q", help="No log lines or warnings on stderr (the file written is still named)."),
) -> None:
    """Import the ultrasteer insertions (EM tracker ground truth, ultrasound tip positions) into a log.

    Example: needle import ultrasteer ../shared/real-data/ultrasteer --out results/real/ultrasteer.h5
    """
    setup_logging(quiet)
    from needlecli.errors import DataError, shown
    from needlecli.io.atomic import check_output_file
    from needlecli.io.logs import write_log
    from needlecli.io.ultrasteer import import_ultrasteer

    if frame not in ("trial", "tracker"):
        raise DataError(f"--frame: {frame!r} is not one of trial, tracker")
    check_output_file(out, what="the log file")
    log = import_ultrasteer(data_dir, align=align, frame=frame)
    write_log(out, log, source=data_dir)
    us = sum(1 for tr in log.trials if "us" in tr.sensors)
    typer.echo(f"log: {shown(out)} ({len(log.trials)} trial(s), {us} with ultrasound)")
