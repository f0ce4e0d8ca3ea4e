"""Bringing a lab's own recorded data (issue 18): the insertion-speed scale of the kinematic models, the
quaternion and trial-frame maths, the CSV layouts of real exports (step-indexed rows, file-name templates,
command files, all-zero rows, quaternions, per-sample sigmas, trial starts and frames), and the whole path
from exports to per-trial fits and a regression on a design factor, on a synthetic set whose truth is known.

References are independent of the code under test: the unicycle's exact circle (a rigid body turning at
``kappa * (speed_scale v)`` about body x), scipy's rotations for the quaternions, ordinary least squares by
``numpy.polyfit`` for the regression, the simulation's own parameters for the recovery.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import yaml
from scipy.spatial.transform import Rotation
from typer.testing import CliRunner

from needlecli.cli.app import app
from needlecli.io.frames import bend_roll, body_bend, chord_pairs, express, path_frame, pose_axes, rolled
from needlecli.io.logs import read_log
from needlecli.models import MODELS
from needlecli.numerics import euler_xyz_to_matrix, matrix_to_quaternion, quaternion_to_matrix, rot_z, so3_exp

ROOT = Path(__file__).resolve().parents[1]
runner = CliRunner()


def run(*args):
    res = runner.invoke(app, [str(a) for a in args])
    return res


def error_lines(res) -> list[str]:
    return [ln for ln in res.output.splitlines() if ln.startswith("error:")]


# ---------------------------------------------------------------------------------------------- the models
@pytest.mark.parametrize("name", ["unicycle", "modified_unicycle"])
def test_speed_scale_slows_the_tip_along_the_same_circle(name):
    """With ``speed_scale = s`` the tip runs the circle of radius 1/kappa at s v: after time t it is where
    the unscaled needle is after s t (exact circle: z = sin(kappa s v t) / kappa)."""
    cls = MODELS.get(name)
    kappa, v, s, dt, n = 0.01, 2.0, 0.87, 0.01, 1000
    m = cls(cls.Params(kappa=kappa, speed_scale=s))
    p = m.param_arrays()
    x = m.initial_state(p)
    for _ in range(n):
        x = m.step(x, np.array([v, 0.0]), p, dt)
    th = kappa * s * v * dt * n
    np.testing.assert_allclose(x[:3], [0.0, (np.cos(th) - 1) / kappa, np.sin(th) / kappa], atol=1e-8)


def test_speed_scale_default_is_bit_identical_to_the_commanded_speed():
    m = MODELS.get("unicycle")()
    rng = np.random.default_rng(0)
    x, u = rng.normal(size=(50, 6)) * 0.3, rng.normal(size=(50, 2))
    p = m.param_arrays()
    bare = {"kappa": p["kappa"]}  # a parameter mapping without the scale means 1
    assert np.array_equal(m.f(x, u, p), m.f(x, u, bare))
    assert np.array_equal(m.step(x, u, p, 0.05), m.step(x, u, bare, 0.05))


def test_negative_curvature_is_the_same_path_as_roll_plus_pi():
    """The symmetry the fits rely on to report a negative kappa as the roll + pi: the same vector field
    for every state and input."""
    m = MODELS.get("unicycle")()
    assert m.curvature_roll_state == "gamma" and MODELS.get("modified_unicycle").curvature_roll_state is None
    rng = np.random.default_rng(1)
    x, u = rng.normal(size=(40, 6)) * 0.4, rng.normal(size=(40, 2))
    p = {"kappa": np.asarray(0.013), "speed_scale": np.asarray(0.9)}
    x2 = x.copy()
    x2[:, 5] += np.pi
    np.testing.assert_allclose(m.f(x, u, p), m.f(x2, u, {**p, "kappa": -p["kappa"]}), atol=1e-12)


# ---------------------------------------------------------------------------------------------- rotations
def test_quaternions_agree_with_scipy():
    r = Rotation.random(500, random_state=3)
    xyzw = r.as_quat()
    wxyz = np.c_[xyzw[:, 3], xyzw[:, :3]]
    np.testing.assert_allclose(quaternion_to_matrix(wxyz), r.as_matrix(), atol=1e-12)
    np.testing.assert_allclose(quaternion_to_matrix(2.5 * wxyz), r.as_matrix(), atol=1e-12)  # any length
    q = matrix_to_quaternion(r.as_matrix())
    assert (q[:, 0] >= 0).all()
    np.testing.assert_allclose(q, wxyz * np.sign(wxyz[:, :1]), atol=1e-12)
    # rotations by pi (w = 0), where the trace method alone loses the axis
    for axis in np.eye(3):
        R = so3_exp(np.pi * axis)
        np.testing.assert_allclose(quaternion_to_matrix(matrix_to_quaternion(R)), R, atol=1e-12)


def test_trial_frame_recovers_a_circle_seen_from_anywhere():
    """A unicycle circle (bending toward -y) seen by a tracker placed anywhere, its coil rolled in the
    needle: the frame maths give back the model frame exactly (origin, axes, roll)."""
    kappa, s = 0.01, np.linspace(0.0, 40.0, 200)
    th = kappa * s
    pos = np.c_[np.zeros_like(s), (np.cos(th) - 1) / kappa, np.sin(th) / kappa]
    rot = euler_xyz_to_matrix(th, 0 * th, 0 * th)  # R = Rx(kappa s): tangent R e3
    A, b, roll = so3_exp(np.radians([10.0, 80.0, 25.0])), np.array([120.0, -40.0, 15.0]), np.radians(35.0)
    p_tr, r_tr = pos @ A.T + b, A @ rot @ rot_z(roll)
    ok = np.ones(len(s), dtype=bool)
    i, j, _, n = chord_pairs(p_tr, ok, 15, 1.0)
    psi, _ = bend_roll(body_bend(r_tr[i], r_tr[j], n))
    np.testing.assert_allclose(psi, -roll, atol=1e-9)
    G = pose_axes(rolled(r_tr[0], psi))
    p2, r2 = express(G, p_tr[0], p_tr, rolled(r_tr, psi))
    np.testing.assert_allclose(p2, pos, atol=1e-9)
    np.testing.assert_allclose(r2, rot, atol=1e-9)
    # from the positions alone: z along the first chord, which is kappa * chord / 2 off the tangent (about
    # body x, in the plane of the path); the bending still on -y
    G2, p0, info = path_frame(p_tr, ok, chord=1.0)
    err = so3_exp(np.zeros(3)).T @ (G2 @ A)  # the frame's axes against the model's
    rv = Rotation.from_matrix(err).as_rotvec()
    np.testing.assert_allclose(rv, [-kappa * 1.0 / 2, 0.0, 0.0], atol=1e-4)  # chord: 1 mm to 1 mm + a sample
    assert info["bend_from"].startswith("mean deviation")


# ---------------------------------------------------------------------------------------------- CSV layouts
def _lab_exports(root: Path, *, lead: dict | None = None) -> dict:
    """Two trials of a lab's exports written by hand: a bevel-tip circle (kappa 0.01 1/mm, bending toward
    the model's -y) inserted along the tracker's +x (the unicycle would be singular there), the coil
    rolled 30 deg in the needle, positions in m, one row per 0.5 mm step at 2 mm/s (0.25 s), quaternions,
    an rms column (mm), all-zero rows where the tip was lost, ``lead[id]`` leading zero rows; a command
    file per trial. Returns the truth per trial in the model frame."""
    lead = lead or {}
    A = so3_exp(np.radians([0.0, 90.0, 0.0]))  # model z -> tracker x
    b = np.array([50.0, 20.0, -10.0])
    kappa, step = 0.01, 0.5
    truth = {}
    (root / "exports").mkdir(parents=True, exist_ok=True)
    for tid, dc, lost in (("A1", 0.25, [5, 6]), ("A2", 0.5, [9])):
        n = 60
        s = step * np.arange(n)
        th = kappa * s
        pos = np.c_[np.zeros(n), (np.cos(th) - 1) / kappa, np.sin(th) / kappa]
        rot = euler_xyz_to_matrix(th, 0 * th, 0 * th)
        p_tr = (pos @ A.T + b) / 1000.0  # m
        q = matrix_to_quaternion(A @ rot @ rot_z(np.radians(30.0)))
        rms = 0.1 + 0.002 * np.arange(n)
        rows = np.c_[np.arange(n), p_tr, q, rms]
        dead = np.zeros(n, dtype=bool)
        dead[lost] = True
        dead[: lead.get(tid, 0)] = True
        rows[dead, 1:] = 0.0
        lines = ["index,X,Y,Z,q0,q1,q2,q3,err"] + [",".join(f"{v:.10g}" for v in r) for r in rows]
        (root / "exports" / f"{tid}_dc{dc}_pose.csv").write_text("\n".join(lines) + "\n")
        (root / "exports" / f"{tid}_cmd.txt").write_text(f"step_length {step}\nspeed 2.0\nrotation_speed 0\n")
        truth[tid] = (pos, rot, dead)
    mapping = {
        "description": "hand-written lab exports",
        "discover": {"files": "exports/{id}_dc{duty_cycle}_pose.csv", "meta_file": "exports/{id}_cmd.txt",
                     "meta": {"needle": "nitinol"}},
        "factors": ["duty_cycle"],
        "time": {"formula": "row * step_length / speed"},
        "missing": {"zero_rows": True},
        "frame": {"reference": "em"},
        "inputs": {"v": {"value": "speed", "unit": "mm/s"}, "u": {"value": "rotation_speed", "unit": "deg/s"}},
        "sensors": {
            "em": {"file": "{id}_dc{duty_cycle}_pose.csv", "columns": {"x": "X", "y": "Y", "z": "Z"},
                   "units": ["m", "m", "m"], "quaternion": {"w": "q0", "x": "q1", "y": "q2", "z": "q3"},
                   "sigma_column": "err", "sigma_unit": "mm",
                   "sensor": {"type": "position", "axes": ["x", "y", "z"], "sigma": 0.15}},
            "tangent": {"file": "{id}_dc{duty_cycle}_pose.csv", "quaternion": {"w": "q0", "x": "q1", "y": "q2", "z": "q3"},
                        "missing": {"zero_rows": True}, "sensor": {"type": "tangent", "sigma": 0.01}},
        },
        "truth": {"file": "{id}_dc{duty_cycle}_pose.csv", "columns": {"x": "X", "y": "Y", "z": "Z"},
                  "units": ["m", "m", "m"], "quaternion": {"w": "q0", "x": "q1", "y": "q2", "z": "q3"}},
    }
    (root / "mapping.yaml").write_text(yaml.safe_dump(mapping, sort_keys=False))
    return truth


def test_lab_exports_import_with_a_mapping_alone(tmp_path):
    truth = _lab_exports(tmp_path, lead={"A2": 3})
    res = run("log", "import-csv", tmp_path / "mapping.yaml", "--out", tmp_path / "lab.h5")
    assert res.exit_code == 0, res.output
    log = read_log(tmp_path / "lab.h5")
    assert [t.id for t in log.trials] == ["A1", "A2"]
    a1, a2 = log.trials
    # metadata from the file name (numbers) and the command file; the design factor listed
    assert a1.meta["duty_cycle"] == 0.25 and a2.meta["duty_cycle"] == 0.5 and a1.meta["needle"] == "nitinol"
    assert a1.meta["step_length"] == 0.5 and json.loads(a1.meta["design_factors"]) == ["duty_cycle"]
    # step-indexed: t = row * 0.5 mm / 2 mm/s; rates from the data; inputs from the command file
    em = a1.sensors["em"]
    np.testing.assert_allclose(em.t, 0.25 * np.arange(60))
    assert em.settings["rate"] == pytest.approx(4.0)
    np.testing.assert_allclose(a1.inputs["v"].value, [[2.0]])
    # all-zero rows are lost samples, counted with their reason
    assert (~em.valid).nonzero()[0].tolist() == [5, 6]
    rep = json.loads(a1.meta["import_report"])
    assert rep["streams"]["em"]["invalid"] == {"all-zero row": 2}
    # trial frame: back to the model frame (m -> mm; origin, insertion along z, bending on -y, the roll undone)
    pos, rot, dead = truth["A1"]
    np.testing.assert_allclose(em.value[em.valid], pos[~dead], atol=1e-6)
    np.testing.assert_allclose(a1.sensors["tangent"].value[em.valid], rot[~dead][:, :, 2], atol=1e-9)
    tn = list(a1.truth.names)
    np.testing.assert_allclose(a1.truth.state[:, [tn.index(k) for k in ("alpha", "beta", "gamma")]],
                               np.c_[0.01 * 0.5 * np.nonzero(~dead)[0], np.zeros((58, 2))], atol=1e-9)
    # per-sample sigma, in mm
    np.testing.assert_allclose(em.sigma[em.valid][:, 0], (0.1 + 0.002 * np.arange(60))[~dead])
    # A2: three leading lost rows -> the trial starts at the first valid sample (t = 0 there), said so
    e2 = a2.sensors["em"]
    assert len(e2.t) == 57 and e2.t[0] == 0.0 and e2.valid[0]
    rep2 = json.loads(a2.meta["import_report"])
    assert rep2["start"]["first_valid_row"] == 3 and rep2["start"]["first_valid_time_s"] == pytest.approx(0.75)
    pos2, _, _ = truth["A2"]
    np.testing.assert_allclose(e2.value[e2.valid][0], [0.0, 0.0, 0.0], atol=1e-9)  # origin: that pose
    info = run("log", "info", tmp_path / "lab.h5")
    assert info.exit_code == 0, info.output
    out = info.output
    assert "design factors: duty_cycle = 0.25" in out and "lost: 2 all-zero row" in out
    assert "started at the first valid em sample (row 3, 0.75 s)" in out
    assert "rolled -30.0 deg (bending onto -y)" in out and "per-sample sigma" in out


def test_leading_invalid_keep_and_trim_are_said(tmp_path):
    _lab_exports(tmp_path, lead={"A2": 8})
    mp = yaml.safe_load((tmp_path / "mapping.yaml").read_text())
    for mode in ("keep", "trim"):
        mp["leading_invalid"] = mode
        mp.pop("frame", None)
        mp["sensors"]["em"].pop("quaternion", None)  # used only by the frame
        (tmp_path / "m.yaml").write_text(yaml.safe_dump(mp))
        res = run("log", "import-csv", tmp_path / "m.yaml", "--out", tmp_path / f"{mode}.h5")
        assert res.exit_code == 0, res.output
        a2 = read_log(tmp_path / f"{mode}.h5").trials[1]
        e2 = a2.sensors["em"]
        if mode == "keep":
            assert len(e2.t) == 60 and not e2.valid[:8].any()
        else:
            assert len(e2.t) == 52 and e2.t[0] == pytest.approx(2.0) and e2.valid[0]
        info = run("log", "info", tmp_path / f"{mode}.h5").output
        assert f"start ({mode})" in info
        assert ("first valid em sample is at 2 s" in info) if mode == "keep" else ("8 leading invalid rows" in info)
        assert "warning: em: first valid sample at 2 s" in info


@pytest.mark.parametrize("change, expect", [
    (lambda m: m["time"].update(formula="row * step_length / sped"), "unknown name 'sped'"),
    (lambda m: m["time"].update(formula="__import__('os')"), "is not allowed"),
    (lambda m: m["discover"].update(files="exports/*_pose.csv"), "must have an {id} field"),
    (lambda m: m.update(factors=["duty_cycle", "tissue"]), "design factor 'tissue' is not in its metadata"),
    (lambda m: m["sensors"]["em"].pop("quaternion") and m.pop("frame") and m["sensors"]["tangent"].update(
        sensor={"type": "position", "axes": ["x"], "sigma": 1.0}, columns={"x": "X"}), "would be unused"),
    (lambda m: m["time"].update(period=0.25), "give exactly one of column, period, formula"),
    (lambda m: m["inputs"]["v"].update(file="x.csv"), "give either file and column, or value"),
    (lambda m: m["frame"].update(reference="camera"), "[frame -> reference] no stream 'camera'"),
])
def test_bad_mapping_gets_one_clear_error(tmp_path, change, expect):
    _lab_exports(tmp_path)
    mp = yaml.safe_load((tmp_path / "mapping.yaml").read_text())
    change(mp)
    (tmp_path / "m.yaml").write_text(yaml.safe_dump(mp))
    res = run("log", "import-csv", tmp_path / "m.yaml", "--out", tmp_path / "x.h5")
    assert res.exit_code == 2, res.output
    lines = error_lines(res)
    assert len(lines) == 1 and expect in lines[0], res.output
    assert not (tmp_path / "x.h5").exists()


def test_command_files_in_every_common_form(tmp_path):
    from needlecli.io.csv_layout import read_meta_file

    forms = {"a.csv": "step_mm,0.5\nspeed,2\n", "b.csv": "step_mm,speed,operator\n0.5,2,jo\n",
             "c.txt": "step_mm = 0.5\nspeed: 2\n# comment\n", "d.yaml": "step_mm: 0.5\nspeed: 2\n",
             "e.txt": "step_mm\t0.5\nspeed\t2\n"}
    for name, text in forms.items():
        (tmp_path / name).write_text(text)
        meta = read_meta_file(tmp_path / name)
        assert meta["step_mm"] == 0.5 and meta["speed"] == 2, (name, meta)
    assert read_meta_file(tmp_path / "b.csv")["operator"] == "jo"
