"""The five models' vector fields, RK4 steps and domain checks, compiled, on *lanes*.

A lane is one state: a sigma point of one run (the UKF), or one run (the truth). States are
component-major, ``X (n, L)``, inputs ``U (m, L)`` and parameters ``Pm (p, L)`` likewise, so that the
inner loops run over lanes with straight-line code, which LLVM vectorises (the sin/cos included:
:func:`~needlecli.kernels.core.sincos`). Each function does the numpy path's operations in the same
order (``needlecli/models/*.py``, :func:`needlecli.numerics.rk4_step`): the two agree to the rounding of
sin and cos (1 ulp at the angles the models see).

Model ids (:data:`MODEL_IDS`, by the name a model declares as its ``compiled_equations``) select the
equations; parameters are in the order of the model's
``Params`` schema (``unicycle``: kappa, speed_scale; ``modified_unicycle``: kappa, beta_cut, speed_scale;
the others their one parameter).
"""

from __future__ import annotations

import math

import numpy as np

from needlecli.kernels._jit import inline, jit
from needlecli.kernels.core import SINCOS_MAX, sincos
from needlecli.kernels.dispatch import KernelError

UNICYCLE, MODIFIED_UNICYCLE, SO3, MNM, BINM = 0, 1, 2, 3, 4
#: the equations compiled here, by the name a model declares (:attr:`needlecli.models.Model.compiled_equations`)
MODEL_IDS = {"unicycle": UNICYCLE, "modified_unicycle": MODIFIED_UNICYCLE, "so3": SO3, "mnm": MNM, "binm": BINM}


def equation_id(model) -> int:
    """The id of the compiled equations ``model`` declares (``compiled_equations``).

    Raises
    ------
    KernelError
        A name the kernels do not know (a plug-in's declaration).
    """
    name = model.compiled_equations
    if name not in MODEL_IDS:
        raise KernelError(f"model {model.registered_name!r}: compiled_equations {name!r} is none of the kernels' "
                          f"({', '.join(MODEL_IDS)})")
    return MODEL_IDS[name]


@jit
def sincos_rows(X, r0, r1, SC, nl):
    """``SC[2 j], SC[2 j + 1] = sin, cos of X[r0 + j]`` for the lanes (a loop of its own: two arrays only,
    so LLVM vectorises it)."""
    for c in range(r0, r1):
        j = 2 * (c - r0)
        for i in range(nl):
            s, co = sincos(X[c, i])
            SC[j, i] = s
            SC[j + 1, i] = co
    for c in range(r0, r1):  # arguments the polynomial does not cover (|x| >= 1e6, inf, NaN): libm
        j = 2 * (c - r0)
        for i in range(nl):
            x = X[c, i]
            if not abs(x) < SINCOS_MAX:
                SC[j, i] = math.sin(x)
                SC[j + 1, i] = math.cos(x)


@inline
def _fu(sa, ca, sb, cb, sg, cg, kap, v, w):
    """The unicycle's vector field from the sines and cosines of its angles (the high-gain observer paper, eq. 1); the
    position rates first, then alpha, beta, gamma."""
    kv = kap * v
    kvc = kv * cg / cb
    vcb = v * cb
    return v * sb, -vcb * sa, vcb * ca, kvc, kv * sg, w - kvc * sb


@inline
def _fmu(sa, ca, sb, cb, sg, cg, kap, bc, v, w):
    """The modified unicycle's (the multi-rate UKF paper, eq. 1; ``kappa' = 0``)."""
    kv = kap * v
    inv_cb = 1.0 / cb
    kvc = kv * cg
    g_r = w - (kvc * sb) * inv_cb
    cut = g_r * (0.5 * bc)
    vcb = v * cb
    return v * sb, -(vcb * sa), vcb * ca, (kvc - cut * sg) * inv_cb, cut * cg + kv * sg, g_r


@inline
def _advance(U, Pm, i, modified):
    """The tip's insertion speed: the commanded ``U[0]`` times the ``speed_scale`` parameter (the row after
    kappa, or after beta_cut for the modified unicycle: the order of the models' ``Params``), when given."""
    row = 2 if modified else 1
    return U[0, i] * Pm[row, i] if Pm.shape[0] > row else U[0, i]


