"""``needle compare``: every applicable observer on the same simulated (or replayed) insertions, the table in
the form of the multi-rate UKF paper's appendix A, skipped observers with their reasons."""

from __future__ import annotations

from pathlib import Path

import h5py
import numpy as np
import pandas as pd
import pytest
from typer.testing import CliRunner

from needlecli.cli.app import app
from needlecli.experiments.config.load import load_config
from needlecli.experiments.simulation.runner import build_sensors
from needlecli.experiments.studies.compare import candidates, compare_observers
from needlecli.io.results import read_results
from needlecli.metrics import compute_errors
from needlecli.models import MODELS
from needlecli.observers import OBSERVERS
from needlecli.observers.defaults import ComparisonContext, direct_components
from needlecli.reports.compare import compare_table

# the multi-rate UKF paper's Table 1 set-up, tiny: 3 insertions of 15 mm, no observers (every one comes from defaults)
TINY003 = """\
name: tiny003
model: {type: modified_unicycle, params: {kappa: 0.005, beta_cut: 0.035}, param_std: {kappa: 0.001}}
inputs: {v: 1.5, u: 0.0}
process_noise: {std: {x: 0.02, y: 0.02, z: 0.02, alpha: 2.0e-4, beta: 2.0e-4, gamma: 5.0e-3}}
sensors:
  - {name: us3d, type: position, rate: 2.0, sigma: 0.3, growth: {transducer: [0.0, 0.0, 90.0], a: 1.0, d_max: 80.0}}
  - {name: robot, type: encoder, rate: 50.0, channels: [roll], sigma: 0.0035}
  - {name: swe, type: elastography, rate: 1.0, sigma: 0.001}
runs: {count: 3, seed: 3}
stop: {depth: 15.0}
simulation: {dt: 0.02}
output: {store_every: 10, covariance: diag}
"""


def invoke(*args):
    return CliRunner().invoke(app, [str(a) for a in args])


def table(result) -> pd.DataFrame:
    """The comparison's table, from its results file alone (as needle compare prints it)."""
    res = read_results(result.path)
    return compare_table(res, compute_errors(res))


@pytest.fixture(scope="module")
def tiny(tmp_path_factory) -> Path:
    d = tmp_path_factory.mktemp("compare")
    (d / "tiny.yaml").write_text(TINY003)
    return d / "tiny.yaml"


