"""Scalar building blocks of the kernels: sin/cos, angle wrapping, and the small dense linear algebra of
the filters (Cholesky with the numpy path's repair, Gaussian elimination), on one matrix at a time.

``sincos`` is a polynomial (fdlibm's minimax kernels on ``[-pi/4, pi/4]`` after a three-part Cody-Waite
reduction by ``pi/2``), within 1 ulp of libm's ``sin`` and ``cos`` for ``|x| < 8`` (2 ulp up to ``1e6``) and, being
branch-free there, vectorised by LLVM over the lanes of the model kernels (2 ns per pair on AVX-512,
against 15 ns for libm's ``tan`` that the numpy path's half-angle formula needs). Larger arguments (and
inf, NaN) go to libm.
"""

from __future__ import annotations

import math

import numpy as np

from needlecli.kernels._jit import inline, jit

PI = math.pi
TWO_PI = 2.0 * math.pi
_TWO_OVER_PI = 0.6366197723675814
_P1 = 1.5707963267341256  # pi/2 in three parts: 33 + 33 + 53 bits (k * P1 and k * P2 exact for |k| < 2^20)
_P2 = 6.077100506303966e-11
_P3 = 2.0222662487959506e-21
_S1, _S2, _S3 = -1.66666666666666324348e-01, 8.33333333332248946124e-03, -1.98412698298579493134e-04
_S4, _S5, _S6 = 2.75573137070700676789e-06, -2.50507602534068634195e-08, 1.58969099521155010221e-10
_C1, _C2, _C3 = 4.16666666666666019037e-02, -1.38888888888741095749e-03, 2.48015872894767294178e-05
_C4, _C5, _C6 = -2.75573143513906633035e-07, 2.08757232129817482790e-09, -1.13596475577881948265e-11


SINCOS_MAX = 1.0e6


@inline
def sincos(x):
    """``(sin x, cos x)`` for ``|x| < SINCOS_MAX`` (no test here, so that loops of it vectorise: callers
    send other arguments to libm)."""
    k = np.floor(x * _TWO_OVER_PI + 0.5)
    r = ((x - k * _P1) - k * _P2) - k * _P3
    z = r * r
    s = r + (z * r) * (_S1 + z * (_S2 + z * (_S3 + z * (_S4 + z * (_S5 + z * _S6)))))
    hz = 0.5 * z
    w = 1.0 - hz
    c = w + (((1.0 - w) - hz) + z * (z * (_C1 + z * (_C2 + z * (_C3 + z * (_C4 + z * (_C5 + z * _C6)))))))
    q = k - 4.0 * np.floor(k * 0.25)  # quadrant 0..3
    odd = (q == 1.0) | (q == 3.0)
    a = c if odd else s
    b = s if odd else c
    return (-a if q >= 2.0 else a), (-b if (q == 1.0) | (q == 2.0) else b)


def _wrap(a):
    """:func:`needlecli.numerics.wrap_angle` on one value (the same operations; ``np.floor``: one vector
    instruction in loops over lanes, where ``math.floor`` is a call)."""
    w = a - TWO_PI * np.floor((a + PI) * (0.5 / PI))
    if w >= PI:
        w = w - TWO_PI
    if w < -PI:
        w = -PI
    return w


wrap = jit(_wrap)
wrap_inline = inline(_wrap)  # the same, inlined into the loops over lanes of the kernels


@jit
def wrap_if_needed(a):
    """``wrap(a)`` where ``|a| >= pi`` (wrapping is the identity inside; the numpy path skips it there)."""
    return wrap(a) if not abs(a) < PI else a


# ---------------------------------------------------------------------------------------------- linear algebra
@jit
def cholesky_into(A, L, n):
    """Lower Cholesky factor of the symmetric ``A[:n, :n]`` (its lower triangle read, as LAPACK does) into
    ``L`` (upper triangle zeroed). Returns False where ``A`` is not numerically positive definite."""
    for j in range(n):
        s = A[j, j]
        for k in range(j):
            s -= L[j, k] * L[j, k]
        if not s > 0.0:
            return False
        d = math.sqrt(s)
        L[j, j] = d
        for i in range(j + 1, n):
            t = A[i, j]
            for k in range(j):
                t -= L[i, k] * L[j, k]
            L[i, j] = t / d
        for i in range(j):
            L[i, j] = 0.0
    return True


@jit
def repaired_root(A, L, n, floor):
    """:func:`needlecli.numerics.unscented.robust_cholesky` for one matrix whose Cholesky failed:
    symmetrised, eigenvalues clipped at ``floor`` times the largest magnitude (at least ``floor``),
    rebuilt, factored again, else the eigen root ``V sqrt(w)``; a matrix with non-finite entries
    becomes the identity (as there). Writes the square root into ``L``."""
    S = np.empty((n, n))
    finite = True
    for i in range(n):
        for j in range(n):
            S[i, j] = 0.5 * (A[i, j] + A[j, i])
            if not np.isfinite(S[i, j]):
                finite = False
    R = np.zeros((n, n))
    if finite:
        w, v = np.linalg.eigh(S)
        top = 1.0
        for i in range(n):
            top = max(top, abs(w[i]))
        top *= floor
        for i in range(n):
            wf = max(w[i], top)
            for a in range(n):
                for b in range(n):
                    R[a, b] += v[a, i] * wf * v[b, i]
    ok = finite
    for a in range(n):
        for b in range(n):
            if not np.isfinite(R[a, b]):
                ok = False
    if not ok:
        for a in range(n):
            for b in range(n):
                R[a, b] = 1.0 if a == b else 0.0
    Q = np.empty((n, n))
    for a in range(n):
        for b in range(n):
            Q[a, b] = 0.5 * (R[a, b] + R[b, a])
    if cholesky_into(Q, L, n):
        return
    w2, v2 = np.linalg.eigh(Q)
    for a in range(n):
        for b in range(n):
            L[a, b] = v2[a, b] * math.sqrt(max(w2[b], 0.0))


@jit
def solve_into(A, B, X, n, k):
    """``X[:n, :k] = A[:n, :n]^{-1} B[:n, :k]`` by Gaussian elimination with partial pivoting (LAPACK's
    ``gesv`` algorithm); ``A`` and ``B`` are copied, not changed. A zero pivot gives inf / NaN as numpy's
    solve gives an error: callers check for finite results."""
    M = np.empty((n, n))
    for i in range(n):
        for j in range(n):
            M[i, j] = A[i, j]
    for i in range(n):
        for j in range(k):
            X[i, j] = B[i, j]
    for c in range(n):
        p = c
        big = abs(M[c, c])
        for i in range(c + 1, n):
            if abs(M[i, c]) > big:
                big = abs(M[i, c])
                p = i
        if p != c:
            for j in range(n):
                t = M[c, j]
                M[c, j] = M[p, j]
                M[p, j] = t
            for j in range(k):
                t = X[c, j]
                X[c, j] = X[p, j]
                X[p, j] = t
        piv = M[c, c]
        for i in range(c + 1, n):
            f = M[i, c] / piv
            if f != 0.0:
                for j in range(c + 1, n):
                    M[i, j] -= f * M[c, j]
                for j in range(k):
                    X[i, j] -= f * X[c, j]
    for c in range(n - 1, -1, -1):
        piv = M[c, c]
        for j in range(k):
            s = X[c, j]
            for i in range(c + 1, n):
                s -= M[c, i] * X[i, j]
            X[c, j] = s / piv
