"""Fair starts everywhere (issue 30, item 1): the observers ``needle compare`` runs start from the config's own
initial state on every paper config, tuned alike, and the observers of one ``simulate`` or ``sweep`` share
one start unless the config says otherwise."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml

from needlecli.experiments.config.load import load_config
from needlecli.experiments.studies.compare import prepare_comparison
from needlecli.models import MODELS
from needlecli.numerics import angle_diff
from needlecli.observers import OBSERVERS
from needlecli.papers import PAPERS

ROOT = Path(__file__).resolve().parents[1]
PAPER_CONFIGS = sorted(p for paper in PAPERS for p in (ROOT / paper.configs).glob("*.yaml"))
RUNS = 200


def expected_start(path: Path) -> tuple[dict[str, float], dict[str, float], set[str]]:
    """From the config file alone: the truth's mean initial state (the model's default pose with the
    config's ``model.initial_state``), its per-run spread (``model.initial_std``), the angle states."""
    data = yaml.safe_load(path.read_text())
    cls = MODELS.get(data["model"]["type"])
    model = cls(cls.Params(**(data["model"].get("params") or {})))
    x0 = np.asarray(model.initial_state(model.param_arrays()), dtype=float).reshape(-1)
    mean = dict(zip(model.state_names, x0.tolist()))
    mean.update({k: float(v) for k, v in (data["model"].get("initial_state") or {}).items()})
    return mean, {k: float(v) for k, v in (data["model"].get("initial_std") or {}).items()}, set(model.angle_states)


@pytest.mark.parametrize("path", PAPER_CONFIGS, ids=lambda p: str(p.relative_to(ROOT / "configs")))
def test_compared_observers_start_from_the_configs_initial_state(path):
    """Every observer that takes the common start starts from a draw around the config's initial state: the
    mean over runs within 4 standard errors of it (the truth's spread and the start's own variance), and
    every run exactly at it where neither spreads (the magnetic needle EM paper's heading and field, once reversed)."""
    cmp = prepare_comparison(path, runs=RUNS, overrides=["stop={time: 0.3}"])
    start = cmp.problem.start
    assert start is not None, cmp.start
    for c in cmp.chosen:
        if OBSERVERS.get(c.type).takes_common_start:
            assert c.start.startswith("common"), (c.name, c.start)
    mean, spread, angles = expected_start(path)
    ref = next((c for c in cmp.chosen if c.start == "common (reference)"), None)
    init = (ref.settings or {}).get("init") or {} if ref is not None and ref.origin == "config" else {}
    prescribed = set(init.get("values") or {})  # a config's own reference that starts a state elsewhere on
    for j, k in enumerate(start.names):  # purpose (the multi-rate UKF paper's Fig. 7: a wrong curvature) says so
        if k not in mean or k in prescribed:  # (or an augmented constant)
            continue
        x = start.mean[:, j]
        d = angle_diff(x, mean[k]) if k in angles else x - mean[k]
        sd = float(np.sqrt(spread.get(k, 0.0) ** 2 + start.cov[j, j]))
        assert abs(np.mean(d)) <= 4 * sd / np.sqrt(len(x)) + 1e-9, (k, float(np.mean(x)), mean[k], sd)
        if spread.get(k, 0.0) == 0 and start.cov[j, j] <= 1e-6:
            np.testing.assert_allclose(d, 0.0, atol=4 * np.sqrt(start.cov[j, j]) + 1e-9, err_msg=k)


# the multi-rate UKF paper's set-up, tiny: two UKFs alike but for their names, and the open loop
from test_shared_start import TWINS  # noqa: E402


