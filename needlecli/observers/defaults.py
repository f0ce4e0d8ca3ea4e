"""What an observer may use to derive its own settings for a fair comparison (``needle compare``).

An observer type declares its derived settings itself (:meth:`Observer.derived_settings
<needlecli.observers.base.Observer.derived_settings>`); it is handed a :class:`ComparisonContext`, the
facts of the experiment that such settings may depend on, and the helpers here that several observers
share: which states a channel measures directly (:func:`direct_components`), a sensor's nominal sigma
(:func:`nominal_sigma`), and the settings of a filter tuned from the experiment alone
(:func:`filter_settings`: the UKF's, from which the EKF and EKS derive theirs).

The comparison (:mod:`needlecli.experiments.studies.compare`) builds the context, fills in each
type's registered name as its settings' ``type`` and adds a name; nothing here names an observer type.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from needlecli.models import NotMeasurable

if TYPE_CHECKING:
    from needlecli.models import Model
    from needlecli.problem import Channel
    from needlecli.sensors.base import Sensor

#: observers that predict the final tip position do so from this fraction of the insertion length too
PREDICTION_FRACTION = 0.25
#: std of the initial error of an angle no sensor measures directly: 5 deg, the multi-rate UKF paper's
INIT_ANGLE_STD = 0.0873


class NotApplicable(Exception):
    """Raised by :meth:`Observer.derived_settings` when it cannot derive settings for this experiment; the
    message is the reason (the comparison skips the observer and reports it)."""


@dataclass(frozen=True)
class ComparisonContext:
    """The facts of an experiment that an observer's derived settings may use.

    Attributes
    ----------
    model : Model
        The experiment's model (its nominal parameters; a replay's model as given).
    sensors : mapping
        Sensor name -> :class:`~needlecli.sensors.base.Sensor`, in the experiment's order.
    replay : bool
        Whether the insertions are replayed logs (no simulated truth to start from).
    final_depth : float
        Mean inserted length at the end of the runs, the model's length unit (0: unknown).
    dt : float
        Step of the simulation grid, s.
    process_std : mapping
        State -> std of the truth's process noise, unit/sqrt(s) (the config's ``process_noise.std``;
        empty for replayed logs).
    param_std : mapping
        Parameter -> per-run spread of the model's parameter (the config's ``model.param_std``; empty for
        replayed logs).
    initial_state : mapping
        State -> the truth's initial value where the config sets it (``model.initial_state``); with the
        model's default pose, the nominal start (:meth:`nominal`).
    initial_std : mapping
        State -> per-run spread of the truth's initial state (the config's ``model.initial_std``; empty
        for replayed logs).
    time : (T,) array or None
        The experiment's time grid, s (None: unknown).
    inputs : (N, T, m) array or None
        The known inputs of every run on that grid (None: unknown); with ``time``, what the nominal
        model's path is predicted from (:func:`parameter_rate_std`).
    channels : mapping or None
        Sensor name -> :class:`~needlecli.problem.Channel`, the samples themselves: a replay's process
        noise is read from them where no truth's is known (:func:`measured_process_std`).
    initial_truth_recorded : bool
        Whether the truth's initial state is known for every run (simulations; logs that recorded it).
    """

    model: Model
    sensors: Mapping[str, Sensor]
    replay: bool
    final_depth: float
    dt: float
    process_std: Mapping[str, float] = field(default_factory=dict)
    param_std: Mapping[str, float] = field(default_factory=dict)
    initial_state: Mapping[str, float] = field(default_factory=dict)
    initial_std: Mapping[str, float] = field(default_factory=dict)
    time: np.ndarray | None = None
    inputs: np.ndarray | None = None
    channels: Mapping[str, Channel] | None = None
    initial_truth_recorded: bool = True

    def nominal(self) -> dict[str, float]:
        """The nominal initial state by state name: the model's default pose at its nominal parameters with
        the config's ``model.initial_state`` on top (the mean of the truth's initial state)."""
        params = {k: float(np.mean(v)) for k, v in self.model.param_arrays().items()}
        x = np.asarray(self.model.initial_state(params), dtype=float).reshape(-1)
        out = dict(zip(self.model.state_names, (float(v) for v in x)))
        out.update({k: float(v) for k, v in self.initial_state.items() if k in out})
        return out


def nominal_sigma(sensor: Sensor) -> np.ndarray | None:
    """A sensor's nominal noise std per channel component, ``(m,)``, or None when it has none (or one
    that does not broadcast to its components)."""
    s = getattr(sensor.settings, "sigma", None)
    if s is None:
        return None
    try:
        return np.broadcast_to(np.asarray(s, dtype=float), (len(sensor.channel_names),)).copy()
    except ValueError:
        return None


def direct_components(sensor: Sensor, model: Model) -> dict[str, tuple[int, str]]:
    """States that a channel component measures directly (``h_j(x) = x_i``): state -> (j, component).
    Found from the finite-difference Jacobian of ``h`` at a generic state; only position, angle and
    curvature states (never the entries of a rotation or a unit vector)."""
    from needlecli.sensors.base import measurement_function

    h = measurement_function(sensor, model)
    if h is None:
        return {}
    params = {k: np.asarray(v, dtype=float) for k, v in model.param_arrays().items()}
    try:
        x0 = np.asarray(model.initial_state(params), dtype=float).reshape(-1)
    except Exception:  # noqa: BLE001 (a model without a default pose)
        return {}
    x0 = x0 + 0.05 * (1 + np.arange(model.n)) / model.n  # away from symmetric points
    eligible = {n for n in model.state_names if n in ("x", "y", "z", "px", "py", "pz")} | set(model.angle_states)
    if model.curvature_param in model.state_names:
        eligible.add(model.curvature_param)
    try:
        with np.errstate(all="ignore"):
            y0 = np.asarray(h(x0[None]), dtype=float)[0]
            eps = 1e-6
            J = np.stack([(np.asarray(h((x0 + eps * np.eye(model.n)[i])[None]), dtype=float)[0] - y0) / eps
                          for i in range(model.n)], axis=1)
    except (NotMeasurable, ValueError, IndexError):
        return {}
    out = {}
    for j, comp in enumerate(sensor.channel_names):
        row = J[j]
        nz = np.nonzero(np.abs(row) > 1e-4)[0]
        if len(nz) == 1 and abs(row[nz[0]] - 1.0) < 1e-3 and model.state_names[nz[0]] in eligible:
            out.setdefault(model.state_names[nz[0]], (j, comp))
    return out


#: the longest lag of :func:`measured_process_std`, s, and the fewest lags it fits
VARIOGRAM_MAX_LAG = 2.0
VARIOGRAM_MIN_LAGS = 3


def measured_process_std(channel: Channel, j: int, max_lag: float = VARIOGRAM_MAX_LAG) -> float | None:
    """The process noise of a state that component ``j`` of ``channel`` measures directly, read from the
    samples alone: std per square-root second (the state's unit), or None when they cannot tell.

    The mean square of the samples' second differences at a lag of ``L`` samples, ``V(L) = E[(y_{i+L} -
    2 y_i + y_{i-L})^2] = 6 s^2 + 2 q^2 L T`` for white noise of std ``s`` on a random walk of intensity
    ``q`` (``T`` the sample period; a trend that is linear over ``2 L T`` cancels), is fitted by least
    squares over the lags ``L = 1, 2, 4, ...`` up to ``max_lag`` seconds (angles wrapped, invalid samples
    left out): ``q^2`` is the slope over ``2 T``. None with fewer than :data:`VARIOGRAM_MIN_LAGS` such
    lags (a slow channel) or a slope that is not positive.
    """
    from needlecli.numerics import angle_diff

    t = np.asarray(channel.t, dtype=float)
    if t.size < 5:
        return None
    period = float(np.median(np.diff(t)))
    if not period > 0:
        return None
    y = np.where(channel.valid, np.asarray(channel.value, dtype=float)[..., j], np.nan)  # (N, M)
    angle = bool(np.asarray(channel.angle, dtype=bool)[j]) if np.size(channel.angle) > j else False
    lags, msd = [], []
    L = 1
    while L * period <= max_lag + 1e-9 and 2 * L < y.shape[1]:
        a, b, c = y[:, 2 * L:], y[:, L:-L], y[:, : -2 * L]
        d = angle_diff(a, b) - angle_diff(b, c) if angle else a - 2 * b + c
        if np.isfinite(d).any():
            lags.append(L * period)
            msd.append(float(np.nanmean(d**2)))
        L *= 2
    if len(lags) < VARIOGRAM_MIN_LAGS:
        return None
    A = np.stack([np.ones(len(lags)), 2.0 * np.asarray(lags)], -1)
    slope = float(np.linalg.lstsq(A, np.asarray(msd), rcond=None)[0][1])
    return float(np.sqrt(slope)) if slope > 0 else None


#: steps of the nominal path between two evaluations of the parameter sensitivity
_SENSITIVITY_EVERY = 10


def parameter_rate_std(ctx: ComparisonContext) -> dict[str, float]:
    """The std of each state's rate error that the spread of a model constant which is not a state causes
    (``param_std``; a constant that is a state, such as the modified unicycle's curvature, is estimated
    instead), unit/s: ``sqrt(sum_p (sigma_p^2 rms(df_i/dp)^2))``, the rms of the sensitivity taken over
    the nominal model's path of every run (its nominal start and parameters, the runs' known inputs).
    A filter that assumes the nominal constant sees this as process noise (:func:`filter_settings`).
    Empty without a spread or without the inputs."""
    model = ctx.model
    spread = {k: float(v) for k, v in ctx.param_std.items() if v > 0 and k not in model.state_names}
    if not spread or ctx.inputs is None or ctx.time is None or len(ctx.time) < 2:
        return {}
    params = {k: np.asarray(np.mean(v), dtype=float) for k, v in model.param_arrays().items()}
    N = ctx.inputs.shape[0]
    nominal = ctx.nominal()
    x = np.broadcast_to(np.array([nominal[k] for k in model.state_names]), (N, model.n)).copy()
    total = np.zeros(model.n)
    count = 0
    with np.errstate(all="ignore"):
        for k in range(len(ctx.time) - 1):
            u = ctx.inputs[:, k]
            if k % _SENSITIVITY_EVERY == 0:
                for name, sd in spread.items():
                    d = np.asarray(model.param_jacobian(x, u, params, name), dtype=float).real
                    d = np.where(np.isfinite(d), d, 0.0)
                    total += sd**2 * np.mean(d**2, axis=0)
                count += 1
            x = model.step(x, u, params, float(ctx.time[k + 1] - ctx.time[k]))
    if not count:
        return {}
    return {k: float(np.sqrt(total[i] / count)) for i, k in enumerate(model.state_names) if total[i] > 0}


def _length_scale(model: Model) -> float:
    return {"mm": 1.0, "m": 1e-3, "cm": 0.1}.get(model.length_unit, 1.0)


def filter_settings(ctx: ComparisonContext) -> dict[str, Any]:
    """The settings of a Kalman-type filter from the experiment alone (the UKF's derived settings; the
    EKF and EKS derive theirs from these), without ``type``.

    * ``measurements``: every sensor whose measurement the model predicts and that has a nominal
      ``sigma``, with that sigma (and its ``growth`` with distance, if any);
    * ``init``: from the truth's initial state (from the nominal one for logs that did not record it), the
      states a channel measures directly from that channel's first sample (``first_measurement``), angle
      states no channel measures with 5 deg std (or the truth's ``initial_std`` if larger), a curvature
      state no channel measures at the nominal parameter, every other state at the nominal start
      (:meth:`ComparisonContext.nominal`: the config's ``model.initial_state`` on the model's default
      pose), never at a run's truth;
    * ``p0``: sigma^2 of the first measurement (times (1 + a)^2 with growth), the init std^2, for the
      curvature (param_std or 25 % of the nominal value)^2, for a state at the nominal start the truth's
      ``initial_std``^2, at least 1e-6;
    * ``q`` (per square-root second, as every observer's): the truth's process noise (a replay, whose truth's is
      unknown: for a state a channel measures directly, the one its samples show,
      :func:`measured_process_std`), with the rate error that the
      spread of a model constant which is not a state causes (:func:`parameter_rate_std`, times
      sqrt(dt)) added in quadrature, at least the floor of a grid step ``dt`` over ``sqrt(dt)`` (per step:
      1e-3 mm for positions, 1e-5 rad for angles, 4e-4 times the nominal curvature, 1e-4 for other states);
    * ``predict_at_depths``: [25 % of the insertion length].

    Raises
    ------
    NotApplicable
        No sensor with a nominal sigma measures something the model predicts.
    """
    from needlecli.sensors.base import measurement_function

    model = ctx.model
    meas, first, p0, where = {}, {}, {}, {}
    for name, sensor in ctx.sensors.items():
        sigma = nominal_sigma(sensor)
        if sigma is None:
            continue
        direct = direct_components(sensor, model)
        if measurement_function(sensor, model) is None:
            continue
        spec: dict[str, Any] = {"sigma": float(sigma[0]) if np.all(sigma == sigma[0]) else [float(s) for s in sigma]}
        growth = getattr(sensor.settings, "growth", None)
        factor = 1.0
        if growth is not None:
            spec["growth"] = growth.model_dump(mode="json")
            factor = 1.0 + float(growth.a)
        meas[name] = spec
        for state, (j, comp) in direct.items():
            if state not in first:
                first[state] = f"{name}.{comp}"
                where[state] = (name, j)
                p0[state] = float((factor * sigma[j]) ** 2)
    if not meas:
        raise NotApplicable("no sensor with a nominal sigma measures something the model predicts")
    std = {a: max(INIT_ANGLE_STD, float(ctx.initial_std.get(a, 0.0))) for a in model.angle_states if a not in first}
    values = {}
    kappa = model.curvature_param
    params = {k: float(np.mean(v)) for k, v in model.param_arrays().items()}
    if kappa in model.state_names and kappa not in first and kappa in params:
        values[kappa] = params[kappa]
        spread = ctx.param_std.get(kappa)
        p0[kappa] = float((spread or 0.25 * abs(params[kappa]) or 1e-3) ** 2)
    for k, v in std.items():
        p0.setdefault(k, v**2)
    nominal = ctx.nominal()
    for k in model.state_names:  # no channel measures it and no noise covers it: the nominal start, its spread
        if k not in first and k not in std and k not in values:
            values[k] = nominal[k]
            p0[k] = max(float(ctx.initial_std.get(k, 0.0)) ** 2, 1e-6)
    for k in model.state_names:
        p0.setdefault(k, 1e-6)
    proc = dict(ctx.process_std)
    if ctx.replay and not proc and ctx.channels:  # no truth's noise known: a measured state's, from its samples
        for k, (name, j) in where.items():
            if name in ctx.channels and (found := measured_process_std(ctx.channels[name], j)) is not None:
                proc[k] = found
    model_error = parameter_rate_std(ctx)
    root_dt = float(np.sqrt(ctx.dt))
    length = _length_scale(model)
    q = {}
    for k, unit in zip(model.state_names, model.state_units):
        if k in model.angle_states:
            floor = 1e-5
        elif k == kappa:
            floor = 4e-4 * abs(params.get(kappa, 0.0)) or 1e-7
        elif unit == model.length_unit:
            floor = 1e-3 * length
        else:
            floor = 1e-4
        q[k] = float(max(np.hypot(proc.get(k, 0.0), model_error.get(k, 0.0)) * root_dt, floor)) / root_dt  # per step, as a std per sqrt(s)
    out: dict[str, Any] = {
        "q": q, "p0": p0, "measurements": meas,
        "init": {"from": "truth" if ctx.initial_truth_recorded else "nominal", "std": std, "values": values,
                 "first_measurement": first},
    }
    if ctx.final_depth > 0:
        out["predict_at_depths"] = [round(PREDICTION_FRACTION * ctx.final_depth, 9)]
    return out
