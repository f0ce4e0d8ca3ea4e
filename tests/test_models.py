"""Unit tests of the kinematic needle models (``needlecli.models``).

References are derived independently of the code under test (see MODELS.md for the equations):

* unicycle / so3: the tip is a rigid body with constant-in-body twist, linear ``(0, 0, v)``, angular
  ``w = (kappa v, 0, u)``. Its pose is ``g(t) = g0 expm(t xi)`` with the 4x4 twist ``xi``; for ``u = 0`` a
  circle of radius ``1 / kappa`` in the plane of the initial tangent and normal, centred at
  ``p0 - R0 e2 / kappa`` (``R' = R hat(kappa v e1)`` gives ``R = R0 Rx(kappa v t)`` and
  ``p = p0 + R0 (0, (cos th - 1) / kappa, sin th / kappa)``); for ``u != 0`` a helix about the axis
  ``R0 w / |w|`` through ``p0 + R0 (w x v e3) / |w|^2``, radius ``kappa v^2 / |w|^2``, pitch
  ``2 pi v u / |w|^2``.
* mnm / binm: ``(h x B) x h`` is orthogonal to ``h``, so ``s = |h|^2`` obeys ``s' = 2 s (1 - s)`` (logistic,
  closed form), the same for ``B``; for a fixed field the angle ``th`` between ``h`` and ``B`` obeys
  ``th' = -c v sin th`` (MNM) and ``th' = -l v tan th`` (BiNM).
"""

from __future__ import annotations

import zlib

import numpy as np
import pytest
import scipy.linalg
from scipy.integrate import solve_ivp

from needlecli.experiments.config.load import load_config
from needlecli.experiments.simulation.truth import simulate_truth
from needlecli.models import MODELS
from needlecli.numerics import (
    euler_xyz_to_matrix,
    finite_difference_jacobian,
    hat,
    rotation_angle,
)

PI = np.pi


# ------------------------------------------------------------------------------------------ helpers
def make(name: str, **params):
    cls = MODELS.get(name)
    model = cls(cls.Params(**params))
    return model, model.param_arrays()


def run(model, x0, u, p, dt, n_steps):
    """States ``(n_steps + 1, ..., n)``; ``u`` is ``(..., m)`` (held) or a callable ``t -> (..., m)``."""
    x = np.asarray(x0, dtype=float)
    out = [x]
    for k in range(n_steps):
        uk = u(k * dt) if callable(u) else u
        x = model.step(x, uk, p, dt)
        out.append(x)
    return np.stack(out)


def twist_matrix(w, v):
    """4x4 se(3) matrix of the body twist: angular ``w (..., 3)``, linear ``(0, 0, v)``."""
    w = np.asarray(w, dtype=float)
    xi = np.zeros(w.shape[:-1] + (4, 4))
    xi[..., :3, :3] = hat(w)
    xi[..., 2, 3] = v
    return xi


def exact_pose(x0, w, v, t):
    """Exact rigid-body pose ``(R, p)`` at times ``t (T,)`` from unicycle states ``x0 (6,)``."""
    g0 = np.eye(4)
    g0[:3, :3] = euler_xyz_to_matrix(x0[3], x0[4], x0[5])
    g0[:3, 3] = x0[:3]
    xi = twist_matrix(w, v)
    g = np.stack([g0 @ scipy.linalg.expm(tk * xi) for tk in t])
    return g[:, :3, :3], g[:, :3, 3]


# Generic initial poses (non-zero alpha, beta, gamma), far from the singularity of the Euler angles along
# the paths below (|cos(beta0) cos(gamma0)| >= 0.4, so |sin(beta)| <= 0.92 on a circle about body x).
X0_BATCH = np.array(
    [
        [0.0, 0.0, 0.0, 0.3, 0.2, 0.5],
        [1.0, -2.0, 3.0, -0.7, 0.4, -0.9],
        [-5.0, 4.0, 0.5, 1.2, -0.5, 0.2],
        [2.0, 2.0, -1.0, -2.5, 0.1, 1.0],
    ]
)


