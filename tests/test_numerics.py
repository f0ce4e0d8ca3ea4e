"""Unit tests of ``needlecli.numerics``: angles, rotations, RK4 and Jacobians.

Every reference is independent of the code under test: closed forms, identities of SO(3), SciPy's matrix
exponential and polar decomposition, or a second numerical method.
"""

from __future__ import annotations

import numpy as np
import pytest
import scipy.linalg
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from needlecli.numerics import (
    angle_diff,
    complex_step_jacobian,
    euler_xyz_to_matrix,
    finite_difference_jacobian,
    hat,
    matrix_to_euler_xyz,
    project_to_so3,
    rk4_step,
    rot_x,
    rot_y,
    rot_z,
    rotation_angle,
    sincos,
    so3_exp,
    so3_log,
    vee,
    wrap_angle,
)
from needlecli.numerics.rotations import orthonormalize

PI = np.pi
FAST = settings(max_examples=60, deadline=None, derandomize=True)

angles = st.floats(-50.0, 50.0, allow_nan=False, allow_infinity=False)
vec3 = hnp.arrays(np.float64, 3, elements=st.floats(-3.0, 3.0, allow_nan=False, allow_infinity=False))
unit_axis = vec3.filter(lambda w: np.linalg.norm(w) > 1e-3).map(lambda w: w / np.linalg.norm(w))


def is_rotation(r: np.ndarray, tol: float = 1e-12) -> bool:
    r = np.asarray(r)
    eye = np.broadcast_to(np.eye(3), r.shape)
    return bool(np.allclose(r @ np.swapaxes(r, -1, -2), eye, atol=tol) and np.allclose(np.linalg.det(r), 1.0, atol=tol))


def random_rotations(rng: np.random.Generator, n: int) -> np.ndarray:
    """Uniform random rotations (QR of Gaussian matrices, sign fixed), independent of so3_exp."""
    q, r = np.linalg.qr(rng.standard_normal((n, 3, 3)))
    q = q * np.sign(np.diagonal(r, axis1=-2, axis2=-1))[..., None, :]
    q[np.linalg.det(q) < 0, :, 0] *= -1.0
    return q


# --------------------------------------------------------------------------------------------- angles
@FAST
@given(angles)
def test_wrap_angle_range_and_congruence(a):
    w = wrap_angle(a)
    assert -PI <= w < PI
    k = (a - w) / (2 * PI)  # a and wrap(a) differ by a whole number of turns
    assert abs(k - round(k)) < 1e-12 * max(1.0, abs(a))


@FAST
@given(angles)
def test_wrap_angle_idempotent(a):
    w = wrap_angle(a)
    assert abs(wrap_angle(w) - w) <= 4 * np.finfo(float).eps * PI


def test_wrap_angle_edges_and_shapes():
    # the half-open range: +pi maps to -pi; one ulp below -pi must not round up to +pi
    assert wrap_angle(PI) == pytest.approx(-PI)
    assert wrap_angle(-PI) == pytest.approx(-PI)
    just_below = np.nextafter(-PI, -np.inf)
    assert -PI <= wrap_angle(just_below) < PI
    a = np.array([[0.0, 2 * PI, -2 * PI], [3 * PI, -3 * PI, 0.5]])
    w = wrap_angle(a)
    assert w.shape == a.shape
    np.testing.assert_allclose(w, [[0, 0, 0], [-PI, -PI, 0.5]], atol=1e-12)
    assert np.all((w >= -PI) & (w < PI))


def test_wrap_angle_in_place_is_the_same():
    """``wrap_angle(a, out=...)`` (in place, the samples of a sensor) gives the same bits as the
    expression, at the cut and its neighbours, zeros of both signs, huge, infinite and NaN angles."""
    k = np.arange(-300, 300)
    c = (2 * k + 1) * PI
    a = np.concatenate([c, np.nextafter(c, np.inf), np.nextafter(c, -np.inf), [0.0, -0.0, 1e300, -1e17, np.inf,
                        np.nan], np.random.default_rng(5).normal(0.0, 50.0, 10_000)]).reshape(-1, 2)
    with np.errstate(invalid="ignore"):
        ref = wrap_angle(a)
        out = np.empty_like(a)
        assert wrap_angle(a, out=out) is out
        b = a.copy()
        wrap_angle(b, out=b)
    for got in (out, b):
        assert np.array_equal(got, ref, equal_nan=True) and np.array_equal(np.signbit(got), np.signbit(ref))


