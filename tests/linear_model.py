"""A linear-Gaussian test model for the observer tests (registered under a test-only name).

State ``(x, y, z, vx, vy, vz)`` in mm and mm/s; inputs ``v`` (insertion speed along z, mm/s) and ``a``
(acceleration, 3 values, mm/s^2); parameters ``damping`` (1/s) and ``omega`` (rad/s):

    p' = vel + v e_z,    vel' = D vel + a,    D = [[-c, w, 0], [-w, -c, 0], [0, 0, -c]]

so ``f(x, u, p) = A x + B u`` with ``A = [[0, I], [0, D]]``, ``B = [[e_z, 0], [0, I]]``
(:func:`linear_system` builds these by hand for the reference Kalman filter). The tip position is
``x[..., :3]``. Importing this module twice (under two names) registers the model once.
"""

from __future__ import annotations

import numpy as np
from pydantic import Field

from needlecli.models import MODELS, Model, ModelParams

NAME = "linear_test_model"


class LinearTestParams(ModelParams):
    damping: float = Field(0.4, description="velocity damping, 1/s")
    omega: float = Field(0.7, description="rotation rate of the velocity, rad/s")


class LinearTestModel(Model):
    """Linear-Gaussian point mass with damped, rotating velocity (tests only)."""

    state_names = ("x", "y", "z", "vx", "vy", "vz")
    state_units = ("mm", "mm", "mm", "mm/s", "mm/s", "mm/s")
    angle_states = ()
    input_names = ("v", "a")
    input_sizes = {"v": 1, "a": 3}
    input_units = {"v": "mm/s", "a": "mm/s^2"}
    insertion_input = "v"
    curvature_param = None
    Params = LinearTestParams

    def f(self, x, u, p):
        c, w = p["damping"], p["omega"]
        vx, vy, vz = x[..., 3], x[..., 4], x[..., 5]
        shape = np.broadcast_shapes(x.shape, u.shape[:-1] + (6,), np.shape(c) + (6,))
        out = np.empty(shape, dtype=np.result_type(x, u, c))
        out[..., 0] = vx
        out[..., 1] = vy
        out[..., 2] = vz + u[..., 0]
        out[..., 3] = -c * vx + w * vy + u[..., 1]
        out[..., 4] = -w * vx - c * vy + u[..., 2]
        out[..., 5] = -c * vz + u[..., 3]
        return out

    def initial_state(self, p):
        return np.zeros(6)

    def tip_position(self, x):
        return x[..., 0:3]


if NAME in MODELS:  # a second import (e.g. as ``tests.linear_model``): keep the registered class
    LinearTestModel = MODELS.get(NAME)  # type: ignore[misc]
else:
    MODELS.register(NAME)(LinearTestModel)


def linear_system(damping: float, omega: float) -> tuple[np.ndarray, np.ndarray]:
    """``A (6, 6)`` and ``B (6, 4)`` of the model, written out by hand."""
    c, w = damping, omega
    A = np.zeros((6, 6))
    A[0:3, 3:6] = np.eye(3)
    A[3:6, 3:6] = [[-c, w, 0.0], [-w, -c, 0.0], [0.0, 0.0, -c]]
    B = np.zeros((6, 4))
    B[2, 0] = 1.0
    B[3:6, 1:4] = np.eye(3)
    return A, B


def rk4_transition(A: np.ndarray, B: np.ndarray, h: float) -> tuple[np.ndarray, np.ndarray]:
    """The discrete map of one classical RK4 step of ``x' = A x + B u`` (u held):
    ``x+ = Phi x + Gamma u`` with ``Phi = sum_{j<=4} (hA)^j / j!`` and
    ``Gamma = h sum_{j<=3} (hA)^j / (j+1)! B``."""
    n = A.shape[0]
    M = h * A
    phi = np.eye(n)
    gam = np.eye(n)
    term = np.eye(n)
    fact = 1.0
    for j in range(1, 5):
        term = term @ M
        fact *= j
        phi = phi + term / fact
        if j <= 3:
            gam = gam + term / (fact * (j + 1))
    return phi, h * gam @ B
