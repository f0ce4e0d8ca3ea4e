"""Closed loops (config section ``control:``): the magnetic needle EM paper's planar control on the camera's opacity.

The loop must hold the needle nearer its plane than the same insertions without it (and the opposite sign
must not), the applied command must be eq. (7) of the recorded opacity from each sample's availability on,
held through lost frames, the field must keep its in-plane direction and unit norm, and configs without
``control:`` must give what they gave before. Reference values are computed here from the results
arrays with plain loops, not with the controller's code.
"""

from __future__ import annotations

from pathlib import Path

import h5py
import numpy as np
import pytest
import yaml
from typer.testing import CliRunner

from needlecli.cli.app import app
from needlecli.control import CONTROLLERS
from needlecli.experiments.config.load import load_config
from needlecli.experiments.simulation.runner import build_sensors, run_experiment
from needlecli.experiments.simulation.truth import TruthSimulator, simulate_truth, stream

# A short insertion with a fast-turning needle (c = 100 1/m) started tilted out of plane (hz, 0.1 std) and
# pushed by process noise on pz and hz; small frames (0.11 mm pixels over 45 x 37.5 mm); a latency that
# is not a multiple of the step (availability 10.5 steps after acquisition -> the 11th grid time).
PLANAR = """\
name: planar_tiny
model: {type: mnm, params: {c: 100.0}, initial_state: {hy: -1.0, By: -1.0}, initial_std: {hz: 0.1}}
inputs: {v: 0.002, omega_B: [0.0, 0.0, 0.05]}
process_noise: {std: {pz: 1.0e-4, hz: 3.0e-3}}
sensors:
  - {name: camera, type: position, rate: 6.0, axes: [x, y], sigma: 5.0e-5, latency: 0.105, pipeline: image,
     image: {device: camera, size: [400, 334], fov: [45.0, 37.5], center: [0.0, -10.0], save_frames: 1}}
  - {name: coils, type: bfield, rate: 18.0, sigma: 1.0e-4}
control:
  - {name: planar, type: opacity_bz, sensor: camera, gain: 2.0, limit: 28.0, field: 19.0}
observers:
  - {name: open_loop, type: open_loop}
runs: {count: 6, seed: 3}
stop: {time: 8.0}
output: {tables: [summary, status, planar_control]}
"""

# The same needle, but the frame ends 14 mm below the entry: the tip leaves it after about 3.5 s, and
# every later frame has no detection (NaN opacity).
LOST = """\
name: planar_lost
model: {type: mnm, params: {c: 100.0}, initial_state: {hy: -1.0, By: -1.0}, initial_std: {hz: 0.1}}
inputs: {v: 0.002, omega_B: [0.0, 0.0, 0.05]}
process_noise: {std: {pz: 1.0e-4, hz: 3.0e-3}}
sensors:
  - {name: camera, type: position, rate: 6.0, axes: [x, y], sigma: 5.0e-5, latency: 0.105, pipeline: image,
     image: {device: camera, size: [180, 144], fov: [20.0, 16.0], center: [0.0, -6.0]}}
control:
  - {name: planar, type: opacity_bz, sensor: camera, gain: 2.0, limit: 28.0, field: 19.0}
runs: {count: 3, seed: 3}
stop: {time: 8.0}
"""
FIELD = ("Bx", "By", "Bz")


def without_control(text: str) -> str:
    data = yaml.safe_load(text)
    data.pop("control")
    return yaml.safe_dump(data, sort_keys=False)


def drift_mm(states: np.ndarray) -> np.ndarray:
    """``pz - pz0`` (N, T) in mm of the magnetic models' states (metres)."""
    return 1000.0 * (states[..., 2] - states[:, :1, 2])


def expected_command(opacity, t_available, time, gain, limit):
    """The magnetic needle EM paper's eq. (7) on the grid, by plain loops: the command of the last sample with a detection that
    is available at ``time[k]`` (``t_available <= t_k``), 0 before any; ``opacity_0`` the first detection."""
    N, M = opacity.shape
    out = np.zeros((N, len(time)))
    for r in range(N):
        first = next((opacity[r, j] for j in range(M) if np.isfinite(opacity[r, j])), None)
        current = 0.0
        j = 0
        for k, t in enumerate(time):
            while j < M and t_available[j] <= t + 1e-9:
                if np.isfinite(opacity[r, j]):
                    current = min(max(gain * (opacity[r, j] - first), -limit), limit)
                j += 1
            out[r, k] = current
    return out


