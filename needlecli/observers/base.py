"""The observer contract.

An observer knows nothing about where measurements come from: it is handed an :class:`EstimationProblem`
(time grid, known inputs, measurement channels each with its ``h``) and returns a :class:`Posterior` with
means, covariances and a status per run, on the problem's time grid. It works on all runs at once.

New observers: subclass :class:`Observer` with a ``Settings`` schema whose ``type`` is a ``Literal``
and decorate with ``@OBSERVERS.register("type")`` (or register it through an entry point). Besides
``run``, an observer class declares what the rest of needlecli needs to know about it, read through
the registry (nothing outside the observer's module names its type):

* ``check``: problems with running on a model and sensors (the config check, ``needle compare``);
* ``takes_common_start``, ``initial_estimate``, ``default_reference``, ``prescribed_start``: its part
  in the common start of a comparison (``needle compare``, ``needle crossval``);
* ``causal``: a filter (True) or a smoother; ``model_only``: the model alone (the open loop), which a
  filter must beat;
* ``derived_settings``: its settings for a fair comparison, from the experiment
  (:class:`~needlecli.observers.defaults.ComparisonContext`);
* ``fit_takes``: what ``from_fit`` may set on it from a fit of ``needle fit-em`` (:class:`FitTakes`);
* ``upgrade_settings``: how its keys of an older config format convert to their current meaning.

Keys mean one thing in every observer: ``q`` is the process noise std per state in the state's unit per
square-root second (the truth's ``process_noise.std``; a filter with ticks takes ``q sqrt(dt_tick)`` per
tick itself), ``p0`` an initial variance per state (the unit squared), ``sigma`` a measurement noise std per
component, ``rate`` a frequency in Hz.

A subclass registered under another name inherits all of it (a UKF variant is compared and tuned as
the UKF is, under its own type).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, ClassVar

import numpy as np
from pydantic import Field

from needlecli.models import Model
from needlecli.observers import OBSERVERS  # noqa: F401  (the registry, at the package's front door)
from needlecli.problem import Channel, CommonStart, EstimationProblem  # noqa: F401  (part of the observer contract)
from needlecli.schema import Name, Strict

if TYPE_CHECKING:
    from needlecli.observers.defaults import ComparisonContext

STATUS_OK = "ok"
STATUS_DIVERGED = "diverged"
STATUS_SINGULAR = "singular"
STATUS_UNOBSERVABLE = "unobservable"  # the inputs cannot make the estimate converge (the SO(3) observer paper)


class ObserverSettings(Strict):
    """Settings every observer has; an observer's ``Settings`` subclass adds its own keys as pydantic
    fields (each with a description: ``needle explain`` and the config reference show them), with
    ``type`` a ``Literal`` of its registered name. Unknown keys are refused.

    Attributes
    ----------
    type : str
        The registered name (the entry point's name for a plug-in).
    name : str or None
        The observer's name in the results file and the tables (default: the type).
    """

    type: str
    name: Name | None = Field(None, description="name in the results file (defaults to the type)")


@dataclass
class Posterior:
    """Observer output on the problem's time grid (``N`` runs, ``T`` grid times, ``n`` estimated states;
    checked by :mod:`needlecli.observers.contract` before it is written).

    Attributes
    ----------
    state : (N, T, n) ndarray
        The estimates; NaN only in a run whose status is not ``ok``, from where it stopped.
    cov : (N, T', n, n) or (N, T', n) ndarray, or None
        Covariances at grid steps ``0, s, 2s, ...`` (``s = problem.cov_stride``, ``T' = ceil(T / s)``) in
        ``problem.cov_layout`` (``full`` or ``diag``); None for layout ``none`` or an observer without one.
        Symmetric and positive semi-definite in every ``ok`` run.
    status, reason : (N,) str
        ``ok`` and ``""``, or ``diverged``, ``singular``, ``unobservable`` with why.
    names, units : tuple of str
        Each state's name and unit: a state the truth has by the same name is compared with it
        (``x``, ``y``, ``z`` give E_xyz, E_x, E_lat, ...).
    angle_states : tuple of str
        The states compared wrapped (angles).
    extras : dict of str to ndarray
        Further arrays with the runs first, stored under the observer's group (``nis/<channel>``, ...).
    attrs : dict
        Further attributes of the observer's group (texts, numbers, lists).
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


@dataclass(frozen=True)
class FitTakes:
    """What ``from_fit`` (:mod:`needlecli.experiments.config.from_fit`) may set on an observer from a fit of
    ``needle fit-em``: always its process noise ``q`` (the std of each fitted state's noise per square-root
    second, ``sqrt(Q_ii)``: the one meaning of ``q`` in every observer) and its model constants ``params``;
    further as declared here.

    Attributes
    ----------
    measurements : bool
        Whether it takes each fitted channel's noise as ``measurements.<channel>.sigma`` (and the
        channel's ``frame`` and ``across_axis`` where R was fitted in needle coordinates).
    sensor_states : bool
        Whether a channel has sensor states in it (``measurements.<channel>.along_offset``): it then takes
        a fitted offset along the needle as that state (``tau``, ``sigma``); without, the offset's
        variance joins the channel's noise along the needle.
    """

    measurements: bool = True
    sensor_states: bool = False


class Observer:
    """Base class of observers. ``compatible(model)`` tells the config check whether it can run."""

    Settings: ClassVar[type[ObserverSettings]] = ObserverSettings
    registered_name: ClassVar[str] = ""
    #: whether :meth:`run` starts from ``problem.start`` when the problem carries a common start
    #: (``needle compare``); an observer that cannot is marked as starting from its own settings
    takes_common_start: ClassVar[bool] = False
    #: whether the estimate at time t uses the samples available up to t only (False: a smoother)
    causal: ClassVar[bool] = True
    #: whether it is the model alone from its start, using no measurement: the reference a filter must
    #: beat (``needle compare`` warns when a filter's error is larger than such an observer's)
    model_only: ClassVar[bool] = False
    #: the compiled kernel that takes longest to compile, ``(module of needlecli.kernels, function)``, which a
    #: first run's warm-up compiles in a second process (:func:`needlecli.kernels.warm_up`); None: no kernel
    compiled_entry: ClassVar[tuple[str, str] | None] = None
    #: whether, with its derived settings, it gives the common start of a comparison whose config's
    #: observers give none (built-in types are tried before plug-ins, each in name order)
    default_reference: ClassVar[bool] = False
    #: what ``from_fit`` may set on it (None: it cannot take a fit)
    fit_takes: ClassVar[FitTakes | None] = None

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

    @classmethod
    def derived_settings(cls, ctx: ComparisonContext) -> dict:
        """Its settings for a fair comparison, derived from the experiment (``needle compare`` runs every
        registered type that the config does not name with these): a mapping in the config's form without
        ``type`` and ``name`` (the comparison fills in the registered name). The default: none, the
        schema's defaults.

        Raises
        ------
        NotApplicable
            (:class:`~needlecli.observers.defaults.NotApplicable`) it cannot derive settings for this
            experiment; the message says why.
        """
        return {}

    @classmethod
    def prescribed_start(cls, settings: ObserverSettings) -> str | None:
        """A start that ``settings`` prescribe on top of a common start (the high-gain observer paper's x_hat0 = beta_hat0 = 0),
        as the note for a comparison's table (``"x, beta = 0"``); None: the common start as it is."""
        return None

    @classmethod
    def upgrade_settings(cls, settings: dict, *, config_format: int, dt: float) -> list[str]:
        """Bring ``settings``, this observer's mapping in a config written in an older format
        (``config_format``, the config's ``format:``; 1 where it has none), to the current meaning of its
        keys, in place; ``dt`` is the config's grid step (``simulation.dt``), s. Called by the loader
        before the schema (:func:`needlecli.experiments.config.load.load_config`), with the values as the
        file gives them (check their types; leave what is not a valid value to the schema).

        Returns
        -------
        list of str
            One line per converted key, saying from what to what (the loader logs each and keeps it in the
            results file above the converted config). The default converts nothing: ``[]``.
        """
        return []

    def run(self, problem: EstimationProblem, rng: np.random.Generator, progress=None) -> Posterior:
        """Estimate every run of ``problem`` at once: the one method an observer must implement.

        Parameters
        ----------
        problem : EstimationProblem
            The time grid ``time (T,)``, the known inputs ``inputs (N, T, m)``, the inserted depth
            ``depth (N, T)``, the measurement channels (``channels``: name -> :class:`Channel`, each with
            its samples ``value (N, M, m)``, ``valid (N, M)``, times ``t (M,)``, ``t_available (M,)``,
            grid index ``index (M,)`` and measurement function ``h``), the experiment's ``model`` and its
            nominal ``params``, the covariances to keep (``cov_stride``, ``cov_layout``), and, in a
            comparison, a common ``start`` (:class:`CommonStart`). ``N = problem.n_runs`` runs.
        rng : numpy.random.Generator
            This observer's own random stream (the same seed gives the same numbers), for a random start
            or sampling; an observer that draws nothing ignores it.
        progress : callable ``(done, total)``, optional
            Told how far the run is (``RunRecorder`` does this from its ``progress``).

        Returns
        -------
        Posterior
            On the problem's time grid: ``state (N, T, n)``; ``cov (N, T', n, n)`` (``full``), ``(N, T', n)``
            (``diag``) or None (``none``, or an observer without a covariance), ``T' = ceil(T /
            cov_stride)``; ``status`` and ``reason`` ``(N,)`` (``ok`` and ``""``, or a stopped run's status
            and why); the ``names`` and ``units`` of the ``n`` states (a state that the truth also has is
            compared with it by name), the ``angle_states`` (compared wrapped), ``extras`` (further arrays
            with the runs first) and ``attrs``. What comes back is checked
            (:mod:`needlecli.observers.contract`) before anything is written.
        """
        raise NotImplementedError
