"""The Kalman passes that EM runs, compiled: the affine filter, the RTS smoother, the closed-form M-step
sums, and the linearisation of the magnetic models (RK4 with its exact Jacobian; measurement Jacobians
by the same central differences), each over all trials at once (trials spread over the cores).

Each function returns what its numpy counterpart in :mod:`needlecli.numerics.kalman` and
:mod:`needlecli.fitting.statespace` returns, with the same operations in the same order where rounding
matters (the symmetrisations, the repairs of matrices that are not positive definite, the order of the
matrix products); only the order of the sums inside a product and per-matrix rather than per-batch
repairs (a matrix is repaired when its own Cholesky fails) differ.
"""

from __future__ import annotations

import math
from collections import namedtuple

import numpy as np

from needlecli.kernels._jit import jit, lanes
from needlecli.kernels._threads import blocks, parallel_for
from needlecli.kernels.channels import kernel_array
from needlecli.kernels.core import cholesky_into, wrap
from needlecli.kernels.models import magnetic_field

LOG_2PI = float(np.log(2.0 * np.pi))


# ---------------------------------------------------------------------------------------------- helpers
@jit
def _mm(A, B, out, n, k, m):
    """``out[:n, :m] = A[:n, :k] @ B[:k, :m]``; the zeros of ``A`` skipped (the Jacobians' structural zeros:
    a term ``0 * B[q, j]`` adds nothing to a finite sum, which keeps its order)."""
    for i in range(n):
        for j in range(m):
            out[i, j] = 0.0
        for q in range(k):
            a = A[i, q]
            if a == 0.0:
                continue
            for j in range(m):
                out[i, j] += a * B[q, j]


@jit
def repair_pd_one(P, n, L):
    """:func:`needlecli.numerics.kalman.repair_pd` for one matrix, in place: symmetrised; where its Cholesky
    fails, eigenvalues clipped at ``max(1e-300, 1e-12 * largest)`` (non-finite: left as is). Returns
    whether it needed the repair (``L`` scratch)."""
    for i in range(n):
        for j in range(i):
            s = 0.5 * (P[i, j] + P[j, i])
            P[i, j] = s
            P[j, i] = s
    if cholesky_into(P, L, n):
        return False
    for i in range(n):
        for j in range(n):
            if not np.isfinite(P[i, j]):
                return True
    w, v = np.linalg.eigh(P[:n, :n].copy())
    top = max(w[n - 1], 1e-300)
    lo = max(1e-300, 1e-12 * top)
    if w[0] > 1e-12 * max(w[n - 1], 0.0):
        return False  # positive definite by the eigenvalue test: numpy's repair_pd leaves it
    for i in range(n):
        w[i] = max(w[i], lo)
    R = np.zeros((n, n))
    for q in range(n):
        for a in range(n):
            for b in range(n):
                R[a, b] += v[a, q] * w[q] * v[b, q]
    for a in range(n):
        for b in range(n):
            P[a, b] = 0.5 * (R[a, b] + R[b, a])
    return True


# ---------------------------------------------------------------------------------------------- lanes
# The passes work on LANES trials at once, each quantity an array whose last axis is the lane (one
# AVX-512 vector): every scalar operation of the filter is one vector operation. The helpers below are
# compiled with their array arguments declared not to overlap (``lanes``), so that LLVM packs the loops
# over lanes; each sum of a product runs in one accumulator of LANES values (kept in a register), the
# terms in the order of the scalar product. The products are dense: a structural zero of a Jacobian adds
# an exact zero to a finite sum (numpy's products add them too). The measurement matrices, whose rows
# have one to three nonzero entries, are taken by their nonzero columns (``hcnt``, ``hidx``). A lane
# whose matrix is not positive definite takes the scalar repair (rare).
#
# A block's filtered and predicted means and covariances (and the transitions it used) are kept in the
# lanes' layout between the filter and the smoother (``(K+1, n, n, LANES)``, one contiguous stream each),
# so that the smoother does not gather each matrix back from eight trials' rows; EM's pass also makes the
# M-step's process-noise sums there, instead of writing the cross-covariances and reading them back.
LANES = 8

# ---------------------------------------------------------------------------------------------- the records
# What the passes are given, in a few records of arrays and numbers (numba takes named tuples as arguments;
# defined here, at module level, so that the cached kernels find their types again). Every caller gives a
# record's fields the same array types (unused ones empty): one compiled block serves them all.

#: the affine model of a pass and its prior: m0 (N, n), P0 and Qc (N, n, n) per trial; dt (K,); A (Ns, K,
#: n, n) and b (Ns, K, n) by row; src (N,) the row of A, b and the samples that trial r filters with;
#: state_angles (n,) bool
Affine = namedtuple("Affine", "m0 P0 Qc dt A b src state_angles")
#: the channels' samples along one axis (:func:`_channels_concat`): slot (J, K+1) the sample of channel j
#: at tick k (-1: none); m (J,) components; Y (Ns, M, mm), V (Ns, M), R (N, J, mm, mm), H (Ns, M, mm, n),
#: D (Ns, M, mm); ang (J, mm) angles; hcnt (J, mm), hidx (J, mm, n) the sparse rows of each channel's H
Samples = namedtuple("Samples", "slot m Y V R H D ang hcnt hidx")
#: a block's means and covariances in the lanes' layout: mS, mfS (K+1, n, LANES) predicted and filtered
#: means, PpS, PfS (K+1, n, n, LANES) their covariances, AS (K, n, n, LANES) the transitions
Block = namedtuple("Block", "mS PpS mfS PfS AS")
#: the filter's outputs (N, K+1, n[, n]) and per trial its log-likelihood and repairs (N,)
Filtered = namedtuple("Filtered", "m_pred P_pred m_filt P_filt loglik repairs")
#: the smoother's outputs, each written where its flag says: m (N, K+1, n), P (N, K+1, n, n); C and G (N,
#: K, n, n) the cross-covariances and gains (keep_C, keep_G); q_sums (N, n, n) the M-step's process-noise
#: sums (keep_Q); sd (N, K+1, n) the standard deviations and finite (N,) (keep_sd); r_sums (N, J, mm,
#: mm) and r_count (N, J) the measurement-noise sums (keep_R); repairs (N,)
Smoothed = namedtuple("Smoothed", "m P C G q_sums sd finite r_sums r_count repairs keep_C keep_G keep_Q keep_sd "
                                  "keep_R")


@jit
def _lanes(lo, hi, r0):
    """The trials of the lanes starting at ``r0`` (past ``hi``: the last one again, computed, not stored)."""
    out = np.empty(LANES, dtype=np.int64)
    for l in range(LANES):
        out[l] = min(r0 + l, hi - 1)
    return out


@lanes
def _Ax(A, x, out, n, acc):
    """``out = A x`` per lane; ``acc (LANES,)`` scratch (as for every helper here)."""
    for a in range(n):
        for l in range(LANES):
            acc[l] = 0.0
        for q in range(n):
            for l in range(LANES):
                acc[l] += A[a, q, l] * x[q, l]
        for l in range(LANES):
            out[a, l] = acc[l]


@lanes
def _XYt(X, Y, out, n, k, m, sym, acc):
    """``out[:n, :m] = X Y^T`` per lane, dense; ``sym``: the result is symmetric (lower triangle computed and
    mirrored)."""
    for a in range(n):
        for c in range(a + 1 if sym else m):
            for l in range(LANES):
                acc[l] = 0.0
            for q in range(k):
                for l in range(LANES):
                    acc[l] += X[a, q, l] * Y[c, q, l]
            for l in range(LANES):
                out[a, c, l] = acc[l]
        if sym:
            for c in range(a):
                for l in range(LANES):
                    out[c, a, l] = out[a, c, l]


@lanes
def _XY(X, Y, out, n, k, m, tx, acc):
    """``out[:n, :m] = op(X) Y`` per lane, dense, ``op(X) = X`` or ``X^T`` (``tx``)."""
    for a in range(n):
        for c in range(m):
            for l in range(LANES):
                acc[l] = 0.0
            if tx:
                for q in range(k):
                    for l in range(LANES):
                        acc[l] += X[q, a, l] * Y[q, c, l]
            else:
                for q in range(k):
                    for l in range(LANES):
                        acc[l] += X[a, q, l] * Y[q, c, l]
            for l in range(LANES):
                out[a, c, l] = acc[l]


