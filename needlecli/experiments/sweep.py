"""Parameter sweeps: many experiments that differ by dotted config overrides, run in parallel.

A sweep is an experiment config plus a grid file (``GRID.yaml``, schema :class:`Grid`). The grid makes
*cells*, each a set of overrides of the config (the keys of ``needle simulate --set``); every cell is one
experiment with its own results file ``DIR/cells/<cell-id>.h5``. The cells are

    (each entry of ``cells``, or one empty cell) x (each of ``random.count`` samples, or one empty
    sample) x (the cartesian product of the ``grid`` axes, the last axis varying fastest)

with ``fixed`` applied to every cell first. Every cell's config is validated before anything runs.

Seeds (``runs.seed`` of a cell):

* a cell whose overrides set ``runs.seed`` (an axis ``runs.seed: range(10)``, a cell entry or ``fixed``)
  keeps it as given;
* otherwise, with ``seeds: derived`` (the default), ``seed = int(sha256("<sweep seed>:<overrides>")[:8],
  16) mod 2**31``, where ``<overrides>`` is the cell's varying overrides (not ``fixed``) as JSON with sorted
  keys and the sweep seed is the grid's ``seed`` (default: the config's ``runs.seed``). Two cells with
  different overrides thus draw different noise, and the same cell gets the same seed in every sweep;
* with ``seeds: common`` every such cell uses the sweep seed itself (common random numbers: the cells see
  the same insertions and noise, so their differences come from the overrides alone).

A cell's results are complete when ``DIR/cells/<id>.h5`` exists, is a readable results file and the config
stored in it hashes to the cell's config hash (sha256 of the overridden config as JSON with sorted keys);
results files are written atomically, so ``resume`` loses at most the cells that were running. A cell
that raises is recorded in ``DIR/cells/<id>.error.txt`` (with its traceback) and as ``failed`` rows of
the table, and the sweep goes on. Each finished cell also leaves ``DIR/cells/<id>.json`` (its overrides,
seed, config hash, status, runtime and metrics).

Executors: ``local`` (a ``ProcessPoolExecutor`` of fresh ``spawn`` processes with the BLAS and OpenMP
thread pools pinned to one thread each), ``dask`` (an existing ``distributed`` cluster by scheduler
address, or a ``LocalCluster`` started for the sweep; ``pip install 'needlecli[dask]'``; the workers must
see ``DIR`` at the same path) and ``inline`` (in this process, one cell after another: for debugging).
"""

from __future__ import annotations

import contextlib
import copy
import hashlib
import itertools
import json
import math
import os
import re
import time
import traceback
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np
import pandas as pd
import yaml
from pydantic import Field, ValidationError, field_validator, model_validator

from needlecli.errors import ConfigError, NeedleError
from needlecli.schema import Strict

SEED_KEY = "runs.seed"
CONNECT_TIMEOUT = "10s"  # to reach a Dask scheduler
MAX_CELLS = 100_000
#: environment variables that size the thread pools of BLAS / OpenMP in a worker process
THREAD_ENV = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "VECLIB_MAXIMUM_THREADS",
              "NUMEXPR_NUM_THREADS", "BLIS_NUM_THREADS")
Progress = Callable[[str, int, int], None]


class SweepError(NeedleError):
    """A sweep that cannot start: a bad grid, a cell whose config is invalid, an executor not available."""


# ---------------------------------------------------------------------------------------------- grid file
_KEY = re.compile(r"^[A-Za-z_][A-Za-z0-9_\-]*(\.[A-Za-z0-9_\-]+)*$")
_RANGE = re.compile(r"^\s*range\(\s*(-?\d+)\s*(?:,\s*(-?\d+)\s*)?(?:,\s*(-?\d+)\s*)?\)\s*$")


def _check_keys(mapping: dict, what: str) -> dict:
    for k in mapping:
        if not isinstance(k, str) or not _KEY.match(k):
            raise ValueError(f"{what} key {k!r} is not a dotted config path like observers.0.q.kappa")
    return mapping


