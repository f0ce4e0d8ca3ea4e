"""The observers of one study share one start unless the config says otherwise (issue 30, item 1):
``runs.common_start`` defaults to the first observer's initial estimate that can be shared, as ``needle
compare`` does, and every table says which start each observer had."""

from __future__ import annotations

import numpy as np

from needlecli.experiments.config.load import load_config
from needlecli.experiments.simulation.runner import run_experiment
from needlecli.io.results import read_results

# the multi-rate UKF paper's set-up, tiny: 2 insertions of 6 mm, two UKFs alike but for their names, and the open loop
TWINS = """\
name: twins
model: {type: modified_unicycle, params: {kappa: 0.005, beta_cut: 0.035}, param_std: {kappa: 0.001}}
inputs: {v: 1.5, u: 0.0}
process_noise: {std: {x: 0.02, y: 0.02, z: 0.02, alpha: 2.0e-4, beta: 2.0e-4, gamma: 5.0e-3}}
sensors:
  - {name: us3d, type: position, rate: 2.0, sigma: 0.3}
  - {name: robot, type: encoder, rate: 50.0, channels: [roll], sigma: 0.0035}
observers:
  - &ukf
    name: first
    type: ukf
    q: {x: 2.0e-3, y: 2.0e-3, z: 2.0e-3, alpha: 2.0e-5, beta: 2.0e-5, gamma: 5.0e-4, kappa: 2.0e-6}
    p0: {x: 1.0, y: 1.0, z: 1.0, alpha: 5.0e-3, beta: 5.0e-3, gamma: 0.1, kappa: 2.0e-6}
    init: {from: truth, std: {alpha: 0.0873, beta: 0.0873, kappa: 0.001}, first_measurement: {x: us3d.x, y: us3d.y, z: us3d.z}}
  - {<<: *ukf, name: second}
  - {name: model, type: open_loop, init: {from: truth, std: {alpha: 0.0873, beta: 0.0873}}}
runs: {count: 2, seed: 5}
stop: {depth: 6.0}
simulation: {dt: 0.02}
output: {covariance: none}
"""


def _simulate(tmp_path, text: str, name: str):
    cfg, raw = load_config(text=text)
    return read_results(run_experiment(cfg, raw, out=tmp_path / f"{name}.h5").path)


def test_observers_of_one_study_share_a_start_by_default(tmp_path):
    """Two observers with identical settings under different names give identical estimates by default (the
    second starts from the first's draw, and the open loop too); with ``runs.common_start: none`` each draws
    its own start; the results file and the summary's caption say which start each observer had."""
    from needlecli.reports.evaluate import results_tables

    res = _simulate(tmp_path, TWINS, "shared")
    est = res.data["estimates"].data
    np.testing.assert_array_equal(est["first"].data["state"], est["second"].data["state"])
    np.testing.assert_array_equal(est["model"].data["state"][:, 0], est["first"].data["state"][:, 0])
    assert est["first"].attrs["start"] == "common (reference): its own init"
    assert est["second"].attrs["start"] == est["model"].attrs["start"] == "common: first's initial estimate"
    caption = results_tables(res, ["summary"], "x")["summary"].attrs["caption"]
    assert "Start: model, second from first's initial estimate (its own draw, made once; runs.common_start)." \
        in caption
    # the first observer's estimates are those it has alone
    alone = _simulate(tmp_path, TWINS.replace("  - {<<: *ukf, name: second}\n", "").replace(
        "  - {name: model, type: open_loop, init: {from: truth, std: {alpha: 0.0873, beta: 0.0873}}}\n", ""), "alone")
    np.testing.assert_array_equal(alone.data["estimates"].data["first"].data["state"], est["first"].data["state"])
    own = _simulate(tmp_path, TWINS.replace("runs: {count: 2, seed: 5}", "runs: {count: 2, seed: 5, common_start: none}"),
                    "own")
    e2 = own.data["estimates"].data
    np.testing.assert_array_equal(e2["first"].data["state"], est["first"].data["state"])
    assert not np.allclose(e2["second"].data["state"][:, 0], e2["first"].data["state"][:, 0])
    assert e2["second"].attrs["start"] == "own init (runs.common_start: none)"
    caption = results_tables(own, ["summary"], "x")["summary"].attrs["caption"]
    assert "Start: each observer from its own init (runs.common_start: none)." in caption
