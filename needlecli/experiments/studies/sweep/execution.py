"""Running a sweep's cells: one cell (its experiment, then its metrics), completeness and resume, the
executors, the whole sweep with its table, and the cell-by-cell form for job arrays.

A cell's results are complete when ``DIR/cells/<id>.h5`` exists, is a readable results file holding the
cell's config, and its record ``DIR/cells/<id>.json`` (written after it: its overrides, seed, resume key,
status, runtime, metrics, the needlecli that planned and ran it) says ``ok`` under the cell's resume key
(:func:`needlecli.experiments.studies.sweep.plan.resume_key`: the resolved config, defaults included, and
the needlecli version and git commit): results computed before a default changed, or by another needlecli,
are run again. Results files are written atomically, so ``resume`` loses at most the cells that were
running. A cell that raises is recorded in ``DIR/cells/<id>.error.txt`` (with its traceback) and as
``failed`` rows of the table, and the sweep goes on; a complete cell has no ``.error.txt`` beside it.

Every cell takes the compiled path (or the numpy one) whatever the state of the kernel cache
(:func:`needlecli.kernels.compile_now`): its numbers never depend on which cell ran first. Processes that
share a kernel cache (the workers of one machine, or of every node when the cache's folder is on shared
storage) compile each kernel once (:mod:`needlecli.kernels._patch_cache_lock`); each cell's kernels run on
its worker's share of the cores (:func:`needlecli.platform.usable_cores` over the cells that run at once).

Executors: ``local`` (processes of this machine started by ``spawn``, BLAS and OpenMP pinned to one thread
each; a worker process that dies fails only its own cell, which runs once more on a fresh worker), ``dask``
(an existing ``distributed`` cluster by scheduler address, or a ``LocalCluster`` started for the sweep;
``pip install 'needlecli[dask]'``; the workers must see ``DIR`` at the same path and run the submitter's
needlecli: one that does not is refused, naming it) and ``inline`` (in this process, one cell after
another). Without an executor, :func:`run_one_cell` runs one cell by its index (a job array's task:
``needle sweep --cell I``) and :func:`collect_sweep` makes the table of whatever cells are complete.
"""

from __future__ import annotations

import contextlib
import json
import logging
import time
import traceback
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

import pandas as pd
import yaml

from needlecli import kernels, platform
from needlecli.errors import NeedleError, SweepError
from needlecli.experiments.studies.sweep.plan import Cell, config_hash
from needlecli.io.atomic import install_worker_signals, worker_task, write_text_atomic
from needlecli.kernels._threads import n_threads
from needlecli.provenance import describe, identity
from needlecli.reports.sweep import cell_metrics, param_info, sweep_table, write_sweep_table

CONNECT_TIMEOUT = "10s"  # to reach a Dask scheduler
RETRIES = 1  # runs more of a cell whose (local) worker process died
Progress = Callable[[str, int, int], None]
log = logging.getLogger("needlecli")


@dataclass
class CellOutcome:
    """What became of a cell: ``status`` ok | failed | skipped (complete results from an earlier run)."""

    id: str
    status: str
    rows: list[dict] = field(default_factory=list)  # one per observer: its metrics
    error: str = ""
    seconds: float = 0.0


class WorkerRefused(SweepError):
    """A worker that runs another needlecli than the submitter's: the sweep stops."""


def _results_hold(cell: Cell) -> bool:
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
        return config_hash(yaml.safe_load(text)) == (cell.text_hash or cell.config_hash)
    except Exception:  # a truncated or foreign file: not complete
        return False


def _record(cell: Cell) -> dict | None:
    try:
        doc = json.loads(_sidecar(cell).read_text())
        return doc if isinstance(doc, dict) else None
    except (OSError, ValueError):
        return None


def results_complete(cell: Cell) -> bool:
    """Whether the cell's results file is complete: readable, the cell's config, and recorded ``ok`` under
    the cell's resume key (see the module docstring)."""
    doc = _record(cell)
    return (doc is not None and doc.get("status") == "ok" and doc.get("config_hash") == cell.config_hash
            and _results_hold(cell))


def _sidecar(cell: Cell) -> Path:
    return Path(cell.path).with_suffix(".json")