def expand_axis(v: Any) -> list:
    """The values of one grid axis: a non-empty list; ``"range(stop)"`` / ``"range(start, stop[, step])"``;
    ``{range: [start, stop, step]}``; ``{linspace: [a, b, n]}``; ``{geomspace: [a, b, n]}`` (a, b > 0)."""
    if isinstance(v, str):
        m = _RANGE.match(v)
        if not m:
            raise ValueError(f"{v!r}: a string axis must be range(stop) or range(start, stop[, step]); "
                             "give other values as a list")
        a, b, c = (int(g) if g is not None else None for g in m.groups())
        args = (a,) if b is None else (a, b) if c is None else (a, b, c)
        if c == 0:
            raise ValueError("range step must not be 0")
        v = list(range(*args))
    elif isinstance(v, dict):
        if len(v) != 1 or next(iter(v)) not in ("range", "linspace", "geomspace"):
            raise ValueError("a mapping axis is one of {range: [start, stop, step]}, {linspace: [a, b, n]}, "
                             "{geomspace: [a, b, n]}")
        kind, args = next(iter(v.items()))
        if not isinstance(args, list) or not all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in args):
            raise ValueError(f"{kind}: needs a list of numbers")
        if kind == "range":
            if not 1 <= len(args) <= 3 or not all(isinstance(x, int) for x in args) or (len(args) == 3 and args[2] == 0):
                raise ValueError("range: needs 1 to 3 integers [start, stop, step], step not 0")
            v = list(range(*args))
        else:
            if len(args) != 3 or not isinstance(args[2], int) or args[2] < 1:
                raise ValueError(f"{kind}: needs [a, b, n] with an integer n >= 1")
            if kind == "geomspace" and (args[0] <= 0 or args[1] <= 0):
                raise ValueError("geomspace: a and b must be > 0")
            fn = np.linspace if kind == "linspace" else np.geomspace
            v = [float(x) for x in fn(args[0], args[1], args[2])]
    elif not isinstance(v, list):
        raise ValueError(f"an axis is a list of values, range(...), or a mapping (linspace, geomspace, range), "
                         f"not {type(v).__name__}")
    if not v:
        raise ValueError("an axis needs at least one value")
    return v


class Distribution(Strict):
    """One randomly sampled parameter: exactly one of the keys."""

    uniform: tuple[float, float] | None = Field(None, description="[lo, hi)")
    loguniform: tuple[float, float] | None = Field(None, description="[lo, hi), both > 0, uniform in log")
    normal: tuple[float, float] | None = Field(None, description="[mean, std]")
    integers: tuple[int, int] | None = Field(None, description="[lo, hi), integers")
    choice: list[Any] | None = Field(None, min_length=1, description="one of these values, equally likely")

    @model_validator(mode="after")
    def _one(self):
        given = [k for k in type(self).model_fields if getattr(self, k) is not None]
        if len(given) != 1:
            raise ValueError("give exactly one of uniform, loguniform, normal, integers, choice")
        k = given[0]
        v = getattr(self, k)
        if k in ("uniform", "loguniform", "integers") and not v[0] < v[1]:
            raise ValueError(f"{k}: needs lo < hi")
        if k == "loguniform" and v[0] <= 0:
            raise ValueError("loguniform: lo must be > 0")
        if k == "normal" and v[1] < 0:
            raise ValueError("normal: std must be >= 0")
        return self

    def sample(self, rng: np.random.Generator) -> Any:
        if self.uniform is not None:
            return float(rng.uniform(*self.uniform))
        if self.loguniform is not None:
            lo, hi = np.log(self.loguniform)
            return float(np.exp(rng.uniform(lo, hi)))
        if self.normal is not None:
            return float(rng.normal(*self.normal))
        if self.integers is not None:
            return int(rng.integers(*self.integers))
        return copy.deepcopy(self.choice[int(rng.integers(len(self.choice)))])


class RandomSamples(Strict):
    """``count`` random cells, each parameter drawn independently (numpy's PCG64 seeded by ``seed``,
    default: the sweep seed)."""

    count: int = Field(ge=1, le=MAX_CELLS)
    seed: int | None = Field(None, ge=0, description="seed of the samples (default: the sweep seed)")
    params: dict[str, Distribution] = Field(min_length=1)

    @field_validator("params")
    @classmethod
    def _keys(cls, v):
        return _check_keys(v, "random.params")


class Grid(Strict):
    """A sweep's grid file (``GRID.yaml``). Keys are dotted config paths as in ``--set`` (list entries by
    number: ``observers.0.q.kappa``); values are YAML values. At least one of ``grid``, ``cells``,
    ``random``; the cells are the product of the three parts (see the module docstring).

    Example::

        description: curvature process noise of the seed 003 filter
        fixed: {runs.count: 10}
        grid:
          observers.0.q.kappa: [5.0e-7, 1.0e-6, 2.0e-6, 4.0e-6, 8.0e-6]
          runs.seed: range(10)
    """

    description: str = ""
    seed: int | None = Field(None, ge=0, description="sweep seed (default: the config's runs.seed)")
    seeds: Literal["derived", "common"] = Field(
        "derived", description="seed of cells that do not set runs.seed: derived per cell, or the sweep seed")
    fixed: dict[str, Any] = Field(default_factory=dict, description="overrides applied to every cell")
    grid: dict[str, Any] = Field(default_factory=dict, description="axes: key -> values (cartesian product)")
    cells: list[dict[str, Any]] = Field(default_factory=list, description="explicit cells: key -> value each")
    random: RandomSamples | None = None

    @field_validator("fixed")
    @classmethod
    def _fixed(cls, v):
        return _check_keys(v, "fixed")

    @field_validator("grid")
    @classmethod
    def _grid(cls, v):
        _check_keys(v, "grid")
        out = {}
        for k, values in v.items():
            try:
                out[k] = expand_axis(values)
            except ValueError as e:
                raise ValueError(f"axis {k}: {e}") from None
        return out

    @field_validator("cells")
    @classmethod
    def _cells(cls, v):
        for i, c in enumerate(v):
            try:
                _check_keys(c, f"cell {i}:")
            except ValueError as e:
                raise ValueError(str(e)) from None
        return v

    @model_validator(mode="after")
    def _parts(self):
        if not self.grid and not self.cells and self.random is None:
            raise ValueError("give at least one of grid, cells, random")
        parts = {"fixed": set(self.fixed), "grid": set(self.grid),
                 "random": set(self.random.params) if self.random else set()}
        parts["cells"] = set().union(*(set(c) for c in self.cells)) if self.cells else set()
        names = list(parts)
        for i, a in enumerate(names):
            for b in names[i + 1 :]:
                both = sorted(parts[a] & parts[b])
                if both:
                    raise ValueError(f"key {both[0]} is set in both {a} and {b}")
        n = (len(self.cells) or 1) * (self.random.count if self.random else 1) * math.prod(len(x) for x in self.grid.values())
        if n > MAX_CELLS:
            raise ValueError(f"the grid makes {n} cells; at most {MAX_CELLS}")
        return self


