"""Bringing a lab's own recorded data (issue 18): the insertion-speed scale of the kinematic models, the
quaternion and trial-frame maths, the CSV layouts of real exports (step-indexed rows, file-name templates,
command files, all-zero rows, quaternions, per-sample sigmas, trial starts and frames), and the whole path
from exports to per-trial fits and a regression on a design factor, on a synthetic set whose truth is known.

References are independent of the code under test: the unicycle's exact circle (a rigid body turning at
``kappa * (speed_scale v)`` about body x), scipy's rotations for the quaternions, ordinary least squares by
``numpy.polyfit`` for the regression, the simulation's own parameters for the recovery.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from typer.testing import CliRunner

from needlecli.cli.app import app
from needlecli.io.frames import bend_roll, body_bend, chord_pairs, express, path_frame, pose_axes, rolled
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
