"""Rotations: hat/vee, elementary rotations, the project's Euler convention, SO(3) exp/log/projection.

Convention (``MODELS.md``): ``R = Rx(alpha) Ry(beta) Rz(gamma)``; the needle tangent is ``R e3``.
All functions broadcast over leading axes and, where they are polynomial/trigonometric, accept complex
input so that complex-step Jacobians work through them.
"""

from __future__ import annotations

import numpy as np


def hat(w: np.ndarray) -> np.ndarray:
    """Skew matrix ``(..., 3, 3)`` of ``w (..., 3)`` so that ``hat(w) @ v = w x v``."""
    w = np.asarray(w)
    z = np.zeros_like(w[..., 0])
    return np.stack(
        [
            np.stack([z, -w[..., 2], w[..., 1]], -1),
            np.stack([w[..., 2], z, -w[..., 0]], -1),
            np.stack([-w[..., 1], w[..., 0], z], -1),
        ],
        -2,
    )


def vee(m: np.ndarray) -> np.ndarray:
    """Inverse of :func:`hat` (uses the skew part)."""
    m = np.asarray(m)
    return 0.5 * np.stack(
        [m[..., 2, 1] - m[..., 1, 2], m[..., 0, 2] - m[..., 2, 0], m[..., 1, 0] - m[..., 0, 1]], -1
    )


def _rot(c: np.ndarray, s: np.ndarray, axis: int) -> np.ndarray:
    o = np.ones_like(c)
    z = np.zeros_like(c)
    if axis == 0:
        rows = [[o, z, z], [z, c, -s], [z, s, c]]
    elif axis == 1:
        rows = [[c, z, s], [z, o, z], [-s, z, c]]
    else:
        rows = [[c, -s, z], [s, c, z], [z, z, o]]
    return np.stack([np.stack(r, -1) for r in rows], -2)


def rot_x(a: np.ndarray) -> np.ndarray:
    a = np.asarray(a)
    return _rot(np.cos(a), np.sin(a), 0)


def rot_y(a: np.ndarray) -> np.ndarray:
    a = np.asarray(a)
    return _rot(np.cos(a), np.sin(a), 1)


def rot_z(a: np.ndarray) -> np.ndarray:
    a = np.asarray(a)
    return _rot(np.cos(a), np.sin(a), 2)


def euler_xyz_to_matrix(alpha: np.ndarray, beta: np.ndarray, gamma: np.ndarray) -> np.ndarray:
    """``Rx(alpha) Ry(beta) Rz(gamma)`` in closed form, shape ``(..., 3, 3)``."""
    ca, sa = np.cos(alpha), np.sin(alpha)
    cb, sb = np.cos(beta), np.sin(beta)
    cg, sg = np.cos(gamma), np.sin(gamma)
    r = [
        [cb * cg, -cb * sg, sb],
        [ca * sg + sa * sb * cg, ca * cg - sa * sb * sg, -sa * cb],
        [sa * sg - ca * sb * cg, sa * cg + ca * sb * sg, ca * cb],
    ]
    return np.stack([np.stack(row, -1) for row in r], -2)


def matrix_to_euler_xyz(r: np.ndarray) -> np.ndarray:
    """Inverse of :func:`euler_xyz_to_matrix`: ``(..., 3)`` angles with beta in [-pi/2, pi/2]."""
    r = np.asarray(r, dtype=float)
    beta = np.arcsin(np.clip(r[..., 0, 2], -1.0, 1.0))
    alpha = np.arctan2(-r[..., 1, 2], r[..., 2, 2])
    gamma = np.arctan2(-r[..., 0, 1], r[..., 0, 0])
    return np.stack([alpha, beta, gamma], -1)


def so3_exp(w: np.ndarray) -> np.ndarray:
    """Rodrigues' formula: rotation matrix of the rotation vector ``w (..., 3)``."""
    w = np.asarray(w, dtype=float)
    th = np.linalg.norm(w, axis=-1)[..., None, None]
    k = hat(w)
    small = th < 1e-8
    ths = np.where(small, 1.0, th)
    a = np.where(small, 1.0 - th**2 / 6.0, np.sin(ths) / ths)
    b = np.where(small, 0.5 - th**2 / 24.0, (1.0 - np.cos(ths)) / ths**2)
    return np.eye(3) + a * k + b * (k @ k)


def rotation_angle(r: np.ndarray) -> np.ndarray:
    """Angle in [0, pi] of a rotation matrix (robust near 0 and pi)."""
    r = np.asarray(r, dtype=float)
    c = 0.5 * (np.trace(r, axis1=-2, axis2=-1) - 1.0)
    s = np.linalg.norm(vee(r), axis=-1)  # sin(angle)
    return np.arctan2(s, np.clip(c, -1.0, 1.0))


