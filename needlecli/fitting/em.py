r"""Expectation-maximisation of the process and measurement noise and the augmented constants (the magnetic needle EM paper,
sec. 2.2, Algorithm 1), batched over trials.

E-step: the iterated EKS (:func:`~needlecli.fitting.smoother.ieks`) with ``x0 <- x_0|N`` until the
initial state and the trajectory settle. M-step: closed-form maximisation of the expected complete-data
log-likelihood of the linearised model, for ``Q`` and for each ``R_j`` separately
(:func:`~needlecli.numerics.kalman.em_process_noise`, :func:`~needlecli.numerics.kalman.em_measurement_noise`),
with an eigenvalue floor on the ``R_j`` that have one (the magnetic needle EM paper: 2.5e-9 m^2 on the camera position). The
unknown constants (``c``, ``l_inv``) are augmented states: their estimate is the smoothed initial state.

Stopping: when neither Q (its fitted block) nor any R_j changed by more than ``tol`` in relative terms
(:func:`relative_change`: the largest ``|log|`` eigenvalue of ``old^{-1} new``, scale-free across the
blocks' very different units) and the E-step has settled (its last pass moved neither ``x0`` nor the
trajectory by more than ``estep_tol`` standard deviations), or after ``max_iter`` iterations. With
``estep_max = 1`` the IEKS iterations run across the EM iterations (one pass each, re-linearised around
the previous smoothed trajectory): the same fixed point at the end, and fewer passes. Each trial stops on its own; only trials still running are computed. The log-likelihood of
the measurements under the linearised model is recorded per iteration; a decrease larger than
``ll_noise * |loglik|`` is counted and reported (EM on the exact linear model never decreases it).

A trial fails when its smoothed trajectory enters or jumps over the model's singularity (BiNM:
``B . h -> 0``; status ``singular``), or when the EM produces non-finite values or exploding covariances
(``diverged``; ``singular`` if it happened next to the singularity).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np

from needlecli.fitting.smoother import SmootherResult, change, ieks, take_linearisation
from needlecli.fitting.statespace import DiscreteModel, MeasurementModel
from needlecli.numerics.kalman import (
    em_measurement_noise,
    em_process_noise,
    floor_eigenvalues,
    symmetrize,
)

STATUS_OK = "ok"
STATUS_MAX_ITER = "max_iter"
STATUS_SINGULAR = "singular"
STATUS_DIVERGED = "diverged"


@dataclass(frozen=True)
class EMOptions:
    """Settings of :func:`fit_em` (the config's ``fit.em`` section maps onto these).

    q_index : states with process noise (the others' rows and columns of Q stay zero); all if None
    q_hold : states whose process noise is held at the initial guess (rows and columns: not fitted)
    q_isotropic : groups of states (indices) whose block of Q is fitted as ``s I``, uncorrelated with the
        other states (:func:`tie_isotropic`): a unit vector's process noise, whose part along the vector
        the data do not see
    r_floor : per channel, a floor on the eigenvalues of R_j (variance, unit^2) or None
    """

    max_iter: int = 100
    tol: float = 1e-3
    estep_max: int = 10
    estep_tol: float = 0.05
    update_x0: bool = True
    q_index: tuple[int, ...] | None = None
    q_hold: tuple[int, ...] = ()
    q_isotropic: tuple[tuple[int, ...], ...] = ()
    q_floor: float = 0.0
    r_floor: tuple[float | None, ...] = ()
    ll_noise: float = 1e-8
    max_cov_trace: float = 1e6
    joseph: bool = False
    accelerate: bool = True
    relin_tol: float = 0.5
    max_step: float = 16.0
    rel_floor: float = 1e-8
    unit_vector_floor: float = 1e-3


@dataclass
class EMResult:
    """Per trial (leading axis N): the fit, its convergence history and its status.

    Qc (N, n, n) per second; R list of (N, m_j, m_j); x0 (N, n) the settled initial state (the augmented
    constants at the end); smoothed m (N, K+1, n), P (N, K+1, n, n); filtered (N, K+1, n) the forward pass
    of the final E-step; ekf (N, K+1, n) the first plain EKF pass (before any fitting);
    history: loglik (N, I), delta (N, I) the stopping criterion, constants (N, I, p), q_trace (N, I),
    r_trace list (N, I) per channel; NaN after a trial stopped.
    """

    Qc: np.ndarray
    R: list[np.ndarray]
    x0: np.ndarray
    m: np.ndarray
    P: np.ndarray
    filtered: np.ndarray
    ekf: np.ndarray
    status: np.ndarray
    reason: np.ndarray
    iterations: np.ndarray
    estep_passes: np.ndarray
    ll_decreases: np.ndarray
    ll_worst_drop: np.ndarray
    floor_hits: np.ndarray
    repairs: np.ndarray
    history: dict[str, np.ndarray] = field(default_factory=dict)
    extrapolations: np.ndarray | None = None
    rejections: np.ndarray | None = None

    @property
    def converged(self) -> np.ndarray:
        return self.status == STATUS_OK


_take_lin = take_linearisation


def relative_change(new: np.ndarray, old: np.ndarray) -> np.ndarray:
    """Scale-free change between covariances ``(N, m, m)``: the largest ``|log lambda|`` over the
    eigenvalues of ``old^{-1} new`` (the largest relative change of the variance in any direction;
    ``0.01`` is about 1 %). Infinite where either is not positive definite or not finite."""
    out = np.full(new.shape[0], np.inf)
    with np.errstate(all="ignore"):
        ok = np.isfinite(new).all((-1, -2)) & np.isfinite(old).all((-1, -2))
        if not ok.any():
            return out
        try:
            L = np.linalg.cholesky(old[ok])
        except np.linalg.LinAlgError:
            return np.array([relative_change(new[i : i + 1], old[i : i + 1])[0] if ok[i] else np.inf
                             for i in range(new.shape[0])]) if new.shape[0] > 1 else out
        Li = np.linalg.inv(L)
        w = np.linalg.eigvalsh(Li @ new[ok] @ np.swapaxes(Li, -1, -2))
        out[ok] = np.where(w[..., 0] > 0, np.abs(np.log(np.where(w > 0, w, 1.0))).max(-1), np.inf)
    return out


def fit_em(
    dm: DiscreteModel,
    meas: Sequence[MeasurementModel],
    m0: np.ndarray,
    P0: np.ndarray,
    Q0: np.ndarray,
    R0: Sequence[np.ndarray],
    options: EMOptions = EMOptions(),
    progress: Callable[[int, int], None] | None = None,
) -> EMResult:
    """EM over every trial at once (the magnetic needle EM paper's Algorithm 1).

    Parameters
    ----------
    dm, meas : the system and its channels (N trials)
    m0 : (N, n) initial guess of the initial state (augmented constants included)
    P0 : (N, n, n) or (n, n) its covariance (fixed)
    Q0 : (N, n, n) or (n, n) initial guess of the process noise per second
    R0 : per channel (N, m, m) or (m, m) initial guesses
    progress : ``progress(done_iterations, max_iter)``
    """
    o = options
    N, n = m0.shape
    K1 = len(dm.ticks)
    J = len(meas)
    P0 = np.array(np.broadcast_to(P0, (N, n, n)), dtype=float)
    Q = np.array(np.broadcast_to(Q0, (N, n, n)), dtype=float)
    q_keep = np.ones(n, dtype=bool)
    if o.q_index is not None:
        q_keep[:] = False
        q_keep[list(o.q_index)] = True
        Q = Q * (q_keep[:, None] & q_keep[None, :])
    Q = tie_isotropic(Q, o.q_isotropic)  # the initial guess too (the mean of its variances on a tied block)
    Q0_held = Q.copy()
    R = [np.array(np.broadcast_to(r, (N, mm.m, mm.m)), dtype=float) for r, mm in zip(R0, meas)]
    floors = list(o.r_floor) + [None] * (J - len(o.r_floor))
    # a unit-vector channel (a measured direction) has no noise along the direction itself: H has no row
    # there and the residual is of second order, so its variance would shrink without end and drive the
    # likelihood up for nothing; it is held at a floor relative to the whole (``unit_vector_floor``)
    rel_floors = [o.unit_vector_floor if mm.unit_vector else o.rel_floor for mm in meas]
    m0 = np.array(m0, dtype=float)
    I = o.max_iter
    hist = {
        "loglik": np.full((N, I), np.nan),
        "delta": np.full((N, I), np.nan),
        "constants": np.full((N, I, n - dm.nx), np.nan),
        "q_trace": np.full((N, I), np.nan),
        "estep_passes": np.zeros((N, I), dtype=np.int64),
    }
    for j in range(J):
        hist[f"r_trace/{meas[j].name}"] = np.full((N, I), np.nan)
    status = np.full(N, STATUS_MAX_ITER, dtype=object)
    reason = np.full(N, "", dtype=object)
    iterations = np.zeros(N, dtype=np.int64)
    estep_passes = np.zeros(N, dtype=np.int64)
    ll_dec = np.zeros(N, dtype=np.int64)
    ll_drop = np.zeros(N)
    floor_hits = np.zeros(N, dtype=np.int64)
    repairs = np.zeros(N, dtype=np.int64)
    out_m = np.full((N, K1, n), np.nan)
    out_P = np.full((N, K1, n, n), np.nan)
    out_f = np.full((N, K1, n), np.nan)
    ekf_m = np.full((N, K1, n), np.nan)
    zbar: np.ndarray | None = None
    active = np.arange(N)
    # the last linearisation, its rows of the trials lin_idx (None: all, in order; taken out only when reused)
    lin_prev, lin_rows, lin_idx = None, None, active
    lin_point = np.full((N, K1, n), np.nan)  # the trajectory each trial's last linearisation was made around
    sd_prev = np.ones((N, K1, n))
    prev_delta = np.full(N, np.inf)

    # the smoothed covariances, the largest output, are copied once at the end: until then each trial's
    # are held by reference to the pass that computed them (a trial stored again points to its newer pass)
    P_keep: dict[int, np.ndarray] = {}
    P_of = np.full(N, -1, dtype=np.int64)
    P_row = np.zeros(N, dtype=np.int64)

    def store(idx_local: np.ndarray, idx_global: np.ndarray, res: SmootherResult) -> None:
        out_m[idx_global] = res.sm.m[idx_local]
        out_f[idx_global] = res.fwd.m_filt[idx_local]
        key = id(res.sm.P)
        P_keep[key] = res.sm.P
        P_of[idx_global] = key
        P_row[idx_global] = idx_local
        for k in [k for k in P_keep if not (P_of == k).any()]:
            del P_keep[k]

    def fail(idx_local, idx_global, res, z_prev, why_nonfinite: np.ndarray, msg: str) -> np.ndarray:
        """Mark trials singular / diverged; returns the local mask of failed ones."""
        with np.errstate(all="ignore"):
            sing = dm_a.left_domain(res.sm.m) | dm_a.left_domain(res.fwd.m_filt)
            near = dm_a.near_singular(z_prev) if z_prev is not None else np.zeros(len(idx_local), dtype=bool)
        bad = sing | why_nonfinite
        if bad.any():
            is_s = bad & (sing | near)
            g = idx_global[bad & is_s]
            status[g] = STATUS_SINGULAR
            reason[g] = f"{dm.model.singular_reason} (EM iteration {it + 1})"
            g = idx_global[bad & ~is_s]
            status[g] = STATUS_DIVERGED
            reason[g] = f"{msg} (EM iteration {it + 1})"
            store(np.nonzero(bad)[0], idx_global[bad], res)
            iterations[idx_global[bad]] = it + 1
        return bad

    # SQUAREM state per trial: phase 0 (at theta0), 1 (at theta1 = F(theta0)), 2 (at the extrapolation)
    phase = np.zeros(N, dtype=np.int64)
    th0 = th1 = th2 = None
    ll0 = np.full(N, np.nan)
    ll1 = np.full(N, np.nan)
    ll_ref = np.full(N, np.nan)  # log-likelihood of the point a plain EM step started from
    rejected = np.zeros(N, dtype=np.int64)
    accepted = np.zeros(N, dtype=np.int64)
    hist["step"] = np.full((N, I), -1, dtype=np.int64)
    qi = np.nonzero(q_keep)[0]
    blk = (slice(None), qi[:, None], qi[None, :])

    it = 0
    for it in range(I):
        if not active.size:
            break
        sub = active.size < N
        dm_a = dm.take(active) if sub else dm
        meas_a = [mm.take(active) for mm in meas] if sub else list(meas)
        R_a = [r[active] for r in R]
        # ---- E-step: iterated EKS, x0 <- x_0|N until settled
        # the last linearisation is reused while the trajectory stayed within relin_tol standard deviations
        # of the one it was made around, and no trial is about to stop (the last E-step must be exact)
        reuse = None
        if lin_prev is not None and lin_idx.size == active.size:
            stale = change(zbar[active], lin_point[active], sd_prev[active])
            if (stale < o.relin_tol).all() and (prev_delta[active] >= o.tol).all():
                reuse = lin_prev if lin_rows is None else _take_lin(lin_prev, lin_rows)
        e = ieks(dm_a, meas_a, m0[active], P0[active], Q[active], R_a,
                 zbar=None if zbar is None else zbar[active], lin=reuse,
                 lin_point=None if reuse is None else lin_point[active], max_iter=o.estep_max, tol=o.estep_tol,
                 update_x0=o.update_x0, joseph=o.joseph)
        res = e.result
        if zbar is None:
            if e.ekf is not None:
                ekf_m[active] = e.ekf
            zbar = np.full((N, K1, n), np.nan)
        estep_passes[active] += e.passes
        hist["estep_passes"][active, it] = e.passes
        hist["step"][active, it] = phase[active]
        repairs[active] += res.fwd.repairs + res.sm.repairs
        ll = res.fwd.loglik
        hist["loglik"][active, it] = ll
        extrapolated = phase[active] == 2
        nonfinite = ~np.isfinite(ll) | ~np.isfinite(res.sm.m).all((-1, -2)) | ~res.sm.all_finite()
        # ---- M-step
        with np.errstate(all="ignore"):
            Qn = em_process_noise(res.sm, res.lin.A, res.lin.b, dm.dt, index=qi, state_angles=dm.angles,
                                  kernels=dm.kernels)
            Qn = tie_isotropic(Qn, o.q_isotropic)  # the maximiser with those blocks s I
            Qn[blk], _ = floor_eigenvalues(Qn[blk], np.maximum(o.q_floor, o.rel_floor * _largest(Qn[blk])))
            Qn = tie_isotropic(Qn, o.q_isotropic)  # (the floor keeps s I up to rounding)
            if o.q_hold:  # held rows and columns: the initial guess (uncorrelated with the fitted states)
                Qn = hold_rows(Qn, Q0_held[active], o.q_hold)
            Rn = []
            for j, mm in enumerate(meas_a):
                r, count = em_measurement_noise(res.sm, mm.channel(R_a[j], res.lin.y[j]), res.lin.H[j], res.lin.d[j],
                                                kernels=dm.kernels)
                r = np.where(count[:, None, None] > 0, r, R_a[j])
                r, _ = floor_eigenvalues(r, rel_floors[j] * _largest(r))
                if floors[j] is not None:
                    r, hit = floor_eigenvalues(r, floors[j])
                    floor_hits[active] += hit
                Rn.append(r)
            delta = relative_change(Qn[blk], Q[active][blk])
            for rn, ra in zip(Rn, R_a):
                delta = np.maximum(delta, relative_change(rn, ra))
            blown = ~np.isfinite(delta) | (np.trace(Qn, axis1=-2, axis2=-1) > o.max_cov_trace) | ~np.isfinite(Qn).all((-1, -2))
        # an extrapolated point that fails, or lowers the likelihood, is rejected (SQUAREM's safeguard)
        with np.errstate(invalid="ignore"):
            worse = extrapolated & ~(ll >= ll1[active] - o.ll_noise * np.maximum(np.abs(ll1[active]), 1.0))
        reject = extrapolated & (worse | nonfinite | blown)
        failed = fail(np.arange(active.size), active, res, zbar[active] if it else res.sm.m, nonfinite & ~reject,
                      "non-finite smoother estimates") & ~reject
        blown &= ~failed & ~reject
        if blown.any():
            near = dm_a.near_singular(res.sm.m)
            g = active[blown]
            status[g] = np.where(near[blown], STATUS_SINGULAR, STATUS_DIVERGED)
            reason[g] = np.where(near[blown], f"{dm.model.singular_reason} (EM iteration {it + 1})",
                                 f"the M-step gave non-finite or exploding covariances (EM iteration {it + 1})")
            store(np.nonzero(blown)[0], g, res)
            iterations[g] = it + 1
            failed = failed | blown
        ok = ~failed & ~reject
        rej = reject & ~failed
        g = active[ok]
        # ---- the log-likelihood along plain EM steps (never lower on an exact linear model)
        check = ok & (phase[active] == 1) if o.accelerate else ok
        if o.accelerate:
            check = check | (ok & (phase[active] == 0) & np.isfinite(ll_ref[active]))
            ref = np.where(phase[active] == 1, ll0[active], ll_ref[active])
        else:
            ref = hist["loglik"][active, it - 1] if it > 0 else np.full(active.size, np.nan)
        with np.errstate(invalid="ignore"):
            drop = ref - ll
            noisy = check & (drop > o.ll_noise * np.maximum(np.abs(ref), 1.0))
        ll_dec[active] += noisy
        ll_drop[active] = np.maximum(ll_drop[active], np.where(noisy, drop, 0.0))
        hist["delta"][g, it] = delta[ok]
        hist["constants"][g, it] = res.sm.m[ok, 0, dm.nx :]
        hist["q_trace"][g, it] = np.trace(Qn[ok], axis1=-2, axis2=-1)
        for j in range(J):
            hist[f"r_trace/{meas[j].name}"][g, it] = np.trace(Rn[j][ok], axis1=-2, axis2=-1)
        # ---- the next parameters: F(theta), or SQUAREM's extrapolation
        Q_next, R_next = Qn, Rn
        if o.accelerate:
            if th0 is None:
                D = _theta(Q[:1][blk], [r[:1] for r in R]).shape[-1]
                th0, th1, th2 = (np.full((N, D), np.nan) for _ in range(3))
            cur = _theta(Q[active][blk], R_a)
            new = _theta(Qn[blk], Rn)
            ph = phase[active]
            nxt = new.copy()
            p0m, p1m, p2m = ok & (ph == 0), ok & (ph == 1), ok & (ph == 2)
            th0[active[p0m]] = cur[p0m]
            th1[active[p0m]] = new[p0m]
            ll0[active[p0m]] = ll[p0m]
            if p1m.any():
                idx = active[p1m]
                th2[idx] = new[p1m]
                r_ = th1[idx] - th0[idx]
                v_ = th2[idx] - 2.0 * th1[idx] + th0[idx]
                nr, nv = np.linalg.norm(r_, axis=-1), np.linalg.norm(v_, axis=-1)
                with np.errstate(all="ignore"):
                    alpha = np.where(nv > 0, -nr / nv, -1.0)
                alpha = np.clip(np.nan_to_num(alpha, nan=-1.0), -o.max_step, -1.0)[:, None]
                nxt[p1m] = th0[idx] - 2.0 * alpha * r_ + alpha**2 * v_
                ll1[idx] = ll[p1m]
            accepted[active[p2m]] += 1
            ll_ref[active[p2m]] = ll[p2m]
            if rej.any():  # back to theta2 = F(theta1), a plain EM step from theta1
                rejected[active[rej]] += 1
                ll_ref[active[rej]] = ll1[active[rej]]
                nxt[rej] = th2[active[rej]]
            phase[active[p0m]] = 1
            phase[active[p1m]] = 2
            phase[active[p2m | rej]] = 0
            Q_next, R_next = _untheta(nxt, Qn, Rn, blk, floors, o.q_floor, o.rel_floor, rel_floors)
            Q_next = tie_isotropic(Q_next, o.q_isotropic)  # an extrapolation of s I in log space is s' I
            Q_next = np.where(rej[:, None, None], Q_next, np.where(ok[:, None, None], Q_next, Qn))
        keep_rows = ok | rej
        gk = active[keep_rows]
        Q[gk] = Q_next[keep_rows]
        for j in range(J):
            R[j][gk] = R_next[j][keep_rows]
        m0[g] = e.m0[ok]
        zbar[g] = res.sm.m[ok]
        store(np.nonzero(ok)[0], g, res)
        lin_prev, lin_rows, lin_idx = e.result.lin, None if keep_rows.all() else np.nonzero(keep_rows)[0], gk
        if e.lin_point is not None:
            lin_point[gk] = e.lin_point[keep_rows]
        sd_prev[g] = res.sm.std()[ok]
        prev_delta[g] = delta[ok]
        done = ok & (delta < o.tol) & e.settled  # and the E-step at its fixed point (x0, linearisation)
        status[active[done]] = STATUS_OK
        iterations[active[ok | rej]] = it + 1
        keep = keep_rows & ~done
        active = active[keep]
        if lin_idx.size != active.size:
            sel = np.isin(lin_idx, active)
            lin_rows, lin_idx = (np.arange(lin_idx.size) if lin_rows is None else lin_rows)[sel], lin_idx[sel]
        if progress is not None:
            progress(it + 1, I)
    if progress is not None:
        progress(I, I)  # every trial has stopped
    for key, P_src in P_keep.items():
        sel = np.nonzero(P_of == key)[0]
        out_P[sel] = P_src[P_row[sel]]
    for g in active:  # ran out of iterations
        last = hist["delta"][g][np.isfinite(hist["delta"][g])]
        reason[g] = (f"no convergence in {I} iterations (last change {last[-1] if last.size else np.nan:.3g} "
                     f">= tol {o.tol:g})")
    return EMResult(
        Qc=Q, R=R, x0=m0, m=out_m, P=out_P, filtered=out_f, ekf=ekf_m, status=status.astype(str),
        reason=reason.astype(str), iterations=iterations, estep_passes=estep_passes, ll_decreases=ll_dec,
        ll_worst_drop=ll_drop, floor_hits=floor_hits, repairs=repairs, history=hist,
        extrapolations=accepted, rejections=rejected,
    )


def tie_isotropic(Q: np.ndarray, groups: Sequence[Sequence[int]]) -> np.ndarray:
    r"""``Q (N, n, n)`` with the block of each group of states replaced by ``s I`` and its covariances with
    every other state set to zero, ``s`` the mean of the block's variances.

    Applied to the M-step's unconstrained maximiser ``S`` (the expected sufficient statistic of the
    process noise per second), this is the maximiser under the constraint: with
    ``Q = blockdiag(Q_rest, s I_d)`` the expected log-likelihood ``-K/2 (log|Q| + tr(Q^-1 S))`` separates
    into ``Q_rest = S_rest`` and ``s = tr(S_bb) / d``. For the process noise of a unit vector (the MNM's
    heading ``h`` and field ``B``) the data see only the directions across the vector (the model holds
    its length at 1 and a direction is measured); a free block would keep its variance along the vector
    near EM's initial guess, and its trace with it. Tied, ``s`` is set by the directions across the vector
    (the fixed point of ``s = (d_seen s_seen + d_unseen s) / d`` is ``s = s_seen``).
    """
    if not groups:
        return Q
    Q = Q.copy()
    for g in groups:
        g = np.asarray(g, dtype=np.int64)
        s = np.trace(Q[:, g[:, None], g[None, :]], axis1=-2, axis2=-1) / len(g)
        Q[:, g, :] = 0.0
        Q[:, :, g] = 0.0
        Q[:, g, g] = s[:, None]
    return Q


def hold_rows(Q: np.ndarray, Q0: np.ndarray, hold: Sequence[int]) -> np.ndarray:
    """``Q (N, n, n)`` with the rows and columns ``hold`` replaced by those of ``Q0`` (their covariances with
    the other states zero): process noise held at its guess, the rest as fitted."""
    Q = Q.copy()
    h = np.asarray(hold, dtype=np.int64)
    Q[:, h, :] = 0.0
    Q[:, :, h] = 0.0
    Q[:, h[:, None], h[None, :]] = Q0[:, h[:, None], h[None, :]]
    return Q


# ---------------------------------------------------------------------------------------------- SQUAREM
def _largest(S: np.ndarray) -> np.ndarray:
    """Largest eigenvalue bound ``(N,)`` of covariances (their trace; NaN rows give NaN)."""
    return np.trace(S, axis1=-2, axis2=-1)


def _eig_map(S: np.ndarray, fn) -> np.ndarray:
    """``V fn(w) V^T`` for symmetric ``S (N, m, m)``; NaN where ``S`` is not finite."""
    S = symmetrize(S)
    out = np.full(S.shape, np.nan)
    ok = np.isfinite(S).all((-1, -2))
    if ok.any():
        w, V = np.linalg.eigh(S[ok])
        with np.errstate(all="ignore"):
            out[ok] = (V * fn(w)[..., None, :]) @ np.swapaxes(V, -1, -2)
    return out


def _logm(S: np.ndarray) -> np.ndarray:
    return _eig_map(S, lambda w: np.log(np.maximum(w, 1e-300)))


def _expm(L: np.ndarray) -> np.ndarray:
    return _eig_map(L, np.exp)


def _theta(Qb: np.ndarray, R: Sequence[np.ndarray]) -> np.ndarray:
    """The parameters as one vector per trial: matrix logarithms of the fitted Q block and of each R_j
    (an extrapolation there stays positive definite, and the scales of the blocks do not matter)."""
    parts = [_logm(Qb).reshape(Qb.shape[0], -1)] + [_logm(r).reshape(r.shape[0], -1) for r in R]
    return np.concatenate(parts, -1)


def _untheta(th, Q_like, R_like, blk, floors, q_floor, rel_floor, rel_floors):
    Q = np.zeros_like(Q_like)  # the rows and columns outside the fitted block are zero
    q = Q[blk].shape[-1]
    a = q * q
    with np.errstate(all="ignore"):
        Qb = _expm(th[:, :a].reshape(-1, q, q))
        Qb, _ = floor_eigenvalues(Qb, np.maximum(q_floor, rel_floor * _largest(Qb)))
        Q[blk] = Qb
        R = []
        for r, fl, rf in zip(R_like, floors, rel_floors):
            m = r.shape[-1]
            Rj = _expm(th[:, a : a + m * m].reshape(-1, m, m))
            Rj, _ = floor_eigenvalues(Rj, rf * _largest(Rj))
            if fl is not None:
                Rj, _ = floor_eigenvalues(Rj, fl)
            R.append(Rj)
            a += m * m
    return Q, R
