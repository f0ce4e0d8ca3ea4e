"""The transverse-plane sensor (needlecli.sensors.transverse): its h, the crossing of the needle's past
path with the image plane, against an independent closed-form crossing of a circle and a plane; its
emulation against its h; the readings an observer may choose."""

from __future__ import annotations

import numpy as np
import pytest

from needlecli.models import MODELS
from needlecli.sensors import SENSORS
from needlecli.sensors.base import measurement_function, sample_context


def _model(name="unicycle", kappa=0.01):
    cls = MODELS.get(name)
    return cls(cls.Params(kappa=kappa))


def _sensor(model, **kw):
    cls = SENSORS.get("transverse")
    return cls(cls.Settings(type="transverse", name="us", rate=10.0, **kw), model)


def _path(model, x0, v=1.5, dt=0.01, steps=4000):
    """The tip's positions ``(steps + 1, 3)`` and final state, integrated forward by the model (pure insertion)."""
    x = np.array(x0, dtype=float)
    u = np.array([v, 0.0])
    p = model.param_arrays()
    pos = [model.tip_position(x)]
    for _ in range(steps):
        x = model.step(x, u, p, dt)
        pos.append(model.tip_position(x))
    return np.array(pos), x


def _circle(a, b, c):
    """Centre, radius and the orthonormal pair ``(e1, e2)`` of the circle through three points, ``e1`` from
    the centre to ``c`` and ``e2`` the direction of travel at ``c`` (from ``a`` through ``b`` to ``c``)."""
    ab, ac = b - a, c - a
    w = np.cross(ab, ac)
    centre = a + (np.dot(ac, ac) * np.cross(w, ab) + np.dot(ab, ab) * np.cross(ac, w)) / (2.0 * np.dot(w, w))
    r = np.linalg.norm(c - centre)
    e1 = (c - centre) / r
    e2 = np.cross(w / np.linalg.norm(w), e1)
    if np.dot(e2, c - b) < 0:
        e2 = -e2
    return centre, r, e1, e2


def _closed_form(centre, r, e1, e2, o, n, theta_near):
    """The point of the circle ``centre + r (cos t e1 + sin t e2)`` on the plane ``n . (X - o) = 0``: the
    root of ``A cos t + B sin t = C`` nearest ``theta_near``."""
    A, B, C = r * np.dot(n, e1), r * np.dot(n, e2), -np.dot(n, centre - o)
    phi, rho = np.arctan2(B, A), np.hypot(A, B)
    roots = phi + np.array([1.0, -1.0]) * np.arccos(C / rho)
    roots = (roots + np.pi) % (2 * np.pi) - np.pi
    t = roots[np.argmin(np.abs(roots - theta_near))]
    return centre + r * (np.cos(t) * e1 + np.sin(t) * e2)


def _plane(normal, tilt, spin):
    """Unit image axes and normal of a plane whose normal is ``normal`` tilted by ``tilt`` about a direction
    at angle ``spin`` across it."""
    n = normal / np.linalg.norm(normal)
    a = np.cross(n, [0.3, 0.5, 0.8])
    a /= np.linalg.norm(a)
    b = np.cross(n, a)
    axis = np.cos(spin) * a + np.sin(spin) * b
    nt = np.cos(tilt) * n + np.sin(tilt) * np.cross(axis, n)
    eu = axis
    ev = np.cross(nt, eu)
    return eu, ev, nt