def load_grid(path: str | Path) -> Grid:
    """Read and validate a grid file. Raises :class:`ConfigError` naming the file and key."""
    from needlecli.io.yamlfile import parse_yaml

    source = str(path)
    try:
        text = Path(path).read_text(encoding="utf-8")
    except FileNotFoundError:
        raise ConfigError(source, (), "no such file") from None
    except (OSError, UnicodeDecodeError) as e:
        raise ConfigError(source, (), f"cannot read the file: {e}") from None
    data = parse_yaml(text, source)
    try:
        return Grid.model_validate(data)
    except ValidationError as e:
        err = e.errors()[0]
        loc = tuple(p for p in err["loc"] if not (isinstance(p, str) and ("[" in p or p.startswith("function-"))))
        msg = err.get("msg", "invalid value")
        msg = msg[len("Value error, "):] if msg.startswith("Value error, ") else msg
        if err.get("type") == "extra_forbidden":
            msg = "unknown key"
        elif err.get("type") == "missing":
            msg = "required key is missing"
        raise ConfigError(source, loc, " ".join(msg.split())) from None


# ---------------------------------------------------------------------------------------------- cells
def _canonical(obj: Any) -> str:
    return json.dumps(obj, sort_keys=True, default=str, separators=(",", ":"))


def config_hash(data: dict) -> str:
    """sha256 of a config's data (after overrides) as JSON with sorted keys."""
    return hashlib.sha256(_canonical(data).encode()).hexdigest()


def derived_seed(sweep_seed: int, overrides: dict) -> int:
    """The seed of a cell that does not set runs.seed: ``int(sha256("<sweep seed>:<overrides JSON>")[:8],
    16) mod 2**31``."""
    h = hashlib.sha256(f"{sweep_seed}:{_canonical(overrides)}".encode()).hexdigest()
    return int(h[:8], 16) % (2**31)


@dataclass(frozen=True)
class Cell:
    """One experiment of a sweep (picklable: it is what a worker receives).

    ``overrides`` are the varying overrides (grid axes, cell entry, random sample) plus ``runs.seed``;
    ``fixed`` the overrides every cell shares; ``config_text`` the complete config with both applied.
    """

    index: int
    id: str
    overrides: dict
    fixed: dict
    seed: int
    seed_from: str  # "grid" (set by the cell), "derived" or "common"
    config_source: str  # the base config file (for messages and relative paths)
    config_text: str
    config_hash: str
    observers: tuple[str, ...]
    n_runs: int
    path: str  # DIR/cells/<id>.h5 (absolute)
    base_dir: str

    def label(self) -> str:
        return ", ".join(f"{k} = {_short(v)}" for k, v in self.overrides.items()) or "(no overrides)"


def _short(v: Any) -> str:
    if isinstance(v, float):
        return f"{v:g}"
    if isinstance(v, (dict, list)):
        return _canonical(v)
    return str(v)


def _n_runs(cfg) -> int:
    """Runs of a cell's experiment as far as the config tells (replayed logs: the trials named, else 0)."""
    if cfg.source is None:
        return int(cfg.runs.count)
    return len(cfg.source.trials or [])


def grid_overrides(grid: Grid) -> list[dict]:
    """The varying overrides of every cell, in sweep order."""
    entries = [dict(c) for c in grid.cells] or [{}]
    samples: list[dict] = [{}]
    if grid.random is not None:
        rng = np.random.default_rng(grid.random.seed if grid.random.seed is not None else (grid.seed or 0))
        samples = [{k: d.sample(rng) for k, d in grid.random.params.items()} for _ in range(grid.random.count)]
    axes = list(grid.grid)
    product = [dict(zip(axes, combo)) for combo in itertools.product(*(grid.grid[k] for k in axes))]
    return [{**e, **s, **p} for e in entries for s in samples for p in product]


