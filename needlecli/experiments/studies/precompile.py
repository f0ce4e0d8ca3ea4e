"""Compile the kernels that experiments need into the on-disk cache before they run (``needle kernels
compile``): the install step that takes the compiler off a first run's path, and the warm-up before a
cluster's job array.

Each config gives one *job* per kind of work it does: its simulation (every run's kernels: truth,
observers, error tables) and, with a ``fit:`` section, its fit (EM's passes, its M-step,
identifiability's log-likelihoods). A job runs a short copy of that work with every kernel compiled
(:func:`needlecli.kernels.compile_now`): the copies the commands themselves compile from on a cold cache
(:func:`needlecli.experiments.simulation.runner.brief_copy`, :func:`needlecli.experiments.studies.fit.brief_fit`),
so the kernels are compiled with the argument types the real runs pass and a later run loads them.

The jobs run in processes of their own, as many at a time as asked (the usable cores by default), the
longest first by the compile times this machine recorded (:func:`needlecli.kernels.compile_estimate`).
Two jobs needing one kernel compile it once: numba saves each kernel under a lock, and the second process
loads what the first saved (:mod:`needlecli.kernels._patch_cache_lock`).
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from pathlib import Path

from needlecli import kernels
from needlecli.errors import ConfigError

#: the bundled configs compiled for when none is given (relative to the checkout's ``configs/``): the default
#: study (the multi-rate UKF, the open loop), the magnetic needle EM paper's fit (both models), the particle
#: filters' Table 1 (pf, rbpf): together every compiled twin (``needle kernels status`` says which)
BUNDLED = ("default.yaml", "em-magnetic-pratt2022/study.yaml", "particles/table1.yaml")


@dataclass
class Job:
    """One short run that compiles the kernels of one kind of work of one config."""

    config: str  # as given (for messages)
    kind: str  # "simulate", "fit" or "truth" (a config without observers or fit)
    entries: list[tuple[str, str]]  # the entry kernels it compiles (those the cache lacks are its work)
    estimate: float = 0.0  # seconds of compilation still to do (this machine's record, else the table's)

    @property
    def label(self) -> str:
        return f"{self.config} ({self.kind})"


@dataclass
class Plan:
    """What ``needle kernels compile`` does: its jobs, and the configs it skipped (with why)."""

    jobs: list[Job] = field(default_factory=list)
    skipped: list[str] = field(default_factory=list)

    def todo(self) -> list[Job]:
        """Every job, the longest first, when the cache lacks a kernel of any (the cache says which functions
        it holds, not for which argument types: a job whose kernels another job compiled still runs, for
        the types of its own config); none when it lacks none."""
        if not kernels.cold(self.entries()):
            return []
        return sorted(self.jobs, key=lambda j: -j.estimate)

    def entries(self) -> list[tuple[str, str]]:
        return sorted({e for j in self.jobs for e in j.entries})


def bundled_configs() -> list[Path]:
    """The bundled configs of :data:`BUNDLED`, from the checkout this package runs from.

    Raises
    ------
    ConfigError
        The package does not run from a checkout (no ``configs/`` beside it): the configs must be given.
    """
    root = Path(__file__).resolve().parents[3] / "configs"
    paths = [_near(root / p) for p in BUNDLED]
    missing = [p for p in paths if not p.is_file()]
    if missing:
        raise ConfigError(str(missing[0]), (), "no bundled config here (needlecli runs from an installed package, "
                          "not a checkout): name the configs to compile for, e.g. needle kernels compile my_study.yaml")
    return paths


def _near(path: Path) -> Path:
    """``path`` relative to the working folder when it is inside it (as a user would name it)."""
    try:
        return path.relative_to(Path.cwd().resolve())
    except ValueError:
        return path


def plan(configs: Iterable[str | Path]) -> Plan:
    """The jobs for ``configs`` (every config read and checked first: a bad one raises before any work).
    A config on ``kernels: numpy`` needs nothing compiled; recorded trials (``source: logs``) compile at
    their first run (their short copy would need the recordings)."""
    from needlecli.experiments.config.load import load_config
    from needlecli.experiments.simulation.runner import run_entries
    from needlecli.experiments.studies.fit import fit_entries

    out = Plan()
    loaded = [(str(p), load_config(Path(p))[0]) for p in configs]
    for name, cfg in loaded:
        if kernels.requested(cfg.simulation.kernels) == "numpy":
            why = f"{kernels.ENV}=numpy" if os.environ.get(kernels.ENV, "").strip() else "kernels: numpy"
            out.skipped.append(f"{name}: {why} (nothing to compile)")
            continue
        if cfg.source is not None:
            out.skipped.append(f"{name}: recorded trials (source:): compiled at its first run")
            continue
        if cfg.observers:
            out.jobs.append(Job(name, "simulate", _known(run_entries(cfg))))
        if cfg.fit is not None:
            out.jobs.append(Job(name, "fit", _known(fit_entries(cfg))))
        if not cfg.observers and cfg.fit is None:
            out.jobs.append(Job(name, "truth", _known(run_entries(cfg)[:1])))
    claimed: set[tuple[str, str]] = set()
    for job in sorted(out.jobs, key=lambda j: -kernels.compile_estimate(j.entries)):
        mine = [e for e in job.entries if e not in claimed]  # a kernel two jobs need counts for the longer one
        claimed.update(mine)
        job.estimate = kernels.compile_estimate(mine) + BRIEF_SECONDS
    return out


#: seconds of a job's short run itself, beside its compilations (the estimate of :func:`makespan`)
BRIEF_SECONDS = 2.0


def _known(entries) -> list[tuple[str, str]]:
    return sorted({e for e in entries if e is not None})


def makespan(estimates: list[float], processes: int) -> float:
    """Seconds ``estimates`` take on ``processes`` processes, each job given to the first free one, the
    longest first (what :func:`run` does)."""
    ends = [0.0] * max(1, processes)
    for s in sorted(estimates, reverse=True):
        i = ends.index(min(ends))
        ends[i] += s
    return max(ends)


@dataclass
class Outcome:
    job: Job
    seconds: float
    error: str | None = None


def run(jobs: list[Job], processes: int, progress: Callable[[Outcome, int, int], None] | None = None) -> list[Outcome]:
    """Run ``jobs`` in their order (the longest first), each in a process of its own, at most ``processes``
    at a time (spawned: nothing of this process is shared but the cache on disk), each on one kernel
    thread and with every kernel compiled (the cold policy ``wait``). ``progress(outcome, done, total)``
    after each. A job that fails is reported in its outcome (the others go on). An interruption of this
    process (Ctrl-C, SIGTERM: raised here) ends the jobs still running before it goes on up: the cache
    keeps what they saved (each save is whole and locked)."""
    import multiprocessing as mp
    from multiprocessing.connection import wait

    ctx = mp.get_context("spawn")
    pending, running, out = list(jobs), {}, []
    try:
        while pending or running:
            while pending and len(running) < max(1, processes):
                job = pending.pop(0)
                recv, send = ctx.Pipe(duplex=False)
                proc = ctx.Process(target=_child, args=(send, job.config, job.kind), name=f"needle-compile-{job.kind}")
                proc.start()
                send.close()
                running[recv] = (proc, job)
            for conn in wait(list(running)):
                proc, job = running.pop(conn)
                try:
                    seconds, error = conn.recv()
                except EOFError:  # the process died without a word (killed, out of memory)
                    proc.join()
                    seconds, error = float("nan"), f"its process ended with exit code {proc.exitcode}"
                conn.close()
                proc.join()
                out.append(Outcome(job, seconds, error))
                if progress is not None:
                    progress(out[-1], len(out), len(jobs))
    finally:
        for proc, _ in running.values():
            proc.terminate()
        for proc, _ in running.values():
            proc.join()
    return out


def _child(conn, config: str, kind: str) -> None:
    """A job's process: its seconds, or what failed, sent back; Ctrl-C is the parent's to handle (it ends
    this process)."""
    import signal

    signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        conn.send((_job(config, kind), None))
    except Exception as e:  # noqa: BLE001  (reported by the parent: a job's failure is its config's)
        conn.send((float("nan"), f"{type(e).__name__}: {e}"))
    finally:
        conn.close()


def _job(config: str, kind: str) -> float:
    """The short copy of ``config``'s ``kind`` of work with every kernel compiled, on one thread; its
    seconds. (The config is read again here, in the job's process: its classes are made at run time, with
    the plug-ins', and do not pickle.)"""
    import logging

    from needlecli import platform
    from needlecli.experiments.config.load import load_config
    from needlecli.experiments.simulation.runner import _compile_briefly, brief_copy
    from needlecli.experiments.studies.fit import _fit_briefly, brief_fit

    logging.getLogger("needlecli").setLevel(logging.ERROR)  # the short run's own lines are not the user's
    cfg, _ = load_config(Path(config))
    t0 = time.perf_counter()
    with platform.single_blas_thread(), kernels.compile_now(), kernels.threads(1):
        if kind == "fit":
            _fit_briefly(brief_fit(cfg), None)
        else:
            _compile_briefly(brief_copy(cfg))
    return time.perf_counter() - t0


def status(entries: Iterable[tuple[str, str]]) -> list[tuple[str, bool, float | None]]:
    """For each entry kernel: its name (``module.function``), whether the cache holds it, and how long it
    took to compile on this machine (None: never recorded)."""
    from needlecli.kernels import _cache

    mine = _cache.recorded_seconds()
    return [(f"{m}.{f}", _cache.cached((m, f)), mine.get(f"{m}.{f}")) for m, f in sorted(set(entries))]
