"""Estimation errors for the summary tables, compiled, read straight from the state arrays (no column
copies, no temporaries of the size of the results): the position error norm, the wrapped errors of the
angles, the absolute errors of the other states (:func:`state_errors`), and the rotation error between two
orientations given as Euler angles (``Rx(alpha) Ry(beta) Rz(gamma)``) without forming the ``(N, T, 3, 3)``
matrices (:func:`rotation_error`). On a thousand insertions these were most of ``needle simulate``'s
summary (10 s: every quantity a few passes over 43 MB arrays, fresh memory each).

The same formulas as :mod:`needlecli.metrics.errors` (``scale * sqrt((d0^2 + d1^2) + d2^2)``, numpy's
``norm`` order; ``wrap_angle``; ``rad2deg`` as ``x * (180 / pi)``), so the errors equal the numpy path's
bit for bit; and as :func:`needlecli.numerics.euler_xyz_to_matrix` and
:func:`needlecli.numerics.rotation_angle` (``atan2(|vee(M)|, clip((tr M - 1) / 2))`` of
``M = R_true^T R_est``), within 1e-10 (sines and cosines to 1 ulp).
"""

from __future__ import annotations

import math

import numpy as np

from needlecli.kernels._jit import inline, jit
from needlecli.kernels._threads import blocks, parallel_for
from needlecli.kernels.channels import kernel_array
from needlecli.kernels.core import PI, SINCOS_MAX, TWO_PI, sincos

NORM, ANGLE, ABS = 0, 1, 2  # kinds of quantity of :func:`state_errors`
_RAD2DEG = 180.0 / math.pi


@jit
def _state_errors(lo, hi, ts, xs, keep, kinds, tcol, ecol, scale, out):
    """``out[q, i, k]`` for kept runs ``i`` in ``lo..hi-1`` (run ``keep[i]``) and every step ``k``."""
    Q = kinds.shape[0]
    T = ts.shape[1]
    for i in range(lo, hi):
        r = keep[i]
        for k in range(T):
            for q in range(Q):
                kd = kinds[q]
                if kd == NORM:
                    d0 = xs[r, k, ecol[q, 0]] - ts[r, k, tcol[q, 0]]
                    d1 = xs[r, k, ecol[q, 1]] - ts[r, k, tcol[q, 1]]
                    d2 = xs[r, k, ecol[q, 2]] - ts[r, k, tcol[q, 2]]
                    out[q, i, k] = scale[q] * math.sqrt((d0 * d0 + d1 * d1) + d2 * d2)
                elif kd == ANGLE:
                    d = xs[r, k, ecol[q, 0]] - ts[r, k, tcol[q, 0]]
                    w = d - TWO_PI * np.floor((d + PI) * (0.5 / PI))  # numerics.wrap_angle
                    w = max(w - TWO_PI if w >= PI else w, -PI)
                    out[q, i, k] = abs(w) * _RAD2DEG
                else:
                    out[q, i, k] = abs(xs[r, k, ecol[q, 0]] - ts[r, k, tcol[q, 0]])


def state_errors(ts: np.ndarray, xs: np.ndarray, keep: np.ndarray, quantities: list[tuple]) -> np.ndarray:
    """Errors ``(Q, len(keep), T)`` of the kept runs: ``quantities`` are ``(kind, truth columns, estimate
    columns, scale)``: :data:`NORM` (three columns each: ``scale`` times the norm of the difference),
    :data:`ANGLE` (one: the absolute wrapped difference in degrees), :data:`ABS` (one: the absolute
    difference)."""
    Q = len(quantities)
    kinds = np.array([q[0] for q in quantities], dtype=np.int64)
    tcol = np.zeros((Q, 3), dtype=np.int64)
    ecol = np.zeros((Q, 3), dtype=np.int64)
    for j, (_, tc, ec, _) in enumerate(quantities):
        tcol[j, : len(tc)] = tc
        ecol[j, : len(ec)] = ec
    scale = np.array([float(q[3]) for q in quantities])
    ts = ts if ts.flags.c_contiguous and ts.dtype == float else kernel_array(ts, dtype=float)
    xs = xs if xs.flags.c_contiguous and xs.dtype == float else kernel_array(xs, dtype=float)
    keep = kernel_array(keep, dtype=np.int64)
    out = np.empty((Q, keep.size, ts.shape[1]))
    parallel_for(_state_errors, blocks(keep.size, per_thread=4), (ts, xs, keep, kinds, tcol, ecol, scale, out))
    return out


