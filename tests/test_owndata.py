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


def test_command_file_layouts_by_their_content(tmp_path):
    """One-line JSON in a .txt file is a mapping (not name,value text); a header with one identical row per
    step gives its constant columns; two columns of texts over two read either way and are refused; a name,
    value file whose first value is a text stays name,value lines."""
    from needlecli.errors import NeedleError
    from needlecli.io.csv_layout import read_meta_file

    forms = {"json.txt": ('{"speed": 2, "operator": "jo"}', {"speed": 2, "operator": "jo"}),
             "steps.csv": ("speed,duty_cycle,operator\n2,0.2,jo\n2,0.2,jo\n2,0.2,jo\n",
                           {"speed": 2, "duty_cycle": 0.2, "operator": "jo"}),
             "steps2.csv": ("speed,duty_cycle\n2,0.2\n2,0.2\n", {"speed": 2, "duty_cycle": 0.2}),
             "texts.csv": ("operator,jo\nspeed,2\nstep_mm,0.5\n", {"operator": "jo", "speed": 2, "step_mm": 0.5}),
             "blank.txt": ("\nspeed = 2\n\n# c\nstep_mm: 0.5\n\n", {"speed": 2, "step_mm": 0.5})}
    for name, (text, want) in forms.items():
        (tmp_path / name).write_text(text)
        assert read_meta_file(tmp_path / name) == want, name
    for name, text, said in (("amb.csv", "operator,needle\njo,nitinol\n", "two readings hold"),
                             ("vary.csv", "speed,duty_cycle\n2,0.2\n2,0.3\n", "[line 3, column duty_cycle] the column varies"),
                             ("twice.txt", "speed 2\n\nspeed 2\n", "[line 3, column 1] 'speed' is given twice (first on line 1)")):
        (tmp_path / name).write_text(text)
        with pytest.raises(NeedleError) as e:
            read_meta_file(tmp_path / name)
        assert said in str(e.value), str(e.value)


def test_csv_blank_lines_at_the_end_are_ignored(tmp_path):
    from needlecli.io.csv_import import read_csv

    (tmp_path / "a.csv").write_text("t,x\n0,1\n1,2\n,\n\n  \n")  # a row of empty cells is a row (a lost sample)
    d = read_csv(tmp_path / "a.csv", ["t", "x"])
    np.testing.assert_array_equal(d["t"][:2], [0.0, 1.0])
    assert len(d["t"]) == 3 and np.isnan(d["x"][2])


def test_frame_bend_from_the_path_matches_the_orientations(tmp_path):
    """``frame.bend: path`` (the roll from the path's deviation from the initial tangent) puts the hand-written
    exports' circle where the orientations put it: on the model's own circle, bending toward -y."""
    truth = _lab_exports(tmp_path)
    mp = yaml.safe_load((tmp_path / "mapping.yaml").read_text())
    mp["frame"] = {"reference": "em", "z": "orientation", "bend": "path"}
    (tmp_path / "m.yaml").write_text(yaml.safe_dump(mp))
    res = run("log", "import-csv", tmp_path / "m.yaml", "--out", tmp_path / "b.h5")
    assert res.exit_code == 0, res.output
    a1 = read_log(tmp_path / "b.h5").trials[0]
    em = a1.sensors["em"]
    pos, rot, dead = truth["A1"]
    np.testing.assert_allclose(em.value[em.valid], pos[~dead], atol=1e-6)
    rep = json.loads(a1.meta["import_report"])["frame"]
    assert rep["bend_from"].startswith("mean deviation of the path") and rep["roll_psi_deg"] == pytest.approx(-30.0, abs=1e-6)


