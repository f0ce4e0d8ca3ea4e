"""``needle log ...``: make, import and inspect log files of recorded (or synthetic) insertions."""

from __future__ import annotations

from pathlib import Path

import typer

from needlecli.cli.common import setup_logging, user_errors
from needlecli.errors import shown

log_app = typer.Typer(help="Log files of recorded insertions: import, convert, inspect.\n\n"
                           "Example: needle log info datasets/multirate-ukf-us3d_like.h5", no_args_is_help=True)


@log_app.command("import-csv")
@user_errors
def import_csv_cmd(
    mapping: Path = typer.Argument(..., help="Mapping YAML describing the CSV exports."),
    out: Path = typer.Option(..., "--out", "-o", help="Log file to write (HDF5)."),
    quiet: bool = typer.Option(False, "--quiet", "-q", help="No log lines or warnings on stderr (the file written is still named)."),
) -> None:
    """Import CSV exports (one file per stream: a time column and value columns) into a log.

    Example: needle log import-csv results/owndata/exports/mapping.yaml --out results/owndata/lab.h5
    """
    setup_logging(quiet)
    from needlecli.cli.common import log as warn
    from needlecli.io.atomic import check_output_file
    from needlecli.io.csv_import import import_csv
    from needlecli.io.logs import write_log

    check_output_file(out, what="the log file")
    log = import_csv(mapping)
    write_log(out, log, source=mapping)
    for line in axis_warnings(log.trials):
        warn.warning("warning: %s", line)
    typer.echo(f"log: {shown(out)} ({len(log.trials)} trial(s))")


@log_app.command("from-results")
@user_errors
def from_results_cmd(
    results: Path = typer.Argument(..., help="Results file of needle simulate."),
    out: Path = typer.Option(..., "--out", "-o", help="Log file to write (HDF5)."),
    description: str = typer.Option("", help="Description stored in the log."),
    truth_every: int = typer.Option(1, "--truth-every", min=1, help="Keep the truth every k-th step (a slower tracker)."),
    prefix: str = typer.Option("run", "--prefix", help="Trial ids are PREFIX followed by the run number."),
    quiet: bool = typer.Option(False, "--quiet", "-q", help="No log lines or warnings on stderr (the file written is still named)."),
) -> None:
    """Turn a simulated experiment into a log (one trial per run), marked synthetic with its config.

    Example: needle log from-results results/default.h5 --out results/default_log.h5 --truth-every 10
    """
    setup_logging(quiet)
    from needlecli.io.atomic import check_output_file
    from needlecli.io.logs import log_from_results, write_log
    from needlecli.io.results import read_results

    check_output_file(out, what="the log file")
    log = log_from_results(read_results(results), description=description, truth_every=truth_every, prefix=prefix)
    write_log(out, log, source=results)
    typer.echo(f"log: {shown(out)} ({len(log.trials)} trial(s), synthetic)")


@log_app.command("export-csv")
@user_errors
def export_csv_cmd(
    log_file: Path = typer.Argument(..., help="Log file (e.g. a simulation made a log by needle log from-results)."),
    out: Path = typer.Option(..., "--out", "-o", help="Folder for the exports and their mapping.yaml."),
    sensor: str = typer.Option("tracker", "--sensor", help="The position sensor written as the tracker's poses."),
    tracker_pose: str = typer.Option(None, "--tracker-pose",
                                     help="Where the tracker sees the model frame: rx,ry,rz,tx,ty,tz (deg, mm)."),
    sensor_roll: float = typer.Option(0.0, "--sensor-roll", help="The tracker coil's roll in the needle, deg."),
    quiet: bool = typer.Option(False, "--quiet", "-q", help="No log lines or warnings on stderr (the file written is still named)."),
) -> None:
    """Write a log as a lab's tracker exports: step-indexed pose files (quaternions, zero rows where a
    sample was lost, each sample's rms), a command file per trial, and the mapping that imports them.

    Example: needle log export-csv results/default_log.h5 --out results/exports --tracker-pose 10,80,25,120,-40,15
    """
    setup_logging(quiet)
    from needlecli.io.atomic import check_output_dir
    from needlecli.io.csv_export import export_lab_csv
    from needlecli.io.logs import read_log

    check_output_dir(out, what="the exports")
    files = export_lab_csv(read_log(log_file), out, sensor=sensor, pose=tracker_pose, roll_deg=sensor_roll)
    typer.echo(f"exports: {shown(out)} ({len(files) - 1} files and mapping.yaml)")


@log_app.command("info")
@user_errors
def info_cmd(
    log_file: Path = typer.Argument(..., help="Log file."),
    meta: bool = typer.Option(False, "--meta", help="Print every trial's metadata too."),
) -> None:
    """Check a log and describe its trials, streams and truth; for imported trials what was read, dropped
    and why, where each trial starts and its frame.

    Example: needle log info datasets/multirate-ukf-us3d_like.h5 --meta
    """
    import logging

    from needlecli.cli.common import log as warn
    from needlecli.io.logs import read_log

    setup_logging(False, level=logging.WARNING)
    log = read_log(log_file)
    typer.echo(f"{shown(log_file)}: {len(log.trials)} trial(s); {log.attrs.get('description', '')}")
    if log.attrs.get("synthetic"):
        typer.echo(f"  synthetic: {log.attrs.get('source', '')}")
    for tr in log.trials:
        parts = [f"{n} ({len(s.t)} samples, {int((~s.valid).sum())} invalid, {s.settings.get('type')}"
                 + (", per-sample sigma" if s.sigma is not None else "") + ")"
                 for n, s in tr.sensors.items()]
        truth = f"truth: {tr.truth.kind}, {len(tr.truth.t)} samples" if tr.truth is not None else "no truth"
        typer.echo(f"  {tr.id}: {tr.end_time:.2f} s; inputs {', '.join(tr.inputs) or 'none'}; "
                   f"sensors {'; '.join(parts)}; {truth}")
        for line in trial_report_lines(tr, meta):
            typer.echo(f"    {line}")
    if not log.attrs.get("synthetic"):  # a simulation's log is in its model's frame
        for line in axis_warnings(log.trials):
            warn.warning("warning: %s", line)


