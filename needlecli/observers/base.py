"""The observer contract.

An observer knows nothing about where measurements come from: it is handed an :class:`EstimationProblem`
(time grid, known inputs, measurement channels each with its ``h``) and returns a :class:`Posterior` with
means, covariances and a status per run, on the problem's time grid. It works on all runs at once.

New observers: subclass :class:`Observer` with a ``Settings`` schema whose ``type`` is a ``Literal``
and decorate with ``@OBSERVERS.register("type")``.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import ClassVar

import numpy as np
from pydantic import Field

from needlecli.models import Model
from needlecli.observers import OBSERVERS  # noqa: F401  (the registry, at the package's front door)
from needlecli.problem import Channel, CommonStart, EstimationProblem  # noqa: F401  (part of the observer contract)
from needlecli.schema import Name, Strict

STATUS_OK = "ok"
STATUS_DIVERGED = "diverged"
STATUS_SINGULAR = "singular"
STATUS_UNOBSERVABLE = "unobservable"  # the inputs cannot make the estimate converge (seed 001)


class ObserverSettings(Strict):
    """Settings every observer has."""

    type: str
    name: Name | None = Field(None, description="name in the results file (defaults to the type)")


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
    #: whether :meth:`run` starts from ``problem.start`` when the problem carries a common start
    #: (``needle compare``); an observer that cannot is marked as starting from its own settings
    takes_common_start: ClassVar[bool] = False
    #: whether the estimate at time t uses the samples available up to t only (False: a smoother)
    causal: ClassVar[bool] = True

    def __init__(self, settings: ObserverSettings) -> None:
        self.settings = settings
        self.name = settings.name or settings.type

    @classmethod
    def check(cls, settings: ObserverSettings, model: Model, sensors: Mapping) -> list[tuple[tuple, str]]:
        """Problems with running on ``model`` with ``sensors`` (name -> Sensor): ``[(loc, message)]``."""
        return []

    @classmethod
    def initial_estimate(cls, settings: ObserverSettings, problem: EstimationProblem,
                         rng: np.random.Generator) -> CommonStart | None:
        """The initial estimate this observer would start from (its own draw from ``rng``), as a common
        start for the others of a comparison; None for an observer that cannot give one."""
        return None

    def run(self, problem: EstimationProblem, rng: np.random.Generator, progress=None) -> Posterior:
        raise NotImplementedError
