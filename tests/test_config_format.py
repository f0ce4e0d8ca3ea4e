"""One meaning per key (issue 26, item 2): ``q`` is a process noise std per square-root second in every
observer. A config of format 1 (no ``format:``) gave the UKF's ``q`` per filter tick: it loads converted,
with one line per observer saying from what to what, and the results file keeps the converted config; a
config of format 2 loads as written. The UKF's tick noise is ``diag(q^2) dt_tick`` (checked on the Q the
tick loop is given); ``from_fit`` and ``needle compare`` give every observer ``q`` in that one meaning."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import pytest
import yaml

from needlecli.experiments.config.load import load_config
from needlecli.experiments.config.types import CONFIG_FORMAT

ROOT = Path(__file__).resolve().parents[1]

Q_TICK = {"x": 2.0e-3, "alpha": 2.0e-5, "kappa": 2.0e-6}


def _config(fmt: int | None, q: dict, rate: float | None = 50.0, dt: float = 0.01) -> str:
    data = {
        "name": "fmt",
        "model": {"type": "modified_unicycle", "params": {"kappa": 0.005, "beta_cut": 0.035}},
        "inputs": {"v": 1.5, "u": 0.0},
        "sensors": [{"name": "us3d", "type": "position", "rate": 1.0, "sigma": 0.3},
                    {"name": "robot", "type": "encoder", "rate": 100.0, "channels": ["roll"], "sigma": 0.0035}],
        "observers": [{"name": "f", "type": "ukf", "q": dict(q), **({"rate": rate} if rate else {}),
                       "init": {"from": "truth", "values": {"kappa": 0.005}}},
                      {"name": "ol", "type": "open_loop", "q": {"x": 0.01}}],
        "runs": {"count": 3, "seed": 1},
        "stop": {"depth": 3.0},
        "simulation": {"dt": dt, "kernels": "numpy"},
    }
    if fmt is not None:
        data = {"format": fmt, **data}
    return yaml.safe_dump(data, sort_keys=False)


def test_a_format_1_config_converts_the_ukf_q_with_one_note(caplog):
    with caplog.at_level(logging.WARNING, logger="needlecli"):
        cfg, text = load_config(text=_config(None, Q_TICK))
    tick = 2 * 0.01  # 50 Hz on the 100 Hz grid
    ukf, ol = cfg.observers
    for k, v in Q_TICK.items():
        assert ukf.q[k] == pytest.approx(v / np.sqrt(tick), rel=1e-15)
    assert ol.q == {"x": 0.01}  # the open loop's q was per square-root second already
    assert cfg.format == CONFIG_FORMAT
    notes = [r.getMessage() for r in caplog.records]
    assert len(notes) == 1, notes  # one line per observer converted
    assert "[observers -> 0] f (ukf): q was per filter tick of 0.02 s" in notes[0]
    assert "x 0.002 -> 0.0141421" in notes[0] and "write format: 2" in notes[0]
    # the results file keeps the converted config, the note above it
    first, *rest = text.splitlines()
    assert first.startswith("# <string>: [observers -> 0] f (ukf): q was per filter tick")
    kept = yaml.safe_load("\n".join(rest))
    assert kept["format"] == 2 and kept["observers"][0]["q"]["x"] == pytest.approx(2.0e-3 / np.sqrt(tick))
    again, _ = load_config(text=text)  # and loads as it ran, without a second conversion
    assert again.observers[0].q == ukf.q


def test_a_format_2_config_loads_as_written(caplog):
    with caplog.at_level(logging.WARNING, logger="needlecli"):
        cfg, text = load_config(text=_config(2, Q_TICK))
    assert cfg.observers[0].q == Q_TICK and not caplog.records
    assert text == _config(2, Q_TICK)
    with pytest.raises(Exception, match=r"\[format\]"):
        load_config(text=_config(3, Q_TICK))


def test_an_override_is_an_edit_of_the_file_in_its_format():
    cfg, _ = load_config(text=_config(None, Q_TICK, rate=None), overrides=["observers.0.q.x=0.001"])
    assert cfg.observers[0].q["x"] == pytest.approx(0.001 / np.sqrt(0.01))


@pytest.mark.parametrize("fmt, q, expected", [
    (2, {"x": 0.02, "alpha": 2.0e-4}, {"x": 0.02**2 * 0.02, "alpha": 2.0e-4**2 * 0.02}),  # q^2 dt_tick
    (None, {"x": 0.002, "alpha": 2.0e-5}, {"x": 0.002**2, "alpha": 2.0e-5**2}),  # format 1: q_tick^2
])
def test_the_ukf_tick_noise_is_q_squared_times_the_tick(fmt, q, expected, monkeypatch, tmp_path):
    """The Q of the tick loop, independent of how it is computed: diag(q^2 dt_tick), dt_tick 0.02 s."""
    from needlecli.experiments.simulation.runner import run_experiment
    from needlecli.observers.ukf import UnscentedKalmanFilter

    seen = {}
    original = UnscentedKalmanFilter._filter

    def spy(self, problem, f, x, progress=None):
        seen["Q"], seen["names"] = f.Q.copy(), f.model.state_names
        return original(self, problem, f, x, progress)

    monkeypatch.setattr(UnscentedKalmanFilter, "_filter", spy)
    cfg, text = load_config(text=_config(fmt, q))
    run_experiment(cfg, text, out=tmp_path / "x.h5", base_dir=tmp_path)
    Q, names = seen["Q"], list(seen["names"])
    for k, v in expected.items():
        assert Q[names.index(k), names.index(k)] == pytest.approx(v, rel=1e-13)
    assert np.count_nonzero(Q) == len(expected)


def test_compare_derives_one_q_for_the_ukf_and_the_ekf():
    from needlecli.models import MODELS
    from needlecli.observers import OBSERVERS
    from needlecli.observers.defaults import ComparisonContext
    from needlecli.sensors import SENSORS

    model = MODELS.get("modified_unicycle")(MODELS.get("modified_unicycle").Params(kappa=0.005, beta_cut=0.035))
    s = SENSORS.get("position")
    sensor = s(s.Settings.model_validate({"name": "us3d", "type": "position", "rate": 1.0, "sigma": 0.3}), model)
    ctx = ComparisonContext(model=model, sensors={"us3d": sensor}, replay=False, final_depth=40.0, dt=0.01,
                            process_std={"x": 0.05, "alpha": 1e-6})
    ukf = OBSERVERS.get("ukf").derived_settings(ctx)["q"]
    ekf = OBSERVERS.get("ekf").derived_settings(ctx)["q"]
    assert ukf == ekf
    assert ukf["x"] == pytest.approx(0.05)  # the truth's std per sqrt(s), above its floor
    assert ukf["alpha"] == pytest.approx(1e-5 / np.sqrt(0.01))  # the floor: 1e-5 rad per 10 ms step


def test_every_bundled_config_gives_q_in_the_current_format():
    """No bundled config, example or doc snippet needs converting (a user copies them)."""
    stale = []
    for path in [*(ROOT / "configs").rglob("*.yaml"), *(ROOT / "examples").rglob("*.yaml")]:
        data = yaml.safe_load(path.read_text())
        if not isinstance(data, dict):
            continue
        for o in data.get("observers") or []:
            if o.get("type") == "ukf" and o.get("q") and data.get("format") != CONFIG_FORMAT:
                stale.append(str(path.relative_to(ROOT)))
    assert not stale, stale
