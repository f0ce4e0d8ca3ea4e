r"""The inserted length as a measurement: an insertion encoder (or the commanded insertion) read against the
needle's path back to where it entered.

The robot knows how much needle it has pushed in: its insertion encoder, or the commanded speed times the
frame intervals. A needle that follows its tip has its whole inserted length on the tip's past path, so
the length is the arc from the entry point to the tip. Sensor ``insertion`` measures it (channel
``length``, model length unit) with the entry pose known with each sample (the robot's needle guide:
``ex, ey, ez`` the entry point, ``dx, dy, dz`` the insertion direction there; the sensor's
:attr:`~needlecli.sensors.base.Sensor.context_channels`):

.. math::  h(x) = -s^\ast / \sigma_v, \qquad n^\top (p(s^\ast) - e) = 0,\quad n = d / |d|

with ``p(s)`` the arc back from the tip with the state's orientation and curvature
(:func:`needlecli.sensors.past.plane_crossing`, the same function as a transverse image plane's, the
plane here the one through the entry point across the insertion direction) and ``sigma_v`` the model's
``speed_scale`` (1 without one: the robot's travel that gives that arc when the needle slips). Exact for
the constant-curvature models while the curvature is constant. With a transverse plane, whose crossings
say nothing about where the tip is along its own path, this is what fixes the tip along the needle.

Emulated: the truth's inserted length (the commanded insertion integrated, ``truth.depth``) at the
sample plus Gaussian noise ``sigma``; the entry pose is each run's starting tip position and tangent.
"""

from __future__ import annotations

from typing import Literal

import numpy as np
from pydantic import Field

from needlecli.schema import NonNeg
from needlecli.sensors.base import NO_PIPELINE, SENSORS, SensorSettings
from needlecli.sensors.past import PathSensor, plane_crossing

ENTRY = ("ex", "ey", "ez", "dx", "dy", "dz")


class InsertionSettings(SensorSettings):
    type: Literal["insertion"]
    sigma: NonNeg = Field(0.1, description="noise std of the inserted length, model length unit")


@SENSORS.register("insertion")
class InsertionSensor(PathSensor):
    """The inserted length against the arc from the entry point to the tip (module docstring)."""

    Settings = InsertionSettings
    context_channels = ENTRY
    neutral_context = (0.0, 0.0, 0.0, 0.0, 0.0, 1.0)

    @property
    def channel_names(self):
        return ("length", *ENTRY)

    @property
    def channel_units(self):
        u = self.model.length_unit
        return (u, u, u, u, "1", "1", "1")

    def h(self, x, context):
        """The inserted length ``(..., 1)`` that puts the tip of states ``x (..., n)`` where it is, its path
        back reaching the entry plane of ``context (..., 6)`` (broadcast)."""
        _, s = plane_crossing(*self.path_twist(x), context[..., 0:3], context[..., 3:6])
        scale = np.asarray(self.model.param_arrays().get("speed_scale", 1.0))
        return (-s / scale)[..., None]

    def sigma(self, truth, idx):
        return np.array([self.settings.sigma] + [0.0] * len(ENTRY))

    def measure(self, truth, rng: np.random.Generator):
        idx = self.sample_indices(truth.time)
        N, M = truth.states.shape[0], len(idx)
        depth = np.asarray(truth.depth, dtype=float)
        length = np.broadcast_to(depth[..., idx] if depth.ndim == 2 else depth[idx], (N, M))
        length = length + self.settings.sigma * rng.standard_normal((N, M))
        x0 = truth.states[:, 0]
        t0 = self.model.tangent(x0)
        entry = np.concatenate([self.model.tip_position(x0), t0 / np.linalg.norm(t0, axis=-1, keepdims=True)], -1)
        value = np.concatenate([length[..., None], np.broadcast_to(entry[:, None], (N, M, len(ENTRY)))], -1)
        valid = np.isfinite(value).all(-1)
        sigma = np.broadcast_to(self.sigma(truth, idx), value.shape).copy()
        return self._stream(truth, idx, NO_PIPELINE, value, valid, sigma, rng)
