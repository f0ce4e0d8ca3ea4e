r"""Kalman filtering and smoothing as pure array functions, batched over a leading run axis.

Every function works on all runs at once: means ``(N, n)``, covariances ``(N, n, n)``, time the axis after
the runs (``(N, K, n)``). There is one loop over time and none over runs.

The state-space model is discrete on a grid of *ticks* ``0..K``:

.. math::
    x_{k+1} = f_k(x_k) + w_k,\quad w_k \sim N(0, Q_c\,\Delta t_k),\qquad
    y_{j,i} = h_j(x_{k(j,i)}) + v_{j,i},\quad v_j \sim N(0, R_j)

with several measurement channels ``j``, each with its own samples ``i`` at its own ticks ``k(j, i)``
(the magnetic needle EM paper's eq. 6). :func:`kalman_forward` is the filter for any linearisation: the caller's ``transition`` and
``measure`` return the predicted mean and the Jacobian, at the filter's own estimate (the EKF) or from an
affine model fixed in advance (one pass of the iterated smoother). :func:`rts_smoother` is the
Rauch-Tung-Striebel smoother with the lag-one cross-covariances that EM needs; :func:`em_process_noise`
and :func:`em_measurement_noise` are the closed-form M-step of the expected log-likelihood.

Covariance updates use the Joseph form and are symmetrised; a covariance that is still not positive
definite is repaired by clipping its eigenvalues (:func:`repair_pd`), and repairs are counted per run.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from needlecli.kernels import twin
from needlecli.numerics.angles import wrap_angle

LOG_2PI = float(np.log(2.0 * np.pi))


# ---------------------------------------------------------------------------------------------- helpers
def symmetrize(p: np.ndarray) -> np.ndarray:
    """``(P + P^T) / 2`` over the last two axes."""
    return 0.5 * (p + np.swapaxes(p, -1, -2))


def repair_pd(p: np.ndarray, floor: float = 1e-300) -> tuple[np.ndarray, np.ndarray]:
    """Make covariances ``(..., n, n)`` positive definite where they are not.

    Returns the repaired array and a boolean mask ``(...)`` of the matrices that needed it. A matrix is
    repaired by clipping its eigenvalues at ``max(floor, 1e-12 * largest eigenvalue)``. Cheap when
    nothing is wrong (one batched Cholesky).
    """
    p = symmetrize(p)
    try:
        np.linalg.cholesky(p)
        return p, np.zeros(p.shape[:-2], dtype=bool)
    except np.linalg.LinAlgError:
        pass
    finite = np.isfinite(p).all((-1, -2))
    w = np.zeros(p.shape[:-1])
    w[finite] = np.linalg.eigvalsh(p[finite])
    bad = ~(w[..., 0] > 1e-12 * np.maximum(w[..., -1], 0.0)) | ~finite
    fix = bad & finite  # a matrix with NaN or inf entries cannot be repaired: it is flagged and left
    if fix.any():
        q = p[fix]
        wq, vq = np.linalg.eigh(q)
        lo = np.maximum(floor, 1e-12 * np.maximum(wq[..., -1:], floor))
        wq = np.maximum(wq, lo)
        p = p.copy()
        p[fix] = symmetrize((vq * wq[..., None, :]) @ np.swapaxes(vq, -1, -2))
    return p, bad


def floor_eigenvalues(r: np.ndarray, floor: float | np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Clip the eigenvalues of covariances ``(..., m, m)`` at ``floor`` (a variance, unit^2).

    Returns the floored matrices and a boolean ``(...)``: which ones the floor changed.
    """
    r = symmetrize(r)
    finite = np.isfinite(r).all((-1, -2))
    out = r.copy()
    hit = np.zeros(r.shape[:-2], dtype=bool)
    if finite.any():
        w, v = np.linalg.eigh(r[finite])
        fl = np.broadcast_to(np.asarray(floor, dtype=float), r.shape[:-2])[finite][..., None]
        hit[finite] = (w < fl).any(-1)
        w = np.maximum(w, fl)
        out[finite] = symmetrize((v * w[..., None, :]) @ np.swapaxes(v, -1, -2))
    return out, hit


def _wrap_where(d: np.ndarray, mask: np.ndarray | None) -> np.ndarray:
    if mask is None or not mask.any():
        return d
    d = d.copy()
    d[..., mask] = wrap_angle(d[..., mask])
    return d


