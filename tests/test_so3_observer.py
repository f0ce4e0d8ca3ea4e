"""The invariant observer on SO(3) (`so3-invariant`): against an independent integration of the error dynamics,
its Lyapunov function, orthonormality, latency, the unobservable case, other models, and the CLI."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from scipy.integrate import solve_ivp
from typer.testing import CliRunner

from needlecli.cli.app import app
from needlecli.errors import ConfigError
from needlecli.experiments.config.load import load_config
from needlecli.experiments.simulation.runner import run_experiment
from needlecli.io.results import Group
from needlecli.metrics.errors import compute_errors
from needlecli.numerics import euler_xyz_to_matrix, hat, rot_z, rotation_angle, so3_exp
from needlecli.observers.so3_invariant import invariant_field

KAPPA, V = 1.0 / 35.0, 10.0

HELIX = """\
name: helix_small
model: {type: so3, params: {kappa: 0.0285714285714}}
inputs:
  v: 10.0
  u: {kind: cases, labels: [pi/4, pi/32], cases: [0.785398163397, 0.0981747704247]}
sensors: [{name: tracker, type: tangent, rate: 100.0, sigma: 0.0}]
observers:
  - {name: from90, type: so3_invariant, gain: 0.65, init: {error_deg: 90.0, axis: measured}}
  - {name: random, type: so3_invariant, gain: 0.65, init: {error_deg: [20.0, 170.0], axis: random}}
runs: {count: 4, seed: 3}
stop: {depth: 100.0}
output: {tables: [rotation_convergence, rotation_half_turns, status]}
"""


def run(text: str, *overrides: str):
    cfg, txt = load_config(text=text, overrides=list(overrides))
    return run_experiment(cfg, txt, write=False)


def rotation_error_deg(res, name: str) -> np.ndarray:
    r = res.truth.model.tip_rotation(res.truth.states)
    post = res.estimates[name]
    rh = post.state[..., :9].reshape(*post.state.shape[:2], 3, 3)
    return np.rad2deg(rotation_angle(np.swapaxes(r, -1, -2) @ rh))


@pytest.fixture(scope="module")
def helix():
    return run(HELIX)


def test_matches_an_independent_integration_of_the_error_dynamics(helix):
    """E = R^T R_hat obeys E' = E hat(w) - hat(w) E + k hat(e3 x E e3) E (k = -0.65); integrated by
    scipy's adaptive RK from E(0) = Rz(90 deg), it gives the same rotation error along the run."""
    err = rotation_error_deg(helix, "from90")
    t = helix.truth.time
    for run_i, u in ((0, np.pi / 4), (1, np.pi / 32)):
        w = hat(np.array([KAPPA * V, 0.0, u]))

        def f(_, e, w=w, e3=np.array([0.0, 0.0, 1.0])):
            m = e.reshape(3, 3)
            return (m @ w - w @ m - 0.65 * hat(np.cross(e3, m @ e3)) @ m).ravel()

        sol = solve_ivp(f, (0, t[-1]), rot_z(np.pi / 2).ravel(), t_eval=t[::100], rtol=1e-11, atol=1e-12)
        ref = np.rad2deg([rotation_angle(s.reshape(3, 3)) for s in sol.y.T])
        np.testing.assert_allclose(err[run_i, ::100], ref, atol=0.05)  # the held sample: see the docstring
    assert err[1, -1] < err[0, -1] < 90.0  # converging, slower with the fast rotation about the tangent


def test_lyapunov_function_is_non_increasing(helix):
    """The rotation error angle (the SO(3) observer paper's V = |log E|^2 / 2) never grows on a noise-free run."""
    for name in ("from90", "random"):
        err = rotation_error_deg(helix, name)
        assert np.diff(err, axis=1).max() < 1e-7, name
        assert (err[:, -1] < err[:, 0]).all()