@pytest.fixture(scope="module")
def closed(tmp_path_factory):
    cfg, raw = load_config(text=PLANAR)
    return run_experiment(cfg, raw, out=tmp_path_factory.mktemp("control") / "closed.h5")


@pytest.fixture(scope="module")
def opened():
    cfg, raw = load_config(text=without_control(PLANAR))
    return run_experiment(cfg, raw, write=False)


# ---------------------------------------------------------------------------------------------- the loop works
def test_closed_loop_reduces_out_of_plane_drift(closed, opened):
    dz_c, dz_o = drift_mm(closed.truth.states), drift_mm(opened.truth.states)
    rms_c, rms_o = np.sqrt(np.mean(dz_c**2)), np.sqrt(np.mean(dz_o**2))
    final_c, final_o = np.abs(dz_c[:, -1]).mean(), np.abs(dz_o[:, -1]).mean()
    assert rms_o > 0.4  # the drift the loop has to fight (mm)
    assert rms_c < 0.6 * rms_o, (rms_c, rms_o)
    assert final_c < 0.5 * final_o, (final_c, final_o)
    assert (closed.truth.status == "ok").all() and (opened.truth.status == "ok").all()
    # the same insertions otherwise: the start and the in-plane path
    assert np.array_equal(closed.truth.states[:, 0, :6], opened.truth.states[:, 0, :6])
    assert np.abs(closed.truth.states[..., :2] - opened.truth.states[..., :2]).max() < 2e-3  # m


def test_the_opposite_sign_drives_the_needle_away(opened, monkeypatch):
    """The sign chain (deeper -> fainter -> opacity up -> B_z > 0 -> the tip turns up) is what stabilises:
    with the command's sign flipped, the drift grows beyond the open loop's."""
    import needlecli.control.opacity_bz as ob

    plain = ob.bz_command
    monkeypatch.setattr(ob, "bz_command", lambda op, op0, gain, limit: plain(op, op0, gain=-gain, limit=limit))
    cfg, raw = load_config(text=PLANAR)
    flipped = run_experiment(cfg, raw, write=False)
    rms_f = np.sqrt(np.mean(drift_mm(flipped.truth.states) ** 2))
    assert rms_f > 1.5 * np.sqrt(np.mean(drift_mm(opened.truth.states) ** 2))


def test_the_field_keeps_unit_norm_and_its_in_plane_direction(closed, opened):
    cols = [closed.truth.model.index(k) for k in FIELD]
    b, b_o = closed.truth.states[..., cols], opened.truth.states[..., cols]
    assert np.abs(np.linalg.norm(b, axis=-1) - 1.0).max() < 1e-12
    # omega_B turns B about z alone: the command changes only its elevation, never its azimuth
    az = np.unwrap(np.arctan2(b[..., 1], b[..., 0]), axis=1)
    az_o = np.unwrap(np.arctan2(b_o[..., 1], b_o[..., 0]), axis=1)
    assert np.abs(az - az_o).max() < 1e-9


# ---------------------------------------------------------------------------------------------- the command
def test_recorded_command_is_eq7_of_the_recorded_opacity_from_its_availability(closed):
    with h5py.File(closed.path) as f:
        time = f["time"][()]
        cam = f["measurements/camera"]
        opacity, t, t_av = cam["opacity"][()], cam["t"][()], cam["t_available"][()]
        g = f["control/planar"]
        command = g["command"][()]
        attrs = dict(g.attrs)
        state = f["truth/state"][()]
        names = [n.decode() if isinstance(n, bytes) else str(n) for n in f["truth/state"].attrs["names"]]
    assert attrs["type"] == "opacity_bz" and attrs["sensor"] == "camera"
    assert (attrs["gain"], attrs["limit"], attrs["field"]) == (2.0, 28.0, 19.0)
    np.testing.assert_allclose(t_av, t + 0.105, rtol=0, atol=1e-12)
    assert command.shape == state.shape[:2]
    want = expected_command(opacity, t_av, time, 2.0, 28.0)
    np.testing.assert_allclose(command, want, rtol=0, atol=1e-9)
    assert np.abs(command).max() > 2.0  # the loop did act
    # the latency matters: acting at acquisition would be another command sequence
    assert np.abs(expected_command(opacity, t, time, 2.0, 28.0) - command).max() > 0.5
    # and the field's elevation is that command against the 19 mT in-plane field, at every grid time
    b = state[..., [names.index(k) for k in FIELD]]
    np.testing.assert_allclose(b[..., 2], want / np.hypot(19.0, want), rtol=0, atol=1e-9)


