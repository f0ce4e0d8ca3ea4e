"""The multi-rate UKF of :mod:`needlecli.observers.ukf`, compiled: every tick of every run in one kernel.

Each run is independent (its own sigma points, gains, masks, status), so runs are spread over the cores
(blocks of runs on worker threads, :mod:`needlecli.kernels._threads`) and each run's whole time loop stays
in cache. Inside a run, the sigma points (and the
final-position rollouts riding along) are the lanes of :func:`needlecli.kernels.models.step`.

What it computes is the numpy path's algorithm, operation for operation where it matters for rounding:
the Cholesky factor in the translation order (position-only sigma points displaced as the central one),
translation states propagated relative to the central point, means and residuals about the central
point with angles wrapped, ``P = sym(sum wc dX dX^T + Q)``, the curvature-variance reset at interfaces,
the updates (one scalar state in closed form; several channels that select states jointly, missing
components masked out, chi-square gates per channel, noise reset by distance to a transducer), the
curvature constraint, divergence and singularity per run, and the predictions. The differences are the
order of a few sums (BLAS against loops) and sin/cos (1 ulp), so results agree with the numpy path
to that rounding as the filter carries it (see ``tests/test_kernels.py``).

Covered: channels whose ``h`` selects states (:class:`~needlecli.models.StateSelection`: position, roll,
curvature). A channel with a nonlinear ``h`` needs sigma points through ``h``: :func:`supports` says no
and the observer runs the numpy path.
"""

from __future__ import annotations

import math
from collections import namedtuple

import numpy as np

from needlecli.kernels._jit import inline, jit, lanes
from needlecli.kernels._threads import blocks, parallel_for
from needlecli.kernels.channels import LAYOUT_FULL, LAYOUT_NONE, estimate_arrays, gaussian_part, kept_covariance, kernel_array
from needlecli.kernels.core import PI, repaired_root, solve_into, wrap_if_needed, wrap_inline
from needlecli.kernels.models import equation_id, step_fast
from needlecli.kernels.truth import margin

OK, DIVERGED, SINGULAR = 0, 1, 2
MODE_NONE, MODE_SCALAR, MODE_SELECT = 0, 1, 2


MAX_CHANNELS = 4


def supports(model, chans) -> bool:
    """Whether the kernel covers this filter: a model with compiled equations
    (:attr:`~needlecli.models.Model.compiled_equations`) and at most :data:`MAX_CHANNELS` channels, each
    selecting states."""
    return (model.compiled_equations is not None and len(chans) <= MAX_CHANNELS
            and all(c["select"] is not None for c in chans))


# ---------------------------------------------------------------------------------------------- the records
# What :func:`run` is given, in four records of arrays and numbers (numba takes named tuples as
# arguments; defined here, at module level, so that the cached kernel finds their types again).

#: the filter and its model: mid the compiled equations; x0 (N, n), P0 (n, n); ticks (nt,) grid indices;
#: inputs (1 or N, T, m); params (p,); dt the grid step; angles (n,) bool; order (n,) the states in the
#: translation order, n_act the states through the model, tmask (n,) the translation states; wm, wc
#: (2n+1,) weights, sq_scale; Q (n, n) per tick; kappa_i the curvature state (-1: none), kappa_max (NaN:
#: no constraint), reset_target (-1: no reset); interfaces (1 or N, K), depth (1 or N, T); max_trace;
#: kind, margin the singularity and its states (:func:`needlecli.kernels.truth.margin`), sing_thr
Filter = namedtuple("Filter", "mid x0 P0 ticks inputs params dt angles order n_act tmask wm wc sq_scale Q kappa_i "
                              "kappa_max reset_target interfaces depth max_trace kind margin sing_thr")
#: the channels (C of them, padded to MAX_CHANNELS where a tuple): vals, valids tuples of (N, M_c, m_c)
#: and (N, M_c); m (C,) components; sel, ang, sig2 (C, mm) the states they select, angles, variances;
#: gate (C,) chi-square thresholds (NaN: none); growth (C,) bool with ga, gd (C,), gtr (C, 3) and pos (C,
#: mm) (the axis of each position component, -1: none) of the noise growing with distance
Channels = namedtuple("Channels", "vals valids m sel ang sig2 gate growth ga gd gtr pos")
#: per tick its events (ev_ptr (nt+1,) into ev_chan, ev_sptr, ev_any; ev_sptr into ev_samp: the samples
#: of an event), tick_mode (nt,) MODE_*, pred_count (nt,) predictions started by each tick
Schedule = namedtuple("Schedule", "ev_ptr ev_chan ev_sptr ev_samp ev_any tick_mode pred_count")
#: written in place: states (N, T, n), cov_full or cov_diag as layout (every stride-th step); status,
#: event, repairs, hits, resets (N,); used, gated (N, C); nis tuple of (N, M_c); roll (N, D, n);
#: progress (N,) ticks done
Outputs = namedtuple("Outputs", "states cov_full cov_diag layout stride status event repairs hits resets used gated "
                                "nis roll progress")


