"""The EKF, the extended Kalman (RTS) smoother and the iterated EKS against a Kalman filter and an RTS
smoother written here independently, on a linear-Gaussian model with two measurement channels at their
own rates (some samples missing); the exact RK4 Jacobians; the analytic Jacobians of the magnetic
models; the ``ekf``/``eks`` observers end to end."""

from __future__ import annotations

import numpy as np
import pytest

from needlecli.fitting.smoother import affine_pass, ekf, eks, ieks, linearise
from needlecli.fitting.statespace import DiscreteModel, MeasurementModel, make_ticks, tangent_basis
from needlecli.models import MODELS
from needlecli.models.base import Model
from needlecli.numerics import complex_step_jacobian
from needlecli.numerics.kalman import kalman_forward, repair_pd, rk4_with_jacobian


class Linear(Model):
    """x' = F x + g u: a damped oscillator and a slow decay, driven by the input."""

    state_names = ("a", "b", "c")
    state_units = ("1", "1", "1")
    input_names = ("v",)
    input_sizes = {"v": 1}
    input_units = {"v": "1"}
    F = np.array([[-0.3, 1.0, 0.0], [-1.0, -0.2, 0.5], [0.0, 0.0, -0.1]])
    g = np.array([1.0, 0.0, 0.5])

    def f(self, x, u, p):
        return x @ self.F.T + u[..., :1] * self.g

    def initial_state(self, p):
        return np.zeros(3)


N, T, DT = 4, 121, 0.05
Qc = np.array([[0.10, 0.02, 0.0], [0.02, 0.20, 0.0], [0.0, 0.0, 0.05]])
R1 = np.array([[0.3]])
R2 = np.array([[0.2, 0.05], [0.05, 0.4]])
P0 = np.diag([0.5, 0.5, 0.8])


def _problem(substeps=None, ticks_every=1):
    rng = np.random.default_rng(42)
    u = rng.standard_normal((N, T, 1))
    idx1 = np.arange(0, T, 3)
    idx2 = np.arange(1, T, 2)
    ticks = make_ticks(T, [idx1, idx2], "measurements" if ticks_every > 1 else "grid", DT)
    dm = DiscreteModel(Linear(), {}, (), DT, ticks, u, substeps)
    y1 = rng.standard_normal((N, len(idx1), 1))
    y2 = rng.standard_normal((N, len(idx2), 2))
    v2 = rng.random((N, len(idx2))) > 0.15  # missing samples, different per run
    m1 = MeasurementModel("c1", lambda x: x[..., :1], 3, np.searchsorted(ticks, idx1), y1,
                          np.ones((N, len(idx1)), dtype=bool), np.zeros(1, dtype=bool))
    m2 = MeasurementModel("c2", lambda x: x[..., 1:] * np.array([1.0, 2.0]), 3, np.searchsorted(ticks, idx2), y2,
                          v2, np.zeros(2, dtype=bool))
    m0 = rng.standard_normal((N, 3))
    return dm, [m1, m2], m0, u, (idx1, y1), (idx2, y2, v2), ticks


def _rk4_matrix(A, h):
    X = A * h
    return np.eye(3) + X + X @ X / 2 + X @ X @ X / 6 + X @ X @ X @ X / 24


