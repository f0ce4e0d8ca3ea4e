"""The sensors of the seeds at the statistical level (``MODELS.md``, "Emulated hardware").

Positions are in the model's length unit (mm; m for the magnetic models), angles in rad. Image-based
versions of the same sensors plug in as pipelines (``pipeline: image``) with the same output.
"""

from __future__ import annotations

from typing import Literal

import numpy as np
from pydantic import Field, field_validator

from needlecli.models import NotMeasurable
from needlecli.schema import DistanceGrowth, NonNeg
from needlecli.sensors.base import SENSORS, Sensor, SensorSettings
from needlecli.sensors.imaging import DEVICES, ImageSection

Sigma = NonNeg | list[NonNeg]


def _per_channel(sigma: float | list[float], m: int, what: str) -> np.ndarray:
    s = np.atleast_1d(np.asarray(sigma, dtype=float))
    if s.size == 1:
        return np.full(m, float(s[0]))
    if s.size != m:
        raise ValueError(f"{what} has {s.size} entries for {m} channels")
    return s


_AXES = ("x", "y", "z")


class PositionSettings(SensorSettings):
    type: Literal["position"]
    axes: list[Literal["x", "y", "z"]] = Field(default_factory=lambda: ["x", "y", "z"], min_length=1,
                                               description="the tip coordinates it measures, each a channel "
                                                           "(2D transverse ultrasound: [x, y])")
    sigma: Sigma = Field(0.3, description="noise std per axis at the transducer, model length unit")
    growth: DistanceGrowth | None = Field(None, description="noise growing with the distance to a transducer, "
                                                            "sigma = (1 + a d / d_max) sigma (the multi-rate UKF paper); default: "
                                                            "constant sigma")
    image: ImageSection | None = Field(
        None, validate_default=True, description="with pipeline: image, the imaging device (sensors/imaging)")

    @field_validator("axes")
    @classmethod
    def _unique(cls, v):
        if len(set(v)) != len(v):
            raise ValueError("axes must not repeat")
        return v

    @field_validator("image")
    @classmethod
    def _image(cls, v, info):
        if info.data.get("pipeline") != "image":
            if v is not None:
                raise ValueError("is used only with pipeline: image")
            return v
        if v is None:
            raise ValueError("required with pipeline: image (device: us2d, us3d or camera)")
        has = DEVICES.get(v.device).axes
        missing = [a for a in info.data.get("axes") or [] if a not in has]
        if missing:
            raise ValueError(f"device {v.device!r} measures {', '.join(has)}, not {', '.join(missing)}: set axes")
        return v


@SENSORS.register("position")
class PositionSensor(Sensor):
    """Tip position, any subset of axes: 2D transverse ultrasound (x, y; the high-gain observer paper), 3D ultrasound
    (x, y, z at 1 Hz, sigma growing with distance; the multi-rate UKF paper), overhead camera (the magnetic needle EM paper)."""

    Settings = PositionSettings
    requires = ("tip_position",)

    def __init__(self, settings, model):
        super().__init__(settings, model)
        self._cols = [_AXES.index(a) for a in settings.axes]
        self._sigma = _per_channel(settings.sigma, len(self._cols), "sigma")

    @property
    def channel_names(self):
        return tuple(self.settings.axes)

    @property
    def channel_units(self):
        return (self.model.length_unit,) * len(self._cols)

    def h(self, x):
        return self.model.tip_position(x)[..., self._cols]

    def state_selection(self):
        sel = self.model.state_selection("tip_position")
        return None if sel is None else sel[self._cols]

    def sigma(self, truth, idx):
        g = self.settings.growth
        if g is None:
            return self._sigma
        return g.factor(self.model.tip_position(truth.states_at(idx)))[..., None] * self._sigma


class EncoderSettings(SensorSettings):
    type: Literal["encoder"]
    channels: list[Literal["depth", "roll", "base_angle"]] = Field(
        default_factory=lambda: ["depth", "roll"], min_length=1,
        description="what it reads: depth (inserted length, model length unit), roll (the needle's roll angle, "
                    "rad), base_angle (rad)",
    )
    sigma: Sigma = Field(0.0035, description="noise std per channel (mm for depth, rad for angles)")

    @field_validator("channels")
    @classmethod
    def _unique(cls, v):
        if len(set(v)) != len(v):
            raise ValueError("channels must not repeat")
        return v


