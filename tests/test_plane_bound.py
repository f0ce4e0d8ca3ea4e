"""The image plane as a one-sided measurement (issue 17, item 3): the UKF's truncated-Gaussian update
against independent references (scipy.stats.truncnorm for a hard bound on a linear 1-D case, quadrature
for the soft bound and for a 2-D state), the emulated image_plane sensor, its validation, and a synthetic
insertion where the plane alone pulls a filter started off along the needle back to the tip."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml
from scipy import stats
from typer.testing import CliRunner

from needlecli.cli.app import app
from needlecli.errors import ConfigError
from needlecli.experiments.config.load import load_config
from needlecli.experiments.simulation.runner import run_experiment
from needlecli.numerics.unscented import MerweWeights
from needlecli.observers.ukf import UnscentedKalmanFilter

UPDATE = UnscentedKalmanFilter._update_bound


def _linear_bound(a: np.ndarray, d: np.ndarray, side: np.ndarray, *, sigma=0.0, margin=0.0, sides=("past", "short")):
    """A channel whose samples say ``side (a . x - d) >= -margin`` (one sample per run)."""
    N = len(d)

    def bound(x, value):
        return np.sum(a * x, -1) - value[..., 0], np.where(value[..., 1] > 0.5, 1.0, -1.0)

    value = np.stack([d, (side > 0).astype(float)], -1)[:, None, :]  # (N, 1, 2)
    return {"name": "plane", "bound": bound, "value": value, "valid": np.ones((N, 1), dtype=bool),
            "sigma": sigma, "margin": margin, "past": "past" in sides, "short": "short" in sides}


def _apply(x, P, b, alpha=1e-3):
    N, n = x.shape
    used, violated = {"plane": np.zeros(N, dtype=np.int64)}, {"plane": np.zeros(N, dtype=np.int64)}
    x1, P1 = UPDATE(x.copy(), P.copy(), b, 0, MerweWeights(n, alpha, 2.0, 0.0), np.zeros(n, dtype=bool),
                    np.ones(N, dtype=bool), used, violated, np.zeros(N, dtype=np.int64))
    return x1, P1, used["plane"], violated["plane"]


@pytest.mark.parametrize("alpha", [1e-3, 1.0])
def test_hard_bound_on_a_scalar_gives_the_truncated_normal_moments(alpha):
    """x ~ N(mu, p), the sample says x >= d (seen) or x <= d (lost): the posterior mean and variance are
    scipy.stats.truncnorm's, from inside the bound (a small correction) to far outside it (a << 0)."""
    mu = np.array([0.0, 0.0, 0.0, 5.0, 1.5, -1.0])
    p = np.array([1.0, 4.0, 0.25, 1.0, 9.0, 0.01])
    d = np.array([0.5, -3.0, 1.5, 0.0, 2.0, -2.0])
    side = np.array([1.0, 1.0, 1.0, -1.0, -1.0, 1.0])
    x1, P1, used, violated = _apply(mu[:, None], p[:, None, None], _linear_bound(np.ones(1), d, side), alpha)
    s = np.sqrt(p)
    lo = np.where(side > 0, (d - mu) / s, -np.inf)
    hi = np.where(side > 0, np.inf, (d - mu) / s)
    ref_mean = stats.truncnorm.mean(lo, hi, loc=mu, scale=s)
    ref_var = stats.truncnorm.var(lo, hi, loc=mu, scale=s)
    np.testing.assert_allclose(x1[:, 0], ref_mean, rtol=1e-7, atol=1e-9)
    np.testing.assert_allclose(P1[:, 0, 0], ref_var, rtol=1e-6, atol=1e-12)
    assert used.tolist() == [1] * 6
    assert violated.tolist() == [int(v) for v in side * (mu - d) < 0]