def test_correction_turns_the_estimated_tangent_toward_the_measured_one():
    rng = np.random.default_rng(0)
    r = so3_exp(rng.standard_normal((50, 3)))  # (N, 3, 3); the step's layout is components first
    y = so3_exp(rng.standard_normal((50, 3)))[:, :, 2]
    soa = lambda a: np.ascontiguousarray(np.moveaxis(a, 0, -1))
    b = np.broadcast_to(np.array([0.0, 0.0, 1.0])[None, :, None], (1, 3, 50))
    dr = invariant_field(soa(r), np.zeros((3, 50)), soa(y)[None], b, -0.65)
    d_yhat = dr[:, 2].T  # derivative of R e3, (N, 3)
    assert (np.einsum("ni,ni->n", d_yhat, y) > 0).all()
    # with w only: R hat(w), checked against the matrix product
    w = rng.standard_normal((50, 3))
    np.testing.assert_allclose(invariant_field(soa(r), soa(w), soa(y)[None], b, 0.0), soa(r @ hat(w)), atol=1e-14)
    # and the correction is k hat(y x R e3) R
    c = np.cross(y, r[:, :, 2])
    np.testing.assert_allclose(invariant_field(soa(r), np.zeros((3, 50)), soa(y)[None], b, -0.65),
                               soa(-0.65 * hat(c) @ r), atol=1e-14)


def test_estimate_stays_on_so3(helix):
    for name, post in helix.estimates.items():
        assert post.extras["orthonormality_error"].max() < 1e-9, name
        rh = post.state[..., :9].reshape(*post.state.shape[:2], 3, 3)
        d = np.swapaxes(rh, -1, -2) @ rh - np.eye(3)
        assert np.abs(d).max() < 1e-9
        assert np.allclose(np.linalg.det(rh), 1.0)


def test_initial_error_about_the_measured_axis(helix):
    err = rotation_error_deg(helix, "from90")
    np.testing.assert_allclose(err[:, 0], 90.0, atol=1e-9)
    post = helix.estimates["from90"]
    y_hat0 = post.state[:, 0, :9].reshape(-1, 3, 3)[:, :, 2]
    y0 = helix.truth.model.tangent(helix.truth.states[:, 0])
    np.testing.assert_allclose(y_hat0, y0, atol=1e-12)  # the tangents agree
    e_rand = rotation_error_deg(helix, "random")[:, 0]
    assert ((e_rand >= 20.0 - 1e-9) & (e_rand <= 170.0 + 1e-9)).all() and np.ptp(e_rand) > 1.0


ONE = HELIX.replace("runs: {count: 4, seed: 3}", "runs: {count: 2, seed: 3}").replace(
    "  - {name: random, type: so3_invariant, gain: 0.65, init: {error_deg: [20.0, 170.0], axis: random}}\n", "")


def test_latency_and_slow_samples_leave_no_bias():
    """A held sample is transported with the known rotation, so a noise-free sensor at 10 Hz with 50 ms
    latency converges as well as one at the grid rate, and a perfect start stays perfect."""
    res = run(ONE, "sensors.0.rate=10", "sensors.0.latency=0.05", "observers.0.init.error_deg=5", "stop.depth=40")
    ref = run(ONE, "observers.0.init.error_deg=5", "stop.depth=40")
    err, err_ref = rotation_error_deg(res, "from90"), rotation_error_deg(ref, "from90")
    assert err[:, -1].max() < 4.5 and np.abs(err[:, -1] - err_ref[:, -1]).max() < 0.05
    res0 = run(ONE, "sensors.0.rate=10", "sensors.0.latency=0.05", "observers.0.init.error_deg=0", "stop.depth=20")
    assert rotation_error_deg(res0, "from90").max() < 1e-6


def test_angular_velocity_parallel_to_the_tangent_is_unobservable():
    res = run(ONE, "inputs.v=0", "stop={time: 3}")
    post = res.estimates["from90"]
    assert list(post.status) == ["unobservable"] * 2
    assert "angular velocity parallel to the measured vector" in post.reason[0]
    # a nearly straight needle: curvature 1e-7 over 3 s is still too little perpendicular rotation
    res = run(ONE, "model.params.kappa=1.0e-7", "stop.depth=30")
    assert set(res.estimates["from90"].status) == {"unobservable"}
    # the helix itself is observable
    assert set(run(ONE, "stop.depth=5").estimates["from90"].status) == {"ok"}


