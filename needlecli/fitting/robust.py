r"""Outlier-robust EM: Student-t measurement noise by iteratively reweighted EM.

A channel with heavy outliers (a 2D ultrasound that locks onto a reflection) pulls EM's Gaussian ``R``
up and the smoothed trajectory toward the outliers. With Student-t noise of ``nu`` degrees of freedom,
``v_i = e_i / sqrt(w_i)``, ``e_i ~ N(0, R)``, ``w_i ~ Gamma(nu/2, nu/2)``, the scale ``w_i`` of every
sample is one more latent variable (Lange, Little and Taylor 1989; for state-space models e.g. Roth,
Ozkan and Gustafsson 2013). Its E-step is closed form,

.. math::

    E[w_i] = \frac{\nu + m}{\nu + \delta_i^2},\qquad
    \delta_i^2 = \operatorname{tr}\big(R^{-1} (r_i r_i^T + H_i P_i H_i^T)\big),\quad
    r_i = y_i - H_i m_i - d_i

with the smoothed mean ``m_i`` and covariance ``P_i`` at the sample; given the weights, a sample is a
Gaussian measurement with noise ``R / w_i`` (:class:`~needlecli.fitting.statespace.MeasurementModel`'s
``weight``: ``y``, ``h`` and ``H`` scaled by ``sqrt(w_i)``), and the closed-form M-step for ``R`` becomes
``R = (1/M) sum_i w_i (r_i r_i^T + H_i P_i H_i^T)``, the weighted covariance. :func:`fit_em_robust`
alternates the two: EM of :func:`~needlecli.fitting.em.fit_em` with the weights held (the trajectory, Q,
R and the constants), then the weights' E-step from its smoothed trajectory, warm-started, until no
weight moved by more than ``tol`` and no R_j by more than EM's own ``tol`` (relative) in the last pass:
a generalised EM of the Student-t model (each pass raises its likelihood). ``nu`` is fixed (small:
heavy tails; large: Gaussian). Started from the Gaussian fit, R falls by a roughly constant factor per
pass: tens of passes, each a few warm-started EM iterations.

The log-likelihoods the inner EM records are those of the Gaussian model with the weights held (each
sample's ``R / w_i``), up to the constant ``sum_i (m/2) log w_i`` of the scaling; compare them within
one weighting only.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from needlecli.fitting.em import EMOptions, EMResult, fit_em, relative_change
from needlecli.fitting.statespace import DiscreteModel, MeasurementModel
from needlecli.numerics import wrap_angle


@dataclass
class RobustInfo:
    """The robust weighting of a fit: per channel the final weights ``(N, M)`` (None for a Gaussian
    channel; 1 where a sample is not valid), the degrees of freedom, and per trial the reweighting passes
    and the largest weight change of the last one."""

    weights: list[np.ndarray | None]
    dof: list[float | None]
    passes: np.ndarray
    last_change: np.ndarray


def sample_weights(mm: MeasurementModel, m: np.ndarray, P: np.ndarray, R: np.ndarray, dof: float) -> np.ndarray:
    """``E[w_i]`` ``(N, M)`` of every sample of channel ``mm`` from the smoothed means ``m (N, K+1, n)``,
    covariances ``P (N, K+1, n, n)`` and the channel's ``R (N, m, m)`` (module docstring)."""
    base = dataclasses.replace(mm, weight=None)
    z = m[:, mm.tick]
    Pk = P[:, mm.tick]
    with np.errstate(all="ignore"):
        _, H, d, y = base.linearise(z)
        r = y - (H @ z[..., None])[..., 0] - d
        if not (mm.tangent or mm.frame == "needle") and mm.angle.any():
            r[..., mm.angle] = wrap_angle(r[..., mm.angle])
        S = r[..., :, None] * r[..., None, :] + H @ Pk @ np.swapaxes(H, -1, -2)
        Ri = np.linalg.inv(R)[:, None]
        delta2 = np.einsum("nkij,nkji->nk", Ri, S)
        w = (dof + mm.m) / (dof + delta2)
    return np.where(mm.valid & np.isfinite(w), w, 1.0)


