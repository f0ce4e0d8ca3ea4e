"""Compiled kernels (numba) for the hot loops, beside the numpy implementation that stays the reference.

This package is light: importing it imports neither numba nor any kernel. The kernel modules
(``needlecli.kernels.models``, ``.truth``, ``.ukf``, ``.kalman``, ``.metrics``) are imported only when a run
uses them, through :func:`twin`.

The table of twins and the one choice between them and the numpy reference, from one explicit setting
(``simulation.kernels``: ``auto``, ``numba``, ``numpy``; the environment variable ``NEEDLECLI_KERNELS``
overrides it), are in :mod:`needlecli.kernels.dispatch`, re-exported here; so is what a command does on a
cold cache (:func:`cold_start`): the numpy path now while a process of its own compiles the kernels for
the next run (:func:`compile_in_background`), or the compilation first, said once.
"""

from __future__ import annotations

import contextlib
import os
import time
from collections.abc import Callable

from needlecli.kernels import dispatch
from needlecli.kernels.dispatch import (
    COLD_ENV,
    ENV,
    MODES,
    TWINS,
    KernelError,
    Twin,
    cold_policy,
    compile_estimate,
    compile_now,
    compiled,
    deferred,
    describe,
    markdown_table,
    numba_available,
    on_cold,
    requested,
    resolve,
    twin,
    would_defer,
)

__all__ = ["COLD_ENV", "ENV", "MODES", "TWINS", "KernelError", "Twin", "WarmUp", "cold", "cold_policy",
           "compile_estimate", "compile_in_background", "compile_now", "compiled", "compiling", "deferred",
           "describe", "markdown_table", "numba_available", "on_cold", "requested", "resolve", "threads", "twin",
           "wait_for_compile", "warm_up", "would_defer"]



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


def cold(entries) -> bool:
    """Whether the on-disk kernel cache lacks any of these compiled entry points, ``(module, function)``
    pairs of :mod:`needlecli.kernels` (the observers' ``compiled_entry``, :attr:`Twin.entry`; None entries
    are skipped), for the kernel sources of this install. Light: numba is not imported."""
    from needlecli.kernels import _cache

    return any(not _cache.cached(e) for e in {e for e in entries if e is not None})


# ---------------------------------------------------------------------------------------------- a cold cache
def compiling() -> bool:
    """Whether a process compiles this install's kernels in the background now (it holds the cache's
    ``needlecli-compiling.lock``)."""
    from needlecli import platform
    from needlecli.kernels import _cache

    return platform.lock_held(_cache.lock_path())


def wait_for_compile(timeout: float | None = None) -> bool:
    """Wait until no background compilation runs (at most ``timeout`` s); True when none does."""
    t0 = time.monotonic()
    while compiling():
        if timeout is not None and time.monotonic() - t0 > timeout:
            return False
        time.sleep(0.2)
    return True


def compile_in_background(fn: Callable, *args) -> bool:
    """Compile kernels for the next run in a process of its own that outlives this one: ``fn(*args)``
    runs there (:func:`needlecli.platform.spawn_detached`) with the cold policy ``wait``, on one kernel
    thread, holding the cache's lock ``needlecli-compiling.lock`` (one such process per install at a time;
    its only output is the cache). True when one runs now (started here, or by another command); False
    where none could be started (no ``fork``): the caller compiles itself."""
    from needlecli import platform
    from needlecli.kernels import _cache

    lock = _cache.lock_path()
    try:
        lock.parent.mkdir(parents=True, exist_ok=True)
    except OSError:
        return False
    if platform.lock_held(lock):
        return True
    pid = platform.spawn_detached(_compile_child, fn, args, ready=lambda: platform.hold_lock(lock))
    return pid is not None or platform.lock_held(lock)


def _compile_child(fn, args) -> None:
    from needlecli.kernels import _cache

    with contextlib.suppress(OSError):  # who holds the lock (a test, or a user, may want to know)
        _cache.lock_path().write_text(f"{os.getpid()}\n")
    with compile_now(), threads(1):
        fn(*args)
    _cache.record_unused(e for e in dispatch.REQUESTED if not _cache.cached(e))


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

    if not platform.fork_available() or _threads.threads() < 2 or mp.current_process().daemon:
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
