"""The particle filters of :mod:`needlecli.observers.pf` (``pf``, and ``rbpf``'s marginal numerics),
compiled: every tick of every run in one kernel.

Runs are independent, so they are spread over the cores (blocks of runs on worker threads,
:mod:`needlecli.kernels._threads`); inside a run the particles are the lanes of
:func:`needlecli.kernels.models.step_fast` (``X (n, P)``, component-major), so a run's whole time loop
works on a few arrays that stay in cache.

The random numbers are the numpy path's: the same counter-based hashes (SplitMix64's finaliser of the
key, the draw's purpose, the run, the tick and the particle's component), computed here in ``uint64``
arithmetic, and the same Box-Muller transform (sine and cosine from one tangent of the half angle, as
:func:`needlecli.numerics.sincos`); nothing random is passed in. What it computes is the numpy path's
algorithm step for step: the prediction (RK4 on the grid steps, noise per tick, angles wrapped where
needed, the model's projection), dead particles (the model's declared singularity, non-finite states),
the updates channel by channel with the latest valid sample of each (Gaussian or Student-t, noise grown
with distance, chi-square gates against the cloud, NIS; a marginal channel's Kalman update), the
weights, the ESS, the estimate (circular means of angles), the status, and systematic resampling with
Liu and West's jitter. The differences are the order of a few sums (BLAS against loops) and the last bit of
``log``, ``tan`` and the models' sines (1 ulp), so results agree with the numpy path to that rounding
(``tests/twins.py``).

Covered: channels whose ``h`` selects states or is a unit vector of states (a model's declared
``unit_vectors``: the magnetic models' tangent and field direction), at most :data:`MAX_CHANNELS`, models
with compiled equations. One-sided channels (the image plane's probit) and other ``h``: the numpy path.
"""

from __future__ import annotations

import math
from collections import namedtuple

import numpy as np

from needlecli.kernels._jit import inline, jit
from needlecli.kernels._threads import blocks, parallel_for
from needlecli.kernels.channels import LAYOUT_FULL, LAYOUT_NONE, estimate_arrays, gaussian_part, kept_covariance, kernel_array
from needlecli.kernels.core import PI, cholesky_into, repaired_root, solve_into, wrap_inline
from needlecli.kernels.models import equation_id, normalize, step_fast
from needlecli.kernels.truth import margin

OK, DIVERGED, SINGULAR, DEAD = 0, 1, 2, 3
INIT, PROCESS, RESAMPLE, ROUGHEN = 0, 1, 2, 3  # as needlecli.observers.pf
MAX_CHANNELS = 4
_G = np.uint64(0x9E3779B97F4A7C15)
_M1 = np.uint64(0xBF58476D1CE4E5B9)
_M2 = np.uint64(0x94D049BB133111EB)
_S30, _S27, _S31, _S11 = np.uint64(30), np.uint64(27), np.uint64(31), np.uint64(11)
_TWO_53 = 2.0**-53
_LOG_2PI = math.log(2.0 * math.pi)


def supports(model, chans, bounds) -> bool:
    """Whether the kernel covers this filter: a model with compiled equations, no one-sided channel, at
    most :data:`MAX_CHANNELS` channels, each selecting states or a unit vector of states."""
    return (model.compiled_equations is not None and not bounds and len(chans) <= MAX_CHANNELS
            and all(c["kind"] in (0, 1) for c in chans))


# ---------------------------------------------------------------------------------------------- the records
#: the filter: mid the compiled equations; x0 (N, n) initial means, B0 (n, k) the factor of the k drawn
#: states; ticks (K,); inputs (1 or N, T, m); params (p,); dt; angles (n,) bool; q (n,) noise std per tick,
#: noisy (j,) the states with noise; marg (t,) translation states in Kalman filters (t = 0: none), Pp0, Qp
#: (t, t); key (uint64); P particles; below the ESS fraction; rough; drawn (k,) the particle states; kind,
#: mi, sing_thr the singularity (needlecli.kernels.truth.margin); max_trace
Filter = namedtuple("Filter", "mid x0 B0 ticks inputs params dt angles q noisy marg Pp0 Qp key P below rough drawn "
                              "kind mi sing_thr max_trace")
