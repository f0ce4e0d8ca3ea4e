"""What an observer or a fit is given: the :class:`EstimationProblem` (time grid, known inputs, the
experiment's model) and its measurement channels (:class:`Channel`), each with the sensor's ``h``.

The runner builds it from a simulation or from recorded logs (:mod:`needlecli.experiments.simulation.runner`);
observers (:mod:`needlecli.observers`) and fits (:mod:`needlecli.fitting`) only read it, so that they
know nothing about where measurements come from.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, field

import numpy as np

from needlecli.models import Model


@dataclass(frozen=True)
class Channel:
    """One measurement stream as an observer sees it (``N`` runs, ``M`` samples of ``m`` components).

    Attributes
    ----------
    name : str
        The sensor's name in the config (the key of ``problem.channels``).
    sensor_type : str
        Its registered type (``position``, ``encoder``, ``tangent``, ...).
    t : (M,) acquisition times, s; ``t_available`` (M,) when they can be used (``t`` plus the latency)
    index : (M,) index of ``t`` on the problem's time grid
    value : (N, M, m), NaN where not ``valid`` (N, M) bool
    names, units : (m,) str
        Each component's name (``x``, ``y``, ``z``; ``roll``; ...) and unit.
    h : ``h(x (..., n)) -> (..., m)`` for the experiment model's state, or None when the channel is not
        a function of the state (e.g. encoder depth)
    h_for : ``h_for(model)`` gives the same measurement function for another model (an observer's own),
        or None where that model cannot predict the channel
    sigma : (m,) the sensor's nominal noise std (observers may use their own R instead)
    sample_sigma : (N, M, m) each sample's noise std where the data give one (a recorded per-sample RMS
        error), else None; filters that use it weigh sample ``i`` by ``sample_sigma_i / sigma``
    angle : (m,) bool, channels compared wrapped
    unit_vector : bool
        Whether the sample is a unit vector (a measured direction: a tangent, a field).
    attrs : mapping
        Further facts of the stream as the results file keeps them (e.g. ``sigma_per_sample``).
    bound_for : ``bound_for(model)`` for a channel that bounds the state from one side (an image plane:
        :func:`needlecli.sensors.base.inequality_function`): ``bound(x, value) -> (g, side)``, each sample
        saying ``side * g(x) >= 0``; None for ordinary channels and models it cannot bound
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
    sample_sigma: np.ndarray | None = None
    bound_for: Callable[[Model], Callable | None] = lambda model: None


@dataclass(frozen=True)
class EstimationProblem:
    """Everything an observer may use: no truth beyond what its settings allow for initialisation.
    ``N`` runs (``n_runs``) on ``T`` grid times, ``m`` inputs, ``n`` states of the experiment's model.

    Attributes
    ----------
    time : (T,) ndarray
        The grid, s, from 0 (the simulation's step ``simulation.dt``); every estimate is on it.
    inputs : (N, T, m) ndarray
        The known inputs of every run, held over ``[t_k, t_k+1)``, in the order of ``input_names``.
    input_names : tuple of str
        The model's inputs (``v``, ``u``, ...); ``model.input_slice(name)`` gives a name's columns.
    depth : (N, T) ndarray
        The inserted length of every run from the commanded insertion, the model's length unit.
    channels : mapping of str to Channel
        Every measurement stream, by sensor name.
    model : Model
        The experiment's model (an observer may build its own from it).
    params : mapping of str to ndarray
        The model's nominal parameters from the config (scalars or ``(N,)``).
    interfaces : ndarray
        Depths of the tissue interfaces the experiment knows (empty without layers).
    initial_truth : (N, n) ndarray or None
        The true initial state, given only to observers whose settings start from the truth.
    cov_stride : int
        Covariances are kept at grid steps ``0, s, 2s, ...``.
    cov_layout : {"full", "diag", "none"}
        How they are kept: ``(..., n, n)``, their diagonal ``(..., n)``, or not at all.
    start : CommonStart or None
        One initial estimate for every observer (``needle compare``), or None: each its own.
    kernels : str
        Compiled kernels or the numpy reference (``auto``, ``numba``, ``numpy``), for observers that have both.
    """

    time: np.ndarray  # (T,)
    inputs: np.ndarray  # (N, T, m) known inputs, held over [t_k, t_k+1)
    input_names: tuple[str, ...]
    depth: np.ndarray  # (N, T) inserted length from the commanded insertion
    channels: Mapping[str, Channel]
    model: Model  # the experiment's model (the observer may use its own)
    params: Mapping[str, np.ndarray]  # nominal model parameters from the config
    interfaces: np.ndarray  # tissue interface depths known to the experiment
    initial_truth: np.ndarray | None = None  # (N, n) only for observers configured to start from it
    #: the config's ``model.initial_state`` by state name: with the model's default pose, the nominal start
    initial_state: Mapping[str, float] = field(default_factory=dict)
    cov_stride: int = 1  # keep covariances every k-th step of the time grid
    cov_layout: str = "full"  # "full" (..., n, n), "diag" (..., n) or "none"
    start: CommonStart | None = None  # one initial estimate for every observer (needle compare), or None
    kernels: str = "auto"  # compiled kernels or the numpy reference (needlecli.kernels.compiled)

    @property
    def n_runs(self) -> int:
        return self.inputs.shape[0]


@dataclass(frozen=True)
class CommonStart:
    """One initial estimate handed to every observer of a comparison (``needle compare``), so that none
    starts better informed than another: the reference observer's initial mean of every run (its random
    draw, made once) and its initial covariance, by state name.

    Attributes
    ----------
    names : the states (and augmented constants) it gives
    mean : (N, len(names)) initial mean per run
    cov : (len(names), len(names)) initial covariance
    source : which observer it comes from and how it was made, in words (for the comparison's table)
    """

    names: tuple[str, ...]
    mean: np.ndarray
    cov: np.ndarray
    source: str

    def index(self, name: str) -> int | None:
        return self.names.index(name) if name in self.names else None
