"""needle crossval: folds as asked (groups kept together, leave-one-out within a group), and on a simulated
study whose hand-tuned model has the wrong constant, the EM-tuned copy, fitted on the other trials only,
tracks the held-out trials better and recovers the constant."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import yaml
from typer.testing import CliRunner

from needlecli.cli.app import app
from needlecli.errors import ConfigError
from needlecli.experiments.studies.crossval import group_of, make_folds
from needlecli.reports.crossval import crossval_tables

ROOT = Path(__file__).resolve().parents[1]


def test_folds_keep_groups_together_and_leave_one_out_within_a_group():
    ids = ["d1-a", "d1-b", "d1-c", "d2-a", "d2-b", "d3-a"]
    groups = [group_of(t, {}, "id~^[^-]+") for t in ids]
    assert groups == ["d1", "d1", "d1", "d2", "d2", "d3"]
    folds = make_folds(ids, groups, k=2, leave_one_out=False, within=False)
    assert [f.test for f in folds] == [["d1-a", "d1-b", "d1-c", "d3-a"], ["d2-a", "d2-b"]]
    assert all(not set(f.test) & set(f.train) for f in folds)
    loo = make_folds(ids[:5], groups[:5], k=None, leave_one_out=True, within=True)
    assert loo[0].test == ["d1-a"] and loo[0].train == ["d1-b", "d1-c"] and loo[3].train == ["d2-b"]
    with pytest.raises(ConfigError, match="alone in its group"):  # d3 has one trial
        make_folds(ids + ["d4-a"], groups + ["d4"], k=None, leave_one_out=True, within=True)
    with pytest.raises(ConfigError, match="give --folds 3 or fewer"):
        make_folds(ids, groups, k=4, leave_one_out=False, within=False)


def test_crossval_tunes_a_wrong_constant_on_held_out_trials(tmp_path, monkeypatch):
    data = yaml.safe_load((ROOT / "configs" / "em-magnetic-pratt2022" / "study.yaml").read_text())
    data["model"].pop("param_cases")
    data["runs"]["count"] = 4
    data["stop"]["time"] = 12.0
    data["fit"]["models"] = ["mnm"]
    data["fit"]["p0"].pop("l_inv")
    data["fit"]["init"]["values"].pop("l_inv")
    data["fit"]["em"]["max_iter"] = 60
    # hand-tuned: the open-loop model with c far off (5 against the true 9.5); both start at the true start
    data["observers"] = [{"name": "model", "type": "open_loop", "params": {"c": 5.0}}]
    cfg = tmp_path / "study.yaml"
    cfg.write_text(yaml.safe_dump(data, sort_keys=False))
    out = tmp_path / "cv"
    monkeypatch.chdir(tmp_path)  # a relative --out (the folds' configs live elsewhere than the fit files' paths)
    r = CliRunner().invoke(app, ["crossval", str(cfg), "--observer", "model", "--folds", "2", "--out", "cv", "--quiet"])
    assert r.exit_code == 0, r.output
    s = pd.read_csv(out / "crossval_summary.csv").set_index("Observer")
    assert set(s.index) == {"model", "model_em"} and (s["Held-out trials"] == 4).all()  # 2 folds of 2
    assert s.loc["model_em", "E_xyz mean [mm]"] < 0.65 * s.loc["model", "E_xyz mean [mm]"]
    assert s.loc["model_em", "E_xyz final mean [mm]"] < 0.5 * s.loc["model", "E_xyz final mean [mm]"]
    c = pd.read_csv(out / "crossval_constants.csv")
    assert len(c) == 2 and np.all(np.abs(c["Median"] - 9.5) < 3 * c["SE (pooled)"] + 1.0)
    for k in range(2):  # the fits saw only their training trials
        fit = yaml.safe_load((out / "folds" / f"fold{k}_train.yaml").read_text())
        held = yaml.safe_load((out / "folds" / f"fold{k}.yaml").read_text()) if (out / "folds" / f"fold{k}.yaml").exists() else None
        assert held is None or not set(fit["source"]["trials"]) & set(held["source"]["trials"])
    assert (out / "crossval_by_depth.md").exists() and (out / "folds" / "fold0.h5").exists()
    # the tables are those of the folds' results files: each says which trials it held out and what its fit gave
    tables = crossval_tables([out / "folds" / f"fold{k}.h5" for k in range(2)])
    pd.testing.assert_frame_equal(tables["constants"], c, check_exact=False, rtol=1e-9)
    pd.testing.assert_frame_equal(tables["summary"].set_index("Observer"), s, check_exact=False, rtol=1e-9)
    import h5py

    with h5py.File(out / "folds" / "fold1.h5") as f:
        g = f["crossval"]
        assert int(g.attrs["fold"]) == 1 and list(g.attrs["tuned"]) == ["model_em"]
        assert not set(g.attrs["train"]) & set(g.attrs["test"]) and len(g.attrs["test"]) == 2
        assert list(g["constants/name"].asstr()[()]) == ["c"]
    assert (out / "crossval_by_depth.png").stat().st_size > 10_000
    # each fold takes its training trials' fits from one EM over all of them: the same as fitting the fold
    r = CliRunner().invoke(app, ["fit-em", str(out / "folds" / "fold0_train.yaml"), "--out", str(tmp_path / "direct.h5"),
                                 "--quiet"])
    assert r.exit_code == 0, r.output
    import h5py

    with h5py.File(out / "folds" / "fold0_fit.h5") as a, h5py.File(tmp_path / "direct.h5") as b:
        ga, gb = a["fit/mnm"], b["fit/mnm"]
        assert list(a["truth/trial_id"][()]) == list(b["truth/trial_id"][()])  # the fold's trials, in order
        np.testing.assert_allclose(ga["constant/c"][()], gb["constant/c"][()], rtol=2e-3)
        np.testing.assert_allclose(ga["identifiability/pooled_se"][()], gb["identifiability/pooled_se"][()], rtol=0.05)
        assert list(ga["status"][()]) == list(gb["status"][()])


def test_crossval_user_errors(tmp_path):
    cfg = ROOT / "configs" / "real" / "em_tracker.yaml"
    r = CliRunner().invoke(app, ["crossval", str(ROOT / "configs" / "default.yaml"), "--observer", "ukf", "--quiet"])
    assert r.exit_code == 2 and "[fit] required key is missing" in r.output
    r = CliRunner().invoke(app, ["crossval", str(cfg), "--observer", "nope", "--quiet"])
    assert r.exit_code == 2 and ("no observer 'nope'" in r.output or "no such" in r.output or "log" in r.output)
    r = CliRunner().invoke(app, ["crossval", str(cfg), "--observer", "open_loop", "--within", "--quiet"])
    assert r.exit_code == 2 and "--within" in r.output


def test_shifted_problem_starts_each_row_at_its_own_step():
    """The problem of predictions from a pose: row b is run runs[b] from grid step starts[b] on, its
    inputs and depths shifted (held past the run's end, the inputs at zero), no measurement, the start given."""
    from needlecli.experiments.studies.crossval import shifted_problem
    from needlecli.models import MODELS
    from needlecli.problem import Channel, CommonStart, EstimationProblem

    T, N = 12, 2
    time = 0.1 * np.arange(T)
    inputs = np.stack([np.arange(T) + 100.0 * r for r in range(N)])[..., None] * np.array([1.0, -1.0])  # (N, T, 2)
    depth = np.cumsum(np.ones((N, T)), axis=1)
    ch = Channel(name="tracker", sensor_type="position", t=time[::3], t_available=time[::3], index=np.arange(0, T, 3),
                 value=np.zeros((N, 4, 3)), valid=np.ones((N, 4), dtype=bool), names=("x", "y", "z"),
                 units=("mm",) * 3, sigma=np.ones(3), angle=np.zeros(3, dtype=bool), h=None,
                 attrs={"per_run": np.array([7.0, 8.0]), "scalar": 3.0})
    model = MODELS.get("unicycle")()
    prob = EstimationProblem(time=time, inputs=inputs, input_names=("v", "u"), depth=depth, channels={"tracker": ch},
                             model=model, params=model.param_arrays(), interfaces=np.zeros(0))
    runs, starts = np.array([1, 0, 1]), np.array([4, 2, 9])
    start = CommonStart(names=("x",), mean=np.zeros((3, 1)), cov=np.zeros((1, 1)), source="test")
    sub = shifted_problem(prob, runs, starts, start)
    assert sub.n_runs == 3 and len(sub.time) == T - 2 and sub.start is start and sub.initial_truth is None
    np.testing.assert_allclose(sub.time, time[: T - 2])
    for b, (r, s) in enumerate(zip(runs, starts)):
        n = T - s
        np.testing.assert_array_equal(sub.inputs[b, :n], inputs[r, s:])
        np.testing.assert_array_equal(sub.inputs[b, n:], 0.0)
        np.testing.assert_array_equal(sub.depth[b, :n], depth[r, s:])
        np.testing.assert_array_equal(sub.depth[b, n:], depth[r, -1])
    c = sub.channels["tracker"]
    assert c.value.shape == (3, 0, 3) and c.valid.shape == (3, 0) and c.t.size == 0
    np.testing.assert_array_equal(c.attrs["per_run"], [8.0, 7.0, 8.0])
    assert c.attrs["scalar"] == 3.0


def _pose_study(tmp_path) -> Path:
    """Four noise-free insertions of the unicycle with half turns, a tracker, a fit section; the hand-tuned
    open loop has the true curvature but starts 3 deg off in each angle (a common start of its own)."""
    cfg = {
        "name": "poses",
        "model": {"type": "unicycle", "params": {"kappa": 0.01}},
        "inputs": {"v": 2.0, "u": {"kind": "flips", "at_depths": [12.0, 26.0], "rate": 3.14159}},
        "sensors": [{"name": "tracker", "type": "position", "rate": 5.0, "sigma": 0.1}],
        "observers": [{"name": "model", "type": "open_loop",
                       "init": {"from": "truth", "std": {"alpha": 0.05, "beta": 0.05, "gamma": 0.05}}}],
        "runs": {"count": 4, "seed": 5},
        "stop": {"depth": 40.0},
        "simulation": {"dt": 0.02},
        "output": {"covariance": "none"},
        "fit": {"models": ["unicycle"], "constants": ["kappa"],
                "q": {"x": 0.02, "y": 0.02, "z": 0.02, "alpha": 2.0e-3, "beta": 2.0e-3, "gamma": 2.0e-3},
                "p0": {"x": 0.05, "y": 0.05, "z": 0.05, "alpha": 1.0e-3, "beta": 1.0e-3, "gamma": 1.0e-2, "kappa": 1.0e-4},
                "measurements": {"tracker": {"sigma": 0.2}},
                "init": {"from": "nominal", "values": {"kappa": 0.008},
                         "first_measurement": {"x": "tracker.x", "y": "tracker.y", "z": "tracker.z"}},
                "em": {"max_iter": 40, "tol": 0.2}},
    }
    path = tmp_path / "poses.yaml"
    path.write_text(yaml.safe_dump(cfg, sort_keys=False))
    return path


def test_crossval_predicts_from_the_recorded_pose_and_tells_the_start_from_the_model(tmp_path):
    """Without process noise the truth is the model's own path: from the recorded (true) pose at any depth
    the open loop with the true curvature follows it exactly (inputs, depths and steps aligned), while from
    the common start, 3 deg off in each angle, it drifts; the error from the start minus the error from the
    pose at 0 is the start pose's part."""
    cfg = _pose_study(tmp_path)
    r = CliRunner().invoke(app, ["crossval", str(cfg), "--observer", "model", "--folds", "2", "--from-depths", "0,10,25",
                                 "--out", str(tmp_path / "cv"), "--quiet"])
    assert r.exit_code == 0, r.output
    t = pd.read_csv(tmp_path / "cv" / "crossval_from_pose.csv")
    assert set(t["Observer"]) == {"model", "model_em"}
    m = t[t["Observer"] == "model"].set_index("From")
    assert list(m.index) == ["common start", "recorded pose at 0 mm", "recorded pose at 10 mm", "recorded pose at 25 mm"]
    assert (m["Trials"] == 4).all()
    bins = [c for c in t.columns if c.endswith(" mm")]
    assert bins[:3] == ["0-10 mm", "10-20 mm", "20-30 mm"]
    exact = m.loc[[i for i in m.index if i.startswith("recorded")], bins].to_numpy(dtype=float)
    assert np.nanmax(exact) < 1e-6  # the model's own path, from the true pose: nothing left
    assert np.isnan(m.loc["recorded pose at 25 mm", "20-30 mm"])  # 15 mm of insertion left after 25 mm
    start = m.loc["common start", bins].to_numpy(dtype=float)
    assert start[2] > 0.3 and start[2] > start[0]  # the start's 3 deg grow into the path
    # the EM-tuned copy has its fitted curvature: from the true pose its error is the curvature's, small
    em = t[t["Observer"] == "model_em"].set_index("From")
    assert 0 < em.loc["recorded pose at 0 mm", "20-30 mm"] < 0.5 * em.loc["common start", "20-30 mm"]
    # the table is the folds' files': the same from crossval_tables, and the arrays are where the layout says
    tables = crossval_tables([tmp_path / "cv" / "folds" / f"fold{k}.h5" for k in range(2)])
    pd.testing.assert_frame_equal(tables["from_pose"].reset_index(drop=True), t, check_exact=False, rtol=1e-9,
                                  check_dtype=False)
    import h5py

    with h5py.File(tmp_path / "cv" / "folds" / "fold0.h5") as f:
        g = f["crossval/from_pose/truth"]
        assert list(g.attrs["depths"]) == [0.0, 10.0, 25.0] and g["start_index"].shape == (2, 3)
        assert g["model/state"].shape[:2] == (2, 3) and g["model/status"].shape == (2, 3)


def test_crossval_pose_options_are_checked_before_any_fit(tmp_path):
    cfg = _pose_study(tmp_path)
    for args, words in ((["--pose-from", "nobody"], "error: --pose-from: "), (["--from-depths", "0,-5"], "error: --from-depths: "),
                        (["--from-depths", "0,x"], "error: --from-depths: ")):
        r = CliRunner().invoke(app, ["crossval", str(cfg), "--observer", "model", "--folds", "2",
                                     "--out", str(tmp_path / "cv"), "--quiet", *args])
        assert r.exit_code == 2 and words in r.output and "Traceback" not in r.output, r.output
        assert not (tmp_path / "cv" / "folds" / "fold0_fit.h5").exists()


def test_the_poses_config_is_the_tracker_config_with_a_smoother():
    """configs/real/em_tracker_poses.yaml (make real-poses) fits exactly what em_tracker.yaml fits, on the same
    trials; it adds the smoother, first (its initial estimate is the folds' common start), and keeps the open loop."""
    a = yaml.safe_load((ROOT / "configs" / "real" / "em_tracker.yaml").read_text())
    b = yaml.safe_load((ROOT / "configs" / "real" / "em_tracker_poses.yaml").read_text())
    for key in ("source", "model", "fit", "runs", "simulation", "output"):
        assert a[key] == b[key], key
    assert [o["type"] for o in b["observers"]] == ["eks", "open_loop"] and b["observers"][1] == a["observers"][0]
    assert b["observers"][0]["q"] == a["fit"]["q"] and b["observers"][0]["init"]["from"] == "nominal"
