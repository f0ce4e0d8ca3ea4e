"""Compiled kernels (numba) for the hot loops, beside the numpy implementation that stays the reference.

This package is light: importing it imports neither numba nor any kernel. The kernel modules
(``needlecli.kernels.models``, ``.truth``, ``.ukf``, ``.kalman``) are imported only when a run uses them.

Which path runs is chosen per run: ``simulation.kernels`` in a config (``auto``, the default: compiled
where a component has a compiled path and numba is installed; ``numba``: the same, and an error when numba
is missing; ``numpy``: the reference everywhere), overridden by the environment variable
``NEEDLECLI_KERNELS`` (same values) for debugging without editing configs. A component without a
compiled path (or a configuration its kernel does not cover) runs on the numpy path either way.
"""

from __future__ import annotations

import contextlib
import functools
import importlib.util
import os
from contextvars import ContextVar

MODES = ("auto", "numba", "numpy")
ENV = "NEEDLECLI_KERNELS"

#: what has a compiled path, for ``needle list`` (kept beside the kernels that implement it)
COMPILED = {
    "models": ("unicycle", "modified_unicycle", "so3", "mnm", "binm"),
    "truth": "the truth simulation (open loop; closed loops step the numpy model)",
    "observers": {
        "ukf": "predict, multi-rate update with masks, gating, resets, constraint, predictions; "
               "channels that select states (position, roll, curvature); others: numpy",
        "eks": "the RTS smoother, the linearisation of mnm and binm, the affine filter with joseph: false",
    },
    "fitting": "fit-em: the affine filter and RTS passes of the iterated EKS over all trials at once, the "
               "M-step sums, the linearisation of mnm and binm",
    "linearised": ("mnm", "binm"),
    "metrics": "the rotation error E_R of orientations given as Euler angles (needle evaluate, summary tables)",
}


_SETTING: ContextVar[str | None] = ContextVar("needlecli_kernels", default=None)


@contextlib.contextmanager
def using(setting: str | None):
    """The kernels setting for pure array functions deep in a computation (the Kalman passes of EM), which
    take no config: ``with kernels.using(cfg.simulation.kernels): ...``."""
    token = _SETTING.set(setting)
    try:
        yield
    finally:
        _SETTING.reset(token)


@contextlib.contextmanager
def threads(n: int | None):
    """Worker threads of the kernels while the block runs (None: as configured; e.g. 1 where processes
    already share the cores: one EM process per model)."""
    from needlecli.kernels import _threads

    before = list(_threads._FORCED)
    _threads.set_threads(n)
    try:
        yield
    finally:
        _threads._FORCED[:] = before


class KernelError(RuntimeError):
    """``kernels: numba`` asked for and numba cannot be imported."""


@functools.lru_cache(maxsize=1)
def numba_available() -> bool:
    return importlib.util.find_spec("numba") is not None


def mode(setting: str | None = None) -> str:
    """The requested mode: ``NEEDLECLI_KERNELS`` if set, else ``setting`` (a config's), else the one of
    :func:`using`, else ``auto``."""
    env = os.environ.get(ENV, "").strip().lower()
    if env:
        if env not in MODES:
            raise KernelError(f"{ENV}={env!r}: expected one of {', '.join(MODES)}")
        return env
    return setting or _SETTING.get() or "auto"


def compiled(setting: str | None = None) -> bool:
    """Whether components with a compiled path should use it."""
    m = mode(setting)
    if m == "numpy":
        return False
    if numba_available():
        return True
    if m == "numba":
        raise KernelError("compiled kernels requested (kernels: numba) but numba is not installed: pip install numba")
    return False


def has_model(name: str) -> bool:
    """Whether model ``name`` has compiled equations."""
    return name in COMPILED["models"]


def describe() -> list[str]:
    """Lines for ``needle list``: what has a compiled path and which path a run would take now."""
    m = mode()
    state = ("numba " + ("available" if numba_available() else "NOT installed: every run takes the numpy path"))
    lines = [f"kernels: {m} ({ENV} or simulation.kernels: auto | numba | numpy); {state}",
             f"  compiled models: {', '.join(COMPILED['models'])} (vector fields, RK4 steps)",
             f"  compiled truth: {COMPILED['truth']}"]
    for name, what in COMPILED["observers"].items():
        lines.append(f"  compiled observer {name}: {what}")
    lines.append(f"  compiled fitting: {COMPILED['fitting']}")
    lines.append(f"  compiled metrics: {COMPILED['metrics']}")
    return lines


#: the kernel that compiles longest for each observer with a compiled path (module, function)
_ENTRY = {"ukf": ("ukf", "run"), "eks": ("kalman", "filter_smoother")}


def cold(observer_types) -> bool:
    """Whether the on-disk kernel cache lacks the compiled code of any of these observers (for the kernel
    sources of this install; imports numba). Observers without a compiled path do not count."""
    from needlecli.kernels import _jit

    entries = {_ENTRY[t] for t in observer_types if t in _ENTRY}
    return any(not any(_jit.CACHE_DIR.rglob(f"{m}.{f}-*.nbi")) for m, f in entries)


class WarmUp:
    """A process compiling kernels into the on-disk cache while this one goes on (:func:`warm_up`)."""

    def __init__(self, proc=None):
        self._proc = proc

    def wait(self) -> None:
        """Until it has finished: then the kernels it compiled load from the cache here."""
        if self._proc is not None:
            self._proc.join()
            self._proc = None

    def cancel(self) -> None:
        if self._proc is not None and self._proc.is_alive():
            self._proc.terminate()
        self.wait()


def warm_up(fn, *args) -> WarmUp:
    """Compile kernels in a second process while this one goes on: ``fn(*args)`` runs in a forked child
    whose only output is the kernel cache on disk (its stdout and stderr go nowhere; numba saves each
    kernel under a file lock, :mod:`needlecli.kernels._jit`, so the two processes' entries do not
    collide). :meth:`WarmUp.wait` before the first call of a kernel it compiles: that call then loads the
    kernel from the cache instead of compiling it again. A first run on an empty cache compiles on both
    cores this way. A no-op where processes cannot be forked or one core is all there is."""
    import multiprocessing as mp

    from needlecli import platform
    from needlecli.kernels import _threads

    if not platform.fork_available() or _threads.n_threads() < 2 or mp.current_process().daemon:
        return WarmUp()  # (a daemonic process, e.g. one of fit-em's, may not start processes of its own)
    p = mp.get_context("fork").Process(target=_warm_child, args=(fn, args), daemon=True)
    try:
        p.start()
    except OSError:  # no process to spare: this run compiles everything itself
        return WarmUp()
    return WarmUp(p)


def _warm_child(fn, args) -> None:
    import signal

    from needlecli import platform

    devnull = os.open(os.devnull, os.O_WRONLY)
    os.dup2(devnull, 1)
    os.dup2(devnull, 2)
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the parent's Ctrl-C is the parent's (it terminates this one)
    try:  # if the parent is killed outright, this one ends too (Linux); the cache's writes are atomic
        if platform.die_with_parent():  # (False: the parent is gone already)
            fn(*args)
    except BaseException:  # noqa: BLE001  (only a cache is lost: the parent compiles what is missing)
        pass
    finally:
        os._exit(0)
