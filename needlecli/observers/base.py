"""The observer contract.

An observer knows nothing about where measurements come from: it is handed an :class:`EstimationProblem`
(time grid, known inputs, measurement channels each with its ``h``) and returns a :class:`Posterior` with
means, covariances and a status per run, on the problem's time grid. It works on all runs at once.

New observers: subclass :class:`Observer` with a ``Settings`` schema whose ``type`` is a ``Literal``
and decorate with ``@OBSERVERS.register("type")``.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import ClassVar

import numpy as np
from pydantic import Field

from needlecli.models import Model
from needlecli.registry import Registry
from needlecli.schema import Strict

STATUS_OK = "ok"
STATUS_DIVERGED = "diverged"
STATUS_SINGULAR = "singular"
STATUS_UNOBSERVABLE = "unobservable"  # the inputs cannot make the estimate converge (seed 001)


class ObserverSettings(Strict):
    """Settings every observer has."""

    type: str
    name: str | None = Field(None, description="name in the results file (defaults to the type)")


@dataclass(frozen=True)
class Channel:
    """One measurement stream as an observer sees it.

    Attributes
    ----------
    name : sensor name
    t : (M,) acquisition times, s; ``t_available`` (M,) when they can be used
    index : (M,) index of ``t`` on the problem's time grid
    value : (N, M, m), NaN where not ``valid`` (N, M)
    h : ``h(x (..., n)) -> (..., m)`` for the experiment model's state, or None when the channel is not
        a function of the state (e.g. encoder depth)
    h_for : ``h_for(model)`` gives the same measurement function for another model (an observer's own),
        or None where that model cannot predict the channel
    sigma : (m,) the sensor's nominal noise std (observers may use their own R instead)
    angle : (m,) bool, channels compared wrapped
    """

    name: str
    sensor_type: str
    t: np.ndarray
    t_available: np.ndarray
    index: np.ndarray
    value: np.ndarray
    valid: np.ndarray
    names: tuple[str, ...]
    units: tuple[str, ...]
    sigma: np.ndarray
    angle: np.ndarray
    h: Callable[[np.ndarray], np.ndarray] | None
    h_for: Callable[[Model], Callable[[np.ndarray], np.ndarray] | None] = lambda model: None
    unit_vector: bool = False
    attrs: Mapping = field(default_factory=dict)


@dataclass(frozen=True)
class EstimationProblem:
    """Everything an observer may use: no truth beyond what its settings allow for initialisation."""

    time: np.ndarray  # (T,)
    inputs: np.ndarray  # (N, T, m) known inputs, held over [t_k, t_k+1)
    input_names: tuple[str, ...]
    depth: np.ndarray  # (N, T) inserted length from the commanded insertion
    channels: Mapping[str, Channel]
    model: Model  # the experiment's model (the observer may use its own)
    params: Mapping[str, np.ndarray]  # nominal model parameters from the config
    interfaces: np.ndarray  # tissue interface depths known to the experiment
    initial_truth: np.ndarray | None = None  # (N, n) only for observers configured to start from it
    cov_stride: int = 1  # keep covariances every k-th step of the time grid
    cov_layout: str = "full"  # "full" (..., n, n), "diag" (..., n) or "none"
    kernels: str = "auto"  # compiled kernels or the numpy reference (needlecli.kernels.compiled)

    @property
    def n_runs(self) -> int:
        return self.inputs.shape[0]


@dataclass
class Posterior:
    """Observer output on the problem's time grid.

    state : (N, T, n); cov : (N, T, n, n) or None; status : (N,) str; reason : (N,) str;
    names, units : per state; extras : further named arrays (stored under the observer's group).
    """

    state: np.ndarray
    cov: np.ndarray | None
    status: np.ndarray
    reason: np.ndarray
    names: tuple[str, ...]
    units: tuple[str, ...]
    angle_states: tuple[str, ...] = ()
    extras: dict[str, np.ndarray] = field(default_factory=dict)
    attrs: dict = field(default_factory=dict)


def cov_steps(n_steps: int, stride: int) -> np.ndarray:
    """Indices of the time grid at which covariances are kept."""
    return np.arange(0, n_steps, stride)


def shrink_cov(p: np.ndarray, layout: str) -> np.ndarray | None:
    """A covariance ``(..., n, n)`` in the stored layout."""
    if layout == "none":
        return None
    if layout == "diag":
        return np.diagonal(p, axis1=-2, axis2=-1).copy()
    return p


class Observer:
    """Base class of observers. ``compatible(model)`` tells the config check whether it can run."""

    Settings: ClassVar[type[ObserverSettings]] = ObserverSettings
    registered_name: ClassVar[str] = ""

    def __init__(self, settings: ObserverSettings) -> None:
        self.settings = settings
        self.name = settings.name or settings.type

    @classmethod
    def check(cls, settings: ObserverSettings, model: Model, sensors: Mapping) -> list[tuple[tuple, str]]:
        """Problems with running on ``model`` with ``sensors`` (name -> Sensor): ``[(loc, message)]``."""
        return []

    def run(self, problem: EstimationProblem, rng: np.random.Generator, progress=None) -> Posterior:
        raise NotImplementedError


OBSERVERS: Registry[type[Observer]] = Registry("observer type")
