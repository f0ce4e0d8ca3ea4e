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
    data = yaml.safe_load((ROOT / "configs" / "seed004" / "study.yaml").read_text())
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
