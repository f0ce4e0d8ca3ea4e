r"""EKF, extended Kalman (RTS) smoother and the iterated EKS of the magnetic needle EM paper (sec. 2.2, Algorithm 1).

* :func:`ekf` linearises at its own estimate as it goes (the transition's exact RK4 Jacobian, the
  measurement Jacobian by central differences at the predicted state).
* :func:`eks` is the EKF followed by the RTS smoother on the EKF's linearisation.
* :func:`ieks` re-linearises the dynamics and every measurement model around the previous smoothed
  trajectory (Bell 1994: a Gauss-Newton step on the MAP trajectory) and, as in the magnetic needle EM paper's Algorithm 1,
  moves the prior mean to the smoothed initial state, ``x0 <- x_0|N``, until both settle.

All work on every run at once; the re-linearisation is computed for all ticks in one batched call.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from needlecli.fitting.statespace import DiscreteModel, MeasurementModel
from needlecli.numerics.kalman import (
    ForwardResult,
    SmoothResult,
    kalman_filter_smoother,
    kalman_forward,
    kalman_loglik_affine,
    rts_smoother,
)


@dataclass
class Linearisation:
    """The affine model of one IEKS pass: ``z_{k+1} = A_k z_k + b_k + w_k``, ``y_j ~ H_j z + d_j``.

    A (N, K, n, n), b (N, K, n); H[j] (N, M_j, m_j, n), d[j] (N, M_j, m_j), y[j] (N, M_j, m_j).
    """

    A: np.ndarray
    b: np.ndarray
    H: list[np.ndarray]
    d: list[np.ndarray]
    y: list[np.ndarray]  # the measurements in the coordinates of H (tangent planes for directions)


@dataclass
class SmootherResult:
    """One filter + smoother pass and the linearisation it used (None for the plain EKS)."""

    fwd: ForwardResult
    sm: SmoothResult
    lin: Linearisation


def _channels(meas: Sequence[MeasurementModel], R: Sequence[np.ndarray], ys=None):
    if ys is None:  # shapes only: the EKF's callback gives the measured values
        ys = [np.zeros(mm.valid.shape + (mm.m,)) for mm in meas]
    return [mm.channel(r, y) for mm, r, y in zip(meas, R, ys)]


def ekf(
    dm: DiscreteModel,
    meas: Sequence[MeasurementModel],
    m0: np.ndarray,
    P0: np.ndarray,
    Qc: np.ndarray,
    R: Sequence[np.ndarray],
    progress: Callable[[int, int], None] | None = None,
) -> ForwardResult:
    """Extended Kalman filter over the ticks of ``dm`` (all runs at once)."""

    def transition(k, m):
        return dm.transition(k, m)

    def measure(j, i, m):
        mm = meas[j]
        y = np.where(mm.valid[:, i, None], mm.y[:, i], 0.0)
        yh, H, _, yo = mm.linearise(m, y, sample=i)
        return yh, H, yo

    return kalman_forward(m0, P0, Qc, dm.dt, transition, measure, _channels(meas, R),
                          state_angles=dm.angles, progress=progress)


def eks(dm, meas, m0, P0, Qc, R, progress=None) -> SmootherResult:
    """EKF then the RTS smoother on the EKF's Jacobians. The returned linearisation is the one the
    filter used (transition Jacobians at the filtered means, measurements at the predicted ones)."""
    fwd = ekf(dm, meas, m0, P0, Qc, R, progress=progress)
    sm = rts_smoother(fwd, state_angles=dm.angles, kernels=dm.kernels)
    # the affine model of this pass, for the M-step: around the filter's own estimates
    fz, _ = _transition_means(dm, fwd.m_filt[:, :-1])
    b = fz - (fwd.A @ fwd.m_filt[:, :-1, :, None])[..., 0]
    H, d, y = [], [], []
    for mm in meas:
        _, Hj, dj, yj = mm.linearise(fwd.m_pred[:, mm.tick])
        H.append(Hj)
        d.append(dj)
        y.append(yj)
    return SmootherResult(fwd, sm, Linearisation(fwd.A, b, H, d, y))


def _transition_means(dm: DiscreteModel, z: np.ndarray):
    with np.errstate(all="ignore"):
        return dm.transition_all(z)


def linearise(dm: DiscreteModel, meas: Sequence[MeasurementModel], zbar: np.ndarray) -> Linearisation:
    """The affine model around a trajectory ``zbar (N, K+1, n)`` for all ticks at once."""
    with np.errstate(all="ignore"):
        fz, A = dm.transition_all(zbar[:, :-1])
        b = fz - (A @ zbar[:, :-1, :, None])[..., 0]
        H, d, y = [], [], []
        for mm in meas:
            _, Hj, dj, yj = mm.linearise(zbar[:, mm.tick])
            H.append(Hj)
            d.append(dj)
            y.append(yj)
    return Linearisation(A, b, H, d, y)


def affine_pass(
    lin: Linearisation,
    dm: DiscreteModel,
    meas: Sequence[MeasurementModel],
    m0: np.ndarray,
    P0: np.ndarray,
    Qc: np.ndarray,
    R: Sequence[np.ndarray],
    joseph: bool = True,
) -> SmootherResult:
    """Kalman filter and RTS smoother on a fixed affine model."""
    A, b = lin.A, lin.b
    if not joseph:  # compiled: without the filter's covariances and the smoother's gains (EM reads neither)
        fwd, sm = kalman_filter_smoother(m0, P0, Qc, dm.dt, A, b, _channels(meas, R, lin.y), lin.H, lin.d,
                                         state_angles=dm.angles, kernels=dm.kernels)
        return SmootherResult(fwd, sm, lin)

    def transition(k, m):
        Ak = A[:, k]
        return (Ak @ m[..., None])[..., 0] + b[:, k], Ak

    def measure(j, i, m):
        Hji = lin.H[j][:, i]
        return (Hji @ m[..., None])[..., 0] + lin.d[j][:, i], Hji

    fwd = kalman_forward(m0, P0, Qc, dm.dt, transition, measure, _channels(meas, R, lin.y),
                         state_angles=dm.angles, joseph=joseph)
    sm = rts_smoother(fwd, state_angles=dm.angles, kernels=dm.kernels)
    return SmootherResult(fwd, sm, lin)


def take_linearisation(lin: Linearisation, idx: np.ndarray) -> Linearisation:
    """The linearisation of the runs ``idx`` only."""
    return Linearisation(lin.A[idx], lin.b[idx], [h[idx] for h in lin.H], [d[idx] for d in lin.d],
                         [y[idx] for y in lin.y])


def affine_loglik(lin: Linearisation, dm: DiscreteModel, meas: Sequence[MeasurementModel], m0: np.ndarray,
                  P0: np.ndarray, Qc: np.ndarray, R: Sequence[np.ndarray], rows: np.ndarray | None = None) -> np.ndarray:
    """The log-likelihood ``(N,)`` of the measurements under a fixed affine model (the forward pass of
    :func:`affine_pass` only: compiled where the kernels cover it). ``rows (N,)``: point r on trial
    ``rows[r]`` of ``lin`` and ``meas`` (``m0, P0, Qc, R``: one row per point), the same numbers as
    :func:`take_linearisation` and ``take`` of those rows."""
    return kalman_loglik_affine(m0, P0, Qc, dm.dt, lin.A, lin.b, _channels(meas, R, lin.y), lin.H, lin.d,
                                state_angles=dm.angles, rows=rows, kernels=dm.kernels)


@dataclass
class IEKSResult:
    """Final pass, the prior mean it settled on, and per run: filter-smoother passes run, iterations to
    the fixed point (passes whose result changed something: a pass that only confirms the previous one
    is not counted, so a linear model settles in 1) and whether it settled within ``max_iter`` passes."""

    result: SmootherResult
    m0: np.ndarray
    passes: np.ndarray  # (N,)
    settled: np.ndarray  # (N,) bool
    ekf: np.ndarray | None = None  # (N, K+1, n) filtered means of the first (plain EKF) pass, if one ran
    lin_point: np.ndarray | None = None  # (N, K+1, n) the trajectory the final pass was linearised around

    @property
    def iterations(self) -> np.ndarray:
        return self.passes - self.settled


def change(new: np.ndarray, old: np.ndarray, scale: np.ndarray) -> np.ndarray:
    """Largest change per run, in units of ``scale`` (a std per state), over all but the run axis."""
    d = np.abs(new - old) / scale
    return np.where(np.isfinite(d), d, np.inf).reshape(d.shape[0], -1).max(-1)


def ieks(
    dm: DiscreteModel,
    meas: Sequence[MeasurementModel],
    m0: np.ndarray,
    P0: np.ndarray,
    Qc: np.ndarray,
    R: Sequence[np.ndarray],
    *,
    zbar: np.ndarray | None = None,
    lin: Linearisation | None = None,
    lin_point: np.ndarray | None = None,
    max_iter: int = 10,
    tol: float = 1e-3,
    update_x0: bool = True,
    joseph: bool = True,
) -> IEKSResult:
    r"""Iterated extended Kalman smoother (the magnetic needle EM paper, Algorithm 1, lines 3-7).

    Each pass linearises around the previous smoothed trajectory ``zbar`` (the EKS for the first pass if
    ``zbar`` is None), filters and smooths; with ``update_x0`` the prior mean becomes the smoothed initial
    state. A run has settled when neither ``x0`` nor the trajectory moved by more than ``tol`` prior
    (resp. smoothed) standard deviations in any state. Runs that settled are not computed again.

    Parameters
    ----------
    m0 : (N, n), P0 : (N, n, n); Qc : (N, n, n); R : per channel (N, m, m)
    zbar : (N, K+1, n) trajectory to linearise around first
    lin, lin_point : a linearisation the caller has and the trajectory it was made around (EM: when the
        trajectory has barely moved since); the first pass then reuses it. A pass has settled when its
        smoothed trajectory is within ``tol`` of the trajectory it was linearised around (the fixed point)
    joseph : Joseph-form covariance updates in the affine passes (else the symmetrised standard form)
    """
    N = m0.shape[0]
    m0 = np.array(m0, dtype=float)
    P0 = np.broadcast_to(P0, (N,) + P0.shape[-2:])
    sd0 = np.sqrt(np.maximum(np.diagonal(P0, axis1=-2, axis2=-1), 1e-300))
    passes = np.zeros(N, dtype=np.int64)
    settled = np.zeros(N, dtype=bool)
    ekf_m = None
    if zbar is None:
        res = eks(dm, meas, m0, P0, Qc, R)
        ekf_m = res.fwd.m_filt
        passes += 1
        zbar_new = res.sm.m
        if update_x0:
            m0_new = res.sm.m[:, 0]
            settled = change(m0_new, m0, sd0) < tol
            m0 = m0_new
        if max_iter <= 1:
            return IEKSResult(res, m0, passes, settled, ekf_m, res.fwd.m_filt)
        zbar = zbar_new
        settled[:] = False  # the EKS linearisation is not the fixed point: always one affine pass
    out: SmootherResult | None = None
    active = np.arange(N)
    full = None
    lp = np.array(zbar if lin is None or lin_point is None else lin_point, dtype=float)
    while active.size and int(passes[active].max(initial=0)) < max_iter:
        sub = active.size < N
        dmi = dm.take(active) if sub else dm
        mi = [mm.take(active) for mm in meas] if sub else list(meas)
        Ri = [r[active] for r in R] if sub else list(R)
        if lin is not None and not sub:
            lin_i, lin = lin, None  # reuse once, for the first pass over every run (lp: its point)
        else:
            lin_i = linearise(dmi, mi, zbar[active])
            lp[active] = zbar[active]
        res = affine_pass(lin_i, dmi, mi, m0[active], P0[active], Qc[active], Ri, joseph=joseph)
        passes[active] += 1
        sdk = res.sm.std()
        moved = change(res.sm.m, lp[active], sdk)
        dx0 = change(res.sm.m[:, 0], m0[active], sd0[active]) if update_x0 else np.zeros(active.size)
        if update_x0:
            m0[active] = res.sm.m[:, 0]
        zbar = zbar.copy()
        zbar[active] = res.sm.m
        done = (moved < tol) & (dx0 < tol)
        full = _scatter(full, res, active, N)
        settled[active[done]] = True
        active = active[~done]
        out = res
    assert out is not None
    return IEKSResult(full if full is not None else out, m0, passes, settled, ekf_m, lp)


def _scatter(full: SmootherResult | None, res: SmootherResult, idx: np.ndarray, N: int) -> SmootherResult:
    """Write the pass of runs ``idx`` into the result of all runs."""
    if full is None and idx.size == N:
        return res
    if full is None:
        raise RuntimeError("the first pass must cover every run")

    def put(a, b):
        a[idx] = b

    for name in ("m_pred", "P_pred", "m_filt", "P_filt", "A", "loglik", "repairs"):
        put(getattr(full.fwd, name), getattr(res.fwd, name))
    for name in ("m", "P", "C", "G", "repairs"):
        put(getattr(full.sm, name), getattr(res.sm, name))
    for name in ("q_sums", "r_sums", "r_count", "sd", "finite"):  # made in the passes (compiled): scattered, or dropped
        a, b = getattr(full.sm, name), getattr(res.sm, name)
        if a is not None and b is not None:
            put(a, b)
        elif a is not None:
            setattr(full.sm, name, None)
    if full.sm.q_sums is None:
        full.sm.q_from = None
    if full.sm.r_sums is None or full.sm.r_count is None:
        full.sm.r_sums = full.sm.r_count = full.sm.r_from = None
    put(full.lin.A, res.lin.A)
    put(full.lin.b, res.lin.b)
    for j in range(len(full.lin.H)):
        put(full.lin.H[j], res.lin.H[j])
        put(full.lin.d[j], res.lin.d[j])
        put(full.lin.y[j], res.lin.y[j])
    return full
