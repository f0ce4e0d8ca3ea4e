"""Parameter sweeps: many experiments that differ by dotted config overrides, run in parallel.

A sweep is an experiment config plus a grid file (``GRID.yaml``). The grid makes *cells*, each a set of
overrides of the config (the keys of ``needle simulate --set``); every cell is one experiment with its
own results file ``DIR/cells/<cell-id>.h5``. One module per job:

* :mod:`.grid`: the grid file's schema (:class:`Grid`), its axes and the varying overrides it makes;
* :mod:`.plan`: the cells (:class:`Cell`): overrides, seed (the seed rule: common random numbers by
  default), config validated up front, hash, id and results path;
* :mod:`.describe`: what a swept key is (name, description, unit from the schema or the model);
* :mod:`.execution`: running cells (one cell, completeness and resume, recorded failures; the ``local``,
  ``dask`` and ``inline`` executors), the whole sweep (:func:`run_sweep`), and the cell-by-cell form of a
  job array: one cell by its index (:func:`run_one_cell`), the table of whatever cells are complete
  (:func:`collect_sweep`);
* the table and plot are reports, in :mod:`needlecli.reports.sweep` (they read results files only).
"""

from needlecli.errors import SweepError
from needlecli.experiments.studies.sweep.describe import describe_key
from needlecli.experiments.studies.sweep.execution import (
    CellOutcome,
    SweepResult,
    WorkerRefused,
    collect_sweep,
    execute,
    results_complete,
    run_cell,
    run_one_cell,
    run_sweep,
    share_of_cores,
)
from needlecli.experiments.studies.sweep.grid import (
    MAX_CELLS,
    Distribution,
    Grid,
    RandomSamples,
    expand_axis,
    grid_overrides,
    load_grid,
)
from needlecli.experiments.studies.sweep.plan import Cell, config_hash, derived_seed, plan_sweep, resume_key
from needlecli.reports.sweep import (
    SEED_KEY,
    cell_metrics,
    default_plot_choice,
    param_columns,
    plot_name,
    plot_sweep,
    seed_summary,
    sweep_table,
    write_sweep_table,
)

__all__ = [
    "MAX_CELLS", "SEED_KEY", "Cell", "CellOutcome", "Distribution", "Grid", "RandomSamples", "SweepError",
    "SweepResult", "WorkerRefused", "cell_metrics", "collect_sweep", "config_hash", "default_plot_choice",
    "derived_seed", "describe_key", "execute", "expand_axis", "grid_overrides", "load_grid", "param_columns",
    "plan_sweep", "plot_name", "plot_sweep", "results_complete", "resume_key", "run_cell", "run_one_cell",
    "run_sweep", "seed_summary", "share_of_cores", "sweep_table", "write_sweep_table",
]
