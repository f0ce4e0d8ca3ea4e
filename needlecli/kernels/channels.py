"""The measurement channels of the compiled filters as padded arrays (the UKF's and the particle filters'
kernels take the same Gaussian part of a channel: which states or components, angles, variances, gate,
noise growing with the distance to the transducer), the arrays of their estimates (states, and the
covariances in the problem's layout), and how every kernel takes an array (:func:`kernel_array`). No
numba here: the kernels' modules import it."""

from __future__ import annotations

from collections import namedtuple

import numpy as np


def kernel_array(a, dtype=None) -> np.ndarray:
    """``a`` as every kernel takes an array: C-contiguous and writeable, a copy only where ``a`` is not
    (a broadcast, a read-only view). numba types an argument by its layout and its flags, so an array
    made otherwise by a caller would compile a kernel again, mid-run; this way a kernel has one type per
    argument whatever the caller's shapes (np.ascontiguousarray keeps a read-only array read-only)."""
    return np.require(a, dtype=dtype, requirements=["C", "W"])


#: per channel ``c`` (rows ``(C,)`` or ``(C, m_max)``, at least one row): ``index`` the states (or
#: components) its samples read, ``angle`` which of them are angles, ``sig2`` the variances, ``gate`` the
#: chi-square threshold (NaN: none), ``growth``/``ga``/``gd``/``gtr`` the distance law of its noise (on,
#: slope, distance at which it stops growing, transducer position), ``pos`` the axis of each position column
#: (-1: none)
Gaussian = namedtuple("Gaussian", "index angle sig2 gate growth ga gd gtr pos")


def gaussian_part(chans: list[dict], index_key: str, unused_sig2: float) -> Gaussian:
    """The Gaussian part of the channels ``chans`` (the observers' channel records: ``m``, ``angle``,
    ``sigma``, ``gate``, ``growth``, ``pos_cols``, ``pos_axes`` and ``index_key``) as padded arrays of
    ``max(len(chans), 1)`` rows and ``m_max`` columns; unused variances are ``unused_sig2``."""
    rows = max(len(chans), 1)
    mmax = max([c["m"] for c in chans], default=1)
    out = Gaussian(np.zeros((rows, mmax), dtype=np.int64), np.zeros((rows, mmax), dtype=np.bool_),
                   np.full((rows, mmax), float(unused_sig2)), np.full(rows, np.nan), np.zeros(rows, dtype=np.bool_),
                   np.zeros(rows), np.ones(rows), np.zeros((rows, 3)), np.full((rows, mmax), -1, dtype=np.int64))
    for ci, c in enumerate(chans):
        m = c["m"]
        out.index[ci, :m] = c[index_key]
        out.angle[ci, :m] = c["angle"]
        out.sig2[ci, :m] = c["sigma"] ** 2
        if c["gate"] is not None:
            out.gate[ci] = c["gate"]
        g = c["growth"]
        if g is not None and c["pos_cols"]:
            out.growth[ci] = True
            out.ga[ci], out.gd[ci] = float(g.a), float(g.d_max)
            out.gtr[ci] = np.asarray(g.transducer, dtype=float)
            for col, ax in zip(c["pos_cols"], c["pos_axes"]):
                out.pos[ci, col] = ax
    return out


#: how a filter keeps its covariances (``problem.cov_layout``), as the kernels read it
LAYOUT_NONE, LAYOUT_DIAG, LAYOUT_FULL = 0, 1, 2
_LAYOUTS = {"none": LAYOUT_NONE, "diag": LAYOUT_DIAG, "full": LAYOUT_FULL}


def estimate_arrays(problem, N: int, T: int, n: int):
    """The arrays a compiled filter writes its estimates into: ``(states (N, T, n), layout, stride,
    cov_full, cov_diag)``, the covariances kept every ``stride`` steps in the problem's layout (the array
    of the other layout a placeholder of the same rank)."""
    layout = _LAYOUTS[problem.cov_layout]
    stride = int(problem.cov_stride)
    Tc = len(range(0, T, stride))
    cov_full = np.empty((N, Tc, n, n)) if layout == LAYOUT_FULL else np.empty((1, 1, 1, 1))
    cov_diag = np.empty((N, Tc, n)) if layout == LAYOUT_DIAG else np.empty((1, 1, 1))
    return np.empty((N, T, n)), layout, stride, cov_full, cov_diag


def kept_covariance(layout: int, cov_full: np.ndarray, cov_diag: np.ndarray) -> np.ndarray | None:
    """The covariances a filter kept (:func:`estimate_arrays`), None where it kept none."""
    return cov_full if layout == LAYOUT_FULL else cov_diag if layout == LAYOUT_DIAG else None
