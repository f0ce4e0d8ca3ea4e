"""Delayed samples (sensor ``latency``): with ``delayed: acquisition`` the UKF updates the state each sample
was taken from (the current sigma points carried back over the latency by the model,
needlecli.sensors.past.retrodict), so that it estimates what a filter given the same samples without
latency estimates; with ``delayed: arrival`` (the default) a sample is used as if it were of now."""

from __future__ import annotations

import numpy as np
import pytest

from needlecli.experiments.config.load import load_config
from needlecli.experiments.simulation.runner import run_experiment
from needlecli.models import MODELS
from needlecli.sensors.past import retrodict

CONFIG = """
format: 2
name: latency
model: {{type: unicycle, params: {{kappa: 0.01}}, initial_state: {{alpha: 0.1, beta: -0.1, gamma: 0.4}}}}
inputs: {{v: 2.0, u: 0.0}}
sensors:
  - {{name: us, type: {sensor}, rate: 10.0, sigma: 0.2, latency: {latency}{extra}}}
observers:
  - &u
    name: acquisition
    type: ukf
    rate: 50.0
    q: {{x: 1.0e-4, y: 1.0e-4, z: 1.0e-4, alpha: 1.0e-6, beta: 1.0e-6, gamma: 1.0e-6}}
    p0: {{x: 1.0, y: 1.0, z: 1.0, alpha: 1.0e-3, beta: 1.0e-3, gamma: 1.0e-4}}
    measurements:
      us: {{sigma: 0.2, delayed: acquisition}}
    init: {{from: truth, std: {{x: 0.5, y: 0.5, z: 0.5}}}}
  - <<: *u
    name: arrival
    measurements:
      us: {{sigma: 0.2}}
runs: {{count: 4, seed: 5}}
stop: {{depth: 30.0}}
simulation: {{dt: 0.01}}
"""


def _run(tmp_path, latency, sensor="position", extra=", axes: [x, y, z]"):
    cfg, text = load_config(text=CONFIG.format(latency=latency, sensor=sensor, extra=extra))
    res = run_experiment(cfg, text, out=tmp_path / f"l{latency}.h5", base_dir=tmp_path)
    return res.truth, {k: v.state[..., :3] for k, v in res.estimates.items()}


def test_retrodict_undoes_the_models_step():
    cls = MODELS.get("modified_unicycle")
    model = cls(cls.Params(kappa=0.01, beta_cut=0.035))
    p = model.param_arrays()
    x0 = np.array([1.0, 2.0, 3.0, 0.2, -0.1, 0.5, 0.01])
    u = np.array([[1.5, 0.3], [1.5, -0.2], [1.0, 0.0]])
    x = x0
    for k in range(len(u)):
        x = model.step(x, u[k], p, 0.01)
    np.testing.assert_allclose(retrodict(model, x, u, p, 0.01), x0, atol=1e-12)


@pytest.mark.parametrize("sensor,extra", [("position", ", axes: [x, y, z]"),
                                          ("transverse", ", probe: {motion: follow, lag: 1.0}")])
def test_a_delayed_sample_updates_the_state_it_was_taken_from(tmp_path, sensor, extra):
    """The same samples 0.3 s late: at the end the filter that carries them back to their acquisition has
    used what the filter given them on time had used 0.3 s earlier, and its tip is that filter's tip
    then moved by the insertion since (the truth's, without process noise), to 2 % of the error the
    late use as if of now makes (or 0.01 mm)."""
    _, on_time = _run(tmp_path, 0.0, sensor, extra)
    truth, late = _run(tmp_path, 0.3, sensor, extra)
    ref = on_time["acquisition"]  # no latency: both settings the same filter
    np.testing.assert_array_equal(ref, on_time["arrival"])
    k = ref.shape[1] - 1
    k0 = k - 30  # 0.3 s earlier
    moved = truth.states[:, k, :3] - truth.states[:, k0, :3]
    off_acq = np.abs(late["acquisition"][:, k] - ref[:, k0] - moved).max()
    off_arr = np.abs(late["arrival"][:, k] - ref[:, k0] - moved).max()
    assert off_acq < max(0.02 * off_arr, 0.01)
    if sensor == "position":  # a tip sample used as of now lags the tip by the latency's travel, 0.6 mm
        assert off_arr > 0.2