@jit
def f_unicycles(X, U, Pm, out, nl, SC, modified):
    sincos_rows(X, 3, 6, SC, nl)
    for i in range(nl):
        v = _advance(U, Pm, i, modified)
        if modified:
            f = _fmu(SC[0, i], SC[1, i], SC[2, i], SC[3, i], SC[4, i], SC[5, i], X[6, i], Pm[1, i], v, U[1, i])
            out[6, i] = 0.0
        else:
            f = _fu(SC[0, i], SC[1, i], SC[2, i], SC[3, i], SC[4, i], SC[5, i], Pm[0, i], v, U[1, i])
        for c in range(6):
            out[c, i] = f[c]


@jit
def f_so3(X, U, Pm, out, nl):
    for i in range(nl):
        kv = Pm[0, i] * U[0, i]
        w0 = kv
        w1 = 0.0
        w2 = U[1, i] + 0.0 * kv
        for r in range(3):
            r0 = X[3 * r, i]
            r1 = X[3 * r + 1, i]
            r2 = X[3 * r + 2, i]
            out[3 * r, i] = r1 * w2 - r2 * w1
            out[3 * r + 1, i] = r2 * w0 - r0 * w2
            out[3 * r + 2, i] = r0 * w1 - r1 * w0


@inline
def magnetic_field(h0, h1, h2, b0, b1, b2, p, v, w0, w1, w2, bicycle):
    """MNM / BiNM vector field (the magnetic needle EM paper, eqs. 1, 4) at one state: ``p = h v``,
    ``h' = g (h x B) x h + h (1 - |h|^2)`` with ``g = c v`` or ``l_inv v / (B . h)``,
    ``B' = w x B + B (1 - |B|^2)``."""
    a0 = h1 * b2 - h2 * b1
    a1 = h2 * b0 - h0 * b2
    a2 = h0 * b1 - h1 * b0
    t0 = a1 * h2 - a2 * h1
    t1 = a2 * h0 - a0 * h2
    t2 = a0 * h1 - a1 * h0
    if bicycle:
        g = (p * v) / (b0 * h0 + b1 * h1 + b2 * h2)
    else:
        g = p * v
    hh = 1.0 - (h0 * h0 + h1 * h1 + h2 * h2)
    bb = 1.0 - (b0 * b0 + b1 * b1 + b2 * b2)
    return (h0 * v, h1 * v, h2 * v, g * t0 + h0 * hh, g * t1 + h1 * hh, g * t2 + h2 * hh,
            (w1 * b2 - w2 * b1) + b0 * bb, (w2 * b0 - w0 * b2) + b1 * bb, (w0 * b1 - w1 * b0) + b2 * bb)


@jit
def f_magnetic(X, U, Pm, out, nl, bicycle):
    for i in range(nl):
        f = magnetic_field(X[3, i], X[4, i], X[5, i], X[6, i], X[7, i], X[8, i], Pm[0, i], U[0, i], U[1, i],
                           U[2, i], U[3, i], bicycle)
        for c in range(9):
            out[c, i] = f[c]


@jit
def field(mid, X, U, Pm, out, nl, SC):
    """``out[:, :nl] = f(X[:, :nl], U, Pm)``; ``SC (>= 6, L)`` scratch."""
    if mid == MODIFIED_UNICYCLE or mid == UNICYCLE:
        f_unicycles(X, U, Pm, out, nl, SC, mid == MODIFIED_UNICYCLE)
    elif mid == SO3:
        f_so3(X, U, Pm, out, nl)
    elif mid == MNM:
        f_magnetic(X, U, Pm, out, nl, False)
    else:
        f_magnetic(X, U, Pm, out, nl, True)


