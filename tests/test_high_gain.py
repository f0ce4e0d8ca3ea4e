"""The high-gain observer (`highgain-us2d`): the transformed system against the unicycle, the error dynamics against
the matrix exponential of theta (A + L C), the sampled loop, zeta, and the CLI end to end."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from scipy.linalg import expm
from typer.testing import CliRunner

from needlecli.cli.app import app
from needlecli.errors import ConfigError
from needlecli.experiments.config.load import load_config
from needlecli.experiments.simulation.runner import run_experiment
from needlecli.models import MODELS
from needlecli.numerics import angle_diff
from needlecli.observers.high_gain import (
    from_transformed,
    is_hurwitz,
    largest_stable_theta,
    lawson_rk4,
    linear_flows,
    observer_step,
    sampled_radius,
    to_transformed,
    transformed_field,
)

GAIN = (-100.0, -1.05, 1.37)


def run(text: str, *overrides: str):
    cfg, txt = load_config(text=text, overrides=list(overrides))
    return run_experiment(cfg, txt, write=False)


# ---------------------------------------------------------------------------------------------- maths
@pytest.mark.parametrize("gamma0", [0.4, 2.6])  # cos(gamma) > 0 and < 0
def test_transformed_system_agrees_with_the_unicycle(gamma0):
    """s = (x, sin b, -cos b sin g) of a unicycle run, differentiated numerically, obeys
    s' = A s + phi(u, s) with zeta = sign(cos g)."""
    model = MODELS.get("unicycle")()
    p = {"kappa": np.array(0.01)}
    v, u, dt = 2.0, 0.3, 1e-3
    x = np.array([0.5, -0.2, 3.0, 0.1, 0.2, gamma0])
    xs = [x]
    for _ in range(1000):
        xs.append(model.step(xs[-1], np.array([v, u]), p, dt))
    xs = np.array(xs)
    s = to_transformed(xs[:, 0], xs[:, 4], xs[:, 5])
    ds = (s[2:] - s[:-2]) / (2 * dt)
    zeta = np.sign(np.cos(xs[1:-1, 5]))
    assert np.all(zeta == zeta[0])  # the run stays on one side of gamma = pi/2
    f = transformed_field(s[1:-1], v, u, 0.01, zeta)
    np.testing.assert_allclose(ds, f, atol=1e-7)
    # and back: (x, beta, gamma) from s and zeta
    xb, bb, gb = from_transformed(s, np.sign(np.cos(xs[:, 5])))
    np.testing.assert_allclose(xb, xs[:, 0], atol=1e-12)
    np.testing.assert_allclose(bb, xs[:, 4], atol=1e-12)
    np.testing.assert_allclose(angle_diff(gb, xs[:, 5]), 0.0, atol=1e-9)


def test_seed_gain_is_hurwitz_and_routh_agrees_with_eigenvalues():
    for v, kappa in ((2.0, 0.002), (10.0, 0.03), (0.5, 0.0005)):
        l1, l2, l3 = GAIN
        m = np.array([[l1, v, 0.0], [l2, 0.0, -v * kappa], [l3, 0.0, 0.0]])
        assert is_hurwitz(v, kappa, GAIN) == bool(np.all(np.linalg.eigvals(m).real < 0))
        assert is_hurwitz(v, kappa, GAIN)
    assert not is_hurwitz(2.0, 0.002, (-100.0, 1.05, 1.37))


# ---------------------------------------------------------------------------------------------- error dynamics
AT_REST = """\
name: at_rest
model: {type: unicycle, params: {kappa: KAPPA}}
inputs: {v: 2.0, u: 0.0}
sensors: [{name: us, type: position, rate: 100.0, axes: [x], sigma: 0.0}]
observers:
  - {name: hg, type: high_gain, theta: THETA, kappa: KAPPA, hold: zoh,
     init: {values: {x: 0.3, beta: 0.02, gamma: -0.03}}}
stop: {time: 3.0}
"""


