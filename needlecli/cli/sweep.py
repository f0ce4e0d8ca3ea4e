"""``needle sweep CONFIG --grid GRID.yaml``: one experiment per cell of a parameter grid, in parallel; or one
cell by its index (``--cell I``, a job array's task) and the table of whatever cells exist (``--collect``)."""

from __future__ import annotations

import shutil
import sys
from pathlib import Path

import typer

from needlecli.cli.common import fail, log, progress_bar, setup_logging, user_errors
from needlecli.errors import Interrupted


@user_errors(outputs="each")  # each cell kept when complete, for --resume
def sweep(
    config: Path = typer.Argument(..., help="Experiment config (YAML): the base of every cell."),
    grid: Path = typer.Option(..., "--grid", "-g", help="Grid file: axes, cells or random samples of dotted overrides."),
    executor: str = typer.Option("local", "--executor", "-e", help="local (processes), dask (a distributed cluster) or inline."),
    scheduler: str = typer.Option(None, "--scheduler", help="Dask scheduler address, e.g. tcp://10.0.0.5:8786 (default: start a LocalCluster)."),
    workers: int = typer.Option(None, "--workers", "-w", min=1, help="Local worker processes (default: the CPU count)."),
    out: Path = typer.Option(None, "--out", "-o", help="Sweep folder (default: results/sweeps/CONFIG_GRID, the files' names)."),
    resume: bool = typer.Option(False, "--resume", help="Skip cells whose complete results already exist."),
    set_: list[str] = typer.Option([], "--set", help="Override a key in every cell: --set runs.count=10"),
    plot_metric: str = typer.Option(None, "--plot-metric", help="Metric column to plot (default: E_xyz_mean)."),
    plot_param: str = typer.Option(None, "--plot-param", help="Swept parameter on the x axis (default: the first)."),
    dry_run: bool = typer.Option(False, "--dry-run", help="Validate every cell and list them (with -q: print their "
                                 "number); run nothing."),
    cell: int = typer.Option(None, "--cell", min=0, help="Run only cell I (0-based, as --dry-run lists them) in this "
                             "process and write DIR/cells/ID.h5: one task of a job array (SLURM_ARRAY_TASK_ID)."),
    collect: bool = typer.Option(False, "--collect", help="Run nothing: the table and plot of whatever cells are "
                                 "complete in DIR (after a job array); exit 1 if some are missing or failed."),
    quiet: bool = typer.Option(False, "--quiet", "-q", help="No progress bar or log lines; print only the paths."),
) -> None:
    """Run one experiment per cell of a grid (each validated first), write DIR/cells/ID.h5, the table
    DIR/sweep.csv and DIR/sweep.md (one row per cell and observer) and a plot of a metric against a
    parameter; print the table's main columns, as many as the terminal's width holds. Exit code 1 when a
    cell failed or (--collect) is missing (the others still ran), 2 for a bad config or grid. On a
    cluster's batch scheduler: --cell I in each task of a job array, then --collect (docs: sweeps).

    Example: needle sweep configs/multirate-ukf-us3d/table1.yaml --grid configs/sweeps/multirate-ukf-us3d_q_kappa.yaml --workers 2
    """
    from needlecli.experiments.studies.sweep import (
        collect_sweep,
        default_plot_choice,
        load_grid,
        plan_sweep,
        plot_name,
        plot_sweep,
        run_one_cell,
        run_sweep,
    )
    from needlecli.reports.tables import to_terminal

    setup_logging(quiet)
    if executor not in ("local", "dask", "inline"):
        fail(f"--executor: unknown executor {executor!r}; use local, dask or inline")
    if scheduler and executor != "dask":
        fail("--scheduler needs --executor dask")
    if cell is not None and collect:
        fail("--cell runs one cell, --collect runs none: give one of them")
    from needlecli.io.atomic import check_output_dir

    g = load_grid(grid)
    out_dir = out if out is not None else Path("results") / "sweeps" / f"{config.stem}_{grid.stem}"
    check_output_dir(out_dir, what="the sweep")
    cells = plan_sweep(config, g, out_dir=out_dir, overrides=set_, grid_source=str(grid))
    check_output_dir(out_dir, what="the sweep's results", size=sum(c.file_bytes for c in cells if not Path(c.path).exists()))
    if dry_run:
        if quiet:  # the number of cells alone: what a job array's script needs (--array=0-$((N-1)))
            typer.echo(str(len(cells)))
            return
        typer.echo(f"{grid}: {len(cells)} valid cell(s) of {config} -> {out_dir}")
        for i, c in enumerate(cells):
            typer.echo(f"  {i:>4}  {c.id}  seed {c.seed} ({c.seed_from})  {c.label()}")
        return
    manifest = {"config": str(config), "grid": str(grid), "grid_spec": g.model_dump(mode="json"), "set": list(set_)}
    if cell is not None:
        _one_cell(cells, cell, out_dir, resume, manifest, run_one_cell)
        return
    if collect:
        log.info("sweep: the table of the complete cells of %d in %s", len(cells), out_dir)
    else:
        log.info("sweep: %d cell(s) on %s -> %s", len(cells), executor, out_dir)
    on_cell = None if quiet or sys.stderr.isatty() else _cell_line  # outside a terminal: a line per cell
    try:
        with progress_bar(not quiet and not collect) as bar:
            result = (collect_sweep(cells, out_dir=out_dir) if collect else
                      run_sweep(cells, out_dir=out_dir, executor=executor, workers=workers, scheduler=scheduler,
                                resume=resume, progress=bar, manifest=manifest, on_cell=on_cell))
        table = result.table
        metric, param = default_plot_choice(table, plot_metric, plot_param)
        plot = None
        if metric is not None and param is not None and (table["status"] == "ok").any():
            plot = plot_sweep(table, metric=metric, param=param, path=out_dir / plot_name(metric, param),
                              units=result.units, title=g.description or config.stem)
    except KeyboardInterrupt as e:  # SIGINT, SIGTERM: the message (needlecli.cli.common) says what is on disk
        sig = e if isinstance(e, Interrupted) else Interrupted(2)
        sig.hint = f"the complete cells are kept in {out_dir / 'cells'}; run again with --resume to finish the others"
        raise sig from None
    if plot is None and (plot_metric or plot_param):
        fail("nothing to plot: no cell succeeded" if not (table["status"] == "ok").any() else
             "nothing to plot: the sweep varies no parameter besides runs.seed")
    if not quiet:  # as much of the table as the terminal holds; all of it is in the files
        typer.echo(to_terminal(table, shutil.get_terminal_size((120, 24)).columns, terminal_columns(table),
                               more=f"in {out_dir / 'sweep.csv'}") + "\n")
        if collect:
            typer.echo(f"cells: {len(cells)} ({result.skipped} complete, {result.failed} failed, {result.missing} "
                       "missing: not run, or run by another config or needlecli)")
        else:
            typer.echo(f"cells: {len(cells)} ({result.ran} run, {result.skipped} skipped as complete, "
                       f"{result.failed} failed) in {result.seconds:.1f} s")
        for o in result.outcomes.values():
            if o.status == "failed":
                typer.echo(f"failed: {o.id}: {o.error} (see {out_dir / 'cells' / (o.id + '.error.txt')})")
    typer.echo(f"table: {out_dir / 'sweep.csv'}, {out_dir / 'sweep.md'}")
    if plot is not None:
        typer.echo(f"plot: {plot}")
    if result.failed or result.missing:
        raise typer.Exit(1)