# ---------------------------------------------------------------------------------------------- the kernel
#: runs per block: the lanes of every per-run quantity (``x (n, LANES)``, ``P (n, n, LANES)``), so that each
#: scalar operation of the filter is one vector operation over LANES runs; in the model steps the lanes are
#: sigma points times runs (``XL (n, rows * LANES)``, lane ``j * LANES + l``: point ``j`` of run ``l``)
LANES = 8


@jit
def run(lo, hi, f, ch, sc, out):
    """The whole filter for runs ``lo..hi-1``, in blocks of :data:`LANES` runs: the records
    :data:`Filter`, :data:`Channels`, :data:`Schedule` and :data:`Outputs` as prepared by
    :func:`filter_runs` (arrays and numbers: the kernel knows no Python objects); outputs are written in
    place. Releases the GIL."""
    mid, x0, P0, ticks, inputs, params, dt = f.mid, f.x0, f.P0, f.ticks, f.inputs, f.params, f.dt
    angles, order, n_act, tmask, wm, wc, sq_scale, Q = f.angles, f.order, f.n_act, f.tmask, f.wm, f.wc, f.sq_scale, f.Q
    kappa_i, kappa_max, reset_target, interfaces, depth = f.kappa_i, f.kappa_max, f.reset_target, f.interfaces, f.depth
    vals, valids, ch_m, ch_sel, ch_ang, ch_sig2 = ch.vals, ch.valids, ch.m, ch.sel, ch.ang, ch.sig2
    ev_ptr, ev_chan, ev_sptr, ev_samp, tick_mode, pred_count = (sc.ev_ptr, sc.ev_chan, sc.ev_sptr, sc.ev_samp,
                                                                 sc.tick_mode, sc.pred_count)
    status, event, repairs, hits, resets, used = out.status, out.event, out.repairs, out.hits, out.resets, out.used
    nisv, roll, progress = out.nis, out.roll, out.progress
    B = LANES
    n = x0.shape[1]
    nt = ticks.shape[0]
    m_in = inputs.shape[2]
    S = 1 + 2 * n_act
    D = roll.shape[1]
    NL = (S + D) * B
    Mmax = 1
    for c in range(ch_m.shape[0]):
        Mmax += ch_m[c]
    K_if = interfaces.shape[1]
    # the block's state, lanes last
    x = np.empty((n, B))
    P = np.empty((n, n, B))
    xs = np.empty((n, B))
    Ps = np.empty((n, n, B))
    Pp = np.empty((n, n, B))
    Lf = np.empty((n, n, B))
    cols = np.empty((n, n, B))
    dX = np.empty((2 * n + 1, n, B))
    sh = np.empty((n, B))
    Rw = np.empty((2 * n + 1, n, B))
    uu = np.empty((n, B))
    acc = np.empty(B)
    dd = np.empty(B)
    g_ = np.empty(B)
    rs_ = np.empty(B)
    nu_ = np.empty(B)
    s_ = np.empty(B)
    y_ = np.empty(B)
    msk = np.empty(B, dtype=np.bool_)
    ok = np.empty(B, dtype=np.bool_)
    alive = np.zeros(B, dtype=np.bool_)
    was = np.zeros(B, dtype=np.bool_)
    rr = np.empty(B, dtype=np.int64)
    XL = np.zeros((n, NL))
    U = np.zeros((m_in, NL))
    Pm = np.zeros((max(params.shape[0], 1), NL))
    W = np.zeros((4, max(n, 6), NL))
    for j in range(params.shape[0]):
        for i in range(NL):
            Pm[j, i] = params[j]
    # one lane as plain arrays, for what is rare (repairs, joint updates, status)
    x1 = np.empty(n)
    P1 = np.empty((n, n))
    L1 = np.empty((n, n))
    ws = _work(n, Mmax)
    for r0 in range(lo, hi, B):
        nb = min(B, hi - r0)
        for l in range(B):  # lanes past the last run repeat the first (computed, never stored)
            rr[l] = r0 + l if l < nb else r0
            alive[l] = l < nb
        for l in range(B):
            r = rr[l]
            for a in range(n):
                x[a, l] = x0[r, a]
                for b in range(n):
                    P[a, b, l] = P0[a, b]
        for q in range(D):  # prediction rows hold finite states until they start
            for a in range(n):
                for l in range(B):
                    XL[a, (S + q) * B + l] = x[a, l]
        for l in range(nb):
            _emit(out, rr[l], 0, x, P, l)
        for it in range(1, nt):
            k0 = ticks[it - 1]
            k1 = ticks[it]
            _copy_lanes(x, P, xs, Ps)
            for l in range(B):
                was[l] = alive[l]
            nr = pred_count[it - 1]
            # ---- sigma points of every lane (a stopped run's from its held estimate: computed, not used)
            _permute_lanes(P, order, Pp)
            cholesky_lanes(Pp, Lf, ok, acc, dd)
            for l in range(B):
                if not ok[l]:
                    if alive[l]:
                        for a in range(n):
                            for b in range(n):
                                P1[a, b] = Pp[a, b, l]
                        repaired_root(P1, L1, n, 1e-12)
                        for a in range(n):
                            for b in range(n):
                                Lf[a, b, l] = L1[a, b]
                        repairs[rr[l]] += 1
                    else:
                        for a in range(n):
                            for b in range(n):
                                Lf[a, b, l] = 0.0
            _sigma_lanes(x, Lf, order, n_act, tmask, sq_scale, cols, XL)
            # ---- propagate the sigma points and the predictions in flight over the grid steps of the tick
            nl = (S + nr) * B
            for k in range(k0, k1):
                for c in range(m_in):
                    for l in range(B):
                        u = inputs[min(rr[l], inputs.shape[0] - 1), k, c]
                        for j in range(S + nr):
                            U[c, j * B + l] = u
                step_fast(mid, XL, U, Pm, dt, nl, W)
            _mean_cov_lanes(XL, cols, n_act, angles, tmask, wm, wc, Q, xs, x, P, dX, sh, Rw, acc)
            # ---- tissue interface: reset the curvature variance
            if reset_target >= 0.0 and kappa_i >= 0 and K_if > 0:
                for l in range(B):
                    if alive[l]:
                        r = rr[l]
                        rd = min(r, depth.shape[0] - 1)
                        rf = min(r, interfaces.shape[0] - 1)
                        d0 = depth[rd, k0]
                        d1 = depth[rd, k1]
                        crossed = False
                        for q in range(K_if):
                            if d0 < interfaces[rf, q] and interfaces[rf, q] <= d1:
                                crossed = True
                        if crossed:
                            t_ = reset_target - P[kappa_i, kappa_i, l]
                            P[kappa_i, kappa_i, l] += t_ if not t_ < 0.0 else 0.0
                            resets[r] += 1
            # ---- update with what arrived in (t_k0, t_k1]
            mode = tick_mode[it]
            if mode == MODE_SCALAR:
                e = ev_ptr[it]
                c = ev_chan[e]
                j = ev_samp[ev_sptr[e]]
                vc = valids[c]
                yc = vals[c]
                for l in range(B):
                    msk[l] = alive[l] and vc[rr[l], j]
                    y_[l] = yc[rr[l], j, 0]
                _update_scalar_lanes(x, P, ch_sel[c, 0], y_, msk, ch_ang[c, 0], ch_sig2[c, 0], uu, g_, rs_, nu_, s_)
                nc = nisv[c]
                for l in range(nb):
                    if msk[l]:
                        used[rr[l], c] += 1
                        nc[rr[l], j] = nu_[l] * nu_[l] / s_[l]
            elif mode == MODE_SELECT:
                for l in range(nb):
                    if alive[l]:
                        _get_lane(x, P, l, x1, P1)
                        _update_select(rr[l], it, x1, P1, ch, sc, out, ws)
                        _set_lane(x1, P1, l, x, P)
            if mode != MODE_NONE:
                _wrap_lanes(x, angles)
            # ---- curvature constraint, divergence, singularity: per run (a stopped run holds its last
            # good estimate)
            for l in range(nb):
                if not alive[l]:
                    continue
                r = rr[l]
                if kappa_i >= 0 and not math.isnan(kappa_max):
                    kk = x[kappa_i, l]
                    if kk < 0.0 or kk > kappa_max:
                        x[kappa_i, l] = xs[kappa_i, l]
                        hits[r] += 1
                code = _check_lane(x, xs, P, l, f.kind, f.margin, f.sing_thr, f.max_trace)
                if code != OK:
                    alive[l] = False
                    status[r] = code
                    event[r] = k1
            for l in range(B):
                if not alive[l]:
                    _restore_lane(xs, Ps, l, x, P)
            # ---- store: the steps between ticks hold the last tick's estimate
            for l in range(nb):
                r = rr[l]
                for k in range(k0 + 1, k1):
                    _emit(out, r, k, xs, Ps, l)
                _emit(out, r, k1, x, P, l)
                progress[r] = it
            for q in range(pred_count[it - 1], pred_count[it]):  # predictions that start now
                for a in range(n):
                    for l in range(B):
                        XL[a, (S + q) * B + l] = x[a, l]
        for l in range(nb):
            for q in range(pred_count[nt - 1]):
                for a in range(n):
                    roll[rr[l], q, a] = XL[a, (S + q) * B + l]