@lanes
def _XY_sym_plus(X, Y, B, out, n, k, acc):
    """``out = B + X Y`` per lane for a symmetric result (lower triangle computed, mirrored; the product's
    sum first, then ``B``)."""
    for a in range(n):
        for c in range(a + 1):
            for l in range(LANES):
                acc[l] = 0.0
            for q in range(k):
                for l in range(LANES):
                    acc[l] += X[a, q, l] * Y[q, c, l]
            for l in range(LANES):
                v = B[a, c, l] + acc[l]
                out[a, c, l] = v
                out[c, a, l] = v


@lanes
def _sym_minus_XtYt(X, Y, P, n, k, acc):
    """``P = P - X^T Y^T`` per lane for a symmetric result (lower triangle computed, mirrored), ``X (k, n)``,
    ``Y (n, k)``."""
    for a in range(n):
        for c in range(a + 1):
            for l in range(LANES):
                acc[l] = 0.0
            for q in range(k):
                for l in range(LANES):
                    acc[l] += X[q, a, l] * Y[c, q, l]
            for l in range(LANES):
                v = P[a, c, l] - acc[l]
                P[a, c, l] = v
                P[c, a, l] = v


@lanes
def _chol(A, Lf, n, ok, acc, inv):
    """Lower Cholesky factors per lane (``ok[l]`` False where one fails: that lane's factor is garbage);
    ``inv (LANES,)`` scratch."""
    for l in range(LANES):
        ok[l] = True
    for j in range(n):
        for l in range(LANES):
            acc[l] = A[j, j, l]
        for q in range(j):
            for l in range(LANES):
                acc[l] -= Lf[j, q, l] * Lf[j, q, l]
        for l in range(LANES):
            d = acc[l]
            good = d > 0.0
            ok[l] = ok[l] and good
            s = np.sqrt(d) if good else 1.0
            Lf[j, j, l] = s
            inv[l] = 1.0 / s
        for i in range(j + 1, n):
            for l in range(LANES):
                acc[l] = A[i, j, l]
            for q in range(j):
                for l in range(LANES):
                    acc[l] -= Lf[i, q, l] * Lf[j, q, l]
            for l in range(LANES):
                Lf[i, j, l] = acc[l] * inv[l]
        for i in range(j):
            for l in range(LANES):
                Lf[i, j, l] = 0.0


@lanes
def _chol_solve(Lf, B, X, n, k, D, acc):
    """``X = (L L^T)^{-1} B`` per lane, ``B, X (n, k, LANES)`` (divisions by the diagonal as multiplications by
    its inverse); ``D`` scratch, at least ``(n, LANES)``."""
    for i in range(n):
        for l in range(LANES):
            D[i, l] = 1.0 / Lf[i, i, l]
    for j in range(k):
        for i in range(n):
            for l in range(LANES):
                acc[l] = B[i, j, l]
            for q in range(i):
                for l in range(LANES):
                    acc[l] -= Lf[i, q, l] * X[q, j, l]
            for l in range(LANES):
                X[i, j, l] = acc[l] * D[i, l]
        for i in range(n - 1, -1, -1):
            for l in range(LANES):
                acc[l] = X[i, j, l]
            for q in range(i + 1, n):
                for l in range(LANES):
                    acc[l] -= Lf[q, i, l] * X[q, j, l]
            for l in range(LANES):
                X[i, j, l] = acc[l] * D[i, l]


@jit
def _fix_lanes(M, L, n, ok, scratch, Ls, count):
    """Lanes whose Cholesky failed: :func:`repair_pd_one` on that lane's matrix (counted in ``count``),
    refactored. ``M`` symmetric."""
    for l in range(LANES):
        if ok[l]:
            continue
        for a in range(n):
            for c in range(n):
                scratch[a, c] = M[a, c, l]
        if repair_pd_one(scratch, n, Ls):
            count[l] += 1
        cholesky_into(scratch, Ls, n)
        for a in range(n):
            for c in range(n):
                M[a, c, l] = scratch[a, c]
                L[a, c, l] = Ls[a, c]


@jit
def _all(ok):
    for l in range(LANES):
        if not ok[l]:
            return False
    return True


@jit
def _scratch(K1, n):
    """A block's means and covariances in the lanes' layout (:data:`Block`)."""
    return Block(np.empty((K1, n, LANES)), np.empty((K1, n, n, LANES)), np.empty((K1, n, LANES)),
                 np.empty((K1, n, n, LANES)), np.empty((max(K1 - 1, 2), n, n, LANES)))