def test_wrap_angle_range_at_odd_multiples_of_pi():
    """Rounding at the branch cut: odd multiples of pi and their neighbours one ulp away, batched."""
    k = np.arange(-3000, 3000)
    c = (2 * k + 1) * PI
    a = np.concatenate([c, np.nextafter(c, np.inf), np.nextafter(c, -np.inf), c + 1e-13, c - 1e-13])
    w = wrap_angle(a)
    assert np.all(w >= -PI) and np.all(w < PI)
    tol = 8 * np.spacing(np.abs(a).max())  # |a| <= 2e4: a itself is known to ~4e-12
    np.testing.assert_allclose(np.cos(w), np.cos(a), atol=tol)
    np.testing.assert_allclose(np.sin(w), np.sin(a), atol=tol)


@FAST
@given(angles, angles)
def test_angle_diff(a, b):
    d = angle_diff(a, b)
    assert -PI <= d < PI
    # same direction: rotating b by d gives a
    assert np.cos(b + d) == pytest.approx(np.cos(a), abs=1e-9)
    assert np.sin(b + d) == pytest.approx(np.sin(a), abs=1e-9)
    # it is the shortest signed difference
    assert abs(d) <= PI
    if abs(abs(d) - PI) > 1e-6:
        assert angle_diff(b, a) == pytest.approx(-d, abs=1e-9)


def test_angle_diff_examples():
    np.testing.assert_allclose(angle_diff(np.deg2rad(179.0), np.deg2rad(-179.0)), np.deg2rad(-2.0), atol=1e-12)
    np.testing.assert_allclose(angle_diff(np.deg2rad(-179.0), np.deg2rad(179.0)), np.deg2rad(2.0), atol=1e-12)
    np.testing.assert_allclose(angle_diff([0.1, 2 * PI + 0.2], [0.0, 0.0]), [0.1, 0.2], atol=1e-12)


# ------------------------------------------------------------------------------------------ hat / vee
@FAST
@given(vec3, vec3)
def test_hat_is_cross_product_and_vee_inverts(w, v):
    k = hat(w)
    np.testing.assert_allclose(k @ v, np.cross(w, v), atol=1e-12)
    np.testing.assert_allclose(k, -k.T, atol=0)
    np.testing.assert_allclose(vee(k), w, atol=0)
    # vee keeps only the skew part
    s = np.outer(v, v)
    np.testing.assert_allclose(vee(k + s), w, atol=1e-12)


def test_hat_vee_batched():
    rng = np.random.default_rng(1)
    w = rng.standard_normal((4, 5, 3))
    v = rng.standard_normal((4, 5, 3))
    k = hat(w)
    assert k.shape == (4, 5, 3, 3)
    np.testing.assert_allclose(np.einsum("...ij,...j->...i", k, v), np.cross(w, v), atol=1e-12)
    np.testing.assert_allclose(vee(k), w, atol=0)


# ---------------------------------------------------------------------------- elementary rotations
def test_elementary_rotations_right_handed():
    a = 0.3
    c, s = np.cos(a), np.sin(a)
    # positive angle turns e2 toward e3 about x, e3 toward e1 about y, e1 toward e2 about z
    np.testing.assert_allclose(rot_x(a) @ [0, 1, 0], [0, c, s], atol=1e-15)
    np.testing.assert_allclose(rot_y(a) @ [0, 0, 1], [s, 0, c], atol=1e-15)
    np.testing.assert_allclose(rot_z(a) @ [1, 0, 0], [c, s, 0], atol=1e-15)
    for i, rot in enumerate((rot_x, rot_y, rot_z)):
        e = np.eye(3)[i]
        np.testing.assert_allclose(rot(a), scipy.linalg.expm(a * hat(e)), atol=1e-14)
    b = np.linspace(-3, 3, 7)
    assert rot_y(b).shape == (7, 3, 3)
    assert is_rotation(rot_y(b))


# ------------------------------------------------------------------------------------------- Euler
@FAST
@given(
    st.floats(-PI + 1e-6, PI - 1e-6),
    st.floats(-PI / 2 + 1e-3, PI / 2 - 1e-3),
    st.floats(-PI + 1e-6, PI - 1e-6),
)
def test_euler_round_trip(a, b, g):
    r = euler_xyz_to_matrix(a, b, g)
    np.testing.assert_allclose(r, rot_x(a) @ rot_y(b) @ rot_z(g), atol=1e-14)
    assert is_rotation(r)
    ang = matrix_to_euler_xyz(r)
    np.testing.assert_allclose(angle_diff(ang, [a, b, g]), 0.0, atol=1e-9)
    # the tangent formula of MODELS.md
    np.testing.assert_allclose(r[:, 2], [np.sin(b), -np.cos(b) * np.sin(a), np.cos(a) * np.cos(b)], atol=1e-15)


