"""Rotation-only needle kinematics on SO(3) (the SO(3) observer paper)."""

from __future__ import annotations

import numpy as np
from pydantic import Field

from needlecli.models.base import MODELS, Model, ModelParams, Params
from needlecli.numerics.rotations import matrix_to_euler_xyz, orthonormalize

_R_NAMES = tuple(f"R{i}{j}" for i in range(1, 4) for j in range(1, 4))


class SO3Params(ModelParams):
    kappa: float = Field(0.002, ge=0.0, description="path curvature, 1/mm")


@MODELS.register("so3")
class RotationSO3(Model):
    r"""Orientation of the needle tip on SO(3): :math:`R' = R\,\hat w`, :math:`w = (\kappa v, 0, u)`.

    State: the 9 entries of ``R`` row by row (``R11, R12, ..., R33``); ``R e3`` is the tangent. Inputs
    ``v`` (mm/s) and ``u`` (rad/s) as for the unicycle, so both are driven by the same schedule; the SO(3) observer paper
    writes the same physics with the tangent on its x axis. Each RK4 step is followed by one Newton
    step toward the polar factor, which keeps ``R`` orthonormal to rounding.
    """

    state_names = _R_NAMES
    state_units = ("1",) * 9
    input_names = ("v", "u")
    input_sizes = {"v": 1, "u": 1}
    input_units = {"v": "mm/s", "u": "rad/s"}
    curvature_param = "kappa"
    Params = SO3Params
    compiled_equations = "so3"

    @staticmethod
    def as_matrix(x: np.ndarray) -> np.ndarray:
        return np.asarray(x).reshape(*np.shape(x)[:-1], 3, 3)

    def body_rate(self, u: np.ndarray, p: Params) -> np.ndarray:
        v, w = u[..., 0], u[..., 1]
        kv = p["kappa"] * v
        return np.stack([kv, np.zeros_like(kv), w + 0 * kv], -1)

    def f(self, x, u, p: Params):
        r = self.as_matrix(x)
        w = self.body_rate(u, p)
        # R hat(w), written out so that it stays analytic for the complex step
        c0 = r[..., :, 1] * w[..., None, 2] - r[..., :, 2] * w[..., None, 1]
        c1 = r[..., :, 2] * w[..., None, 0] - r[..., :, 0] * w[..., None, 2]
        c2 = r[..., :, 0] * w[..., None, 1] - r[..., :, 1] * w[..., None, 0]
        dr = np.stack([c0, c1, c2], -1)
        return dr.reshape(*dr.shape[:-2], 9)

    def normalize(self, x):
        r = orthonormalize(self.as_matrix(x))
        return r.reshape(*r.shape[:-2], 9)

    def initial_state(self, p: Params) -> np.ndarray:
        return np.eye(3).reshape(9)

    def tip_rotation(self, x):
        return self.as_matrix(x)

    def euler(self, x) -> np.ndarray:
        """``(alpha, beta, gamma)`` of the project's convention, for tables."""
        return matrix_to_euler_xyz(self.as_matrix(x))
