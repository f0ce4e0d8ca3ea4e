r"""The image plane of a 2D transverse ultrasound probe: where the plane is, and whether the needle is in it.

A transverse probe that follows the needle images its cross section in a plane that runs ahead of or
behind the tip. The plane's pose is known (the probe is tracked or robot-held) and so is the detector's
verdict: a needle **seen** in the image has its tip past the plane (its shaft crosses it), a frame
**lost** (no needle in the image) has its tip short of it. Neither is a function of the state to be
predicted with noise; together they are an inequality on the tip's position along the plane's normal:

.. math::  s\,(n^T p(x) - d) \ge 0, \qquad s = +1 \text{ (seen)}, -1 \text{ (lost)}

with ``n`` the plane's unit normal pointing along the insertion and ``d = n^T c`` the plane's signed
position along it (``c`` any point of the plane). Channels: ``nx, ny, nz`` (the normal), ``d`` (mm),
``seen`` (1 or 0). A filter uses it through :meth:`ImagePlaneSensor.bound` (the UKF's truncated update,
``needlecli.observers.ukf``); it has no ``h``, so no observer takes it for an ordinary measurement.

Emulated (simulations): the plane is normal to the true tangent and sits ``o`` along it from the tip,
``o`` an Ornstein-Uhlenbeck offset per run (``offset_tau``, ``offset_sigma``: a probe servo that lags
and overshoots); the needle is seen where ``o <= 0`` (the plane behind the tip) unless the frame
drops out (``dropout``: the sample is then missing, not lost).
"""

from __future__ import annotations

from typing import Literal

import numpy as np
from pydantic import Field, field_validator

from needlecli.models import NotMeasurable
from needlecli.schema import NonNeg, Positive
from needlecli.sensors.base import SENSORS, MeasurementStream, Sensor, SensorSettings

NAMES = ("nx", "ny", "nz", "d", "seen")


class ImagePlaneSettings(SensorSettings):
    type: Literal["image_plane"]
    offset_sigma: NonNeg = Field(3.0, description="emulated: stationary std of the plane's offset from the tip "
                                                  "along the tangent (model length unit)")
    offset_tau: Positive = Field(8.0, description="emulated: time constant of the offset (Ornstein-Uhlenbeck), s")

    @field_validator("pipeline")
    @classmethod
    def _pipeline(cls, v):
        if v != "gaussian":
            raise ValueError("an image plane is emulated from the truth (its own offset): no image pipeline")
        return v


@SENSORS.register("image_plane")
class ImagePlaneSensor(Sensor):
    """Pose of a transverse ultrasound image plane and whether the needle is seen in it: a one-sided
    bound on the tip's position along the plane's normal (module docstring)."""

    Settings = ImagePlaneSettings
    requires = ("tip_position", "tangent")
    inequality = True

    @property
    def channel_names(self):
        return NAMES

    @property
    def channel_units(self):
        u = self.model.length_unit
        return ("1", "1", "1", u, "1")

    def h(self, x):
        raise NotMeasurable("an image plane bounds the tip from one side: it is not a function of the state")

    def bound(self, x: np.ndarray, value: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(g, s)``: ``g = n^T p(x) - d`` for states ``x (..., n)`` and samples ``value (..., 5)``
        (broadcast), and the side ``s`` (+1 seen, -1 lost) with which the sample says ``s g >= 0``."""
        g = np.sum(value[..., :3] * self.model.tip_position(x), -1) - value[..., 3]
        return g, np.where(value[..., 4] > 0.5, 1.0, -1.0)

    def sigma(self, truth, idx):
        return np.zeros(len(NAMES))

    def measure(self, truth, rng: np.random.Generator) -> MeasurementStream:
        idx = self.sample_indices(truth.time)
        x = truth.states_at(idx)  # (N, M, n)
        N, M = x.shape[:2]
        t = truth.time[idx]
        s, tau = self.settings.offset_sigma, self.settings.offset_tau
        o = np.zeros((N, M))  # the exact discretisation of the Ornstein-Uhlenbeck offset
        if M:
            o[:, 0] = s * rng.standard_normal(N)
        for j in range(1, M):  # over samples (a recursion in time), every run at once
            a = np.exp(-(t[j] - t[j - 1]) / tau)
            o[:, j] = a * o[:, j - 1] + s * np.sqrt(1.0 - a * a) * rng.standard_normal(N)
        n = self.model.tangent(x)
        p = self.model.tip_position(x)
        d = np.sum(n * (p + o[..., None] * n), -1)
        value = np.concatenate([n, d[..., None], (o <= 0.0)[..., None].astype(float)], -1)
        valid = np.isfinite(value).all(-1)
        return self._stream(truth, idx, _NoExtras, value, valid, np.zeros_like(value), rng)


class _NoExtras:
    extras: dict = {}