# ------------------------------------------------------------------------------------- 1. circle
def test_unicycle_circle_batch():
    model, _ = make("unicycle")
    kappa = np.array([0.01, 0.02, 0.05, 0.03])
    v = np.array([4.0, 2.0, 2.0, 1.5])
    p = {"kappa": kappa}  # per-run parameter, broadcast over the batch
    u = np.stack([v, np.zeros(4)], -1)
    dt, n_steps = 0.05, 500
    xs = run(model, X0_BATCH, u, p, dt, n_steps)  # (T, 4, 6)
    assert xs.shape == (n_steps + 1, 4, 6)
    assert np.isfinite(xs).all()

    r0 = euler_xyz_to_matrix(X0_BATCH[:, 3], X0_BATCH[:, 4], X0_BATCH[:, 5])  # (4, 3, 3)
    p0 = X0_BATCH[:, :3]
    centre = p0 - r0[:, :, 1] / kappa[:, None]  # 1/kappa along -R0 e2
    pos = model.tip_position(xs)
    dist = np.linalg.norm(pos - centre, axis=-1)
    np.testing.assert_allclose(dist, np.broadcast_to(1.0 / kappa, dist.shape), rtol=1e-9)
    # planar: no motion along the initial binormal R0 e1, and the tangent stays in the plane
    normal = r0[:, :, 0]
    np.testing.assert_allclose(np.sum((pos - p0) * normal, -1), 0.0, atol=1e-9)
    np.testing.assert_allclose(np.sum(model.tangent(xs) * normal, -1), 0.0, atol=1e-11)
    # and the closed-form position along the arc
    t = dt * np.arange(n_steps + 1)[:, None]
    th = kappa * v * t
    local = np.stack([np.zeros_like(th), (np.cos(th) - 1) / kappa, np.sin(th) / kappa], -1)  # (T, 4, 3)
    expected = p0 + np.einsum("nij,tnj->tni", r0, local)
    np.testing.assert_allclose(pos, expected, atol=1e-8)
    # the arc is long enough to mean something (at least 1 rad for every run)
    assert np.all(th[-1] >= 1.0)


# -------------------------------------------------------------------------------------- 2. helix
def test_unicycle_helix_radius_pitch_and_exact_solution():
    model, _ = make("unicycle")
    kappa, v = 0.05, 2.0
    kv = kappa * v
    periods = np.array([10.0, 20.0, 16.0])  # s; choose |w| so that a period is a whole number of steps
    wn = 2 * PI / periods
    u_rate = np.sqrt(wn**2 - kv**2) * np.array([1.0, -1.0, 1.0])  # both handednesses
    x0 = X0_BATCH[:3]
    dt = 0.02
    n_steps = int(round(periods.max() / dt))
    u = np.stack([np.full(3, v), u_rate], -1)
    xs = run(model, x0, u, {"kappa": np.full(3, kappa)}, dt, n_steps)
    pos = model.tip_position(xs)

    for i in range(3):
        w = np.array([kv, 0.0, u_rate[i]])
        radius = kv * v / wn[i] ** 2
        pitch = 2 * PI * v * u_rate[i] / wn[i] ** 2
        r0 = euler_xyz_to_matrix(*x0[i, 3:6])
        axis = r0 @ w / wn[i]
        q = x0[i, :3] + r0 @ np.cross(w, [0.0, 0.0, v]) / wn[i] ** 2  # a point on the axis
        d = pos[:, i] - q
        d_perp = d - np.outer(d @ axis, axis)
        np.testing.assert_allclose(np.linalg.norm(d_perp, axis=-1), radius, rtol=1e-8)
        k_per = int(round(periods[i] / dt))
        adv = pos[k_per, i] - pos[0, i]
        np.testing.assert_allclose(adv, pitch * axis, atol=1e-8)

        # the same numbers estimated from the simulated positions alone: the advance over one period
        # gives axis and pitch; the mean over one period (uniform in phase) is on the axis
        est_pitch = np.linalg.norm(adv)
        est_axis = adv / est_pitch
        seg = pos[:k_per, i]
        c = seg.mean(0)
        dd = seg - c
        dd -= np.outer(dd @ est_axis, est_axis)
        rad = np.linalg.norm(dd, axis=-1)
        assert est_pitch == pytest.approx(abs(pitch), rel=1e-8)
        assert np.ptp(rad) < 1e-6 * radius  # constant distance from the fitted axis
        assert rad.mean() == pytest.approx(radius, rel=1e-6)

        # exact rigid-body solution g0 expm(t xi), every 25 steps
        idx = np.arange(0, n_steps + 1, 25)
        r_ex, p_ex = exact_pose(x0[i], w, v, idx * dt)
        np.testing.assert_allclose(pos[idx, i], p_ex, atol=1e-8)
        r_sim = model.tip_rotation(xs[idx, i])
        err = rotation_angle(np.swapaxes(r_sim, -1, -2) @ r_ex)
        assert err.max() < 1e-9


# --------------------------------------------------------------------------- 3. unicycle == so3
def _flip_input(t):
    """Insertion at 2 mm/s; shaft rotation: a slow drift, one 180 deg flip at pi rad/s from t = 2 s,
    then a slow rotation the other way."""
    if t < 2.0:
        w = 0.1
    elif t < 3.0:
        w = PI
    else:
        w = -0.3
    return np.array([2.0, w])