# ---------------------------------------------------------------------------------------------- the filter
@lanes
def _forward_block(rl, aff, obs, blk, ll, rep):
    """The affine filter (:data:`Affine`, :data:`Samples`) on the trials ``rl`` (one per lane) into the
    block's layout (:data:`Block`); ``ll, rep`` the log-likelihood and the repairs per lane."""
    m0, P0, Qc, dt, A, b, src, state_angles = aff.m0, aff.P0, aff.Qc, aff.dt, aff.A, aff.b, aff.src, aff.state_angles
    slot, ch_m, Y, V, R, H, D = obs.slot, obs.m, obs.Y, obs.V, obs.R, obs.H, obs.D
    ang_c, hcnt, hidx = obs.ang, obs.hcnt, obs.hidx
    mS, PpS, mfS, PfS, AS = blk.mS, blk.PpS, blk.mfS, blk.PfS, blk.AS
    n = m0.shape[1]
    K1 = slot.shape[1]
    J = slot.shape[0]
    mt_max = 0
    for j in range(J):
        mt_max += ch_m[j]
    mt_max = max(mt_max, 1)
    nm = max(n, mt_max)
    m = np.empty((n, LANES))
    m2 = np.empty((n, LANES))
    T1 = np.empty((n, n, LANES))
    Lc = np.empty((n, n, LANES))
    Hl = np.zeros((mt_max, n, LANES))
    yv = np.empty((mt_max, LANES))
    nu = np.empty((mt_max, 1, LANES))
    PHt = np.empty((n, mt_max, LANES))
    HtT = np.empty((mt_max, n, LANES))
    S = np.empty((mt_max, mt_max, LANES))
    Ls = np.empty((mt_max, mt_max, LANES))
    X = np.empty((mt_max, n, LANES))
    g2 = np.empty((mt_max, 1, LANES))
    dg = np.empty((nm, LANES))
    acc = np.empty(LANES)
    inv = np.empty(LANES)
    ok = np.empty(LANES, dtype=np.bool_)
    nval = np.zeros(LANES)
    sc_n = np.empty((n, n))
    sc_nL = np.empty((n, n))
    sc_m = np.empty((mt_max, mt_max))
    sc_mL = np.empty((mt_max, mt_max))
    rowc = np.empty(mt_max, dtype=np.int64)
    rowi = np.empty(mt_max, dtype=np.int64)
    rowq = np.empty(mt_max, dtype=np.int64)
    ring = mS.shape[0] < K1  # the log-likelihood only: two ticks of scratch, alternating
    for l in range(LANES):
        r = rl[l]
        rep[l] = 0
        ll[l] = 0.0
        for a in range(n):
            m[a, l] = m0[r, a]
            for c in range(n):
                PpS[0, a, c, l] = P0[r, a, c]
    for k in range(K1):
        s = k % 2 if ring else k  # this tick's slot of the scratch
        s0 = (k - 1) % 2 if ring else k - 1
        if k > 0:  # the prediction, into PpS[k]; the transition into AS[k - 1]
            Ak = AS[s0]
            for l in range(LANES):
                r = src[rl[l]]
                for a in range(n):
                    for c in range(n):
                        Ak[a, c, l] = A[r, k - 1, a, c]
            _Ax(Ak, m, m2, n, acc)
            for l in range(LANES):
                r = src[rl[l]]
                for a in range(n):
                    m[a, l] = m2[a, l] + b[r, k - 1, a]
            _XY(Ak, PfS[s0], T1, n, n, n, False, acc)
            Pk = PpS[s]
            _XYt(T1, Ak, Pk, n, n, n, True, acc)
            h = dt[k - 1]
            for l in range(LANES):
                r = rl[l]
                for a in range(n):
                    for c in range(n):
                        Pk[a, c, l] += Qc[r, a, c] * h
        P = PfS[s]  # updated in place from the prediction
        for a in range(n):
            for l in range(LANES):
                mS[s, a, l] = m[a, l]
            for c in range(n):
                for l in range(LANES):
                    P[a, c, l] = PpS[s, a, c, l]
        # ---- the joint update with every sample of this tick (invalid ones: zero rows, unit noise)
        mt = 0
        for j in range(J):
            i = slot[j, k]
            if i < 0:
                continue
            for q in range(ch_m[j]):
                rowc[mt] = j
                rowi[mt] = i
                rowq[mt] = q
                mt += 1
        if mt > 0:
            for l in range(LANES):
                nval[l] = 0.0
            for q in range(mt):
                j, i, qq = rowc[q], rowi[q], rowq[q]
                for l in range(LANES):
                    r = src[rl[l]]
                    v = V[r, i]
                    yv[q, l] = (Y[r, i, qq] - D[r, i, qq]) if v else 0.0
                    if v:
                        nval[l] += 1.0
                    for t in range(hcnt[j, qq]):
                        c = hidx[j, qq, t]
                        Hl[q, c, l] = H[r, i, qq, c] if v else 0.0
            for q in range(mt):  # nu = y - H m; PHt = P H^T (sparse rows of H)
                j, qq = rowc[q], rowq[q]
                for l in range(LANES):
                    nu[q, 0, l] = yv[q, l]
                for t in range(hcnt[j, qq]):
                    c = hidx[j, qq, t]
                    for l in range(LANES):
                        g2[q, 0, l] = Hl[q, c, l] * m[c, l] if t == 0 else g2[q, 0, l] + Hl[q, c, l] * m[c, l]
                for l in range(LANES):
                    d = nu[q, 0, l] - (g2[q, 0, l] if hcnt[j, qq] else 0.0)
                    nu[q, 0, l] = wrap(d) if ang_c[j, qq] else d
                for a in range(n):
                    for l in range(LANES):
                        PHt[a, q, l] = 0.0
                    for t in range(hcnt[j, qq]):
                        c = hidx[j, qq, t]
                        for l in range(LANES):
                            PHt[a, q, l] += P[a, c, l] * Hl[q, c, l]
                    for l in range(LANES):
                        HtT[q, a, l] = PHt[a, q, l]
            for q in range(mt):  # S = H PHt + R, symmetric (lower mirrored); unit blocks for invalid samples
                j, i, qq = rowc[q], rowi[q], rowq[q]
                for q2 in range(q + 1):
                    for l in range(LANES):
                        S[q, q2, l] = 0.0
                    for t in range(hcnt[j, qq]):
                        c = hidx[j, qq, t]
                        for l in range(LANES):
                            S[q, q2, l] += Hl[q, c, l] * PHt[c, q2, l]
                    if rowc[q2] == j:
                        for l in range(LANES):
                            if V[src[rl[l]], i]:
                                S[q, q2, l] += R[rl[l], j, qq, rowq[q2]]
                            elif q == q2:
                                S[q, q2, l] += 1.0
                    for l in range(LANES):
                        S[q2, q, l] = S[q, q2, l]
            _chol(S, Ls, mt, ok, acc, inv)
            if not _all(ok):
                _fix_lanes(S, Ls, mt, ok, sc_m, sc_mL, rep)
            _chol_solve(Ls, HtT, X, mt, n, dg, acc)  # X = S^-1 (P H^T)^T: the gain transposed
            for a in range(n):  # m + K nu
                for l in range(LANES):
                    acc[l] = 0.0
                for q in range(mt):
                    for l in range(LANES):
                        acc[l] += X[q, a, l] * nu[q, 0, l]
                for l in range(LANES):
                    v = m[a, l] + acc[l]
                    m[a, l] = wrap(v) if state_angles[a] else v
            _sym_minus_XtYt(X, PHt, P, n, mt, acc)  # P - K PHt^T, symmetric
            # ---- the log-likelihood of these innovations
            _chol_solve(Ls, nu, g2, mt, 1, dg, acc)
            for l in range(LANES):
                logdet = 0.0
                quad = 0.0
                for q in range(mt):
                    logdet += math.log(Ls[q, q, l])
                    quad += nu[q, 0, l] * g2[q, 0, l]
                ll[l] += -0.5 * (quad + 2.0 * logdet + nval[l] * LOG_2PI)
            for q in range(mt):  # Hl back to zeros for the next tick's sparse rows
                j, qq = rowc[q], rowq[q]
                for t in range(hcnt[j, qq]):
                    c = hidx[j, qq, t]
                    for l in range(LANES):
                        Hl[q, c, l] = 0.0
        # ---- the filtered covariance checked for positive definiteness (numpy: after the pass)
        _chol(P, Lc, n, ok, acc, inv)
        if not _all(ok):
            _fix_lanes(P, Lc, n, ok, sc_n, sc_nL, rep)
        for a in range(n):
            for l in range(LANES):
                mfS[s, a, l] = m[a, l]


@jit
def forward_affine(lo, hi, aff, obs, out, store):
    """:func:`needlecli.numerics.kalman.kalman_forward_affine` for trials ``lo..hi-1`` (lanes of LANES) of
    the model :data:`Affine` and the channels :data:`Samples` into :data:`Filtered` ``out`` (written in
    place); with ``store`` False only the log-likelihood and the repairs (the means and covariances not
    written). Trial r filters with row ``aff.src[r]`` of ``A, b, Y, V, H, D`` (its own noise, prior and
    outputs: identifiability's evaluation points share their trial's linearisation without copies). The
    gain uses the Cholesky factor of the innovation covariance (numpy: LU; the same to rounding), which the
    log-likelihood needs anyway.
    """
    m_pred, P_pred, m_filt, P_filt, loglik, repairs = (out.m_pred, out.P_pred, out.m_filt, out.P_filt, out.loglik,
                                                       out.repairs)
    n = aff.m0.shape[1]
    K1 = obs.slot.shape[1]
    blk = _scratch(K1 if store else 2, n)  # not stored: two ticks of scratch, alternating
    mS, PpS, mfS, PfS = blk.mS, blk.PpS, blk.mfS, blk.PfS
    ll = np.zeros(LANES)
    rep = np.zeros(LANES, dtype=np.int64)
    for r0 in range(lo, hi, LANES):
        rl = _lanes(lo, hi, r0)
        _forward_block(rl, aff, obs, blk, ll, rep)
        nl = min(LANES, hi - r0)
        for l in range(nl):
            loglik[rl[l]] = ll[l]
            repairs[rl[l]] += rep[l]
        if store:
            for k in range(K1):
                for l in range(nl):
                    r = rl[l]
                    for a in range(n):
                        m_pred[r, k, a] = mS[k, a, l]
                        m_filt[r, k, a] = mfS[k, a, l]
                        for c in range(n):
                            P_pred[r, k, a, c] = PpS[k, a, c, l]
                            P_filt[r, k, a, c] = PfS[k, a, c, l]


