"""``needle crossval CONFIG --observer NAME``: EM-tuned observers on trials their fit never saw."""

from __future__ import annotations

from pathlib import Path

import typer

from needlecli.cli.common import progress_bar, setup_logging, user_errors


@user_errors
def crossval(
    config: Path = typer.Argument(..., help="Experiment config with a fit: section (recorded trials through source: logs, or simulated)."),
    observer: list[str] = typer.Option(..., "--observer", "-O", help="Observer of the config to tune by EM (repeatable)."),
    model: str = typer.Option(None, "--model", "-m", help="Fitted model whose parameters the tuned observers take (default: the fit's only one)."),
    folds: int = typer.Option(None, "--folds", "-k", help="Number of folds (default 5; whole groups with --group-by)."),
    leave_one_out: bool = typer.Option(False, "--leave-one-out", help="Hold out one trial at a time."),
    group_by: str = typer.Option(None, "--group-by", help="Group trials by a metadata key, or id~REGEX on their ids (e.g. 'id~^[^-]+')."),
    within: bool = typer.Option(False, "--within", help="With --leave-one-out: fit on the other trials of the held-out one's group only."),
    out: Path = typer.Option(None, "--out", "-o", help="Folder for folds, fits and tables (default: results/NAME_crossval)."),
    from_depths: str = typer.Option("0,20,40", "--from-depths", help="Also predict each held-out trial from its pose at these inserted depths (comma-separated, the model's length unit; '' for none)."),
    pose_from: list[str] = typer.Option(["truth"], "--pose-from", help="Where that pose comes from (repeatable): truth (the recorded pose) or an observer of the folds (e.g. a smoother tuned by the fold's fit: NAME_em)."),
    set_: list[str] = typer.Option([], "--set", help="Override a config key: --set fit.em.max_iter=50"),
    quiet: bool = typer.Option(False, "--quiet", "-q", help="No progress bar or log lines."),
) -> None:
    """Fit the config's fit: section by EM on the training trials of each fold and run the held-out trials
    through the hand-tuned observers and their EM-tuned copies (NAME_em), from one common start; print
    and write the held-out errors (summary, by depth) and each fold's fitted constants. Each held-out trial is
    also predicted from its own pose at --from-depths, with no measurement after it (table from_pose): the
    error from that pose is the model's part of the held-out error, the rest of the error from the start is
    the start pose's.

    Example: needle crossval configs/real/em_tracker.yaml --observer open_loop --leave-one-out --group-by 'id~^[^-]+' --within
    """
    from needlecli.errors import shown
    from needlecli.experiments.studies.crossval import check_args
    from needlecli.experiments.studies.crossval import crossval as run_crossval
    from needlecli.reports.crossval import crossval_plot, crossval_tables
    from needlecli.reports.tables import to_markdown, write_table

    setup_logging(quiet)
    check_args(leave_one_out, within, folds, group_by)  # the options alone, before anything is read or written
    depths = _depths(from_depths)
    with progress_bar(not quiet) as bar:
        result = run_crossval(config, observers=observer, model=model, folds=folds,
                              leave_one_out=leave_one_out, group_by=group_by, within=within, out_dir=out,
                              overrides=set_, progress=bar, from_depths=depths, pose_from=pose_from)
    tables = crossval_tables(result.results)  # from the folds' results files alone
    how = ("leave-one-out" + (f" within groups ({group_by})" if within else "") if leave_one_out
           else f"{len(result.folds)} folds" + (f" of whole groups ({group_by})" if group_by else ""))
    captions = {
        "summary": f"Held-out trials ({how}): position error of each observer over every held-out trial and time "
                   f"step after the first; <name>_em: the observer with Q, R and constants fitted by EM ({result.model}) "
                   "on the training trials only (measurements, never the truth); all from one common start.",
        "by_depth": f"Held-out trials ({how}): mean position error per inserted depth"
                    + (", over all of them and per group of the held-out trials." if group_by else "."),
        "constants": f"Constants fitted by EM ({result.model}) on each fold's training trials: median over its trials "
                     "fitted ok and the pooled standard error (identifiability).",
        "from_pose": f"Held-out trials ({how}): mean position error against the distance predicted ahead, from the common "
                     "start (the error at each inserted depth) and from the trial's own pose at each start depth, with no "
                     "measurement after it (the recorded pose: its truth at the first sample there; or an observer's estimate "
                     "there): the error from a pose is the model's part (parameters, path), the rest of the error from the "
                     "start over the same distance is the start pose's.",
    }
    for name, df in tables.items():
        write_table(df, result.out_dir / f"crossval_{name}", ["md", "csv", "tex"], caption=captions[name])
        if not quiet:
            typer.echo(f"## {name}\n\n{captions[name]}\n")
            typer.echo(to_markdown(df) if not df.empty else "(empty)")
            typer.echo("")
    crossval_plot(tables["by_depth"], result.out_dir / "crossval_by_depth.png",
                  f"held-out trials ({how}): mean position error against depth")
    typer.echo(f"tables: {shown(result.out_dir)}")


def _depths(text: str) -> list[float]:
    """``--from-depths`` as numbers (``''``: none)."""
    from needlecli.errors import ConfigError

    out = []
    for part in (p.strip() for p in text.split(",")):
        if not part:
            continue
        try:
            out.append(float(part))
        except ValueError:
            raise ConfigError("--from-depths", (), f"{part!r} is not a number: give depths like 0,20,40") from None
    return out