def _error_file(cell: Cell) -> Path:
    return Path(cell.path).with_suffix(".error.txt")


def _write_sidecar(cell: Cell, out: CellOutcome) -> None:
    doc = {"id": cell.id, "index": cell.index, "overrides": cell.overrides, "fixed": cell.fixed, "seed": cell.seed,
           "seed_from": cell.seed_from, "config_hash": cell.config_hash, "status": out.status,
           "seconds": out.seconds, "error": out.error, "rows": out.rows, "planned_by": cell.planned_by,
           "ran_by": identity()}
    write_text_atomic(_sidecar(cell), json.dumps(doc, indent=1, default=str) + "\n")


def _record_failure(cell: Cell, out: CellOutcome, details: str) -> None:
    write_text_atomic(_error_file(cell), f"cell {cell.id} ({cell.label()})\n{details}\n")
    _write_sidecar(cell, out)


def run_cell(cell: Cell, threads: int | None = None) -> CellOutcome:
    """Run one cell: its experiment (results file written atomically), then its metrics, its kernels on
    ``threads`` worker threads (None: the process's usable cores). Never raises: a failure is returned
    (and written to ``<id>.error.txt``); a signal (SIGINT, SIGTERM) is raised, the cell's temporary file
    removed."""
    t0 = time.perf_counter()
    path = Path(cell.path)
    with worker_task():
        return _run_cell(cell, path, t0, threads)


def _run_cell(cell: Cell, path: Path, t0: float, threads: int | None) -> CellOutcome:
    from needlecli.experiments.config.load import load_config
    from needlecli.experiments.simulation.runner import run_experiment

    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        for stale in (_error_file(cell), _sidecar(cell)):  # an earlier results file stays until the new one replaces it
            stale.unlink(missing_ok=True)
        # BLAS pinned (local workers also start with platform.THREAD_ENV at 1); the kernels on this worker's
        # share of the cores (NEEDLECLI_THREADS, if smaller, wins), and compiled whatever the cache's state:
        # every cell takes one path
        if threads is not None:
            threads = min(threads, n_threads())
        with platform.thread_pools_limited(1), kernels.threads(threads), kernels.compile_now():
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
    """The outcome of a cell whose complete results exist (its metrics from its record), its stale error
    file removed; None when it must run."""
    if not results_complete(cell):
        return None
    doc = _record(cell) or {}
    _error_file(cell).unlink(missing_ok=True)  # a failure of an earlier attempt, since completed
    return CellOutcome(cell.id, "skipped", rows=doc.get("rows", []), seconds=float(doc.get("seconds", 0.0)))


# ---------------------------------------------------------------------------------------------- executors
def _pin_worker_threads() -> None:
    """Start of a local worker process: the environment already pins BLAS / OpenMP (set before the
    process started, so before numpy is imported); threadpoolctl, if installed, makes sure. SIGINT and
    SIGTERM stop the cell being run cleanly (its temporary file removed)."""
    install_worker_signals()
    platform.pin_thread_pools()


#: the thread-pool variables at 1 while worker processes are started (they inherit them)
_thread_env = platform.one_thread_env


def _failed(cell: Cell, e: BaseException | str) -> CellOutcome:
    said = e if isinstance(e, str) else (f"{type(e).__name__}: {e}".splitlines()[0] or type(e).__name__)
    out = CellOutcome(cell.id, "failed", error=said)
    try:
        _record_failure(cell, out, said if isinstance(e, str) else "".join(traceback.format_exception(e)))
    except Exception:  # noqa: BLE001
        pass
    return out