def axis_warnings(trials) -> list[str]:
    """One line per recorded trial and stream whose path starts more than
    :data:`~needlecli.io.frames.AXIS_WARNING_DEG` from ``+z``, the insertion axis of the models' default pose
    (a trial frame's ``z``): the streams with a tip position (position sensors with x, y, z; a truth with
    them)."""
    import numpy as np

    from needlecli.io.frames import AXIS_WARNING_DEG, axis_angles, initial_directions

    out = []
    for tr in trials:
        streams = [(f"sensor {n}", s.names, s.value, s.valid) for n, s in tr.sensors.items()
                   if s.settings.get("type") == "position"]
        if tr.truth is not None:
            streams.append(("the truth", tr.truth.names, tr.truth.state, np.ones(len(tr.truth.t), dtype=bool)))
        for what, names, value, valid in streams:
            names = list(names)
            if not {"x", "y", "z"} <= set(names) or np.ndim(value) != 2:
                continue
            pos = np.asarray(value, dtype=float)[:, [names.index(a) for a in "xyz"]]
            ang = float(axis_angles(initial_directions(pos[None], np.asarray(valid, dtype=bool)[None]), [0.0, 0.0, 1.0])[0])
            if ang > AXIS_WARNING_DEG:
                framed = '"frame"' in str(tr.meta.get("import_report", ""))
                hint = ("the trial frame of its import does not put the insertion on z: check the reference's "
                        "orientation (its quaternion's convention), or take the axes from the path (frame z: path)"
                        if framed else "express the trial in its own frame (a CSV mapping's frame: {reference: ...})")
                out.append(f"trial {tr.id}: the path of {what} starts {ang:.0f} deg from the model's insertion axis +z "
                           f"(more than {AXIS_WARNING_DEG:g} deg): {hint} before fitting it")
    return out


def trial_report_lines(tr, all_meta: bool = False) -> list[str]:
    """What ``needle log info`` says about one trial beyond its streams: its design factors, and for an
    imported trial (``import_report``) each stream's rows read, valid, lost and why, the rate, where the
    trial starts, its frame, warnings."""
    import json

    from needlecli.io.logs import design_factors

    out = []
    factors = design_factors(tr)
    if factors:
        out.append("design factors: " + ", ".join(f"{f} = {tr.meta.get(f)}" for f in factors))
    if all_meta:
        out.append("metadata: " + "; ".join(f"{k} = {v}" for k, v in tr.meta.items() if k != "import_report"))
    raw = tr.meta.get("import_report")
    if not raw:
        return out
    try:
        rep = json.loads(raw)
    except (json.JSONDecodeError, TypeError):
        return out + ["import report: not readable"]
    for name, st in rep.get("streams", {}).items():
        if "constant" in st:
            out.append(f"{name}: constant {st['value']} = {st['constant']}")
            continue
        bits = [f"{st.get('file', '?')}: {st.get('rows', '?')} rows", f"time from {st.get('time', '?')}"]
        if "valid" in st:
            bits.append(f"{st['valid']} valid")
        inv = st.get("invalid") or {}
        if inv:
            bits.append("lost: " + ", ".join(f"{v} {k}" for k, v in inv.items()))
        for k, v in st.items():
            if k.startswith("dropped") or k.startswith("left out"):
                bits.append(f"{v} {k}")
        if st.get("rate_hz"):
            bits.append(f"{float(st['rate_hz']):.4g} Hz")
        out.append(f"read {name}: " + "; ".join(bits))
    start = rep.get("start")
    if start:
        out.append(f"start ({start.get('mode')}): {start.get('what')}")
    fr = rep.get("frame")
    if fr:
        bits = [f"origin {fr.get('origin')} {fr.get('origin_unit', '')}", f"z from {fr.get('z_from')}"]
        if "roll_psi_deg" in fr:
            bits.append(f"rolled {fr['roll_psi_deg']} deg (bending onto -y)")
        elif "bend_from" in fr:
            bits.append(f"-y from {fr['bend_from']}")
        out.append("frame: " + "; ".join(bits))
    for w in rep.get("warnings", []):
        out.append(f"warning: {w}")
    return out


@log_app.command("merge")
@user_errors
def merge_cmd(
    logs: list[Path] = typer.Argument(..., help="Log files to merge."),
    out: Path = typer.Option(..., "--out", "-o", help="Merged log file."),
    description: str = typer.Option("", help="Description stored in the log."),
    quiet: bool = typer.Option(False, "--quiet", "-q", help="No log lines or warnings on stderr (the file written is still named)."),
) -> None:
    """Merge the trials of several logs into one file.

    Example: needle log merge a.h5 b.h5 --out merged.h5 --description "two sessions"
    """
    setup_logging(quiet)
    from needlecli.io.atomic import check_output_file
    from needlecli.io.logs import merge_logs, read_log, write_log

    check_output_file(out, what="the merged log")
    merged = merge_logs([read_log(p) for p in logs], description=description)
    write_log(out, merged, source=", ".join(str(p) for p in logs))
    typer.echo(f"log: {shown(out)} ({len(merged.trials)} trial(s))")