# ---------------------------------------------------------------------------------------------- lanes
@inline
def _wrap_needed(a):
    return wrap_inline(a) if not abs(a) < PI else a


@lanes
def _copy_lanes(x, P, x_to, P_to):
    n = x.shape[0]
    for a in range(n):
        for l in range(LANES):
            x_to[a, l] = x[a, l]
        for b in range(n):
            for l in range(LANES):
                P_to[a, b, l] = P[a, b, l]


@lanes
def _permute_lanes(P, order, Pp):
    n = P.shape[0]
    for a in range(n):
        for b in range(n):
            for l in range(LANES):
                Pp[a, b, l] = P[order[a], order[b], l]


@lanes
def cholesky_lanes(A, L, ok, acc, dd):
    """:func:`~needlecli.kernels.core.cholesky_into` on every lane: ``ok[l]`` False where lane ``l`` is not
    numerically positive definite (its factor is then garbage: the caller repairs it)."""
    n = A.shape[0]
    for l in range(LANES):
        ok[l] = True
    for j in range(n):
        for l in range(LANES):
            acc[l] = A[j, j, l]
        for k in range(j):
            for l in range(LANES):
                acc[l] -= L[j, k, l] * L[j, k, l]
        for l in range(LANES):
            ok[l] = ok[l] and acc[l] > 0.0
            dd[l] = np.sqrt(acc[l]) if acc[l] > 0.0 else 1.0
            L[j, j, l] = dd[l]
        for i in range(j + 1, n):
            for l in range(LANES):
                acc[l] = A[i, j, l]
            for k in range(j):
                for l in range(LANES):
                    acc[l] -= L[i, k, l] * L[j, k, l]
            for l in range(LANES):
                L[i, j, l] = acc[l] / dd[l]
        for i in range(j):
            for l in range(LANES):
                L[i, j, l] = 0.0