def test_matrix_euler_matrix_round_trip_batched():
    r = random_rotations(np.random.default_rng(2), 200)
    ang = matrix_to_euler_xyz(r)
    assert ang.shape == (200, 3)
    assert np.all(np.abs(ang[:, 1]) <= PI / 2)
    np.testing.assert_allclose(euler_xyz_to_matrix(ang[:, 0], ang[:, 1], ang[:, 2]), r, atol=1e-9)


def test_euler_accepts_complex():
    # complex-step Jacobians go through the closed form: d(R)/d(beta) at beta = b
    a, b, g, h = 0.2, -0.4, 1.1, 1e-30
    drdb = euler_xyz_to_matrix(a, b + 1j * h, g).imag / h
    expected = rot_x(a) @ (rot_y(b) @ hat([0.0, 1.0, 0.0])) @ rot_z(g)  # d/db Ry(b) = Ry(b) hat(e2)
    np.testing.assert_allclose(drdb, expected, atol=1e-14)


# ------------------------------------------------------------------------------------- exp / log
@FAST
@given(vec3)
def test_so3_exp_matches_matrix_exponential(w):
    r = so3_exp(w)
    np.testing.assert_allclose(r, scipy.linalg.expm(hat(w)), atol=1e-12)
    assert is_rotation(r)
    np.testing.assert_allclose(r @ w, w, atol=1e-12)  # the axis is fixed


def test_so3_exp_small_angles():
    for th in (0.0, 1e-12, 1e-9, 1e-7, 1e-5):
        w = th * np.array([0.6, -0.8, 0.0])
        np.testing.assert_allclose(so3_exp(w), scipy.linalg.expm(hat(w)), atol=1e-15)


@FAST
@given(unit_axis, st.floats(0.0, PI - 1e-6))
def test_so3_log_round_trip(axis, th):
    w = th * axis
    np.testing.assert_allclose(so3_log(so3_exp(w)), w, atol=1e-10)


@FAST
@given(unit_axis, st.floats(-12.0, -3.0))
def test_so3_log_near_pi(axis, log10_delta):
    """Angles within 1e-3 of pi (the branch that reads the axis from the symmetric part)."""
    delta = 10.0**log10_delta
    th = PI - delta
    r = so3_exp(th * axis)
    w = so3_log(r)
    assert np.linalg.norm(w) == pytest.approx(th, abs=1e-12)
    np.testing.assert_allclose(so3_exp(w), r, atol=1e-12)
    if delta > 1e-8:  # the sign is determined away from exactly pi
        np.testing.assert_allclose(w, th * axis, atol=1e-10)
    else:  # at pi, w and -w are the same rotation
        assert min(np.linalg.norm(w - th * axis), np.linalg.norm(w + th * axis)) < 1e-7


def test_so3_log_exactly_pi_and_identity():
    for axis in np.eye(3):
        r = 2 * np.outer(axis, axis) - np.eye(3)  # rotation by pi, closed form
        w = so3_log(r)
        assert np.linalg.norm(w) == pytest.approx(PI)
        np.testing.assert_allclose(np.abs(w), PI * axis, atol=1e-12)
    np.testing.assert_allclose(so3_log(np.eye(3)), 0.0, atol=0)


def test_so3_log_batched_mixed_branches():
    rng = np.random.default_rng(3)
    axis = rng.standard_normal((6, 3))
    axis /= np.linalg.norm(axis, axis=-1, keepdims=True)
    th = np.array([0.0, 1e-10, 0.5, 2.0, PI - 1e-3, PI - 1e-6])
    w = axis * th[:, None]
    np.testing.assert_allclose(so3_log(so3_exp(w)), w, atol=1e-9)


@FAST
@given(unit_axis, st.floats(0.0, PI))
def test_rotation_angle(axis, th):
    assert rotation_angle(so3_exp(th * axis)) == pytest.approx(th, abs=1e-12)


