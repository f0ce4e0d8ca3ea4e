"""Unscented transform pieces, batched: weights, robust matrix square roots, sigma points, weighted
means and covariances on spaces with angle components. Sigma points are one more array axis."""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np

from needlecli.numerics.angles import wrap_angle


@dataclass(frozen=True)
class MerweWeights:
    """Van der Merwe's scaled sigma-point weights for dimension ``n``."""

    n: int
    alpha: float = 1e-3
    beta: float = 2.0
    kappa: float = 0.0

    @property
    def lam(self) -> float:
        return self.alpha**2 * (self.n + self.kappa) - self.n

    @property
    def scale(self) -> float:
        """``n + lambda``: sigma points sit at ``x +- sqrt(scale P)`` columns."""
        return self.n + self.lam

    @property
    def wm(self) -> np.ndarray:
        w = np.full(2 * self.n + 1, 1.0 / (2.0 * self.scale))
        w[0] = self.lam / self.scale
        return w

    @property
    def wc(self) -> np.ndarray:
        w = self.wm.copy()
        w[0] += 1.0 - self.alpha**2 + self.beta
        return w


def symmetrize(p: np.ndarray) -> np.ndarray:
    return 0.5 * (p + np.swapaxes(p, -1, -2))


def robust_cholesky(p: np.ndarray, floor: float = 1e-12) -> tuple[np.ndarray, np.ndarray]:
    """Lower Cholesky factors of symmetric ``p (..., n, n)``, repairing the matrices where it fails.

    A failing matrix is symmetrised, its eigenvalues clipped at ``floor`` times its largest (at least
    ``floor``), rebuilt and factored again. Returns ``(L, repaired)`` with ``repaired (...)`` bool.
    """
    p = np.asarray(p, dtype=float)
    repaired = np.zeros(p.shape[:-2], dtype=bool)
    try:  # LAPACK reads the lower triangle only: the same factor as of the symmetrised matrix
        return np.linalg.cholesky(p), repaired
    except np.linalg.LinAlgError:
        pass
    p = symmetrize(p)
    w, v = np.linalg.eigh(p)
    top = np.maximum(np.max(np.abs(w), axis=-1, keepdims=True), 1.0) * floor
    ok = np.all(w > top, axis=-1) & np.all(np.isfinite(w), axis=-1)
    bad = ~ok
    w_fixed = np.where(np.isfinite(w), np.maximum(w, top), top)
    rebuilt = (v * w_fixed[..., None, :]) @ np.swapaxes(v, -1, -2)
    rebuilt = np.where(np.isfinite(rebuilt), rebuilt, 0.0) + np.where(
        np.isfinite(rebuilt).all(axis=(-1, -2), keepdims=True), 0.0, np.eye(p.shape[-1])
    )
    q = np.where(bad[..., None, None], symmetrize(rebuilt), p)
    try:
        return np.linalg.cholesky(q), bad
    except np.linalg.LinAlgError:
        # factor the rebuilt matrices the eigen way: any square root serves for sigma points
        w2, v2 = np.linalg.eigh(q)
        root = v2 * np.sqrt(np.maximum(w2, 0.0))[..., None, :]
        return root, bad


@functools.lru_cache(maxsize=64)
def _selection(mask: bytes) -> slice | np.ndarray | None:
    idx = np.flatnonzero(np.frombuffer(mask, dtype=bool))
    if idx.size == 0:
        return None
    if idx[-1] - idx[0] + 1 == idx.size:
        return slice(int(idx[0]), int(idx[-1]) + 1)
    return idx


def angle_selection(angles: np.ndarray) -> slice | np.ndarray | None:
    """The angle components of a mask ``(n,)`` as a slice when contiguous (cheaper than a boolean
    index), else their indices; None when there are none. Cached: masks repeat on hot paths."""
    return _selection(np.ascontiguousarray(angles, dtype=bool).tobytes())


def wrap_where_needed(d: np.ndarray, sel) -> float:
    """Wrap ``d[..., sel]`` in place; skipped (one cheap test) when every entry is inside (-pi, pi).
    Returns the largest magnitude of the (wrapped) entries."""
    sub = d[..., sel]
    if not sub.size:
        return 0.0
    big = float(np.max(np.abs(sub)))
    if big < np.pi:
        return big
    d[..., sel] = wrap_angle(sub)
    return np.pi


def residual(a: np.ndarray, b: np.ndarray, angles: np.ndarray) -> np.ndarray:
    """``a - b`` with the components flagged in ``angles (n,)`` wrapped to [-pi, pi)."""
    d = a - b
    sel = angle_selection(angles)
    if sel is not None:
        wrap_where_needed(d, sel)
    return d


def sigma_points(x: np.ndarray, root: np.ndarray, w: MerweWeights, angles: np.ndarray) -> np.ndarray:
    """``(..., 2n+1, n)`` sigma points around ``x (..., n)`` with ``root`` a square root of ``P``."""
    cols = np.sqrt(w.scale) * np.swapaxes(root, -1, -2)  # (..., n, n): row i = column i of sqrt(scale P)
    # angle components are not wrapped here: the models are periodic in them, and unwrapped points keep
    # their differences to the central point small (see weighted_mean)
    return np.concatenate([x[..., None, :], x[..., None, :] + cols, x[..., None, :] - cols], axis=-2)


def weighted_mean(pts: np.ndarray, wm: np.ndarray, angles: np.ndarray) -> np.ndarray:
    """Weighted mean over the sigma axis (-2); angle components averaged as residuals about the
    central point, so that points on both sides of +-pi average correctly."""
    return mean_and_residuals(pts, wm, angles, residuals=False)[0]


def mean_and_residuals(pts: np.ndarray, wm: np.ndarray, angles: np.ndarray, residuals: bool = True):
    """:func:`weighted_mean` and the residuals ``pts - mean`` ``(..., S, n)`` (angles wrapped) in one pass:
    the residuals about the central point, minus their weighted mean. Returns ``(mean, residuals)``."""
    ref = pts[..., 0, :]
    d = pts - ref[..., None, :]
    sel = angle_selection(angles)
    big = wrap_where_needed(d, sel) if sel is not None else 0.0
    shift = np.matmul(wm, d)
    m = ref + shift
    if sel is not None:
        wrap_where_needed(m, sel)
    if not residuals:
        return m, None
    d -= shift[..., None, :]
    # |d - shift| < pi where |d| + |shift| < pi: the common case needs no second pass over the points
    if sel is not None and big + float(np.max(np.abs(shift[..., sel]))) >= np.pi:
        wrap_where_needed(d, sel)
    return m, d


def weighted_cov(da: np.ndarray, db: np.ndarray, wc: np.ndarray) -> np.ndarray:
    """``sum_i wc_i da_i db_i^T`` over the sigma axis of residuals ``da (..., S, p)``, ``db (..., S, q)``."""
    return np.matmul(np.swapaxes(da * wc[:, None], -1, -2), db)