def test_unicycle_and_so3_give_the_same_tip_frame():
    uni, _ = make("unicycle")
    so3, _ = make("so3")
    kappa = np.array([0.02, 0.05, 0.01])
    p = {"kappa": kappa}
    x0 = X0_BATCH[:3]
    r0 = euler_xyz_to_matrix(x0[:, 3], x0[:, 4], x0[:, 5]).reshape(3, 9)
    dt, n_steps = 0.005, 1600  # 8 s
    xu = run(uni, x0, _flip_input, p, dt, n_steps)
    xr = run(so3, r0, _flip_input, p, dt, n_steps)
    r_uni = uni.tip_rotation(xu)
    r_so3 = so3.tip_rotation(xr)
    assert r_so3.shape == (n_steps + 1, 3, 3, 3)
    np.testing.assert_allclose(r_uni, r_so3, atol=1e-8)
    np.testing.assert_allclose(uni.tangent(xu), so3.tangent(xr), atol=1e-8)
    # the so3 state stays a rotation (one Newton step after every RK4 step)
    rrt = r_so3 @ np.swapaxes(r_so3, -1, -2)
    np.testing.assert_allclose(rrt, np.broadcast_to(np.eye(3), rrt.shape), atol=1e-12)
    # and the tip really turned (the comparison is not vacuous)
    assert rotation_angle(r_so3[0].swapaxes(-1, -2) @ r_so3[-1]).min() > 0.3


def test_unicycle_tangent_is_third_column_of_tip_rotation():
    uni, _ = make("unicycle")
    rng = np.random.default_rng(0)
    x = np.concatenate([rng.standard_normal((20, 3)), rng.uniform(-1.4, 1.4, (20, 3))], -1)
    np.testing.assert_allclose(uni.tangent(x), uni.tip_rotation(x)[..., :, 2], atol=1e-15)


# ---------------------------------------------------------------------------------- 4. MNM norms
def _unit(a):
    return a / np.linalg.norm(a, axis=-1, keepdims=True)


def test_mnm_keeps_unit_norms():
    model, p = make("mnm", c=20.0)
    rng = np.random.default_rng(1)
    n = 4
    h = _unit(rng.standard_normal((n, 3)))
    b = _unit(rng.standard_normal((n, 3)))
    x0 = np.concatenate([np.zeros((n, 3)), h, b], -1)
    u = np.concatenate([np.full((n, 1), 0.002), rng.uniform(-0.6, 0.6, (n, 3))], -1)
    xs = run(model, x0, u, p, 0.01, 2000)
    assert np.isfinite(xs).all()
    np.testing.assert_allclose(np.linalg.norm(xs[..., 3:6], axis=-1), 1.0, atol=1e-9)
    np.testing.assert_allclose(np.linalg.norm(xs[..., 6:9], axis=-1), 1.0, atol=1e-9)
    # the run is not trivial: the field and the tip turned
    assert np.all(np.linalg.norm(xs[-1, :, 6:9] - b, axis=-1) > 0.1)
    assert np.all(np.linalg.norm(xs[-1, :, 3:6] - h, axis=-1) > 0.01)


def test_mnm_norms_are_attracted_to_one_logistically():
    model, p = make("mnm", c=20.0)
    rng = np.random.default_rng(2)
    s0_h = np.array([0.25, 2.25, 0.81, 1.44])  # |h|^2 at t = 0
    s0_b = np.array([1.69, 0.49, 1.21, 0.64])
    h = _unit(rng.standard_normal((4, 3))) * np.sqrt(s0_h)[:, None]
    b = _unit(rng.standard_normal((4, 3))) * np.sqrt(s0_b)[:, None]
    x0 = np.concatenate([np.zeros((4, 3)), h, b], -1)
    u = np.concatenate([np.full((4, 1), 0.002), rng.uniform(-0.6, 0.6, (4, 3))], -1)
    dt, n_steps = 0.01, 500
    xs = run(model, x0, u, p, dt, n_steps)
    t = dt * np.arange(n_steps + 1)[:, None]

    def logistic(s0):
        return 1.0 / (1.0 + (1.0 / s0 - 1.0) * np.exp(-2.0 * t))

    sh = np.sum(xs[..., 3:6] ** 2, -1)
    sb = np.sum(xs[..., 6:9] ** 2, -1)
    np.testing.assert_allclose(sh, logistic(s0_h), rtol=1e-8)
    np.testing.assert_allclose(sb, logistic(s0_b), rtol=1e-8)
    # monotone approach toward 1
    assert np.all(np.diff(np.abs(sh - 1.0), axis=0) <= 1e-15)
    assert np.all(np.abs(sh[-1] - 1.0) < 1e-3)