# ---------------------------------------------------------------------------------------------- data
@dataclass(frozen=True)
class Channel:
    """One measurement channel on the tick grid.

    tick : (M,) int, increasing and unique: the tick each sample describes
    y : (N, M, m) values (anything where not ``valid``)
    valid : (N, M) bool
    R : (N, m, m) or (m, m) noise covariance
    angle : (m,) bool, residuals wrapped to (-pi, pi]; None for none
    """

    tick: np.ndarray
    y: np.ndarray
    valid: np.ndarray
    R: np.ndarray
    angle: np.ndarray | None = None

    @property
    def m(self) -> int:
        return self.y.shape[-1]


@dataclass
class ForwardResult:
    """Output of :func:`kalman_forward`. ``K + 1`` ticks, ``K`` intervals.

    m_pred, P_pred : (N, K+1, n), (N, K+1, n, n) prior at each tick (tick 0: the initial prior)
    m_filt, P_filt : (N, K+1, n), (N, K+1, n, n) after the tick's measurements
    A : (N, K, n, n) transition Jacobian of each interval (as used by the filter)
    loglik : (N,) log-likelihood of the measurements, from the innovations
    repairs : (N,) covariances repaired (not positive definite after an update)
    """

    m_pred: np.ndarray
    P_pred: np.ndarray
    m_filt: np.ndarray
    P_filt: np.ndarray
    A: np.ndarray
    loglik: np.ndarray
    repairs: np.ndarray


@dataclass
class SmoothResult:
    """Output of :func:`rts_smoother`.

    m, P : (N, K+1, n), (N, K+1, n, n) smoothed means and covariances
    C : (N, K, n, n) lag-one cross-covariances ``Cov(x_{k+1}, x_k | all data)``
    G : (N, K, n, n) smoother gains
    repairs : (N,) predicted covariances repaired before inversion
    """

    m: np.ndarray
    P: np.ndarray
    C: np.ndarray
    G: np.ndarray
    repairs: np.ndarray
    q_sums: np.ndarray | None = None  # (N, n, n) em_process_noise's sums, made in the pass (compiled)
    q_from: tuple | None = None  # the (A, b, dt, state_angles) they were made with
    r_sums: np.ndarray | None = None  # (N, J, mm, mm) em_measurement_noise's R per channel, made in the pass
    r_count: np.ndarray | None = None  # (N, J) its counts of samples
    r_from: list | None = None  # per channel, the (tick, y, valid, H, d, angle) they were made with
    sd: np.ndarray | None = None  # (N, K+1, n) sqrt(maximum(diag P, 1e-300)), made in the pass (compiled)
    finite: np.ndarray | None = None  # (N,) every entry of each run's P finite, made in the pass (compiled)

    def std(self) -> np.ndarray:
        """``sqrt(maximum(diag P, 1e-300))`` ``(N, K+1, n)`` (NaN stays NaN)."""
        if self.sd is not None:
            return self.sd
        return np.sqrt(np.maximum(np.diagonal(self.P, axis1=-2, axis2=-1), 1e-300))

    def all_finite(self) -> np.ndarray:
        """``(N,)``: every entry of each run's smoothed covariances is finite."""
        if self.finite is not None:
            return self.finite
        return np.isfinite(self.P).all((-1, -2, -3))


Transition = Callable[[int, np.ndarray], tuple[np.ndarray, np.ndarray]]
Measure = Callable[[int, int, np.ndarray], tuple[np.ndarray, np.ndarray]]


def arrivals(channels: Sequence[Channel], n_ticks: int) -> list[list[tuple[int, int]]]:
    """For each tick, the ``(channel, sample)`` pairs that describe it."""
    out: list[list[tuple[int, int]]] = [[] for _ in range(n_ticks)]
    for j, ch in enumerate(channels):
        for i, k in enumerate(np.asarray(ch.tick)):
            if 0 <= k < n_ticks:
                out[int(k)].append((j, i))
    return out