@pytest.mark.parametrize("model_name", ["unicycle", "modified_unicycle"])
def test_h_is_the_closed_form_crossing_of_the_travelled_circle(model_name):
    model = _model(model_name, kappa=0.01)  # radius 100 mm; 60 mm travelled: 0.6 rad of arc
    rng = np.random.default_rng(3)
    x0 = model.initial_state(model.param_arrays()).astype(float)
    x0[3:6] = [0.3, -0.2, 1.1]
    if model_name == "modified_unicycle":
        x0[6] = 0.01
    path, tip = _path(model, x0)
    centre, r, e1, e2 = _circle(path[0], path[len(path) // 2], path[-1])
    assert abs(r - 100.0) < 1e-6  # the path is the circle of radius 1 / kappa (RK4 to rounding)
    sensor = _sensor(model)
    h = measurement_function(sensor, model)
    contexts, expected = [], []
    for back in (0.0, 3.0, 12.5, 30.0, 55.0, -4.0):  # mm behind the tip (negative: a plane ahead of it)
        theta = -back / r
        on = centre + r * (np.cos(theta) * e1 + np.sin(theta) * e2)
        tangent = -np.sin(theta) * e1 + np.cos(theta) * e2
        for tilt, spin, shift in ((0.0, 0.0, 0.0), (0.5, 1.0, 0.7), (-0.9, 2.5, -1.3)):
            eu, ev, n = _plane(tangent, tilt, spin)
            o = on + shift * n + rng.normal(0.0, 2.0) * eu + rng.normal(0.0, 2.0) * ev  # origin anywhere on it
            X = _closed_form(centre, r, e1, e2, o, n, theta)
            contexts.append(np.concatenate([o, eu, ev]))
            expected.append([np.dot(eu, X - o), np.dot(ev, X - o)])
    contexts = np.array(contexts)
    got = h(np.broadcast_to(tip, (len(contexts), tip.size)), contexts)
    np.testing.assert_allclose(got, np.array(expected), atol=1e-8)


def test_the_tip_reading_is_the_tip_in_the_planes_coordinates():
    model = _model()
    sensor = _sensor(model)
    tip_h = measurement_function(sensor, model, "tip")
    x = np.array([1.0, -2.0, 30.0, 0.2, 0.1, 0.4])
    o, eu, ev = np.array([0.5, 0.5, 25.0]), np.array([1.0, 0.0, 0.0]), np.array([0.0, 1.0, 0.0])
    np.testing.assert_allclose(tip_h(x, np.concatenate([o, eu, ev])), [0.5, -2.5, 5.0])
    assert tip_h.extra == ("w",)
    with pytest.raises(ValueError, match="no reading 'nope'"):
        measurement_function(sensor, model, "nope")


@pytest.mark.parametrize("motion", ["follow", "scan", "fixed"])
def test_emulated_samples_are_h_of_the_truth(motion, tmp_path):
    """With no noise, each emulated sample (the truth's recorded path crossed with the probe's plane,
    linear between grid steps) is h of the true state at its time: the emulation and the observers'
    measurement function agree."""
    from needlecli.experiments.config.load import load_config
    from needlecli.experiments.simulation.runner import build_sensors
    from needlecli.experiments.simulation.truth import simulate_truth

    cfg_text = f"""
format: 2
name: t
model: {{type: unicycle, params: {{kappa: 0.008}}, initial_state: {{alpha: 0.2, beta: -0.1, gamma: 0.7}}}}
inputs: {{v: 1.5, u: 0.0}}
sensors:
  - {{name: us, type: transverse, rate: 2.0, sigma: 0.0,
      probe: {{motion: {motion}, lag: 3.0, offset: {10.0 if motion == 'fixed' else -4.0}, amplitude: 5.0, period: 9.0, tilt: 15.0}}}}
observers: []
runs: {{count: 3, seed: 1}}
stop: {{depth: 40.0}}
simulation: {{dt: 0.01}}
output: {{path: {tmp_path / 'x.h5'}}}
"""
    cfg, _ = load_config(text=cfg_text)
    truth = simulate_truth(cfg)
    (sensor,) = build_sensors(cfg, truth.model)
    stream = sensor.measure(truth, np.random.default_rng(0))
    assert stream.valid.sum() > 10
    x = truth.states[:, stream.index]
    want = sensor.h(x, sample_context(sensor, stream.value))
    got = stream.value[..., :2]
    # linear between grid steps of 0.015 mm on a 125 mm radius: below 1e-6 mm
    np.testing.assert_allclose(got[stream.valid], want[stream.valid], atol=1e-6)
    if motion == "fixed":  # the tip short of the plane (before it reaches it, 10 mm: 6.7 s) is lost
        assert not stream.valid[:, :13].any() and stream.valid[:, 14:].all()


def _data_dir():
    import os
    from pathlib import Path

    from needlecli.io import ultrasteer as us_io

    env = os.environ.get(us_io.ENV_VAR)
    return Path(env) if env else Path(__file__).resolve().parents[2] / "shared" / "real-data" / "ultrasteer"


@pytest.mark.skipif(not (_data_dir() / "resultsOrig").is_dir(), reason="real data set not found")
def test_ultrasteer_import_gives_the_plane_pose_of_every_frame():
    """resultsOrig's ``transverse`` channel: the crossing ``(u, v)`` placed back in 3D with the frame's pose,
    ``o + u e_u + v e_v``, is the ultrasound point (``us``, from MeasPos); the axes are unit and orthogonal, the
    normal along the insertion, and ``u`` is MeasUv's first image coordinate (its second
    is ``v`` offset by 0.80-0.86 mm)."""
    from needlecli.io import ultrasteer as us_io

    raws = us_io.find_trials(_data_dir())
    al = us_io.estimate_alignment(raws)
    raw = next(r for r in raws if r.id == "resultsOrig")
    tr = us_io.to_trial(raw, al[raw.session])
    tv, us = tr.sensors["transverse"], tr.sensors["us"]
    assert tv.settings["type"] == "transverse"
    np.testing.assert_array_equal(tv.valid, us.valid)
    u, v, o, eu, ev = tv.value[:, :1], tv.value[:, 1:2], tv.value[:, 2:5], tv.value[:, 5:8], tv.value[:, 8:11]
    ok = tv.valid
    # the recorded axes are orthogonal to 1.4e-4: 15 mm into the image that is 2e-3 mm
    np.testing.assert_allclose((o + u * eu + v * ev)[ok], us.value[ok], atol=0.01)
    np.testing.assert_allclose(np.linalg.norm(eu[ok], axis=-1), 1.0, atol=1e-9)
    np.testing.assert_allclose(np.sum(eu * ev, -1)[ok], 0.0, atol=2e-4)
    assert np.median(np.cross(eu, ev)[ok][:, 2] ** 2) > 0.8  # the plane across the insertion (trial z)
    uv = us_io.read_numbers(_data_dir() / "resultsOrig" / "MeasUv.dat").reshape(2, -1).T
    keep = slice(int(np.nonzero(raw.ok)[0][0]), int(np.nonzero(raw.ok)[0][-1]) + 1)
    np.testing.assert_allclose(u[ok, 0], uv[keep][ok, 0], atol=0.01)


def test_a_csv_mapping_names_the_plane_pose_columns(tmp_path):
    """A lab's export of a transverse probe: the crossing in the image (here in cm) and the plane's pose as
    columns of the CSV; the import converts the lengths, keeps the axes, and a column set without the pose is
    refused by name."""
    from needlecli.errors import ConfigError
    from needlecli.io.csv_import import import_csv

    rng = np.random.default_rng(0)
    n = 6
    t = np.arange(n) * 0.2
    rows = np.c_[t, rng.normal(size=(n, 5)), np.tile([1.0, 0.0, 0.0, 0.0, 0.6, 0.8], (n, 1))]
    head = "t,cu,cv,px,py,pz,ax,ay,az,bx,by,bz"
    d = tmp_path / "tr1"
    d.mkdir()
    np.savetxt(d / "us.csv", rows, delimiter=",", header=head, comments="")
    np.savetxt(d / "robot.csv", np.c_[t, np.full(n, 1.0)], delimiter=",", header="t,speed", comments="")
    cols = "{u: cu, v: cv, ox: px, oy: py, oz: pz, ux: ax, uy: ay, uz: az, vx: bx, vy: by, vz: bz}"
    mapping = f"""
trials: [{{id: tr1, dir: tr1}}]
inputs: {{v: {{file: robot.csv, column: speed, unit: mm/s}}}}
sensors:
  us:
    file: us.csv
    columns: {cols}
    units: [cm, cm, cm, cm, cm, '1', '1', '1', '1', '1', '1']
    sensor: {{type: transverse, rate: 5.0, sigma: 0.5}}
"""
    (tmp_path / "m.yaml").write_text(mapping)
    log = import_csv(tmp_path / "m.yaml")
    s = log.trials[0].sensors["us"]
    assert s.names == ("u", "v", "ox", "oy", "oz", "ux", "uy", "uz", "vx", "vy", "vz")
    np.testing.assert_allclose(s.value[:, :5], 10.0 * rows[:, 1:6])
    np.testing.assert_allclose(s.value[:, 5:], rows[:, 6:])
    (tmp_path / "m.yaml").write_text(mapping.replace(", vx: bx, vy: by, vz: bz", "").replace(", '1', '1', '1']", "]"))
    with pytest.raises(ConfigError, match="no column for channel 'vx'"):
        import_csv(tmp_path / "m.yaml")


def test_scanning_probe_study_shaft_model_beats_the_tip_model(tmp_path):
    """configs/shaft/scan.yaml, smaller (10 runs to 40 mm): the shaft-crossing model's along-needle error is
    at most a third of the tip model's, its ANEES inside the 95 % band, and the NIS of the transverse
    channel counts its own degrees of freedom (2 measured; the tip reading's 3 with its constraint)."""
    from pathlib import Path

    from needlecli.experiments.config.load import load_config
    from needlecli.experiments.simulation.runner import run_experiment
    from needlecli.reports.evaluate import evaluate_results

    cfg_path = Path(__file__).resolve().parents[1] / "configs" / "shaft" / "scan.yaml"
    cfg, text = load_config(cfg_path, runs=10, overrides=["stop.depth=40"])
    out = tmp_path / "scan.h5"
    run_experiment(cfg, text, out=out, base_dir=tmp_path)
    tables = evaluate_results(out, tables=["summary", "consistency"])
    s = tables["summary"].set_index(["Observer", "Quantity"])["Mean"]
    assert s[("shaft", "E_ax [mm]")] <= s[("tip", "E_ax [mm]")] / 3.0
    c = tables["consistency"].set_index(["Observer", "Test", "Of"])
    row = c.loc[("shaft", "ANEES", "all states (x, y, z, alpha, beta, gamma, kappa)")]
    assert row["95% low"] <= row["Mean"] <= row["95% high"]
    assert c.loc[("shaft", "ANIS", "us"), "Dof"] == 2 and c.loc[("tip", "ANIS", "us"), "Dof"] == 3


@pytest.mark.parametrize("model_name", ["unicycle", "modified_unicycle"])
def test_insertion_h_is_the_length_travelled_from_the_entry(model_name):
    """Sensor insertion: h of the tip after the model carried it ``L`` along its circle from the entry pose
    is ``L`` (the integration's own travelled length, 1.5 mm/s for t s), for 0-60 mm (0.6 rad of arc)."""
    model = _model(model_name, kappa=0.01)
    x0 = model.initial_state(model.param_arrays()).astype(float)
    x0[0:6] = [2.0, -1.0, 3.0, 0.3, -0.2, 1.1]
    if model_name == "modified_unicycle":
        x0[6] = 0.01
    cls = SENSORS.get("insertion")
    sensor = cls(cls.Settings(type="insertion", name="robot", rate=10.0), model)
    t0 = model.tangent(x0)
    entry = np.concatenate([model.tip_position(x0), t0 / np.linalg.norm(t0)])
    h = measurement_function(sensor, model)
    for steps in (1, 700, 2000, 4000):
        _, tip = _path(model, x0, steps=steps)
        np.testing.assert_allclose(h(tip, entry), [1.5 * 0.01 * steps], atol=1e-8)
