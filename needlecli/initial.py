"""Where an estimate starts: one settings schema (:class:`InitialEstimate`, an observer's or a fit's
``init:``) and one function that builds the initial mean from it (:func:`initial_mean`) and one the
initial covariance (:func:`initial_covariance`), shared by the ``open_loop``, ``ukf``, ``ekf`` and
``eks`` observers and by ``needle fit-em``.

The initial mean of every run, in this order:

1. the base: the true initial state (``from: truth``; simulations, or logs that recorded it; where a
   run's truth is unknown the nominal state stands) or the nominal one (``from: nominal``: the model's
   default pose with the config's ``model.initial_state``, :func:`nominal_state`); augmented constants
   from the model's parameters;
2. ``values`` fix states (and augmented constants) for every run;
3. Gaussian noise of ``std`` per state (drawn from the observer's own random stream, every run at once);
4. ``first_measurement`` takes states from the first valid sample of a channel component
   (``{x: us3d.x}``), where a run has one;
5. angles wrapped, the state brought back onto its manifold.

The observers that start as a paper prescribes in other terms (the high-gain observer (`highgain-us2d`),
the SO(3) observer paper's rotation error about the measured axis) have their own ``init`` sections.

**A common start.** When the problem carries a :class:`~needlecli.problem.CommonStart` (``needle
compare``: the reference observer's initial estimate, drawn once), :func:`initial_mean` and
:func:`initial_covariance` return it, by state name, instead of what the observer's own ``init`` says:
every observer then starts from the same information. States it does not give start at the nominal
state (:func:`nominal_state`, never a run's truth) with the observer's own initial variance.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Literal

import numpy as np
from pydantic import Field, field_validator

from needlecli.models import Model
from needlecli.numerics import wrap_angle
from needlecli.problem import CommonStart, EstimationProblem
from needlecli.schema import NonNeg, Strict


class InitialEstimate(Strict):
    """Initial estimate: ``from`` a base (the truth or the nominal state), then fixed ``values``, Gaussian
    noise of ``std`` per state, and states from the ``first_measurement`` of a channel component."""

    from_: Literal["truth", "nominal"] = Field(
        "truth", alias="from",
        description="truth: the true initial state (simulations; nominal where unknown); nominal: the model's "
                    "default pose with model.initial_state")
    values: dict[str, float] = Field(default_factory=dict, description="fixed initial values per state")
    std: dict[str, NonNeg] = Field(default_factory=dict,
                                   description="std of Gaussian noise added per state (and the default P0: std^2)")
    first_measurement: dict[str, str] = Field(
        default_factory=dict, description="states from the first valid sample of channel.component, e.g. {x: us3d.x}")

    @field_validator("first_measurement")
    @classmethod
    def _spec(cls, v):
        for state, spec in v.items():
            if "." not in spec:
                raise ValueError(f"{state}: {spec!r} is not of the form channel.component")
        return v


def check_initial_states(init: InitialEstimate, names: Sequence[str], model_name: str,
                         hint: Sequence[str] = ()) -> list[tuple[tuple, str]]:
    """States an ``init`` section names that are not among ``names``: ``[(loc under init, message)]``.
    ``hint`` lists parameters that could be augmented states (said in the message)."""
    out = []
    for where, keys in (("std", init.std), ("values", init.values), ("first_measurement", init.first_measurement)):
        for k in keys:
            if k not in names:
                out.append(((where, k), f"model {model_name!r} has no state {k!r}"
                            + (" (augment it to estimate a parameter)" if k in hint else "")))
    return out


def check_initial_sensors(init: InitialEstimate, sensors: Mapping) -> list[tuple[tuple, str]]:
    """First measurements of sensors (name -> Sensor) or components that do not exist."""
    out = []
    for state, spec in init.first_measurement.items():
        ch, comp = spec.rsplit(".", 1)
        if ch not in sensors:
            out.append((("first_measurement", state), f"no sensor named {ch!r}"))
        elif comp not in sensors[ch].channel_names:
            out.append((("first_measurement", state),
                        f"sensor {ch!r} has no component {comp!r}; it has {', '.join(sensors[ch].channel_names)}"))
    return out


def check_initial(init: InitialEstimate, names: Sequence[str], model_name: str, sensors: Mapping,
                  hint: Sequence[str] = ()) -> list[tuple[tuple, str]]:
    """Config problems of an ``init`` section for states ``names`` and ``sensors``."""
    return check_initial_states(init, names, model_name, hint) + check_initial_sensors(init, sensors)


def first_sample(problem: EstimationProblem, spec: str) -> tuple[np.ndarray, np.ndarray]:
    """First valid sample ``(N,)`` of ``channel.component`` and whether a run has one."""
    ch_name, comp = spec.rsplit(".", 1)
    if ch_name not in problem.channels:
        raise ValueError(f"no channel {ch_name!r}; channels: {', '.join(problem.channels)}")
    ch = problem.channels[ch_name]
    if comp not in ch.names:
        raise ValueError(f"channel {ch_name!r} has no component {comp!r}; it has {', '.join(ch.names)}")
    first = np.argmax(ch.valid, axis=1)
    has = ch.valid.any(axis=1)
    return ch.value[np.arange(ch.value.shape[0]), first, ch.names.index(comp)], has


def nominal_state(problem: EstimationProblem, model: Model, params: Mapping) -> np.ndarray:
    """The nominal initial state ``(N, model.n)`` of every run: ``model``'s default pose with the
    experiment's ``model.initial_state`` (``problem.initial_state``, by state name) where ``model`` has
    those states -- the mean of the truth's initial state, which ``model.initial_std`` spreads."""
    x = np.broadcast_to(np.asarray(model.initial_state(params), dtype=float), (problem.n_runs, model.n)).copy()
    for name, v in problem.initial_state.items():
        if name in model.state_names:
            x[:, model.index(name)] = v
    return x