# ---------------------------------------------------------------------------------------------- filter
def kalman_forward(
    m0: np.ndarray,
    P0: np.ndarray,
    Qc: np.ndarray,
    dt: np.ndarray,
    transition: Transition,
    measure: Measure,
    channels: Sequence[Channel],
    *,
    state_angles: np.ndarray | None = None,
    joseph: bool = True,
    progress: Callable[[int, int], None] | None = None,
) -> ForwardResult:
    r"""Kalman filter over ``K + 1`` ticks with any linearisation.

    Parameters
    ----------
    m0 : (N, n) prior mean at tick 0; P0 : (N, n, n) or (n, n)
    Qc : (N, n, n) or (n, n) process noise per second; interval ``k`` gets ``Qc * dt[k]``
    dt : (K,) interval lengths, s
    transition : ``transition(k, m (N, n)) -> (m_next (N, n), A (N, n, n))``: the mean propagated over
        interval ``k`` and the Jacobian used for the covariance (``P <- A P A^T + Qc dt_k``)
    measure : ``measure(j, i, m (N, n)) -> (y_hat (N, m_j), H (N, m_j, n))`` for sample ``i`` of channel ``j``,
        or ``(y_hat, H, y)`` with the measured value in the same coordinates (then ``channel.y`` only gives
        the shape)
    channels : the measurement channels (several at their own rates; all samples at a tick are used in
        one joint update with block-diagonal noise)
    state_angles : (n,) bool, states wrapped after each update
    joseph : the Joseph form of the covariance update (else ``P - K S K^T``, symmetrised; the filtered
        covariances are then checked once after the pass and repaired where not positive definite)

    Returns
    -------
    ForwardResult. The log-likelihood counts valid measurement components only.
    """
    m = np.array(m0, dtype=float)
    N, n = m.shape
    K = len(dt)
    P = np.array(np.broadcast_to(P0, (N, n, n)), dtype=float)
    Qc = np.broadcast_to(Qc, (N, n, n))
    eye = np.eye(n)
    m_pred = np.empty((N, K + 1, n))
    P_pred = np.empty((N, K + 1, n, n))
    m_filt = np.empty((N, K + 1, n))
    P_filt = np.empty((N, K + 1, n, n))
    A_all = np.empty((N, K, n, n))
    loglik = np.zeros(N)
    repairs = np.zeros(N, dtype=np.int64)
    arr = arrivals(channels, K + 1)
    all_valid = [np.asarray(ch.valid).all(axis=0) for ch in channels]
    R_full = [np.broadcast_to(ch.R, (N, ch.m, ch.m)) for ch in channels]
    every = max(1, K // 50)
    with np.errstate(all="ignore"):
        for k in range(K + 1):
            if k > 0:
                m, A = transition(k - 1, m)
                A_all[:, k - 1] = A
                P = A @ P @ np.swapaxes(A, -1, -2) + Qc * dt[k - 1]
            m_pred[:, k] = m
            P_pred[:, k] = P
            if arr[k]:
                m, P, ll, rep = _update(m, P, arr[k], channels, measure, all_valid, R_full, eye, joseph)
                loglik += ll
                repairs += rep
                if state_angles is not None and state_angles.any():
                    m[:, state_angles] = wrap_angle(m[:, state_angles])
            m_filt[:, k] = m
            P_filt[:, k] = P
            if progress is not None and (k % every == 0 or k == K):
                progress(k, K)
    if not joseph:
        P_filt, bad = repair_pd(P_filt)
        repairs += bad.reshape(N, -1).sum(-1)
    return ForwardResult(m_pred, P_pred, m_filt, P_filt, A_all, loglik, repairs)


def _update(m, P, arrived, channels, measure, all_valid, R_full, eye, joseph=True):
    """Joint update with every sample of this tick (Joseph form, or the symmetrised standard form)."""
    N, n = m.shape
    nus, Hs, Rs, masks, blocks = [], [], [], [], []
    for j, i in arrived:
        ch = channels[j]
        out = measure(j, i, m)
        if len(out) == 3:  # the measured value in the callback's own coordinates (e.g. a tangent plane)
            y_hat, H, y_obs = out
        else:
            (y_hat, H), y_obs = out, ch.y[:, i]
        nu = y_obs - y_hat
        if ch.angle is not None and ch.angle.any():
            nu = _wrap_where(nu, ch.angle)
        R = R_full[j]
        if all_valid[j][i]:
            mask = None
        else:
            v = np.asarray(ch.valid[:, i])
            nu = np.where(v[:, None], nu, 0.0)
            H = H * v[:, None, None]
            R = np.where(v[:, None, None], R, np.eye(ch.m))
            mask = np.broadcast_to(v[:, None], (N, ch.m))
        nus.append(nu)
        Hs.append(H)
        Rs.append(R)
        masks.append(mask)
        blocks.append(ch.m)
    if len(nus) == 1:
        nu, H, R = nus[0], Hs[0], Rs[0]
    else:
        nu = np.concatenate(nus, -1)
        H = np.concatenate(Hs, -2)
        mt = nu.shape[-1]
        R = np.zeros((N, mt, mt))
        a = 0
        for Rj, mj in zip(Rs, blocks):
            R[:, a : a + mj, a : a + mj] = Rj
            a += mj
    mt = nu.shape[-1]
    if all(mk is None for mk in masks):
        n_valid = np.full(N, mt)
    else:
        n_valid = sum(
            (mk.sum(-1) if mk is not None else np.full(N, mj)) for mk, mj in zip(masks, blocks)
        )
    PHt = P @ np.swapaxes(H, -1, -2)  # (N, n, mt)
    S = symmetrize(H @ PHt + R)
    rep = np.zeros(N, dtype=np.int64)
    try:
        L = np.linalg.cholesky(S)
    except np.linalg.LinAlgError:
        S, bad = repair_pd(S)
        rep += bad
        L = np.linalg.cholesky(S)
    logdet = 2.0 * np.log(np.diagonal(L, axis1=-2, axis2=-1)).sum(-1)
    X = np.linalg.solve(S, np.concatenate([np.swapaxes(PHt, -1, -2), nu[..., None]], -1))
    K = np.swapaxes(X[..., :n], -1, -2)  # (N, n, mt)
    s_nu = X[..., n]
    ll = -0.5 * (np.einsum("ni,ni->n", nu, s_nu) + logdet + n_valid * LOG_2PI)
    m = m + (K @ nu[..., None])[..., 0]
    if joseph:
        IKH = eye - K @ H
        P = IKH @ P @ np.swapaxes(IKH, -1, -2) + K @ R @ np.swapaxes(K, -1, -2)
    else:  # P - K S K^T = P - K (P H^T)^T: symmetrised here, checked for definiteness after the pass
        P = P - K @ np.swapaxes(PHt, -1, -2)
    return m, symmetrize(P), ll, rep


def kalman_forward_affine(
    m0: np.ndarray,
    P0: np.ndarray,
    Qc: np.ndarray,
    dt: np.ndarray,
    A: np.ndarray,
    b: np.ndarray,
    channels: Sequence[Channel],
    H: Sequence[np.ndarray],
    d: Sequence[np.ndarray],
    *,
    state_angles: np.ndarray | None = None,
    kernels: str | None,
) -> ForwardResult:
    r"""The Kalman filter of the affine model ``x_{k+1} = A_k x_k + b_k + w_k``, ``y_j = H_j x + d_j + v_j``
    (one pass of the iterated smoother). Same result as :func:`kalman_forward` with affine callbacks and
    ``joseph=False``, with everything that does not depend on the filter's state prepared before the loop
    (measurements stacked per tick, invalid components masked) and the log-likelihood computed after it
    from the stored innovations: about half the array operations per tick.

    Parameters
    ----------
    A : (N, K, n, n), b : (N, K, n); H[j] : (N, M_j, m_j, n), d[j] : (N, M_j, m_j) per channel
    kernels : the kernels setting (``auto``, ``numba``, ``numpy``: :func:`needlecli.kernels.resolve`); the
        compiled twin ``kalman_forward_affine`` where it resolves to numba
    """
    fast = twin("kalman_forward_affine", kernels)
    if fast is not None:
        return ForwardResult(*fast(m0, P0, Qc, dt, A, b, channels, H, d, state_angles=state_angles))
    m = np.array(m0, dtype=float)
    N, n = m.shape
    K = len(dt)
    P = np.array(np.broadcast_to(P0, (N, n, n)), dtype=float)
    Qd = np.broadcast_to(Qc, (N, n, n))[:, None] * np.asarray(dt, dtype=float)[None, :, None, None]
    AT = np.swapaxes(A, -1, -2)
    # ---- measurements stacked per tick, grouped by which channels arrive
    arr = arrivals(channels, K + 1)
    groups: dict[tuple[int, ...], list[int]] = {}
    for k, a in enumerate(arr):
        if a:
            groups.setdefault(tuple(j for j, _ in a), []).append(k)
    slot: dict[int, tuple[tuple[int, ...], int]] = {}
    stacks = {}
    for pattern, ks in groups.items():
        ks_a = np.asarray(ks)
        Hs, ys, Rs, vs, angs = [], [], [], [], []
        for j in pattern:
            ch = channels[j]
            i = np.searchsorted(np.asarray(ch.tick), ks_a)
            v = np.asarray(ch.valid)[:, i]  # (N, Kp)
            Hj = H[j][:, i] * v[..., None, None]
            yj = np.where(v[..., None], ch.y[:, i] - d[j][:, i], 0.0)
            Rj = np.where(v[..., None, None], np.broadcast_to(ch.R, (N, ch.m, ch.m))[:, None], np.eye(ch.m))
            Hs.append(Hj)
            ys.append(yj)
            Rs.append(Rj)
            vs.append(np.repeat(v[..., None], ch.m, -1))
            angs.append(ch.angle if ch.angle is not None else np.zeros(ch.m, dtype=bool))
        mt = sum(channels[j].m for j in pattern)
        R = np.zeros((N, len(ks), mt, mt))
        a0 = 0
        for Rj in Rs:
            mj = Rj.shape[-1]
            R[..., a0 : a0 + mj, a0 : a0 + mj] = Rj
            a0 += mj
        Hcat = np.concatenate(Hs, -2)
        ang = np.concatenate(angs)
        stacks[pattern] = {
            "H": Hcat, "HT": np.swapaxes(Hcat, -1, -2).copy(), "y": np.concatenate(ys, -1), "R": R,
            "valid": np.concatenate(vs, -1), "S": np.empty((N, len(ks), mt, mt)), "nu": np.empty((N, len(ks), mt)),
            "angle": ang if ang.any() else None,
        }
        for pos, k in enumerate(ks):
            slot[k] = (pattern, pos)
    m_pred = np.empty((N, K + 1, n))
    P_pred = np.empty((N, K + 1, n, n))
    m_filt = np.empty((N, K + 1, n))
    P_filt = np.empty((N, K + 1, n, n))
    repairs = np.zeros(N, dtype=np.int64)
    wrap = state_angles is not None and state_angles.any()
    with np.errstate(all="ignore"):
        for k in range(K + 1):
            if k > 0:
                m = (A[:, k - 1] @ m[..., None])[..., 0] + b[:, k - 1]
                P = A[:, k - 1] @ P @ AT[:, k - 1] + Qd[:, k - 1]
            m_pred[:, k] = m
            P_pred[:, k] = P
            if k in slot:
                pattern, pos = slot[k]
                st = stacks[pattern]
                Hk = st["H"][:, pos]
                nu = st["y"][:, pos] - (Hk @ m[..., None])[..., 0]
                if st["angle"] is not None:
                    nu = _wrap_where(nu, st["angle"])
                PHt = P @ st["HT"][:, pos]
                S = Hk @ PHt + st["R"][:, pos]
                try:
                    Si = np.linalg.inv(S)
                except np.linalg.LinAlgError:
                    S, bad = repair_pd(S)
                    repairs += bad
                    Si = np.linalg.inv(S)
                Kg = PHt @ Si
                m = m + (Kg @ nu[..., None])[..., 0]
                P = P - Kg @ np.swapaxes(PHt, -1, -2)
                P = 0.5 * (P + np.swapaxes(P, -1, -2))
                st["S"][:, pos] = S
                st["nu"][:, pos] = nu
                if wrap:
                    m[:, state_angles] = wrap_angle(m[:, state_angles])
            m_filt[:, k] = m
            P_filt[:, k] = P
        P_filt, bad = repair_pd(P_filt)
        repairs += bad.reshape(N, -1).sum(-1)
        loglik = np.zeros(N)
        for st in stacks.values():
            S, rep = repair_pd(st["S"])
            repairs += rep.reshape(N, -1).sum(-1)
            L = np.linalg.cholesky(S)
            logdet = 2.0 * np.log(np.diagonal(L, axis1=-2, axis2=-1)).sum(-1)
            quad = np.einsum("nki,nki->nk", st["nu"], np.linalg.solve(S, st["nu"][..., None])[..., 0])
            nval = st["valid"].sum(-1)
            loglik += (-0.5 * (quad + logdet + nval * LOG_2PI)).sum(-1)
    return ForwardResult(m_pred, P_pred, m_filt, P_filt, np.asarray(A), loglik, repairs)


def kalman_loglik_affine(*args: np.ndarray | Sequence, state_angles: np.ndarray | None = None,
                         rows: np.ndarray | None = None, kernels: str | None) -> np.ndarray:
    """The log-likelihood ``(N,)`` of :func:`kalman_forward_affine` (the same arguments ``m0, P0, Qc, dt, A,
    b, channels, H, d``, and ``kernels``), the same numbers, without keeping its means and covariances (the
    compiled pass does not write them: many evaluation points at a time). ``rows (N,)``: point r is
    filtered on row ``rows[r]`` of ``A, b, H, d`` and of the channels' samples (with its own ``m0, P0, Qc``
    and channel noise ``R``): many points on one trial's linearisation, which the compiled pass reads
    without copies."""
    fast = twin("kalman_loglik_affine", kernels)
    if fast is not None:
        return fast(*args, state_angles=state_angles, store=False, rows=rows)[5]
    if rows is not None:
        m0, P0, Qc, dt, A, b, channels, H, d = args
        channels = [Channel(ch.tick, ch.y[rows], ch.valid[rows], ch.R, ch.angle) for ch in channels]
        args = (m0, P0, Qc, dt, A[rows], b[rows], channels, [h[rows] for h in H], [x[rows] for x in d])
    return kalman_forward_affine(*args, state_angles=state_angles, kernels=kernels).loglik


def kalman_filter_smoother(
    m0: np.ndarray,
    P0: np.ndarray,
    Qc: np.ndarray,
    dt: np.ndarray,
    A: np.ndarray,
    b: np.ndarray,
    channels: Sequence[Channel],
    H: Sequence[np.ndarray],
    d: Sequence[np.ndarray],
    *,
    state_angles: np.ndarray | None = None,
    kernels: str | None,
) -> tuple[ForwardResult, SmoothResult]:
    """:func:`kalman_forward_affine` then :func:`rts_smoother` (one pass of the iterated smoother). The
    compiled path runs both on each block of trials in turn and writes neither the filter's covariances
    nor the smoother's gains (``P_pred``, ``P_filt`` and ``G`` are then empty, ``(N, 0, n, n)``), and it
    makes the sums of :func:`em_process_noise` in the same pass instead of writing the cross-covariances
    (``C`` empty; ``q_sums``, read by :func:`em_process_noise` for this ``A, b, dt``), and those of
    :func:`em_measurement_noise` for each channel (``r_sums``, read for the same channel, ``H`` and ``d``);
    every other field is the two functions' own. ``kernels``: the setting (:func:`kalman_forward_affine`)."""
    fast = twin("kalman_filter_smoother", kernels)
    if fast is not None:
        f, s, (q, r, count), sd, finite = fast(m0, P0, Qc, dt, A, b, channels, H, d, state_angles=state_angles,
                                               q_sums=True)
        r_from = [(ch.tick, ch.y, ch.valid, Hj, dj, ch.angle) for ch, Hj, dj in zip(channels, H, d)]
        return ForwardResult(*f), SmoothResult(*s, q_sums=q, q_from=(A, b, dt, state_angles), r_sums=r, r_count=count,
                                               r_from=r_from, sd=sd, finite=finite)
    fwd = kalman_forward_affine(m0, P0, Qc, dt, A, b, channels, H, d, state_angles=state_angles, kernels=kernels)
    return fwd, rts_smoother(fwd, state_angles=state_angles, kernels=kernels)


# ---------------------------------------------------------------------------------------------- smoother
def rts_smoother(fwd: ForwardResult, *, state_angles: np.ndarray | None = None, kernels: str | None) -> SmoothResult:
    r"""Rauch-Tung-Striebel smoother on the filter's own linearisation.

    .. math::
        G_k = P_{k|k} A_k^T P_{k+1|k}^{-1},\quad
        m_{k|K} = m_{k|k} + G_k (m_{k+1|K} - m_{k+1|k}),\quad
        P_{k|K} = P_{k|k} + G_k (P_{k+1|K} - P_{k+1|k}) G_k^T

    and the lag-one cross-covariance ``Cov(x_{k+1}, x_k | all) = P_{k+1|K} G_k^T``. The gains are
    computed for all ticks at once; only the recursion loops over time. ``kernels``: the setting
    (:func:`kalman_forward_affine`).
    """
    fast = twin("rts_smoother", kernels)
    if fast is not None:
        m_s, P_s, C, G, repairs = fast(fwd, state_angles=state_angles)
        return SmoothResult(m=m_s, P=P_s, C=C, G=G, repairs=repairs)
    N, K1, n = fwd.m_filt.shape
    K = K1 - 1
    Pp, rep = repair_pd(fwd.P_pred[:, 1:])
    repairs = rep.sum(-1).astype(np.int64) if rep.ndim > 1 else rep.astype(np.int64)
    with np.errstate(all="ignore"):
        APf = fwd.A @ fwd.P_filt[:, :-1]  # (N, K, n, n)
        G = np.swapaxes(np.linalg.solve(Pp, APf), -1, -2)  # P_f A^T Pp^{-1}
    m_s = np.empty_like(fwd.m_filt)
    P_s = np.empty_like(fwd.P_filt)
    m_s[:, K] = fwd.m_filt[:, K]
    P_s[:, K] = fwd.P_filt[:, K]
    ms, Ps = m_s[:, K], P_s[:, K]
    wrap = state_angles is not None and state_angles.any()
    GT = np.swapaxes(G, -1, -2)
    with np.errstate(all="ignore"):
        for k in range(K - 1, -1, -1):
            d = ms - fwd.m_pred[:, k + 1]
            if wrap:
                d = _wrap_where(d, state_angles)
            ms = fwd.m_filt[:, k] + (G[:, k] @ d[..., None])[..., 0]
            if wrap:
                ms[:, state_angles] = wrap_angle(ms[:, state_angles])
            Ps = fwd.P_filt[:, k] + G[:, k] @ (Ps - Pp[:, k]) @ GT[:, k]
            m_s[:, k] = ms
            P_s[:, k] = Ps
        P_s = symmetrize(P_s)
        C = P_s[:, 1:] @ GT
    return SmoothResult(m=m_s, P=P_s, C=C, G=G, repairs=repairs)


# ---------------------------------------------------------------------------------------------- M-step
def em_process_noise(
    sm: SmoothResult,
    A: np.ndarray,
    b: np.ndarray,
    dt: np.ndarray,
    *,
    index: np.ndarray | None = None,
    state_angles: np.ndarray | None = None,
    kernels: str | None,
) -> np.ndarray:
    r"""Closed-form M-step for the process noise per second, ``Q_c``, of the affine model
    ``x_{k+1} = A_k x_k + b_k + w_k``, ``w_k ~ N(0, Q_c dt_k)``:

    .. math::
        Q_c = \frac1K \sum_k \frac{1}{dt_k}\Big(e_k e_k^T + P_{k+1} - C_k A_k^T - A_k C_k^T
              + A_k P_k A_k^T\Big),\quad e_k = m_{k+1} - A_k m_k - b_k

    with smoothed means ``m``, covariances ``P`` and lag-one cross-covariances ``C``.

    Parameters
    ----------
    sm : the smoother's output; A : (N, K, n, n); b : (N, K, n); dt : (K,)
    index : states that have process noise; the rows and columns of the others are zero (the
        maximiser of the likelihood of ``w`` restricted to those states). All states if None.
    kernels : the kernels setting (:func:`kalman_forward_affine`)

    Returns
    -------
    Qc : (N, n, n)
    """
    if sm.q_sums is not None and _same_inputs(sm.q_from, (A, b, dt, state_angles)):  # made in the pass
        Qc = sm.q_sums
    elif sm.C.shape[1] == 0 and sm.m.shape[1] > 1:
        raise ValueError("em_process_noise: this pass kept no cross-covariances (its sums were made for "
                         "another A, b, dt)")
    elif (fast := twin("em_process_noise", kernels)) is not None:
        return fast(sm, A, b, dt, index=index, state_angles=state_angles)
    else:
        Qc = _process_noise_numpy(sm, A, b, dt, state_angles)
    if index is not None:
        keep = np.zeros(Qc.shape[-1], dtype=bool)
        keep[np.asarray(index)] = True
        Qc = Qc * (keep[:, None] & keep[None, :])
    return Qc


def _same_inputs(a: tuple | None, b: tuple) -> bool:
    """The arrays of ``a`` are those of ``b`` (the same objects, or equal small ones: ``dt``, the angles)."""
    if a is None or len(a) != len(b):
        return False
    for x, y in zip(a, b):
        if x is y:
            continue
        if x is None or y is None or np.shape(x) != np.shape(y) or np.size(x) > 100_000 or not np.array_equal(x, y):
            return False
    return True


def _process_noise_numpy(sm: SmoothResult, A, b, dt, state_angles) -> np.ndarray:
    m, P, C = sm.m, sm.P, sm.C
    e = m[:, 1:] - (A @ m[:, :-1, :, None])[..., 0] - b
    if state_angles is not None and state_angles.any():
        e = _wrap_where(e, state_angles)
    AC = A @ np.swapaxes(C, -1, -2)  # A_k C_k^T
    S = e[..., :, None] * e[..., None, :] + P[:, 1:] - AC - np.swapaxes(AC, -1, -2)
    S = S + A @ P[:, :-1] @ np.swapaxes(A, -1, -2)
    return symmetrize((S / np.asarray(dt)[None, :, None, None]).mean(1))


def em_measurement_noise(
    sm: SmoothResult,
    channel: Channel,
    H: np.ndarray,
    d: np.ndarray,
    *,
    kernels: str | None,
) -> tuple[np.ndarray, np.ndarray]:
    r"""Closed-form M-step for one channel's noise covariance, linearised ``y ~ H x + d``:

    .. math:: R_j = \frac{1}{M_j}\sum_i \big(r_i r_i^T + H_i P_{k(i)} H_i^T\big),\quad r_i = y_i - H_i m_{k(i)} - d_i

    over the valid samples of each run.

    Parameters
    ----------
    H : (N, M, m, n), d : (N, M, m) the linearisation at each sample
    kernels : the kernels setting (:func:`kalman_forward_affine`)

    Returns
    -------
    R : (N, m, m) (NaN for a run without valid samples) and the count of samples used (N,)
    """
    if sm.r_sums is not None:  # made in the pass, for the same samples and linearisation
        key = (channel.tick, channel.y, channel.valid, H, d, channel.angle)
        for j, src in enumerate(sm.r_from):
            if _same_inputs(src, key):
                m = channel.y.shape[-1]
                return sm.r_sums[:, j, :m, :m].copy(), sm.r_count[:, j].copy()
    fast = twin("em_measurement_noise", kernels)
    if fast is not None:
        return fast(sm, channel, H, d)
    tick = np.asarray(channel.tick)
    m_k = sm.m[:, tick]
    P_k = sm.P[:, tick]
    r = channel.y - (H @ m_k[..., None])[..., 0] - d
    if channel.angle is not None and channel.angle.any():
        r = _wrap_where(r, channel.angle)
    v = np.asarray(channel.valid)
    r = np.where(v[..., None], r, 0.0)
    S = r[..., :, None] * r[..., None, :] + H @ P_k @ np.swapaxes(H, -1, -2)
    S = np.where(v[..., None, None], S, 0.0)
    count = v.sum(1)
    with np.errstate(all="ignore"):
        R = S.sum(1) / count[:, None, None]
    return symmetrize(R), count


# ---------------------------------------------------------------------------------------------- integration
def rk4_with_jacobian(
    f: Callable[[np.ndarray], np.ndarray],
    jac: Callable[[np.ndarray], np.ndarray],
    x: np.ndarray,
    dt: float | np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    r"""One RK4 step of ``x' = f(x)`` and its exact Jacobian ``d x_next / d x`` (chain rule through the
    four stages, with the vector field's Jacobian ``jac``; exact to rounding, no finite differences).

    Parameters
    ----------
    x : (..., n); dt : float or array broadcastable to ``x.shape[:-1]``

    Returns
    -------
    x_next : (..., n), F : (..., n, n)
    """
    dt = np.asarray(dt, dtype=float)
    h = dt[..., None]
    hm = dt[..., None, None]
    k1 = f(x)
    x2 = x + 0.5 * h * k1
    k2 = f(x2)
    x3 = x + 0.5 * h * k2
    k3 = f(x3)
    x4 = x + h * k3
    k4 = f(x4)
    D1 = jac(x)
    J2 = jac(x2)
    D2 = J2 + (0.5 * hm) * (J2 @ D1)
    J3 = jac(x3)
    D3 = J3 + (0.5 * hm) * (J3 @ D2)
    J4 = jac(x4)
    D4 = J4 + hm * (J4 @ D3)
    x_next = x + (h / 6.0) * (k1 + 2.0 * (k2 + k3) + k4)
    F = np.eye(x.shape[-1]) + (hm / 6.0) * (D1 + 2.0 * (D2 + D3) + D4)
    return x_next, F


def finite_difference_h(h: Callable[[np.ndarray], np.ndarray], x: np.ndarray, eps: float = 1e-6):
    """``h(x)`` and its Jacobian ``(..., m, n)`` by central differences (for measurement functions that
    are not analytic, such as a normalised unit vector). One batched call of ``h``."""
    x = np.asarray(x, dtype=float)
    n = x.shape[-1]
    step = eps * np.maximum(1.0, np.abs(x))  # (..., n)
    E = step[..., None, :] * np.eye(n)  # (..., n, n)
    pts = np.concatenate([x[..., None, :], x[..., None, :] + E, x[..., None, :] - E], -2)
    out = h(pts)  # (..., 2n+1, m)
    y = out[..., 0, :]
    J = (out[..., 1 : n + 1, :] - out[..., n + 1 :, :]) / (2.0 * step[..., :, None])
    return y, np.swapaxes(J, -1, -2)