@jit
def normalize(mid, X, nl):
    """The model's projection after a step (SO(3): one Newton step toward the polar factor,
    ``1.5 R - 0.5 (R R^T) R``); the identity for the others."""
    if mid != SO3:
        return
    M = np.empty((3, 3))
    N = np.empty((3, 3))
    for i in range(nl):
        for a in range(3):
            for b in range(3):
                s = 0.0
                for k in range(3):
                    s += X[3 * a + k, i] * X[3 * b + k, i]
                M[a, b] = s
        for a in range(3):
            for b in range(3):
                s = 0.0
                for k in range(3):
                    s += M[a, k] * X[3 * k + b, i]
                N[a, b] = s
        for a in range(3):
            for b in range(3):
                X[3 * a + b, i] = 1.5 * X[3 * a + b, i] - 0.5 * N[a, b]


@jit
def step(mid, X, U, Pm, dt, nl, W):
    """One RK4 step of lanes ``X[:, :nl]`` in place (:func:`needlecli.numerics.rk4_step`'s order), then
    the model's normalisation. ``W (4, max(n, 6), L)`` is scratch."""
    n = X.shape[0]
    K = W[0]
    Z = W[1]
    A = W[2]
    SC = W[3]
    half = 0.5 * dt
    field(mid, X, U, Pm, K, nl, SC)
    for c in range(n):
        for i in range(nl):
            Z[c, i] = K[c, i] * half + X[c, i]
    field(mid, Z, U, Pm, A, nl, SC)  # A = k2
    for c in range(n):
        for i in range(nl):
            k2 = A[c, i]
            Z[c, i] = k2 * half + X[c, i]
            A[c, i] = (K[c, i] + k2) + k2
    field(mid, Z, U, Pm, K, nl, SC)  # K = k3
    for c in range(n):
        for i in range(nl):
            k3 = K[c, i]
            A[c, i] = (A[c, i] + k3) + k3
            Z[c, i] = k3 * dt + X[c, i]
    field(mid, Z, U, Pm, K, nl, SC)  # K = k4
    sixth = dt / 6.0
    for c in range(n):
        for i in range(nl):
            X[c, i] = (A[c, i] + K[c, i]) * sixth + X[c, i]
    normalize(mid, X, nl)


# ---------------------------------------------------------------------------------------------- fused RK4
# The same step as :func:`step`, each lane's four stages in one loop body (registers, no stage arrays, one
# loop per step): 3-4x less overhead at the UKF's lanes. The angles of stages 2 to 4 differ from the
# stage-1 angles by d = h k (milliradians at the models' rates): their sines and cosines come from the
# stage-1 ones by angle addition with short series for sin d and cos d - 1 (a third of the polynomial's
# work, within 2 ulp of libm as it is). Neither libm fallback is inlined: a lane whose stage-1 angle
# leaves the polynomial's range, or whose stage angle moves by more than 1/8 rad, sets the returned flag
# and the caller redoes the step with :func:`step`.
D_MAX = 0.125  # |d| up to which the series below are exact to 2e-17 (relative): terms to d^9 and d^10
_SD3, _SD5, _SD7, _SD9 = -1.0 / 6.0, 1.0 / 120.0, -1.0 / 5040.0, 1.0 / 362880.0
_CD2, _CD4, _CD6, _CD8, _CD10 = -0.5, 1.0 / 24.0, -1.0 / 720.0, 1.0 / 40320.0, -1.0 / 3628800.0


@inline
def _big(a):
    return not abs(a) < SINCOS_MAX


@inline
def _far(d):
    return not abs(d) <= D_MAX


@inline
def shifted(s, c, d):
    """``(sin(x + d), cos(x + d))`` from ``s = sin x``, ``c = cos x``, ``|d| <= D_MAX``: the correction to
    ``s`` and ``c`` is summed first (within 1.5 ulp given ``s``, ``c`` to 1 ulp)."""
    z = d * d
    sd = d + d * (z * (_SD3 + z * (_SD5 + z * (_SD7 + z * _SD9))))
    cm = z * (_CD2 + z * (_CD4 + z * (_CD6 + z * (_CD8 + z * _CD10))))
    return s + (c * sd + s * cm), c + (c * cm - s * sd)


@inline
def _f_sc(sa, ca, sb, cb, sg, cg, kap, bc, v, w, modified):
    if modified:
        return _fmu(sa, ca, sb, cb, sg, cg, kap, bc, v, w)
    return _fu(sa, ca, sb, cb, sg, cg, kap, v, w)