def plan_sweep(
    config: str | Path,
    grid: Grid,
    *,
    out_dir: str | Path,
    overrides: list[str] | None = None,
    grid_source: str = "grid",
) -> list[Cell]:
    """Make every cell of a sweep and validate its config (all before anything runs).

    ``overrides`` (``key=value`` strings, as ``--set``) join ``grid.fixed``. Raises :class:`SweepError`
    naming the cell, its overrides and the config key at fault.
    """
    from needlecli.experiments.config import load_config
    from needlecli.experiments.overrides import set_dotted
    from needlecli.io.yamlfile import parse_yaml

    config = Path(config)
    source = str(config)
    try:
        text = config.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise ConfigError(source, (), "no such file") from None
    except (OSError, UnicodeDecodeError) as e:
        raise ConfigError(source, (), f"cannot read the file: {e}") from None
    base = parse_yaml(text, source)
    fixed = dict(grid.fixed)
    for ov in overrides or []:
        if "=" not in ov:
            raise ConfigError(source, (), f"override {ov!r} is not of the form key.path=value")
        k, v = ov.split("=", 1)
        fixed[k.strip()] = yaml.safe_load(v)
    cells_dir = Path(out_dir).resolve() / "cells"
    base_seed = (base.get("runs") or {}).get("seed", 0) if isinstance(base.get("runs"), dict) else 0
    sweep_seed = grid.seed if grid.seed is not None else int(base_seed or 0)
    cells: list[Cell] = []
    seen: dict[str, int] = {}
    all_ov = grid_overrides(grid)
    for i, varying in enumerate(all_ov):
        ov = dict(varying)
        if SEED_KEY in ov or SEED_KEY in fixed:
            seed_from = "grid"
            seed = ov.get(SEED_KEY, fixed.get(SEED_KEY))
        elif grid.seeds == "common":
            seed_from, seed = "common", sweep_seed
            ov[SEED_KEY] = seed
        else:
            seed_from, seed = "derived", derived_seed(sweep_seed, varying)
            ov[SEED_KEY] = seed
        where = f"{grid_source}: cell {i} of {len(all_ov)} ({', '.join(f'{k} = {_short(v)}' for k, v in varying.items()) or 'no overrides'})"
        data = copy.deepcopy(base)
        try:
            for k, v in {**fixed, **ov}.items():
                set_dotted(data, k, copy.deepcopy(v), source)
            cell_text = yaml.safe_dump(data, sort_keys=False)
            cfg, cell_text = load_config(config, text=cell_text)
        except ConfigError as e:
            raise SweepError(f"{where}: {e}") from None
        except NeedleError as e:  # a replay config whose logs are bad
            raise SweepError(f"{where}: {e}") from None
        h = config_hash(yaml.safe_load(cell_text))
        cid = hashlib.sha256(_canonical(ov).encode()).hexdigest()[:10]
        if cid in seen:
            raise SweepError(f"{where}: the same overrides as cell {seen[cid]}; each cell must differ")
        seen[cid] = i
        cells.append(Cell(
            index=i, id=cid, overrides=ov, fixed=fixed, seed=int(cfg.runs.seed), seed_from=seed_from,
            config_source=str(config.resolve()), config_text=cell_text, config_hash=h,
            observers=tuple(o.name or o.type for o in cfg.observers), n_runs=_n_runs(cfg),
            path=str(cells_dir / f"{cid}.h5"), base_dir=str(config.resolve().parent),
        ))
    return cells


# ---------------------------------------------------------------------------------------------- one cell
@dataclass
class CellOutcome:
    """What became of a cell: ``status`` ok | failed | skipped (complete results from an earlier run)."""

    id: str
    status: str
    rows: list[dict] = field(default_factory=list)  # one per observer: its metrics
    error: str = ""
    seconds: float = 0.0


@contextlib.contextmanager
def _one_thread() -> Iterator[None]:
    """Pin the BLAS/OpenMP thread pools to one thread while a cell runs (threadpoolctl if installed; the
    local executor's workers are also started with the environment variables set)."""
    try:
        from threadpoolctl import threadpool_limits
    except ImportError:
        yield
        return
    with threadpool_limits(limits=1):
        yield


def _write_text_atomic(path: Path, text: str) -> None:
    from needlecli.reports.tables import _atomic_text

    _atomic_text(path, text)


def _read_for_errors(path: str | Path):
    """The parts of a results file :func:`compute_errors` needs (no measurements, no covariances)."""
    import h5py

    from needlecli.io.results import Group, _decode

    def grp(g, names=None) -> Group:
        out = Group(attrs={k: _decode(v) for k, v in g.attrs.items()})
        for k, v in g.items():
            if names is not None and k not in names:
                continue
            if isinstance(v, h5py.Group):
                out.data[k] = grp(v)
            else:
                arr = v[()]
                out.data[k] = _decode(arr) if v.dtype.kind in "OS" else arr
        return out

    with h5py.File(path, "r") as f:
        res = Group(attrs={k: _decode(v) for k, v in f.attrs.items()})
        res.data["truth"] = grp(f["truth"], {"state", "status", "params"})
        est = Group()
        for name, g in f.get("estimates", {}).items():
            est.data[name] = grp(g, {"state", "status"})
        res.data["estimates"] = est
    return res