def test_soft_bound_and_margin_match_quadrature():
    """sigma > 0: the likelihood Phi((side (x - d) + margin) / sigma); the posterior moments by quadrature
    on a fine grid."""
    mu, p, d = np.array([1.0, -2.0, 0.0]), np.array([2.0, 0.5, 1.0]), np.array([2.0, -1.0, 3.0])
    side, sigma, margin = np.array([1.0, -1.0, 1.0]), 0.7, 0.4
    x1, P1, _, _ = _apply(mu[:, None], p[:, None, None], _linear_bound(np.ones(1), d, side, sigma=sigma, margin=margin))
    for i in range(3):
        g = np.linspace(mu[i] - 12 * np.sqrt(p[i]), mu[i] + 12 * np.sqrt(p[i]), 200001)
        w = stats.norm.pdf(g, mu[i], np.sqrt(p[i])) * stats.norm.cdf((side[i] * (g - d[i]) + margin) / sigma)
        m = np.sum(w * g) / np.sum(w)
        v = np.sum(w * (g - m) ** 2) / np.sum(w)
        assert x1[i, 0] == pytest.approx(m, rel=1e-6, abs=1e-8)
        assert P1[i, 0, 0] == pytest.approx(v, rel=1e-5)


def test_bound_on_a_direction_of_a_correlated_state_matches_2d_quadrature():
    """A plane n . x >= d on a correlated 2-D Gaussian: the first two moments of the truncated density,
    by quadrature over the plane, are the update's (the regression on z is exact for a linear bound)."""
    mu = np.array([[0.3, -0.2]])
    P = np.array([[[2.0, 0.8], [0.8, 1.0]]])
    n = np.array([0.6, 0.8])
    b = _linear_bound(n, np.array([1.0]), np.array([1.0]))
    x1, P1, _, _ = _apply(mu, P, b)
    g = np.linspace(-10, 10, 1601)
    X, Y = np.meshgrid(g, g, indexing="ij")
    pts = np.stack([X, Y], -1)
    dens = stats.multivariate_normal(mu[0], P[0]).pdf(pts) * (pts @ n >= 1.0)
    m = np.einsum("ij,ijk->k", dens, pts) / dens.sum()
    r = pts - m
    C = np.einsum("ij,ijk,ijl->kl", dens, r, r) / dens.sum()
    np.testing.assert_allclose(x1[0], m, atol=3e-3)
    np.testing.assert_allclose(P1[0], C, atol=5e-3)
    assert np.all(np.linalg.eigvalsh(P1[0]) > 0)


def test_sides_select_the_samples_used():
    mu, p = np.zeros((2, 1)), np.ones((2, 1, 1))
    b = _linear_bound(np.ones(1), np.array([1.0, 1.0]), np.array([1.0, -1.0]), sides=("short",))
    x1, P1, used, _ = _apply(mu, p, b)
    assert used.tolist() == [0, 1]
    assert x1[0, 0] == 0.0 and P1[0, 0, 0] == 1.0  # the seen sample is not used
    assert x1[1, 0] < 0.0  # the lost one is: x <= 1 pulls the mean down


# ---------------------------------------------------------------------------------------------- end to end
SIM = """\
name: plane
model: {type: unicycle, params: {kappa: 0.01}}
inputs: {v: 1.0}
sensors:
  - {type: image_plane, name: plane, rate: 5, offset_sigma: 2.0, offset_tau: 4.0}
observers:
  - name: with_plane
    type: ukf
    q: {x: 1.0e-3, y: 1.0e-3, z: 1.0e-3}
    p0: {x: 1.0, y: 1.0, z: 25.0, alpha: 1.0e-4, beta: 1.0e-4, gamma: 1.0e-4}
    measurements:
      plane: {sigma: 0.2}
    init: {from: truth, values: {z: 5.0}}
    rate: 20
  - name: without
    type: ukf
    q: {x: 1.0e-3, y: 1.0e-3, z: 1.0e-3}
    p0: {x: 1.0, y: 1.0, z: 25.0, alpha: 1.0e-4, beta: 1.0e-4, gamma: 1.0e-4}
    init: {from: truth, values: {z: 5.0}}
    rate: 20
runs: {count: 8, seed: 3}
stop: {depth: 40}
simulation: {dt: 0.05}
output: {covariance: none, tables: [summary]}
"""


