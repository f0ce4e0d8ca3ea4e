"""numba patch: the ``noalias`` compiler flag, which numba's decorators do not take.

The array arguments of a function so marked never overlap; that is what lets LLVM pack the loops over
lanes (runs) of the kernels into vector operations: without it every store might change what the next
load reads, and the loops stay scalar. numba's compiler has the flag (``Flags.noalias``, set for the
outlined bodies of ``parallel=True``) but ``@njit`` does not take it; numba/numba#9108 ("Add noalias
option to jit decorator") was closed unmerged. This registers it as an option of the CPU target, so
that ``njit(noalias=True)`` sets it. Only functions whose array arguments are distinct arrays by
construction use it (:func:`needlecli.kernels._jit.lanes`). Where numba lacks the flag, :data:`NOALIAS` is
empty and those functions compile without it (the same numbers, slower). Drop when ``@njit`` takes
``noalias``.
"""

from __future__ import annotations


def noalias_option() -> dict:
    """``{"noalias": True}`` for ``njit``'s options once the CPU target takes it, else ``{}``."""
    try:
        from numba.core import cpu as _cpu
        from numba.core import options as _options

        if not hasattr(_cpu.CPUTargetOptions, "noalias"):
            _cpu.CPUTargetOptions.noalias = _options.TargetOptions.Mapping("noalias")
        return {"noalias": True}
    except (ImportError, AttributeError):  # pragma: no cover  (a numba without the flag)
        return {}


#: the options that mark a function's array arguments as not overlapping (empty: not available)
NOALIAS = noalias_option()