def test_ekf_takes_the_distance_growth_of_r_as_the_ukf_does(tmp_path):
    """The EKF with ``growth`` weighs each sample as the UKF does (sigma (1 + a d / d_max) at the measured
    position): the same as the EKF without it on samples that carry that sigma as a recorded per-sample
    sigma; and the EKF and EKS derive the UKF's measurement settings, growth included."""
    import dataclasses

    from needlecli.experiments.simulation.runner import build_problem, simulate_and_measure
    from needlecli.experiments.simulation.truth import stream
    from needlecli.schema import DistanceGrowth

    growth = {"transducer": [0.0, 0.0, 90.0], "a": 1.0, "d_max": 80.0}
    cfg, _ = load_config(text=TWINS.replace("output: {covariance: none}", "output: {covariance: diag}"))
    truth, sensors, streams, _ = simulate_and_measure(cfg)
    problem = build_problem(cfg, truth, sensors, streams)
    ch = problem.channels["us3d"]
    f = DistanceGrowth(**growth).factor(ch.value)
    per_sample = np.where(ch.valid[..., None], np.broadcast_to(0.3 * f[..., None], ch.value.shape), np.nan)
    recorded = dataclasses.replace(ch, sample_sigma=per_sample)
    other = dataclasses.replace(problem, channels={**problem.channels, "us3d": recorded})
    base = {"type": "ekf", "q": {"x": 0.02, "y": 0.02, "z": 0.02, "alpha": 2e-4, "beta": 2e-4, "gamma": 5e-3},
            "p0": {"x": 1.0, "y": 1.0, "z": 1.0, "alpha": 5e-3, "beta": 5e-3, "gamma": 0.1, "kappa": 2e-6},
            "init": {"from": "truth", "first_measurement": {"x": "us3d.x", "y": "us3d.y", "z": "us3d.z"}}}
    ekf = OBSERVERS.get("ekf")
    with_growth = ekf.Settings.model_validate({**base, "measurements": {"us3d": {"sigma": 0.3, "growth": growth},
                                                                       "robot": {"sigma": 0.0035}}})
    plain = ekf.Settings.model_validate({**base, "measurements": {"us3d": {"sigma": 0.3}, "robot": {"sigma": 0.0035}}})
    a = ekf(with_growth).run(problem, stream(1, "x"))
    b = ekf(plain).run(other, stream(1, "x"))
    c = ekf(plain).run(problem, stream(1, "x"))
    np.testing.assert_allclose(a.state, b.state, rtol=1e-9, atol=1e-12)
    assert not np.allclose(a.state, c.state, rtol=1e-6)  # the growth matters here
    # derived alike: the comparison's EKF and EKS take the UKF's measurement settings, growth and all
    from needlecli.experiments.studies.compare import comparison_context

    grown = load_config(text=TWINS.replace("sigma: 0.3}", f"sigma: 0.3, growth: {growth}}}"))[0]
    t2, s2, st2, _ = simulate_and_measure(grown)
    ctx = comparison_context(grown, t2, s2, build_problem(grown, t2, s2, st2))
    ukf = OBSERVERS.get("ukf").derived_settings(ctx)["measurements"]
    for kind in ("ekf", "eks"):
        assert OBSERVERS.get(kind).derived_settings(ctx)["measurements"] == ukf
    assert ukf["us3d"]["growth"]["a"] == 1.0


def test_a_replays_process_noise_is_read_from_the_samples():
    """A state measured directly: white noise of std s on a random walk of intensity q (and a trend, which
    the second differences cancel), sampled every T; the variogram of the second differences gives q back
    (within 10 % over 200 runs of 20 s at 100 Hz), without the trend's help; a channel too slow for three
    lags under 2 s gives none."""
    import dataclasses

    from needlecli.observers.defaults import measured_process_std
    from needlecli.problem import Channel

    rng = np.random.default_rng(4)
    N, T, q, s = 200, 0.01, 5e-3, 3.5e-3
    t = np.arange(0.0, 20.0, T)
    walk = np.cumsum(q * np.sqrt(T) * rng.standard_normal((N, t.size)), axis=1) + 0.3 * t  # rad, a 0.3 rad/s turn
    y = walk + s * rng.standard_normal(walk.shape)
    ch = Channel(name="robot", sensor_type="encoder", t=t, t_available=t, index=np.arange(t.size),
                 value=y[..., None], valid=np.ones(y.shape, dtype=bool), names=("roll",), units=("rad",),
                 sigma=np.array([s]), angle=np.array([True]), h=None)
    assert measured_process_std(ch, 0) == pytest.approx(q, rel=0.1)
    quiet = dataclasses.replace(ch, value=(0.3 * t + s * rng.standard_normal((N, t.size)))[..., None])
    assert (measured_process_std(quiet, 0) or 0.0) < 0.2 * q  # no random walk: (nearly) none found
    slow = dataclasses.replace(ch, t=t[::100], t_available=t[::100], index=np.arange(t[::100].size),
                               value=y[:, ::100, None], valid=np.ones((N, t[::100].size), dtype=bool))
    assert measured_process_std(slow, 0) is None  # 1 Hz: lags 1 and 2 s only