@jit
def rk4_unicycles(X, U, Pm, dt, nl, Y, modified):
    """The fused step of the unicycle (``modified``: the modified unicycle, curvature the state x[6])."""
    half = 0.5 * dt
    sixth = dt / 6.0
    bad = False
    for i in range(nl):
        v = _advance(U, Pm, i, modified)
        w = U[1, i]
        kap = X[6, i] if modified else Pm[0, i]
        bc = Pm[1, i] if modified else 0.0
        x3, x4, x5 = X[3, i], X[4, i], X[5, i]
        bad |= _big(x3) | _big(x4) | _big(x5)
        sa, ca = sincos(x3)
        sb, cb = sincos(x4)
        sg, cg = sincos(x5)
        a0, a1, a2, a3, a4, a5 = _f_sc(sa, ca, sb, cb, sg, cg, kap, bc, v, w, modified)
        d3, d4, d5 = (a3 * half + x3) - x3, (a4 * half + x4) - x4, (a5 * half + x5) - x5
        bad |= _far(d3) | _far(d4) | _far(d5)
        s3, c3 = shifted(sa, ca, d3)
        s4, c4 = shifted(sb, cb, d4)
        s5, c5 = shifted(sg, cg, d5)
        b0, b1, b2, b3, b4, b5 = _f_sc(s3, c3, s4, c4, s5, c5, kap, bc, v, w, modified)
        d3, d4, d5 = (b3 * half + x3) - x3, (b4 * half + x4) - x4, (b5 * half + x5) - x5
        a0, a1, a2, a3, a4, a5 = (a0 + b0) + b0, (a1 + b1) + b1, (a2 + b2) + b2, (a3 + b3) + b3, (a4 + b4) + b4, (a5 + b5) + b5
        bad |= _far(d3) | _far(d4) | _far(d5)
        s3, c3 = shifted(sa, ca, d3)
        s4, c4 = shifted(sb, cb, d4)
        s5, c5 = shifted(sg, cg, d5)
        b0, b1, b2, b3, b4, b5 = _f_sc(s3, c3, s4, c4, s5, c5, kap, bc, v, w, modified)
        d3, d4, d5 = (b3 * dt + x3) - x3, (b4 * dt + x4) - x4, (b5 * dt + x5) - x5
        a0, a1, a2, a3, a4, a5 = (a0 + b0) + b0, (a1 + b1) + b1, (a2 + b2) + b2, (a3 + b3) + b3, (a4 + b4) + b4, (a5 + b5) + b5
        bad |= _far(d3) | _far(d4) | _far(d5)
        s3, c3 = shifted(sa, ca, d3)
        s4, c4 = shifted(sb, cb, d4)
        s5, c5 = shifted(sg, cg, d5)
        b0, b1, b2, b3, b4, b5 = _f_sc(s3, c3, s4, c4, s5, c5, kap, bc, v, w, modified)
        Y[0, i] = (a0 + b0) * sixth + X[0, i]
        Y[1, i] = (a1 + b1) * sixth + X[1, i]
        Y[2, i] = (a2 + b2) * sixth + X[2, i]
        Y[3, i] = (a3 + b3) * sixth + x3
        Y[4, i] = (a4 + b4) * sixth + x4
        Y[5, i] = (a5 + b5) * sixth + x5
        if modified:
            Y[6, i] = 0.0 * sixth + kap  # kappa' = 0
    return bad


@jit
def step_fast(mid, X, U, Pm, dt, nl, W):
    """:func:`step`, fused for the unicycles (the other models: :func:`step` itself); the same numbers."""
    if mid == MODIFIED_UNICYCLE or mid == UNICYCLE:
        Y = W[0]
        bad = rk4_unicycles(X, U, Pm, dt, nl, Y, mid == MODIFIED_UNICYCLE)
        if bad:
            step(mid, X, U, Pm, dt, nl, W)
            return
        n = X.shape[0]
        for c in range(n):
            for i in range(nl):
                X[c, i] = Y[c, i]
        return
    step(mid, X, U, Pm, dt, nl, W)