def initial_mean(init: InitialEstimate, problem: EstimationProblem, model: Model, params: Mapping,
                 rng: np.random.Generator | None, augment: Sequence[str] = ()) -> np.ndarray:
    """The initial mean ``(N, n + len(augment))`` of every run, as the module docstring says.

    Parameters
    ----------
    model, params : the estimator's own model and its parameter arrays (broadcastable to ``(N,)``)
    rng : the observer's random stream; None draws no noise (``needle fit-em``)
    augment : parameters of ``model`` estimated as constant states after the model's own
    """
    N, n = problem.n_runs, model.n
    x = nominal_state(problem, model, params)
    if problem.start is not None:
        return _from_start(problem.start, x, model, params, augment)
    if init.from_ == "truth" and problem.initial_truth is not None:
        for i, name in enumerate(model.state_names):
            if name in problem.model.state_names:
                known = problem.initial_truth[:, problem.model.index(name)]
                x[:, i] = np.where(np.isfinite(known), known, x[:, i])  # unknown truth: nominal
    if augment:
        x = np.concatenate([x, np.stack([np.broadcast_to(np.asarray(params[a], dtype=float), (N,)) for a in augment], -1)], -1)
    names = tuple(model.state_names) + tuple(augment)
    for name, v in init.values.items():
        if name in names:
            x[:, names.index(name)] = v
    if rng is not None:
        std = np.array([init.std.get(k, 0.0) for k in names])
        x = x + std * rng.standard_normal(x.shape)
    for state, spec in init.first_measurement.items():
        if state in names:
            vals, has = first_sample(problem, spec)
            x[has, names.index(state)] = vals[has]
    ang = np.zeros(len(names), dtype=bool)
    ang[:n] = model.angle_mask
    if ang.any():
        x[:, ang] = wrap_angle(x[:, ang])
    x[:, :n] = model.normalize(x[:, :n])
    return x