@lanes
def _sigma_lanes(x, Lf, order, n_act, tmask, sq_scale, cols, XL):
    """Sigma points of every lane into rows ``0 .. 2 n_act`` of ``XL`` (translation states relative to the
    central point); ``cols[j]`` the j-th column of ``sqrt(scale P)`` (the factor in the translation order)."""
    n = x.shape[0]
    B = LANES
    for a in range(n):
        for j in range(n):
            for l in range(B):
                cols[j, order[a], l] = Lf[a, j, l] * sq_scale
    for a in range(n):
        if tmask[a]:
            for l in range(B):
                XL[a, l] = 0.0
            for j in range(n_act):
                for l in range(B):
                    XL[a, (1 + j) * B + l] = cols[j, a, l]
                    XL[a, (1 + n_act + j) * B + l] = -cols[j, a, l]
        else:
            for l in range(B):
                XL[a, l] = x[a, l]
            for j in range(n_act):
                for l in range(B):
                    XL[a, (1 + j) * B + l] = x[a, l] + cols[j, a, l]
                    XL[a, (1 + n_act + j) * B + l] = x[a, l] - cols[j, a, l]


@lanes
def _mean_cov_lanes(XL, cols, n_act, angles, tmask, wm, wc, Q, xs, x, P, dX, sh, Rw, acc):
    """Weighted mean and covariance of the 2n+1 propagated points of every lane (the position-only ones
    displaced as the central one), residuals about the central point, angles wrapped;
    ``P = sum wc dX dX^T + Q`` (its lower triangle computed, mirrored). Every sum over points runs in point
    order: the numbers of the scalar filter, lane by lane. ``dX``, ``Rw (2n + 1, n, LANES)``: the
    residuals (centred in place), and them times their weights; ``acc (LANES,)`` scratch."""
    n = x.shape[0]
    B = LANES
    S = 1 + 2 * n_act
    n_fix = n - n_act
    n_pts = 2 * n + 1
    for a in range(n):
        for l in range(B):
            sh[a, l] = 0.0
            dX[0, a, l] = 0.0  # the central point's residual
    for j in range(1, S):
        w_ = wm[j]
        for a in range(n):
            if angles[a]:
                for l in range(B):
                    d = _wrap_needed(XL[a, j * B + l] - XL[a, l])
                    dX[j, a, l] = d
                    sh[a, l] += w_ * d
            else:
                for l in range(B):
                    d = XL[a, j * B + l] - XL[a, l]
                    dX[j, a, l] = d
                    sh[a, l] += w_ * d
    for h in range(2):
        sgn = 1.0 if h == 0 else -1.0
        for j in range(n_fix):
            p_ = S + h * n_fix + j
            w_ = wm[p_]
            for a in range(n):
                for l in range(B):
                    ref = XL[a, l]
                    d = (ref + sgn * cols[n_act + j, a, l]) - ref
                    if angles[a]:
                        d = _wrap_needed(d)
                    dX[p_, a, l] = d
                    sh[a, l] += w_ * d
    for a in range(n):
        for l in range(B):
            mv = XL[a, l] + sh[a, l]
            if angles[a]:
                mv = _wrap_needed(mv)
            x[a, l] = mv + xs[a, l] if tmask[a] else mv
    for j in range(n_pts):  # centred residuals, and times their weights
        w_ = wc[j]
        for a in range(n):
            if angles[a]:
                for l in range(B):
                    d = _wrap_needed(dX[j, a, l] - sh[a, l])
                    dX[j, a, l] = d
                    Rw[j, a, l] = d * w_
            else:
                for l in range(B):
                    d = dX[j, a, l] - sh[a, l]
                    dX[j, a, l] = d
                    Rw[j, a, l] = d * w_
    for a in range(n):
        for b in range(a + 1):
            q_ = Q[a, b]
            for l in range(B):  # the sum in registers (P[a, b] and P[b, a] are one array)
                acc[l] = 0.0
            for j in range(n_pts):
                for l in range(B):
                    acc[l] += Rw[j, a, l] * dX[j, b, l]
            for l in range(B):
                p_ = acc[l] + q_
                P[a, b, l] = p_
                P[b, a, l] = p_