# ---------------------------------------------------------------------------------------------- the smoother
@lanes
def _backward_block(rl, nl, blk, aff, obs, sm, rep):
    """The RTS smoother on a block in the lanes' layout (:data:`Block`, the filter's
    :func:`_forward_block`), lanes ``0..nl-1`` written to the trials ``rl`` of :data:`Smoothed` ``sm``: the
    gains from the Cholesky factor of the predicted covariance (its check of positive definiteness
    computes it anyway), the backward recursion, the smoothed means and covariances; the lag-one
    cross-covariances if ``sm.keep_C``, the gains if ``sm.keep_G``. With ``keep_Q`` also the sums of
    :func:`process_noise_sums` (``aff.b``, ``aff.dt``) into ``q_sums``, each interval's term as that
    kernel's (the sum over intervals in reverse). With ``keep_sd`` the smoothed standard deviations ``sd``
    (``sqrt(max(diag P, 1e-300))``, NaN kept, as numpy's) and whether every entry of each trial's
    covariances is finite (``finite``). With ``keep_R`` the sums of :func:`measurement_noise_sums` of every
    channel of ``obs`` (the forward pass's) into ``r_sums``, ``r_count`` (the samples in reverse order)."""
    mS, PpS, mfS, PfS, AS = blk.mS, blk.PpS, blk.mfS, blk.PfS, blk.AS
    state_angles, b, dt = aff.state_angles, aff.b, aff.dt
    m_s, P_s, C, G, q_sums, sd, finite, r_sums, r_count = (sm.m, sm.P, sm.C, sm.G, sm.q_sums, sm.sd, sm.finite,
                                                           sm.r_sums, sm.r_count)
    keep_C, keep_G, keep_Q, keep_sd, keep_R = sm.keep_C, sm.keep_G, sm.keep_Q, sm.keep_sd, sm.keep_R
    slot, ch_m, Y = obs.slot, obs.m, obs.Y
    K1 = mS.shape[0]
    n = mS.shape[1]
    K = K1 - 1
    # working matrices, each reused once its value is dead (8 of them fit the first-level cache better)
    Pp = np.empty((n, n, LANES))  # P_{k+1|k} symmetrised; then C_k A_k^T
    W1 = np.empty((n, n, LANES))  # A_k P_f; then G (Ps - Pp); then A_k P_k A_k^T
    W2 = np.empty((n, n, LANES))  # the Cholesky factor of Pp; then Ps - Pp; then A_k P_k
    Gt = np.empty((n, n, LANES))
    Cl = np.empty((n, n, LANES))
    PP = np.empty((2, n, n, LANES))  # P_s[k + 1] and P_s[k], alternating
    Qa = np.zeros((n, n, LANES))
    ms = np.empty((n, LANES))
    mn = np.empty((n, LANES))
    d = np.empty((n, LANES))
    e = np.empty((n, LANES))
    acc = np.empty(LANES)
    dg = np.empty((n, LANES))
    inv = np.empty(LANES)
    ok = np.empty(LANES, dtype=np.bool_)
    sc = np.empty((n, n))
    scL = np.empty((n, n))
    fz = np.zeros(LANES)  # 0 while every covariance entry is finite (x * 0 is NaN for inf and NaN)
    J = slot.shape[0]
    mm = Y.shape[2]
    Ra = np.zeros((J, mm, mm, LANES))
    Rc = np.zeros((J, LANES), dtype=np.int64)
    Hl = np.zeros((mm, n, LANES))
    HP = np.empty((mm, n, LANES))
    rv = np.empty((mm, LANES))
    vm = np.empty(LANES, dtype=np.bool_)
    for a in range(n):
        for l in range(LANES):
            ms[a, l] = mfS[K, a, l]
        for c in range(n):
            for l in range(LANES):
                PP[1, a, c, l] = PfS[K, a, c, l]
                fz[l] += PfS[K, a, c, l] * 0.0
    if keep_R:
        _r_sums(K, rl, ms, PP[1], obs, Ra, Rc, Hl, HP, rv, vm, acc)
    for l in range(nl):
        r = rl[l]
        for a in range(n):
            m_s[r, K, a] = ms[a, l]
            if keep_sd:
                sd[r, K, a] = _sd(PP[1, a, a, l])
            for c in range(n):
                P_s[r, K, a, c] = PP[1, a, c, l]
    for k in range(K - 1, -1, -1):
        cur = (K - 1 - k) % 2
        Ps = PP[1 - cur]  # P_s[k + 1]
        Pn = PP[cur]  # P_s[k], computed here
        Pf = PfS[k]
        Ak = AS[k]
        for a in range(n):
            for c in range(n):
                for l in range(LANES):
                    Pp[a, c, l] = 0.5 * (PpS[k + 1, a, c, l] + PpS[k + 1, c, a, l])
        _chol(Pp, W2, n, ok, acc, inv)
        if not _all(ok):
            _fix_lanes(Pp, W2, n, ok, sc, scL, rep)
        _XY(Ak, Pf, W1, n, n, n, False, acc)
        _chol_solve(W2, W1, Gt, n, n, dg, acc)  # G^T = Pp^-1 A P_f
        for a in range(n):
            for l in range(LANES):
                dd = ms[a, l] - mS[k + 1, a, l]
                d[a, l] = wrap(dd) if state_angles[a] else dd
                mn[a, l] = ms[a, l]
        for a in range(n):
            for l in range(LANES):
                acc[l] = 0.0
            for c in range(n):
                for l in range(LANES):
                    acc[l] += Gt[c, a, l] * d[c, l]
            for l in range(LANES):
                v = mfS[k, a, l] + acc[l]
                ms[a, l] = wrap(v) if state_angles[a] else v
        _XY(Ps, Gt, Cl, n, n, n, False, acc)  # C_k = P_s[k + 1] G_k^T
        for a in range(n):
            for c in range(n):
                for l in range(LANES):
                    W2[a, c, l] = Ps[a, c, l] - Pp[a, c, l]
        _XY(Gt, W2, W1, n, n, n, True, acc)  # G (Ps - Pp)
        _XY_sym_plus(W1, Gt, Pf, Pn, n, n, acc)  # P_f + G (Ps - Pp) G^T, symmetric
        if keep_Q:  # (e e^T + P_{k+1} - C A^T - A C^T + A P_k A^T) / dt_k, e = m_{k+1} - A m_k - b_k
            _Ax(Ak, ms, d, n, acc)
            for l in range(LANES):
                r = rl[l]
                for a in range(n):
                    v = (mn[a, l] - d[a, l]) - b[r, k, a]
                    e[a, l] = wrap(v) if state_angles[a] else v
            _XYt(Cl, Ak, Pp, n, n, n, False, acc)  # C A^T
            _XY(Ak, Pn, W2, n, n, n, False, acc)
            _XYt(W2, Ak, W1, n, n, n, True, acc)  # A P_k A^T
            h = dt[k]
            for a in range(n):
                for c in range(n):
                    for l in range(LANES):
                        Qa[a, c, l] += ((((e[a, l] * e[c, l] + Ps[a, c, l]) - Pp[c, a, l]) - Pp[a, c, l])
                                        + W1[a, c, l]) / h
        if keep_R:
            _r_sums(k, rl, ms, Pn, obs, Ra, Rc, Hl, HP, rv, vm, acc)
        if keep_sd:
            for a in range(n):
                for c in range(n):
                    for l in range(LANES):
                        fz[l] += Pn[a, c, l] * 0.0
        for l in range(nl):
            r = rl[l]
            for a in range(n):
                m_s[r, k, a] = ms[a, l]
                if keep_sd:
                    sd[r, k, a] = _sd(Pn[a, a, l])
                for c in range(n):
                    P_s[r, k, a, c] = Pn[a, c, l]
            if keep_C:
                for a in range(n):
                    for c in range(n):
                        C[r, k, a, c] = Cl[a, c, l]
            if keep_G:
                for a in range(n):
                    for c in range(n):
                        G[r, k, a, c] = Gt[c, a, l]
    if keep_Q:
        for l in range(nl):
            r = rl[l]
            for a in range(n):
                for c in range(n):
                    q_sums[r, a, c] = 0.5 * (Qa[a, c, l] / K + Qa[c, a, l] / K)
    if keep_sd:
        for l in range(nl):
            finite[rl[l]] = fz[l] == 0.0
    if keep_R:
        for l in range(nl):
            r = rl[l]
            for j in range(J):
                cnt = Rc[j, l]
                r_count[r, j] = cnt
                for a in range(ch_m[j]):
                    for c in range(ch_m[j]):
                        r_sums[r, j, a, c] = 0.5 * (Ra[j, a, c, l] / cnt + Ra[j, c, a, l] / cnt)


@lanes
def _r_sums(k, rl, m, P, obs, Ra, Rc, Hl, HP, rv, vm, acc):
    """The terms of :func:`measurement_noise_sums` of the samples of ``obs`` (:data:`Samples`) at tick ``k``
    (smoothed ``m (n, LANES)``, ``P (n, n, LANES)``), added to ``Ra (J, mm, mm, LANES)`` and counted in
    ``Rc (J, LANES)`` where valid: ``r r^T + H P H^T``, ``r = y - H m - d`` (``H``'s structural zeros
    skipped, as that kernel's ``_mm``)."""
    slot, ch_m, Y, V, H, D = obs.slot, obs.m, obs.Y, obs.V, obs.H, obs.D
    ang_c, hcnt, hidx = obs.ang, obs.hcnt, obs.hidx
    n = m.shape[0]
    for j in range(slot.shape[0]):
        i = slot[j, k]
        if i < 0:
            continue
        mj = ch_m[j]
        for l in range(LANES):
            r = rl[l]
            vm[l] = V[r, i]
            for a in range(mj):
                for t in range(hcnt[j, a]):
                    c = hidx[j, a, t]
                    Hl[a, c, l] = H[r, i, a, c]
        for a in range(mj):
            for l in range(LANES):
                acc[l] = 0.0
            for t in range(hcnt[j, a]):
                c = hidx[j, a, t]
                for l in range(LANES):
                    acc[l] += Hl[a, c, l] * m[c, l]
            for l in range(LANES):
                r = rl[l]
                v = (Y[r, i, a] - acc[l]) - D[r, i, a]
                rv[a, l] = wrap(v) if ang_c[j, a] else v
            for q in range(n):
                for l in range(LANES):
                    acc[l] = 0.0
                for t in range(hcnt[j, a]):
                    c = hidx[j, a, t]
                    for l in range(LANES):
                        acc[l] += Hl[a, c, l] * P[c, q, l]
                for l in range(LANES):
                    HP[a, q, l] = acc[l]
        for a in range(mj):
            for c in range(mj):
                for l in range(LANES):
                    acc[l] = 0.0
                for t in range(hcnt[j, c]):
                    q = hidx[j, c, t]
                    for l in range(LANES):
                        acc[l] += HP[a, q, l] * Hl[c, q, l]
                for l in range(LANES):
                    term = rv[a, l] * rv[c, l] + acc[l]
                    Ra[j, a, c, l] += term if vm[l] else 0.0
        for l in range(LANES):
            Rc[j, l] += 1 if vm[l] else 0
        for a in range(mj):  # back to zeros for the next sample's rows
            for t in range(hcnt[j, a]):
                c = hidx[j, a, t]
                for l in range(LANES):
                    Hl[a, c, l] = 0.0