#: the channels (C, padded to MAX_CHANNELS in the tuples): vals (N, M, m), valids (N, M); m (C,); kind (C,)
#: 0 selection, 1 unit vector; idx, ang, sig2, pos, mpos (C, mm); gate (C,) (NaN: none); growth (C,) bool,
#: ga, gd (C,), gtr (C, 3); student (C,) bool, dof, const (C,); marginal (C,) bool (mpos: the entries'
#: places among the translation states)
Channels = namedtuple("Channels", "vals valids m kind idx ang sig2 gate growth ga gd gtr pos student dof const "
                                  "marginal mpos")
#: per tick its events (ev_ptr (K+1,) into ev_chan, ev_sptr; ev_sptr into ev_samp: the samples of an event)
Schedule = namedtuple("Schedule", "ev_ptr ev_chan ev_sptr ev_samp")
#: written in place: states (N, T, n); cov_full or cov_diag as layout, every stride-th step; status, event
#: (N,); used, gated (N, C); nis tuple of (N, M_c); ess, resampled (N, K); loglik (N,); progress (N,)
Outputs = namedtuple("Outputs", "states cov_full cov_diag layout stride status event used gated nis ess resampled "
                                "loglik progress")


# ---------------------------------------------------------------------------------------------- random numbers
@inline
def _mix(z):
    z = (z ^ (z >> _S30)) * _M1
    z = (z ^ (z >> _S27)) * _M2
    return z ^ (z >> _S31)


@jit
def stream_base(key, purpose, run, tick):
    """:func:`needlecli.observers.pf.stream_base` of one run."""
    b = _mix(np.uint64(key) + _G * np.uint64(purpose + 1))
    b = _mix(b + _G * (np.uint64(run) + np.uint64(1)))
    return _mix(b + _G * np.uint64(tick + 1))


@inline
def uniform(base, e):
    """Draw ``e`` (0-based) of :func:`needlecli.observers.pf.uniforms`."""
    z = _mix(base + _G * (np.uint64(e) + np.uint64(1)))
    return float(z >> _S11) * _TWO_53