def test_initial_directions_and_axis_angles():
    """Paths along known directions (in any length unit, with lost samples first) start along them: the
    angle to +z is the one they were drawn at; a path of one valid sample has none."""
    from needlecli.io.frames import axis_angles, initial_directions

    ang = np.radians([0.0, 35.0, 90.0, 176.0])
    s = np.linspace(0.0, 40.0, 81)
    d = np.c_[np.zeros(4), np.sin(ang), np.cos(ang)]  # (4, 3)
    pos = s[None, :, None] * d[:, None, :] + np.array([5.0, -3.0, 100.0])
    pos[1] *= 1e-3  # metres
    ok = np.ones(pos.shape[:2], dtype=bool)
    ok[2, :7] = False
    pos[2, :7] = 0.0  # a tracker's zero rows, marked lost
    ok[3, 1:] = False
    got = axis_angles(initial_directions(pos, ok), np.array([0.0, 0.0, 1.0]))
    np.testing.assert_allclose(got[:3], [0.0, 35.0, 90.0], atol=1e-6)
    assert np.isnan(got[3])


def test_a_fitted_value_outside_its_bounds_is_never_identified():
    """A drift constant whose schema says g > 0, fitted on data drifting backwards (g = -0.5, well
    measured): the likelihood identifies it sharply, the verdict is "outside its bounds", per trial and
    pooled; the same data drifting forwards are identified."""
    from pydantic import Field

    from needlecli.fitting.identify import IDENTIFIED, OUTSIDE, Bounds, identify, parameter_bounds
    from needlecli.fitting.statespace import DiscreteModel, MeasurementModel
    from needlecli.models.base import Model, ModelParams

    class P(ModelParams):
        g: float = Field(0.5, gt=0.0, le=2.0, description="drift per unit input")

    class Drift(Model):
        state_names, state_units = ("a",), ("mm",)
        input_names, input_sizes, input_units = ("u",), {"u": 1}, {"u": "1"}
        Params = P

        def f(self, x, u, p):
            return (p["g"] * u[..., 0])[..., None] + 0.0 * x

        def initial_state(self, p):
            return np.zeros(1)

    assert parameter_bounds(Drift, "g") == Bounds(0.0, 2.0, True, False)
    assert str(parameter_bounds(MODELS.get("unicycle"), "speed_scale")) == "(0, 2]"
    assert str(parameter_bounds(MODELS.get("unicycle"), "kappa")) == "[0, inf)"
    N, T, dt = 3, 120, 0.1
    rng = np.random.default_rng(4)
    u = np.ones((N, T, 1))
    for g, want in ((-0.5, OUTSIDE), (0.5, IDENTIFIED)):
        y = (g * dt * np.arange(T) + 0.05 * rng.standard_normal((N, T)))[..., None]
        dm = DiscreteModel(Drift(P()), {"g": np.full(N, g)}, ("g",), dt, np.arange(T), u, None)
        mm = MeasurementModel("pos", lambda z: z[..., :1], 1, np.arange(T), y, np.ones((N, T), bool),
                              np.zeros(1, bool), names=("a",), units=("mm",))
        x0 = np.c_[np.zeros(N), np.full(N, g)]
        res = identify(dm, [mm], x0, np.zeros((2, 2)), np.zeros((N, 2, 2)), [np.full((N, 1, 1), 0.0025)],
                       np.ones(N, bool), const_sd=np.full((N, 1), 0.01))
        k = res.names.index("g")
        assert (res.verdict[:, k] == want).all() and res.pooled_verdict[k] == want, (g, res.verdict, res.reason)
        assert (res.rse[:, k] < 0.05).all()  # sharply identified by the likelihood either way
        if want == OUTSIDE:
            assert "g = -0.5 is outside its bounds (0, 2]" in res.reason[0, k]


# ---------------------------------------------------------------------------------------------- end to end
KAPPA0, SLOPE = 0.012, -0.012  # the study's law: kappa = 0.012 (1 - duty_cycle) 1/mm


def _fit_config(tmp: Path, log: Path, *, speed_scale: bool) -> Path:
    """The shipped fit config (with the speed scale, or the same fit without it) on ``log``."""
    name = "fit.yaml" if speed_scale else "fit_no_scale.yaml"
    cfg = yaml.safe_load((ROOT / "configs/owndata" / name).read_text())
    cfg["source"]["logs"] = [str(log)]
    p = tmp / name
    p.write_text(yaml.safe_dump(cfg, sort_keys=False))
    return p


