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
    set_: list[str] = typer.Option([], "--set", help="Override a config key: --set fit.em.max_iter=50"),
    quiet: bool = typer.Option(False, "--quiet", "-q", help="No progress bar or log lines."),
) -> None:
    """Fit the config's fit: section by EM on the training trials of each fold and run the held-out trials
    through the hand-tuned observers and their EM-tuned copies (NAME_em), from one common start; print
    and write the held-out errors (summary, by depth) and each fold's fitted constants.

    Example: needle crossval configs/real/em_tracker.yaml --observer open_loop --leave-one-out --group-by 'id~^[^-]+' --within
    """
    from needlecli.errors import shown
    from needlecli.experiments.studies.crossval import check_args
    from needlecli.experiments.studies.crossval import crossval as run_crossval
    from needlecli.reports.crossval import crossval_plot, crossval_tables
    from needlecli.reports.tables import to_markdown, write_table

    setup_logging(quiet)
    check_args(leave_one_out, within, folds, group_by)  # the options alone, before anything is read or written
    with progress_bar(not quiet) as bar:
        result = run_crossval(config, observers=observer, model=model, folds=folds,
                              leave_one_out=leave_one_out, group_by=group_by, within=within, out_dir=out,
                              overrides=set_, progress=bar)
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
