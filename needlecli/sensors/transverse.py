r"""A 2D transverse ultrasound image: where the needle's shaft crosses the image plane.

The most common imaging in needle steering is a 2D ultrasound plane across the needle. The plane sees
where the **shaft** crosses it, which is the tip only when the plane happens to be at the tip. Each
sample carries the plane's pose (tracked or robot-held probe: recorded, or emulated here) and measures
the crossing in the plane's two coordinates:

.. math::  y = \big(e_u^T (X - o),\; e_v^T (X - o)\big) + \varepsilon, \qquad
           X = \text{the needle's path} \cap \{n^T (X - o) = 0\},\quad n = e_u \times e_v

with ``o`` the plane's origin and ``e_u, e_v`` its unit image axes (channels ``u, v``, model length unit;
then ``ox, oy, oz, ux, uy, uz, vx, vy, vz``, the pose, known with each sample: the sensor's
:attr:`~needlecli.sensors.base.Sensor.context_channels`). The shaft follows the tip (follow-the-leader),
so ``X`` lies on the tip's past path; ``h`` finds it on the arc back from the tip with the state's own
orientation and curvature (:func:`needlecli.sensors.past.plane_crossing`, the module saying why an arc
and not past states as clones), one function for the UKF, the EKF/EKS and EM. A plane ahead of the tip
is crossed by the arc continued ahead (a smooth ``h`` for sigma points on both sides; the emulated
sensor loses such frames).

The reading ``tip`` (``measurements.<name>.reading: tip`` of an observer) takes each sample as the tip's
own position instead, ``(e_u^T (p - o), e_v^T (p - o), n^T (p - o)) = (u, v, 0)``: the tip in the image at
``(u, v)`` (the constraint ``w = 0``: the plane is at the tip), what treating a transverse image as a noisy
tip position amounts to, the model a study compares with (its sigma: three entries, or one for all).

Emulated (simulations): the crossing of the plane with the truth's own past tip positions (the whole
recorded path, found where it enters the plane's far side, interpolated between grid steps) plus
Gaussian noise ``sigma`` per image axis; a frame whose tip is short of the plane (no shaft in the image)
is lost (invalid). The probe (``probe:``) follows the tip with a lag, scans back and forth around it,
or stays put; its plane is normal to the needle's tangent (at the point it follows), tilted by ``tilt``
about the image's ``u`` axis.
"""

from __future__ import annotations

from typing import Literal

import numpy as np
from pydantic import Field, field_validator

from needlecli.schema import NonNeg, Positive, Strict
from needlecli.sensors.base import NO_PIPELINE, SENSORS, MeasurementStream, SensorSettings
from needlecli.sensors.past import PathSensor, plane_crossing

POSE = ("ox", "oy", "oz", "ux", "uy", "uz", "vx", "vy", "vz")
NAMES = ("u", "v", *POSE)


class ProbeMotion(Strict):
    """How the emulated probe holds its image plane (simulations; a recording carries the pose itself)."""

    motion: Literal["follow", "scan", "fixed"] = Field(
        "follow", description="follow: the plane through the tip's position lag s ago, normal to the tangent "
        "there; scan: normal to the tip's tangent, moving back and forth along it around the tip (offset + "
        "amplitude sin(2 pi t / period)); fixed: where the tip started, normal to the initial tangent, never moved")
    lag: NonNeg = Field(0.0, description="follow: how far behind in time the probe is, s")
    offset: float = Field(0.0, description="the plane's distance along the tangent from the point it holds to "
                          "(positive: ahead), model length unit")
    amplitude: NonNeg = Field(5.0, description="scan: half the back-and-forth travel, model length unit")
    period: Positive = Field(10.0, description="scan: the period of the back-and-forth motion, s")
    tilt: float = Field(0.0, ge=-80.0, le=80.0, description="the plane's normal tilted from the tangent about the "
                        "image's u axis, deg")