@pytest.mark.parametrize("theta, kappa", [(5.0, 0.0), (5.0, 0.002), (2.0e3, 0.002)])
def test_error_dynamics_are_theta_A_plus_LC(theta, kappa):
    """A needle at rest at x = 0 (beta = gamma = 0, u = 0) gives a constant output, so the held sample is
    the continuous output and the error e = s_hat - s is exactly linear:
    Lambda^-1 e(t) = expm(theta (A + L C) t + (kappa v / theta) e3 e2^T t) Lambda^-1 e(0), the last term
    being phi's linear part (phi = 0 for kappa = 0). The stiff theta = 2000 case checks the exact flow."""
    text = AT_REST.replace("THETA", str(theta)).replace("KAPPA", str(kappa))
    res = run(text)
    truth = res.truth.states
    assert np.abs(truth[0, :, [0, 4, 5]]).max() == 0.0
    post = res.estimates["hg"]
    e = post.extras["s"][0]  # the observer's own state; truth s = 0
    if theta < 100:  # small errors stay representable as (x, beta, gamma)
        est = post.state[0]
        np.testing.assert_allclose(to_transformed(est[:, 0], est[:, 1], est[:, 2]), e, atol=1e-15)
    v = 2.0
    l1, l2, l3 = GAIN
    a_lc = np.array([[l1, v, 0.0], [l2, 0.0, -v * kappa], [l3, 0.0, 0.0]])
    extra = np.zeros((3, 3))
    extra[2, 1] = kappa * v / theta
    lam = np.array([theta, theta**2, theta**3])
    t = res.truth.time[::15]
    e = e[::15]
    ref = np.stack([lam * (expm((theta * a_lc + extra) * tk) @ (e[0] / lam)) for tk in t])
    np.testing.assert_allclose(e / lam, ref / lam, rtol=0, atol=1e-12 * np.abs(e[0] / lam).max() + 1e-15)
    # the scaled error decays (A + L C Hurwitz) when kappa > 0
    if kappa > 0:
        assert np.linalg.norm(e[-1] / lam) < np.linalg.norm(e[0] / lam)


def test_sampled_loop_radius_matches_a_brute_force_simulation():
    """The per-sample error map of the predictor hold, by stepping the linear error system finely."""
    v, kappa, theta, period = 2.0, 0.002, 500.0, 0.04
    l1, l2, l3 = GAIN
    lam = np.array([theta, theta**2, theta**3])
    m = np.zeros((4, 4))
    m[0, 1], m[1, 2], m[2, 1] = v, -v * kappa, kappa * v
    m[:3, 3] = lam * np.array(GAIN)
    m[3, 3] = theta * l1
    # columns of the map: reset r = e1, flow over the period with many small exact substeps
    sub = expm(m * period / 1000)
    cols = []
    for i in range(3):
        z = np.zeros(4)
        z[i] = 1.0
        z[3] = z[0]
        for _ in range(1000):
            z = sub @ z
        cols.append(z[:3])
    rho = np.max(np.abs(np.linalg.eigvals(np.array(cols).T)))
    assert sampled_radius(v, kappa, theta, GAIN, period) == pytest.approx(rho, rel=1e-6)
    top = largest_stable_theta(v, kappa, GAIN, period)
    assert sampled_radius(v, kappa, 0.98 * top, GAIN, period) < 1.0 < sampled_radius(v, kappa, 1.03 * top, GAIN, period)
    assert 1000 < top < 5000  # 25 Hz at 2 mm/s: theta of order 10^3 at most


# ---------------------------------------------------------------------------------------------- whole runs
SIM = """\
name: hg_small
model:
  type: unicycle
  params: {kappa: 0.0019}
  initial_state: {gamma: 0.05236, beta: 0.05}
  initial_std: {beta: 0.02}
inputs:
  v: 2.0
  u: {kind: piecewise, times: [0.0, 3.0, 4.0472, 8.0, 9.0472, 14.0, 15.5708],
      values: [0.0, 1.0, 0.0, 1.0, 0.0, -1.0, 0.0]}
sensors: [{name: us, type: position, rate: 100.0, axes: [x], sigma: 0.0}]
observers:
  - {name: high_gain, type: high_gain, measurement: us, theta: 1000.0, kappa: 0.002,
     init: {values: {x: 0.0, beta: 0.0}}}
runs: {count: 3, seed: 0}
stop: {depth: 40.0}
output: {tables: [x_pitch_roll_error, status]}
"""


def test_converges_with_curvature_mismatch_and_tracks_zeta():
    res = run(SIM)
    truth, post = res.truth.states, res.estimates["high_gain"]
    assert list(post.status) == ["ok"] * 3
    assert post.names == ("x", "beta", "gamma") and "not observable" in post.attrs["not_estimated"]
    e_beta = np.abs(angle_diff(post.state[..., 1], truth[..., 4]))
    e_gamma = np.abs(angle_diff(post.state[..., 2], truth[..., 5]))
    assert e_beta[:, 0].min() > 0.005  # it starts wrong ...
    assert e_beta[:, -1].max() < 1e-4  # ... and converges despite the 5 % curvature error
    assert np.abs(post.state[:, -1, 0] - truth[:, -1, 0]).max() < 1e-6
    # gamma crosses pi/2 twice (63 -> 123 -> 33 deg): zeta flips twice and the roll is right at the end
    assert list(post.extras["zeta_flips"]) == [2, 2, 2]
    assert e_gamma[:, -1].max() < 0.05