def _reference_kf(m0, u, meas1, meas2, ticks):
    """A textbook Kalman filter, one run at a time, on the same discrete model (RK4 per grid step)."""
    idx1, y1 = meas1
    idx2, y2, v2 = meas2
    Phi = _rk4_matrix(Linear.F, DT)
    # the input enters RK4 affinely: x_next = Phi x + Gamma u with Gamma from RK4 on x' = F x + g u
    Gm = DT * (np.eye(3) + Linear.F * DT / 2 + Linear.F @ Linear.F * DT**2 / 6
               + Linear.F @ Linear.F @ Linear.F * DT**3 / 24) @ Linear.g
    H1 = np.array([[1.0, 0.0, 0.0]])
    H2 = np.array([[0.0, 1.0, 0.0], [0.0, 0.0, 2.0]])
    out_m, out_P, out_mp, out_Pp, lls = [], [], [], [], []
    for r in range(N):
        m, P = m0[r].copy(), P0.copy()
        ms, Ps, mps, Pps, ll = [], [], [], [], 0.0
        for k in range(len(ticks)):
            if k > 0:  # the model's convention: the interval's noise Qc * dt enters once, at its end
                for j in range(ticks[k - 1], ticks[k]):
                    m = Phi @ m + Gm * u[r, j, 0]
                    P = Phi @ P @ Phi.T
                P = P + Qc * DT * (ticks[k] - ticks[k - 1])
            mps.append(m.copy())
            Pps.append(P.copy())
            Hs, ys, Rs = [], [], []
            g = ticks[k]
            if g in idx1:
                i = int(np.nonzero(idx1 == g)[0][0])
                Hs.append(H1)
                ys.append(y1[r, i])
                Rs.append(R1)
            if g in idx2:
                i = int(np.nonzero(idx2 == g)[0][0])
                if v2[r, i]:
                    Hs.append(H2)
                    ys.append(y2[r, i])
                    Rs.append(R2)
            if Hs:
                H = np.vstack(Hs)
                y = np.concatenate(ys)
                R = np.zeros((len(y), len(y)))
                a = 0
                for Rj in Rs:
                    R[a : a + len(Rj), a : a + len(Rj)] = Rj
                    a += len(Rj)
                S = H @ P @ H.T + R
                K = P @ H.T @ np.linalg.inv(S)
                nu = y - H @ m
                ll += -0.5 * (nu @ np.linalg.solve(S, nu) + np.log(np.linalg.det(S)) + len(y) * np.log(2 * np.pi))
                m = m + K @ nu
                P = (np.eye(3) - K @ H) @ P
            ms.append(m)
            Ps.append(P)
        out_m.append(ms)
        out_P.append(Ps)
        out_mp.append(mps)
        out_Pp.append(Pps)
        lls.append(ll)
    return (np.array(out_m), np.array(out_P), np.array(out_mp), np.array(out_Pp), np.array(lls))


def _reference_rts(mf, Pf, mp, Pp, ticks):
    """A textbook RTS smoother on the same model, one run at a time."""
    Phi = _rk4_matrix(Linear.F, DT)
    ms, Ps = mf.copy(), Pf.copy()
    for r in range(N):
        for k in range(len(ticks) - 2, -1, -1):
            A = np.linalg.matrix_power(Phi, int(ticks[k + 1] - ticks[k]))
            G = Pf[r, k] @ A.T @ np.linalg.inv(Pp[r, k + 1])
            ms[r, k] = mf[r, k] + G @ (ms[r, k + 1] - mp[r, k + 1])
            Ps[r, k] = Pf[r, k] + G @ (Ps[r, k + 1] - Pp[r, k + 1]) @ G.T
    return ms, Ps


def _noise(dm, meas):
    Q = np.broadcast_to(Qc, (N, 3, 3))
    R = [np.broadcast_to(R1, (N, 1, 1)), np.broadcast_to(R2, (N, 2, 2))]
    return Q, R


@pytest.mark.parametrize("ticks_every", [1, 2])
def test_ekf_and_eks_equal_kalman_filter_and_rts_smoother(ticks_every):
    dm, meas, m0, u, meas1, meas2, ticks = _problem(ticks_every=ticks_every)
    Q, R = _noise(dm, meas)
    ref_m, ref_P, ref_mp, ref_Pp, ref_ll = _reference_kf(m0, u, meas1, meas2, ticks)
    fwd = ekf(dm, meas, m0, P0, Q, R)
    np.testing.assert_allclose(fwd.m_filt, ref_m, atol=1e-9, rtol=0)
    np.testing.assert_allclose(fwd.P_filt, ref_P, atol=1e-9, rtol=0)
    np.testing.assert_allclose(fwd.loglik, ref_ll, atol=1e-9, rtol=1e-12)
    res = eks(dm, meas, m0, P0, Q, R)
    sm_m, sm_P = _reference_rts(ref_m, ref_P, ref_mp, ref_Pp, ticks)
    np.testing.assert_allclose(res.sm.m, sm_m, atol=1e-9, rtol=0)
    np.testing.assert_allclose(res.sm.P, sm_P, atol=1e-9, rtol=0)
    # the lag-one cross-covariance is that of the joint smoothed distribution: Cov(x_k+1, x_k) = P_k+1 G_k^T
    G = res.sm.G
    np.testing.assert_allclose(res.sm.C, res.sm.P[:, 1:] @ np.swapaxes(G, -1, -2), atol=1e-12)
    # the fast affine pass (EM's) and the generic Joseph-form pass give the same
    lin = linearise(dm, meas, res.sm.m)
    a = affine_pass(lin, dm, meas, m0, np.broadcast_to(P0, (N, 3, 3)), Q, R, joseph=True)
    b = affine_pass(lin, dm, meas, m0, np.broadcast_to(P0, (N, 3, 3)), Q, R, joseph=False)
    np.testing.assert_allclose(a.sm.m, sm_m, atol=1e-9)
    np.testing.assert_allclose(b.sm.m, sm_m, atol=1e-9)
    np.testing.assert_allclose(b.sm.P, sm_P, atol=1e-9)
    np.testing.assert_allclose(b.fwd.loglik, ref_ll, atol=1e-8, rtol=1e-12)


