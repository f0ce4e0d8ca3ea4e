"""Recorded insertions of the ultrasteer data set (issue 8): the importer, the orientation convention found
in the data, lost ultrasound frames, and the UKF against the raw ultrasound on resultsOrig.

The data live outside the repository (``../shared/real-data/ultrasteer`` beside the checkout, or
``$NEEDLECLI_REAL_DATA``); the tests that need them are skipped with a reason when they are absent. The
synthetic-folder tests at the end run everywhere."""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path

import h5py
import numpy as np
import pytest
import yaml
from typer.testing import CliRunner

from needlecli.cli.app import app
from needlecli.experiments.config.load import load_config
from needlecli.experiments.simulation.runner import run_experiment
from needlecli.io import ultrasteer as us_io
from needlecli.io.logs import read_log, write_log
from needlecli.io.results import read_results
from needlecli.numerics import euler_xyz_to_matrix, rotation_angle
from needlecli.reports.evaluate import evaluate_results

ROOT = Path(__file__).resolve().parents[1]
_env = os.environ.get(us_io.ENV_VAR)
DATA = Path(_env) if _env else Path(__file__).resolve().parents[2] / "shared" / "real-data" / "ultrasteer"
HAVE_DATA = (DATA / "trials").is_dir() and (DATA / "resultsOrig").is_dir()
needs_data = pytest.mark.skipif(not HAVE_DATA, reason=f"real data set not found at {DATA} (set {us_io.ENV_VAR})")


@pytest.fixture(scope="module")
def raws():
    return us_io.find_trials(DATA)


@pytest.fixture(scope="module")
def log(tmp_path_factory):
    path = tmp_path_factory.mktemp("real") / "ultrasteer.h5"
    lg = us_io.import_ultrasteer(DATA)
    write_log(path, lg)
    return lg, path


def _unit(a):
    return a / np.linalg.norm(a, axis=-1, keepdims=True)


def _mean_cos(raw, axis_vectors):
    """Mean cosine between ``axis_vectors (N, 3)`` at the chord's two ends and the chords of ~5 mm."""
    i, j, c, _ = us_io.chords(raw, length=5.0)
    return float(np.mean(np.sum(_unit(axis_vectors[i] + axis_vectors[j]) * c, -1)))


# ---------------------------------------------------------------------------------------------- the data
@needs_data
def test_data_set_has_18_trials_and_results_orig(raws):
    ids = [r.id for r in raws]
    assert len(ids) == 19 and ids[-1] == "resultsOrig"
    assert {r.speed for r in raws} == {0.5, 1.0, 2.0, 3.0}
    orig = raws[-1]
    assert orig.session == "9_18_15" and orig.trial == 3 and orig.same_as == "9_18_15-1mm-Trial3"
    assert orig.rho == 98.0 and orig.dt_source == "dts.dat"


@needs_data
def test_rotations_are_flattened_by_column_with_the_tangent_on_e3(raws):
    """Read by column, the third column follows the direction of motion on every trial; read by row,
    it does not on the 1_7_16 trials; the first two columns never do."""
    for r in raws:
        ok = r.ok
        rot = np.where(ok[:, None, None], r.rot, np.eye(3))
        assert _mean_cos(r, rot[:, :, 2]) > 0.9, r.id
        assert max(abs(_mean_cos(r, rot[:, :, 0])), abs(_mean_cos(r, rot[:, :, 1]))) < 0.5, r.id
        by_row = np.swapaxes(rot, -1, -2)
        if r.session == "1_7_16":
            assert _mean_cos(r, by_row[:, :, 2]) < 0.6, r.id