def _from_start(start: CommonStart, nominal: np.ndarray, model: Model, params: Mapping,
                augment: Sequence[str]) -> np.ndarray:
    N = nominal.shape[0]
    x = nominal
    if augment:
        x = np.concatenate([x, np.stack([np.broadcast_to(np.asarray(params[a], dtype=float), (N,)) for a in augment], -1)], -1)
    names = tuple(model.state_names) + tuple(augment)
    for i, name in enumerate(names):
        j = start.index(name)
        if j is not None:
            x[:, i] = start.mean[:, j]
    ang = np.zeros(len(names), dtype=bool)
    ang[: model.n] = model.angle_mask
    if ang.any():
        x[:, ang] = wrap_angle(x[:, ang])
    x[:, : model.n] = model.normalize(x[:, : model.n])
    return x


def start_state(problem: EstimationProblem, model: Model, params: Mapping) -> np.ndarray:
    """The state ``(N, model.n)`` of ``model`` that the problem's common start gives (the nominal state
    where it gives none), for observers with their own ``init`` schema (high-gain, SO(3))."""
    x = nominal_state(problem, model, params)
    return _from_start(problem.start, x, model, params, ()) if problem.start is not None else x


def initial_covariance(init: InitialEstimate, names: Sequence[str], p0: Mapping[str, float], floor: float,
                       start: CommonStart | None = None) -> np.ndarray:
    """``P0 = diag(p0)`` per state, ``std^2`` of ``init`` where ``p0`` does not name a state, each at least
    ``floor`` (a variance); with a common ``start``, its covariance for the states it gives."""
    var = np.array([p0.get(k, init.std.get(k, 0.0) ** 2) for k in names], dtype=float)
    return with_start_covariance(np.diag(np.maximum(var, floor)), names, start)


def with_start_covariance(P: np.ndarray, names: Sequence[str], start: CommonStart | None) -> np.ndarray:
    """``P (n, n)`` of states ``names`` with the common start's covariance where the start gives them."""
    if start is None:
        return P
    P = P.copy()
    mine = [i for i, k in enumerate(names) if start.index(k) is not None]
    theirs = [start.index(names[i]) for i in mine]
    P[np.ix_(mine, mine)] = start.cov[np.ix_(theirs, theirs)]
    return P


def describe(init: InitialEstimate, names: Sequence[str]) -> str:
    """An ``init`` section in words, naming every state that starts at a run's exact truth."""
    first = {k: v for k, v in init.first_measurement.items() if k in names}
    noisy = [k for k in names if init.std.get(k, 0.0) > 0 and k not in first]
    fixed = [k for k in names if k in init.values and k not in first]
    exact = [k for k in names if init.from_ == "truth" and k not in first and k not in noisy and k not in fixed]
    parts = [("truth" if init.from_ == "truth" else "nominal")
             + (f" + N(0, std) on {', '.join(noisy)}" if noisy else "")]
    if fixed:
        parts.append(f"fixed {', '.join(fixed)}")
    if first:
        by: dict[str, list[str]] = {}
        for k, spec in first.items():
            by.setdefault(spec.rsplit(".", 1)[0], []).append(k)
        parts.append("first sample of " + "; ".join(f"{ch} ({', '.join(ks)})" for ch, ks in by.items()))
    if exact:
        parts.append(f"EXACT TRUTH: {', '.join(exact)}")
    return "; ".join(parts)


def make_start(init: InitialEstimate, problem: EstimationProblem, model: Model, params: Mapping,
               rng: np.random.Generator | None, cov: np.ndarray, observer: str,
               augment: Sequence[str] = ()) -> CommonStart:
    """The common start an observer with this ``init`` and initial covariance ``cov`` gives (its own draw
    from ``rng``, the stream it would start from)."""
    names = tuple(model.state_names) + tuple(augment)
    mean = initial_mean(init, problem, model, params, rng, augment)
    return CommonStart(names=names, mean=mean, cov=np.asarray(cov, dtype=float),
                       source=f"{observer}'s initial estimate: {describe(init, names)}")