@pytest.fixture(scope="module")
def study(tmp_path_factory):
    """configs/owndata/study.yaml simulated, made a log, exported as a lab would (step-indexed, zero rows,
    quaternions, rms; the tracker placed elsewhere and its coil rolled 35 deg), imported by the mapping
    the export wrote, and fitted by EM with and without the speed scale: what ``make owndata`` does."""
    d = tmp_path_factory.mktemp("owndata")
    steps = [
        ("simulate", ROOT / "configs/owndata/study.yaml", "--out", d / "study.h5", "--quiet"),
        ("log", "from-results", d / "study.h5", "--out", d / "study_log.h5"),
        ("log", "export-csv", d / "study_log.h5", "--out", d / "exports", "--tracker-pose", "10,80,25,120,-40,15",
         "--sensor-roll", "35"),
        ("log", "import-csv", d / "exports" / "mapping.yaml", "--out", d / "lab.h5"),
        ("fit-em", _fit_config(d, d / "lab.h5", speed_scale=True), "--out", d / "fit.h5", "--quiet"),
        ("fit-em", _fit_config(d, d / "lab.h5", speed_scale=False), "--out", d / "fit_no_scale.h5", "--quiet"),
    ]
    for args in steps:
        res = run(*args)
        assert res.exit_code == 0, (args, res.output)
    return d