def test_compare_prints_the_appendix_table_with_ukf_and_open_loop(tiny, tmp_path):
    r = invoke("compare", tiny, "--out", tmp_path, "--quiet")
    assert r.exit_code == 0, r.output
    md = (tmp_path / "compare.md").read_text()
    header = next(line for line in md.splitlines() if line.startswith("|"))
    assert "ukf" in header and "open_loop" in header
    for row in ("Sensor frequency", "Online curvature estimation", "E_xyz (mm)", "E_x (mm)", "E_gamma (deg)",
                "E_kappa (1/mm)", "Prediction error* (mm)", "Runtime per step", "Runs that failed",
                "Number of insertions", "Start"):
        assert f"| {row}" in md
    assert "1 Hz" in r.output and "50 Hz" in r.output and "2 Hz" in r.output
    assert "skipped: so3_invariant" in r.output and "tangent sensor" in r.output  # no tangent sensor here
    df = pd.read_csv(tmp_path / "compare.csv").set_index("observer")
    assert df.loc["ukf", "online_curvature"] == "yes"
    assert df.loc["open_loop", "online_curvature"].startswith("no")
    assert df.loc["ukf", "pred_depth"] == pytest.approx(3.75)  # 25 % of 15 mm
    assert np.isfinite(df.loc["ukf", "pred_mean_mm"]) and np.isnan(df.loc["open_loop", "pred_mean_mm"])
    assert (df["runs"] == 3).all() and (df["runs_failed"] == 0).all() and (df["ms_per_step"] > 0).all()
    # the UKF beats the open loop on the same insertions
    assert df.loc["ukf", "E_xyz_mean"] < df.loc["open_loop", "E_xyz_mean"]
    assert (tmp_path / "compare_error_vs_depth.png").exists() and "plots:" in r.output
    # the same quantities for every observer: the high-gain observer's pitch and roll beside the others',
    # n/a (NaN) where it does not estimate a state
    errs = [c for c in df.columns if c.startswith("E_")]
    for q in ("E_xyz", "E_x", "E_y", "E_z", "E_alpha", "E_beta", "E_gamma", "E_R", "E_kappa"):
        assert f"{q}_mean" in errs and f"{q}_std" in errs
    assert df.loc[["ukf", "ekf", "eks", "open_loop"], errs].notna().all().all()
    hg = df.loc["high_gain"]
    assert np.isfinite(hg[["E_x_mean", "E_beta_mean", "E_gamma_mean"]].astype(float)).all()
    assert np.isnan(hg[["E_xyz_mean", "E_y_mean", "E_alpha_mean", "E_kappa_mean"]].astype(float)).all()
    res = read_results(tmp_path / "tiny003_compare.h5")  # E_x by hand: |x_hat - x| after initialisation
    t_names = list(res.data["truth"].attrs["names"])
    for name in ("high_gain", "ukf"):
        g = res.data["estimates"].data[name]
        e = np.abs(g.data["state"][:, 1:, list(g.attrs["names"]).index("x")]
                   - res.data["truth"].data["state"][:, 1:, t_names.index("x")])
        assert df.loc[name, "E_x_mean"] == pytest.approx(e.mean(), rel=1e-12)
        assert df.loc[name, "E_x_std"] == pytest.approx(e.std(), rel=1e-12)
    head = next(ln for ln in r.output.splitlines() if ln.startswith("| mean error"))  # one column per observer
    assert all(o in head for o in df.index)
    assert any(ln.startswith("| E_gamma (deg)") for ln in r.output.splitlines())
    assert "Skipped:" in (tmp_path / "compare.md").read_text()
    assert (tmp_path / "tiny003_compare.h5").exists()
    r = invoke("evaluate", tmp_path / "tiny003_compare.h5", "--out", tmp_path / "ev", "--no-plots", "--quiet")
    assert r.exit_code == 0, r.output
    # the tables are the results file's: needle evaluate gives the same ones, to the runtime
    r = invoke("evaluate", tmp_path / "tiny003_compare.h5", "--tables", "compare,compare_appendix", "--out",
               tmp_path / "ev2", "--format", "csv", "--no-plots", "--quiet")
    assert r.exit_code == 0, r.output
    pd.testing.assert_frame_equal(pd.read_csv(tmp_path / "ev2" / "tiny003_compare.csv"),
                                  pd.read_csv(tmp_path / "compare.csv"))
    wide = pd.read_csv(tmp_path / "ev2" / "tiny003_compare_appendix.csv")
    assert list(wide.columns[1:]) == list(df.index) and "Start" in set(wide.iloc[:, 0])
    with h5py.File(tmp_path / "tiny003_compare.h5") as f:  # what the comparison decided, for the tables
        g = f["compare"]
        assert list(g["observer"].asstr()[()]) == list(df.index)
        assert dict(zip(g["skipped/observer"].asstr()[()], g["skipped/reason"].asstr()[()]))["so3_invariant"].endswith(
            "the SO(3) observer needs a tangent sensor; there is none")
        assert "initial estimate" in g.attrs["start"] and list(g.attrs["sensors"]) == ["us3d", "robot", "swe"]


def test_compare_tables_of_another_results_file_are_empty(tiny, tmp_path):
    r = invoke("simulate", tiny, "--out", tmp_path / "sim.h5", "--quiet")
    assert r.exit_code == 0, r.output
    res = read_results(tmp_path / "sim.h5")
    assert compare_table(res, compute_errors(res)).empty


