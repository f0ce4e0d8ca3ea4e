"""Estimation errors for the summary tables, compiled: the rotation error between two orientations given
as Euler angles (``Rx(alpha) Ry(beta) Rz(gamma)``) without forming the ``(N, T, 3, 3)`` matrices, the
largest cost (time and memory) of ``needle evaluate`` on a thousand insertions.

The same formulas as :func:`needlecli.numerics.euler_xyz_to_matrix` and
:func:`needlecli.numerics.rotation_angle` (``atan2(|vee(M)|, clip((tr M - 1) / 2))`` of
``M = R_true^T R_est``), one element at a time.
"""

from __future__ import annotations

import math

import numpy as np

from needlecli.kernels._jit import jit
from needlecli.kernels._threads import blocks, parallel_for


@jit
def _euler(a, b, g, R):
    ca, sa = math.cos(a), math.sin(a)
    cb, sb = math.cos(b), math.sin(b)
    cg, sg = math.cos(g), math.sin(g)
    R[0, 0] = cb * cg
    R[0, 1] = -cb * sg
    R[0, 2] = sb
    R[1, 0] = ca * sg + sa * sb * cg
    R[1, 1] = ca * cg - sa * sb * sg
    R[1, 2] = -sa * cb
    R[2, 0] = sa * sg - ca * sb * cg
    R[2, 1] = sa * cg + ca * sb * sg
    R[2, 2] = ca * cb


@jit
def euler_error_angles(lo, hi, t_ang, e_ang, out):
    """``out[r, k]``: the angle (rad) of ``R(t_ang[r, k])^T R(e_ang[r, k])`` for runs ``lo..hi-1``;
    ``t_ang``, ``e_ang`` (N, T, 3) alpha, beta, gamma."""
    T = t_ang.shape[1]
    Rt = np.empty((3, 3))
    Re = np.empty((3, 3))
    M = np.empty((3, 3))
    for r in range(lo, hi):
        for k in range(T):
            _euler(t_ang[r, k, 0], t_ang[r, k, 1], t_ang[r, k, 2], Rt)
            _euler(e_ang[r, k, 0], e_ang[r, k, 1], e_ang[r, k, 2], Re)
            for i in range(3):
                for j in range(3):
                    M[i, j] = Rt[0, i] * Re[0, j] + Rt[1, i] * Re[1, j] + Rt[2, i] * Re[2, j]
            c = 0.5 * (((M[0, 0] + M[1, 1]) + M[2, 2]) - 1.0)
            v0 = 0.5 * (M[2, 1] - M[1, 2])
            v1 = 0.5 * (M[0, 2] - M[2, 0])
            v2 = 0.5 * (M[1, 0] - M[0, 1])
            s = math.sqrt(v0 * v0 + v1 * v1 + v2 * v2)
            out[r, k] = math.atan2(s, min(max(c, -1.0), 1.0))


def rotation_error(t_ang: np.ndarray, e_ang: np.ndarray) -> np.ndarray:
    """Rotation error angles ``(N, T)`` in rad from Euler angles ``(N, T, 3)`` of the truth and the
    estimate."""
    t_ang = np.ascontiguousarray(t_ang, dtype=float)
    e_ang = np.ascontiguousarray(e_ang, dtype=float)
    out = np.empty(t_ang.shape[:2])
    parallel_for(euler_error_angles, blocks(t_ang.shape[0], per_thread=4), (t_ang, e_ang, out))
    return out
