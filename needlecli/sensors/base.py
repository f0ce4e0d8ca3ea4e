"""The sensor contract and the seam for measurement pipelines.

A sensor owns its clock (rate, start, latency), its measurement function ``h``, its noise and its
dropouts. *How* a measurement is made from the truth is a :class:`Pipeline`: ``gaussian`` adds
statistical noise to ``h(truth)``; image pipelines (render a frame, segment it) register under another
name and are chosen per sensor with ``pipeline:`` in the config, with the same clock and output.

New sensors: subclass :class:`Sensor` with a ``Settings`` schema whose ``type`` is a ``Literal`` and
decorate with ``@SENSORS.register("type")``. New pipelines: subclass :class:`Pipeline`, list the sensor
types it supports, decorate with ``@PIPELINES.register("name")``.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, ClassVar

import numpy as np
from pydantic import Field, model_validator

from needlecli.models.base import NotMeasurable, StateSelection
from needlecli.numerics import wrap_angle
from needlecli.schema import Name, NonNeg, Positive, Probability, Strict
from needlecli.sensors import PIPELINES, SENSORS  # noqa: F401  (the registries, at the package's front door)

if TYPE_CHECKING:
    from needlecli.experiments.simulation.truth import Truth
    from needlecli.models import Model


class Outliers(Strict):
    """Gross errors of a sensor: each sample, with ``probability``, has ``scale`` times the noise std."""

    probability: Probability = Field(description="share of the samples that are gross errors")
    scale: Positive = Field(10.0, description="their noise std, in multiples of the sensor's sigma")


class SensorSettings(Strict):
    """Settings every sensor has. Times in s, rates in Hz."""

    type: str
    name: Name | None = Field(None, description="name in the results file (defaults to the type)")
    rate: Positive = Field(description="sampling rate, Hz")
    start: NonNeg = Field(0.0, description="time of the first sample, s")
    latency: NonNeg = Field(0.0, description="delay between acquisition and availability, s")
    dropout: Probability = Field(0.0, description="probability that a sample is lost")
    pipeline: str = Field("gaussian", description="how measurements are made: gaussian, or an image pipeline")
    outliers: Outliers | None = Field(None, description="gross errors (pipeline gaussian): a share of the samples "
                                                        "with scale times the noise std, a heavy-tailed (contaminated "
                                                        "Gaussian) sensor; default: none")

    @model_validator(mode="after")
    def _outliers(self):
        if self.outliers is not None and self.pipeline != "gaussian":
            raise ValueError("outliers are made by the gaussian pipeline; an image pipeline makes its own")
        return self


@dataclass(frozen=True)
class MeasurementStream:
    """What a sensor produced for all runs.

    Attributes
    ----------
    t : (M,) acquisition times (the state the measurement describes), s
    t_available : (M,) times the measurement becomes available (``t + latency``), s
    index : (M,) index of ``t`` on the simulation time grid
    value : (N, M, m) measured values; entries where ``valid`` is False are NaN
    valid : (N, M) bool
    sigma : (N, M, m) noise standard deviation used (the sensor's truth; observers bring their own R)
    """

    t: np.ndarray
    t_available: np.ndarray
    index: np.ndarray
    value: np.ndarray
    valid: np.ndarray
    sigma: np.ndarray
    names: tuple[str, ...]
    units: tuple[str, ...]
    attrs: dict = field(default_factory=dict)


class Sensor:
    """Base class of emulated sensors.

    Class attributes
    ----------------
    Settings : the pydantic schema of the sensor's config entry.
    requires : model quantities the sensor needs (names of :class:`~needlecli.models.Model` methods).
    """

    Settings: ClassVar[type[SensorSettings]] = SensorSettings
    requires: ClassVar[tuple[str, ...]] = ()
    registered_name: ClassVar[str] = ""

    def __init__(self, settings: SensorSettings, model: Model) -> None:
        self.settings = settings
        self.model = model
        self.name = settings.name or settings.type

    # ------------------------------------------------------------------ description
    @property
    def channel_names(self) -> tuple[str, ...]:
        raise NotImplementedError

    @property
    def channel_units(self) -> tuple[str, ...]:
        raise NotImplementedError

    @property
    def angle_channels(self) -> np.ndarray:
        """Boolean mask of channels that are angles (wrapped)."""
        return np.zeros(len(self.channel_names), dtype=bool)

    unit_vector: ClassVar[bool] = False  # channels form one unit vector (renormalised after noise)

    #: channels of each sample that are not measured but known with it (a transverse image plane's pose,
    #: :mod:`needlecli.sensors.transverse`): observers compare ``h`` with the other channels only and pass
    #: these to ``h`` as its ``context`` (:func:`context_columns`; the results file keeps every channel)
    context_channels: ClassVar[tuple[str, ...]] = ()
    #: the context given to ``h`` for a sample that is not valid (its stored context is NaN; masked out of
    #: every update, but NaN would survive the mask as ``NaN * 0``): one value per context channel, or empty
    #: for zeros
    neutral_context: ClassVar[tuple[float, ...]] = ()
    #: other readings of the same samples, by name: ``(method, extra)``, the name of a method ``(x, context) ->
    #: (..., m + len(extra))`` like :meth:`h` whose first ``m`` components predict the measured channels and
    #: whose ``extra`` ones are constraints the reading says are zero. An observer may choose one per channel
    #: (a transverse plane's ``tip``: each sample read as the tip's own position, in the plane at ``(u, v)``,
    #: the constraint ``w`` the tip's distance from the plane; the model a study compares with)
    readings: ClassVar[dict[str, tuple[str, tuple[str, ...]]]] = {}

    def check_model(self) -> str | None:
        """Why this sensor cannot measure the model, or None."""
        for q in self.requires:
            if not self.model.provides(q):
                return (
                    f"sensor {self.registered_name!r} measures {q.replace('_', ' ')}, which model "
                    f"{self.model.registered_name!r} does not have"
                )
        return None

    # ------------------------------------------------------------------ clock
    def sample_indices(self, time: np.ndarray) -> np.ndarray:
        """Indices of the simulation grid at which samples are acquired (nearest grid point)."""
        dt = float(time[1] - time[0]) if len(time) > 1 else 1.0
        t_end = float(time[-1])
        period = 1.0 / self.settings.rate
        n = int(np.floor((t_end - self.settings.start) / period + 1e-9)) + 1
        if n <= 0:
            return np.zeros(0, dtype=np.int64)
        ideal = self.settings.start + period * np.arange(n)
        idx = np.rint(ideal / dt).astype(np.int64)
        idx = idx[idx < len(time)]
        return np.unique(idx)

    # ------------------------------------------------------------------ measurement model
    def h(self, x: np.ndarray) -> np.ndarray:
        """Noise-free measurement ``(..., m)`` of states ``x (..., n)`` (for observers). A sensor with
        :attr:`context_channels` takes ``h(x, context)``, ``context (..., k)`` those channels of the sample
        (broadcast against ``x``'s leading axes), and predicts the other ``m`` channels."""
        raise NotImplementedError

    def state_selection(self) -> np.ndarray | None:
        """Indices ``(m,)`` of the model's states when ``h(x) = x[..., indices]``, else None (the default:
        a sensor that knows its ``h`` is a plain selection says so, and filters may use the closed form)."""
        return None

    def ideal(self, truth: Truth, idx: np.ndarray) -> np.ndarray:
        """Noise-free measurement ``(N, M, m)`` of the truth at grid indices ``idx``."""
        return self.h(truth.states_at(idx))

    def sigma(self, truth: Truth, idx: np.ndarray) -> np.ndarray:
        """Noise standard deviation ``(N, M, m)`` at those samples."""
        raise NotImplementedError

    def perturb(self, ideal: np.ndarray, sigma: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """Add Gaussian noise; wrap angle channels; renormalise unit vectors. In place in the draws' array
        (the same numbers as ``ideal + sigma * z``: no temporaries the size of the samples)."""
        ideal, sigma = np.asarray(ideal, dtype=float), np.asarray(sigma, dtype=float)
        y = rng.standard_normal(ideal.shape)
        if np.broadcast_shapes(ideal.shape, sigma.shape) == ideal.shape:
            y *= sigma
            y += ideal
        else:
            y = ideal + sigma * y
        if self.unit_vector:
            y = y / np.linalg.norm(y, axis=-1, keepdims=True)
        mask = self.angle_channels
        if mask.size and mask.all():
            wrap_angle(y, out=y)
        elif mask.any():
            y[..., mask] = wrap_angle(y[..., mask])
        return y

    # ------------------------------------------------------------------ the whole thing
    #: ``progress(samples done, samples)``, set by the runner before :meth:`measure`: a pipeline that takes
    #: long (rendering frames) reports to it
    progress: Callable[[int, int], None] | None = None

    def measure(self, truth: Truth, rng: np.random.Generator) -> MeasurementStream:
        """Sample the truth on this sensor's clock through its pipeline, then apply dropouts."""
        idx = self.sample_indices(truth.time)
        pipeline = PIPELINES.get(self.settings.pipeline)()
        pipeline.progress = self.progress
        value, valid, sigma = pipeline.measure(self, truth, idx, rng)
        return self._stream(truth, idx, pipeline, value, valid, sigma, rng)

    def measure_live(self, sim, rng: np.random.Generator, on_frame) -> Callable[[Truth], MeasurementStream]:
        """Measure while the truth is simulated (``sim``: a :class:`~needlecli.experiments.simulation.truth.
        TruthSimulator`), in one pass, handing each sample's outputs to ``on_frame(j, outputs)`` before
        the simulation passes the sample's time (a controller in the loop). Returns ``finish(truth)``,
        which makes the stream of that pass once the truth is complete (noise ``sigma``, dropouts and the
        end of runs applied as :meth:`measure` does, from the same random stream afterwards)."""
        idx = self.sample_indices(sim.time)
        pipeline = PIPELINES.get(self.settings.pipeline)()
        value, valid = pipeline.measure_live(self, sim, idx, rng, on_frame)

        def finish(truth: Truth) -> MeasurementStream:
            sigma = pipeline.sigma_of(self, truth, idx, value)
            return self._stream(truth, idx, pipeline, value, valid, sigma, rng)

        return finish

    def _stream(self, truth, idx, pipeline, value, valid, sigma, rng) -> MeasurementStream:
        if self.settings.dropout > 0:
            valid = valid & (rng.random(valid.shape) >= self.settings.dropout)
        # a run's samples after its truth stopped (singular / diverged) are not measurements
        valid = valid & (truth.time[idx][None, :] <= truth.valid_until[:, None])
        value = np.where(valid[..., None], value, np.nan)
        t = truth.time[idx]
        return MeasurementStream(
            t=t,
            t_available=t + self.settings.latency,
            index=idx,
            value=value,
            valid=valid,
            sigma=sigma,
            names=self.channel_names,
            units=self.channel_units,
            attrs={"type": self.registered_name, "rate": self.settings.rate, "latency": self.settings.latency,
                   "dropout": self.settings.dropout, "pipeline": self.settings.pipeline, **pipeline.extras},
        )


class Pipeline:
    """How a sensor turns the truth into measurements. ``supports``: sensor types, or ``("*",)``."""

    supports: ClassVar[tuple[str, ...]] = ("*",)
    registered_name: ClassVar[str] = ""

    def __init__(self) -> None:
        #: further arrays of the last ``measure`` (e.g. saved frames), stored beside the stream's values
        self.extras: dict[str, np.ndarray] = {}
        #: ``progress(samples done, samples)``, set by the sensor before ``measure``; a pipeline that takes
        #: long (one frame at a time) calls it, a quick one may ignore it
        self.progress: Callable[[int, int], None] | None = None

    def measure(
        self, sensor: Sensor, truth: Truth, idx: np.ndarray, rng: np.random.Generator
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Return ``value (N, M, m)``, ``valid (N, M)`` and ``sigma (N, M, m)``."""
        raise NotImplementedError

    #: whether :meth:`measure_live` works (the pipeline can measure while the truth is simulated)
    live: ClassVar[bool] = False

    def measure_live(self, sensor: Sensor, sim, idx: np.ndarray, rng: np.random.Generator,
                     on_frame) -> tuple[np.ndarray, np.ndarray]:
        """Measure sample by sample while ``sim`` runs, advancing it only as far as each sample needs and
        calling ``on_frame(j, outputs)`` after sample ``j``. Return ``value (N, M, m)``, ``valid (N, M)``."""
        raise NotImplementedError(f"pipeline {self.registered_name!r} cannot measure while the truth is simulated")

    def sigma_of(self, sensor: Sensor, truth: Truth, idx: np.ndarray, value: np.ndarray) -> np.ndarray:
        """The sensor's stated noise ``(N, M, m)`` at its samples of the finished truth."""
        return np.ascontiguousarray(np.broadcast_to(sensor.sigma(truth, idx), value.shape))

    @classmethod
    def accepts(cls, sensor_type: str) -> bool:
        return "*" in cls.supports or sensor_type in cls.supports




@PIPELINES.register("gaussian")
class GaussianPipeline(Pipeline):
    """The statistical pipeline: ``h(truth) + N(0, sigma^2)`` per channel; with ``outliers``, a share of the
    samples ``h(truth) + N(0, (scale sigma)^2)`` instead (gross errors: a contaminated Gaussian)."""

    def measure(self, sensor, truth, idx, rng):
        ideal = sensor.ideal(truth, idx)
        sigma = np.broadcast_to(sensor.sigma(truth, idx), ideal.shape)
        value = sensor.perturb(ideal, sigma, rng)
        o = getattr(sensor.settings, "outliers", None)
        if o is not None:  # drawn after the ordinary noise: the same noise as without them
            gross = rng.random(ideal.shape[:2]) < o.probability
            value = np.where(gross[..., None], sensor.perturb(ideal, sigma * o.scale, rng), value)
        valid = np.ones(ideal.shape[:2], dtype=bool)
        return value, valid, np.ascontiguousarray(sigma)


class _NoPipeline:
    """What :meth:`Sensor._stream` reads of a pipeline, for sensors that make their samples themselves (a
    transverse plane's crossing, the inserted length): no extra arrays."""

    extras: dict = {}


#: the stand-in pipeline of sensors that make their samples themselves
NO_PIPELINE = _NoPipeline()


def measurement_function(sensor, model, reading: str | None = None):
    """``h`` of ``sensor`` for the state of ``model`` (which may be an observer's own), or None; with
    ``reading`` (one of the sensor's :attr:`~Sensor.readings`) that reading of the samples instead. A sensor
    with :attr:`~Sensor.context_channels` gives ``h(x, context)``."""
    if reading is not None and reading not in sensor.readings:
        raise ValueError(f"sensor {sensor.name!r} ({sensor.registered_name}) has no reading {reading!r}"
                         + (f"; readings: {', '.join(sensor.readings)}" if sensor.readings else ""))
    if model is not sensor.model:
        sensor = type(sensor)(sensor.settings, model)
        if sensor.check_model():
            return None
    fn = sensor.h if reading is None else Reading(getattr(sensor, sensor.readings[reading][0]),
                                                  sensor.readings[reading][1])
    k = len(sensor.context_channels)
    try:
        with np.errstate(all="ignore"):
            fn(np.zeros((1, model.n)), *((np.zeros((1, k)),) if k else ()))
    except NotMeasurable:
        return None
    sel = None if k or reading is not None else sensor.state_selection()
    return fn if sel is None else StateSelection(sel)


class Reading:
    """Another reading of a sensor's samples (:attr:`Sensor.readings`): ``fn(x, *context) -> (..., m + e)``,
    the first ``m`` components predicting the measured channels, the last ``e`` the constraints ``extra``
    (names) that the reading says are zero (observers append zeros to the samples for them)."""

    __slots__ = ("fn", "extra")

    def __init__(self, fn, extra: tuple[str, ...] = ()) -> None:
        self.fn = fn
        self.extra = tuple(extra)

    def __call__(self, x, *context):
        return self.fn(x, *context)


def with_constraints(h, value: np.ndarray, names: tuple[str, ...]) -> tuple[np.ndarray, tuple[str, ...]]:
    """The samples ``value (N, M, m)`` and channel ``names`` that ``h`` predicts: those of the channel, with
    a zero (NaN where the sample is NaN) and the name of each constraint of a :class:`Reading` appended."""
    extra = getattr(h, "extra", ())
    if not extra:
        return value, tuple(names)
    nan = ~np.isfinite(value).all(-1, keepdims=True)
    zeros = np.where(nan, np.nan, np.zeros(value.shape[:-1] + (len(extra),)))
    return np.concatenate([value, zeros], -1), (*names, *extra)


def sample_context(sensor, value: np.ndarray) -> np.ndarray | None:
    """The context of a sensor's samples ``value (N, M, channels)``: ``(N, M, k)``, finite everywhere (a
    sample without one, not valid, gets :attr:`~Sensor.neutral_context`); None for a sensor without
    :attr:`~Sensor.context_channels`."""
    _, ctx = context_columns(sensor)
    if ctx is None:
        return None
    c = np.asarray(value, dtype=float)[..., ctx]
    fill = np.asarray(sensor.neutral_context or np.zeros(len(ctx)), dtype=float)
    return np.ascontiguousarray(np.where(np.isfinite(c).all(-1, keepdims=True), c, fill))


def context_columns(sensor) -> tuple[np.ndarray, np.ndarray | None]:
    """Indices of a sensor's measured channels ``(m,)`` and of its context channels ``(k,)`` (None: it has
    none) among :attr:`~Sensor.channel_names` (:attr:`~Sensor.context_channels`)."""
    names = list(sensor.channel_names)
    ctx = [names.index(c) for c in sensor.context_channels]
    meas = np.array([i for i in range(len(names)) if i not in ctx], dtype=np.int64)
    return meas, (np.array(ctx, dtype=np.int64) if ctx else None)


def inequality_function(sensor, model):
    """For a sensor whose samples bound the state from one side (``inequality = True``, e.g. an image
    plane): ``bound(x, value) -> (g, side)`` for the state of ``model``, each sample saying
    ``side * g >= 0``; None for other sensors or a model the sensor cannot bound."""
    if not getattr(sensor, "inequality", False):
        return None
    if model is not sensor.model:
        sensor = type(sensor)(sensor.settings, model)
    return None if sensor.check_model() else sensor.bound