@pytest.mark.parametrize("name", ["mnm", "binm"])
def test_magnetic_tip_turns_toward_a_fixed_field(name):
    """With omega_B = 0: th' = -c v sin th (MNM), th' = -l v tan th (BiNM), closed forms
    tan(th/2) = tan(th0/2) exp(-c v t) and sin(th) = sin(th0) exp(-l v t)."""
    gain = 20.0
    model, p = make(name, **({"c": gain} if name == "mnm" else {"l_inv": gain}))
    th0 = np.array([0.3, 1.0, 1.4])
    h = np.stack([np.zeros(3), np.cos(th0), np.sin(th0)], -1)  # B = e2, h at angle th0 in the y-z plane
    b = np.broadcast_to([0.0, 1.0, 0.0], (3, 3))
    x0 = np.concatenate([np.zeros((3, 3)), h, b], -1)
    v = 0.002
    u = np.broadcast_to([v, 0.0, 0.0, 0.0], (3, 4))
    dt, n_steps = 0.05, 400
    xs = run(model, x0, u, p, dt, n_steps)
    t = dt * np.arange(n_steps + 1)[:, None]
    th = np.arccos(np.clip(np.sum(xs[..., 3:6] * xs[..., 6:9], -1), -1, 1))
    if name == "mnm":
        expected = 2 * np.arctan(np.tan(th0 / 2) * np.exp(-gain * v * t))
    else:
        expected = np.arcsin(np.sin(th0) * np.exp(-gain * v * t))
    np.testing.assert_allclose(th, expected, atol=1e-9)
    # the position integrates h v (trapezoid rule over the stored steps, error O(dt^2))
    disp = v * dt * (0.5 * (xs[0, :, 3:6] + xs[-1, :, 3:6]) + xs[1:-1, :, 3:6].sum(0))
    np.testing.assert_allclose(xs[-1, :, :3], disp, rtol=1e-4, atol=1e-9)


# ------------------------------------------------------------------------------ 5. singularities
BINM_YAML = """
model:
  type: binm
  params: {{l_inv: {l_inv}}}
inputs:
  v: 0.002
  omega_B: [0.0, 0.0, {omega}]
stop: {{time: {stop}}}
simulation: {{dt: {dt}}}
runs: {{count: 2, seed: 3}}
"""


def _binm_event_reference(l_inv, v, omega, margin):
    """Time at which |cos th| = margin for th' = omega - l v tan th, th(0) = 0 (h chases the field
    rotating about z in the plane of h and B; the initial state has h = B = e_y)."""

    def rhs(t, y):
        return [omega - l_inv * v * np.tan(y[0])]

    def hit(t, y):
        return np.cos(y[0]) - margin

    hit.terminal = True
    sol = solve_ivp(rhs, (0.0, 100.0), [0.0], events=hit, rtol=1e-11, atol=1e-12, method="LSODA")
    return float(sol.t_events[0][0])


@pytest.mark.parametrize("dt", [0.001, 0.01])
def test_binm_driven_into_singularity_is_reported(dt):
    """The field turns away at 0.5 rad/s while the tip follows at l v tan th: with l v = 2e-4 1/s the
    equilibrium angle has cos = 4e-4, inside the singular band. With dt = 0.01 the field turns 5 mrad
    per step and the state jumps over the band: a crossing must be reported too."""
    l_inv, omega = 0.1, 0.5
    cfg, _ = load_config(text=BINM_YAML.format(l_inv=l_inv, omega=omega, stop=4.0, dt=dt))
    truth = simulate_truth(cfg)
    model = truth.model
    assert list(truth.status) == ["singular", "singular"]
    assert all("B . h" in r for r in truth.reason)
    assert np.isfinite(truth.event_time).all()
    assert np.isfinite(truth.states).all()
    t_ref = _binm_event_reference(l_inv, 0.002, omega, model.singular_threshold)
    assert 2.0 < t_ref < 3.5
    np.testing.assert_allclose(truth.event_time, t_ref, atol=3 * dt)
    # states up to the event are in the domain, then held
    k_ev = int(round(truth.event_time[0] / dt))
    assert not model.singular(truth.states[:, :k_ev], model.param_arrays()).any()
    held = truth.states[:, k_ev:]
    np.testing.assert_array_equal(held, np.broadcast_to(truth.states[:, k_ev - 1 : k_ev], held.shape))
    # B . h kept its sign up to the event (no silent crossing)
    bh = np.sum(truth.states[..., 3:6] * truth.states[..., 6:9], -1)
    assert np.all(bh > 0)