@inline
def _sc(x):
    if abs(x) < SINCOS_MAX:
        return sincos(x)
    return math.sin(x), math.cos(x)


@inline
def _euler(a, b, g):
    """The entries of ``Rx(a) Ry(b) Rz(g)``, row by row."""
    sa, ca = _sc(a)
    sb, cb = _sc(b)
    sg, cg = _sc(g)
    return (cb * cg, -cb * sg, sb,
            ca * sg + sa * sb * cg, ca * cg - sa * sb * sg, -sa * cb,
            sa * sg - ca * sb * cg, sa * cg + ca * sb * sg, ca * cb)


@jit
def euler_error_angles(lo, hi, ts, xs, keep, tc, ec, out):
    """``out[i, k]``: the angle (rad) of ``R(t)^T R(e)`` for kept runs ``i`` in ``lo..hi-1`` (run
    ``keep[i]``); the angles alpha, beta, gamma are columns ``tc`` of ``ts`` and ``ec`` of ``xs``
    (``(N, T, n)`` state arrays)."""
    T = ts.shape[1]
    for i in range(lo, hi):
        r = keep[i]
        for k in range(T):
            a0, a1, a2, a3, a4, a5, a6, a7, a8 = _euler(ts[r, k, tc[0]], ts[r, k, tc[1]], ts[r, k, tc[2]])
            b0, b1, b2, b3, b4, b5, b6, b7, b8 = _euler(xs[r, k, ec[0]], xs[r, k, ec[1]], xs[r, k, ec[2]])
            # M = Rt^T Re: M[i, j] = Rt[0, i] Re[0, j] + Rt[1, i] Re[1, j] + Rt[2, i] Re[2, j]
            m00 = a0 * b0 + a3 * b3 + a6 * b6
            m11 = a1 * b1 + a4 * b4 + a7 * b7
            m22 = a2 * b2 + a5 * b5 + a8 * b8
            m21 = a2 * b1 + a5 * b4 + a8 * b7
            m12 = a1 * b2 + a4 * b5 + a7 * b8
            m02 = a0 * b2 + a3 * b5 + a6 * b8
            m20 = a2 * b0 + a5 * b3 + a8 * b6
            m10 = a1 * b0 + a4 * b3 + a7 * b6
            m01 = a0 * b1 + a3 * b4 + a6 * b7
            c = 0.5 * (((m00 + m11) + m22) - 1.0)
            v0 = 0.5 * (m21 - m12)
            v1 = 0.5 * (m02 - m20)
            v2 = 0.5 * (m10 - m01)
            s = math.sqrt(v0 * v0 + v1 * v1 + v2 * v2)
            out[i, k] = math.atan2(s, min(max(c, -1.0), 1.0))


def rotation_error(t_ang: np.ndarray, e_ang: np.ndarray, keep: np.ndarray | None = None,
                   t_cols=(0, 1, 2), e_cols=(0, 1, 2)) -> np.ndarray:
    """Rotation error angles ``(len(keep), T)`` in rad of the kept runs (default: all) from Euler angles:
    columns ``t_cols`` of the truth's ``(N, T, n)`` states and ``e_cols`` of the estimate's."""
    t_ang = t_ang if t_ang.flags.c_contiguous and t_ang.dtype == float else kernel_array(t_ang, dtype=float)
    e_ang = e_ang if e_ang.flags.c_contiguous and e_ang.dtype == float else kernel_array(e_ang, dtype=float)
    keep = np.arange(t_ang.shape[0]) if keep is None else kernel_array(keep, dtype=np.int64)
    out = np.empty((keep.size, t_ang.shape[1]))
    parallel_for(euler_error_angles, blocks(keep.size, per_thread=4),
                 (t_ang, e_ang, keep, np.asarray(t_cols, dtype=np.int64), np.asarray(e_cols, dtype=np.int64), out))
    return out
