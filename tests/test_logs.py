"""Log files: format round trip, replay, CSV import, the bad-log corpus, regression baselines."""

from __future__ import annotations

from pathlib import Path

import h5py
import numpy as np
import pytest
import yaml
from typer.testing import CliRunner

from needlecli.cli.app import app
from needlecli.experiments.config.load import load_config
from needlecli.experiments.simulation.runner import run_experiment
from needlecli.io.logs import log_from_results, read_log, write_log
from needlecli.io.results import read_results

ROOT = Path(__file__).resolve().parents[1]
CORPUS = Path(__file__).parent / "bad_logs"
EXPECT = yaml.safe_load((CORPUS / "expect.yaml").read_text())
runner = CliRunner()

REPLAY = """
name: replay_test
source: {{logs: [{log}]}}
model: {{type: unicycle, params: {{kappa: 0.002}}}}
observers:
  - {{name: ol, type: open_loop}}
simulation: {{dt: 0.1}}
"""


def run(*args):
    return runner.invoke(app, [str(a) for a in args])


def error_lines(result) -> list[str]:
    return [ln for ln in result.output.splitlines() if ln.startswith("error:")]


def test_corpus_is_large_enough():
    assert len(EXPECT) >= 20


@pytest.mark.parametrize("name", sorted(EXPECT))
def test_bad_log_gets_one_clear_error(name, tmp_path):
    case = EXPECT[name]
    out = tmp_path / "out" / "x.h5"
    if case["command"] == "replay":
        cfg = tmp_path / "replay.yaml"
        cfg.write_text(REPLAY.format(log=CORPUS / name))
        res = run("simulate", cfg, "--out", out, "--quiet")
    else:
        res = run("log", "import-csv", CORPUS / name, "--out", out)
    assert res.exit_code == 2, res.output
    lines = error_lines(res)
    assert len(lines) == 1, res.output
    assert "Traceback" not in res.output
    assert case["expect"] in lines[0], lines[0]
    assert Path(name).parts[0] in lines[0]  # names the file (or its folder)
    assert not out.exists()
    assert not list((tmp_path / "out").glob("*")) if (tmp_path / "out").exists() else True


def test_good_log_replays_and_evaluates(tmp_path):
    cfg = tmp_path / "replay.yaml"
    cfg.write_text(REPLAY.format(log=CORPUS / "good.h5"))
    out = tmp_path / "r.h5"
    res = run("simulate", cfg, "--out", out, "--quiet")
    assert res.exit_code == 0, res.output
    r = read_results(out)
    assert r.attrs["source"] == "replay"
    assert list(r.data["truth"].data["trial_id"]) == ["t1"]
    assert r.data["measurements"].data["us"].data["value"].shape == (1, 40, 3)
    e = r.data["estimates"].data["ol"].data["state"]
    s = 2.0 * 3.9  # 2 mm/s for 3.9 s, the input held between samples; z of an arc of curvature 0.002
    assert np.isclose(e[0, -1, 2], np.sin(0.002 * s) / 0.002, atol=1e-9)


@pytest.fixture(scope="module")
def simulated(tmp_path_factory):
    d = tmp_path_factory.mktemp("sim")
    cfg, text = load_config(ROOT / "configs/multirate-ukf-us3d/table1.yaml", overrides=["stop.depth=8", "runs.count=3"])
    r = run_experiment(cfg, text, out=d / "sim.h5")
    return cfg, text, r, d


def test_log_round_trip_identical_arrays(simulated, tmp_path):
    _, _, r, d = simulated
    log = log_from_results(read_results(r.path))
    write_log(tmp_path / "log.h5", log)
    back = read_log(tmp_path / "log.h5")
    assert [t.id for t in back.trials] == [t.id for t in log.trials]
    for a, b in zip(log.trials, back.trials):
        for name in a.sensors:
            np.testing.assert_array_equal(a.sensors[name].t, b.sensors[name].t)
            np.testing.assert_array_equal(a.sensors[name].value, b.sensors[name].value)
            np.testing.assert_array_equal(a.sensors[name].valid, b.sensors[name].valid)
            assert a.sensors[name].settings == b.sensors[name].settings
        for name in a.inputs:
            np.testing.assert_array_equal(a.inputs[name].value, b.inputs[name].value)
        np.testing.assert_array_equal(a.truth.state, b.truth.state)
    assert back.attrs["synthetic"]
    assert "pose_curvature_error" in back.attrs["config"]


def test_replay_of_own_streams_gives_the_same_estimates(simulated, tmp_path):
    cfg, text, r, d = simulated
    write_log(tmp_path / "log.h5", log_from_results(read_results(r.path)))
    data = yaml.safe_load(text)
    for k in ("inputs", "sensors", "stop", "process_noise", "tissue"):
        data.pop(k, None)
    data["source"] = {"logs": [str(tmp_path / "log.h5")]}
    cfg2, text2 = load_config(text=yaml.safe_dump(data, sort_keys=False))
    r2 = run_experiment(cfg2, text2, write=False)
    np.testing.assert_array_equal(r.estimates["ukf"].state, r2.estimates["ukf"].state)
    np.testing.assert_array_equal(r.truth.states, r2.truth.states)
    for name in r.measurements:
        np.testing.assert_array_equal(r.measurements[name].valid, r2.measurements[name].valid)