def test_binm_following_field_is_not_singular():
    """Control: with l v = 0.04 1/s the tip keeps up; the angle settles at atan(omega / (l v))."""
    l_inv, omega = 20.0, 0.5
    cfg, _ = load_config(text=BINM_YAML.format(l_inv=l_inv, omega=omega, stop=10.0, dt=0.01))
    truth = simulate_truth(cfg)
    assert list(truth.status) == ["ok", "ok"]
    assert np.isnan(truth.event_time).all()
    x = truth.states[0, -1]
    cos_th = x[3:6] @ x[6:9]
    assert cos_th == pytest.approx(np.cos(np.arctan(omega / (l_inv * 0.002))), rel=1e-4)


UNICYCLE_YAML = """
model:
  type: unicycle
  params: {{kappa: {kappa}}}
  initial_state: {{alpha: 0.0, beta: 0.0, gamma: {gamma}}}
inputs:
  v: {v}
  u: 0.0
stop: {{time: 20.0}}
simulation: {{dt: 0.01}}
"""


def test_unicycle_driven_to_beta_pi_over_2_is_reported():
    """gamma = pi/2, u = 0: gamma' = 0, alpha' = 0 and beta' = kappa v, so beta = kappa v t reaches pi/2
    at t = pi / (2 kappa v) = 15.7 s."""
    kappa, v = 0.05, 2.0
    cfg, _ = load_config(text=UNICYCLE_YAML.format(kappa=kappa, gamma=PI / 2, v=v))
    truth = simulate_truth(cfg)
    assert list(truth.status) == ["singular"]
    assert "cos(beta)" in truth.reason[0]
    assert np.isfinite(truth.states).all()
    t_ref = PI / 2 / (kappa * v)
    assert truth.event_time[0] == pytest.approx(t_ref, abs=0.011)
    beta = truth.states[0, :, 4]
    assert np.all(np.abs(beta) < PI / 2)
    k = truth.time < t_ref - 0.01
    np.testing.assert_allclose(beta[k], kappa * v * truth.time[k], atol=1e-9)


def test_unicycle_away_from_singularity_is_ok():
    cfg, _ = load_config(text=UNICYCLE_YAML.format(kappa=0.05, gamma=1.0, v=2.0))
    truth = simulate_truth(cfg)
    assert list(truth.status) == ["ok"]
    assert np.isnan(truth.event_time).all()


def test_singular_predicates():
    uni, p = make("unicycle")
    x = np.zeros((4, 6))
    x[:, 4] = [0.0, 1.5, PI / 2, -PI / 2]
    np.testing.assert_array_equal(uni.singular(x, p), [False, False, True, True])
    binm, pb = make("binm")
    h = np.array([[0, 1, 0], [0, 1, 0], [0, 1, 0]], dtype=float)
    b = np.array([[0, 1, 0], [1, 0, 0], [-1, 1e-4, 0]], dtype=float)
    xb = np.concatenate([np.zeros((3, 3)), h, b], -1)
    np.testing.assert_array_equal(binm.singular(xb, pb), [False, True, True])
    mnm, pm = make("mnm")
    assert not mnm.singular(xb, pm).any()  # MNM has no singularity
    # a step that jumps over B . h = 0 without landing in the band is a crossing
    xa = xb[[0, 0, 0]]
    xn = xb[[0, 0, 0]].copy()
    xn[1, 6:9] = [1.0, -0.1, 0.0]  # B . h < 0 after the step
    xn[2, 6:9] = [1.0, 0.1, 0.0]  # still positive
    np.testing.assert_array_equal(binm.crossed_singularity(xa, xn, pb), [False, True, False])
    assert not mnm.crossed_singularity(xa, xn, pm).any()


# -------------------------------------------------------------------------------- 6. RK4 order
def _order(errors):
    errors = np.asarray(errors)
    return np.log2(errors[:-1] / errors[1:])


def test_rk4_order_unicycle_against_exact_helix():
    model, p = make("unicycle", kappa=0.05)
    v, u_rate, t_end = 2.0, 0.3, 10.0
    x0 = X0_BATCH[:2]
    w = np.array([0.05 * v, 0.0, u_rate])
    exact = [exact_pose(x0[i], w, v, [t_end]) for i in range(2)]
    errors = []
    for dt in (0.5, 0.25, 0.125):
        x = run(model, x0, np.array([v, u_rate]), p, dt, int(round(t_end / dt)))[-1]
        e = 0.0
        for i in range(2):
            r_ex, p_ex = exact[i]
            e += np.linalg.norm(x[i, :3] - p_ex[0])
            e += rotation_angle(model.tip_rotation(x[i]).T @ r_ex[0])
        errors.append(e)
    order = _order(errors)
    assert np.all((order > 3.6) & (order < 4.4)), (errors, order)


