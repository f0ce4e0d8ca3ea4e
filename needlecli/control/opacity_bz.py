"""The magnetic needle EM paper's planar control (sec. 2.3.6, eq. 7): the out-of-plane field from the camera's opacity.

``B_z = clip(gain (opacity - opacity_0), -limit, limit)`` mT, ``opacity`` the grey level at the tip in
the overhead camera's frame (:mod:`needlecli.sensors.imaging.camera`), ``opacity_0`` the opacity at the
run's first detection (the initial insertion point). Deeper needle -> fainter -> higher grey level ->
``B_z > 0`` -> the field tilts toward +z -> the tip turns up: the loop pulls the needle back to the depth
it started at.

How the command acts: ``B`` of the magnetic models (states ``Bx, By, Bz``) is the unit direction of the
coils' field. The coils update at 300 Hz, far faster than the 6 Hz camera, so when a command becomes
available (the first grid time at or after the sample's ``t + latency``) the field direction is set,
before the RK4 step from that grid time, to ``(F b_xy, B_z) / |(F b_xy, B_z)|``: ``b_xy`` the current
in-plane direction of ``B``, ``F`` the in-plane field strength (``field``, mT). The recorded state at that
grid time is the one after the change. ``B_z`` then holds until the next command (``omega_B`` about z
rotates ``B`` without changing its z component; other components of ``omega_B`` would move it between
commands). A frame without a detection (NaN opacity) keeps the previous command; before the first
detection the command is 0 (set at ``t = 0``: the paper's open-loop experiments had ``B_z = 0``).
"""

from __future__ import annotations

from typing import Literal

import numpy as np
from pydantic import Field

from needlecli.control.base import CONTROLLERS, Controller, ControllerSettings, available_index
from needlecli.io.tree import Group
from needlecli.schema import NonNeg, Positive
from needlecli.sensors.imaging.camera import bz_command

_FIELD = ("Bx", "By", "Bz")


class OpacityBzSettings(ControllerSettings):
    """The magnetic needle EM paper's eq. (7) on a camera sensor; field strengths in mT."""

    type: Literal["opacity_bz"]
    gain: NonNeg = Field(2.0, description="mT of B_z per grey level of opacity (the magnetic needle EM paper: 2.0)")
    limit: Positive = Field(28.0, description="saturation of B_z, mT (the coils' 28 mT)")
    field: Positive = Field(description="in-plane field strength, mT (the magnetic needle EM paper: 10, 19 or 28)")


@CONTROLLERS.register("opacity_bz")
class OpacityBz(Controller):
    """Proportional control of the field's out-of-plane component on the camera's opacity (module docstring)."""

    Settings = OpacityBzSettings
    acts_on = "the field direction's out-of-plane component (Bz)"

    @classmethod
    def check(cls, settings, model, sensors):
        out = []
        s = sensors[settings.sensor]
        image = getattr(s.settings, "image", None)
        if not (s.registered_name == "position" and s.settings.pipeline == "image" and image is not None
                and image.device == "camera"):
            out.append((("sensor",), f"sensor {settings.sensor!r} gives no opacity: opacity_bz needs a camera "
                                     "(type: position, pipeline: image, image: {device: camera})"))
        if not (model.provides("field_direction") and all(k in model.state_names for k in _FIELD)):
            out.append((("type",), f"opacity_bz sets the magnetic field's direction, which model "
                                   f"{model.registered_name!r} does not have (states Bx, By, Bz: mnm, binm)"))
        return out

    def start(self, time, n_runs, sample_index, t_available):
        dt = float(time[1] - time[0]) if len(time) > 1 else 1.0
        T, M = len(time), len(sample_index)
        self.time = np.asarray(time)
        self.t = self.time[np.asarray(sample_index)]
        self.t_available = np.asarray(t_available, dtype=float)
        self.act_index = available_index(self.t_available, dt)  # (M,) where each sample's command acts
        self.cols = [self.model.index(k) for k in _FIELD]
        self.opacity_0 = np.full(n_runs, np.nan)
        self.sample_command = np.full((n_runs, M), np.nan)  # from each sample; NaN: no detection
        self.current = np.zeros(n_runs)  # B_z in effect, mT (0 before the first detection)
        self.command = np.full((n_runs, T), np.nan)  # B_z in effect over [t_k, t_k+1), mT
        self._next = 0  # next sample whose command is not applied yet
        self._measured = 0  # samples measured so far

    def first_action(self, j):
        return int(self.act_index[j])

    def on_sample(self, j, outputs):
        op = np.array(outputs["opacity"], dtype=float)
        first = np.isnan(self.opacity_0) & np.isfinite(op)
        self.opacity_0[first] = op[first]
        s = self.settings
        self.sample_command[:, j] = bz_command(op, self.opacity_0, gain=s.gain, limit=s.limit)
        self._measured = j + 1

    def before_step(self, k, x):
        changed = k == 0
        while self._next < self._measured and self.act_index[self._next] <= k:
            cmd = self.sample_command[:, self._next]
            self.current = np.where(np.isfinite(cmd), cmd, self.current)
            self._next += 1
            changed = True
        self.command[:, k] = self.current
        if not changed:
            return x
        return self.set_field(x, self.current)

    def set_field(self, x: np.ndarray, bz: np.ndarray) -> np.ndarray:
        """States ``x (N, n)`` with the field direction ``(F b_xy, bz) / |.|`` (``bz (N,)`` mT); a field
        along z (no in-plane direction) is left as it is."""
        b = x[:, self.cols]
        r = np.hypot(b[:, 0], b[:, 1])
        ok = r > 1e-12
        F = self.settings.field
        bxy = b[:, :2] * (F / np.where(ok, r, 1.0))[:, None]
        new = np.concatenate([bxy, bz[:, None]], -1)
        new = new / np.linalg.norm(new, axis=-1, keepdims=True)
        out = x.copy()
        out[:, self.cols] = np.where(ok[:, None], new, b)
        return out

    def results(self, truth):
        s = self.settings
        stopped = truth.time[None, :] > truth.valid_until[:, None]
        return Group(
            data={
                "command": np.where(stopped, np.nan, self.command),
                "sample_command": self.sample_command,
                "t": self.t,
                "t_available": self.t_available,
                "index": self.act_index,
                "opacity_0": self.opacity_0,
            },
            attrs={"type": self.registered_name, "sensor": s.sensor, "gain": s.gain, "limit": s.limit,
                   "field": s.field, "unit": "mT", "acts_on": self.acts_on,
                   "applied": "at the first grid time >= t_available, before the RK4 step from it"},
            dataset_attrs={"command": {"unit": "mT"}, "sample_command": {"unit": "mT"}},
        )