@SENSORS.register("encoder")
class EncoderSensor(Sensor):
    """Robot encoders (the high-gain observer and multi-rate UKF papers): insertion depth, the needle's roll angle, the base angle
    (integral of the shaft rotation input). The multi-rate UKF paper reads the tip roll gamma from the robot
    (0.2 deg std)."""

    Settings = EncoderSettings

    def __init__(self, settings, model):
        super().__init__(settings, model)
        self._sigma = _per_channel(settings.sigma, len(settings.channels), "sigma")

    @property
    def requires(self):  # type: ignore[override]
        return ("roll",) if "roll" in self.settings.channels else ()

    @property
    def channel_names(self):
        return tuple(self.settings.channels)

    @property
    def channel_units(self):
        return tuple(self.model.length_unit if c == "depth" else "rad" for c in self.settings.channels)

    @property
    def angle_channels(self):
        return np.array([c != "depth" for c in self.settings.channels])

    def h(self, x):
        if any(c != "roll" for c in self.settings.channels):
            raise NotMeasurable("encoder depth and base angle are inputs, not functions of the state")
        return self.model.roll(x)[..., None]

    def state_selection(self):
        if any(c != "roll" for c in self.settings.channels):
            return None
        return self.model.state_selection("roll")

    def ideal(self, truth, idx):
        n_runs = truth.states.shape[0]
        cols = []
        for c in self.settings.channels:
            if c == "depth":
                cols.append(np.broadcast_to(truth.depth[idx], (n_runs, len(idx))))
            elif c == "base_angle":
                cols.append(truth.base_angle[:, idx])
            else:
                cols.append(self.model.roll(truth.states_at(idx)))
        return np.stack(cols, -1)

    def sigma(self, truth, idx):
        return self._sigma


class ElastographySettings(SensorSettings):
    type: Literal["elastography"]
    sigma: NonNeg = Field(1e-3, description="curvature noise std, 1/(model length unit)")
    interface_sigma: NonNeg = Field(0.0, description="std of the interface depths it reports")
    preoperative: bool = Field(False, description="a pre-operative map (the multi-rate UKF paper): one acquisition at start, not a stream at rate")


@SENSORS.register("elastography")
class ElastographySensor(Sensor):
    """Shear-wave elastography (the multi-rate UKF paper): the stiffness map gives the curvature at the tip's depth
    and the tissue interfaces (reported in the stream's attributes); ``preoperative: true`` makes it the
    pre-operative map of the multi-rate UKF paper's simulations: one acquisition at ``start``, no stream."""

    Settings = ElastographySettings

    @property
    def channel_names(self):
        return ("kappa",)

    @property
    def channel_units(self):
        return (f"1/{self.model.length_unit}",)

    def check_model(self):
        if self.model.curvature_param is None:
            return f"model {self.model.registered_name!r} has no curvature for elastography to measure"
        return None

    def h(self, x):
        name = self.model.curvature_param
        if name not in self.model.state_names:
            raise NotMeasurable(f"model {self.model.registered_name!r} does not carry curvature as a state")
        return x[..., [self.model.index(name)]]

    def state_selection(self):
        name = self.model.curvature_param
        return np.array([self.model.index(name)]) if name in self.model.state_names else None

    def sample_indices(self, time):
        idx = super().sample_indices(time)
        return idx[:1] if self.settings.preoperative else idx  # the map, once, before the insertion goes on

    def ideal(self, truth, idx):
        return truth.params[self.model.curvature_param][:, idx][..., None]

    def sigma(self, truth, idx):
        return np.array([self.settings.sigma])

    def measure(self, truth, rng):
        stream = super().measure(truth, rng)
        depths = np.asarray(truth.interfaces, dtype=float)
        if depths.size and self.settings.interface_sigma > 0:
            depths = depths + self.settings.interface_sigma * rng.standard_normal(
                (truth.states.shape[0], depths.size)
            )
        else:
            depths = np.broadcast_to(depths, (truth.states.shape[0], depths.size))
        stream.attrs["interfaces"] = np.ascontiguousarray(depths)
        return stream


class UnitVectorSettings(SensorSettings):
    sigma: NonNeg = Field(0.01, description="angular noise std, rad")


class TangentSettings(UnitVectorSettings):
    type: Literal["tangent"]


@SENSORS.register("tangent")
class TangentSensor(Sensor):
    """Needle tangent direction as a unit vector (bi-plane fluoroscopy or an EM tracker; the SO(3) observer paper)."""

    Settings = TangentSettings
    requires = ("tangent",)
    unit_vector = True

    @property
    def channel_names(self):
        return ("tx", "ty", "tz")

    @property
    def channel_units(self):
        return ("1", "1", "1")

    def h(self, x):
        return self.model.tangent(x)

    def sigma(self, truth, idx):
        return np.full(3, self.settings.sigma)


class FieldSettings(UnitVectorSettings):
    type: Literal["bfield"]


@SENSORS.register("bfield")
class FieldDirectionSensor(Sensor):
    """Direction of the magnetic field from the Helmholtz coils' record (the magnetic needle EM paper: 18 Hz)."""

    Settings = FieldSettings
    requires = ("field_direction",)
    unit_vector = True

    @property
    def channel_names(self):
        return ("bx", "by", "bz")

    @property
    def channel_units(self):
        return ("1", "1", "1")

    def h(self, x):
        return self.model.field_direction(x)

    def sigma(self, truth, idx):
        return np.full(3, self.settings.sigma)