def test_large_theta_is_numerically_stable_with_zoh_and_reported_with_predictor():
    """theta = 67e4 (the high-gain observer paper's simulation, as legible): with the held sample the exact flow stays finite;
    with the predictor the sampled loop is unstable and every run says why."""
    res = run(SIM, "observers.0.theta=670000", "observers.0.hold=zoh", "stop.depth=10")
    post = res.estimates["high_gain"]
    assert np.isfinite(post.state).all() and list(post.status) == ["ok"] * 3
    res = run(SIM, "observers.0.theta=670000", "stop.depth=10")
    post = res.estimates["high_gain"]
    assert list(post.status) == ["diverged"] * 3
    assert "sampled loop unstable" in post.reason[0] and "hold: zoh" in post.reason[0]


def test_latency_and_dropouts_are_bridged():
    res = run(SIM, "sensors.0.rate=25", "sensors.0.latency=0.04", "sensors.0.dropout=0.1", "observers.0.theta=300")
    post, truth = res.estimates["high_gain"], res.truth.states
    assert list(post.status) == ["ok"] * 3
    assert np.abs(angle_diff(post.state[:, -1, 1], truth[:, -1, 4])).max() < 1e-3


@pytest.mark.parametrize(
    "override, where",
    [
        ("observers.0.gain=[-100, 1.05, 1.37]", "gain"),
        ("observers.0.measurement=nope", "measurement"),
        ("observers.0.theta=0", "theta"),
    ],
)
def test_bad_settings_are_config_errors(override, where):
    with pytest.raises(ConfigError) as e:
        load_config(text=SIM, overrides=[override])
    assert where in str(e.value)


def test_needs_a_position_sensor_with_x():
    with pytest.raises(ConfigError, match="position"):
        load_config(text=SIM, overrides=["sensors.0.axes=[y]"])


def test_cli_simulate_and_evaluate_table1(tmp_path: Path):
    cfg = tmp_path / "hg.yaml"
    cfg.write_text(SIM)
    out = tmp_path / "hg.h5"
    r = CliRunner().invoke(app, ["simulate", str(cfg), "--out", str(out), "--quiet"])
    assert r.exit_code == 0, r.output + repr(r.exception)
    r = CliRunner().invoke(app, ["evaluate", str(out), "--out", str(tmp_path / "t"), "--no-plots", "--quiet"])
    assert r.exit_code == 0, r.output + repr(r.exception)
    df = pd.read_csv(tmp_path / "t" / "hg_small_x_pitch_roll_error.csv")
    assert list(df["Error"]) == ["e_x [mm]", "e_beta [rad]", "e_gamma [rad]"]
    row = df.set_index("Error").loc["e_beta [rad]"]
    assert row["Final"] < 0.01 and row["Average Absolute Estimation Error"] < 0.01
    assert row["RMSE"] >= row["Average Absolute Estimation Error"]


def test_the_written_out_step_is_lawson_rk4_and_exact_without_the_square_root():
    rng = np.random.default_rng(1)
    q = rng.normal(scale=0.3, size=(6, 5))
    zu = rng.normal(size=6)
    for hold in ("predictor", "zoh"):
        eh, e = linear_flows(2.0, 0.002, 50.0, GAIN, hold, 0.01)

        def nonlin(x):
            out = np.zeros_like(x)
            out[:, 2] = -zu * np.sqrt(np.maximum(1 - x[:, 1] ** 2 - x[:, 2] ** 2, 0.0))
            return out

        np.testing.assert_allclose(observer_step(q, eh.T, e.T, zu, 0.01), lawson_rk4(q, eh, e, nonlin, 0.01),
                                   rtol=1e-12, atol=1e-12)
        # per-run flows (runs at different speeds) give the same as the shared one
        per_run = np.broadcast_to(e.T, (6, 5, 5)), np.broadcast_to(eh.T, (6, 5, 5))
        np.testing.assert_allclose(observer_step(q, per_run[1], per_run[0], zu, 0.01),
                                   observer_step(q, eh.T, e.T, zu, 0.01), rtol=1e-13, atol=1e-15)
        # no rotation: the step is the exact linear flow
        np.testing.assert_allclose(observer_step(q, eh.T, e.T, np.zeros(6), 0.01), q @ e.T, rtol=1e-14)