def test_rk4_order_mnm_against_fine_reference():
    model, p = make("mnm", c=20.0)
    h0 = _unit(np.array([0.3, 1.0, 0.2])) * 1.2  # off the unit sphere: the attraction term is exercised
    x0 = np.concatenate([[0.0, 0.0, 0.0], h0, [0.8, 0.6, 0.0]])
    u = np.array([0.002, 0.2, -0.1, 0.4])
    t_end = 10.0
    ref = solve_ivp(lambda t, x: model.f(x, u, p), (0.0, t_end), x0, method="DOP853", rtol=1e-13, atol=1e-15).y[:, -1]
    errors = []
    for dt in (0.25, 0.125, 0.0625):
        x = run(model, x0, u, p, dt, int(round(t_end / dt)))[-1]
        errors.append(np.abs(x - ref).max())
    order = _order(errors)
    assert np.all((order > 3.6) & (order < 4.4)), (errors, order)


# ------------------------------------------------------------------------------ 7. Jacobians
def _sample_states(name, model, rng, n):
    """Random states inside each model's domain."""
    if name in ("unicycle", "modified_unicycle"):
        x = np.concatenate([rng.normal(0, 10, (n, 3)), rng.uniform(-1.3, 1.3, (n, 3))], -1)
        if name == "modified_unicycle":
            x = np.concatenate([x, rng.uniform(0.005, 0.05, (n, 1))], -1)
        return x
    if name == "so3":
        q, r = np.linalg.qr(rng.standard_normal((n, 3, 3)))
        q[np.linalg.det(q) < 0, :, 0] *= -1
        return q.reshape(n, 9)
    if name in ("mnm", "binm"):
        h = _unit(rng.standard_normal((n, 3))) * rng.uniform(0.8, 1.2, (n, 1))
        b = _unit(h + 0.8 * _unit(rng.standard_normal((n, 3))))  # B . h well away from 0
        return np.concatenate([rng.normal(0, 0.05, (n, 3)), h, b], -1)
    x0 = np.asarray(model.initial_state(model.param_arrays()), dtype=float)  # models added later
    return model.normalize(x0 + 0.1 * rng.standard_normal((n, model.n)))


def _sample_inputs(name, model, rng, n):
    u = rng.standard_normal((n, model.m))
    if name in ("mnm", "binm"):
        u[:, 0] = rng.uniform(0.001, 0.003, n)
    else:
        u[:, 0] = rng.uniform(0.5, 3.0, n)
    return u


def _per_run(p, rng, n):
    return {k: v * rng.uniform(0.5, 1.5, n) if np.ndim(v) == 0 else v for k, v in p.items()}


@pytest.mark.parametrize("name", MODELS.names())
@pytest.mark.parametrize("per_run_params", [False, True])
def test_jacobians_agree_with_finite_differences(name, per_run_params):
    rng = np.random.default_rng([10, zlib.crc32(name.encode()), per_run_params])
    params = {"beta_cut": 0.06} if name == "modified_unicycle" else {}
    model, p = make(name, **params)
    n = 6
    x = _sample_states(name, model, rng, n)
    u = _sample_inputs(name, model, rng, n)
    if per_run_params:
        p = _per_run(p, rng, n)
    pe = {k: (v[:, None] if np.ndim(v) else v) for k, v in p.items()}
    jx = model.jacobian(x, u, p)
    ju = model.input_jacobian(x, u, p)
    assert jx.shape == (n, model.n, model.n)
    assert ju.shape == (n, model.n, model.m)
    fd_x = finite_difference_jacobian(lambda xx: model.f(xx, u[:, None, :], pe), x)
    fd_u = finite_difference_jacobian(lambda uu: model.f(x[:, None, :], uu, pe), u)
    scale_x = 1.0 + np.abs(fd_x).max()
    scale_u = 1.0 + np.abs(fd_u).max()
    np.testing.assert_allclose(jx, fd_x, atol=1e-7 * scale_x, rtol=1e-6)
    np.testing.assert_allclose(ju, fd_u, atol=1e-7 * scale_u, rtol=1e-6)
    # the batch is handled row by row: the Jacobian of one run alone is the same
    p0 = {k: (v[0] if np.ndim(v) else v) for k, v in p.items()}
    np.testing.assert_allclose(model.jacobian(x[0], u[0], p0), jx[0], rtol=1e-12, atol=1e-15)