def fit_em_robust(
    dm: DiscreteModel,
    meas: Sequence[MeasurementModel],
    m0: np.ndarray,
    P0: np.ndarray,
    Q0: np.ndarray,
    R0: Sequence[np.ndarray],
    options: EMOptions,
    dof: Sequence[float | None],
    *,
    max_passes: int = 50,
    tol: float = 0.01,
    progress: Callable[[int, int], None] | None = None,
) -> tuple[EMResult, RobustInfo, list[MeasurementModel]]:
    """EM with Student-t noise on the channels whose ``dof`` is set (module docstring). Returns the
    result, the weighting and the channels with their final weights (what the fit's identifiability
    assesses).

    The first pass is the Gaussian EM; each further pass holds the weights from the previous one's
    smoothed trajectory and starts EM from its fit (Q, R, x0). Trials that failed (singular, diverged)
    keep the pass they failed in. ``iterations`` and ``estep_passes`` of the result count every pass;
    ``ekf`` is the plain EKF before any fitting; the history is the last pass's.
    """
    meas = list(meas)
    N = m0.shape[0]
    res = fit_em(dm, meas, m0, P0, Q0, R0, options, progress=progress)
    res.status, res.reason = res.status.astype(object), res.reason.astype(object)  # strings of any length
    robust = [j for j, nu in enumerate(dof) if nu is not None]
    weights: list[np.ndarray | None] = [np.ones(mm.valid.shape) if j in robust else None for j, mm in enumerate(meas)]
    passes = np.ones(N, dtype=np.int64)
    last = np.full(N, np.inf if robust else 0.0)
    going = np.isin(res.status, ("ok", "max_iter")) & bool(robust)
    P0 = np.broadcast_to(P0, (N,) + np.shape(P0)[-2:])
    cur = meas
    for _ in range(max_passes - 1):
        idx = np.nonzero(going)[0]
        if not idx.size:
            break
        change = np.zeros(idx.size)
        for j in robust:
            w = sample_weights(meas[j].take(idx), res.m[idx], res.P[idx], res.R[j][idx], float(dof[j]))
            change = np.maximum(change, np.abs(w - weights[j][idx]).max(-1))
            weights[j][idx] = w
        last[idx] = change
        cur = [dataclasses.replace(mm, weight=weights[j]) if j in robust else mm for j, mm in enumerate(meas)]
        before = [r[idx].copy() for r in res.R]
        sub = fit_em(dm.take(idx), [mm.take(idx) for mm in cur], res.x0[idx], P0[idx], res.Qc[idx],
                     [r[idx] for r in res.R], options, progress=progress)
        _merge(res, sub, idx)
        passes[idx] += 1
        moved = np.max([relative_change(res.R[j][idx], before[j]) for j in robust], axis=0)
        going[idx] = ((change >= tol) | (moved >= options.tol)) & np.isin(sub.status, ("ok", "max_iter"))
    cur = [dataclasses.replace(mm, weight=weights[j]) if j in robust else mm for j, mm in enumerate(meas)]
    res.status, res.reason = res.status.astype(str), res.reason.astype(str)
    return res, RobustInfo(weights, list(dof), passes, last), cur


def _merge(full: EMResult, part: EMResult, idx: np.ndarray) -> None:
    """Write the trials ``idx`` of a further pass into the result of all trials (counts accumulate)."""
    for name in ("Qc", "x0", "m", "P", "filtered", "status", "reason"):
        getattr(full, name)[idx] = getattr(part, name)
    full.ll_worst_drop[idx] = np.maximum(full.ll_worst_drop[idx], part.ll_worst_drop)
    for name in ("iterations", "estep_passes", "ll_decreases", "floor_hits", "repairs", "extrapolations", "rejections"):
        a, b = getattr(full, name), getattr(part, name)
        if a is not None and b is not None:
            a[idx] += b
    for j, r in enumerate(part.R):
        full.R[j][idx] = r
    for k, v in part.history.items():
        if k in full.history:
            full.history[k][idx] = v