@jit
def _sd(v):
    """numpy's ``sqrt(maximum(v, 1e-300))`` (NaN stays NaN)."""
    return math.sqrt(v) if (v > 1e-300 or v != v) else math.sqrt(1e-300)


@jit
def rts(lo, hi, flt, aff, obs, sm):
    """:func:`needlecli.numerics.kalman.rts_smoother` for trials ``lo..hi-1`` (lanes of LANES): a filter's
    output (:data:`Filtered`, the transitions ``aff.A``) gathered into the lanes' layout, then
    :func:`_backward_block` into ``sm``."""
    A, m_pred, P_pred, m_filt, P_filt = aff.A, flt.m_pred, flt.P_pred, flt.m_filt, flt.P_filt
    repairs = sm.repairs
    N, K1, n = m_filt.shape
    blk = _scratch(K1, n)
    mS, PpS, mfS, PfS, AS = blk.mS, blk.PpS, blk.mfS, blk.PfS, blk.AS
    rep = np.zeros(LANES, dtype=np.int64)
    for r0 in range(lo, hi, LANES):
        rl = _lanes(lo, hi, r0)
        for l in range(LANES):
            rep[l] = 0
        for k in range(K1):
            for l in range(LANES):
                r = rl[l]
                for a in range(n):
                    mS[k, a, l] = m_pred[r, k, a]
                    mfS[k, a, l] = m_filt[r, k, a]
                    for c in range(n):
                        PpS[k, a, c, l] = P_pred[r, k, a, c]
                        PfS[k, a, c, l] = P_filt[r, k, a, c]
                        if k < K1 - 1:
                            AS[k, a, c, l] = A[r, k, a, c]
        nl = min(LANES, hi - r0)
        _backward_block(rl, nl, blk, aff, obs, sm, rep)
        for l in range(nl):
            repairs[rl[l]] += rep[l]


@jit
def filter_smoother(lo, hi, aff, obs, flt, sm):
    """:func:`forward_affine` then :func:`rts` on each block without leaving the lanes' layout in between
    (the filter's covariances are not written out into ``flt``; nor the smoother's gains into ``sm``); with
    ``sm.keep_Q`` the M-step's sums of :func:`process_noise_sums` too, in the same pass (then the
    cross-covariances need not be written: ``keep_C``)."""
    m_pred, m_filt, loglik, repairs_f = flt.m_pred, flt.m_filt, flt.loglik, flt.repairs
    repairs_s = sm.repairs
    n = aff.m0.shape[1]
    K1 = obs.slot.shape[1]
    blk = _scratch(K1, n)
    mS, mfS = blk.mS, blk.mfS
    ll = np.zeros(LANES)
    rep = np.zeros(LANES, dtype=np.int64)
    rep_s = np.zeros(LANES, dtype=np.int64)
    for r0 in range(lo, hi, LANES):
        rl = _lanes(lo, hi, r0)
        nl = min(LANES, hi - r0)
        _forward_block(rl, aff, obs, blk, ll, rep)
        for l in range(nl):
            loglik[rl[l]] = ll[l]
            repairs_f[rl[l]] += rep[l]
            rep_s[l] = 0
        for k in range(K1):
            for l in range(nl):
                r = rl[l]
                for a in range(n):
                    m_pred[r, k, a] = mS[k, a, l]
                    m_filt[r, k, a] = mfS[k, a, l]
        _backward_block(rl, nl, blk, aff, obs, sm, rep_s)
        for l in range(nl):
            repairs_s[rl[l]] += rep_s[l]


# ---------------------------------------------------------------------------------------------- the M-step
@jit
def process_noise_sums(lo, hi, m, P, C, A, b, dt, keep, state_angles, Q):
    """:func:`needlecli.numerics.kalman.em_process_noise` for trials ``lo..hi-1`` (lanes of LANES) into
    ``Q (N, n, n)``: ``mean_k (e e^T + P_{k+1} - A C^T - C A^T + A P_k A^T) / dt_k``, symmetrised."""
    N, K1, n = m.shape
    K = K1 - 1
    e = np.empty((n, LANES))
    mk = np.empty((n, LANES))
    Am = np.empty((n, LANES))
    Ak = np.empty((n, n, LANES))
    Ck = np.empty((n, n, LANES))
    Pk = np.empty((n, n, LANES))
    CAt = np.empty((n, n, LANES))
    AP = np.empty((n, n, LANES))
    APA = np.empty((n, n, LANES))
    acc = np.empty((n, n, LANES))
    acc1 = np.empty(LANES)
    for r0 in range(lo, hi, LANES):
        rl = _lanes(lo, hi, r0)
        for a in range(n):
            for c in range(n):
                for l in range(LANES):
                    acc[a, c, l] = 0.0
        for k in range(K):
            for l in range(LANES):
                r = rl[l]
                for a in range(n):
                    mk[a, l] = m[r, k, a]
                    for c in range(n):
                        Ak[a, c, l] = A[r, k, a, c]
                        Ck[a, c, l] = C[r, k, a, c]
                        Pk[a, c, l] = P[r, k, a, c]
            _Ax(Ak, mk, Am, n, acc1)
            for l in range(LANES):
                r = rl[l]
                for a in range(n):
                    v = (m[r, k + 1, a] - Am[a, l]) - b[r, k, a]
                    e[a, l] = wrap(v) if state_angles[a] else v
            _XYt(Ck, Ak, CAt, n, n, n, False, acc1)  # C_k A_k^T = (A_k C_k^T)^T
            _XY(Ak, Pk, AP, n, n, n, False, acc1)
            _XYt(AP, Ak, APA, n, n, n, True, acc1)
            h = dt[k]
            for l in range(LANES):
                r = rl[l]
                for a in range(n):
                    for c in range(n):
                        acc[a, c, l] += ((((e[a, l] * e[c, l] + P[r, k + 1, a, c]) - CAt[c, a, l]) - CAt[a, c, l])
                                         + APA[a, c, l]) / h
        for l in range(min(LANES, hi - r0)):
            r = rl[l]
            for a in range(n):
                for c in range(n):
                    v = 0.5 * (acc[a, c, l] / K + acc[c, a, l] / K)
                    Q[r, a, c] = v * (1.0 if (keep[a] and keep[c]) else 0.0)  # as numpy: NaN stays NaN


@jit
def measurement_noise_sums(lo, hi, m, P, tick, y, valid, H, d, angle, R, count):
    """:func:`needlecli.numerics.kalman.em_measurement_noise` for one channel, trials ``lo..hi-1``."""
    M = tick.shape[0]
    mc = y.shape[2]
    n = m.shape[2]
    rv = np.empty(mc)
    HP = np.empty((mc, n))
    acc = np.empty((mc, mc))
    for r in range(lo, hi):
        for a in range(mc):
            for c in range(mc):
                acc[a, c] = 0.0
        cnt = 0
        for i in range(M):
            if not valid[r, i]:
                continue
            cnt += 1
            k = tick[i]
            for a in range(mc):
                s = 0.0
                for c in range(n):
                    s += H[r, i, a, c] * m[r, k, c]
                v = (y[r, i, a] - s) - d[r, i, a]
                rv[a] = wrap(v) if angle[a] else v
            _mm(H[r, i], P[r, k], HP, mc, n, n)
            for a in range(mc):
                for c in range(mc):
                    s = 0.0
                    for q in range(n):
                        s += HP[a, q] * H[r, i, c, q]
                    acc[a, c] += rv[a] * rv[c] + s
        count[r] = cnt
        for a in range(mc):
            for c in range(mc):
                R[r, a, c] = 0.5 * (acc[a, c] / cnt + acc[c, a] / cnt)