@needs_data
def test_junk_frames_are_not_ground_truth(raws, log):
    lg, _ = log
    # the last frame is not a measurement, except on 1_7_16 Trials 1 and 2
    assert [r.id for r in raws if r.ok[-1]] == ["1_7_16-05mm-Trial1", "1_7_16-05mm-Trial2"]
    for tr in lg.trials:
        rot = tr.truth.state[:, 6:15].reshape(-1, 3, 3)
        assert us_io.rotation_valid(rot, 1e-6).all(), tr.id
        step = np.linalg.norm(np.diff(tr.truth.state[:, :3], axis=0), axis=-1)
        assert step.max() < us_io.JUMP_MM, tr.id
    t5 = next(r for r in raws if r.id == "9_18_15-2mm-Trial5")
    assert not t5.ok[142] and t5.ok[141] and t5.ok[143]


# ---------------------------------------------------------------------------------------------- the log
@needs_data
def test_import_round_trips(log):
    lg, path = log
    back = read_log(path)
    assert [t.id for t in back.trials] == [t.id for t in lg.trials]
    for a, b in zip(lg.trials, back.trials):
        assert set(a.sensors) == set(b.sensors) and set(a.inputs) == set(b.inputs)
        for name, s in a.sensors.items():
            np.testing.assert_array_equal(s.t, b.sensors[name].t)
            np.testing.assert_array_equal(s.value, b.sensors[name].value)
            np.testing.assert_array_equal(s.valid, b.sensors[name].valid)
            assert s.names == b.sensors[name].names and s.settings == b.sensors[name].settings
        for name, s in a.inputs.items():
            np.testing.assert_array_equal(s.t, b.inputs[name].t)
            np.testing.assert_array_equal(s.value, b.inputs[name].value)
        np.testing.assert_array_equal(a.truth.t, b.truth.t)
        np.testing.assert_array_equal(a.truth.state, b.truth.state)
        assert a.truth.names == b.truth.names == us_io.TRUTH_NAMES
        assert b.meta["speed_mm_s"] == a.meta["speed_mm_s"]


