"""Magnetic needle models of the magnetic needle EM paper, in metres: MNM (eq. 1) and the bicycle model BiNM (eq. 4)."""

from __future__ import annotations

import numpy as np
from pydantic import Field

from needlecli.models.base import MODELS, Model, ModelParams, Params


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Cross product that stays analytic for complex input (``np.cross`` does too, but is slow)."""
    return np.stack(
        [
            a[..., 1] * b[..., 2] - a[..., 2] * b[..., 1],
            a[..., 2] * b[..., 0] - a[..., 0] * b[..., 2],
            a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0],
        ],
        -1,
    )


def _dot(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return a[..., 0] * b[..., 0] + a[..., 1] * b[..., 1] + a[..., 2] * b[..., 2]


def _skew(w: np.ndarray) -> np.ndarray:
    """``[w]_x`` ``(..., 3, 3)`` with ``[w]_x b = w x b``."""
    z = np.zeros_like(w[..., 0])
    return np.stack(
        [np.stack([z, -w[..., 2], w[..., 1]], -1), np.stack([w[..., 2], z, -w[..., 0]], -1),
         np.stack([-w[..., 1], w[..., 0], z], -1)], -2)


def _turn_parts(h: np.ndarray, b: np.ndarray):
    """``T = (h x B) x h = B (h.h) - h (h.B)`` and its Jacobians ``dT/dh``, ``dT/dB`` ``(..., 3, 3)``."""
    hh, hb = _dot(h, h), _dot(h, b)
    t = b * hh[..., None] - h * hb[..., None]
    eye = np.eye(3)
    dth = 2.0 * b[..., :, None] * h[..., None, :] - hb[..., None, None] * eye - h[..., :, None] * b[..., None, :]
    dtb = hh[..., None, None] * eye - h[..., :, None] * h[..., None, :]
    return t, dth, dtb, hb


class MNMParams(ModelParams):
    c: float = Field(20.0, ge=0.0, description="steering constant, 1/m")


class _MagneticBase(Model):
    state_names = ("px", "py", "pz", "hx", "hy", "hz", "Bx", "By", "Bz")
    state_units = ("m", "m", "m", "1", "1", "1", "1", "1", "1")
    input_names = ("v", "omega_B")
    input_sizes = {"v": 1, "omega_B": 3}
    input_units = {"v": "m/s", "omega_B": "rad/s"}
    length_unit = "m"
    translation_states = ("px", "py", "pz")
    selections = {"tip_position": ("px", "py", "pz")}
    unit_vectors = {"tangent": ("hx", "hy", "hz"), "field_direction": ("Bx", "By", "Bz")}

    def _turn(self, h, b, v, p):
        raise NotImplementedError

    def f(self, x, u, p: Params):
        h, b = x[..., 3:6], x[..., 6:9]
        v, wb = u[..., 0], u[..., 1:4]
        dp = h * v[..., None]
        dh = self._turn(h, b, v, p) + h * (1.0 - _dot(h, h))[..., None]
        db = _cross(wb, b) + b * (1.0 - _dot(b, b))[..., None]
        return np.concatenate([dp, dh, db], -1)

    def _turn_jacobian(self, h, b, v, p):
        """``(d turn/d h, d turn/d B, d turn/d param)``: ``(..., 3, 3)``, ``(..., 3, 3)``, ``(..., 3)``."""
        raise NotImplementedError

    def jacobian(self, x, u, p: Params):
        """Analytic ``df/dx`` ``(..., 9, 9)`` (the complex step is 20 times slower on large batches)."""
        x, u = np.asarray(x), np.asarray(u)
        h, b = x[..., 3:6], x[..., 6:9]
        v, wb = u[..., 0], u[..., 1:4]
        shape = np.broadcast_shapes(x.shape[:-1], u.shape[:-1], *(np.shape(a) for a in p.values()))
        eye = np.eye(3)
        J = np.zeros(shape + (9, 9), dtype=np.result_type(x, u, *p.values()))
        J[..., 0:3, 3:6] = v[..., None, None] * eye
        jh, jb, _ = self._turn_jacobian(h, b, v, p)
        hh = _dot(h, h)[..., None, None]
        J[..., 3:6, 3:6] = jh + (1.0 - hh) * eye - 2.0 * h[..., :, None] * h[..., None, :]
        J[..., 3:6, 6:9] = jb
        bb = _dot(b, b)[..., None, None]
        J[..., 6:9, 6:9] = _skew(wb) + (1.0 - bb) * eye - 2.0 * b[..., :, None] * b[..., None, :]
        return J

    def param_jacobian(self, x, u, p: Params, name: str):
        if name != self.curvature_param:
            return super().param_jacobian(x, u, p, name)
        x, u = np.asarray(x), np.asarray(u)
        _, _, dp = self._turn_jacobian(x[..., 3:6], x[..., 6:9], u[..., 0], p)
        out = np.zeros(dp.shape[:-1] + (9,), dtype=dp.dtype)
        out[..., 3:6] = dp
        return out

    def initial_state(self, p: Params) -> np.ndarray:
        # tip along +y in the camera plane, field along the tip
        return np.array([0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 1.0, 0.0])

    def tip_position(self, x):
        return x[..., 0:3]

    def tangent(self, x):
        h = x[..., 3:6]
        return h / np.linalg.norm(h, axis=-1, keepdims=True)

    def field_direction(self, x):
        b = x[..., 6:9]
        return b / np.linalg.norm(b, axis=-1, keepdims=True)


@MODELS.register("mnm")
class MagneticNeedleModel(_MagneticBase):
    r"""Magnetic needle model (the magnetic needle EM paper, eq. 1), metres.

    .. math::
        p' = h v,\quad h' = c v (h \times B) \times h + h (1 - |h|^2),\quad
        B' = \omega_B \times B + B (1 - |B|^2)

    The ``(1 - |.|^2)`` terms make ``|h| = |B| = 1`` attracting invariant sets.
    """

    curvature_param = "c"
    Params = MNMParams
    compiled_equations = "mnm"

    def _turn(self, h, b, v, p):
        return (p["c"] * v)[..., None] * _cross(_cross(h, b), h)

    def _turn_jacobian(self, h, b, v, p):
        t, dth, dtb, _ = _turn_parts(h, b)
        cv = (p["c"] * v)[..., None, None]
        return cv * dth, cv * dtb, v[..., None] * t


class BiNMParams(ModelParams):
    l_inv: float = Field(20.0, ge=0.0, description="inverse bicycle length, 1/m")


@MODELS.register("binm")
class BicycleNeedleModel(_MagneticBase):
    r"""Bicycle needle model (the magnetic needle EM paper, eq. 4), metres.

    .. math:: h' = l^{-1} v \frac{(h \times B) \times h}{B \cdot h} + h (1 - |h|^2)

    Singular when the field is perpendicular to the tip (``B . h -> 0``): the run is reported
    ``singular`` with the time it happened.
    """

    curvature_param = "l_inv"
    Params = BiNMParams
    compiled_equations = "binm"
    compiled_margin = ("perpendicular", ("hx", "hy", "hz", "Bx", "By", "Bz"))
    singular_reason = "B . h -> 0: the bicycle model is singular when the field is perpendicular to the tip"

    def _turn(self, h, b, v, p):
        return ((p["l_inv"] * v) / _dot(b, h))[..., None] * _cross(_cross(h, b), h)

    def _turn_jacobian(self, h, b, v, p):
        t, dth, dtb, s = _turn_parts(h, b)
        lv = (p["l_inv"] * v)[..., None, None]
        s2 = s[..., None, None]
        jh = lv * (dth / s2 - t[..., :, None] * b[..., None, :] / s2**2)
        jb = lv * (dtb / s2 - t[..., :, None] * h[..., None, :] / s2**2)
        return jh, jb, (v / s)[..., None] * t

    singular_threshold = 1e-3  # |cos| of the angle between B and h
    near_singular_threshold = 5e-2

    def singularity_margin(self, x, p):
        h, b = x[..., 3:6], x[..., 6:9]
        return np.abs(_dot(h, b)) / (np.linalg.norm(h, axis=-1) * np.linalg.norm(b, axis=-1))

    def crossed_singularity(self, x, xn, p):
        # B . h changes sign only through the singularity (which repels the exact flow): a step that
        # jumps over the band |cos| < singular_threshold is caught here
        return _dot(x[..., 3:6], x[..., 6:9]) * _dot(xn[..., 3:6], xn[..., 6:9]) < 0