# ---------------------------------------------------------------------------------------------- linearisation
@jit
def _f_mag(z, u, nx, bicycle, out):
    """The magnetic models' vector field at one augmented state (the constant is ``z[nx]``)."""
    f = magnetic_field(z[3], z[4], z[5], z[6], z[7], z[8], z[nx], u[0], u[1], u[2], u[3], bicycle)
    for i in range(9):
        out[i] = f[i]
    for i in range(nx, z.shape[0]):
        out[i] = 0.0


@jit
def _jac_mag(z, u, nx, bicycle, J):
    """``df/dz`` of the augmented magnetic model (:meth:`MagneticModel.jacobian` and ``param_jacobian``)."""
    n = z.shape[0]
    for i in range(n):
        for j in range(n):
            J[i, j] = 0.0
    h = z[3:6]
    bv = z[6:9]
    v = u[0]
    hh = h[0] * h[0] + h[1] * h[1] + h[2] * h[2]
    hb = h[0] * bv[0] + h[1] * bv[1] + h[2] * bv[2]
    bb = bv[0] * bv[0] + bv[1] * bv[1] + bv[2] * bv[2]
    for i in range(3):
        J[i, 3 + i] = v
    p = z[nx]
    if bicycle:
        s = bv[0] * h[0] + bv[1] * h[1] + bv[2] * h[2]
        lv = p * v
    else:
        cv = p * v
    for i in range(3):
        t_i = bv[i] * hh - h[i] * hb
        for j in range(3):
            dth = (2.0 * bv[i] * h[j] - (hb if i == j else 0.0)) - h[i] * bv[j]
            dtb = (hh if i == j else 0.0) - h[i] * h[j]
            if bicycle:
                jh = lv * (dth / s - t_i * bv[j] / s**2)
                jb = lv * (dtb / s - t_i * h[j] / s**2)
            else:
                jh = cv * dth
                jb = cv * dtb
            J[3 + i, 3 + j] = (jh + (1.0 - hh) * (1.0 if i == j else 0.0)) - 2.0 * h[i] * h[j]
            J[3 + i, 6 + j] = jb
        J[3 + i, nx] = (v / s) * t_i if bicycle else v * t_i
    w = u[1:4]
    sk = ((0.0, -w[2], w[1]), (w[2], 0.0, -w[0]), (-w[1], w[0], 0.0))
    for i in range(3):
        for j in range(3):
            J[6 + i, 6 + j] = (sk[i][j] + (1.0 - bb) * (1.0 if i == j else 0.0)) - 2.0 * bv[i] * bv[j]


@jit
def _stage_jacobian(x, u, nx, bicycle, J, T, D_prev, h, D_out):
    """``D_out = J(x) + h J(x) D_prev``: the chain rule through one RK4 stage."""
    n = x.shape[0]
    _jac_mag(x, u, nx, bicycle, J)
    _mm(J, D_prev, T, n, n, n)
    for a in range(n):
        for c in range(n):
            D_out[a, c] = J[a, c] + h * T[a, c]


@jit
def transitions(lo, hi, zbar, sub_dt, sub_u, nx, bicycle, z_out, A_out):
    """:meth:`DiscreteModel.transition_all` for the magnetic models, trials ``lo..hi-1``: every interval's
    RK4 substeps from ``zbar`` with the exact Jacobian (:func:`rk4_with_jacobian`'s chain rule)."""
    N, K, n = zbar.shape
    S = sub_dt.shape[1]
    x = np.empty(n)
    x2 = np.empty(n)
    k1 = np.empty(n)
    k2 = np.empty(n)
    k3 = np.empty(n)
    k4 = np.empty(n)
    D1 = np.empty((n, n))
    J = np.empty((n, n))
    D2 = np.empty((n, n))
    D3 = np.empty((n, n))
    D4 = np.empty((n, n))
    T = np.empty((n, n))
    F = np.empty((n, n))
    Acc = np.empty((n, n))
    for r in range(lo, hi):
        for k in range(K):
            for a in range(n):
                x[a] = zbar[r, k, a]
            first = True
            for j in range(S):
                h = sub_dt[k, j]
                if h == 0.0:
                    continue
                u = sub_u[r, k, j]
                half = 0.5 * h
                _f_mag(x, u, nx, bicycle, k1)
                for a in range(n):
                    x2[a] = x[a] + half * k1[a]
                _f_mag(x2, u, nx, bicycle, k2)
                _jac_mag(x, u, nx, bicycle, D1)
                _stage_jacobian(x2, u, nx, bicycle, J, T, D1, half, D2)
                for a in range(n):
                    x2[a] = x[a] + half * k2[a]
                _f_mag(x2, u, nx, bicycle, k3)
                _stage_jacobian(x2, u, nx, bicycle, J, T, D2, half, D3)
                for a in range(n):
                    x2[a] = x[a] + h * k3[a]
                _f_mag(x2, u, nx, bicycle, k4)
                _stage_jacobian(x2, u, nx, bicycle, J, T, D3, h, D4)
                sixth = h / 6.0
                for a in range(n):
                    x[a] = x[a] + sixth * ((k1[a] + 2.0 * (k2[a] + k3[a])) + k4[a])
                    for c in range(n):
                        F[a, c] = (1.0 if a == c else 0.0) + sixth * ((D1[a, c] + 2.0 * (D2[a, c] + D3[a, c])) + D4[a, c])
                if first:
                    for a in range(n):
                        for c in range(n):
                            Acc[a, c] = F[a, c]
                    first = False
                else:
                    _mm(F, Acc, T, n, n, n)
                    for a in range(n):
                        for c in range(n):
                            Acc[a, c] = T[a, c]
            for a in range(n):
                z_out[r, k, a] = x[a]
                for c in range(n):
                    A_out[r, k, a, c] = Acc[a, c] if not first else (1.0 if a == c else 0.0)


@jit
def fd_linearise(lo, hi, z, kind, idx, y, valid, axis, yh_out, H_out, d_out, y_out):
    """:meth:`MeasurementModel.linearise` (central differences of ``h``, a measured direction in the plane
    across it) for trials ``lo..hi-1`` at states ``z (N, M, n)``. kind 0: ``h = z[idx]``; kind 1:
    ``h = z[idx] / |z[idx]|`` (a direction), then in the tangent plane of the predicted one about
    ``axis``."""
    N, M, n = z.shape
    mr = idx.shape[0]
    x = np.empty(n)
    step = np.empty(n)
    hp = np.empty(mr)
    hm = np.empty(mr)
    y0 = np.empty(mr)
    Jr = np.empty((mr, n))
    for r in range(lo, hi):
        for i in range(M):
            for a in range(n):
                x[a] = z[r, i, a]
                step[a] = 1e-6 * max(1.0, abs(x[a]))
            _h(x, kind, idx, y0)
            for a in range(n):
                xa = x[a]
                x[a] = xa + step[a]
                _h(x, kind, idx, hp)
                x[a] = xa - step[a]
                _h(x, kind, idx, hm)
                x[a] = xa
                for q in range(mr):
                    Jr[q, a] = (hp[q] - hm[q]) / (2.0 * step[a])
            if kind == 0:
                for q in range(mr):
                    yh_out[r, i, q] = y0[q]
                    for a in range(n):
                        H_out[r, i, q, a] = Jr[q, a]
                    s = 0.0
                    for a in range(n):
                        s += Jr[q, a] * x[a]
                    d_out[r, i, q] = y0[q] - s
                    y_out[r, i, q] = y[r, i, q] if valid[r, i] else 0.0
            else:
                nr = math.sqrt(y0[0] * y0[0] + y0[1] * y0[1] + y0[2] * y0[2])
                u0, u1, u2 = y0[0] / nr, y0[1] / nr, y0[2] / nr
                a0 = 1.0 if axis == 0 else 0.0
                a1 = 1.0 if axis == 1 else 0.0
                a2 = 1.0 if axis == 2 else 0.0
                e0 = a1 * u2 - a2 * u1
                e1 = a2 * u0 - a0 * u2
                e2 = a0 * u1 - a1 * u0
                ne = math.sqrt(e0 * e0 + e1 * e1 + e2 * e2)
                e0, e1, e2 = e0 / ne, e1 / ne, e2 / ne
                f0 = u1 * e2 - u2 * e1
                f1 = u2 * e0 - u0 * e2
                f2 = u0 * e1 - u1 * e0
                E = ((e0, f0), (e1, f1), (e2, f2))
                for q in range(2):
                    yh = E[0][q] * y0[0] + E[1][q] * y0[1] + E[2][q] * y0[2]
                    yh_out[r, i, q] = yh
                    s = 0.0
                    for a in range(n):
                        Hq = E[0][q] * Jr[0, a] + E[1][q] * Jr[1, a] + E[2][q] * Jr[2, a]
                        H_out[r, i, q, a] = Hq
                        s += Hq * x[a]
                    d_out[r, i, q] = yh - s
                    if valid[r, i]:
                        y_out[r, i, q] = E[0][q] * y[r, i, 0] + E[1][q] * y[r, i, 1] + E[2][q] * y[r, i, 2]
                    else:
                        y_out[r, i, q] = 0.0