@needs_data
def test_truth_follows_the_motion_and_the_project_convention(log):
    lg, _ = log
    for tr in lg.trials:
        st = tr.truth.state
        R = st[:, 6:15].reshape(-1, 3, 3)
        np.testing.assert_allclose(euler_xyz_to_matrix(st[:, 3], st[:, 4], st[:, 5]), R, atol=1e-9)
        np.testing.assert_allclose(st[0, :6], 0.0, atol=1e-9)  # the trial frame: first tracker pose
        k = max(3, int(round(5.0 / (tr.meta["speed_mm_s"] * 0.177))))
        chord = _unit(st[k:, :3] - st[:-k, :3])
        cos = np.sum(_unit(R[k:, :, 2] + R[:-k, :, 2]) * chord, -1)
        assert np.mean(cos) > 0.9 and np.median(cos) > 0.98, tr.id  # aligned: 2-10 deg before, 1-5 after
        assert st[-1, 2] > 30.0  # z is the insertion direction
        assert np.mean(st[len(st) // 2:, 3]) > 0.0  # bends toward -y: alpha grows (alpha' = kappa v cos g)


@needs_data
def test_lost_ultrasound_frames_are_invalid(log, raws):
    lg, _ = log
    orig = next(t for t in lg.trials if t.id == "resultsOrig")
    s = orig.sensors["us"]
    raw = raws[-1]
    dop = us_io.read_numbers(DATA / "resultsOrig" / "MeasDoppler.dat").ravel()[: len(s.t)]
    np.testing.assert_array_equal(s.valid, dop > 0)
    assert (~s.valid).sum() == 152
    assert np.isfinite(s.value).all()  # kept as recorded, marked invalid
    err = np.linalg.norm(s.value - orig.sensors["tracker"].value, axis=-1)
    assert np.median(err[s.valid]) < 4.0 and np.median(err[~s.valid]) > 15.0
    assert "us" not in next(t for t in lg.trials if t.id != "resultsOrig").sensors
    assert raw.us_lost.sum() == 152  # the cut last frame was an outlier, not lost


@needs_data
def test_ultrasound_error_along_the_needle_is_where_its_image_plane_is(raws):
    """What docs/real-data.md builds on: resultsOrig's ultrasound point lies in its image plane
    (the recorded corners and axes MeasFul, MeasBx, MeasBy), and its error along the needle is, frame by
    frame, where that plane crosses the needle's axis relative to the tracker's tip: the point is the
    axis's crossing of the plane (median 0.07 mm off), whatever the plane's distance (8 mm ahead to 14 mm
    behind). The frames the detector lost are those where the plane ran ahead of the tip (97 %)."""
    raw = raws[-1]
    assert raw.id == "resultsOrig"
    n_frames = len(raw.pos)
    rd = lambda name: us_io.read_numbers(DATA / "resultsOrig" / name).reshape(3, -1).T[:n_frames]  # noqa: E731
    corner, bx, by = rd("MeasFul.dat"), rd("MeasBx.dat"), rd("MeasBy.dat")
    normal = _unit(np.cross(bx, by))
    t = raw.rot[:, :, 2]  # the tracker's tangent (third column)
    valid = ~raw.us_lost & raw.ok
    with np.errstate(all="ignore"):
        assert np.abs(np.sum((raw.us - corner) * normal, -1))[valid].max() < 1e-3  # in the plane
        dist = np.sum((raw.pos - corner) * normal, -1)  # the tip's distance past the plane
        ahead = dist / np.sum(normal * t, -1)  # the axis crosses the plane this far behind the tip
    along = np.sum((raw.us - raw.pos) * t, -1)
    use = valid & (np.abs(np.sum(normal * t, -1)) > 0.5)
    assert use.sum() > 200
    off = np.abs(along[use] + ahead[use])
    assert np.median(off) < 0.15 and np.quantile(off, 0.9) < 0.6
    assert along[use].min() < -10 and along[use].max() > 5  # the plane ranges far either way
    lost = raw.us_lost & raw.ok & np.isfinite(dist)
    assert np.mean(dist[lost] < 0) > 0.9


@needs_data
def test_image_plane_channel_is_the_recorded_plane_and_the_detectors_verdict(log):
    """resultsOrig's ``plane`` channel (the image plane as a one-sided bound): the ultrasound point of
    every valid frame lies in the imported plane (n . p = d, in the trial frame), the normal points along
    the insertion, ``seen`` is the us channel's validity, and against the tracker (which no filter sees)
    the bound holds for 97 % of the lost frames and 64 % of the seen ones (docs/real-data.md, (a2))."""
    lg, _ = log
    orig = next(t for t in lg.trials if t.id == "resultsOrig")
    pl, us, trk = orig.sensors["plane"], orig.sensors["us"], orig.sensors["tracker"]
    assert pl.settings["type"] == "image_plane" and pl.valid.all() and pl.value.shape == (len(us.t), 5)
    n, d, seen = pl.value[:, :3], pl.value[:, 3], pl.value[:, 4] > 0.5
    np.testing.assert_allclose(np.linalg.norm(n, axis=-1), 1.0, atol=1e-9)
    np.testing.assert_array_equal(seen, us.valid)
    assert np.abs(np.sum(n * us.value, -1) - d)[us.valid].max() < 1e-3  # the point is in the plane
    assert np.median(n[:, 2]) > 0.9  # along the insertion (the trial frame's z)
    g = np.sum(n * trk.value, -1) - d  # the tracker's tip past the plane
    ok = trk.valid
    assert np.mean(g[ok & ~seen] < 0) == pytest.approx(0.967, abs=0.005)
    assert np.mean(g[ok & seen] > 0) == pytest.approx(0.643, abs=0.005)
    assert "plane" not in next(t for t in lg.trials if t.id != "resultsOrig").sensors


@needs_data
def test_the_detectors_boundary_is_not_where_the_tracked_tip_is(log):
    """Why the shaft model's along constant is not in resultsOrig without the tracker (docs/real-data.md,
    (a4); ``make real-start``): the inserted length's reference, the first frame that saw the needle, has
    its plane 2.03 mm behind the tracked tip; the only along information the ultrasound has, the plane
    position at which the detector stops seeing the needle, lies 5.3 mm ahead of the tracked tip on average
    over the changes of verdict in the first 30 s (4.0 to 8.7) and 0.75 mm ahead after them (-1.65 to
    2.58): the first sweep's farthest seen plane is 5.57 mm ahead. Checked against the tracker, never by a
    filter."""
    lg, _ = log
    orig = next(t for t in lg.trials if t.id == "resultsOrig")
    pl, trk, ins = orig.sensors["plane"], orig.sensors["tracker"], orig.sensors["inserted"]
    assert trk.valid.all()
    n, d, seen = pl.value[:, :3], pl.value[:, 3], pl.value[:, 4] > 0.5
    g = np.sum(n * trk.value, -1) - d  # the tracker's tip past the plane (negative: the plane ahead of it)
    first = int(np.argmax(ins.valid))
    assert first == 0 and seen[0] and g[0] == pytest.approx(2.03, abs=0.01)
    np.testing.assert_allclose(ins.value[first, 1:4], orig.sensors["us"].value[first])  # its reference
    k = np.nonzero(seen[1:] != seen[:-1])[0]
    mid, when = (g[k] + g[k + 1]) / 2, pl.t[k + 1]
    early, late = mid[when < 30.0], mid[(when >= 30.0) & (when < 61.0)]
    assert len(early) == 11 and len(late) == 10
    assert early.mean() == pytest.approx(-5.31, abs=0.01) and early.max() == pytest.approx(-4.00, abs=0.01)
    assert late.mean() == pytest.approx(-0.75, abs=0.01) and np.abs(late).max() < 2.6
    first_lost = int(np.argmin(seen))
    assert g[:first_lost].min() == pytest.approx(-5.57, abs=0.01)


def test_doppler_edge_is_the_first_fall_below_the_running_maximums_fraction():
    """:func:`needlecli.io.ultrasteer.doppler_edge` against a hand computation: a profile that rises to 800,
    falls, then rises again; the half maximum (400) is crossed between frames 6 (500) and 7 (399), 100/101
    of the way, and 0.45 of it (360) between frames 7 and 8 (300), 39/99 of the way; it reads no frame after
    the edge (a later larger maximum does not move it), and a power that never falls gives None."""
    p = np.array([100.0, 600.0, 800.0, 700.0, 600.0, 550.0, 500.0, 399.0, 300.0, 2000.0, 0.0])
    k, w = us_io.doppler_edge(p)
    assert k == 7 and w == pytest.approx((500.0 - 400.0) / (500.0 - 399.0))
    k, w = us_io.doppler_edge(p, 0.45)
    assert k == 8 and w == pytest.approx((399.0 - 360.0) / (399.0 - 300.0))
    assert us_io.doppler_edge(np.array([1.0, 2.0, 3.0])) is None


@needs_data
def test_resultsorig_doppler_edge_is_where_the_plane_passes_the_tracked_tip(log):
    """Channel ``inserted_edge`` (docs/real-data.md, (a4)): resultsOrig's first sweep's Doppler power falls to
    half its maximum 1.24 s in (frame 7), the needle's crossing there 0.08 mm behind the tracked tip along the
    insertion (checked against the tracker, never by a filter), where the first frame that saw the needle had
    it 2.08 mm behind;
    the channel's length counts from there and is valid from that frame on."""
    lg, _ = log
    orig = next(t for t in lg.trials if t.id == "resultsOrig")
    edge, ins = orig.sensors["inserted_edge"], orig.sensors["inserted"]
    k = int(np.argmax(edge.valid))
    assert k == 7 and edge.valid[k:].all() and not edge.valid[:k].any()
    assert edge.t[k] == pytest.approx(1.24, abs=0.01)
    tip = orig.sensors["tracker"].value
    t0 = edge.t[k] - edge.value[k, 0] / 1.0  # V = 1 mm/s here: the edge's time
    ref_tip = np.array([np.interp(t0, edge.t, tip[:, i]) for i in range(3)])
    assert ref_tip[2] - edge.value[k, 3] == pytest.approx(0.08, abs=0.01)  # the reference behind the tracked tip
    assert abs(ins.value[0, 3] - tip[0, 2]) == pytest.approx(2.08, abs=0.01)  # inserted's: 2 mm behind
    np.testing.assert_allclose(np.diff(edge.value[k:, 0]), np.diff(ins.value[k:, 0]))  # the same length


@needs_data
def test_the_shaft_fit_and_filter_read_no_tracker_past_the_start(log, tmp_path):
    """configs/real/em_resultsorig_shaft.yaml, ..._shaft_edge.yaml and their filters ukf_shaft_em and
    ukf_shaft_edge_em of configs/real/ukf_resultsorig_shaft.yaml are tracker-free (docs/real-data.md, (a3),
    (a4)): with every tracker frame after the first (the first is the
    trial's start, where every filter takes its orientation from) replaced by another pose, truth and the
    ``tracker`` channel alike, EM fits the same noise and the filters give the same estimates."""
    lg, _ = log
    orig = next(t for t in lg.trials if t.id == "resultsOrig")
    garbled = dataclasses.replace(orig, sensors=dict(orig.sensors))
    rng = np.random.default_rng(3)
    state = orig.truth.state.copy()
    state[1:, :3] += rng.normal(0.0, 5.0, (len(state) - 1, 3))
    state[1:, 3:6] += rng.normal(0.0, 0.3, (len(state) - 1, 3))
    garbled.truth = dataclasses.replace(orig.truth, state=state)
    trk = orig.sensors["tracker"]
    garbled.sensors["tracker"] = dataclasses.replace(trk, value=np.r_[trk.value[:1], state[1:, :3]])
    runner, out = CliRunner(), {}
    for name, tr in (("recorded", orig), ("garbled", garbled)):
        path = tmp_path / f"{name}.h5"
        write_log(path, dataclasses.replace(lg, trials=[tr]))
        for fitted in ("shaft", "shaft_edge"):
            fit = yaml.safe_load((ROOT / "configs" / "real" / f"em_resultsorig_{fitted}.yaml").read_text())
            fit["source"]["logs"] = [str(path)]
            fit["fit"]["em"] = {"max_iter": 20, "tol": 1.0e-3}  # converges in 4
            (tmp_path / f"fit_{fitted}_{name}.yaml").write_text(yaml.safe_dump(fit))
            res = runner.invoke(app, ["fit-em", str(tmp_path / f"fit_{fitted}_{name}.yaml"), "--out",
                                      str(tmp_path / f"fit_{fitted}_{name}.h5"), "--quiet"])
            assert res.exit_code == 0, res.output
        data = yaml.safe_load((ROOT / "configs" / "real" / "ukf_resultsorig_shaft.yaml").read_text())
        obs = {o["name"]: o for o in data["observers"]}
        data["observers"] = [dict(obs[k], rate=20.0) for k in ("ukf_gated", "ukf_shaft_em", "ukf_shaft_edge_em")]
        data["observers"][1]["from_fit"]["file"] = str(tmp_path / "fit_shaft_recorded.h5")
        data["observers"][2]["from_fit"]["file"] = str(tmp_path / "fit_shaft_edge_recorded.h5")
        data["source"] = {"logs": [str(path)], "trials": ["resultsOrig"]}
        data["runs"] = {"seed": 8, "common_start": {"observer": "ukf_gated",
                                                    "observers": ["ukf_shaft_em", "ukf_shaft_edge_em"]}}
        (tmp_path / f"ukf_{name}.yaml").write_text(yaml.safe_dump(data))
        cfg, text = load_config(tmp_path / f"ukf_{name}.yaml")
        run_experiment(cfg, text, out=tmp_path / f"ukf_{name}.h5", base_dir=tmp_path)
        res = read_results(tmp_path / f"ukf_{name}.h5")
        r = {}
        for fitted, channel in (("shaft", "inserted"), ("shaft_edge", "inserted_edge")):
            with h5py.File(tmp_path / f"fit_{fitted}_{name}.h5") as f:
                r.update({(fitted, k): f[f"fit/unicycle/R/{k}"][()] for k in ("transverse", channel)})
        est = res.data["estimates"].data
        out[name] = (r, np.stack([np.asarray(est[k].data["state"]) for k in ("ukf_shaft_em", "ukf_shaft_edge_em")]),
                     np.asarray(res.data["truth"].data["state"]))
    (r0, x0, t0), (r1, x1, t1) = out["recorded"], out["garbled"]
    assert np.nanmax(np.abs(t0 - t1)) > 1.0  # the tracker did change
    for k in r0:
        np.testing.assert_array_equal(r0[k], r1[k])
    np.testing.assert_array_equal(x0, x1)


@pytest.fixture(scope="module")
def resultsorig(log, tmp_path_factory):
    """configs/real/ukf_resultsorig.yaml on two copies of resultsOrig, the filters at 20 Hz."""
    _, path = log
    tmp_path = tmp_path_factory.mktemp("orig")
    data = yaml.safe_load((ROOT / "configs" / "real" / "ukf_resultsorig.yaml").read_text())
    data["source"]["logs"] = [str(path)]
    data["source"]["trials"] = ["resultsOrig", "resultsOrig"]
    data["observers"] = [dict(o, rate=20.0) for o in data["observers"] if o["name"].startswith("ukf")]
    for o in data["observers"]:
        o.pop("predict_at_depths", None)
    cfg_path = tmp_path / "ukf.yaml"
    cfg_path.write_text(yaml.safe_dump(data))
    cfg, text = load_config(cfg_path)
    out = tmp_path / "ukf.h5"
    run_experiment(cfg, text, out=out, base_dir=tmp_path)
    return out


@needs_data
def test_gated_ukf_beats_the_raw_ultrasound(resultsorig):
    """Issue 8's "done when": on resultsOrig the UKF with gating has a lower mean tip error against the
    tracker than the raw ultrasound measurements, and the table reports both (a 20 Hz filter here)."""
    tables = evaluate_results(resultsorig, tables=["real_tip_error", "measurement_use"])
    df = tables["real_tip_error"].set_index(["Source", "Compared at"])
    at = "valid us frames (E_xyz)"
    raw_err = df.loc[("us (raw measurements)", at), "Mean"]
    assert df.loc[("ukf_gated", at), "Mean"] < raw_err
    assert df.loc[("ukf_gated", "every reference frame (E_xyz)"), "Mean"] < raw_err
    use = tables["measurement_use"]
    gated, ungated = use[use["Observer"] == "ukf_gated"], use[use["Observer"] == "ukf_ungated"]
    # the two copies of the recording used and gated the same samples: one row each, for both runs
    assert len(gated) == 1 and (gated["Gated"] > 0).all() and (ungated["Gated"] == 0).all()
    assert (gated["Valid"] == 213).all() and (gated["Trial"] == "resultsOrig").all() and (gated["Runs"] == "2/2").all()


@needs_data
def test_plots_of_the_recorded_insertion_hold_data(resultsorig, tmp_path, monkeypatch):
    """Issue 15: on the replay of resultsOrig (truth only at the tracker's frames) every plot is drawn
    from the frames where the truth exists: no empty axes, the tracker drawn where listed."""
    from report_checks import capture_figures, figure_problems

    from needlecli.metrics import compute_errors
    from needlecli.reports.plots import draw_plots, observer_colours

    figs = capture_figures(monkeypatch, render=False)
    res = read_results(resultsorig)
    written = {p.name for p in draw_plots(res, compute_errors(res), tmp_path / "p")}
    assert {"p_error_vs_depth.png", "p_rotation_error.png", "p_trajectories.png"} <= written
    problems = [p for fig in figs for p in figure_problems(fig, observer_colours(res), layout=False)]
    assert not problems, "\n".join(problems)


@needs_data
def test_cli_imports(tmp_path):
    out = tmp_path / "u.h5"
    res = CliRunner().invoke(app, ["import", "ultrasteer", str(DATA), "--out", str(out), "--frame", "tracker"])
    assert res.exit_code == 0, res.output
    assert "19 trial(s), 1 with ultrasound" in res.output
    lg = read_log(out)
    assert lg.trials[0].meta["frame"] == "tracker"


# ---------------------------------------------------------------------------------------------- everywhere
def test_speed_from_folder_names():
    assert us_io.speed_from_folder("05mm") == 0.5
    assert us_io.speed_from_folder("1mm") == 1.0
    assert us_io.speed_from_folder("3mm") == 3.0
    assert us_io.speed_from_folder("Trial1") is None
    assert us_io.session_date("9_18_15") == "2015-09-18"


def _write(path: Path, a: np.ndarray) -> None:
    np.savetxt(path, np.atleast_2d(a), fmt="%.9f")


def _fake_data_set(root: Path) -> tuple[np.ndarray, np.ndarray]:
    """One synthetic trial: an arc of radius 100 mm at 2 mm/s, bending toward the body's +y (the lab's
    convention), rotations written by column, a zero rotation and a position jump as the last frame."""
    folder = root / "trials" / "2_3_16" / "2mm" / "Trial1"
    folder.mkdir(parents=True)
    n, v, dt, rho = 120, 2.0, 0.177, 100.0
    s = v * dt * np.arange(n)
    phi = s / rho
    # needle frame of the lab: R = Rx(-phi), tangent e3, position (0, rho (1 - cos), rho sin)
    R = np.zeros((n, 3, 3))
    R[:, 0, 0] = 1.0
    R[:, 1, 1] = R[:, 2, 2] = np.cos(phi)
    R[:, 1, 2], R[:, 2, 1] = np.sin(phi), -np.sin(phi)
    p = np.stack([np.zeros(n), rho * (1 - np.cos(phi)), rho * np.sin(phi)], -1) + [10.0, 20.0, 30.0]
    R[-1] = 0.0
    p[-1] = [500.0, 0.0, 0.0]
    _write(folder / "FullStateGroundTruthPos.dat", p)
    _write(folder / "FullStateGroundTruthRs.dat", np.swapaxes(R, -1, -2).reshape(n, 9).T)  # by column
    return p, R


def test_importer_on_a_synthetic_folder(tmp_path):
    p, R = _fake_data_set(tmp_path)
    raws = us_io.find_trials(tmp_path)
    assert len(raws) == 1 and raws[0].speed == 2.0 and raws[0].session == "2_3_16"
    np.testing.assert_allclose(raws[0].rot[:-1], R[:-1], atol=1e-8)  # read back by column
    assert raws[0].ok[:-1].all() and not raws[0].ok[-1]
    lg = us_io.import_ultrasteer(tmp_path)
    tr = lg.trials[0]
    assert len(tr.truth.t) == len(p) - 1  # the junk last frame is cut
    st = tr.truth.state
    al = us_io.estimate_alignment(raws)["2_3_16"]
    assert al.residual_deg < 2.0 and np.degrees(rotation_angle(al.W)) < 2.0  # tangent already on the motion
    # the bending toward the lab's +y becomes ours, toward -y: alpha grows, beta and gamma stay 0
    assert st[-1, 3] > 0.3 and abs(st[-1, 4]) < 1e-3 and abs(st[-1, 5]) < 1e-3
    np.testing.assert_allclose(np.linalg.norm(st[-1, :3]), np.linalg.norm(p[-2] - p[0]), rtol=1e-9)
    assert tr.inputs["v"].value[0, 0] == 2.0 and "u" not in tr.inputs


def test_importer_errors_are_one_line(tmp_path):
    res = CliRunner().invoke(app, ["import", "ultrasteer", str(tmp_path / "nothing"), "--out", str(tmp_path / "x.h5")])
    assert res.exit_code == 2 and res.output.startswith("error:") and "Traceback" not in res.output
    (tmp_path / "empty").mkdir()
    res = CliRunner().invoke(app, ["import", "ultrasteer", str(tmp_path / "empty"), "--out", str(tmp_path / "x.h5")])
    assert res.exit_code == 2 and "no trials" in res.output


@needs_data
@pytest.mark.parametrize("name", sorted(p.name for p in (ROOT / "configs" / "real").glob("*.yaml")))
def test_real_configs_validate(name, log, tmp_path):
    """The configs of configs/real validate against the imported log (they point at the one `make real`
    writes, results/real/ultrasteer.h5, outside the repository's files)."""
    _, path = log
    data = yaml.safe_load((ROOT / "configs" / "real" / name).read_text())
    assert data["source"]["logs"] == ["../../results/real/ultrasteer.h5"]
    data["source"]["logs"] = [str(path)]
    # from_fit: the fit files `make real` writes before the config runs (results/real/, relative to here)
    for spec in [o.get("from_fit") for o in data.get("observers", [])] + [(data.get("fit") or {}).get("from_fit")]:
        if spec is not None:
            fit = (ROOT / "configs" / "real" / spec["file"]).resolve()
            if not fit.exists():
                pytest.skip(f"{name} takes {fit.name} (from_fit), which `make real` writes: not there yet")
            spec["file"] = str(fit)
    cfg = tmp_path / name
    cfg.write_text(yaml.safe_dump(data))
    res = CliRunner().invoke(app, ["validate", str(cfg)])
    assert res.exit_code == 0, res.output


def test_validate_reports_a_missing_log_in_one_line(tmp_path):
    cfg = tmp_path / "replay.yaml"
    cfg.write_text("name: r\nsource: {logs: [nowhere.h5]}\nmodel: {type: unicycle}\nobservers: []\n")
    res = CliRunner().invoke(app, ["validate", str(cfg)])
    assert res.exit_code == 2 and "no such log file" in res.output and "Traceback" not in res.output


@needs_data
def test_crossval_folds_of_trials_of_unequal_length(log, tmp_path):
    """Leave-one-out on three tracker trials of 9_18_15 at 1, 2 and 3 mm/s (64, 32 and 21 s): the folds
    that hold out the longest trial have a shorter time axis than the fit over all trials, and their fit
    files keep to it (ticks inside /time: the layout check at open), so the tuned observer runs."""
    from needlecli.io.fit import read_fit

    _, path = log
    data = yaml.safe_load((ROOT / "configs" / "real" / "em_tracker.yaml").read_text())
    data["source"]["logs"] = [str(path)]
    data["source"]["trials"] = ["9_18_15-1mm-Trial1", "9_18_15-2mm-Trial1", "9_18_15-3mm-Trial1"]
    data["fit"]["identify"] = {"enabled": False}
    cfg = tmp_path / "em.yaml"
    cfg.write_text(yaml.safe_dump(data))
    res = CliRunner().invoke(app, ["crossval", str(cfg), "--observer", "open_loop", "--leave-one-out",
                                   "--out", str(tmp_path / "cv"), "--quiet"])
    assert res.exit_code == 0, res.output
    lengths = []
    for k in range(3):
        f = read_fit(tmp_path / "cv" / "folds" / f"fold{k}_fit.h5")
        T = len(f.data["time"])
        assert int(np.max(f.data["fit"].data["unicycle"].data["ticks"])) < T
        lengths.append(T)
    assert len(set(lengths)) > 1  # the folds do have different time axes