def cell_metrics(path: str | Path) -> list[dict]:
    """One record per observer of a results file: runs, runs kept and failed, and mean / std / max of each
    error quantity over the kept runs and every time step (the summary table's statistics)."""
    from needlecli.metrics import compute_errors
    from needlecli.reports.tables import order_quantities

    res = _read_for_errors(path)
    rows = []
    for obs, es in compute_errors(res).items():
        kept = es.n_runs - sum(es.excluded.values())
        row: dict[str, Any] = {"observer": obs, "runs": es.n_runs, "runs_kept": kept, "runs_failed": es.n_runs - kept,
                               "failures": "; ".join(f"{k}: {v}" for k, v in es.excluded.items())}
        units = {}
        for q in order_quantities(es.quantities):
            qe = es.quantities[q]
            v = qe.values[np.isfinite(qe.values)]
            row[f"{q}_mean"] = float(np.mean(v)) if v.size else float("nan")
            row[f"{q}_std"] = float(np.std(v)) if v.size else float("nan")
            row[f"{q}_max"] = float(np.max(v)) if v.size else float("nan")
            units[q] = qe.unit
        row["_units"] = units
        rows.append(row)
    return rows


def results_complete(cell: Cell) -> bool:
    """Whether the cell's results file exists, is readable and holds the cell's config."""
    import h5py

    p = Path(cell.path)
    if not p.is_file():
        return False
    try:
        with h5py.File(p, "r") as f:
            if "format" not in f.attrs or "truth" not in f or "time" not in f:
                return False
            text = f.attrs.get("config", "")
            text = text.decode() if isinstance(text, bytes) else str(text)
        return config_hash(yaml.safe_load(text)) == cell.config_hash
    except Exception:  # a truncated or foreign file: not complete
        return False


def _sidecar(cell: Cell) -> Path:
    return Path(cell.path).with_suffix(".json")


def _error_file(cell: Cell) -> Path:
    return Path(cell.path).with_suffix(".error.txt")


def _write_sidecar(cell: Cell, out: CellOutcome) -> None:
    doc = {"id": cell.id, "index": cell.index, "overrides": cell.overrides, "fixed": cell.fixed, "seed": cell.seed,
           "seed_from": cell.seed_from, "config_hash": cell.config_hash, "status": out.status,
           "seconds": out.seconds, "error": out.error, "rows": out.rows}
    _write_text_atomic(_sidecar(cell), json.dumps(doc, indent=1, default=str) + "\n")


def _record_failure(cell: Cell, out: CellOutcome, details: str) -> None:
    _write_text_atomic(_error_file(cell), f"cell {cell.id} ({cell.label()})\n{details}\n")
    _write_sidecar(cell, out)