@jit
def _h(x, kind, idx, out):
    m = idx.shape[0]
    for q in range(m):
        out[q] = x[idx[q]]
    if kind == 1:
        nrm = math.sqrt(out[0] * out[0] + out[1] * out[1] + out[2] * out[2])
        for q in range(m):
            out[q] = out[q] / nrm


# ---------------------------------------------------------------------------------------------- the seams
def _trials(N: int, work: int = 1 << 20):
    """Blocks of trials for the workers; one block (the calling thread) for little work (``work``: about
    the number of matrix operations)."""
    return blocks(N, per_thread=4) if work >= 20000 else [(0, N)]


def _lane_blocks(N: int):
    """Blocks of trials for the kernels that work on LANES trials at once: whole lane blocks (a block of
    fewer trials would compute the missing lanes for nothing)."""
    return blocks(N, per_thread=4, minimum=LANES)


def _channels_concat(channels, H, d, N, n, Ns=None):
    """The channels' samples along one axis (each channel's samples after the previous one's); ``N`` rows
    of noise, ``Ns`` (default ``N``) of samples and their linearisation."""
    Ns = N if Ns is None else Ns
    J = len(channels)
    mm = max([ch.m for ch in channels], default=1)
    M = sum(len(np.asarray(ch.tick)) for ch in channels)
    Y = np.zeros((Ns, max(M, 1), mm))
    V = np.zeros((Ns, max(M, 1)), dtype=np.bool_)
    R = np.zeros((N, max(J, 1), mm, mm))
    Hc = np.zeros((Ns, max(M, 1), mm, n))
    Dc = np.zeros((Ns, max(M, 1), mm))
    ang = np.zeros((max(J, 1), mm), dtype=np.bool_)
    hcnt = np.zeros((max(J, 1), mm), dtype=np.int64)
    hidx = np.zeros((max(J, 1), mm, n), dtype=np.int64)
    ch_m = np.zeros(max(J, 1), dtype=np.int64)
    offsets = []
    o = 0
    for j, ch in enumerate(channels):
        Mj, mj = ch.y.shape[1], ch.m
        Y[:, o : o + Mj, :mj] = ch.y
        V[:, o : o + Mj] = ch.valid
        R[:, j, :mj, :mj] = np.broadcast_to(ch.R, (N, mj, mj))
        Hc[:, o : o + Mj, :mj] = H[j]
        Dc[:, o : o + Mj, :mj] = d[j]
        if ch.angle is not None:
            ang[j, :mj] = ch.angle
        nz = (np.asarray(H[j]) != 0).reshape(-1, mj, n).any(axis=0) if np.size(H[j]) else np.ones((mj, n), bool)
        for q in range(mj):
            cols = np.nonzero(nz[q])[0]
            hcnt[j, q] = cols.size
            hidx[j, q, : cols.size] = cols
        ch_m[j] = mj
        offsets.append(o)
        o += Mj
    return Y, V, R, Hc, Dc, ang, hcnt, hidx, ch_m, offsets


def kalman_forward_affine(m0, P0, Qc, dt, A, b, channels, H, d, *, state_angles=None, store=True, rows=None):
    """:func:`needlecli.numerics.kalman.kalman_forward_affine`, compiled: the fields of its ``ForwardResult``
    (``m_pred, P_pred, m_filt, P_filt, A, loglik, repairs``; the caller builds the result: the kernels import
    nothing of the package above them). ``store=False``: the log-likelihood and repairs only (the four
    arrays of means and covariances are then empty: 2.4 GB a pass not written for the evaluation points
    of :mod:`needlecli.fitting.identify`). ``rows (N,)``: trial r filters with row ``rows[r]`` of ``A, b,
    H, d`` and of the channels' samples (their leading axis that long), with its own ``m0, P0, Qc`` and
    noise (the channels' ``R``, N rows); the same numbers as those rows copied out first."""
    m0 = kernel_array(m0, dtype=float)
    N, n = m0.shape
    src = np.arange(N, dtype=np.int64) if rows is None else kernel_array(rows, dtype=np.int64)
    if len(src) != N:
        raise ValueError(f"rows: {len(src)} rows for {N} trials")
    K = len(dt)
    aff, obs = _forward_inputs(m0, P0, Qc, dt, A, b, channels, H, d, state_angles, np.shape(A)[0], src)
    Ks = K + 1 if store else 0
    out = Filtered(np.empty((N, Ks, n)), np.empty((N, Ks, n, n)), np.empty((N, Ks, n)), np.empty((N, Ks, n, n)),
                   np.zeros(N), np.zeros(N, dtype=np.int64))
    parallel_for(forward_affine, _lane_blocks(N), (aff, obs, out, bool(store)))
    return out.m_pred, out.P_pred, out.m_filt, out.P_filt, aff.A, out.loglik, out.repairs


def _forward_inputs(m0, P0, Qc, dt, A, b, channels, H, d, state_angles, Ns, src):
    """The records :data:`Affine` and :data:`Samples` of a pass, contiguous."""
    N, n = m0.shape
    K = len(dt)
    # (a broadcast of an (N, n, n) array is read-only: copied, so that the records have one type, the RTS
    # smoother's too: one compilation of the backward block)
    P0 = kernel_array(np.broadcast_to(P0, (N, n, n)), dtype=float)
    Qc = kernel_array(np.broadcast_to(Qc, (N, n, n)), dtype=float)
    A = kernel_array(A, dtype=float)
    b = kernel_array(b, dtype=float)
    Y, V, R, Hc, Dc, ang, hcnt, hidx, ch_m, offsets = _channels_concat(channels, H, d, N, n, Ns)
    J = len(channels)
    slot = np.full((max(J, 1), K + 1), -1, dtype=np.int64)
    for j, ch in enumerate(channels):
        t = np.asarray(ch.tick)
        ok = (t >= 0) & (t < K + 1)
        slot[j, t[ok]] = offsets[j] + np.nonzero(ok)[0]
    return (Affine(m0, P0, Qc, kernel_array(dt, dtype=float), A, b, src, _angles(state_angles, n)),
            Samples(slot, ch_m, Y, V, R, Hc, Dc, ang, hcnt, hidx))


def _angles(state_angles, n):
    return np.zeros(n, dtype=np.bool_) if state_angles is None else kernel_array(state_angles, dtype=np.bool_)


def _no_samples(n, K1):
    """:data:`Samples` of no channel (the smoother of a stored filter makes no M-step sums): the array types
    of a pass's, empty."""
    return Samples(np.empty((0, K1), dtype=np.int64), np.empty(0, dtype=np.int64), np.empty((0, 0, 1)),
                   np.empty((0, 0), dtype=np.bool_), np.empty((0, 0, 1, 1)), np.empty((0, 0, 1, n)), np.empty((0, 0, 1)),
                   np.empty((0, 1), dtype=np.bool_), np.empty((0, 1), dtype=np.int64), np.empty((0, 1, n), dtype=np.int64))


