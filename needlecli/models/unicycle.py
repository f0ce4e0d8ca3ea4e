"""Bevel-tip needle models in generalized coordinates (the high-gain observer and multi-rate UKF papers), in mm, rad, s.

Frame (``MODELS.md``): ``R = Rx(alpha) Ry(beta) Rz(gamma)``, tangent ``R e3``, body twist linear
``(0, 0, v)`` and angular ``(kappa v, 0, u)``.
"""

from __future__ import annotations

import numpy as np
from pydantic import Field

from needlecli.models.base import MODELS, Model, ModelParams, Params
from needlecli.numerics import euler_xyz_to_matrix, sincos


class UnicycleParams(ModelParams):
    kappa: float = Field(0.002, ge=0.0, description="path curvature, 1/mm")
    speed_scale: float = Field(
        1.0, gt=0.0, le=2.0,
        description="actual over commanded insertion (slip in the tissue: the tip advances speed_scale * v), 1")


def _advance(v, p: Params):
    """The tip's insertion speed: the commanded ``v`` times the ``speed_scale`` parameter (slip), when
    the parameters have one (a bare ``{kappa: ...}`` mapping means 1). ``v * 1.0`` is ``v`` exactly."""
    s = p.get("speed_scale")
    return v if s is None else v * s


@MODELS.register("unicycle")
class Unicycle(Model):
    r"""3D unicycle in generalized coordinates (the high-gain observer paper, eq. 1).

    .. math::
        x' = v \sin b,\; y' = -v \cos b \sin a,\; z' = v \cos a \cos b,\\
        a' = \kappa v \cos g / \cos b,\; b' = \kappa v \sin g,\; g' = u - \kappa v \cos g \tan b

    State ``(x, y, z, alpha, beta, gamma)`` in mm and rad; inputs ``v`` (mm/s) and ``u`` (rad/s);
    parameters ``kappa`` (1/mm) and ``speed_scale`` (the tip advances ``speed_scale * v``: a needle that
    slips in the tissue has it below 1; default 1). Singular at ``cos(beta) = 0``.

    ``(kappa, gamma)`` and ``(-kappa, gamma + pi)`` give the same path (the body rotated by pi about the
    tangent): a fit that finds a negative curvature has found the roll + pi (``curvature_roll_state``).
    """

    state_names = ("x", "y", "z", "alpha", "beta", "gamma")
    state_units = ("mm", "mm", "mm", "rad", "rad", "rad")
    angle_states = ("alpha", "beta", "gamma")
    input_names = ("v", "u")
    input_sizes = {"v": 1, "u": 1}
    input_units = {"v": "mm/s", "u": "rad/s"}
    curvature_param = "kappa"
    Params = UnicycleParams
    state_bounds = {"beta": (-np.pi / 2, np.pi / 2)}
    translation_states = ("x", "y", "z")
    selections = {"tip_position": ("x", "y", "z"), "roll": ("gamma",)}
    singular_reason = "cos(beta) -> 0: the generalized-coordinate unicycle is undefined at beta = +-pi/2"
    curvature_roll_state = "gamma"
    compiled_equations = "unicycle"
    compiled_margin = ("cos", ("beta",))

    component_major = True

    def f_components(self, x, u, p: Params):
        v, w = _advance(u[0], p), u[1]
        (sa, sb, sg), (ca, cb, cg) = sincos(x[3:6])
        kv = p["kappa"] * v
        kvc = kv * cg / cb
        vcb = v * cb
        out = np.empty((6,) + np.broadcast_shapes(sa.shape, kv.shape, w.shape), dtype=np.result_type(x, u, kv))
        out[0] = v * sb
        out[1] = -vcb * sa
        out[2] = vcb * ca
        out[3] = kvc
        out[4] = kv * sg
        out[5] = w - kvc * sb
        return out

    def initial_state(self, p: Params) -> np.ndarray:
        return np.zeros(6)

    singular_threshold = 1e-6  # cos(beta)
    near_singular_threshold = 1e-2

    def singularity_margin(self, x, p):
        # signed: cos(beta) < 0 is outside the domain (-pi/2, pi/2), so a step that jumps over pi/2 counts
        return np.cos(x[..., 4])

    def tip_position(self, x):
        return x[..., 0:3]

    def tip_rotation(self, x):
        return euler_xyz_to_matrix(x[..., 3], x[..., 4], x[..., 5])

    def tangent(self, x):
        a, b = x[..., 3], x[..., 4]
        return np.stack([np.sin(b), -np.cos(b) * np.sin(a), np.cos(a) * np.cos(b)], -1)

    def roll(self, x):
        return x[..., 5]


class ModifiedUnicycleParams(ModelParams):
    kappa: float = Field(0.002, ge=0.0, description="true curvature, 1/mm (initial value of the state)")
    beta_cut: float = Field(
        0.0, ge=0.0, le=np.deg2rad(6.0), description="cutting angle of the bevel, rad (0..6 deg)"
    )
    speed_scale: float = UnicycleParams.model_fields["speed_scale"]


@MODELS.register("modified_unicycle")
class ModifiedUnicycle(Unicycle):
    r"""Modified unicycle with cutting angle and curvature as a state (the multi-rate UKF paper, eq. 1).

    Rotating the shaft adds a body-y angular velocity ``(beta_cut / 2) g_r`` with
    ``g_r = u2 - kappa cos g tan b u1`` the roll rate of the plain unicycle (``MODELS.md``):

    .. math::
        a' = \kappa \cos g / \cos b\, u_1 - (\beta_c/2) \sin g / \cos b\, g_r,\quad
        b' = \kappa \sin g\, u_1 + (\beta_c/2) \cos g\, g_r,\quad g' = g_r,\quad \kappa' = 0

    State ``(x, y, z, alpha, beta, gamma, kappa)``; inputs ``v = u1`` and ``u = u2``.
    """

    state_names = Unicycle.state_names + ("kappa",)
    state_units = Unicycle.state_units + ("1/mm",)
    Params = ModifiedUnicycleParams
    curvature_roll_state = None  # the cutting angle's terms change sign with the roll: no such symmetry
    param_states = {"kappa": "kappa"}
    compiled_equations = "modified_unicycle"

    def f_components(self, x, u, p: Params):
        # written into the output rows in place: this is the UKF's hot path (15 sigma points per run)
        v, w = _advance(u[0], p), u[1]
        (sa, sb, sg), (ca, cb, cg) = sincos(x[3:6])
        kv = x[6] * v
        inv_cb = 1.0 / cb
        kvc = kv * cg
        g_r = kvc * sb
        g_r *= inv_cb
        np.subtract(w, g_r, out=g_r)  # the roll rate
        cut = g_r * (0.5 * p["beta_cut"])
        out = np.empty((7,) + cut.shape, dtype=cut.dtype)
        np.multiply(v, sb, out=out[0])
        vcb = v * cb
        np.multiply(vcb, sa, out=out[1])
        np.negative(out[1], out=out[1])
        np.multiply(vcb, ca, out=out[2])
        np.multiply(cut, sg, out=out[3])
        np.subtract(kvc, out[3], out=out[3])
        out[3] *= inv_cb
        np.multiply(cut, cg, out=out[4])
        out[4] += kv * sg
        out[5] = g_r
        out[6] = 0.0
        return out

    def initial_state(self, p: Params) -> np.ndarray:
        x0 = np.zeros(7)
        x0[6] = float(np.mean(p["kappa"]))
        return x0