def test_unicycle_jacobian_spot_checks():
    model, _ = make("unicycle")
    kappa = 0.03
    p = {"kappa": np.asarray(kappa)}
    a, b, g = 0.4, -0.3, 0.9
    v, w = 1.7, 0.2
    x = np.array([1.0, 2.0, 3.0, a, b, g])
    u = np.array([v, w])
    j = model.jacobian(x, u, p)
    ju = model.input_jacobian(x, u, p)
    # differentiated by hand from MODELS.md, eq. 1 of the high-gain observer paper
    assert j[0, 4] == pytest.approx(v * np.cos(b))  # d x' / d beta
    assert j[1, 3] == pytest.approx(-v * np.cos(b) * np.cos(a))  # d y' / d alpha
    assert j[2, 4] == pytest.approx(-v * np.cos(a) * np.sin(b))  # d z' / d beta
    assert j[3, 5] == pytest.approx(-kappa * v * np.sin(g) / np.cos(b))  # d alpha' / d gamma
    assert j[3, 4] == pytest.approx(kappa * v * np.cos(g) * np.sin(b) / np.cos(b) ** 2)  # d alpha' / d beta
    assert j[4, 5] == pytest.approx(kappa * v * np.cos(g))  # d beta' / d gamma
    assert j[5, 4] == pytest.approx(-kappa * v * np.cos(g) / np.cos(b) ** 2)  # d gamma' / d beta
    np.testing.assert_allclose(j[:, :3], 0.0, atol=0)  # nothing depends on the position
    np.testing.assert_allclose(
        ju[:, 0],
        [
            np.sin(b),
            -np.cos(b) * np.sin(a),
            np.cos(a) * np.cos(b),
            kappa * np.cos(g) / np.cos(b),
            kappa * np.sin(g),
            -kappa * np.cos(g) * np.tan(b),
        ],
        rtol=1e-12,
    )
    np.testing.assert_allclose(ju[:, 1], [0, 0, 0, 0, 0, 1], atol=0)


def test_so3_jacobian_closed_form():
    model, _ = make("so3")
    kappa = 0.04
    p = {"kappa": np.asarray(kappa)}
    rng = np.random.default_rng(11)
    x = _sample_states("so3", model, rng, 3)
    u = np.array([[2.0, 0.5], [1.0, -0.3], [0.5, 2.0]])
    j = model.jacobian(x, u, p)
    ju = model.input_jacobian(x, u, p)
    for k in range(3):
        w = np.array([kappa * u[k, 0], 0.0, u[k, 1]])
        # f(R) = R hat(w) is linear: vec_row(R W) = (I kron W^T) vec_row(R)
        np.testing.assert_allclose(j[k], np.kron(np.eye(3), hat(w).T), atol=1e-15)
        r = x[k].reshape(3, 3)
        np.testing.assert_allclose(ju[k, :, 0], (r @ hat([kappa, 0.0, 0.0])).reshape(9), atol=1e-15)
        np.testing.assert_allclose(ju[k, :, 1], (r @ hat([0.0, 0.0, 1.0])).reshape(9), atol=1e-15)


def test_mnm_jacobian_spot_checks():
    model, p = make("mnm", c=20.0)
    rng = np.random.default_rng(12)
    x = _sample_states("mnm", model, rng, 3)
    u = _sample_inputs("mnm", model, rng, 3)
    j = model.jacobian(x, u, p)
    ju = model.input_jacobian(x, u, p)
    for k in range(3):
        h, b = x[k, 3:6], x[k, 6:9]
        np.testing.assert_allclose(j[k, 0:3, 3:6], u[k, 0] * np.eye(3), atol=1e-15)  # p' = h v
        np.testing.assert_allclose(j[k, 0:3, 0:3], 0.0, atol=0)
        np.testing.assert_allclose(j[k, 6:9, 3:6], 0.0, atol=0)  # B does not see h
        # B' = omega x B + B (1 - |B|^2): d/dB = hat(omega) + (1 - |B|^2) I - 2 B B^T
        np.testing.assert_allclose(
            j[k, 6:9, 6:9], hat(u[k, 1:4]) + (1 - b @ b) * np.eye(3) - 2 * np.outer(b, b), atol=1e-14
        )
        np.testing.assert_allclose(ju[k, 0:3, 0], h, atol=1e-15)  # d p' / d v
        np.testing.assert_allclose(ju[k, 6:9, 1:4], -hat(b), atol=1e-15)  # d (omega x B) / d omega
        # d h' / d v = c (h x B) x h
        np.testing.assert_allclose(ju[k, 3:6, 0], 20.0 * np.cross(np.cross(h, b), h), atol=1e-13)


