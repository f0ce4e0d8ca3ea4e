"""numba, configured once for needlecli's kernels: the on-disk cache, numba's patches, the decorators.

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

# numba, patched where it lacks what the kernels need, each patch in its own module saying which upstream
# issue it works around and when to drop it: vector code (SLP, 512-bit vectors), locked cache saves, noalias
from needlecli.kernels import _patch_cache_lock, _patch_vectorize  # noqa: F401  (applied on import)
from needlecli.kernels._patch_noalias import NOALIAS

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