def test_same_insertions_for_every_observer_and_config_settings_kept(tiny, tmp_path):
    text = tiny.read_text() + """observers:
  - name: my_ukf
    type: ukf
    q: {x: 2.0e-3, y: 2.0e-3, z: 2.0e-3, alpha: 2.0e-5, beta: 2.0e-5, gamma: 5.0e-4, kappa: 2.0e-6}
    p0: {x: 1.0, y: 1.0, z: 1.0, alpha: 5.0e-3, beta: 5.0e-3, gamma: 0.1, kappa: 2.0e-6}
    init: {from: truth, std: {alpha: 0.0873, beta: 0.0873}, first_measurement: {x: us3d.x, y: us3d.y, z: us3d.z}}
    predict_at_depths: [3.0]
"""
    cfg_path = tmp_path / "own.yaml"
    cfg_path.write_text(text)
    res = compare_observers(cfg_path, observers=["my_ukf", "open_loop"], out_dir=tmp_path / "o")
    df = table(res).set_index("observer")
    assert list(df.index) == ["my_ukf", "open_loop"]
    assert df.loc["my_ukf", "settings"] == "config" and df.loc["open_loop", "settings"] == "defaults"
    assert res.cfg.observers[0].predict_at_depths == [3.0, 3.75]  # 25 % added to its own depths
    f = read_results(res.path)
    assert set(f.data["estimates"].data) == {"my_ukf", "open_loop"}
    # the same truth as a plain simulation of the config: simulated once, shared by the observers
    plain, _ = load_config(cfg_path)
    from needlecli.experiments.simulation.runner import run_experiment

    ref = run_experiment(plain, text, write=False)
    np.testing.assert_array_equal(f.data["truth"].data["state"], ref.truth.states)
    np.testing.assert_array_equal(f.data["estimates"].data["my_ukf"].data["state"][:, :1],
                                  ref.estimates["my_ukf"].state[:, :1])


def test_ukf_defaults_from_the_sensors(tiny):
    cfg, _ = load_config(tiny)
    model = MODELS.get(cfg.model.type)(cfg.model.params)
    sensors = {s.name: s for s in build_sensors(cfg, model)}
    assert direct_components(sensors["us3d"], model) == {"x": (0, "x"), "y": (1, "y"), "z": (2, "z")}
    assert direct_components(sensors["robot"], model) == {"gamma": (0, "roll")}
    assert direct_components(sensors["swe"], model) == {"kappa": (0, "kappa")}
    ctx = ComparisonContext(model=model, sensors=sensors, replay=False, final_depth=15.0, dt=0.02,
                            process_std=cfg.process_noise.std, param_std=cfg.model.param_std)
    s = OBSERVERS.get("ukf").derived_settings(ctx)
    assert s["measurements"]["us3d"]["sigma"] == 0.3 and s["measurements"]["us3d"]["growth"]["a"] == 1.0
    assert s["init"]["first_measurement"] == {"x": "us3d.x", "y": "us3d.y", "z": "us3d.z", "gamma": "robot.roll",
                                              "kappa": "swe.kappa"}
    assert s["init"]["std"] == {"alpha": 0.0873, "beta": 0.0873}
    assert s["p0"]["x"] == pytest.approx((2 * 0.3) ** 2) and s["p0"]["kappa"] == pytest.approx(1e-6)
    assert s["q"]["x"] == pytest.approx(0.02)  # the truth's process noise, per square-root second as every q
    assert s["predict_at_depths"] == [3.75]
    OBSERVERS.get("ukf").Settings.model_validate({"type": "ukf", **s})
    # without a sensor with a nominal sigma that the model predicts, the UKF is skipped with the reason
    bare = ComparisonContext(model=model, sensors={}, replay=False, final_depth=15.0, dt=0.02)
    cands = {c.type: c for c in candidates(bare, [], None)}
    assert "no sensor" in cands["ukf"].skip and not cands["open_loop"].skip


def test_compare_replays_a_log_with_the_model_given(tiny, tmp_path):
    r = invoke("simulate", tiny, "--out", tmp_path / "sim.h5", "--quiet")
    assert r.exit_code == 0, r.output
    r = invoke("log", "from-results", tmp_path / "sim.h5", "--out", tmp_path / "tiny.log.h5", "--truth-every", "5")
    assert r.exit_code == 0, r.output
    r = invoke("compare", tmp_path / "tiny.log.h5", "--quiet")
    assert r.exit_code == 2 and "needs --model" in r.output
    r = invoke("compare", tmp_path / "tiny.log.h5", "--model", "modified_unicycle", "--runs", "2",
               "--observers", "ukf,open_loop", "--out", tmp_path / "rp", "--quiet")
    assert r.exit_code == 0, r.output
    df = pd.read_csv(tmp_path / "rp" / "compare.csv").set_index("observer")
    assert set(df.index) == {"ukf", "open_loop"} and (df["runs"] == 2).all()
    assert np.isfinite(df.loc["ukf", "E_xyz_mean"])  # against the logged truth
    from needlecli.io.logs import read_log

    res = read_results(next((tmp_path / "rp").glob("*_compare.h5")))  # --runs: the log's first trials
    assert [str(t) for t in res.data["truth"].data["trial_id"]] == [t.id for t in read_log(tmp_path / "tiny.log.h5").trials][:2]
    # the replay's filters are derived from what the log records: the sensors' sigmas, the truth's start
    import yaml

    ukf = next(o for o in yaml.safe_load(res.attrs["config"])["observers"] if o["name"] == "ukf")
    assert ukf["measurements"]["us3d"]["sigma"] == 0.3 and ukf["init"]["from"] == "truth"


