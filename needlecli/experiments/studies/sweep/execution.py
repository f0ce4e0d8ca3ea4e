"""Running a sweep's cells: one cell (its experiment, then its metrics), completeness and resume, the
executors, and the whole sweep with its table.

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
import json
import os
import time
import traceback
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

import pandas as pd
import yaml

from needlecli import platform
from needlecli.errors import NeedleError, SweepError
from needlecli.experiments.studies.sweep.plan import Cell, config_hash
from needlecli.io.atomic import install_worker_signals, worker_task, write_text_atomic
from needlecli.reports.sweep import cell_metrics, param_info, sweep_table, write_sweep_table

CONNECT_TIMEOUT = "10s"  # to reach a Dask scheduler
Progress = Callable[[str, int, int], None]


@dataclass
class CellOutcome:
    """What became of a cell: ``status`` ok | failed | skipped (complete results from an earlier run)."""

    id: str
    status: str
    rows: list[dict] = field(default_factory=list)  # one per observer: its metrics
    error: str = ""
    seconds: float = 0.0


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
    write_text_atomic(_sidecar(cell), json.dumps(doc, indent=1, default=str) + "\n")


def _record_failure(cell: Cell, out: CellOutcome, details: str) -> None:
    write_text_atomic(_error_file(cell), f"cell {cell.id} ({cell.label()})\n{details}\n")
    _write_sidecar(cell, out)


def run_cell(cell: Cell) -> CellOutcome:
    """Run one cell: its experiment (results file written atomically), then its metrics. Never raises: a
    failure is returned (and written to ``<id>.error.txt``); a signal (SIGINT, SIGTERM) is raised, the
    cell's temporary file removed."""
    t0 = time.perf_counter()
    path = Path(cell.path)
    with worker_task():
        return _run_cell(cell, path, t0)


def _run_cell(cell: Cell, path: Path, t0: float) -> CellOutcome:
    from needlecli.experiments.config.load import load_config
    from needlecli.experiments.simulation.runner import run_experiment

    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        for stale in (_error_file(cell), _sidecar(cell)):  # an earlier results file stays until the new one replaces it
            stale.unlink(missing_ok=True)
        with platform.thread_pools_limited(1):  # (local workers also start with platform.THREAD_ENV at 1)
            cfg, text = load_config(cell.config_source, text=cell.config_text)
            run_experiment(cfg, text, out=path, base_dir=cell.base_dir)
            rows = cell_metrics(path)
        out = CellOutcome(cell.id, "ok", rows=rows, seconds=time.perf_counter() - t0)
        _write_sidecar(cell, out)
        return out
    except Exception as e:  # noqa: BLE001 (a cell's failure is data: recorded, the sweep goes on)
        said = str(e) if isinstance(e, NeedleError) else f"{type(e).__name__}: {e}"  # (a user's error says what)
        out = CellOutcome(cell.id, "failed", error=said.splitlines()[0], seconds=time.perf_counter() - t0)
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
    process started, so before numpy is imported); threadpoolctl, if installed, makes sure. SIGINT and
    SIGTERM stop the cell being run cleanly (its temporary file removed)."""
    install_worker_signals()
    platform.pin_thread_pools()


#: the thread-pool variables at 1 while worker processes are started (they inherit them)
_thread_env = platform.one_thread_env


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
    except BaseException:  # interrupted: the running cells stop too (each removes its temporary file)
        _stop_workers(pool)
        raise
    finally:  # interrupted (or the consumer stopped): drop the cells not started, do not wait for them
        pool.shutdown(wait=False, cancel_futures=True)


def _stop_workers(pool, timeout: float = 10.0) -> None:
    """SIGTERM to every worker process of ``pool``, then wait for them (SIGKILL after ``timeout``)."""
    procs = list(getattr(pool, "_processes", {}).values())  # the executor has no public handle on them
    for p in procs:
        with contextlib.suppress(Exception):
            p.terminate()
    deadline = time.monotonic() + timeout
    for p in procs:
        with contextlib.suppress(Exception):
            p.join(max(0.0, deadline - time.monotonic()))
            if p.is_alive():
                p.kill()


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
                      "seed_from": c.seed_from, "config_hash": c.config_hash} for c in cells],
           "params": param_info(cells), **(manifest or {})}
    write_text_atomic(out_dir / "sweep.json", json.dumps(doc, indent=1, default=str) + "\n")
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