def test_lost_frames_hold_the_previous_command():
    cfg, raw = load_config(text=LOST)
    res = run_experiment(cfg, raw, write=False)
    cam = res.measurements["camera"]
    opacity = cam.attrs["opacity"]
    lost = ~np.isfinite(opacity)
    assert lost[:, :10].sum() == 0 and lost[:, -10:].all()  # detections first, then the tip left the frame
    g = res.control["planar"].data
    command = g["command"]
    np.testing.assert_allclose(command, expected_command(opacity, cam.t_available, res.truth.time, 2.0, 28.0),
                               rtol=0, atol=1e-9)
    last = np.array([np.nonzero(~lost[r])[0][-1] for r in range(lost.shape[0])])
    k_last = np.ceil(cam.t_available[last] / cfg.simulation.dt - 1e-9).astype(int)
    for r in range(lost.shape[0]):  # from the last detection's availability on, its command holds
        held = command[r, k_last[r]:]
        assert held.size > 300 and np.all(held == held[0]) and held[0] != 0.0
        bz = res.truth.states[r, k_last[r]:, res.truth.model.index("Bz")]
        assert np.ptp(bz) < 1e-12  # and so does B_z (omega_B is about z)


def test_controller_holds_per_run_and_starts_at_zero():
    """The controller alone, fed samples by hand: run 0 detects at sample 0, 1 and 3 (lost at 2), run 1 first
    detects at sample 1; commands act from their availability index; before that B_z is 0."""
    from needlecli.models import MODELS

    model = MODELS.get("mnm")()
    ctl = CONTROLLERS.get("opacity_bz")(CONTROLLERS.get("opacity_bz").Settings(
        type="opacity_bz", sensor="camera", gain=2.0, limit=28.0, field=10.0), model)
    time = 0.01 * np.arange(40)
    ctl.start(time, 2, np.array([0, 10, 20, 30]), np.array([0.05, 0.15, 0.25, 0.35]))
    samples = [np.array([100.0, np.nan]), np.array([104.0, 50.0]), np.array([np.nan, 40.0]), np.array([90.0, 80.0])]
    x = np.zeros((2, 9))
    x[:, 6:9] = [[0.0, -1.0, 0.0], [0.6, 0.8, 0.0]]
    seen = []
    for k in range(len(time)):
        j = k // 10
        if k % 10 == 0 and j < 4:
            ctl.on_sample(j, {"opacity": samples[j]})
        x = ctl.before_step(k, x)
        seen.append(x[:, 6:9].copy())
    cmd = ctl.command
    want0 = np.repeat([0.0, 0.0, 8.0, 8.0, -20.0], [5, 10, 10, 10, 5])  # sample 2 lost: 8 mT held
    want1 = np.repeat([0.0, 0.0, -20.0, 28.0], [15, 10, 10, 5])  # opacity_0 = 50; 60 grey levels -> 28 mT
    np.testing.assert_array_equal(cmd[0], want0)
    np.testing.assert_array_equal(cmd[1], want1)
    seen = np.array(seen)  # (T, N, 3)
    np.testing.assert_allclose(seen[-1, 0], np.array([0.0, -10.0, -20.0]) / np.hypot(10.0, 20.0), atol=1e-15)
    np.testing.assert_allclose(seen[-1, 1], np.array([6.0, 8.0, 28.0]) / np.hypot(10.0, 28.0), atol=1e-15)
    assert np.all(seen[:5, :, 2] == 0.0)


def test_a_change_that_leaves_the_domain_stops_the_run_there():
    """A state change between steps is checked like a step: BiNM with the field turned perpendicular to the
    tip at grid index 5 (run 0 only) stops run 0 there as singular, holding its state from before."""
    cfg, _ = load_config(text="model: {type: binm, initial_state: {hy: -1.0, By: -1.0}}\n"
                              "inputs: {v: 0.002, omega_B: [0.0, 0.0, 0.1]}\nruns: {count: 2}\nstop: {time: 0.2}\n")

    def perpendicular(k, x):
        if k != 5:
            return x
        x = x.copy()
        x[0, 6:9] = [0.0, 0.0, 1.0]
        return x

    sim = TruthSimulator(cfg, before_step=perpendicular)
    truth = sim.finish()
    assert list(truth.status) == ["singular", "ok"] and truth.event_time[0] == truth.time[5]
    assert np.all(truth.states[0, 5:] == truth.states[0, 5])  # held from t_5 on ...
    assert abs(truth.states[0, 5, 8]) < 1e-12  # ... with the field as it was before the change
    assert np.ptp(truth.states[1, 5:, 0:2], axis=0).max() > 0  # the other run goes on