@lanes
def _update_scalar_lanes(x, P, i_s, y, msk, angle, sig2, u, g, rs, nu, s0):
    """:func:`_update_scalar` on the lanes where ``msk`` (one scalar sample ``y`` of state ``i_s``); the
    others unchanged. ``nu``, ``s0``: the innovation and its variance (for the normalised innovation)."""
    n = x.shape[0]
    B = LANES
    for l in range(B):
        d = y[l] - x[i_s, l]
        if angle:
            d = wrap_inline(d)
        nu[l] = d
        sv = P[i_s, i_s, l] + sig2
        s0[l] = sv
        g[l] = d / sv
        rs[l] = np.sqrt(sv)
    for a in range(n):
        for l in range(B):
            pa = P[a, i_s, l]
            u[a, l] = pa / rs[l]
            xa = x[a, l] + pa * g[l]
            x[a, l] = xa if msk[l] else x[a, l]
    for a in range(n):
        for b in range(n):
            for l in range(B):
                pn = P[a, b, l] - u[a, l] * u[b, l]
                P[a, b, l] = pn if msk[l] else P[a, b, l]


@lanes
def _wrap_lanes(x, angles):
    n = x.shape[0]
    for a in range(n):
        if angles[a]:
            for l in range(LANES):
                x[a, l] = _wrap_needed(x[a, l])


@jit
def _get_lane(x, P, l, x1, P1):
    n = x.shape[0]
    for a in range(n):
        x1[a] = x[a, l]
        for b in range(n):
            P1[a, b] = P[a, b, l]


@jit
def _set_lane(x1, P1, l, x, P):
    n = x.shape[0]
    for a in range(n):
        x[a, l] = x1[a]
        for b in range(n):
            P[a, b, l] = P1[a, b]


@jit
def _restore_lane(xs, Ps, l, x, P):
    n = x.shape[0]
    for a in range(n):
        x[a, l] = xs[a, l]
        for b in range(n):
            P[a, b, l] = Ps[a, b, l]


_Work = namedtuple("_Work", "Pp Lf C Kg yv msk Rv sel ang nu blk_c blk_0 Pyy Pxy A B Xs KS g1 g2 idx blk_j")


@jit
def _work(n, M):
    """Scratch of one run (allocated once per run)."""
    return _Work(np.empty((n, n)), np.empty((n, n)), np.empty((n, n)), np.empty((n, 1)), np.empty(M), np.empty(M),
                 np.empty(M), np.empty(M, dtype=np.int64), np.empty(M, dtype=np.bool_), np.empty(M),
                 np.empty(M, dtype=np.int64), np.empty(M, dtype=np.int64), np.empty((M, M)), np.empty((n, M)),
                 np.empty((M, max(M, n))), np.empty((M, n)), np.empty((M, n)), np.empty((n, M)), np.empty((M, 1)),
                 np.empty((M, 1)), np.empty(M, dtype=np.int64), np.empty(M, dtype=np.int64))