def _cell_line(cell, out, done: int, total: int) -> None:
    """A finished cell, one line on stderr (outside a terminal, where no progress bar is drawn)."""
    said = f": {out.error}" if out.status == "failed" else ""
    typer.echo(f"cell {done}/{total} {out.status} in {out.seconds:.1f} s: {cell.id} ({cell.label()}){said}", err=True)


def _one_cell(cells, index: int, out_dir: Path, resume: bool, manifest: dict, run_one_cell) -> None:
    """``--cell I``: cell I in this process, one line saying what became of it; exit 1 if it failed."""
    out = run_one_cell(cells, index, out_dir=out_dir, resume=resume, manifest=manifest)
    c = cells[index]
    what = "complete from an earlier run" if out.status == "skipped" else f"{out.status} in {out.seconds:.1f} s"
    typer.echo(f"cell {index} of {len(cells)} {what}: {c.id} ({c.label()})" +
               (f": {out.error} (see {Path(c.path).with_suffix('.error.txt')})" if out.status == "failed" else ""))
    typer.echo(f"results: {c.path}")
    if out.status == "failed":
        raise typer.Exit(1)


def terminal_columns(table) -> list:
    """The sweep table's columns in their order of importance for a terminal: the cell, its parameters,
    status and observer, the first error's mean (E_xyz), the failed runs, the other errors' means, then
    the rest; errors and failures only where a cell has some."""
    params = list(table.attrs.get("params", []))
    means = [c for c in table.columns if c.endswith("_mean")]
    first = ["cell", *params, "status", "observer", *means[:1], "runs_failed", *means[1:]]
    notes = [c for c in ("error", "failures") if c in table.columns and table[c].astype(str).str.len().gt(0).any()]
    return [*first, *notes, *[c for c in table.columns if c not in first and c not in notes]]