def test_batch_of_one_equals_the_batch():
    dm, meas, m0, u, *_ = _problem()
    Q, R = _noise(dm, meas)
    full = eks(dm, meas, m0, P0, Q, R)
    i = np.array([2])
    one = eks(dm.take(i), [m.take(i) for m in meas], m0[i], P0, Q[i], [r[i] for r in R])
    np.testing.assert_allclose(one.sm.m[0], full.sm.m[2], atol=1e-12)


def test_ieks_on_a_linear_model_settles_in_one_iteration():
    dm, meas, m0, *_ = _problem()
    Q, R = _noise(dm, meas)
    e = ieks(dm, meas, m0, P0, Q, R, update_x0=False, max_iter=10, tol=1e-6)
    assert e.settled.all()
    assert (e.iterations == 1).all()  # the re-linearised pass only confirms the first
    np.testing.assert_allclose(e.result.sm.m, eks(dm, meas, m0, P0, Q, R).sm.m, atol=1e-9)
    # with x0 <- x_0|N (the magnetic needle EM paper) the prior mean moves to the smoothed initial state until it settles
    e2 = ieks(dm, meas, m0, P0, Q, R, update_x0=True, max_iter=100, tol=1e-6)
    assert e2.settled.all()
    np.testing.assert_allclose(e2.m0, e2.result.sm.m[:, 0], atol=1e-5)


def test_rk4_step_jacobian_is_exact():
    model = MODELS.get("mnm")()
    rng = np.random.default_rng(1)
    x = np.concatenate([rng.normal(0, 0.01, (5, 3)), rng.standard_normal((5, 6))], -1)
    u = np.concatenate([np.full((5, 1), 0.002), rng.normal(0, 0.2, (5, 3))], -1)
    p = {"c": np.asarray(9.0)}
    f = lambda xx: model.f(xx, u[:, None, :] if xx.ndim == 3 else u, p)
    jac = lambda xx: model.jacobian(xx, u, p)
    _, F = rk4_with_jacobian(f, jac, x, 0.05)
    ref = complex_step_jacobian(lambda xx: model.step(xx, u[:, None, :], p, 0.05), x)
    np.testing.assert_allclose(F, ref, atol=1e-13, rtol=1e-11)


@pytest.mark.parametrize("name", ["mnm", "binm"])
def test_magnetic_parameter_jacobian(name):
    model = MODELS.get(name)()
    rng = np.random.default_rng(2)
    h = rng.standard_normal((6, 3))
    b = h + 0.5 * rng.standard_normal((6, 3))
    x = np.concatenate([rng.normal(0, 0.01, (6, 3)), h, b], -1)
    u = np.concatenate([np.full((6, 1), 0.002), rng.standard_normal((6, 3))], -1)
    p = {model.curvature_param: rng.uniform(2, 20, 6)}
    got = model.param_jacobian(x, u, p, model.curvature_param)
    ref = Model.param_jacobian(model, x, u, p, model.curvature_param)  # the complex-step default
    np.testing.assert_allclose(got, ref, rtol=1e-12, atol=1e-18)