def test_replay_without_truth_says_what_it_cannot_compute(tmp_path):
    src = CORPUS / "good.h5"
    log = tmp_path / "notruth.h5"
    log.write_bytes(src.read_bytes())
    with h5py.File(log, "r+") as f:
        del f["trials/t1/truth"]
    cfg = tmp_path / "replay.yaml"
    cfg.write_text(REPLAY.format(log=log))
    res = run("simulate", cfg, "--out", tmp_path / "r.h5", "--quiet")
    assert res.exit_code == 0, res.output
    assert "not computable (the logs have no ground truth)" in res.output


def test_csv_import_converts_units_and_counts_missing_samples(tmp_path):
    d = tmp_path / "exports" / "trial1"
    d.mkdir(parents=True)
    (d / "robot.csv").write_text("time,speed,rot\n0,0.002,0\n1000,0.002,90\n2000,0.002,0\n")
    (d / "us.csv").write_text("time,tx,ty,tz,ok\n0,0.001,0,0,1\n1000,0.001,,0.002,1\n2000,0.0,0.0,0.004,0\n")
    (d / "em.csv").write_text("time,px,py,pz\n0,0,0,0\n500,0,0,0.001\n1000,0,0,0.002\n")
    mapping = {
        "description": "test export",
        "time_column": "time",
        "time_unit": "ms",
        "trials": [{"id": "trial1", "dir": "exports/trial1", "meta": {"medium": "agar"}}],
        "inputs": {"v": {"file": "robot.csv", "column": "speed", "unit": "m/s"},
                   "u": {"file": "robot.csv", "column": "rot", "unit": "deg/s", "kind": "measured"}},
        "sensors": {"us": {"file": "us.csv", "columns": {"x": "tx", "y": "ty", "z": "tz"}, "units": ["m", "m", "m"],
                           "valid_column": "ok", "sensor": {"type": "position", "rate": 1.0, "sigma": 0.3}}},
        "truth": {"file": "em.csv", "columns": {"x": "px", "y": "py", "z": "pz"}, "units": ["m", "m", "m"]},
    }
    mp = tmp_path / "mapping.yaml"
    mp.write_text(yaml.safe_dump(mapping))
    res = run("log", "import-csv", mp, "--out", tmp_path / "log.h5")
    assert res.exit_code == 0, res.output
    log = read_log(tmp_path / "log.h5")
    tr = log.trials[0]
    np.testing.assert_allclose(tr.inputs["v"].value[:, 0], 2.0)  # m/s -> mm/s
    np.testing.assert_allclose(tr.inputs["u"].value[1, 0], np.pi / 2)  # deg/s -> rad/s
    np.testing.assert_allclose(tr.sensors["us"].t, [0.0, 1.0, 2.0])  # ms -> s
    np.testing.assert_allclose(tr.sensors["us"].value[0], [1.0, 0.0, 0.0])  # m -> mm
    assert tr.sensors["us"].valid.tolist() == [True, False, False]  # a missing value, then ok = 0
    assert tr.meta["us_missing_values"] == 1 and tr.meta["medium"] == "agar"
    np.testing.assert_allclose(tr.truth.state[:, 2], [0.0, 1.0, 2.0])


def test_regression_baseline_holds_and_a_tightened_one_fails(tmp_path):
    out = tmp_path / "r.h5"
    res = run("simulate", ROOT / "configs/replay/em-magnetic-pratt2022_like.yaml", "--out", out, "--quiet")
    assert res.exit_code == 0, res.output
    base = ROOT / "datasets/baselines/em-magnetic-pratt2022_like.yaml"
    res = run("evaluate", out, "--out", tmp_path / "t", "--no-plots", "--quiet", "--baseline", base)
    assert res.exit_code == 0, res.output
    data = yaml.safe_load(base.read_text())
    cell = next(c for c in data["cells"] if c["column"] == "Mean")
    cell["value"] = cell["value"] * 0.5  # tightened below what the code achieves
    tight = tmp_path / "tight.yaml"
    tight.write_text(yaml.safe_dump(data))
    res = run("evaluate", out, "--out", tmp_path / "t", "--no-plots", "--quiet", "--baseline", tight)
    assert res.exit_code == 1
    assert "REGRESSION: 1 of" in res.output
    assert "outside the tolerance" in res.output and cell["table"] in res.output


def test_polynomial_reference_agrees_with_the_logged_truth():
    """The high-gain observer paper's reference (polynomials fitted to the 2D ultrasound) against the synthetic set's own
    ground truth: the fit recovers x within 0.03 mm and beta within 0.005 rad on average."""
    cfg, text = load_config(ROOT / "configs/replay/highgain-us2d_like_polynomial.yaml")
    poly = run_experiment(cfg, text, write=False, base_dir=ROOT / "configs/replay").truth
    cfg2, text2 = load_config(ROOT / "configs/replay/highgain-us2d_like.yaml", overrides=["observers=[]"])
    true = run_experiment(cfg2, text2, write=False, base_dir=ROOT / "configs/replay").truth
    assert poly.truth_kind.startswith("polynomial fit of us2d")
    for name, tol in (("x", 0.03), ("beta", 0.005)):
        i = poly.model.index(name)
        both = np.isfinite(poly.states[..., i]) & np.isfinite(true.states[..., i])
        assert both.sum() > 1000
        assert np.mean(np.abs(poly.states[..., i] - true.states[..., i])[both]) < tol
    assert np.isnan(poly.states[..., poly.model.index("z")]).all()  # the fit gives no z: not invented