def kalman_filter_smoother(m0, P0, Qc, dt, A, b, channels, H, d, *, state_angles=None, q_sums=False):
    """:func:`kalman_forward_affine` then :func:`rts_smoother` in one compiled pass over each block of trials:
    the fields of the ``ForwardResult`` and of the ``SmoothResult``, without the filter's covariances and
    the smoother's gains (those three arrays empty, ``(N, 0, n, n)``: what EM does not read is not written,
    2 x 19 MB a pass for the magnetic needle EM paper's 48 trials). ``q_sums``: also the M-step's sums, ``(Q, R, count)`` (else
    None): those of :func:`em_process_noise` (all states kept, ``(N, n, n)``) and of
    :func:`em_measurement_noise` for every channel (``(N, J, mm, mm)``, ``(N, J)``), and not the
    cross-covariances (empty), which only those sums read. Then the smoothed standard deviations ``(N, K+1, n)`` and whether each trial's covariances are all
    finite ``(N,)``: what EM computes from the covariances at every pass, made as they are written."""
    m0 = kernel_array(m0, dtype=float)
    N, n = m0.shape
    K = len(dt)
    aff, obs = _forward_inputs(m0, P0, Qc, dt, A, b, channels, H, d, state_angles, N, np.arange(N, dtype=np.int64))
    none = np.empty((N, 0, n, n))
    flt = Filtered(np.empty((N, K + 1, n)), none, np.empty((N, K + 1, n)), none, np.zeros(N), np.zeros(N, dtype=np.int64))
    _, J, mm, _ = obs.R.shape  # the channels' noise, (N, J, mm, mm)
    q = bool(q_sums)
    sm = Smoothed(np.empty((N, K + 1, n)), np.empty((N, K + 1, n, n)), np.empty((N, 0 if q else K, n, n)),
                  np.empty((0, 0, n, n)),  # the gains: not written (array arguments of the blocks must not overlap)
                  np.empty((N if q else 0, n, n)), np.empty((N, K + 1, n)), np.zeros(N, dtype=np.bool_),
                  np.zeros((N if q else 0, J, mm, mm)), np.zeros((N if q else 0, J), dtype=np.int64),
                  np.zeros(N, dtype=np.int64), not q, False, q, True, q)
    parallel_for(filter_smoother, _lane_blocks(N), (aff, obs, flt, sm))
    m_step = (sm.q_sums, sm.r_sums, sm.r_count) if q else None
    return ((flt.m_pred, none, flt.m_filt, none, aff.A, flt.loglik, flt.repairs), (sm.m, sm.P, sm.C, none, sm.repairs),
            m_step, sm.sd, sm.finite)


def rts_smoother(fwd, *, state_angles=None):
    """:func:`needlecli.numerics.kalman.rts_smoother`, compiled: the fields of its ``SmoothResult``
    (``m, P, C, G, repairs``)."""
    N, K1, n = fwd.m_filt.shape
    c = kernel_array
    flt = Filtered(c(fwd.m_pred, dtype=float), c(fwd.P_pred, dtype=float), c(fwd.m_filt, dtype=float),
                   c(fwd.P_filt, dtype=float), np.zeros(0), np.zeros(0, dtype=np.int64))
    aff = Affine(np.empty((0, n)), np.empty((0, n, n)), np.empty((0, n, n)), np.empty(0), c(fwd.A, dtype=float),
                 np.empty((0, 0, n)), np.empty(0, dtype=np.int64), _angles(state_angles, n))  # no M-step sums here
    sm = Smoothed(np.empty((N, K1, n)), np.empty((N, K1, n, n)), np.empty((N, K1 - 1, n, n)), np.empty((N, K1 - 1, n, n)),
                  np.empty((0, n, n)), np.empty((0, 0, n)), np.empty(0, dtype=np.bool_), np.empty((0, 0, 1, 1)),
                  np.empty((0, 0), dtype=np.int64), np.zeros(N, dtype=np.int64), True, True, False, False, False)
    parallel_for(rts, _lane_blocks(N), (flt, aff, _no_samples(n, K1), sm))
    return sm.m, sm.P, sm.C, sm.G, sm.repairs


def em_process_noise(sm, A, b, dt, *, index=None, state_angles=None):
    """:func:`needlecli.numerics.kalman.em_process_noise`, compiled."""
    N, K1, n = sm.m.shape
    c = kernel_array
    keep = np.ones(n, dtype=np.bool_)
    if index is not None:
        keep[:] = False
        keep[np.asarray(index)] = True
    sa = _angles(state_angles, n)
    A = c(A, dtype=float)
    Q = np.empty((N, n, n))
    parallel_for(process_noise_sums, _lane_blocks(N), (c(sm.m, dtype=float), c(sm.P, dtype=float), c(sm.C, dtype=float),
                                                  A, c(b, dtype=float), c(dt, dtype=float), keep, sa, Q))
    return Q


def em_measurement_noise(sm, channel, H, d):
    """:func:`needlecli.numerics.kalman.em_measurement_noise`, compiled."""
    N = sm.m.shape[0]
    c = kernel_array
    m = channel.y.shape[-1]
    ang = np.zeros(m, dtype=np.bool_) if channel.angle is None else c(channel.angle, dtype=np.bool_)
    R = np.empty((N, m, m))
    count = np.zeros(N, dtype=np.int64)
    parallel_for(measurement_noise_sums, _trials(N), (c(sm.m, dtype=float), c(sm.P, dtype=float),
                                                      c(channel.tick, dtype=np.int64), c(channel.y, dtype=float),
                                                      c(channel.valid, dtype=np.bool_), c(H, dtype=float),
                                                      c(d, dtype=float), ang, R, count))
    return R, count


def transition_all(dm, zbar):
    """:meth:`DiscreteModel.transition_all` of a magnetic model (augmented with its constant), compiled."""
    N, K, n = zbar.shape
    z = np.empty((N, K, n))
    A = np.empty((N, K, n, n))
    c = kernel_array
    parallel_for(transitions, _trials(N), (c(zbar, dtype=float), c(dm.sub_dt, dtype=float), c(dm.sub_u, dtype=float),
                                           int(dm.nx), dm.model.compiled_equations == "binm", z, A))
    return z, A


def transition_one(dm, k, z):
    """:meth:`DiscreteModel.transition` of interval ``k`` (before the normalisation), compiled: the same
    kernel as :func:`transition_all` on one interval, ``(z_next (N, n), A (N, n, n))``."""
    N, n = z.shape
    z_out = np.empty((N, 1, n))
    A = np.empty((N, 1, n, n))
    c = kernel_array
    parallel_for(transitions, _trials(N, N * n * n), (c(z[:, None], dtype=float), c(dm.sub_dt[k : k + 1], dtype=float),
                                                      c(dm.sub_u[:, k : k + 1], dtype=float), int(dm.nx),
                                                      dm.model.compiled_equations == "binm", z_out, A))
    return z_out[:, 0], A[:, 0]


#: the compiled equations (:data:`needlecli.kernels.models.MODEL_IDS`) whose RK4 Jacobian
#: :func:`transitions` has (their curvature parameter augmented)
LINEARISED = ("mnm", "binm")


def transitions_supported(dm) -> bool:
    """Whether :func:`transitions` covers the system ``dm``: a model with equations it linearises, their
    curvature parameter (and nothing else) augmented."""
    return (dm.model.compiled_equations in LINEARISED and len(dm.augment) == 1
            and dm.augment[0] == dm.model.curvature_param and dm.nx == 9)


def linearise(mm, kind, z, y=None):
    """:meth:`MeasurementModel.linearise`, compiled: ``(h(z), H, d, y)`` at ``z (N, M, n)`` or ``(N, n)``."""
    kd, idx = kind
    one = z.ndim == 2
    z3 = kernel_array(z[:, None] if one else z, dtype=float)
    N, M, n = z3.shape
    if y is None:
        yy, valid = mm.y, mm.valid
    else:
        yy, valid = (y[:, None] if one else y), np.ones((N, M), dtype=bool)
    m = mm.m
    yh = np.empty((N, M, m))
    H = np.empty((N, M, m, n))
    d = np.empty((N, M, m))
    yo = np.empty((N, M, m))
    axis = mm._axis() if kd == 1 else 0  # (idx copied: one compiled signature, whether given writable or not)
    parallel_for(fd_linearise, _trials(N, N * M * n), (z3, kd, np.array(idx, dtype=np.int64), kernel_array(yy, dtype=float),
                                            kernel_array(valid, dtype=np.bool_), int(axis), yh, H, d, yo))
    if one:
        return yh[:, 0], H[:, 0], d[:, 0], yo[:, 0]
    return yh, H, d, yo
