"""The controller contract: a controller reads one sensor's samples as they are measured and acts on the
truth's state between grid steps.

A closed-loop experiment (:func:`needlecli.experiments.simulation.closed_loop.simulate_closed_loop`) runs the truth as a
stepper (:class:`~needlecli.experiments.simulation.truth.TruthSimulator`); the controller's sensor measures while it
runs, one sample at a time, and hands each sample's outputs to :meth:`Controller.on_sample` before the
simulation passes the sample's time. A command becomes effective at the first grid time at or after the
sample's availability (``t + latency``, as observers use samples), where :meth:`Controller.before_step`
changes the state before the RK4 step from that time.

New controllers: subclass :class:`Controller` with a ``Settings`` schema whose ``type`` is a ``Literal``
and decorate with ``@CONTROLLERS.register("type")``; the settings join the config schema.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import ClassVar

import numpy as np
from pydantic import Field

from needlecli.control import CONTROLLERS  # noqa: F401  (the registry, at the package's front door)
from needlecli.io.tree import Group
from needlecli.schema import Name, Strict


class ControllerSettings(Strict):
    """Settings every controller has."""

    type: str
    name: Name | None = Field(None, description="name in the results file (default: the type)")
    sensor: str = Field(description="the sensor whose samples the controller acts on (it is measured in the loop)")


def available_index(t_available: np.ndarray, dt: float) -> np.ndarray:
    """Grid index at which samples available at ``t_available`` can first be used (as the observers do)."""
    return np.ceil(np.asarray(t_available, dtype=float) / dt - 1e-9).astype(np.int64)


class Controller:
    """Base class of controllers.

    Class attributes
    ----------------
    Settings : the pydantic schema of the controller's config entry.
    acts_on : what the controller sets (two controllers of one experiment cannot set the same thing).
    """

    Settings: ClassVar[type[ControllerSettings]] = ControllerSettings
    acts_on: ClassVar[str] = ""
    registered_name: ClassVar[str] = ""

    def __init__(self, settings: ControllerSettings, model) -> None:
        self.settings = settings
        self.model = model
        self.name = settings.name or settings.type

    @classmethod
    def check(cls, settings: ControllerSettings, model, sensors: Mapping) -> list[tuple[tuple, str]]:
        """Problems with running on ``model`` with ``sensors`` (name -> Sensor; the named sensor exists):
        ``[(loc, message)]``, ``loc`` relative to the controller's entry."""
        return []

    def start(self, time: np.ndarray, n_runs: int, sample_index: np.ndarray, t_available: np.ndarray) -> None:
        """Before the simulation: the grid ``time (T,)``, the sensor's samples (grid index of each
        acquisition ``(M,)`` and availability time ``(M,)``)."""
        raise NotImplementedError

    def on_sample(self, j: int, outputs: dict[str, np.ndarray]) -> None:
        """Sample ``j`` of the sensor is measured for every run (``outputs``: the device's per-sample
        arrays, ``(N, ...)``); called before the simulation passes the sample's acquisition time."""
        raise NotImplementedError

    def first_action(self, j: int) -> int:
        """Grid index at which sample ``j`` first acts (the loop checks it is not in the past)."""
        raise NotImplementedError

    def before_step(self, k: int, x: np.ndarray) -> np.ndarray:
        """Act at grid index ``k`` (before the step from ``t_k``) on the states ``x (N, n)``; return the
        new states, or ``x`` itself when nothing changes. Called once for every grid index, in order."""
        raise NotImplementedError

    def results(self, truth) -> Group:
        """What the controller did, for ``/control/<name>`` of the results file."""
        raise NotImplementedError
