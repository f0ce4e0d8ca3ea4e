"""numba, configured once for needlecli's kernels: the on-disk cache and the decorators.

Imported only by the kernel modules (never by ``needle --help`` or a run on the numpy path). The
compiled code is cached on disk (``cache=True``) in a directory named after a hash of the kernel
sources, so that one cached kernel that calls another is never reused after either changed (numba
itself checks only the file that defines a function) and an installed package and an editable checkout
each find their own cache. The directory is ``$NEEDLECLI_KERNEL_CACHE`` if set, else
``$NUMBA_CACHE_DIR/needlecli`` if that is set, else ``~/.cache/needlecli/numba`` (``$XDG_CACHE_HOME``
respected); it is set only while the kernel modules are imported, so other numba users in the process
keep their own.
"""

from __future__ import annotations

import contextlib
import hashlib
import os
from pathlib import Path

import numba
from numba import njit, prange  # noqa: F401  (re-exported for the kernel modules)

HERE = Path(__file__).resolve().parent


def source_hash() -> str:
    """A hash of every kernel module's source (and numba's version)."""
    h = hashlib.sha256(numba.__version__.encode())
    for p in sorted(HERE.glob("*.py")):
        h.update(p.name.encode())
        h.update(p.read_bytes())
    return h.hexdigest()[:16]


def cache_root() -> Path:
    if os.environ.get("NEEDLECLI_KERNEL_CACHE"):
        return Path(os.environ["NEEDLECLI_KERNEL_CACHE"])
    if os.environ.get("NUMBA_CACHE_DIR"):
        return Path(os.environ["NUMBA_CACHE_DIR"]) / "needlecli"
    base = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache")
    return base / "needlecli" / "numba"


CACHE_DIR = cache_root() / source_hash()

# LLVM's SLP vectoriser (off by default in numba): the kernels keep a few independent sums in registers
# (lanes of the Kalman passes) that it turns into vector operations, twice the speed. It packs
# operations, it does not reorder them (no fastmath): the same numbers. Process-wide, for compilations
# from here on.
numba.config.SLP_VECTORIZE = 1


def _full_width_vectors() -> None:
    """Let LLVM use 512-bit vectors where the CPU has them (AVX-512). LLVM's tuning for recent Intel cores
    prefers 256-bit ones (a hedge against the clock drop of older AVX-512 parts); the kernels' loops over
    8 or 16 lanes run 1.3-1.4x faster at full width here (benchmarks/bench_kernels.py). The same numbers:
    vector width changes no operation. An explicit ``NUMBA_CPU_FEATURES`` (or ``NUMBA_DISABLE_AVX``) wins;
    set before numba builds its code generator (the first compilation or cache load of the process)."""
    if numba.config.CPU_FEATURES is not None or not numba.config.ENABLE_AVX:
        return
    try:
        import llvmlite.binding as ll

        features = ll.get_host_cpu_features()
    except (RuntimeError, ImportError):  # pragma: no cover
        return
    if features.get("avx512f"):
        numba.config.CPU_FEATURES = features.flatten() + ",-prefer-256-bit"


_full_width_vectors()


def _locked_cache_saves() -> None:
    """numba saves a compiled function by reading its cache index, adding the entry and writing it back;
    two processes compiling the same function at once (a first run that compiles in two processes,
    :func:`needlecli.kernels.warm_up`) could then lose an entry or overwrite each other's data file. Each
    save here holds an exclusive lock on a file beside the index (:func:`needlecli.platform.file_lock`:
    ``flock`` where the platform has it), so saves of one function follow one another; loads are unchanged
    (the index and data files are replaced atomically)."""
    from numba.core import caching

    from needlecli.platform import file_lock
    cls = caching.IndexDataCacheFile
    if getattr(cls.save, "_needlecli_locked", False):
        return
    plain = cls.save

    def save(self, key, data):
        with file_lock(self._index_path + ".lock"):
            return plain(self, key, data)

    save._needlecli_locked = True
    cls.save = save


_locked_cache_saves()


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


# ``noalias`` (a flag of numba's compiler that its decorators do not expose): the array arguments of a
# function so marked never overlap, which is what lets LLVM pack the loops over lanes (runs) of the
# kernels into vector operations; without it every store might change what the next load reads, and
# the loops stay scalar. Only functions whose array arguments are distinct arrays by construction use it
# (:func:`lanes`); where numba lacks the flag they are compiled without it (the same numbers, slower).
try:
    from numba.core import cpu as _cpu
    from numba.core import options as _options

    if not hasattr(_cpu.CPUTargetOptions, "noalias"):
        _cpu.CPUTargetOptions.noalias = _options.TargetOptions.Mapping("noalias")
    _NOALIAS = {"noalias": True}
except (ImportError, AttributeError):  # pragma: no cover  (a numba without the flag)
    _NOALIAS = {}


def lanes(fn=None, **kw):
    """:func:`jit` for loops over the lanes of a block of runs: array arguments declared not to overlap
    (each must be a distinct array, never a view of another argument)."""
    return jit(fn, **{**_NOALIAS, **kw})


def inline(fn):
    """A small function inlined into its callers (no cache of its own)."""
    return njit(inline="always", error_model="numpy", nogil=True)(fn)
