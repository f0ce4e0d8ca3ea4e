"""Fitted parameters in observers (``from_fit``): the values taken are the fit file's (checked against the
file read here), per observer type in its own units; every mistake is one error with its key path; a
simulation with a fitted EKF runs and records where its values came from."""

from __future__ import annotations

from pathlib import Path

import h5py
import numpy as np
import pytest
import yaml
from typer.testing import CliRunner

from needlecli.cli.app import app
from needlecli.errors import ConfigError
from needlecli.experiments.config.load import load_config

ROOT = Path(__file__).resolve().parents[1]


def _config(fit: Path, observer: dict) -> str:
    data = yaml.safe_load((ROOT / "configs" / "seed004" / "study.yaml").read_text())
    data.pop("fit")
    data["runs"]["count"] = 4
    data["stop"]["time"] = 3.0
    observer = dict(observer)
    ff = {"file": str(fit), "model": "mnm", **observer.pop("_ff", {})}
    data["observers"] = [{"name": "tuned", **observer, "from_fit": ff}]
    return yaml.safe_dump(data, sort_keys=False)


def _fitted(fit: Path, reduce=np.median):
    with h5py.File(fit) as f:
        g = f["fit/mnm"]
        ok = np.array([s.decode() if isinstance(s, bytes) else s for s in g["status"][()]]) == "ok"
        names = [s.decode() if isinstance(s, bytes) else s for s in g.attrs["names"]]
        Q = reduce(g["Q"][()][ok], axis=0)
        R = reduce(g["R/camera"][()][ok], axis=0)
        c = float(reduce(g["constant/c"][()][ok]))
    return names, Q, R, c


def test_ekf_takes_q_r_and_c_per_square_root_second(seed004_fit):
    cfg, text = load_config(text=_config(seed004_fit, {"type": "ekf"}))
    names, Q, R, c = _fitted(seed004_fit)
    o = cfg.observers[0]
    for s in ("px", "py", "hx", "hy", "Bx", "By"):
        assert o.q[s] == pytest.approx(np.sqrt(Q[names.index(s), names.index(s)]), rel=1e-12)
    assert "pz" not in o.q  # no process noise fitted there
    np.testing.assert_allclose(o.measurements["camera"].sigma, np.sqrt(np.diag(R)), rtol=1e-12)
    assert "coils" not in o.measurements or o.measurements["coils"].sigma is None  # a direction: not taken
    assert o.params["c"] == pytest.approx(c, rel=1e-12)
    assert text.startswith("# observer tuned:") and "from_fit" in text.splitlines()[0]


def test_ukf_takes_q_per_square_root_second_and_a_picked_trial(seed004_fit):
    """q means one thing in every observer: the UKF takes sqrt(Q_ii) as the EKF does, whatever its rate
    (it converts to its 50 Hz tick itself)."""
    cfg, _ = load_config(text=_config(seed004_fit, {"type": "ukf", "rate": 50.0, "_ff": {"pick": "trial", "trial": 2}}))
    with h5py.File(seed004_fit) as f:
        g = f["fit/mnm"]
        names = [s.decode() if isinstance(s, bytes) else s for s in g.attrs["names"]]
        Q = g["Q"][()][2]
        c = g["constant/c"][()][2]
    o = cfg.observers[0]
    assert o.q["hx"] == pytest.approx(np.sqrt(Q[names.index("hx"), names.index("hx")]), rel=1e-12)
    assert o.params["c"] == pytest.approx(c, rel=1e-12)


@pytest.mark.parametrize("observer, loc, message", [
    ({"type": "ekf", "q": {"px": 1e-4}}, "observers -> 0 -> q", "from_fit sets it"),
    ({"type": "ekf", "_ff": {"model": "binm"}, "model": "mnm"}, "observers -> 0 -> from_fit -> model", "does not apply"),
    ({"type": "ekf", "_ff": {"pick": "trial", "trial": 99}}, "observers -> 0 -> from_fit -> trial", "no trial 99"),
    ({"type": "ekf", "_ff": {"pick": "trial"}}, "observers -> 0 -> from_fit -> trial", "required key is missing"),
    ({"type": "ekf", "_ff": {"file": "no_such_fit.h5"}}, "observers -> 0 -> from_fit -> file", "no such fit file"),
    ({"type": "ekf", "_ff": {"pick": "mode"}}, "observers -> 0 -> from_fit -> pick", "median"),
    ({"type": "high_gain"}, "observers -> 0 -> type", "'high_gain' cannot take a fit"),
    ({"type": "high_gain"}, "observers -> 0 -> type", "from_fit works for ekf, eks, open_loop, ukf"),
    ({"type": "kalman"}, "observers -> 0 -> type", "unknown observer type 'kalman'"),
    ({"type": "ekf", "measurements": {"camera": {"sigma": 1e-4}}}, "observers -> 0 -> measurements -> camera -> sigma",
     "from_fit sets it"),
])
def test_from_fit_mistakes(seed004_fit, observer, loc, message):
    with pytest.raises(ConfigError) as e:
        load_config(text=_config(seed004_fit, observer))
    assert f"[{loc}]" in str(e.value) and message in str(e.value), str(e.value)


def test_a_fitted_ekf_runs_in_a_simulation(seed004_fit, tmp_path):
    cfg = tmp_path / "tuned.yaml"
    cfg.write_text(_config(seed004_fit, {"type": "ekf"}))
    out = tmp_path / "tuned.h5"
    r = CliRunner().invoke(app, ["simulate", str(cfg), "--out", str(out), "--quiet"])
    assert r.exit_code == 0, r.output
    with h5py.File(out) as f:
        config = f.attrs["config"]
        assert "from_fit" in config.splitlines()[0] and "from_fit:" not in config  # values written out
        assert np.isfinite(f["estimates/tuned/state"][()]).all()
