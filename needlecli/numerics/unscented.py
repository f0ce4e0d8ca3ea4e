"""Unscented transform pieces, batched: weights, robust matrix square roots, sigma points, weighted
means and covariances on spaces with angle components. Sigma points are one more array axis."""

from __future__ import annotations

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
    p = symmetrize(np.asarray(p, dtype=float))
    repaired = np.zeros(p.shape[:-2], dtype=bool)
    try:
        return np.linalg.cholesky(p), repaired
    except np.linalg.LinAlgError:
        pass
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


def _select(angles: np.ndarray) -> slice | np.ndarray | None:
    """The angle components as a slice when contiguous (cheaper than a boolean index), else the mask;
    None when there are none."""
    idx = np.flatnonzero(angles)
    if idx.size == 0:
        return None
    if idx[-1] - idx[0] + 1 == idx.size:
        return slice(int(idx[0]), int(idx[-1]) + 1)
    return idx


def _wrap_where_needed(d: np.ndarray, sel) -> None:
    """Wrap ``d[..., sel]`` in place; skipped (one cheap test) when every entry is inside [-pi, pi)."""
    sub = d[..., sel]
    if sub.size and not (np.max(sub) < np.pi and np.min(sub) >= -np.pi):
        d[..., sel] = wrap_angle(sub)


def residual(a: np.ndarray, b: np.ndarray, angles: np.ndarray) -> np.ndarray:
    """``a - b`` with the components flagged in ``angles (n,)`` wrapped to [-pi, pi)."""
    d = a - b
    sel = _select(angles)
    if sel is not None:
        _wrap_where_needed(d, sel)
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
    ref = pts[..., 0, :]
    d = residual(pts, ref[..., None, :], angles)
    m = ref + np.matmul(wm, d)
    sel = _select(angles)
    if sel is not None:
        _wrap_where_needed(m, sel)
    return m


def weighted_cov(da: np.ndarray, db: np.ndarray, wc: np.ndarray) -> np.ndarray:
    """``sum_i wc_i da_i db_i^T`` over the sigma axis of residuals ``da (..., S, p)``, ``db (..., S, q)``."""
    return np.matmul(np.swapaxes(da * wc[:, None], -1, -2), db)