def share_of_cores(workers: int, cores: int | None = None) -> int:
    """Kernel threads of each of ``workers`` cells running at once on a machine of ``cores`` usable cores
    (default: this process's, :func:`needlecli.platform.usable_cores`): at least 1."""
    return max(1, (cores if cores is not None else platform.usable_cores()) // max(1, workers))


def _local_worker(conn, threads: int) -> None:
    """A local worker process: cells from ``conn`` one at a time, their outcomes back; ends at None."""
    _pin_worker_threads()
    while True:
        try:
            cell = conn.recv()
        except (EOFError, OSError):
            return
        if cell is None:
            return
        conn.send(run_cell(cell, threads))


class _Pool:
    """``workers`` processes of this machine, one cell each at a time. A process that dies (killed, out of
    memory) fails its own cell only: the cell runs once more (:data:`RETRIES`) on a fresh process; the
    other cells are not touched."""

    def __init__(self, workers: int) -> None:
        import multiprocessing as mp

        self.ctx = mp.get_context("spawn")
        self.workers = workers
        self.threads = share_of_cores(workers)
        self.procs: dict = {}  # process -> [conn, cell or None]

    def _start(self):
        parent, child = self.ctx.Pipe()
        with _thread_env():  # started pinned: the variables are read before numpy is imported
            p = self.ctx.Process(target=_local_worker, args=(child, self.threads), daemon=True)
            p.start()
        child.close()
        self.procs[p] = [parent, None]
        return p

    def run(self, cells: list[Cell]) -> Iterator[CellOutcome]:
        from multiprocessing.connection import wait

        todo = [(c, 0) for c in cells]
        try:
            while todo or any(job[1] is not None for job in self.procs.values()):
                for job in self.procs.values():  # an idle process takes the next cell
                    if job[1] is None and todo:
                        job[1] = todo.pop(0)
                        job[0].send(job[1][0])
                while todo and len(self.procs) < self.workers:
                    p = self._start()
                    self.procs[p][1] = todo.pop(0)
                    self.procs[p][0].send(self.procs[p][1][0])
                busy = {job[0]: p for p, job in self.procs.items() if job[1] is not None}
                ready = wait([*busy, *(p.sentinel for p in busy.values())])
                for p, job in list(self.procs.items()):
                    conn, running = job
                    if running is None:
                        continue
                    cell, attempt = running
                    if conn in ready or conn.poll():
                        try:
                            out = conn.recv()
                        except (EOFError, OSError):
                            out = None
                        if out is not None:
                            job[1] = None
                            yield out
                            continue
                    if not p.is_alive():  # died with the cell: it alone fails (again: once more)
                        p.join()
                        del self.procs[p]
                        conn.close()
                        if attempt < RETRIES:
                            log.info("cell %s: its worker process ended (exit code %s); running it again",
                                     cell.id, p.exitcode)
                            todo.insert(0, (cell, attempt + 1))
                        else:
                            yield _failed(cell, f"its worker process ended (exit code {p.exitcode}), "
                                                f"{attempt + 1} time(s)")
            self.close()
        except BaseException:  # interrupted: the running cells stop too (each removes its temporary file)
            self.stop()
            raise

    def close(self) -> None:
        for conn, _ in list(self.procs.values()):
            with contextlib.suppress(OSError, ValueError):
                conn.send(None)
        for p in list(self.procs):
            p.join(10)
            if p.is_alive():
                p.kill()
                p.join()
        self.procs.clear()

    def stop(self, timeout: float = 10.0) -> None:
        """SIGTERM to every worker process, then wait for them (SIGKILL after ``timeout``)."""
        procs = list(self.procs)
        for p in procs:
            with contextlib.suppress(Exception):
                p.terminate()
        deadline = time.monotonic() + timeout
        for p in procs:
            with contextlib.suppress(Exception):
                p.join(max(0.0, deadline - time.monotonic()))
                if p.is_alive():
                    p.kill()
        self.procs.clear()


def _run_local(cells: list[Cell], workers: int) -> Iterator[CellOutcome]:
    yield from _Pool(workers).run(cells)


# ---------------------------------------------------------------------------------------------- dask
def _worker_facts() -> dict:
    """What a Dask worker tells the submitter: its needlecli, host and usable cores (run on each)."""
    import socket

    return {"needlecli": identity(), "host": socket.gethostname(), "cores": platform.usable_cores()}


def _dask_cell(cell: Cell, expected: dict, shares: dict) -> CellOutcome:
    """A cell on a Dask worker: refused (the sweep stops) if the worker runs another needlecli than the
    submitter's; its kernels on the worker's share of its host's cores."""
    mine = identity()
    if mine != expected:
        try:
            from distributed import get_worker

            where = get_worker().address
        except (ImportError, ValueError):
            where = "a worker"
        raise WorkerRefused(f"dask worker {where} runs {describe(mine)}, the submitter {describe(expected)}: "
                            "every worker must run the submitter's needlecli")
    try:
        from distributed import get_worker

        threads = shares.get(get_worker().address)
    except (ImportError, ValueError):
        threads = None
    return run_cell(cell, threads)


def _dask_client(scheduler: str | None, workers: int):
    try:
        from distributed import Client, LocalCluster
    except ImportError:
        raise SweepError("the dask executor needs the distributed package: pip install 'needlecli[dask]' "
                         "(or pip install 'dask[distributed]')") from None
    if scheduler:
        try:
            client = Client(scheduler, timeout=CONNECT_TIMEOUT)
        except (OSError, TimeoutError) as e:
            raise SweepError(f"cannot reach the Dask scheduler at {scheduler}: {e}") from None
        return client, None
    for name in ("distributed", "distributed.scheduler", "distributed.worker", "distributed.nanny", "distributed.core"):
        logging.getLogger(name).setLevel(logging.WARNING)  # the cluster's start-up chatter is not the user's news
    with _thread_env():
        cluster = LocalCluster(n_workers=workers, threads_per_worker=1, processes=True, dashboard_address=":0")
    return Client(cluster), cluster


def _check_workers(client, expected: dict) -> dict[str, int]:
    """Every worker's needlecli against the submitter's (:class:`WorkerRefused` naming the first that
    differs), and each worker's kernel threads: its host's usable cores over the cells that run there at
    once (the workers' threads on that host)."""
    facts = client.run(_worker_facts)
    info = client.scheduler_info().get("workers", {})
    for addr in sorted(facts):
        if facts[addr]["needlecli"] != expected:
            raise WorkerRefused(f"dask worker {addr} runs {describe(facts[addr]['needlecli'])}, the submitter "
                                f"{describe(expected)}: every worker must run the submitter's needlecli")
    per_host: dict[str, int] = {}
    for addr, f in facts.items():
        per_host[f["host"]] = per_host.get(f["host"], 0) + int(info.get(addr, {}).get("nthreads", 1) or 1)
    return {addr: share_of_cores(per_host[f["host"]], f["cores"]) for addr, f in facts.items()}


def _close_dask(client, cluster) -> None:
    """The client closed, and the cluster if this sweep started it. (Its worker processes end within the
    nanny's 4 s, not killed: a process that loaded the kernels skips the last collection of numba's
    objects at its end, :mod:`needlecli.kernels._jit`.)"""
    client.close()
    if cluster is not None:
        cluster.close()


def _run_dask(cells: list[Cell], scheduler: str | None, workers: int) -> Iterator[CellOutcome]:
    client, cluster = _dask_client(scheduler, workers)
    from distributed import as_completed
    try:
        link = getattr(client, "dashboard_link", None)
        n = len(client.scheduler_info().get("workers", {}))
        log.info("dask: %s with %d worker(s)%s", "a local cluster" if cluster is not None else f"scheduler {scheduler}",
                 n, f"; dashboard: {link}" if link else "")
        expected = identity()
        shares = _check_workers(client, expected)
        stamp = time.time_ns()
        futures = [client.submit(_dask_cell, c, expected, shares, key=f"needle-cell-{c.id}-{stamp}", pure=False)
                   for c in cells]
        by_key = {f.key: c for f, c in zip(futures, cells)}
        for fut in as_completed(futures):
            try:
                yield fut.result()
            except WorkerRefused:
                for f in futures:
                    f.cancel()
                raise
            except Exception as e:  # noqa: BLE001 (a worker died or the task could not be sent)
                yield _failed(by_key[fut.key], e)
            fut.release()
    finally:
        _close_dask(client, cluster)


def execute(cells: list[Cell], *, executor: str = "local", workers: int | None = None,
            scheduler: str | None = None) -> Iterator[CellOutcome]:
    """Run cells on an executor, yielding each outcome as it finishes (in no particular order)."""
    if not cells:
        return iter(())
    workers = max(1, workers or platform.usable_cores())
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
    missing: int = 0  # cells without complete results (``collect``)


#: ``on_cell(cell, outcome, done, total)``: told of each finished cell (the command's line per cell)
OnCell = Callable[[Cell, CellOutcome, int, int], None]


def _manifest(cells: list[Cell], out_dir: Path, manifest: dict | None) -> None:
    doc = {"cells": [{"index": c.index, "id": c.id, "overrides": c.overrides, "seed": c.seed,
                      "seed_from": c.seed_from, "config_hash": c.config_hash} for c in cells],
           "params": param_info(cells), "needlecli": identity(), **(manifest or {})}
    write_text_atomic(out_dir / "sweep.json", json.dumps(doc, indent=1, default=str) + "\n")


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
    on_cell: OnCell | None = None,
) -> SweepResult:
    """Run the cells (skipping complete ones when ``resume``), write ``DIR/sweep.csv`` and ``DIR/sweep.md``.

    ``executor`` is ``local``, ``dask`` or ``inline``; ``workers`` the number of local processes (or of
    the ``LocalCluster`` started when ``dask`` has no ``scheduler`` address); default the usable cores.
    """
    t0 = time.perf_counter()
    out_dir = Path(out_dir)
    (out_dir / "cells").mkdir(parents=True, exist_ok=True)
    _manifest(cells, out_dir, manifest)
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
    by_id = {c.id: c for c in cells}
    for out in execute(todo, executor=executor, workers=workers, scheduler=scheduler):
        outcomes[out.id] = out
        if progress:
            progress("cells", len(outcomes), len(cells))
        if on_cell is not None:
            on_cell(by_id[out.id], out, len(outcomes), len(cells))
    table, units = sweep_table(cells, outcomes)
    write_sweep_table(table, out_dir, units)
    return SweepResult(cells=cells, outcomes=outcomes, table=table, out_dir=out_dir, ran=len(todo),
                       skipped=skipped, failed=sum(o.status == "failed" for o in outcomes.values()),
                       seconds=time.perf_counter() - t0, units=units)