def so3_log(r: np.ndarray) -> np.ndarray:
    """Rotation vector ``(..., 3)`` of ``r``; angle in [0, pi]."""
    r = np.asarray(r, dtype=float)
    th = rotation_angle(r)
    v = vee(r)  # = sin(th) * axis
    near_pi = th > np.pi - 1e-4
    s = np.sin(th)
    ss = np.where(np.abs(s) < 1e-12, 1.0, s)
    small = th < 1e-8
    out = np.where(small[..., None], v, v * (th / ss)[..., None])
    if np.any(near_pi):
        # axis from the symmetric part: (R + R^T) / 2 - cos(th) I = (1 - cos th) a a^T (exact; R + I is not
        # symmetric away from th = pi and biased the axis by O(pi - th))
        b = 0.5 * (r + np.swapaxes(r, -1, -2)) - np.cos(th)[..., None, None] * np.eye(3)
        diag = np.diagonal(b, axis1=-2, axis2=-1)
        i = np.argmax(diag, axis=-1)
        col = np.take_along_axis(b, i[..., None, None], axis=-1)[..., 0]
        nrm = np.linalg.norm(col, axis=-1, keepdims=True)
        ax = col / np.where(nrm > 0, nrm, 1.0)  # zero only away from pi, where it is not used
        sign = np.where(np.sum(ax * v, axis=-1, keepdims=True) < 0, -1.0, 1.0)
        out = np.where(near_pi[..., None], sign * ax * th[..., None], out)
    return out


def project_to_so3(r: np.ndarray) -> np.ndarray:
    """Nearest rotation (polar factor) of ``r (..., 3, 3)`` by SVD, determinant +1."""
    u, _, vt = np.linalg.svd(np.asarray(r, dtype=float))
    d = np.sign(np.linalg.det(u @ vt))
    u = u.copy()
    u[..., :, 2] *= d[..., None]
    return u @ vt


def orthonormalize(r: np.ndarray) -> np.ndarray:
    """One Newton step toward the polar factor: ``1.5 R - 0.5 R R^T R`` (cheap, for near-rotations)."""
    return 1.5 * r - 0.5 * (r @ np.swapaxes(r, -1, -2) @ r)


def quaternion_to_matrix(q: np.ndarray) -> np.ndarray:
    """Rotation matrices ``(..., 3, 3)`` of unit quaternions ``q (..., 4)`` in the order ``(w, x, y, z)``
    (scalar first; normalised here, so a quaternion of any non-zero length gives its rotation)."""
    q = np.asarray(q, dtype=float)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    r = [
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ]
    return np.stack([np.stack(row, -1) for row in r], -2)


def matrix_to_quaternion(r: np.ndarray) -> np.ndarray:
    """Unit quaternions ``(..., 4)``, ``(w, x, y, z)`` with ``w >= 0``, of rotation matrices ``(..., 3, 3)``
    (Shepperd's method: the largest of ``w, x, y, z`` is computed first, stable for every angle)."""
    r = np.asarray(r, dtype=float)
    t = np.trace(r, axis1=-2, axis2=-1)
    d = np.diagonal(r, axis1=-2, axis2=-1)
    cand = np.stack([t, d[..., 0], d[..., 1], d[..., 2]], -1)  # 4 w^2 - 1 + ..., one per component
    k = np.argmax(cand, axis=-1)
    s = {}
    s[0] = np.sqrt(np.maximum(1.0 + t, 0.0)) * 2.0
    s[1] = np.sqrt(np.maximum(1.0 + 2 * d[..., 0] - t, 0.0)) * 2.0
    s[2] = np.sqrt(np.maximum(1.0 + 2 * d[..., 1] - t, 0.0)) * 2.0
    s[3] = np.sqrt(np.maximum(1.0 + 2 * d[..., 2] - t, 0.0)) * 2.0
    with np.errstate(all="ignore"):
        rows = {
            0: (0.25 * s[0], (r[..., 2, 1] - r[..., 1, 2]) / s[0], (r[..., 0, 2] - r[..., 2, 0]) / s[0],
                (r[..., 1, 0] - r[..., 0, 1]) / s[0]),
            1: ((r[..., 2, 1] - r[..., 1, 2]) / s[1], 0.25 * s[1], (r[..., 0, 1] + r[..., 1, 0]) / s[1],
                (r[..., 0, 2] + r[..., 2, 0]) / s[1]),
            2: ((r[..., 0, 2] - r[..., 2, 0]) / s[2], (r[..., 0, 1] + r[..., 1, 0]) / s[2], 0.25 * s[2],
                (r[..., 1, 2] + r[..., 2, 1]) / s[2]),
            3: ((r[..., 1, 0] - r[..., 0, 1]) / s[3], (r[..., 0, 2] + r[..., 2, 0]) / s[3],
                (r[..., 1, 2] + r[..., 2, 1]) / s[3], 0.25 * s[3]),
        }
    q = np.stack(rows[0], -1)
    for i in (1, 2, 3):
        q = np.where((k == i)[..., None], np.stack(rows[i], -1), q)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    return np.where(q[..., :1] < 0, -q, q)