def test_rotation_angle_of_random_rotations():
    r = random_rotations(np.random.default_rng(4), 50)
    th = rotation_angle(r)
    # independent: angle from the eigenvalues exp(+-i th)
    ev = np.linalg.eigvals(r)
    np.testing.assert_allclose(th, np.max(np.abs(np.angle(ev)), axis=-1), atol=1e-9)
    # relative rotation: the angle between r and itself is 0
    np.testing.assert_allclose(rotation_angle(np.swapaxes(r, -1, -2) @ r), 0.0, atol=1e-7)


# -------------------------------------------------------------------------------------- projection
def test_project_to_so3_returns_rotations():
    rng = np.random.default_rng(5)
    m = rng.standard_normal((100, 3, 3))  # about half with negative determinant
    assert np.any(np.linalg.det(m) < 0)
    r = project_to_so3(m)
    assert is_rotation(r, tol=1e-12)


def test_project_to_so3_is_the_polar_factor_and_nearest():
    rng = np.random.default_rng(6)
    q = random_rotations(rng, 20)
    m = q + 0.1 * rng.standard_normal((20, 3, 3))  # near rotations: positive determinant
    assert np.all(np.linalg.det(m) > 0)
    r = project_to_so3(m)
    for mi, ri in zip(m, r):
        u, _ = scipy.linalg.polar(mi)
        np.testing.assert_allclose(ri, u, atol=1e-12)
    # nearest in Frobenius norm among many rotations
    others = random_rotations(rng, 500)
    d_best = np.linalg.norm(m - r, axis=(-2, -1))
    for k in range(20):
        d_other = np.linalg.norm(m[k] - others, axis=(-2, -1))
        assert d_best[k] <= d_other.min() + 1e-12
    # a rotation is its own projection
    np.testing.assert_allclose(project_to_so3(q), q, atol=1e-12)


def test_orthonormalize_converges_quadratically():
    rng = np.random.default_rng(7)
    q = random_rotations(rng, 10)
    e = 1e-4 * rng.standard_normal((10, 3, 3))
    m = q + e
    err0 = np.linalg.norm(m @ np.swapaxes(m, -1, -2) - np.eye(3), axis=(-2, -1))
    r = orthonormalize(m)
    err1 = np.linalg.norm(r @ np.swapaxes(r, -1, -2) - np.eye(3), axis=(-2, -1))
    assert np.all(err1 < 10 * err0**2 + 1e-14)


# ------------------------------------------------------------------------------------------ RK4
def test_rk4_step_linear_scalar_is_fourth_order_taylor():
    # x' = lam x: one RK4 step multiplies by the degree-4 Taylor polynomial of exp(lam dt)
    lam = np.array([-1.3, 0.7, 2.0 + 1.0j])
    x0 = np.array([1.0, -2.0, 0.5], dtype=complex)
    dt = 0.37
    z = lam * dt
    x1 = rk4_step(lambda x: lam * x, x0, dt)
    np.testing.assert_allclose(x1, x0 * (1 + z + z**2 / 2 + z**3 / 6 + z**4 / 24), rtol=1e-14)


def test_rk4_step_linear_system_and_batched_dt():
    rng = np.random.default_rng(8)
    a = rng.standard_normal((3, 3))
    x0 = rng.standard_normal((4, 3))
    dt = np.array([0.1, 0.2, 0.05, 0.3])[:, None]
    x1 = rk4_step(lambda x: x @ a.T, x0, dt)
    for k in range(4):
        z = a * dt[k, 0]
        poly = np.eye(3) + z + z @ z / 2 + z @ z @ z / 6 + z @ z @ z @ z / 24
        np.testing.assert_allclose(x1[k], poly @ x0[k], rtol=1e-13, atol=1e-14)


def test_rk4_global_order_on_nonlinear_ode():
    # x' = x^2, x(0) = 1/2: x(t) = 1 / (2 - t)
    def solve(dt):
        x = np.array([0.5])
        for _ in range(int(round(1.0 / dt))):
            x = rk4_step(lambda y: y**2, x, dt)
        return abs(x[0] - 1.0)

    e = np.array([solve(dt) for dt in (0.1, 0.05, 0.025)])
    order = np.log2(e[:-1] / e[1:])
    assert np.all((order > 3.6) & (order < 4.4)), order


# -------------------------------------------------------------------------------------- Jacobians
def _f_test(x):
    """A smooth test function R^3 -> R^4, analytic for complex input, batched."""
    x0, x1, x2 = x[..., 0], x[..., 1], x[..., 2]
    return np.stack([x0**2 * x1, np.sin(x2) * x0, np.exp(x0) * x2 - x1, x1 / (2.0 + np.cos(x0))], -1)