@jit
def fill_normals(base, count, out):
    """``out[:count]`` = draws ``0..count-1`` of :func:`needlecli.observers.pf.normals` (each Box-Muller pair
    computed once)."""
    for j in range((count + 1) // 2):
        u1 = uniform(base, 2 * j)
        u2 = uniform(base, 2 * j + 1)
        rho = math.sqrt(-2.0 * math.log1p(-u1))
        t = math.tan(((2.0 * PI) * u2) * 0.5)
        t2 = t * t
        r = 1.0 / (t2 + 1.0)
        out[2 * j] = rho * ((1.0 - t2) * r)
        if 2 * j + 1 < count:
            out[2 * j + 1] = rho * ((t + t) * r)


@inline
def _sincos_half(a):
    """``(sin a, cos a)`` as :func:`needlecli.numerics.sincos` computes them."""
    t = math.tan(a * 0.5)
    t2 = t * t
    r = 1.0 / (t2 + 1.0)
    return (t + t) * r, (1.0 - t2) * r


@inline
def _wrap_needed(a):
    return wrap_inline(a) if not abs(a) < PI else a


# ---------------------------------------------------------------------------------------------- the kernel
@jit
def run(lo, hi, f, ch, sc, out):
    """The whole filter for runs ``lo..hi-1``: the records :data:`Filter`, :data:`Channels`,
    :data:`Schedule`, :data:`Outputs` as prepared by :func:`filter_runs`; outputs written in place.
    Releases the GIL."""
    P = f.P
    n = f.x0.shape[1]
    K = f.ticks.shape[0]
    m_in = f.inputs.shape[2]
    k_dr = f.drawn.shape[0]
    nt = f.marg.shape[0]
    nq = f.noisy.shape[0]
    mmax = 1
    for c in range(ch.m.shape[0]):
        mmax = max(mmax, ch.m[c])
    X = np.empty((n, P))
    Xp = np.empty((n, P))
    Xn = np.empty((n, P))
    U = np.zeros((m_in, P))
    Pm = np.zeros((max(f.params.shape[0], 1), P))
    for j in range(f.params.shape[0]):
        for i in range(P):
            Pm[j, i] = f.params[j]
    W = np.zeros((4, max(n, 6), P))
    lw = np.empty(P)
    post = np.empty(P)
    w = np.empty(P)
    nu = np.empty((mmax, P))
    cum = np.empty(P)
    idx = np.empty(P, dtype=np.int64)
    left = np.empty(P, dtype=np.bool_)
    x = np.empty(n)
    xh = np.empty(n)
    C = np.empty((n, n))
    Ch = np.empty((n, n))
    Pp = np.empty((max(nt, 1), max(nt, 1)))
    Cd = np.empty((max(k_dr, 1), max(k_dr, 1)))
    Ld = np.empty((max(k_dr, 1), max(k_dr, 1)))
    xm = np.empty((n, 1))
    # small dense work of an update
    y = np.empty(mmax)
    r_ = np.empty(mmax)
    nub = np.empty(mmax)
    S = np.empty((mmax, mmax))
    Sk = np.empty((mmax, mmax))
    Ski = np.empty((mmax, mmax))
    eye = np.zeros((mmax, mmax))
    for a in range(mmax):
        eye[a, a] = 1.0
    g1 = np.empty((mmax, 1))
    g2 = np.empty((mmax, 1))
    Gk = np.empty((max(nt, 1), mmax))
    Lk = np.empty((mmax, mmax))
    Pt = np.empty((max(nt, 1), max(nt, 1)))
    Z = np.empty(P * max(n, 1))
    for r in range(lo, hi):
        ri = min(r, f.inputs.shape[0] - 1)
        alive = True
        # ---- the initial particles: x0 + B0 z
        fill_normals(stream_base(f.key, INIT, r, 0), P * k_dr, Z)
        for i in range(P):
            for a in range(n):
                s_ = 0.0
                for j in range(k_dr):
                    s_ += f.B0[a, j] * Z[i * k_dr + j]
                X[a, i] = f.x0[r, a] + s_
        _wrap_angles(X, f.angles, P)
        normalize(f.mid, X, P)
        for a in range(nt):
            for b in range(nt):
                Pp[a, b] = f.Pp0[a, b]
        for i in range(P):
            lw[i] = -math.log(P)
            w[i] = 1.0 / P
        _estimate(f, X, w, Pp, x, C, xm)
        _emit(out, r, 0, x, C)
        for a in range(n):
            xh[a] = x[a]
            for b in range(n):
                Ch[a, b] = C[a, b]
        out.ess[r, 0] = P
        loglik = 0.0
        for it in range(1, K):
            k0 = f.ticks[it - 1]
            k1 = f.ticks[it]
            for a in range(n):
                for i in range(P):
                    Xp[a, i] = X[a, i]
            # ---- predict
            for k in range(k0, k1):
                for c in range(m_in):
                    u = f.inputs[ri, k, c]
                    for i in range(P):
                        U[c, i] = u
                step_fast(f.mid, X, U, Pm, f.dt, P, W)
            if nq:
                fill_normals(stream_base(f.key, PROCESS, r, it), P * nq, Z)
                for i in range(P):
                    for j in range(nq):
                        a = f.noisy[j]
                        X[a, i] = X[a, i] + f.q[a] * Z[i * nq + j]
            _wrap_angles(X, f.angles, P)
            normalize(f.mid, X, P)
            for a in range(nt):
                for b in range(nt):
                    Pp[a, b] = Pp[a, b] + f.Qp[a, b]
            # ---- dead particles: weight zero, their state held
            any_left = False
            for i in range(P):
                fin = True
                for a in range(n):
                    if not np.isfinite(X[a, i]):
                        fin = False
                lft = _left_domain(Xp, X, i, f.kind, f.mi, f.sing_thr)
                left[i] = lft
                if lft or not fin:
                    for a in range(n):
                        X[a, i] = Xp[a, i]
                    lw[i] = -np.inf
                    if lft:
                        fin_p = True
                        for a in range(n):
                            if not np.isfinite(Xp[a, i]):
                                fin_p = False
                        any_left = any_left or fin_p
            prior = _logsumexp(lw, P)
            if not np.isfinite(prior):  # every particle dead: the run stops
                if alive:
                    alive = False
                    out.status[r] = SINGULAR if any_left else DEAD
                    out.event[r] = k1
                for i in range(P):
                    lw[i] = -math.log(P)
                prior = 0.0
            for i in range(P):
                w[i] = math.exp(lw[i] - prior)
                post[i] = lw[i]
            # ---- update with what arrived in (t_k0, t_k1], channel by channel
            for e in range(sc.ev_ptr[it], sc.ev_ptr[it + 1]):
                c = sc.ev_chan[e]
                mc = ch.m[c]
                vc = ch.valids[c]
                yc = ch.vals[c]
                jv = -1
                for q in range(sc.ev_sptr[e], sc.ev_sptr[e + 1]):
                    j = sc.ev_samp[q]
                    if alive and vc[r, j]:
                        jv = j
                if jv < 0:
                    continue
                for k in range(mc):
                    y[k] = yc[r, jv, k]
                fac = 1.0
                if ch.growth[c]:
                    dd = 0.0
                    for k in range(mc):
                        if ch.pos[c, k] >= 0:
                            t_ = y[k] - ch.gtr[c, ch.pos[c, k]]
                            dd += t_ * t_
                    fac = 1.0 + ch.ga[c] * math.sqrt(dd) / ch.gd[c]
                for k in range(mc):
                    rv = ch.sig2[c, k]
                    if ch.growth[c] and ch.pos[c, k] >= 0:
                        rv = rv * (fac * fac)
                    r_[k] = rv
                # innovations per particle, their weighted mean and spread
                for i in range(P):
                    if ch.kind[c] == 1:
                        s2 = 0.0
                        for k in range(mc):
                            s2 += X[ch.idx[c, k], i] * X[ch.idx[c, k], i]
                        nrm = math.sqrt(s2)
                        for k in range(mc):
                            nu[k, i] = y[k] - X[ch.idx[c, k], i] / nrm
                    else:
                        for k in range(mc):
                            nu[k, i] = y[k] - X[ch.idx[c, k], i]
                    for k in range(mc):
                        if ch.ang[c, k]:
                            nu[k, i] = _wrap_needed(nu[k, i])
                for k in range(mc):
                    s_ = 0.0
                    for i in range(P):
                        s_ += w[i] * nu[k, i]
                    nub[k] = s_
                for k in range(mc):
                    for l in range(mc):
                        s_ = 0.0
                        for i in range(P):
                            s_ += (nu[k, i] - nub[k]) * w[i] * (nu[l, i] - nub[l])
                        S[k, l] = s_
                mg = ch.marginal[c]
                for k in range(mc):
                    for l in range(mc):
                        Sk[k, l] = (Pp[ch.mpos[c, k], ch.mpos[c, l]] if mg else 0.0) + (r_[k] if k == l else 0.0)
                        S[k, l] = S[k, l] + Sk[k, l]
                for k in range(mc):
                    g1[k, 0] = nub[k]
                solve_into(S, g1, g2, mc, 1)
                nis = 0.0
                for k in range(mc):
                    nis += nub[k] * g2[k, 0]
                if not math.isnan(ch.gate[c]) and not nis <= ch.gate[c]:
                    out.gated[r, c] += 1
                    continue
                out.used[r, c] += 1
                out.nis[c][r, jv] = nis
                if mg:  # the marginal likelihood N(y; H p_i, Sk) and the Kalman update
                    solve_into(Sk, eye, Ski, mc, mc)
                    logdet = _logdet(Sk, Lk, mc)
                    cst = -0.5 * (mc * _LOG_2PI + logdet)
                    for i in range(P):
                        d2 = 0.0
                        for k in range(mc):
                            s_ = 0.0
                            for l in range(mc):
                                s_ += nu[l, i] * Ski[l, k]
                            d2 += s_ * nu[k, i]
                        post[i] += -0.5 * d2 + cst
                    for a in range(nt):  # G = Pp[:, pi] Sk^-1
                        for k in range(mc):
                            s_ = 0.0
                            for l in range(mc):
                                s_ += Pp[a, ch.mpos[c, l]] * Ski[l, k]
                            Gk[a, k] = s_
                    for i in range(P):
                        for a in range(nt):
                            s_ = 0.0
                            for k in range(mc):
                                s_ += nu[k, i] * Gk[a, k]
                            X[f.marg[a], i] += s_
                    for a in range(nt):
                        for b in range(nt):
                            s_ = 0.0
                            for k in range(mc):
                                s_ += Gk[a, k] * Pp[b, ch.mpos[c, k]]
                            Pt[a, b] = Pp[a, b] - s_
                    for a in range(nt):
                        for b in range(nt):
                            Pp[a, b] = 0.5 * (Pt[a, b] + Pt[b, a])
                else:
                    logdet = 0.0
                    for k in range(mc):
                        logdet += math.log(r_[k])
                    cst = ch.const[c] - 0.5 * logdet
                    for i in range(P):
                        d2 = 0.0
                        for k in range(mc):
                            d2 += nu[k, i] * nu[k, i] * (1.0 / r_[k])
                        if ch.student[c]:
                            post[i] += cst - 0.5 * (ch.dof[c] + mc) * math.log1p(d2 / ch.dof[c])
                        else:
                            post[i] += cst - 0.5 * d2
            total = _logsumexp(post, P)
            if alive:
                loglik += total - prior
            for i in range(P):
                lw[i] = post[i] - total
                w[i] = math.exp(lw[i])
            s_ = 0.0
            for i in range(P):
                s_ += w[i] * w[i]
            ess = 1.0 / s_
            out.ess[r, it] = ess
            # ---- the estimate, the status; a stopped run holds its last good estimate
            _estimate(f, X, w, Pp, x, C, xm)
            if alive:
                tr = 0.0
                fin = True
                for a in range(n):
                    tr += C[a, a]
                    if not np.isfinite(x[a]):
                        fin = False
                if not fin or not np.isfinite(tr) or tr > f.max_trace:
                    alive = False
                    out.status[r] = DIVERGED
                    out.event[r] = k1
            for k in range(k0 + 1, k1):  # the steps between ticks hold the last tick's estimate
                _emit(out, r, k, xh, Ch)
            if alive:
                for a in range(n):
                    xh[a] = x[a]
                    for b in range(n):
                        Ch[a, b] = C[a, b]
            _emit(out, r, k1, xh, Ch)
            out.progress[r] = it
            # ---- systematic resampling, roughening
            if alive and ess < f.below * P:
                out.resampled[r, it] = True
                _resample(f, X, Xn, w, cum, idx, r, it, P)
                for i in range(P):
                    lw[i] = -math.log(P)
                if f.rough > 0.0:
                    _jitter(f, X, x, C, Cd, Ld, Z, r, it, P, k_dr)
        out.loglik[r] = loglik


# ---------------------------------------------------------------------------------------------- pieces
@jit
def _wrap_angles(X, angles, P):
    for a in range(X.shape[0]):
        if angles[a]:
            for i in range(P):
                X[a, i] = _wrap_needed(X[a, i])


@jit
def _left_domain(Xp, X, i, kind, mi, thr):
    """:meth:`~needlecli.models.Model.left_domain` of particle ``i`` (the declared singularity, as
    :func:`needlecli.kernels.ukf._check_lane` checks it)."""
    if kind == 1:
        return not math.cos(X[mi[0], i]) > thr
    if kind == 2:
        h0, h1, h2 = X[mi[0], i], X[mi[1], i], X[mi[2], i]
        b0, b1, b2 = X[mi[3], i], X[mi[4], i], X[mi[5], i]
        dd = h0 * b0 + h1 * b1 + h2 * b2
        mg = abs(dd) / (math.sqrt(h0 * h0 + h1 * h1 + h2 * h2) * math.sqrt(b0 * b0 + b1 * b1 + b2 * b2))
        d0 = Xp[mi[0], i] * Xp[mi[3], i] + Xp[mi[1], i] * Xp[mi[4], i] + Xp[mi[2], i] * Xp[mi[5], i]
        return (not mg > thr) or d0 * dd < 0.0
    return False


@jit
def _logsumexp(a, P):
    m = -np.inf
    for i in range(P):
        if a[i] > m:
            m = a[i]
    if not np.isfinite(m):
        return m
    s = 0.0
    for i in range(P):
        s += math.exp(a[i] - m)
    return m + math.log(s)


@jit
def _logdet(A, L, m):
    """``log det A`` of a symmetric positive definite ``A[:m, :m]`` (its Cholesky factor)."""
    out = 0.0
    for j in range(m):
        s = A[j, j]
        for k in range(j):
            s -= L[j, k] * L[j, k]
        d = math.sqrt(s)
        L[j, j] = d
        out += 2.0 * math.log(d)
        for i in range(j + 1, m):
            t = A[i, j]
            for k in range(j):
                t -= L[i, k] * L[j, k]
            L[i, j] = t / d
    return out


@jit
def _estimate(f, X, w, Pp, x, C, xm):
    """The weighted mean ``x (n,)`` (circular for angles, the model's projection on it) and the covariance
    about it ``C (n, n)`` (angle residuals wrapped; plus ``Pp`` on the translation states)."""
    n, P = X.shape
    for a in range(n):
        if f.angles[a]:
            ss = 0.0
            cc = 0.0
            for i in range(P):
                s_, c_ = _sincos_half(X[a, i])
                ss += w[i] * s_
                cc += w[i] * c_
            xm[a, 0] = math.atan2(ss, cc)
        else:
            s_ = 0.0
            for i in range(P):
                s_ += w[i] * X[a, i]
            xm[a, 0] = s_
    normalize(f.mid, xm, 1)
    for a in range(n):
        x[a] = xm[a, 0]
    for a in range(n):
        for b in range(a + 1):
            C[a, b] = 0.0
    d = np.empty(n)
    for i in range(P):
        for a in range(n):
            v = X[a, i] - x[a]
            d[a] = _wrap_needed(v) if f.angles[a] else v
        wi = w[i]
        for a in range(n):
            da = d[a] * wi
            for b in range(a + 1):
                C[a, b] += da * d[b]
    for a in range(n):
        for b in range(a):
            C[b, a] = C[a, b]
    nt = f.marg.shape[0]
    for a in range(nt):
        for b in range(nt):
            C[f.marg[a], f.marg[b]] += Pp[a, b]


@jit
def _resample(f, X, Xn, w, cum, idx, r, it, P):
    """Systematic resampling (:meth:`needlecli.observers.pf.ParticleFilter._resample`): particle ``i``
    becomes the one whose cumulative weight interval holds ``(u + i) / P``."""
    s_ = 0.0
    for i in range(P):
        s_ += w[i]
        cum[i] = s_
    cum[P - 1] = 1.0
    u = uniform(stream_base(f.key, RESAMPLE, r, it), 0)
    j = 0
    for i in range(P):
        pos = (u + i) / P
        while j < P and cum[j] <= pos:
            j += 1
        idx[i] = min(j, P - 1)
    n = X.shape[0]
    for a in range(n):
        for i in range(P):
            Xn[a, i] = X[a, idx[i]]
    for a in range(n):
        for i in range(P):
            X[a, i] = Xn[a, i]


@jit
def _jitter(f, X, x, C, Cd, Ld, Z, r, it, P, k_dr):
    """Liu and West's kernel smoothing of the drawn states (:meth:`ParticleFilter._jitter
    <needlecli.observers.pf.ParticleFilter._jitter>`): ``x + a (X - x) + h L z``, ``L`` the Cholesky factor
    of the drawn states' block of the cloud's covariance ``C``."""
    h = f.rough
    a_ = math.sqrt(1.0 - h * h)
    for j in range(k_dr):
        for l in range(k_dr):
            Cd[j, l] = C[f.drawn[j], f.drawn[l]]
    if not cholesky_into(Cd, Ld, k_dr):
        repaired_root(Cd, Ld, k_dr, 1e-12)
    fill_normals(stream_base(f.key, ROUGHEN, r, it), P * k_dr, Z)
    for i in range(P):
        for j in range(k_dr):
            a = f.drawn[j]
            d = X[a, i] - x[a]
            if f.angles[a]:
                d = _wrap_needed(d)
            s_ = 0.0
            for l in range(k_dr):
                s_ += Z[i * k_dr + l] * Ld[j, l]
            X[a, i] = (x[a] + a_ * d) + h * s_
    _wrap_angles(X, f.angles, P)
    normalize(f.mid, X, P)


@jit
def _emit(out, r, k, x, C):
    n = x.shape[0]
    for a in range(n):
        out.states[r, k, a] = x[a]
    if out.layout == LAYOUT_NONE or k % out.stride != 0:
        return
    j = k // out.stride
    if out.layout == LAYOUT_FULL:
        for a in range(n):
            for b in range(n):
                out.cov_full[r, j, a, b] = C[a, b]
    else:
        for a in range(n):
            out.cov_diag[r, j, a] = C[a, a]


# ---------------------------------------------------------------------------------------------- the seam
def schedule(chans, ticks) -> Schedule:
    """:meth:`UnscentedKalmanFilter._schedule <needlecli.observers.ukf.UnscentedKalmanFilter._schedule>` as
    arrays: per tick its events, each a channel and its samples that became available since the last
    tick (in time order; channels in their order)."""
    nt = len(ticks)
    e_tick, e_chan, samples = [], [], []
    for ci, c in enumerate(chans):
        tick_of = np.searchsorted(ticks, c["avail"], side="left")
        keep = (tick_of > 0) & (tick_of < nt)
        t_k, j_k = tick_of[keep], np.asarray(c["order"])[keep]
        for t in np.unique(t_k):
            e_tick.append(int(t))
            e_chan.append(ci)
            samples.append(j_k[t_k == t])
    o = np.lexsort((np.array(e_chan, dtype=np.int64), np.array(e_tick, dtype=np.int64))) if e_tick else []
    ev_chan = np.array([e_chan[i] for i in o], dtype=np.int64)
    ev_tick = np.array([e_tick[i] for i in o], dtype=np.int64)
    samp = [samples[i] for i in o]
    ev_sptr = np.r_[0, np.cumsum([len(s) for s in samp])].astype(np.int64)
    ev_samp = np.concatenate(samp).astype(np.int64) if samp else np.zeros(1, dtype=np.int64)
    ev_ptr = np.searchsorted(ev_tick, np.arange(nt + 1), side="left").astype(np.int64)
    return Schedule(ev_ptr, ev_chan if ev_chan.size else np.zeros(1, dtype=np.int64), ev_sptr, ev_samp)


def filter_runs(f, problem, max_trace: float, progress=None) -> dict:
    """Everything :meth:`ParticleFilter._filter <needlecli.observers.pf.ParticleFilter._filter>` computes,
    from its set-up ``f`` (:class:`needlecli.observers.pf._Setup`), by :func:`run`."""
    model = f.model
    N, n = f.x0.shape
    T = len(problem.time)
    K = len(f.ticks)
    u = f.inputs
    u3 = kernel_array(u[:1] if u.strides[0] == 0 else u, dtype=float)
    p_arr = np.array([float(np.asarray(v)) for v in f.params.values()], dtype=float)
    chans = f.chans
    C = len(chans)
    mmax = max([c["m"] for c in chans], default=1)
    pad = max(C, 1)
    ch_m = np.array([c["m"] for c in chans] or [1], dtype=np.int64)
    kind = np.zeros(pad, dtype=np.int64)
    idx, ang, sig2, gate, growth, ga, gd, gtr, pos = gaussian_part(chans, "idx", 1.0)
    mpos = np.zeros((pad, mmax), dtype=np.int64)
    student = np.zeros(pad, dtype=np.bool_)
    dof, const = np.ones(pad), np.zeros(pad)
    marginal = np.zeros(pad, dtype=np.bool_)
    marg = np.zeros(0, dtype=np.int64) if f.marg is None else np.asarray(f.marg, dtype=np.int64)
    for ci, c in enumerate(chans):
        m = c["m"]
        kind[ci] = c["kind"]
        student[ci], dof[ci], const[ci] = c["student"], c["dof"] or 1.0, c["const"]
        if c["marginal"]:
            marginal[ci] = True
            mpos[ci, :m] = [int(np.nonzero(marg == i)[0][0]) for i in c["idx"]]
    vals = tuple([kernel_array(c["value"], dtype=float) for c in chans] + [np.zeros((1, 1, 1))] * (MAX_CHANNELS - C))
    valids = tuple([kernel_array(c["valid"], dtype=np.bool_) for c in chans]
                   + [np.zeros((1, 1), dtype=np.bool_)] * (MAX_CHANNELS - C))
    nisv = tuple([np.full(np.shape(c["valid"]), np.nan) for c in chans] + [np.full((1, 1), np.nan)] * (MAX_CHANNELS - C))
    states, layout, stride, cov_full, cov_diag = estimate_arrays(problem, N, T, n)
    status = np.zeros(N, dtype=np.int64)
    event = np.full(N, -1, dtype=np.int64)
    used = np.zeros((N, pad), dtype=np.int64)
    gated = np.zeros((N, pad), dtype=np.int64)
    ess = np.empty((N, K))
    resampled = np.zeros((N, K), dtype=np.bool_)
    loglik = np.zeros(N)
    prog = np.zeros(N, dtype=np.int64)
    kd, mi = margin(model)
    nt = marg.size
    Pp0 = np.zeros((1, 1)) if f.Pp0 is None else kernel_array(f.Pp0, dtype=float)
    Qp = np.zeros((1, 1)) if f.Qp is None else kernel_array(f.Qp, dtype=float)
    args = (Filter(equation_id(model), kernel_array(f.x0, dtype=float), kernel_array(f.B0, dtype=float),
                   kernel_array(f.ticks, dtype=np.int64), u3, p_arr, float(f.dt),
                   kernel_array(f.angles, dtype=np.bool_), kernel_array(f.q, dtype=float),
                   kernel_array(f.noisy, dtype=np.int64), marg, Pp0 if nt else np.zeros((0, 0)),
                   Qp if nt else np.zeros((0, 0)), np.uint64(f.key), int(f.P), float(f.below), float(f.rough),
                   kernel_array(f.drawn, dtype=np.int64), kd, mi, float(model.singular_threshold),
                   float(max_trace)),
            Channels(vals, valids, ch_m, kind, idx, ang, sig2, gate, growth, ga, gd, gtr, pos, student, dof, const,
                     marginal, mpos),
            schedule(chans, f.ticks),
            Outputs(states, cov_full, cov_diag, layout, stride, status, event, used, gated, nisv, ess, resampled,
                    loglik, prog))
    total = N * max(K - 1, 1)
    poll = None if progress is None else (lambda: progress(int(prog.sum()) * (K - 1) // total, K - 1))
    parallel_for(run, blocks(N, per_thread=2), args, poll)
    cov = kept_covariance(layout, cov_full, cov_diag)
    return {"states": states, "cov": cov, "status": status, "event": event, "used": used[:, :C],
            "gated": gated[:, :C], "nis": nisv[:C], "ess": ess, "resampled": resampled, "loglik": loglik}