def test_tangent_basis_and_repair():
    u = np.array([[0.0, -1.0, 0.0], [0.6, 0.8, 0.0]])
    E = tangent_basis(u, 2)
    np.testing.assert_allclose(np.swapaxes(E, -1, -2) @ E, np.broadcast_to(np.eye(2), (2, 2, 2)), atol=1e-15)
    np.testing.assert_allclose((u[:, :, None] * E).sum(1), 0.0, atol=1e-15)
    bad = np.array([[[1.0, 2.0], [2.0, 1.0]], [[2.0, 0.0], [0.0, 1.0]]])
    fixed, mask = repair_pd(bad)
    assert mask.tolist() == [True, False]
    assert np.all(np.linalg.eigvalsh(fixed) > 0)
    np.testing.assert_array_equal(fixed[1], bad[1])


def test_kalman_forward_masks_missing_samples_like_removing_them():
    dm, meas, m0, *_ = _problem()
    Q, R = _noise(dm, meas)
    meas_all = [meas[0], MeasurementModel("c2", meas[1].h, 3, meas[1].tick, meas[1].y,
                                          np.zeros_like(meas[1].valid), meas[1].angle)]
    only1 = ekf(dm, [meas[0]], m0, P0, Q, R[:1])
    masked = ekf(dm, meas_all, m0, P0, Q, R)
    np.testing.assert_allclose(masked.m_filt, only1.m_filt, atol=1e-12)
    np.testing.assert_allclose(masked.loglik, only1.loglik, atol=1e-9)
    assert callable(kalman_forward)


OBS = """\
name: kalman_obs
model: {type: mnm, params: {c: 9.5}, initial_state: {hy: -1.0, By: -1.0}}
inputs:
  v: 0.002
  omega_B: {kind: piecewise, times: [0.0, 2.0], values: [[0, 0, 0.4], [0, 0, 0.02]]}
process_noise: {std: {px: 1.0e-5, py: 1.0e-5, hx: 2.0e-3, hy: 2.0e-3, Bx: 1.0e-4, By: 1.0e-4}}
sensors:
  - {name: camera, type: position, rate: 6.0, axes: [x, y], sigma: 5.2e-5}
  - {name: coils, type: bfield, rate: 18.0, sigma: 1.0e-4}
observers:
  - {name: ekf, type: ekf, ticks: measurements, substeps: 1, augment: [c], q: {px: 1.0e-5, py: 1.0e-5, hx: 2.0e-3, hy: 2.0e-3, Bx: 1.0e-4, By: 1.0e-4}, p0: {hx: 1.0e-4, c: 25.0}, init: {values: {c: 7.0}}}
  - {name: eks, type: eks, ticks: measurements, substeps: 1, augment: [c], q: {px: 1.0e-5, py: 1.0e-5, hx: 2.0e-3, hy: 2.0e-3, Bx: 1.0e-4, By: 1.0e-4}, p0: {hx: 1.0e-4, c: 25.0}, init: {values: {c: 7.0}}}
  - {name: ieks, type: eks, iterations: 4, update_x0: true, ticks: measurements, substeps: 1, augment: [c], q: {px: 1.0e-5, py: 1.0e-5, hx: 2.0e-3, hy: 2.0e-3, Bx: 1.0e-4, By: 1.0e-4}, p0: {hx: 1.0e-4, c: 25.0}, init: {values: {c: 7.0}}}
runs: {count: 3, seed: 3}
stop: {time: 10.0}
output: {store_every: 50}
"""


def test_ekf_and_eks_observers_end_to_end():
    from needlecli.experiments.config.load import load_config
    from needlecli.experiments.simulation.runner import run_experiment
    from needlecli.metrics import compute_errors

    cfg, text = load_config(text=OBS)
    res = run_experiment(cfg, text, write=False)
    est = res.estimates
    for name in ("ekf", "eks", "ieks"):
        assert (est[name].status == "ok").all()
        assert est[name].names[-1] == "c"
        assert est[name].state.shape == (3, len(res.truth.time), 10)
    truth_p = res.truth.states[..., :2]
    err = {k: np.sqrt(((est[k].state[..., :2] - truth_p) ** 2).sum(-1)).mean() for k in est}
    assert err["eks"] < err["ekf"] < 5.2e-5  # the smoother beats the filter, both beat the camera's noise
    c_err = {k: np.abs(est[k].state[:, -1, -1] - 9.5).mean() for k in ("ekf", "eks")}
    assert c_err["eks"] < 2.5  # from 7.0, with 10 s of data
    assert "iterations" in est["ieks"].extras
    del compute_errors