def run_one_cell(cells: list[Cell], index: int, *, out_dir: str | Path, resume: bool = False,
                 manifest: dict | None = None) -> CellOutcome:
    """Cell ``index`` (0-based, the plan's order) alone, in this process (a job array's task: ``needle
    sweep --cell I``), its kernels on this process's usable cores; with ``resume`` a complete cell is not
    run again. Raises :class:`SweepError` for an index that is no cell."""
    if not 0 <= index < len(cells):
        raise SweepError(f"--cell {index}: the grid has {len(cells)} cell(s), numbered 0 to {len(cells) - 1}")
    out_dir = Path(out_dir)
    (out_dir / "cells").mkdir(parents=True, exist_ok=True)
    _manifest(cells, out_dir, manifest)  # (every task writes the same, atomically)
    cell = cells[index]
    done = _resumed(cell) if resume else None
    return done if done is not None else run_cell(cell)


def collect_sweep(cells: list[Cell], *, out_dir: str | Path) -> SweepResult:
    """The table of the cells whose results are complete (and those recorded as failed), written as by
    :func:`run_sweep`; the others are ``not run`` rows (``missing``): results from another config or
    needlecli included (their resume key differs)."""
    t0 = time.perf_counter()
    out_dir = Path(out_dir)
    outcomes: dict[str, CellOutcome] = {}
    for c in cells:
        done = _resumed(c)
        if done is not None:
            outcomes[c.id] = CellOutcome(c.id, "ok", rows=done.rows, seconds=done.seconds)
            continue
        doc = _record(c)
        if doc is not None and doc.get("status") == "failed" and doc.get("config_hash") == c.config_hash:
            outcomes[c.id] = CellOutcome(c.id, "failed", error=str(doc.get("error", "")),
                                         seconds=float(doc.get("seconds", 0.0)))
    table, units = sweep_table(cells, outcomes)
    write_sweep_table(table, out_dir, units)
    failed = sum(o.status == "failed" for o in outcomes.values())
    return SweepResult(cells=cells, outcomes=outcomes, table=table, out_dir=out_dir, ran=0,
                       skipped=len(outcomes) - failed, failed=failed, seconds=time.perf_counter() - t0,
                       units=units, missing=len(cells) - len(outcomes))
