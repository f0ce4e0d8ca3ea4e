"""The configured components, built and called at the boundary: every call the runner, the closed loop and
the studies make into a model, sensor, observer or controller goes through here, built-in or plug-in alike.

Each call is guarded (:class:`needlecli.guard.Component`: a failure, ``sys.exit`` included, is one
:class:`~needlecli.errors.ComponentError` naming the component and its package) and what it returns is
checked against the problem by its role's contract (:func:`needlecli.observers.contract.check_posterior`,
:func:`needlecli.sensors.contract.check_stream`), before anything is written.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING

import numpy as np

from needlecli.control import CONTROLLERS
from needlecli.guard import Component
from needlecli.models import MODELS
from needlecli.observers import OBSERVERS
from needlecli.observers.contract import check_posterior, check_start
from needlecli.sensors import SENSORS
from needlecli.sensors.contract import check_stream

if TYPE_CHECKING:
    from needlecli.control.base import Controller, ControllerSettings
    from needlecli.experiments.config.types import ExperimentConfig
    from needlecli.experiments.simulation.truth import Truth
    from needlecli.observers.base import Observer, ObserverSettings, Posterior
    from needlecli.problem import CommonStart, EstimationProblem
    from needlecli.sensors.base import MeasurementStream, Sensor


# ---------------------------------------------------------------------------------------------- models
def model_component(cfg: ExperimentConfig) -> Component:
    """The experiment's model, as messages name it."""
    return Component.of(MODELS, cfg.model.type)


def simulated(cfg: ExperimentConfig, what: str, fn: Callable, /, *args, **kwargs):
    """``fn(*args, **kwargs)``, a step of the truth simulation (the model's own code runs there), guarded as
    the model's call ``what``."""
    return model_component(cfg).call(what, fn, *args, **kwargs)


# ---------------------------------------------------------------------------------------------- sensors
def sensor_component(sensor: Sensor) -> Component:
    return Component.of(SENSORS, sensor.settings.type, sensor.name)


def build_sensors(cfg: ExperimentConfig, model) -> list[Sensor]:
    """One sensor per entry of the config's ``sensors`` (each constructor guarded)."""
    return [Component.of(SENSORS, s.type, s.name).call("__init__", SENSORS.get(s.type), s, model)
            for s in cfg.sensors]


def measure(sensor: Sensor, truth: Truth, rng: np.random.Generator) -> MeasurementStream:
    """``sensor.measure(truth, rng)``, guarded, its stream checked against the truth."""
    comp = sensor_component(sensor)
    st = comp.call("measure", sensor.measure, truth, rng)
    comp.returned("measure", check_stream, st, truth.states.shape[0], len(truth.time))
    return st


def measured(sensor: Sensor, what: str, fn: Callable[..., MeasurementStream], truth: Truth, /, *args) -> MeasurementStream:
    """A stream the sensor makes another way (``fn(truth, *args)``: the closed loop's pass), guarded and
    checked as :func:`measure`."""
    comp = sensor_component(sensor)
    st = comp.call(what, fn, truth, *args)
    comp.returned(what, check_stream, st, truth.states.shape[0], len(truth.time))
    return st


# ---------------------------------------------------------------------------------------------- observers
def observer_component(o: ObserverSettings) -> Component:
    return Component.of(OBSERVERS, o.type, o.name)


def build_observer(o: ObserverSettings) -> Observer:
    """The observer of config entry ``o`` (its constructor guarded)."""
    return observer_component(o).call("__init__", OBSERVERS.get(o.type), o)


def run_observer(obs: Observer, o: ObserverSettings, problem: EstimationProblem, rng: np.random.Generator,
                 progress: Callable[[int, int], None] | None = None) -> Posterior:
    """``obs.run(problem, rng, progress=progress)``, guarded, its posterior checked against ``problem``."""
    comp = observer_component(o)
    post = comp.call("run", obs.run, problem, rng, progress=progress)
    comp.returned("run", check_posterior, post, problem)
    return post


def initial_estimate(o: ObserverSettings, problem: EstimationProblem, rng: np.random.Generator) -> CommonStart | None:
    """The initial estimate the observer of ``o`` shares (``Observer.initial_estimate``), guarded and checked."""
    comp = observer_component(o)
    start = comp.call("initial_estimate", OBSERVERS.get(o.type).initial_estimate, o, problem, rng)
    comp.returned("initial_estimate", check_start, start, problem)
    return start


# ---------------------------------------------------------------------------------------------- controllers
class GuardedController:
    """A controller whose every call is guarded; ``before_step`` must return the states' shape."""

    def __init__(self, c: ControllerSettings, model) -> None:
        self.component = Component.of(CONTROLLERS, c.type, c.name)
        self.inner: Controller = self.component.call("__init__", CONTROLLERS.get(c.type), c, model)
        self.name = self.inner.name
        self.settings = self.inner.settings

    def start(self, time, n_runs, sample_index, t_available) -> None:
        self.component.call("start", self.inner.start, time, n_runs, sample_index, t_available)

    def on_sample(self, j: int, outputs: dict) -> None:
        self.component.call("on_sample", self.inner.on_sample, j, outputs)

    def first_action(self, j: int) -> int:
        k = self.component.call("first_action", self.inner.first_action, j)
        if not isinstance(k, (int, np.integer)) or isinstance(k, bool):
            raise self.component.broke("first_action", f"{k!r}, not a grid index")
        return int(k)

    def before_step(self, k: int, x: np.ndarray) -> np.ndarray:
        xa = self.component.call("before_step", self.inner.before_step, k, x)
        if xa is not x and (not isinstance(xa, np.ndarray) or xa.shape != x.shape or xa.dtype.kind not in "fiu"):
            shape = getattr(xa, "shape", None)
            raise self.component.broke("before_step", f"{type(xa).__name__} of shape {shape}, expected the "
                                       f"states' (N, n) = {x.shape}")
        return xa

    def results(self, truth):
        return self.component.call("results", self.inner.results, truth)