def run_cell(cell: Cell) -> CellOutcome:
    """Run one cell: its experiment (results file written atomically), then its metrics. Never raises: a
    failure is returned (and written to ``<id>.error.txt``)."""
    from needlecli.experiments.config import load_config
    from needlecli.experiments.runner import run_experiment

    t0 = time.perf_counter()
    path = Path(cell.path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        for stale in (path, _error_file(cell), _sidecar(cell)):
            stale.unlink(missing_ok=True)
        with _one_thread():
            cfg, text = load_config(cell.config_source, text=cell.config_text)
            run_experiment(cfg, text, out=path, base_dir=cell.base_dir)
            rows = cell_metrics(path)
        out = CellOutcome(cell.id, "ok", rows=rows, seconds=time.perf_counter() - t0)
        _write_sidecar(cell, out)
        return out
    except Exception as e:  # noqa: BLE001 (a cell's failure is data: recorded, the sweep goes on)
        out = CellOutcome(cell.id, "failed", error=f"{type(e).__name__}: {e}".splitlines()[0],
                          seconds=time.perf_counter() - t0)
        try:
            _record_failure(cell, out, traceback.format_exc())
        except Exception:  # noqa: BLE001 (the folder went away: the outcome still says why)
            pass
        return out


def _resumed(cell: Cell) -> CellOutcome | None:
    """The outcome of a cell whose complete results exist (metrics from its sidecar, else recomputed)."""
    if not results_complete(cell):
        return None
    try:
        doc = json.loads(_sidecar(cell).read_text())
        if doc.get("config_hash") == cell.config_hash and doc.get("status") == "ok":
            return CellOutcome(cell.id, "skipped", rows=doc["rows"], seconds=float(doc.get("seconds", 0.0)))
    except (OSError, ValueError, KeyError):
        pass
    try:
        out = CellOutcome(cell.id, "skipped", rows=cell_metrics(cell.path))
    except Exception:  # noqa: BLE001 (unreadable after all: run it again)
        return None
    _write_sidecar(cell, CellOutcome(cell.id, "ok", rows=out.rows))
    return out


# ---------------------------------------------------------------------------------------------- executors
def _pin_worker_threads() -> None:
    """Initializer of local worker processes: the environment already pins BLAS / OpenMP (set before the
    process started, so before numpy is imported); threadpoolctl, if installed, makes sure."""
    for k in THREAD_ENV:
        os.environ[k] = "1"
    try:
        from threadpoolctl import threadpool_limits

        threadpool_limits(limits=1)
    except ImportError:
        pass


@contextlib.contextmanager
def _thread_env() -> Iterator[None]:
    """Set the thread-pool variables to 1 while worker processes are started (they inherit them)."""
    old = {k: os.environ.get(k) for k in THREAD_ENV}
    os.environ.update({k: "1" for k in THREAD_ENV})
    try:
        yield
    finally:
        for k, v in old.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


def _failed(cell: Cell, e: BaseException) -> CellOutcome:
    out = CellOutcome(cell.id, "failed", error=f"{type(e).__name__}: {e}".splitlines()[0] or type(e).__name__)
    try:
        _record_failure(cell, out, "".join(traceback.format_exception(e)))
    except Exception:  # noqa: BLE001
        pass
    return out


def _run_local(cells: list[Cell], workers: int) -> Iterator[CellOutcome]:
    import multiprocessing as mp
    from concurrent.futures import ProcessPoolExecutor, as_completed

    pool = ProcessPoolExecutor(max_workers=workers, mp_context=mp.get_context("spawn"), initializer=_pin_worker_threads)
    try:
        with _thread_env():  # the workers start at the first submits and inherit the pinned environment
            futures = {pool.submit(run_cell, c): c for c in cells}
        for fut in as_completed(futures):
            try:
                yield fut.result()
            except Exception as e:  # noqa: BLE001 (a worker process died: BrokenProcessPool)
                yield _failed(futures[fut], e)
        pool.shutdown(wait=True)
    finally:  # interrupted (or the consumer stopped): drop the cells not started, do not wait for them
        pool.shutdown(wait=False, cancel_futures=True)


def _dask_client(scheduler: str | None, workers: int):
    try:
        from distributed import Client, LocalCluster
    except ImportError:
        raise SweepError("the dask executor needs the distributed package: pip install 'needlecli[dask]' "
                         "(or pip install 'dask[distributed]')") from None
    if scheduler:
        try:
            return Client(scheduler, timeout=CONNECT_TIMEOUT), None
        except (OSError, TimeoutError) as e:
            raise SweepError(f"cannot reach the Dask scheduler at {scheduler}: {e}") from None
    import logging

    for name in ("distributed", "distributed.scheduler", "distributed.worker", "distributed.nanny", "distributed.core"):
        logging.getLogger(name).setLevel(logging.WARNING)  # the cluster's start-up chatter is not the user's news
    with _thread_env():
        cluster = LocalCluster(n_workers=workers, threads_per_worker=1, processes=True, dashboard_address=":0")
    return Client(cluster), cluster


def _run_dask(cells: list[Cell], scheduler: str | None, workers: int) -> Iterator[CellOutcome]:
    client, cluster = _dask_client(scheduler, workers)
    from distributed import as_completed
    try:
        stamp = time.time_ns()
        futures = [client.submit(run_cell, c, key=f"needle-cell-{c.id}-{stamp}", pure=False) for c in cells]
        by_key = {f.key: c for f, c in zip(futures, cells)}
        for fut in as_completed(futures):
            try:
                yield fut.result()
            except Exception as e:  # noqa: BLE001 (a worker died or the task could not be sent)
                yield _failed(by_key[fut.key], e)
            fut.release()
    finally:
        client.close()
        if cluster is not None:
            cluster.close()


def execute(cells: list[Cell], *, executor: str = "local", workers: int | None = None,
            scheduler: str | None = None) -> Iterator[CellOutcome]:
    """Run cells on an executor, yielding each outcome as it finishes (in no particular order)."""
    if not cells:
        return iter(())
    workers = max(1, workers or os.cpu_count() or 1)
    if executor == "inline":
        return (run_cell(c) for c in cells)
    if executor == "local":
        return _run_local(cells, min(workers, len(cells)))
    if executor == "dask":
        return _run_dask(cells, scheduler, workers)
    raise SweepError(f"unknown executor {executor!r}; use local, dask or inline")


# ---------------------------------------------------------------------------------------------- the sweep
@dataclass
class SweepResult:
    cells: list[Cell]
    outcomes: dict[str, CellOutcome]
    table: pd.DataFrame
    out_dir: Path
    ran: int
    skipped: int
    failed: int
    seconds: float
    units: dict[str, str] = field(default_factory=dict)


def run_sweep(
    cells: list[Cell],
    *,
    out_dir: str | Path,
    executor: str = "local",
    workers: int | None = None,
    scheduler: str | None = None,
    resume: bool = False,
    progress: Progress | None = None,
    manifest: dict | None = None,
) -> SweepResult:
    """Run the cells (skipping complete ones when ``resume``), write ``DIR/sweep.csv`` and ``DIR/sweep.md``.

    ``executor`` is ``local``, ``dask`` or ``inline``; ``workers`` the number of local processes (or of
    the ``LocalCluster`` started when ``dask`` has no ``scheduler`` address); default the CPU count.
    """
    t0 = time.perf_counter()
    out_dir = Path(out_dir)
    (out_dir / "cells").mkdir(parents=True, exist_ok=True)
    doc = {"cells": [{"index": c.index, "id": c.id, "overrides": c.overrides, "seed": c.seed,
                      "seed_from": c.seed_from, "config_hash": c.config_hash} for c in cells], **(manifest or {})}
    _write_text_atomic(out_dir / "sweep.json", json.dumps(doc, indent=1, default=str) + "\n")
    outcomes: dict[str, CellOutcome] = {}
    todo = []
    for c in cells:
        done = _resumed(c) if resume else None
        if done is not None:
            outcomes[c.id] = done
        else:
            todo.append(c)
    skipped = len(outcomes)
    if progress:
        progress("cells", skipped, len(cells))
    for out in execute(todo, executor=executor, workers=workers, scheduler=scheduler):
        outcomes[out.id] = out
        if progress:
            progress("cells", len(outcomes), len(cells))
    table, units = sweep_table(cells, outcomes)
    write_sweep_table(table, out_dir, units)
    return SweepResult(cells=cells, outcomes=outcomes, table=table, out_dir=out_dir, ran=len(todo),
                       skipped=skipped, failed=sum(o.status == "failed" for o in outcomes.values()),
                       seconds=time.perf_counter() - t0, units=units)


def param_columns(cells: list[Cell]) -> list[str]:
    """The override keys of a sweep, in first-seen order (``runs.seed`` last)."""
    keys = list(dict.fromkeys(k for c in cells for k in c.overrides))
    return [k for k in keys if k != SEED_KEY] + [SEED_KEY]


def _cell_value(v: Any) -> Any:
    return v if isinstance(v, (int, float, str, bool)) or v is None else _canonical(v)


def sweep_table(cells: list[Cell], outcomes: dict[str, CellOutcome]) -> tuple[pd.DataFrame, dict[str, str]]:
    """One row per cell and observer: the cell's override values, status, runs, and the metrics."""
    params = param_columns(cells)
    rows, units = [], {}
    for c in sorted(cells, key=lambda c: c.index):
        out = outcomes.get(c.id, CellOutcome(c.id, "not run"))
        base = {"cell": c.id, **{k: _cell_value(c.overrides.get(k)) for k in params}}
        status = "ok" if out.status in ("ok", "skipped") else out.status
        if out.rows:
            for r in out.rows:
                units.update(r.get("_units", {}))
                rows.append({**base, "status": status, **{k: v for k, v in r.items() if k != "_units"},
                             "seconds": out.seconds, "error": ""})
        else:
            for obs in c.observers or ("",):
                rows.append({**base, "status": status, "observer": obs, "runs": c.n_runs, "runs_kept": 0,
                             "runs_failed": c.n_runs, "seconds": out.seconds, "error": out.error})
    df = pd.DataFrame(rows)
    lead = ["cell", *params, "status", "observer", "runs", "runs_kept", "runs_failed"]
    metrics = [k for k in df.columns if k.endswith(("_mean", "_std", "_max")) and k not in lead]
    tail = ["failures", "seconds", "error"]
    for col in lead + tail:
        if col not in df.columns:
            df[col] = np.nan if col not in ("failures", "error") else ""
    df = df[[*lead, *metrics, *tail]]
    df["failures"] = df["failures"].fillna("")
    df.attrs["params"] = params
    return df, units


def seed_summary(df: pd.DataFrame) -> pd.DataFrame | None:
    """Over the seeds: one row per observer and combination of the other parameters, with the mean and the
    std across seeds (cells) of each ``*_mean`` metric and the runs that failed. None when the sweep has a
    single seed per combination."""
    params = [k for k in df.attrs.get("params", []) if k != SEED_KEY]
    ok = df[df["status"] == "ok"]
    if ok.empty or SEED_KEY not in ok or ok.groupby(["observer", *params], dropna=False)[SEED_KEY].nunique().max() < 2:
        return None
    metrics = [c for c in ok.columns if c.endswith("_mean")]
    rows = []
    for key, g in ok.groupby([*params, "observer"], dropna=False, sort=True):
        key = key if isinstance(key, tuple) else (key,)
        row = dict(zip([*params, "observer"], key))
        row["cells"] = len(g)
        row["runs"] = int(g["runs"].sum())
        row["runs_failed"] = int(g["runs_failed"].sum())
        for m in metrics:
            row[m] = float(g[m].mean())
            row[m[: -len("_mean")] + "_mean_std"] = float(g[m].std(ddof=1)) if len(g) > 1 else float("nan")
        rows.append(row)
    failed = {}
    for _, r in df[df["status"] != "ok"].iterrows():
        k = tuple(r[c] for c in [*params, "observer"])
        failed[k] = failed.get(k, 0) + 1
    out = pd.DataFrame(rows)
    out.insert(len(params) + 2, "cells_failed", [failed.get(tuple(r[c] for c in [*params, "observer"]), 0)
                                                 for _, r in out.iterrows()])
    return out


def write_sweep_table(df: pd.DataFrame, out_dir: Path, units: dict[str, str]) -> list[Path]:
    """``DIR/sweep.{csv,md}``, and ``DIR/sweep_over_seeds.{csv,md}`` when runs.seed is a sweep axis."""
    from needlecli.reports.tables import write_table

    unit_text = ", ".join(f"{q} in {u}" for q, u in units.items())
    units_note = f" ({unit_text})" if unit_text else ""
    caption = ("Sweep: one row per cell and observer; mean / std / max of each error over the kept runs and all "
               "time steps" + units_note + ".")
    paths = write_table(df, out_dir / "sweep", ["csv", "md"], caption=caption)
    summary = seed_summary(df)
    if summary is not None:
        paths += write_table(summary, out_dir / "sweep_over_seeds", ["csv", "md"], caption=(
            "Sweep over seeds: per observer and parameter values, the mean over the cells (seeds) of each "
            "error's mean, and its std across seeds (`*_mean_std`)" + units_note + "."))
    return paths


# ---------------------------------------------------------------------------------------------- plot
def default_plot_choice(df: pd.DataFrame, metric: str | None, param: str | None) -> tuple[str | None, str | None]:
    """The metric (default ``E_xyz_mean``, else the first) and the parameter (default the first varying
    numeric one that is not ``runs.seed``) to plot."""
    metrics = [c for c in df.columns if c.endswith(("_mean", "_std", "_max"))]
    if metric is None:
        metric = "E_xyz_mean" if "E_xyz_mean" in metrics else (metrics[0] if metrics else None)
    if param is None:
        for k in df.attrs.get("params", []):
            if k == SEED_KEY:
                continue
            vals = df[k].dropna().unique()
            if len(vals) > 1:
                param = k
                break
    return metric, param


def plot_sweep(df: pd.DataFrame, *, metric: str, param: str, path: str | Path, units: dict[str, str] | None = None,
               title: str = "") -> Path:
    """``metric`` against ``param``, one line per observer and combination of the other parameters; the
    mean over seeds with their std as error bars when several cells differ only in ``runs.seed``."""
    from needlecli.reports.plots import plt, save_figure

    if metric not in df.columns:
        known = [c for c in df.columns if c.endswith(("_mean", "_std", "_max"))]
        raise SweepError(f"--plot-metric: no metric {metric!r}; the table has {', '.join(known) or 'none'}")
    params = df.attrs.get("params", [])
    if param not in params:
        raise SweepError(f"--plot-param: {param!r} is not a swept parameter; parameters: {', '.join(params)}")
    ok = df[df["status"] == "ok"]
    others = [k for k in params if k not in (param, SEED_KEY)]
    groups = ["observer", *others]
    fig, ax = plt.subplots(figsize=(7, 4.2))
    xs_all = pd.to_numeric(ok[param], errors="coerce")
    numeric = bool(len(ok)) and xs_all.notna().all()
    cats = list(dict.fromkeys(ok[param])) if not numeric else None
    seeds_axis = False
    for key, g in ok.groupby(groups, dropna=False, sort=True):
        key = key if isinstance(key, tuple) else (key,)
        agg = g.groupby(param, sort=True)[metric].agg(["mean", "std", "count"])
        seeds_axis |= bool((agg["count"] > 1).any())
        x = agg.index.to_numpy()
        if not numeric:
            x = np.array([cats.index(v) for v in x])
        label = ", ".join([str(key[0])] + [f"{k} = {_short(v)}" for k, v in zip(others, key[1:])])
        ax.errorbar(x, agg["mean"], yerr=agg["std"].fillna(0.0) if (agg["count"] > 1).any() else None,
                    marker="o", capsize=3, label=label)
    if numeric and len(xs_all) and (xs_all > 0).all() and xs_all.max() / xs_all.min() >= 20:
        ax.set_xscale("log")
    if cats is not None:
        ax.set_xticks(range(len(cats)), [str(c) for c in cats])
    q = metric.rsplit("_", 1)[0]
    unit = (units or {}).get(q, "")
    ax.set_xlabel(param)
    ax.set_ylabel(f"{metric}" + (f" [{unit}]" if unit else ""))
    ax.grid(alpha=0.3)
    if len(ax.get_legend_handles_labels()[0]):
        ax.legend(fontsize="small")
    note = "mean and std over seeds" if seeds_axis else "one cell per point"
    ax.set_title((title + ": " if title else "") + f"{metric} against {param} ({note})", fontsize="medium")
    return save_figure(fig, Path(path))


def plot_name(metric: str, param: str) -> str:
    return "sweep_" + re.sub(r"[^A-Za-z0-9_.-]+", "_", f"{metric}_vs_{param}") + ".png"