UNICYCLE = """\
name: so3_on_unicycle
model: {type: unicycle, params: {kappa: 0.05}, initial_state: {beta: 0.1, gamma: 0.3}}
inputs: {v: 5.0, u: 0.5}
sensors: [{name: em, type: tangent, rate: 50.0, sigma: 0.0}]
observers: [{name: inv, type: so3_invariant, gain: 0.5, init: {error_deg: 40.0}}]
runs: {count: 2, seed: 0}
stop: {depth: 50.0}
"""


def test_works_on_the_unicycle_and_gives_euler_angles():
    res = run(UNICYCLE)
    post = res.estimates["inv"]
    err = rotation_error_deg(res, "inv")
    assert err[:, 0] == pytest.approx(40.0) and err[:, -1].max() < 25.0
    assert np.diff(err, axis=1).max() < 1e-7
    # Euler angles beside R (the same rotation): evaluation compares them with the truth's
    names = list(post.names)
    tr = res.truth.states
    eul = post.state[..., [names.index(a) for a in ("alpha", "beta", "gamma")]]
    np.testing.assert_allclose(euler_xyz_to_matrix(*np.moveaxis(eul, -1, 0)),
                               post.state[..., :9].reshape(*eul.shape[:2], 3, 3), atol=1e-12)
    g = Group(data={"truth": Group(data={"state": tr, "status": res.truth.status},
                                   attrs={"names": res.truth.model.state_names, "units": res.truth.model.state_units,
                                          "angles": res.truth.model.angle_states}),
                    "estimates": Group(data={"inv": Group(data={"state": post.state, "status": post.status},
                                                          attrs={"names": post.names, "units": post.units,
                                                                 "angles": post.angle_states})})},
              attrs={"length_unit": "mm"})
    q = compute_errors(g)["inv"].quantities
    assert {"E_R", "E_alpha", "E_beta", "E_gamma"} <= set(q)


@pytest.mark.parametrize(
    "override, match",
    [
        ("observers.0.gain=-0.65", "gain"),
        ("observers.0.init.error_deg=181", "error_deg"),
        ("observers.0.measurements={nope: {}}", "nope"),
        ("sensors=[]", "needs a tangent sensor"),
    ],
)
def test_bad_settings_are_config_errors(override, match):
    with pytest.raises(ConfigError, match=match):
        load_config(text=HELIX, overrides=[override])


def test_cli_simulate_and_evaluate(tmp_path: Path):
    cfg = tmp_path / "helix.yaml"
    cfg.write_text(ONE.replace("stop: {depth: 100.0}", "stop: {depth: 120.0}\nsimulation: {dt: 0.02}"))
    out = tmp_path / "helix.h5"
    r = CliRunner().invoke(app, ["simulate", str(cfg), "--out", str(out), "--quiet"])
    assert r.exit_code == 0, r.output + repr(r.exception)
    r = CliRunner().invoke(app, ["evaluate", str(out), "--out", str(tmp_path / "t"), "--quiet"])
    assert r.exit_code == 0, r.output + repr(r.exception)
    conv = pd.read_csv(tmp_path / "t" / "helix_small_rotation_convergence.csv")
    assert set(conv["Case"]) == {"pi/4", "pi/32"}
    row = conv[(conv["Observer"] == "from90") & (conv["Case"] == "pi/32")].iloc[0]
    assert row["E_R at 0 [deg]"] == pytest.approx(90.0) and row["final [deg]"] < 35.0
    half = pd.read_csv(tmp_path / "t" / "helix_small_rotation_half_turns.csv")
    sel = half[(half["Observer"] == "from90") & (half["Case"] == "pi/32")]
    assert list(sel["Half turns"]) == [0, 1]
    assert sel["Distance [mm]"].iloc[1] == pytest.approx(np.pi * 35.0, abs=0.2)
    assert sel["Reduction [%]"].iloc[1] > 50
    assert (tmp_path / "t" / "helix_small_rotation_error.png").stat().st_size > 1000