@pytest.mark.parametrize("args, message", [
    (["--observers", "kalman"], "unknown observer 'kalman'"),
    (["--model", "unicycle"], "--model is for log files"),
    (["--set", "runs.count=0"], "[runs -> count]"),
])
def test_compare_user_errors(tiny, tmp_path, args, message):
    r = invoke("compare", tiny, "--out", tmp_path, "--quiet", *args)
    assert r.exit_code == 2 and message in r.output, r.output
    assert "Traceback" not in r.output


OWN_UKF = """observers:
  - name: my_ukf
    type: ukf
    q: {x: 2.0e-3, y: 2.0e-3, z: 2.0e-3, alpha: 2.0e-5, beta: 2.0e-5, gamma: 5.0e-4, kappa: 2.0e-6}
    p0: {x: 1.0, y: 1.0, z: 1.0, alpha: 5.0e-3, beta: 5.0e-3, gamma: 0.1, kappa: 2.0e-6}
    init: {from: truth, std: {alpha: 0.0873, beta: 0.0873}, first_measurement: {x: us3d.x, y: us3d.y, z: us3d.z, gamma: robot.roll, kappa: swe.kappa}}
"""


def test_no_observer_starts_better_informed_than_the_reference(tiny, tmp_path):
    """Every observer starts from the reference's initial estimate (the same draw): the open loop's
    start is the UKF's to the bit, and no observer's curvature starts at the run's truth."""
    cfg_path = tmp_path / "fair.yaml"
    cfg_path.write_text(tiny.read_text() + OWN_UKF)
    res = compare_observers(cfg_path, out_dir=tmp_path / "o")
    f = read_results(res.path)
    est = f.data["estimates"].data
    ukf0 = est["my_ukf"].data["state"][:, 0]
    np.testing.assert_array_equal(est["open_loop"].data["state"][:, 0], ukf0)
    truth = f.data["truth"].data["state"]
    k = list(f.data["truth"].attrs["names"]).index("kappa")
    for name in ("ekf", "eks", "open_loop"):
        names = list(est[name].attrs["names"])
        err0 = np.abs(est[name].data["state"][:, 0, names.index("kappa")] - truth[:, 0, k])
        assert err0.min() > 1e-6, (name, err0)  # not the run's own truth
    df = table(res).set_index("observer")
    assert df.loc["my_ukf", "start"] == "common (reference)"
    assert (df.drop(index="my_ukf")["start"].str.startswith("common")).all()
    assert df.loc["high_gain", "start"] == "common; x, beta = 0"  # the high-gain observer paper's prescribed start on top
    assert not df.loc["eks", "causal"] and df.loc["ekf", "causal"]
    assert "my_ukf's initial estimate" in res.start and "EXACT TRUTH" not in res.start


