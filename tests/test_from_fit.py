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
    data = yaml.safe_load((ROOT / "configs" / "em-magnetic-pratt2022" / "study.yaml").read_text())
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


def _damaged_copy(fit: Path, tmp_path: Path, edit) -> Path:
    out = tmp_path / "damaged_fit.h5"
    out.write_bytes(fit.read_bytes())
    with h5py.File(out, "r+") as f:
        edit(f)
    return out


def _set(f, path: str, index: tuple, value) -> None:
    v = f[path][()]
    v[index] = value
    del f[path]
    f[path] = v


@pytest.mark.parametrize("edit, hdf5, message", [
    (lambda f: _set(f, "fit/mnm/Q", (1, 3, 3), -1e-6), "/fit/mnm/Q", "trial 1: entry (3, 3) = -1e-06 < 0"),
    (lambda f: _set(f, "fit/mnm/R/camera", (0, 0, 1), 1.0), "/fit/mnm/R/camera", "trial 0: not symmetric"),
    (lambda f: f["fit/mnm"].attrs.modify("names", ["px", "py", "pz", "hx", "hy", "hz", "Bx", "By", "Bz", "kappa"]),
     "/fit/mnm attribute names", "'kappa' is neither a state nor a constant of model 'mnm'"),
])
def test_a_damaged_fit_is_refused_whatever_the_observer_takes(seed004_fit, tmp_path, edit, hdf5, message):
    """The open loop takes q and the constants only, the EKF R too: both refuse a damaged fit, naming the
    config's key and the fit file's HDF5 path (a negative variance was taken as q = 0)."""
    fit = _damaged_copy(seed004_fit, tmp_path, edit)
    for kind in ("open_loop", "ekf"):
        with pytest.raises(ConfigError) as e:
            load_config(text=_config(fit, {"type": kind}))
        text = str(e.value)
        assert "[observers -> 0 -> from_fit -> file]" in text and f"[{hdf5}" in text and message in text, text


def test_a_fit_section_takes_q_from_a_fit_of_other_sensors(seed004_fit):
    """A fit section's from_fit takes q and the constants, not R: the other fit's channels (camera, coils)
    need not be this config's sensors (here the camera is named cam), while an observer's must be."""
    data = yaml.safe_load(_config(seed004_fit, {"type": "ekf"}))
    data["sensors"][0]["name"] = "cam"
    observer = data.pop("observers")
    data["fit"] = {"models": ["mnm"], "from_fit": {"file": str(seed004_fit), "model": "mnm"},
                   "measurements": {"cam": {"sigma": 1e-4}, "coils": {"sigma": 3e-4}},
                   "init": {"values": {"hy": -1.0}, "first_measurement": {"px": "cam.x", "py": "cam.y"}}}
    cfg, _ = load_config(text=yaml.safe_dump(data, sort_keys=False))
    names, Q, _, _ = _fitted(seed004_fit)
    assert cfg.fit.q["hx"] == pytest.approx(np.sqrt(Q[names.index("hx"), names.index("hx")]), rel=1e-12)
    data["observers"] = observer
    with pytest.raises(ConfigError) as e:
        load_config(text=yaml.safe_dump(data, sort_keys=False))
    assert "the fit's channel 'camera' is no sensor of this config (sensors: cam, coils)" in str(e.value)
