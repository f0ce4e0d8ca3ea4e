"""Runs spread over the cores by Python threads calling compiled kernels that release the GIL.

numba's own ``parallel=True`` would do the same with less code, but its parallel-loop compilation costs
about 10 s per kernel on a cold cache (half the first-run budget) and its static schedule waits for a
core another process has taken; threads pulling blocks of runs from a queue keep both cores busy on a
shared machine, and leave the main thread free to draw the progress bar.
"""

from __future__ import annotations

import os
import threading
from collections.abc import Callable, Sequence

from needlecli import platform


def n_threads() -> int:
    """Worker threads: ``NEEDLECLI_THREADS``, else ``NUMBA_NUM_THREADS``, else the usable cores."""
    for var in ("NEEDLECLI_THREADS", "NUMBA_NUM_THREADS"):
        v = os.environ.get(var, "").strip()
        if v.isdigit() and int(v) > 0:
            return int(v)
    return platform.usable_cores()


_FORCED: list[int] = []


def set_threads(n: int | None) -> None:
    """Process-wide number of kernel threads (None: back to :func:`n_threads`); e.g. 1 in each of several
    processes that already share the cores."""
    _FORCED[:] = [] if n is None else [max(1, int(n))]


def threads() -> int:
    return _FORCED[0] if _FORCED else n_threads()


def blocks(n: int, per_thread: int = 8, minimum: int = 1) -> list[tuple[int, int]]:
    """``[lo, hi)`` ranges covering ``0..n``: about ``per_thread`` blocks per worker, so that a worker whose
    core is taken by another process holds up little at the end."""
    t = threads()
    size = max(minimum, -(-n // max(1, t * per_thread)))
    size = -(-size // minimum) * minimum  # whole multiples of ``minimum`` (lanes of a block kernel)
    return [(lo, min(n, lo + size)) for lo in range(0, n, size)]


def parallel_for(fn: Callable, ranges: Sequence[tuple[int, int]], args: tuple,
                 poll: Callable[[], None] | None = None) -> None:
    """``fn(lo, hi, *args)`` for every range, on :func:`threads` workers pulling ranges in order; ``poll()``
    is called about ten times a second on the calling thread while they work (a progress bar)."""
    t = min(threads(), len(ranges))
    if t <= 1 and poll is None:
        for lo, hi in ranges:
            fn(lo, hi, *args)
        return
    lock = threading.Lock()
    nxt = [0]
    err: list[BaseException] = []

    def work():
        try:
            while not err:
                with lock:
                    i = nxt[0]
                    nxt[0] += 1
                if i >= len(ranges):
                    return
                lo, hi = ranges[i]
                fn(lo, hi, *args)
        except BaseException as e:  # noqa: BLE001  (re-raised on the calling thread)
            err.append(e)

    workers = [threading.Thread(target=work, daemon=True) for _ in range(max(t, 1))]
    for w in workers:
        w.start()
    for w in workers:
        while w.is_alive():
            w.join(0.1)
            if poll is not None:
                poll()
    if err:
        raise err[0]
    if poll is not None:
        poll()