# ---------------------------------------------------------------------- 8. modified unicycle
def test_modified_unicycle_turn_tilts_tangent_by_beta_cut():
    """kappa = 0: the body rate is g_r (0, beta_cut/2, 1) to first order in beta_cut, a rotation about an
    axis at phi = atan(beta_cut/2) from the tangent; half a turn of the shaft swings the tangent across
    the cone, by 2 phi ~ beta_cut."""
    beta_cut = np.deg2rad(np.array([2.0, 4.0, 6.0]))
    model, _ = make("modified_unicycle", kappa=0.0)
    p = {"beta_cut": beta_cut}
    x0 = np.zeros((3, 7))
    x0[:, 3:6] = [[0.0, 0.0, 0.0], [0.2, -0.1, 0.7], [-0.3, 0.15, -1.2]]
    rate = 20.0  # rad/s: a fast 180 deg turn
    dt = PI / rate / 200
    u = np.broadcast_to([1.0, rate], (3, 2))
    xs = run(model, x0, u, p, dt, 200)
    np.testing.assert_allclose(xs[-1, :, 5] - x0[:, 5], PI, atol=1e-9)  # gamma turned by pi
    t0, t1 = model.tangent(xs[0]), model.tangent(xs[-1])
    tilt = np.arccos(np.clip(np.sum(t0 * t1, -1), -1, 1))
    np.testing.assert_allclose(tilt, beta_cut, rtol=0.03)
    # kappa stays put, and with kappa = 0 the path is straight during the turn apart from the tilt
    np.testing.assert_allclose(xs[:, :, 6], 0.0, atol=0)


def test_modified_unicycle_with_zero_cut_is_the_unicycle():
    mod, _ = make("modified_unicycle", kappa=0.02, beta_cut=0.0)
    uni, _ = make("unicycle")
    kappa = np.array([0.02, 0.04, 0.01])
    x0 = X0_BATCH[:3]
    x0m = np.concatenate([x0, kappa[:, None]], -1)
    dt, n_steps = 0.01, 600
    xm = run(mod, x0m, _flip_input, {"beta_cut": np.zeros(3)}, dt, n_steps)
    xu = run(uni, x0, _flip_input, {"kappa": kappa}, dt, n_steps)
    np.testing.assert_allclose(xm[..., :6], xu, rtol=1e-12, atol=1e-12)
    np.testing.assert_array_equal(xm[..., 6], np.broadcast_to(kappa, (n_steps + 1, 3)))


def test_modified_unicycle_curvature_state_and_sync():
    mod, p = make("modified_unicycle", kappa=0.03, beta_cut=0.05)
    x0 = mod.initial_state(p)
    assert x0.shape == (7,) and x0[6] == pytest.approx(0.03)
    x = np.zeros((2, 7))
    synced = mod.sync_params(x, {"kappa": np.array([0.01, 0.02]), "beta_cut": 0.05})
    np.testing.assert_allclose(synced[:, 6], [0.01, 0.02])
    np.testing.assert_array_equal(x, 0.0)  # the input is not modified in place


@pytest.mark.parametrize("name", [m for m in MODELS.names() if MODELS.get(m).translation_states])
def test_vector_field_does_not_depend_on_translation_states(name):
    """What a model declares in ``translation_states`` (filters skip sigma points on it) must hold: moving
    those states leaves f unchanged, exactly."""
    rng = np.random.default_rng([11, zlib.crc32(name.encode())])
    model, p = make(name)
    x = _sample_states(name, model, rng, 8)
    u = _sample_inputs(name, model, rng, 8)
    idx = [model.index(k) for k in model.translation_states]
    moved = x.copy()
    moved[:, idx] += rng.uniform(-100.0, 100.0, (8, len(idx))) * (1e-3 if model.length_unit == "m" else 1.0)
    np.testing.assert_array_equal(model.f(moved, u, p), model.f(x, u, p))
    d = model.step(moved, u, p, 0.01) - moved
    np.testing.assert_allclose(d, model.step(x, u, p, 0.01) - x, rtol=0, atol=1e-12)


@pytest.mark.parametrize("name", MODELS.names())
def test_declared_state_selections_are_what_the_model_measures(name):
    rng = np.random.default_rng([12, zlib.crc32(name.encode())])
    model, _ = make(name)
    x = _sample_states(name, model, rng, 5)
    for quantity in model.selections:
        sel = model.state_selection(quantity)
        np.testing.assert_array_equal(np.reshape(getattr(model, quantity)(x), (5, -1)), x[:, sel])