def test_exports_have_the_lab_shape_and_import_back(study):
    """The exports are what the issue describes (no time column, zero rows, quaternions, a command file),
    and the import gives back the simulation: the same samples lost, the orientation exactly, the
    positions up to the tracker's noise at the first valid sample (the trial's origin), the design factor."""
    from needlecli.io.results import read_results

    head = (study / "exports" / "run0005_pose.csv").read_text().splitlines()
    assert head[0] == "step,px,py,pz,qw,qx,qy,qz,rms" and head[1] == "0,0,0,0,0,0,0,0,0"  # run 5: lost at first
    assert "duty_cycle,0.2" in (study / "exports" / "run0005_cmd.csv").read_text()
    sim = read_results(study / "study.h5")
    meas = sim.data["measurements"].data["tracker"]
    truth = sim.data["truth"].data["state"]
    log = read_log(study / "lab.h5")
    for r, tr in enumerate(log.trials):
        em = tr.sensors["tracker"]
        valid = meas.data["valid"][r]
        first = int(np.argmax(valid))  # the trial starts at its first valid sample
        assert tr.meta["duty_cycle"] == pytest.approx([0.0, 0.2, 0.4, 0.6][r // 3])
        np.testing.assert_array_equal(em.valid, valid[first:])
        np.testing.assert_allclose(em.t, meas.data["t"][first:] - meas.data["t"][first], atol=1e-9)
        x0 = truth[r, meas.data["index"][first]]
        R0 = euler_xyz_to_matrix(*x0[3:6])  # the frame: that pose's axes, its measured position the origin
        v = meas.data["value"][r][first:]
        np.testing.assert_allclose(em.value[em.valid], ((v - v[0]) @ R0)[em.valid], atol=1e-5)  # 9 digits written
        k = meas.data["index"][first:][em.valid]
        tn = list(tr.truth.names)
        Rt = tr.truth.state[:, [tn.index(f"R{i}{j}") for i in range(1, 4) for j in range(1, 4)]].reshape(-1, 3, 3)
        np.testing.assert_allclose(Rt, R0.T @ euler_xyz_to_matrix(*truth[r, k, 3:6].T), atol=1e-7)  # rolled back
        np.testing.assert_allclose(em.sigma[em.valid], sim.data["measurements"].data["tracker"].data["sigma"][r][first:][em.valid],
                                   rtol=1e-8)
    rep = json.loads(log.trials[5].meta["import_report"])
    assert rep["start"]["first_valid_row"] == 2 and rep["frame"]["roll_psi_deg"] == pytest.approx(-35.0, abs=1e-6)


def test_fit_recovers_the_curvature_law_and_the_slip(study, monkeypatch):
    """EM with the speed scale: the regression of the fitted kappa on the duty cycle has the true slope and
    intercept within two standard errors (from the spread across trials), the same numbers as numpy's
    least squares; every trial's slip within 0.01 of the truth; needle evaluate writes the tables and
    plots (the magnetic needle EM paper's Fig. 5 on a unicycle fit, the regression with its data)."""
    from needlecli.io.fit import read_fit
    from needlecli.io.results import read_results
    from needlecli.reports import design

    fit = read_fit(study / "fit.h5")
    sim = read_results(study / "study.h5")
    g = fit.data["fit"].data["unicycle"]
    k, s = (np.asarray(g.data["constant"].data[c]) for c in ("kappa", "speed_scale"))
    true_s = sim.data["truth"].data["params"].data["speed_scale"][:, 0]
    assert np.abs(s - true_s).max() < 0.01
    dc = fit.data["truth"].data["meta"].data["duty_cycle"]
    assert list(fit.data["truth"].data["meta"].attrs["design_factors"]) == ["duty_cycle"]
    table = design.fit_regression(fit)
    row = table[table["Constant"].str.startswith("kappa")].iloc[0]
    keep = ~np.isin(np.asarray(g.data["status"]).astype(str), ("singular", "diverged"))
    slope, intercept = np.polyfit(dc[keep], k[keep], 1)
    assert row["Slope"] == pytest.approx(slope, rel=1e-9) and row["Intercept"] == pytest.approx(intercept, rel=1e-9)
    assert abs(row["Slope"] - SLOPE) < 2 * row["Slope SE"] and abs(row["Intercept"] - KAPPA0) < 2 * row["Intercept SE"]
    assert row["R^2"] > 0.9 and "spread of the per-trial estimates" in row["SE from"]
    by = design.fit_by_design(fit)
    assert sorted(by["Level"].unique()) == pytest.approx([0.0, 0.2, 0.4, 0.6])
    # needle evaluate on the fit: every fit table, Fig. 5 of a unicycle fit, the regression plot with its data
    drawn = {}

    def keep_figure(fig, path):
        drawn[Path(path).name] = [ln.get_xydata() for ax in fig.axes for ln in ax.get_lines()]
        return path

    monkeypatch.setattr(design, "save_figure", keep_figure)
    res = run("evaluate", study / "fit.h5", "--out", study / "tables", "--regress", "kappa:duty_cycle",
              "--group-by", "duty_cycle")
    assert res.exit_code == 0, res.output
    assert (study / "tables" / "owndata_fit_fit_paths.png").stat().st_size > 1000
    pts = drawn["owndata_fit_fit_regression.png"]
    assert any(np.allclose(np.sort(p[:, 0]), np.sort(dc[keep & (np.asarray(g.data["status"]) == "ok")])) for p in pts)
    for t in ("fit_by_design", "fit_regression", "fit_warnings", "fit_status"):
        assert (study / "tables" / f"owndata_fit_{t}.tex").exists()


def test_without_the_speed_scale_the_bias_shows(study):
    """The same fit taking the commanded speed as the actual one: every curvature comes out low (the slip
    pushed into the position process noise along the needle), and the law's intercept is off by more than
    two standard errors."""
    from needlecli.io.fit import read_fit
    from needlecli.io.results import read_results
    from needlecli.reports.design import fit_regression

    sim = read_results(study / "study.h5")
    true_k = sim.data["truth"].data["params"].data["kappa"][:, 0]
    fits = {n: read_fit(study / f"{n}.h5") for n in ("fit", "fit_no_scale")}
    ratio = {n: np.asarray(f.data["fit"].data["unicycle"].data["constant"].data["kappa"]) / true_k
             for n, f in fits.items()}
    assert 0.95 < np.median(ratio["fit"]) < 1.05
    assert np.median(ratio["fit_no_scale"]) < 0.95 and np.mean(ratio["fit_no_scale"]) < 0.9
    qz = {n: np.median(np.sqrt(np.asarray(f.data["fit"].data["unicycle"].data["Q"])[:, 2, 2])) for n, f in fits.items()}
    assert qz["fit_no_scale"] > 3 * qz["fit"]
    row = fit_regression(fits["fit_no_scale"]).iloc[0]
    assert KAPPA0 - row["Intercept"] > 2 * row["Intercept SE"]


def test_a_negative_curvature_is_reported_as_the_roll_plus_pi(study, tmp_path):
    """Started with the roll off by pi (and held there by its prior), EM bends the path the right way with
    a negative kappa; the fit file reports |kappa| with gamma + pi, flags the trials, says so in the
    reason and in fit_warnings: the same kappa as the fit started right."""
    from needlecli.io.fit import read_fit
    from needlecli.reports.design import fit_warnings

    cfg = yaml.safe_load((study / "fit.yaml").read_text())
    cfg["source"]["trials"] = ["run0000", "run0006"]
    cfg["fit"]["init"]["values"]["gamma"] = float(np.pi)
    cfg["fit"]["p0"]["gamma"] = 1e-4
    cfg["fit"]["em"]["max_iter"] = 60
    (tmp_path / "flip.yaml").write_text(yaml.safe_dump(cfg))
    res = run("fit-em", tmp_path / "flip.yaml", "--out", tmp_path / "flip.h5")
    assert res.exit_code == 0, res.output
    g = read_fit(tmp_path / "flip.h5").data["fit"].data["unicycle"]
    assert np.asarray(g.data["roll_flipped"]).all()
    k = np.asarray(g.data["constant"].data["kappa"])
    ref = np.asarray(read_fit(study / "fit.h5").data["fit"].data["unicycle"].data["constant"].data["kappa"])[[0, 6]]
    np.testing.assert_allclose(k, ref, rtol=0.05)
    names = list(g.attrs["names"])
    assert np.abs(np.asarray(g.data["x0"])[:, names.index("gamma")]).max() < 0.1  # pi + pi, wrapped
    assert all("kappa < 0 fitted: reported as -kappa with gamma + pi" in r for r in np.asarray(g.data["reason"]).astype(str))
    w = fit_warnings(read_fit(tmp_path / "flip.h5"))
    assert (w["Warning"].str.contains("negative kappa fitted")).sum() == 2
    assert "negative curvature in 2 of 2 trial(s): run0000, run0006" in res.output


def test_per_sample_sigmas_weigh_each_sample():
    """A tip at rest measured with a recorded sigma per sample: the smoother's estimate is the weighted
    mean sum(y_i / s_i^2) / sum(1 / s_i^2) with its variance 1 / sum(1 / s_i^2) (a closed form), where the
    same samples with the nominal sigma give the plain mean."""
    from needlecli.fitting.smoother import eks
    from needlecli.fitting.statespace import DiscreteModel, MeasurementModel

    model = MODELS.get("unicycle")()
    M = 40
    rng = np.random.default_rng(5)
    s = rng.uniform(0.1, 1.0, size=(1, M, 3))
    y = rng.normal(size=(1, M, 3)) * s + np.array([1.0, -2.0, 3.0])
    ticks = np.arange(M)
    dm = DiscreteModel(model, model.param_arrays(), (), 0.1, ticks, np.zeros((1, M, 2)))
    h = model.tip_position
    ref = 0.5
    for scale, w in ((s / ref, 1.0 / s**2), (None, np.ones_like(s))):
        mm = MeasurementModel("p", h, 6, ticks, y, np.ones((1, M), dtype=bool), np.zeros(3, dtype=bool),
                              ("x", "y", "z"), ("mm",) * 3, False, scale)
        P0 = np.diag([1e6] * 3 + [1e-12] * 3)
        res = eks(dm, [mm], np.zeros((1, 6)), P0, np.zeros((6, 6)), [np.eye(3) * ref**2])
        mean = (w * y).sum(1) / w.sum(1)
        var = (ref**2 if scale is None else 1.0) / w.sum(1)
        np.testing.assert_allclose(res.sm.m[0, 0, :3], mean[0], rtol=1e-6)
        np.testing.assert_allclose(np.diagonal(res.sm.P[0, 0])[:3], var[0], rtol=1e-5)


# a trial that diverges makes numerics/kalman.py's rts_smoother symmetrise inf - inf (a RuntimeWarning there,
# before the trial is marked singular): not what this test is about
@pytest.mark.filterwarnings("ignore:invalid value encountered:RuntimeWarning")
def test_a_fit_on_raw_exports_says_what_in_the_data_is_wrong(tmp_path):
    """Issue 18's first encounter: the exports imported without the lost-row rule and without a trial frame
    (an insertion along the tracker's x, rows of zeros read as positions). EM fails at the unicycle's
    singularity; the reason says which data caused it, not only the model."""
    _lab_exports(tmp_path)
    mp = yaml.safe_load((tmp_path / "mapping.yaml").read_text())
    for k in ("frame", "missing"):
        mp.pop(k)
    for k in ("quaternion", "sigma_column", "sigma_unit"):  # (a zero rms would mark the zero rows lost)
        mp["sensors"]["em"].pop(k)
    mp["sensors"].pop("tangent")
    mp["truth"].pop("quaternion")
    (tmp_path / "raw.yaml").write_text(yaml.safe_dump(mp))
    assert run("log", "import-csv", tmp_path / "raw.yaml", "--out", tmp_path / "raw.h5").exit_code == 0
    cfg = yaml.safe_load((ROOT / "configs/owndata/fit.yaml").read_text())
    cfg["source"] = {"logs": [str(tmp_path / "raw.h5")]}
    cfg["fit"]["measurements"] = {"em": {"sigma": 0.2}}
    cfg["fit"]["init"]["first_measurement"] = {"x": "em.x", "y": "em.y", "z": "em.z"}
    cfg["fit"]["em"]["max_iter"] = 5
    (tmp_path / "raw_fit.yaml").write_text(yaml.safe_dump(cfg))
    res = run("fit-em", tmp_path / "raw_fit.yaml", "--out", tmp_path / "raw_fit.h5")
    assert res.exit_code == 0, res.output
    from needlecli.io.fit import read_fit

    g = read_fit(tmp_path / "raw_fit.h5").data["fit"].data["unicycle"]
    reasons = np.asarray(g.data["reason"]).astype(str)
    assert (np.asarray(g.data["status"]).astype(str) == "singular").all(), reasons
    assert "samples of em are exactly zero and marked valid" in reasons[0]  # A1 has two zero rows
    assert all("deg from the model's +z: express the trial in its own frame" in r for r in reasons)


def test_the_readme_mapping_is_a_valid_mapping_and_says_what_export_csv_writes(study):
    """The tutorial's mapping (docs/tutorials/own-data.md, "Bringing your own recorded data") passes the
    schema and has the keys the export writes for the synthetic set (the same layout)."""
    from needlecli.io.csv_import import Mapping

    text = (ROOT / "docs" / "tutorials" / "own-data.md").read_text()
    section = text[text.index("# Bringing your own recorded data"):]
    block = section[section.index("```yaml\n") + 8:]
    doc = yaml.safe_load(block[: block.index("```")])
    Mapping.model_validate(doc)
    written = yaml.safe_load((study / "exports" / "mapping.yaml").read_text())
    for key in ("discover", "factors", "time", "missing", "leading_invalid", "frame", "inputs", "truth"):
        assert doc[key] == written[key], key
    doc_s, wr_s = doc["sensors"]["tracker"], written["sensors"]["tracker"]
    assert {k: v for k, v in doc_s.items() if k != "sensor"} == {k: v for k, v in wr_s.items() if k != "sensor"}