@jit
def _update_select(r, it, x, P, ch, sc, out, ws):
    """Joint update of run ``r`` at tick ``it`` (``x (n,)``, ``P (n, n)``) with every channel of this tick,
    each selecting states (the numpy path's ``_update`` with ``X = None``): the latest valid sample of a
    channel wins, missing channels are masked out, noise reset by distance where configured, chi-square
    gates per channel; the normalised innovation squared of each channel's sample used (its own block of
    ``S``) goes to ``out.nis``."""
    vals, valids, ch_m, ch_sel, ch_ang, ch_sig2 = ch.vals, ch.valids, ch.m, ch.sel, ch.ang, ch.sig2
    ch_gate, ch_growth, ch_ga, ch_gd, ch_gtr, ch_pos = ch.gate, ch.growth, ch.ga, ch.gd, ch.gtr, ch.pos
    ev_ptr, ev_chan, ev_sptr, ev_samp, ev_any = sc.ev_ptr, sc.ev_chan, sc.ev_sptr, sc.ev_samp, sc.ev_any
    used, gated, nisv = out.used, out.gated, out.nis
    n = x.shape[0]
    yv, msk, Rv, sel, ang, nu = ws.yv, ws.msk, ws.Rv, ws.sel, ws.ang, ws.nu
    Pyy, Pxy = ws.Pyy, ws.Pxy
    M = 0
    Mtot = 0
    nb = 0
    for e in range(ev_ptr[it], ev_ptr[it + 1]):
        c = ev_chan[e]
        mc = ch_m[c]
        v = False
        jv = -1
        for q in range(ev_sptr[e], ev_sptr[e + 1]):
            j = ev_samp[q]
            if valids[c][r, j]:
                v = True
                jv = j
                for k in range(mc):
                    yv[M + k] = vals[c][r, j, k]
        if not ev_any[e]:  # no run has a sample: the numpy path leaves the channel out
            continue
        Mtot += mc
        f_ = 1.0
        if ch_growth[c] and v:
            dd = 0.0
            for k in range(mc):
                if ch_pos[c, k] >= 0:
                    t_ = yv[M + k] - ch_gtr[c, ch_pos[c, k]]
                    dd += t_ * t_
            f_ = 1.0 + ch_ga[c] * math.sqrt(dd) / ch_gd[c]
        for k in range(mc):
            sel[M + k] = ch_sel[c, k]
            ang[M + k] = ch_ang[c, k]
            msk[M + k] = 1.0 if v else 0.0
            rv = ch_sig2[c, k]
            if ch_growth[c] and ch_pos[c, k] >= 0:
                rv = rv * (f_ * f_)
            Rv[M + k] = rv
            if not v:
                yv[M + k] = 0.0
        ws.blk_c[nb] = c
        ws.blk_0[nb] = M
        ws.blk_j[nb] = jv
        nb += 1
        M += mc
    if M == 0:
        return
    for k in range(M):
        d = yv[k] - x[sel[k]]
        if ang[k]:
            d = wrap_if_needed(d)
        nu[k] = d * msk[k]
        for l in range(M):
            Pyy[k, l] = P[sel[k], sel[l]]
        Pyy[k, k] += Rv[k]
        for a in range(n):
            Pxy[a, k] = P[a, sel[k]]
    for b_ in range(nb):  # chi-square gates per channel block
        c = ws.blk_c[b_]
        o = ws.blk_0[b_]
        mc = ch_m[c]
        on = msk[o] > 0.0
        if on:
            if mc == 1:
                nis = nu[o] * nu[o] / Pyy[o, o]
            else:
                for k in range(mc):
                    ws.g1[k, 0] = nu[o + k]
                    for l in range(mc):
                        ws.A[k, l] = Pyy[o + k, o + l]
                solve_into(ws.A, ws.g1, ws.g2, mc, 1)
                nis = 0.0
                for k in range(mc):
                    nis += nu[o + k] * ws.g2[k, 0]
            if not math.isnan(ch_gate[c]) and not nis <= ch_gate[c]:
                for k in range(mc):
                    msk[o + k] = 0.0
                    nu[o + k] = 0.0
                gated[r, c] += 1
                on = False
        if on:
            used[r, c] += 1
            nisv[c][r, ws.blk_j[b_]] = nis
    if Mtot == 1:  # one scalar measurement: the closed form without a solve
        if msk[0] > 0.0:
            s0 = Pyy[0, 0]
            g = nu[0] / s0
            rs = math.sqrt(s0)
            for a in range(n):
                x[a] = x[a] + Pxy[a, 0] * g
                ws.Kg[a, 0] = Pxy[a, 0] / rs
            for a in range(n):
                for b in range(n):
                    P[a, b] = P[a, b] - ws.Kg[a, 0] * ws.Kg[b, 0]
        return
    mv = 0  # the components that arrived: K = Pxy Pyy^-1 on those (masked ones have zero gain)
    for k in range(M):
        if msk[k] > 0.0:
            ws.idx[mv] = k
            mv += 1
    if mv == 0:
        return
    A, B, Xs, KS, C = ws.A, ws.B, ws.Xs, ws.KS, ws.C
    idx = ws.idx
    for k in range(mv):
        for l in range(mv):
            A[k, l] = Pyy[idx[k], idx[l]]
        for a in range(n):
            B[k, a] = Pxy[a, idx[k]]
    solve_into(A, B, Xs, mv, n)  # K^T (mv, n)
    for a in range(n):
        s_ = 0.0
        for k in range(mv):
            s_ += Xs[k, a] * nu[idx[k]]
        x[a] = x[a] + s_
    for a in range(n):
        for k in range(mv):
            s_ = 0.0
            for l in range(mv):
                s_ += Xs[l, a] * A[l, k]
            KS[a, k] = s_
    for a in range(n):
        for b in range(n):
            s_ = 0.0
            for k in range(mv):
                s_ += KS[a, k] * Xs[k, b]
            C[a, b] = P[a, b] - s_
    for a in range(n):
        for b in range(n):
            P[a, b] = 0.5 * (C[a, b] + C[b, a])


@jit
def _check_lane(x, xs, P, l, kind, mi, sing_thr, max_trace):
    """Divergence (non-finite estimate or covariance, trace beyond ``max_trace``) and the model's
    singularity (left the domain, or jumped over it since ``xs``; ``kind`` and its states ``mi``:
    :func:`needlecli.kernels.truth.margin`) of lane ``l``: the run's status code."""
    n = x.shape[0]
    tr = 0.0
    for a in range(n):
        tr += P[a, a, l]
    finite = np.isfinite(tr)
    for a in range(n):
        if not np.isfinite(x[a, l]):
            finite = False
    sing = False
    if kind == 1:
        sing = not math.cos(x[mi[0], l]) > sing_thr
    elif kind == 2:
        h0, h1, h2 = x[mi[0], l], x[mi[1], l], x[mi[2], l]
        b0, b1, b2 = x[mi[3], l], x[mi[4], l], x[mi[5], l]
        dd = h0 * b0 + h1 * b1 + h2 * b2
        mg = abs(dd) / (math.sqrt(h0 * h0 + h1 * h1 + h2 * h2) * math.sqrt(b0 * b0 + b1 * b1 + b2 * b2))
        d0 = xs[mi[0], l] * xs[mi[3], l] + xs[mi[1], l] * xs[mi[4], l] + xs[mi[2], l] * xs[mi[5], l]
        sing = (not mg > sing_thr) or d0 * dd < 0.0
    if (not finite) or tr > max_trace or sing:
        return SINGULAR if (sing and finite) else DIVERGED
    return OK


