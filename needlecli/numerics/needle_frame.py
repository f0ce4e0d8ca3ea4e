r"""Coordinates aligned with the needle: along its tangent, and two directions across it.

A 2D transverse ultrasound images the needle's cross section in a plane that runs a few millimetres
ahead of or behind the tip: across the needle it locates the shaft to about a millimetre, along the
needle its error is wherever the image plane happens to be. Its noise is therefore a covariance in the
needle's own frame, ``R_world = F R_n F^T`` with ``F`` the basis below at the needle's tangent, not a
diagonal in world axes. Filters (``frame: needle`` on a position channel) and EM (its ``R`` fitted in
these coordinates) share these functions, so that the components mean the same in a fit file and in the
observer that takes it.

The basis at a unit tangent ``t``: ``F = [t, e1, e2]`` (columns), ``e1 = a x t / |a x t|``,
``e2 = t x e1``, with ``a`` one world axis for the whole channel (``across_axis``; by default the one
least aligned with the needle's initial tangent). For a needle along ``+z`` and ``a = x``: ``e1 = -y``,
``e2 = x``.
"""

from __future__ import annotations

import numpy as np

AXES = ("x", "y", "z")


def reference_axis(tangent: np.ndarray) -> int:
    """The world axis least aligned with the tangents ``(..., 3)`` (mean absolute cosine; ties: the lower
    index): the reference ``a`` of :func:`needle_basis` that stays far from parallel to the needle."""
    t = np.asarray(tangent, dtype=float).reshape(-1, 3)
    with np.errstate(invalid="ignore"):
        mean = np.nanmean(np.abs(t), axis=0) if np.isfinite(t).any() else np.ones(3)
    return int(np.argmin(np.nan_to_num(mean, nan=1.0)))


def needle_basis(tangent: np.ndarray, axis: int) -> np.ndarray:
    """Orthonormal bases ``(..., 3, 3)``, columns ``(t, e1, e2)``, at tangents ``(..., 3)`` (normalised
    here). ``axis``: the reference world axis (0, 1, 2)."""
    t = np.asarray(tangent, dtype=float)
    t = t / np.linalg.norm(t, axis=-1, keepdims=True)
    a = np.zeros(3)
    a[axis] = 1.0
    e1 = np.cross(a, t)
    e1 = e1 / np.linalg.norm(e1, axis=-1, keepdims=True)
    e2 = np.cross(t, e1)
    return np.stack([t, e1, e2], -1)


def world_covariance(basis: np.ndarray, cov_needle: np.ndarray) -> np.ndarray:
    """``F R_n F^T`` ``(..., 3, 3)`` for bases ``(..., 3, 3)`` and a covariance in needle coordinates
    ``(3, 3)`` or ``(..., 3, 3)`` (a vector ``(3,)`` is a diagonal of variances)."""
    R = np.asarray(cov_needle, dtype=float)
    if R.ndim == 1:
        R = np.diag(R)
    return basis @ R @ np.swapaxes(basis, -1, -2)


def to_needle(basis: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Components ``(..., 3)`` of world vectors ``v (..., 3)`` along ``(t, e1, e2)``: ``F^T v``."""
    return np.einsum("...ji,...j->...i", basis, v)


def block_noise(blocks: list[np.ndarray]) -> np.ndarray:
    """Block-diagonal noise ``(N, M, M)`` from per-channel blocks: variances ``(N, m)`` (a diagonal) or
    covariances ``(N, m, m)``."""
    N = blocks[0].shape[0]
    sizes = [b.shape[1] for b in blocks]
    out = np.zeros((N, sum(sizes), sum(sizes)))
    a = 0
    for b, m in zip(blocks, sizes):
        sl = slice(a, a + m)
        if b.ndim == 3:
            out[:, sl, sl] = b
        else:
            out[:, np.arange(a, a + m), np.arange(a, a + m)] = b
        a += m
    return out
