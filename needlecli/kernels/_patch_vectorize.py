"""numba patch: LLVM's SLP vectoriser on, and full-width (512-bit) vectors where the CPU has AVX-512.

Process-wide settings of numba's code generator, made when :mod:`needlecli.kernels._jit` is imported (before
the first compilation or cache load of the process); neither changes a number (they pack operations into
vector instructions, they do not reorder them: no fastmath).

* **SLP vectoriser.** numba switched it off by default after miscompilations were reported with the LLVM
  of the time (numba/numba#8852, xref numba/numba#8705, numba/numba#8681). The kernels keep a few
  independent sums in registers (the lanes of the Kalman passes) that it turns into vector operations:
  twice the speed. The kernels' agreement tests (``tests/test_twins.py``) run with it on. Drop when numba
  turns it on again by default (``numba.config.SLP_VECTORIZE``).
* **512-bit vectors.** LLVM's tuning for recent Intel cores prefers 256-bit vectors even where AVX-512 is
  there, a hedge against the clock drop of older AVX-512 parts (https://reviews.llvm.org/D67259;
  llvm/llvm-project#47680 keeps it); numba has no per-function vector width, only ``NUMBA_CPU_FEATURES``
  (numba/numba#5757 sets ``-prefer-256-bit`` the same way in its tests). The kernels' loops over 8 or 16
  lanes run 1.3-1.4x faster at full width (``benchmarks/bench_kernels.py``). An explicit
  ``NUMBA_CPU_FEATURES`` (or ``NUMBA_DISABLE_AVX``) wins. Drop when LLVM prefers 512-bit vectors on the
  host CPU, or numba lets a function ask for them.
"""

from __future__ import annotations

import numba


def slp_vectorize() -> None:
    """LLVM's SLP vectoriser, for compilations from here on."""
    numba.config.SLP_VECTORIZE = 1


def full_width_vectors() -> None:
    """Let LLVM use 512-bit vectors where the CPU has them (AVX-512), unless the user set the CPU features."""
    if numba.config.CPU_FEATURES is not None or not numba.config.ENABLE_AVX:
        return
    try:
        import llvmlite.binding as ll

        features = ll.get_host_cpu_features()
    except (RuntimeError, ImportError):  # pragma: no cover
        return
    if features.get("avx512f"):
        numba.config.CPU_FEATURES = features.flatten() + ",-prefer-256-bit"


slp_vectorize()
full_width_vectors()