def test_emulated_plane_is_normal_to_the_tangent_and_seen_behind_the_tip(tmp_path):
    import h5py

    cfg_path = tmp_path / "plane.yaml"
    cfg_path.write_text(SIM)
    cfg, text = load_config(cfg_path)
    out = tmp_path / "plane.h5"
    run_experiment(cfg, text, out=out, base_dir=tmp_path)
    with h5py.File(out, "r") as f:
        m = f["measurements/plane"]
        value, valid, idx = m["value"][()], m["valid"][()], m["index"][()]
        truth = f["truth/state"][()]
        est = {o: f[f"estimates/{o}/state"][()] for o in ("with_plane", "without")}
        used = f["estimates/with_plane/used/plane"][()]
    assert valid.all() and value.shape[-1] == 5
    from needlecli.models import MODELS

    model = MODELS.get("unicycle")(MODELS.get("unicycle").Params(kappa=0.01))
    x = truth[:, idx]
    np.testing.assert_allclose(value[..., :3], model.tangent(x), atol=1e-12)
    g = np.sum(value[..., :3] * x[..., :3], -1) - value[..., 3]  # the tip's distance past the plane
    np.testing.assert_array_equal(value[..., 4] > 0.5, g >= -1e-9)
    assert 0.2 < np.mean(value[..., 4]) < 0.8  # the plane runs on both sides of the tip
    # the plane alone brings the filter started 5 mm off along the needle to the tip
    assert (used > 0.9 * len(idx)).all()
    err = {o: np.abs(e[:, -1, 2] - truth[:, -1, 2]).mean() for o, e in est.items()}
    assert err["without"] > 4.0 and err["with_plane"] < 1.5


@pytest.mark.parametrize("spec, loc, message", [
    ({"sigma": 1.0, "gate": 0.99}, "measurements -> plane -> gate", "not for a one-sided channel"),
    ({"sigma": [1.0, 2.0]}, "measurements -> plane -> sigma", "one bound"),
    ({"sigma": 1.0, "frame": "needle"}, "measurements -> plane -> frame", "not for a one-sided channel"),
    ({"sigma": 1.0, "sides": ["behind"]}, "measurements -> plane -> sides", ""),
])
def test_one_sided_channel_mistakes(tmp_path, spec, loc, message):
    data = yaml.safe_load(SIM)
    data["observers"][0]["measurements"]["plane"] = spec
    p = tmp_path / "bad.yaml"
    p.write_text(yaml.safe_dump(data))
    with pytest.raises(ConfigError) as e:
        load_config(p)
    assert loc.replace(" -> ", ".") in str(e.value).replace(" -> ", ".") or loc in str(e.value)
    assert message in str(e.value)


def test_sides_and_margin_are_only_for_one_sided_channels(tmp_path):
    data = yaml.safe_load(SIM)
    data["sensors"].append({"type": "position", "name": "us", "rate": 5, "sigma": 1.0})
    data["observers"][1]["measurements"] = {"us": {"sigma": 1.0, "margin": 2.0}}
    p = tmp_path / "bad.yaml"
    p.write_text(yaml.safe_dump(data))
    r = CliRunner().invoke(app, ["validate", str(p)])
    assert r.exit_code == 2
    assert "margin" in r.output and "only for a channel that bounds the state from one side" in r.output


def test_the_plane_is_not_an_ordinary_measurement_of_any_observer(tmp_path):
    """image_plane has no h: a filter given every channel by default does not take it (the bound must be
    asked for by name), and a model without a tangent cannot carry the sensor."""
    data = yaml.safe_load(SIM)
    data["model"] = {"type": "unicycle", "params": {"kappa": 0.01}}
    data["observers"] = [{"name": "ekf", "type": "ekf", "init": {"from": "truth"}}]
    p = tmp_path / "ok.yaml"
    p.write_text(yaml.safe_dump(data))
    cfg, text = load_config(p)
    out = tmp_path / "ok.h5"
    run_experiment(cfg, text, out=out, base_dir=tmp_path)
    assert Path(out).exists()


def test_image_plane_takes_no_image_pipeline(tmp_path):
    data = yaml.safe_load(SIM)
    data["sensors"][0]["pipeline"] = "image"
    p = tmp_path / "bad.yaml"
    p.write_text(yaml.safe_dump(data))
    with pytest.raises(ConfigError, match="no image pipeline"):
        load_config(p)