@jit
def _emit(out, r, k, x, P, l):
    """Lane ``l``'s estimate as run ``r``'s at grid step ``k`` (and its covariance where kept)."""
    states, cov_full, cov_diag, layout, stride = out.states, out.cov_full, out.cov_diag, out.layout, out.stride
    n = x.shape[0]
    for a in range(n):
        states[r, k, a] = x[a, l]
    if layout == LAYOUT_NONE or k % stride != 0:
        return
    j = k // stride
    if layout == LAYOUT_FULL:
        for a in range(n):
            for b in range(n):
                cov_full[r, j, a, b] = P[a, b, l]
    else:
        for a in range(n):
            cov_diag[r, j, a] = P[a, a, l]


# ---------------------------------------------------------------------------------------------- the seam
def filter_runs(model, params, problem, s, chans, ticks, inputs, x0, P0, Q, kappa_i, interfaces,
                depths, weights, order, n_act, progress=None) -> dict:
    """Everything :meth:`UnscentedKalmanFilter.run` computes in its tick loop, from the arrays it has set
    up (its names), by :func:`run`."""
    N, n = x0.shape
    T = len(problem.time)
    nt = len(ticks)
    dt_grid = float(problem.time[1] - problem.time[0]) if T > 1 else 1.0
    mid = equation_id(model)
    angles = kernel_array(model.angle_mask, dtype=np.bool_)
    tmask = np.zeros(n, dtype=np.bool_)
    if order is None:
        order_a = np.arange(n, dtype=np.int64)
    else:
        order_a = np.arange(n, dtype=np.int64)[order].astype(np.int64)
        tmask[[model.index(k) for k in model.translation_states]] = True
    p_arr = np.array([float(np.asarray(v)) for v in params.values()], dtype=float)
    u = inputs
    u3 = kernel_array(u[:1] if u.strides[0] == 0 else u, dtype=float)
    depth = problem.depth
    depth2 = kernel_array(depth[:1] if depth.strides[0] == 0 else depth, dtype=float)
    itf = np.asarray(interfaces, dtype=float)
    itf2 = kernel_array(itf.reshape(1, -1) if itf.ndim == 1 else itf)
    reset_target = -1.0
    if s.kappa_reset is not None and kappa_i is not None and itf.size:
        reset_target = float(s.kappa_reset.factor * P0[kappa_i, kappa_i])
    # ---- channels as arrays; their samples as a tuple of MAX_CHANNELS arrays (padded: one compiled kernel for
    # any number of channels; numba's typed lists would cost 0.6 s of compilation in every process)
    C = len(chans)
    ch_m = np.array([c["m"] for c in chans], dtype=np.int64)
    ch_sel, ch_ang, ch_sig2, ch_gate, ch_growth, ch_ga, ch_gd, ch_gtr, ch_pos = gaussian_part(chans, "select", 0.0)
    vals, valids = [], []
    for c in chans:
        vals.append(kernel_array(c["value"], dtype=float))
        valids.append(kernel_array(c["valid"], dtype=np.bool_))
    nisv = tuple([np.full(np.shape(c["valid"]), np.nan) for c in chans] + [np.full((1, 1), np.nan)] * (MAX_CHANNELS - C))
    vals = tuple(vals + [np.zeros((1, 1, 1))] * (MAX_CHANNELS - C))
    valids = tuple(valids + [np.zeros((1, 1), dtype=np.bool_)] * (MAX_CHANNELS - C))
    # ---- the schedule (UnscentedKalmanFilter._schedule as arrays): per tick its events, each a channel and
    # the samples of it that became available since the last tick (time order); channels in their order
    e_tick, e_chan, e_first, e_count, samples, any_valid = [], [], [], [], [], []
    base = 0
    for ci, c in enumerate(chans):
        tick_of = np.searchsorted(ticks, c["avail"], side="left")  # c["avail"] sorted, c["order"] maps back
        keep = (tick_of > 0) & (tick_of < nt)  # samples available at the first tick serve initialisation
        t_k, j_k = tick_of[keep], np.asarray(c["order"])[keep]
        starts = np.flatnonzero(np.r_[True, t_k[1:] != t_k[:-1]]) if t_k.size else np.zeros(0, dtype=np.int64)
        e_tick.append(t_k[starts])
        e_chan.append(np.full(starts.size, ci))
        e_first.append(base + starts)
        e_count.append(np.diff(np.r_[starts, t_k.size]))
        samples.append(j_k)
        any_valid.append(np.asarray(c["valid"]).any(axis=0)[j_k])  # does any run have this sample
        base += t_k.size
    cat = (lambda parts, dt: np.concatenate(parts).astype(dt) if parts else np.zeros(0, dtype=dt))
    e_tick, e_chan = cat(e_tick, np.int64), cat(e_chan, np.int64)
    e_first, e_count = cat(e_first, np.int64), cat(e_count, np.int64)
    samples, any_valid = cat(samples, np.int64), cat(any_valid, np.bool_)
    o = np.lexsort((e_chan, e_tick))  # by tick, then channel
    e_tick, e_chan, e_first, e_count = e_tick[o], e_chan[o], e_first[o], e_count[o]
    ev_sptr_a = np.r_[0, np.cumsum(e_count)].astype(np.int64)
    gather = np.repeat(e_first - ev_sptr_a[:-1], e_count) + np.arange(ev_sptr_a[-1])
    ev_samp_a = samples[gather] if gather.size else np.zeros(1, dtype=np.int64)
    ev_any_a = np.logical_or.reduceat(any_valid[gather], ev_sptr_a[:-1]) if gather.size else np.zeros(1, dtype=np.bool_)
    ev_chan_a = e_chan if e_chan.size else np.zeros(1, dtype=np.int64)
    ev_ptr = np.searchsorted(e_tick, np.arange(nt + 1), side="left").astype(np.int64)
    n_ev = np.diff(ev_ptr)
    mode = np.where(n_ev == 0, MODE_NONE, MODE_SELECT).astype(np.int64)
    if e_chan.size:
        first = np.minimum(ev_ptr[:-1], e_chan.size - 1)
        scalar = np.array([c["scalar"] for c in chans], dtype=bool)
        mode[(n_ev == 1) & scalar[e_chan[first]] & (e_count[first] == 1)] = MODE_SCALAR
    # ---- predictions: which start at which tick (from the first run's depth, as the numpy path)
    D = len(depths)
    pred_tick = np.full(D, -1, dtype=np.int64)
    pred_count = np.zeros(nt, dtype=np.int64)
    started = 0
    for i in range(1, nt):
        if D:
            dnow = problem.depth[0, ticks[i]]
            due = np.nonzero((pred_tick < 0) & (depths <= dnow + 1e-9))[0]
            pred_tick[due] = ticks[i]
            started += due.size
        pred_count[i] = started
    # ---- outputs
    states, layout, stride, cov_full, cov_diag = estimate_arrays(problem, N, T, n)
    status = np.zeros(N, dtype=np.int64)
    event = np.full(N, -1, dtype=np.int64)
    repairs = np.zeros(N, dtype=np.int64)
    hits = np.zeros(N, dtype=np.int64)
    resets = np.zeros(N, dtype=np.int64)
    used = np.zeros((N, max(C, 1)), dtype=np.int64)
    gated = np.zeros((N, max(C, 1)), dtype=np.int64)
    roll = np.full((N, D, n), np.nan)
    prog = np.zeros(N, dtype=np.int64)
    kind, mi = margin(model)
    kmax = float(s.kappa_max) if s.kappa_max is not None else np.nan
    args = (Filter(mid, kernel_array(x0, dtype=float), kernel_array(P0, dtype=float),
                   kernel_array(ticks, dtype=np.int64), u3, p_arr, dt_grid, angles, order_a, int(n_act), tmask,
                   kernel_array(weights.wm), kernel_array(weights.wc), float(np.sqrt(weights.scale)),
                   kernel_array(Q, dtype=float), -1 if kappa_i is None else int(kappa_i), kmax, reset_target,
                   itf2 if itf2.shape[1] else np.zeros((1, 0)), depth2, float(s.max_cov_trace), kind, mi,
                   float(model.singular_threshold)),
            Channels(vals, valids, ch_m if C else np.zeros(1, dtype=np.int64), ch_sel, ch_ang, ch_sig2, ch_gate,
                     ch_growth, ch_ga, ch_gd, ch_gtr, ch_pos),
            Schedule(ev_ptr, ev_chan_a, ev_sptr_a, ev_samp_a, ev_any_a, mode, pred_count),
            Outputs(states, cov_full, cov_diag, layout, stride, status, event, repairs, hits, resets, used, gated, nisv,
                    roll, prog))
    total = N * max(nt - 1, 1)
    poll = None if progress is None else (lambda: progress(int(prog.sum()) * (nt - 1) // total, nt - 1))
    parallel_for(run, blocks(N, minimum=LANES), args, poll)
    cov = kept_covariance(layout, cov_full, cov_diag)
    return {"states": states, "cov": cov, "status": status, "event": event, "repairs": repairs, "hits": hits,
            "resets": resets, "used": used[:, :C], "gated": gated[:, :C], "nis": nisv[:C], "roll": roll,
            "pred_tick": pred_tick}