def _jac_test(x):
    x0, x1, x2 = x[..., 0], x[..., 1], x[..., 2]
    z = np.zeros_like(x0)
    d = 2.0 + np.cos(x0)
    rows = [
        [2 * x0 * x1, x0**2, z],
        [np.sin(x2), z, x0 * np.cos(x2)],
        [np.exp(x0) * x2, -np.ones_like(x0), np.exp(x0)],
        [x1 * np.sin(x0) / d**2, 1.0 / d, z],
    ]
    return np.stack([np.stack(r, -1) for r in rows], -2)


def test_complex_step_and_finite_difference_against_analytic():
    rng = np.random.default_rng(9)
    x = rng.standard_normal((5, 2, 3))
    j_exact = _jac_test(x)
    j_cs = complex_step_jacobian(_f_test, x)
    j_fd = finite_difference_jacobian(_f_test, x)
    assert j_cs.shape == j_fd.shape == (5, 2, 4, 3)
    np.testing.assert_allclose(j_cs, j_exact, rtol=1e-13, atol=1e-14)
    np.testing.assert_allclose(j_fd, j_exact, rtol=1e-7, atol=1e-8)
    np.testing.assert_allclose(j_cs, j_fd, rtol=1e-7, atol=1e-8)


def test_complex_step_jacobian_through_rotations():
    # d/dw of so3-free closed form: f(w) = euler_xyz_to_matrix(w) @ e3 (the tangent), against differences
    def tangent(w):
        r = euler_xyz_to_matrix(w[..., 0], w[..., 1], w[..., 2])
        return r[..., :, 2]

    x = np.array([[0.3, -0.2, 1.0], [-1.0, 0.7, -2.5]])
    np.testing.assert_allclose(complex_step_jacobian(tangent, x), finite_difference_jacobian(tangent, x), atol=1e-8)


# --------------------------------------------------------------------------------------------- sincos
def test_sincos_agrees_with_sin_and_cos():
    """The half-angle-tangent sin and cos against numpy's: within 1 ulp of 1 in absolute value everywhere
    (also at the cuts and at large angles), 2 ulp relative for sin near 0, exact at 0 and +-pi."""
    rng = np.random.default_rng(7)
    a = np.concatenate([
        rng.uniform(-4.0, 4.0, 200_000), rng.uniform(-1e4, 1e4, 100_000), 10.0 ** rng.uniform(-300, 0, 10_000),
        np.array([0.0, -0.0, PI, -PI, PI / 2, -PI / 2, np.nextafter(PI, 0), 3 * PI, 1e-300]),
        (np.arange(-64, 65) * PI / 4),
    ])
    s, c = sincos(a)
    assert np.abs(s - np.sin(a)).max() <= 2.3e-16
    assert np.abs(c - np.cos(a)).max() <= 2.3e-16
    small = np.abs(a) < 1.0
    rel = np.abs(s[small] - np.sin(a[small])) / np.maximum(np.abs(np.sin(a[small])), 1e-300)
    assert rel.max() <= 4.5e-16
    assert sincos(np.array([0.0]))[0][0] == 0.0 and sincos(np.array([0.0]))[1][0] == 1.0
    assert sincos(np.array([PI]))[1][0] == -1.0


@FAST
@given(hnp.arrays(np.float64, (3, 4), elements=angles))
def test_sincos_shapes_and_identity(a):
    s, c = sincos(a)
    assert s.shape == c.shape == a.shape
    np.testing.assert_allclose(s * s + c * c, 1.0, rtol=0, atol=1e-15)


def test_sincos_scalars_complex_step_and_nan():
    s, c = sincos(0.3)
    assert abs(s - np.sin(0.3)) < 1e-16 and abs(c - np.cos(0.3)) < 1e-16
    a = np.array([-2.0, 0.1, 0.7, 3.0])
    ds, dc = (v.imag / 1e-30 for v in sincos(a + 1e-30j))  # analytic: complex-step derivatives to rounding
    np.testing.assert_allclose(ds, np.cos(a), rtol=0, atol=1e-14)
    np.testing.assert_allclose(dc, -np.sin(a), rtol=0, atol=1e-14)
    with np.errstate(invalid="ignore"):
        s, c = sincos(np.array([np.nan, np.inf]))
    assert np.isnan(s).all() and np.isnan(c).all()