# ---------------------------------------------------------------------------------------------- open loop unchanged
def test_stepper_in_chunks_is_simulate_truth_bit_for_bit():
    cfg, _ = load_config(text=without_control(PLANAR))
    ref = simulate_truth(cfg)
    sim = TruthSimulator(cfg)
    for k in (0, 1, 7, 7, 250, 251, 600):
        sim.advance_to(k)
        assert sim.k == k
    got = sim.finish()
    for a, b in ((ref.states, got.states), (ref.event_time, got.event_time), (ref.inputs, got.inputs)):
        assert np.array_equal(a, b, equal_nan=True)
    assert list(ref.status) == list(got.status)


def test_camera_measured_while_the_truth_runs_equals_the_camera_on_the_finished_truth():
    """The loop's mechanism alone (no controller): a camera measured frame by frame on the stepper gives
    the stream, extras and frames of the camera measured after the simulation, bit for bit."""
    cfg, _ = load_config(text=without_control(PLANAR))
    truth = simulate_truth(cfg)
    cam = build_sensors(cfg, truth.model)[0]
    ref = cam.measure(truth, stream(cfg.runs.seed, "sensor/camera"))
    sim = TruthSimulator(cfg)
    frames = []
    finish = cam.measure_live(sim, stream(cfg.runs.seed, "sensor/camera"), lambda j, out: frames.append((j, sim.k)))
    got = finish(sim.finish())
    assert [j for j, _ in frames] == list(range(len(ref.t)))
    assert all(k == i for (_, k), i in zip(frames, ref.index))  # the simulation waited for each frame
    assert np.array_equal(got.value, ref.value, equal_nan=True) and np.array_equal(got.valid, ref.valid)
    assert np.array_equal(got.sigma, ref.sigma)
    for key, v in ref.attrs.items():
        a, b = np.asarray(got.attrs[key]), np.asarray(v)
        assert np.array_equal(a, b, equal_nan=a.dtype.kind == "f"), key


def test_config_without_control_gives_the_open_loop_results(opened):
    cfg, _ = load_config(text=without_control(PLANAR))
    truth = simulate_truth(cfg)
    assert np.array_equal(opened.truth.states, truth.states)
    assert opened.control == {}
    for s in build_sensors(cfg, truth.model):
        st = s.measure(truth, stream(cfg.runs.seed, f"sensor/{s.name}"))
        assert np.array_equal(opened.measurements[s.name].value, st.value, equal_nan=True), s.name


# ---------------------------------------------------------------------------------------------- end to end
def test_simulate_and_evaluate_a_closed_loop_config(tmp_path: Path):
    def invoke(*args):
        return CliRunner().invoke(app, [str(a) for a in args])

    cfg = tmp_path / "planar.yaml"
    cfg.write_text(PLANAR.replace("runs: {count: 6, seed: 3}", "runs: {count: 2, seed: 3}").replace("8.0}", "3.0}"))
    out = tmp_path / "r" / "planar.h5"
    dry = invoke("simulate", cfg, "--out", out, "--dry-run")
    assert dry.exit_code == 0 and "1 controller(s) in closed loop" in dry.stdout
    result = invoke("simulate", cfg, "--out", out, "--quiet")
    assert result.exit_code == 0, result.output + repr(result.exception)
    assert result.stdout.splitlines()[-1] == f"results: {out}"
    with h5py.File(out) as f:
        assert f["control/planar/command"].shape == f["truth/state"].shape[:2] == (2, 301)
        assert f["control/planar/sample_command"].shape == f["measurements/camera/opacity"].shape == (2, 19)
        assert f["control/planar"].attrs["type"] == "opacity_bz" and f["control/planar/command"].attrs["unit"] == "mT"
        assert "bz_command" in f["measurements/camera"]
    ev = invoke("evaluate", out, "--out", tmp_path / "t", "--no-plots", "--quiet")
    assert ev.exit_code == 0, ev.output + repr(ev.exception)
    for table in ("summary", "status", "planar_control"):
        assert (tmp_path / "t" / f"planar_tiny_{table}.md").exists(), table
    rows = (tmp_path / "t" / "planar_tiny_planar_control.csv").read_text().splitlines()
    assert rows[0].startswith("Control,Run,Status,Mean |dz| [mm]") and len(rows) == 1 + 3
    assert rows[1].startswith("planar,all ok (2/2),ok,")
    listing = invoke("list")
    assert "controllers: opacity_bz" in listing.stdout and "planar_control" in listing.stdout