class TransverseSettings(SensorSettings):
    type: Literal["transverse"]
    sigma: NonNeg | list[NonNeg] = Field(0.3, description="noise std of the crossing per image axis (u, v), model "
                                         "length unit")
    probe: ProbeMotion = Field(default_factory=ProbeMotion, description="emulated: how the probe moves its plane")

    @field_validator("sigma")
    @classmethod
    def _two(cls, v):
        if isinstance(v, list) and len(v) not in (1, 2):
            raise ValueError(f"has {len(v)} entries for the 2 image axes (u, v)")
        return v

    @field_validator("pipeline")
    @classmethod
    def _pipeline(cls, v):
        if v != "gaussian":
            raise ValueError("a transverse plane is emulated from the truth's path: no image pipeline")
        return v


def image_axes(normal: np.ndarray, tilt_deg: float = 0.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Unit image axes ``(e_u, e_v)`` and the plane's normal ``(..., 3)`` for planes normal to ``normal``
    tilted by ``tilt_deg`` about ``e_u``: ``e_u`` along ``a x n`` (``a`` the world x axis, or y where ``n`` is
    near x), ``e_v = n x e_u``."""
    n = normal / np.linalg.norm(normal, axis=-1, keepdims=True)
    a = np.where((np.abs(n[..., :1]) < 0.9), np.array([1.0, 0.0, 0.0]), np.array([0.0, 1.0, 0.0]))
    eu = np.cross(a, n)
    eu /= np.linalg.norm(eu, axis=-1, keepdims=True)
    ev = np.cross(n, eu)
    if tilt_deg:
        c, s = np.cos(np.radians(tilt_deg)), np.sin(np.radians(tilt_deg))
        n, ev = c * n + s * ev, c * ev - s * n
    return eu, ev, n


def path_crossing(path: np.ndarray, origin: np.ndarray, normal: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Where a sampled path ``path (N, L, 3)`` (oldest first, the tip last) last entered the far side of the
    plane ``(origin, normal) (N, 3)``: ``(X (N, 3), found (N,))``, linear between the two samples around the
    crossing; not found where the tip (the last sample) is short of the plane or the path never crossed it."""
    g = np.einsum("nli,ni->nl", path - origin[:, None, :], normal)
    enter = (g[:, :-1] < 0.0) & (g[:, 1:] >= 0.0)
    L = path.shape[1]
    last = np.where(enter, np.arange(L - 1), -1).max(axis=1) if L > 1 else np.full(len(path), -1)
    found = (last >= 0) & (g[:, -1] >= 0.0)
    j = np.maximum(last, 0)
    r = np.arange(len(path))
    g0, g1 = g[r, j], g[r, np.minimum(j + 1, L - 1)]
    with np.errstate(all="ignore"):
        a = np.where(found, g0 / (g0 - g1), 0.0)
    X = path[r, j] + a[:, None] * (path[r, np.minimum(j + 1, L - 1)] - path[r, j])
    return X, found


@SENSORS.register("transverse")
class TransverseSensor(PathSensor):
    """A 2D transverse ultrasound image plane with its pose: the shaft's crossing in the plane's two
    coordinates (module docstring)."""

    Settings = TransverseSettings
    context_channels = POSE
    neutral_context = (0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0, 0.0)  # the world's x-y plane
    readings = {"tip": ("h_tip", ("w",))}

    def __init__(self, settings, model):
        super().__init__(settings, model)
        s = np.atleast_1d(np.asarray(settings.sigma, dtype=float))
        self._sigma = np.broadcast_to(s, (2,)).copy()

    @property
    def channel_names(self):
        return NAMES

    @property
    def channel_units(self):  # the crossing and the origin in length, the unit axes
        return (self.model.length_unit,) * 5 + ("1",) * 6

    # ------------------------------------------------------------------ measurement model
    @staticmethod
    def _pose(context: np.ndarray):
        o, eu, ev = context[..., 0:3], context[..., 3:6], context[..., 6:9]
        return o, eu, ev, np.cross(eu, ev)

    def h(self, x, context):
        """The crossing of the image plane with the arc back from the tip, ``(..., 2)`` in the plane's
        coordinates, for states ``x (..., n)`` and poses ``context (..., 9)`` (broadcast)."""
        o, eu, ev, n = self._pose(context)
        X, _ = plane_crossing(*self.path_twist(x), o, n)
        d = X - o
        return np.stack([np.einsum("...i,...i->...", eu, d), np.einsum("...i,...i->...", ev, d)], -1)

    def h_tip(self, x, context):
        """The reading ``tip``: the samples taken as the tip's own position, ``(..., 3)``: the tip in the
        plane's coordinates and its distance from the plane along the normal, ``w``, which this reading
        says is zero (the plane at the tip)."""
        o, eu, ev, n = self._pose(context)
        d = self.model.tip_position(x) - o
        n = n / np.linalg.norm(n, axis=-1, keepdims=True)
        return np.stack([np.einsum("...i,...i->...", e, d) for e in (eu, ev, n)], -1)

    def sigma(self, truth, idx):
        return np.concatenate([self._sigma, np.zeros(len(POSE))])

    # ------------------------------------------------------------------ emulation
    def planes(self, truth, idx: np.ndarray):
        """The probe's planes at the samples ``idx (M,)``: origin, ``e_u``, ``e_v``, normal, each ``(N, M, 3)``,
        and the grid index ``(M,)`` of the tip position each plane is placed from."""
        pr = self.settings.probe
        model = self.model
        time = truth.time
        dt = float(time[1] - time[0]) if len(time) > 1 else 1.0
        if pr.motion == "follow":
            at = np.maximum(idx - int(round(pr.lag / dt)), 0)
        elif pr.motion == "fixed":
            at = np.zeros_like(idx)
        else:
            at = idx
        x = truth.states_at(at)
        p, t = model.tip_position(x), model.tangent(x)
        t = t / np.linalg.norm(t, axis=-1, keepdims=True)
        along = pr.offset + (pr.amplitude * np.sin(2.0 * np.pi * time[idx] / pr.period) if pr.motion == "scan" else 0.0)
        eu, ev, n = image_axes(t, pr.tilt)
        return p + np.asarray(along)[..., None] * t, eu, ev, n, at

    def measure(self, truth, rng: np.random.Generator) -> MeasurementStream:
        idx = self.sample_indices(truth.time)
        o, eu, ev, n, at = self.planes(truth, idx)
        N, M = o.shape[:2]
        tip = self.model.tip_position(truth.states)  # (N, T, 3): the path, the shaft's positions
        X = np.full((N, M, 3), np.nan)
        found = np.zeros((N, M), dtype=bool)
        # the search back starts this far behind the point the plane is placed from (the runs' largest
        # commanded depth; speed_scale and the tilt are inside the 10-unit margin)
        depth = np.asarray(truth.depth, dtype=float)
        reach = depth.max(axis=0) if depth.ndim == 2 else depth
        pr = self.settings.probe
        back = abs(pr.offset) + (pr.amplitude if pr.motion == "scan" else 0.0) + 10.0
        lo = np.searchsorted(reach, reach[at] - back, side="left")
        if pr.motion == "fixed":
            lo[:] = 0
        for j, k in enumerate(idx):  # over samples (each its own plane); every run at once
            X[:, j], found[:, j] = path_crossing(tip[:, lo[j] : k + 1], o[:, j], n[:, j])
        d = X - o
        uv = np.stack([np.sum(eu * d, -1), np.sum(ev * d, -1)], -1)
        uv = uv + self._sigma * rng.standard_normal(uv.shape)
        value = np.concatenate([uv, o, eu, ev], -1)
        valid = found & np.isfinite(value).all(-1)
        sigma = np.broadcast_to(self.sigma(truth, idx), value.shape).copy()
        return self._stream(truth, idx, NO_PIPELINE, value, valid, sigma, rng)