def test_the_common_start_is_what_each_observer_starts_from(tiny, tmp_path):
    """The mechanism, observer by observer: with a common start in the problem, the initial mean and
    covariance each observer builds are the start's, whatever its own init says."""
    import dataclasses

    from needlecli.experiments.simulation.runner import build_problem, simulate_and_measure
    from needlecli.experiments.simulation.truth import stream
    from needlecli.initial import initial_covariance, initial_mean

    cfg_path = tmp_path / "fair.yaml"
    cfg_path.write_text(tiny.read_text() + OWN_UKF)
    cfg, _ = load_config(cfg_path)
    truth, sensors, streams, _ = simulate_and_measure(cfg)
    problem = build_problem(cfg, truth, sensors, streams)
    ukf = OBSERVERS.get("ukf")
    start = ukf.initial_estimate(cfg.observers[0], problem, stream(cfg.runs.seed, "observer/my_ukf"))
    shared = dataclasses.replace(problem, start=start)
    model = truth.model
    for init in ({}, {"from": "nominal", "values": {"kappa": 0.1}}, {"std": {"x": 5.0}}):
        s = OBSERVERS.get("open_loop").Settings.model_validate({"type": "open_loop", "init": init})
        x = initial_mean(s.init, shared, model, model.param_arrays(), np.random.default_rng(9))
        np.testing.assert_array_equal(x, start.mean)
        P = initial_covariance(s.init, model.state_names, {"x": 7.0}, 1e-12, start=start)
        np.testing.assert_array_equal(P, start.cov)
    # without it, the UKF's own init gives the same numbers (the reference is unchanged by the mechanism)
    own = initial_mean(cfg.observers[0].init, problem, model, model.param_arrays(), stream(cfg.runs.seed, "observer/my_ukf"))
    np.testing.assert_array_equal(own, start.mean)


def test_compare_table_fits_80_columns_and_names_results_once(tiny, tmp_path):
    r = invoke("compare", tiny, "--out", tmp_path, "--quiet")
    assert r.exit_code == 0, r.output
    lines = r.output.splitlines()
    long = [ln for ln in lines if len(ln) > 80 and not ln.startswith(("table:", "results:", "plots:", "compare: "))]
    assert not long, long
    assert sum(ln.startswith("results:") for ln in lines) == 1
    assert any(ln.startswith("| observer") and "start" in ln for ln in lines)


def test_a_filter_worse_than_the_model_alone_is_warned_about(tiny, tmp_path):
    """A filter that does worse than the open loop from the same start: a warning in the output and in the
    table's notes (here a UKF held straight by a curvature bound, without the position it could correct)."""
    cfg_path = tmp_path / "bad.yaml"
    cfg_path.write_text(tiny.read_text() + """observers:
  - name: straight
    type: ukf
    measurements: {robot: {sigma: 0.0035}}
    kappa_max: 1.0e-7
    init: {from: truth, std: {alpha: 0.0873, beta: 0.0873}, values: {kappa: 0.0}, first_measurement: {x: us3d.x, y: us3d.y, z: us3d.z}}
""")
    r = invoke("compare", cfg_path, "--observers", "straight,ekf,open_loop", "--out", tmp_path / "o")  # (--quiet
    assert r.exit_code == 0, r.output                                                         # silences warnings)
    df = pd.read_csv(tmp_path / "o" / "compare.csv").set_index("observer")
    assert df.loc["straight", "E_xyz_mean"] > df.loc["open_loop", "E_xyz_mean"] > df.loc["ekf", "E_xyz_mean"]
    said = " ".join(r.output.split())  # (the log's warning, on stderr)
    assert "compare: straight does worse than open_loop, the model alone from the same start (E_xyz" in said
    assert "ekf does worse" not in said
    md = (tmp_path / "o" / "compare.md").read_text()
    assert "Warning:\n- straight does worse than open_loop" in md


def test_worse_than_model_compares_like_with_like():
    """Only observers from the common start against a model-only one from it; the tip norm where both have
    it, else the axes the observer has (the high-gain observer (`highgain-us2d`): E_x)."""
    from needlecli.reports.compare import worse_than_model

    nan = float("nan")
    df = pd.DataFrame({
        "observer": ["ol", "kf", "hg", "own", "good"], "model_only": [True, False, False, False, False],
        "start": ["common", "common (reference)", "common; x, beta = 0", "own settings", "common"],
        "E_xyz_mean": [1.0, 2.0, nan, 3.0, 0.5], "E_x_mean": [0.5, 0.1, 0.6, 3.0, 0.1],
    })
    warn = worse_than_model(df)
    assert [w.split()[0] for w in warn] == ["kf", "hg"]
    assert "E_xyz 2 against 1 mm" in warn[0] and "E_x 0.6 against 0.5 mm" in warn[1]
    assert worse_than_model(df.assign(start="own settings")) == []
