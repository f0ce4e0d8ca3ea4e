"""Study configs faithful to the papers (issue 15, item 5): the multi-rate UKF paper's Table 1 simulated as the paper did
(constant 0.3 mm ultrasound noise, the distance law only in the filter's R, elastography a pre-operative
map), the former set-up kept as a variant; the high-gain observer paper's experiment-like high-gain observer with a theta
that converges within the insertion, beside a small sweep of theta; the SO(3) observer paper's caption saying what its
3.5 cm-radius reading does and does not reproduce."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import yaml

from needlecli.experiments.config.load import load_config
from needlecli.experiments.simulation.runner import run_experiment
from needlecli.io.results import Group, read_results
from needlecli.observers.high_gain import error_matrix
from needlecli.reports.evaluate import evaluate_results
from needlecli.reports.seed000_001 import _convergence_note

ROOT = Path(__file__).resolve().parents[1]
CONFIGS = ROOT / "configs"


def test_seed003_table1_simulates_as_the_paper(tmp_path):
    cfg, text = load_config(CONFIGS / "multirate-ukf-us3d/table1.yaml", overrides=["runs.count=2", "stop.depth=6",
                                                                      "observers.0.predict_at_depths=[]"])
    sensors = {s.name: s for s in cfg.sensors}
    assert sensors["us3d"].growth is None and sensors["us3d"].sigma == 0.3
    assert sensors["swe"].preoperative
    ukf = cfg.observers[0]
    assert ukf.measurements["us3d"].growth is not None  # the distance law: the filter's R reset
    res = read_results(run_experiment(cfg, text, out=tmp_path / "t1.h5").path)
    us = res.data["measurements"].data["us3d"]
    assert np.all(us.data["sigma"] == 0.3)  # constant, wherever the tip is
    swe = res.data["measurements"].data["swe"]
    assert swe.data["t"].tolist() == [0.0] and swe.data["valid"].all()  # one map, before the insertion
    assert np.isnan(res.data["estimates"].data["ukf"].data["nis"].data["swe"]).all()  # it initialises only
    # today's former set-up, kept as a named variant
    var, _ = load_config(CONFIGS / "multirate-ukf-us3d/table1_growth_stream.yaml")
    vs = {s.name: s for s in var.sensors}
    assert vs["us3d"].growth is not None and not vs["swe"].preoperative and vs["swe"].rate == 1.0
    full, _ = load_config(CONFIGS / "multirate-ukf-us3d/table1.yaml")
    assert var.observers[0].model_dump() == full.observers[0].model_dump()  # the same filter


def test_seed000_theta_converges_within_the_insertion():
    """The linear error dynamics theta (A + L C): the configured observer reaches 1 % of an initial error
    within the 50 s insertion, theta = 3 (the former setting) does not; the sweep shares the data."""
    data = yaml.safe_load((CONFIGS / "highgain-us2d/experiment_like.yaml").read_text())
    v, stop = data["inputs"]["v"], data["stop"]["depth"]
    duration = stop / v
    settle = {}
    for o in data["observers"]:
        poles = o["theta"] * np.linalg.eigvals(error_matrix(v, o["kappa"], (-100.0, -1.05, 1.37))).real
        settle[o["name"]] = np.log(100) / -poles.max()
    assert settle["high_gain"] < 0.7 * duration
    assert settle["theta_3"] > duration and settle["theta_5"] > duration
    assert sorted(o["theta"] for o in data["observers"]) == [3.0, 5.0, 10.0, 15.0, 30.0, 100.0]
    assert len({yaml.safe_dump(o["init"]) for o in data["observers"]}) == 1  # the same start for all


def test_seed000_caption_gives_each_observers_settling(tmp_path):
    cfg, text = load_config(CONFIGS / "highgain-us2d/experiment_like.yaml", overrides=[
        "runs.count=1", "stop.depth=4",
        "observers=[{name: high_gain, type: high_gain, measurement: us2d, theta: 15.0, kappa: 0.002}]"])
    res = read_results(run_experiment(cfg, text, out=tmp_path / "e.h5").path)
    g = res.data["estimates"].data["high_gain"]
    expected = np.sort(15.0 * np.linalg.eigvals(error_matrix(2.0, 0.002, (-100.0, -1.05, 1.37))).real)
    np.testing.assert_allclose(g.attrs["error_poles"], expected)
    est = Group(data={"a": Group(attrs={"theta": 15.0, "error_poles": expected}),
                      "b": Group(attrs={"theta": 3.0, "error_poles": expected / 5})})
    note = _convergence_note(Group(data={"time": np.linspace(0, 50, 11), "estimates": est}))
    assert "a (theta 15): slowest error pole 0.145 /s" in note and "1 % of an initial error after 31.7 s, within the 50 s run" in note
    assert "b (theta 3): slowest error pole 0.0291 /s" in note and "not within the 50 s run" in note
    caption = evaluate_results(tmp_path / "e.h5", tables=["x_pitch_roll_error"])["x_pitch_roll_error"].attrs["caption"]
    assert "Convergence of the linear error dynamics: high_gain (theta 15)" in caption


def test_seed001_caption_says_what_the_radius_reading_does_not_reproduce(tmp_path):
    cfg, text = load_config(CONFIGS / "so3-invariant/helix.yaml", overrides=[
        "runs.count=1", "stop.depth=225", "inputs.u={kind: cases, labels: [omega = pi/32], cases: [0.0981748]}",
        "observers=[{name: from90, type: so3_invariant, gain: 0.65, init: {error_deg: 90.0, axis: measured}}]"])
    assert cfg.model.params.kappa == 0.028571  # the 3.5 cm helix radius
    run_experiment(cfg, text, out=tmp_path / "h.h5")
    tables = evaluate_results(tmp_path / "h.h5", tables=["rotation_convergence", "rotation_half_turns"])
    for df in tables.values():
        c = df.attrs["caption"]
        assert "about 7 cm of insertion for an adequate estimate from 90 deg" in c
        assert "Here (arc radius 35.0 mm): from90, omega = pi/32: E_R 90 deg at 0, 55 deg at 70 mm, 31 deg after " \
               "one half turn (110 mm), 82 % less over the second: the SO(3) observer paper's about 7 cm from 90 deg is not " \
               "reproduced (under 10 deg from 183 mm)" in c
    alt = yaml.safe_load((CONFIGS / "so3-invariant/helix_kappa35.yaml").read_text())
    assert alt["model"]["params"]["kappa"] == 0.35
    assert "alternative reading" in (CONFIGS / "so3-invariant/helix_kappa35.yaml").read_text()
