"""numba, configured once for needlecli's kernels: the on-disk cache, numba's patches, the decorators.

Imported only by the kernel modules (never by ``needle --help`` or a run on the numpy path). The
compiled code is cached on disk (``cache=True``) in a directory named after a hash of the kernel
sources (:mod:`needlecli.kernels._cache`), so that one cached kernel that calls another is never reused
after either changed (numba itself checks only the file that defines a function); it is set only while
the kernel modules are imported, so other numba users in the process keep their own. How long each
kernel took to compile here is recorded (:func:`_cache.record_seconds`), for the estimate a command that
must wait for a compilation prints.
"""

from __future__ import annotations

import atexit
import contextlib
import gc
import time

import numba
from numba import njit, prange  # noqa: F401  (re-exported for the kernel modules)

# numba, patched where it lacks what the kernels need, each patch in its own module saying which upstream
# issue it works around and when to drop it: vector code (SLP, 512-bit vectors), locked cache saves, noalias
from needlecli.kernels import _cache, _patch_cache_lock, _patch_vectorize, dispatch  # noqa: F401  (patches: applied on import)
from needlecli.kernels._patch_noalias import NOALIAS

CACHE_DIR = _cache.cache_dir()

# A process that loaded kernels holds millions of numba's objects; the cyclic collections of the
# interpreter's finalization walk them all (0.3 to 1 s of a command's end here, and more than the 4 s a
# Dask nanny waits for its worker process to end before it kills it). Frozen at exit, they are left to the
# operating system: what has a finaliser of its own (files, temporary folders: atexit and weakref.finalize)
# is unaffected, as is everything freed by reference counting.
atexit.register(gc.freeze)


@contextlib.contextmanager
def kernel_cache():
    """numba's cache directory for the functions decorated inside (restored after)."""
    before = numba.config.CACHE_DIR
    numba.config.CACHE_DIR = str(CACHE_DIR)
    try:
        yield
    finally:
        numba.config.CACHE_DIR = before


def jit(fn=None, **kw):
    """``njit`` with the cache on (IEEE arithmetic: no fastmath, so results stay those of the numpy
    reference up to the order of sums)."""
    opts = {"cache": True, "nogil": True, "error_model": "numpy", **kw}

    def deco(f):
        with kernel_cache():
            return njit(**opts)(f)

    return deco(fn) if fn is not None else deco


def pjit(fn=None, **kw):
    """:func:`jit` with ``parallel=True``: ``prange`` loops spread runs over the cores."""
    return jit(fn, parallel=True, **kw)


def lanes(fn=None, **kw):
    """:func:`jit` for loops over the lanes of a block of runs: array arguments declared not to overlap
    (each must be a distinct array, never a view of another argument)."""
    return jit(fn, **{**NOALIAS, **kw})


def inline(fn):
    """A small function inlined into its callers (no cache of its own)."""
    return njit(inline="always", error_model="numpy", nogil=True)(fn)


# ---------------------------------------------------------------------------------------------- compile times
class _CompileTimes(numba.core.event.Listener):
    """Records how long each outermost compilation of a kernel took (inclusive of the kernels it calls)."""

    def __init__(self) -> None:
        self.depth = 0
        self.t0 = 0.0

    def on_start(self, event) -> None:
        if self.depth == 0:
            self.t0 = time.perf_counter()
            name = _name(getattr(event.data.get("dispatcher"), "py_func", None))
            if name is not None:  # once per command: "compiling kernels, once per install: about N s"
                dispatch.announce(name)
        self.depth += 1

    def on_end(self, event) -> None:
        self.depth -= 1
        if self.depth:
            return
        name = _name(getattr(event.data.get("dispatcher"), "py_func", None))
        if name is not None:
            _cache.record_seconds(name, time.perf_counter() - self.t0)


def _name(fn) -> str | None:
    """``module.function`` of a kernel of needlecli (``ukf.run``), else None."""
    module = getattr(fn, "__module__", "") or ""
    return f"{module.rsplit('.', 1)[1]}.{fn.__name__}" if module.startswith("needlecli.kernels.") else None


numba.core.event.register("numba:compile", _CompileTimes())
