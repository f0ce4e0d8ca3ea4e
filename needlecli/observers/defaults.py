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
    from needlecli.sensors.base import Sensor

#: observers that predict the final tip position do so from this fraction of the insertion length too
PREDICTION_FRACTION = 0.25
#: std of the initial error of an angle no sensor measures directly: 5 deg, seed 003's
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
    """

    model: Model
    sensors: Mapping[str, Sensor]
    replay: bool
    final_depth: float
    dt: float
    process_std: Mapping[str, float] = field(default_factory=dict)
    param_std: Mapping[str, float] = field(default_factory=dict)


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


def _length_scale(model: Model) -> float:
    return {"mm": 1.0, "m": 1e-3, "cm": 0.1}.get(model.length_unit, 1.0)


def filter_settings(ctx: ComparisonContext) -> dict[str, Any]:
    """The settings of a Kalman-type filter from the experiment alone (the UKF's derived settings; the
    EKF and EKS derive theirs from these), without ``type``.

    * ``measurements``: every sensor whose measurement the model predicts and that has a nominal
      ``sigma``, with that sigma (and its ``growth`` with distance, if any);
    * ``init``: from the truth's initial state (from the model's nominal one for replayed logs), the
      states a channel measures directly from that channel's first sample (``first_measurement``), angle
      states no channel measures with 5 deg std, a curvature state no channel measures at the nominal
      parameter;
    * ``p0``: sigma^2 of the first measurement (times (1 + a)^2 with growth), the init std^2, for the
      curvature (param_std or 25 % of the nominal value)^2, else 1e-6;
    * ``q`` (per square-root second, as every observer's): the truth's process noise, at least the floor of
      a grid step ``dt`` over ``sqrt(dt)`` (per step: 1e-3 mm for positions, 1e-5 rad for angles, 4e-4 times
      the nominal curvature, 1e-4 for other states);
    * ``predict_at_depths``: [25 % of the insertion length].

    Raises
    ------
    NotApplicable
        No sensor with a nominal sigma measures something the model predicts.
    """
    from needlecli.sensors.base import measurement_function

    model = ctx.model
    meas, first, p0 = {}, {}, {}
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
                p0[state] = float((factor * sigma[j]) ** 2)
    if not meas:
        raise NotApplicable("no sensor with a nominal sigma measures something the model predicts")
    std = {a: INIT_ANGLE_STD for a in model.angle_states if a not in first}
    values = {}
    kappa = model.curvature_param
    params = {k: float(np.mean(v)) for k, v in model.param_arrays().items()}
    if kappa in model.state_names and kappa not in first and kappa in params:
        values[kappa] = params[kappa]
        spread = ctx.param_std.get(kappa)
        p0[kappa] = float((spread or 0.25 * abs(params[kappa]) or 1e-3) ** 2)
    for k, v in std.items():
        p0.setdefault(k, v**2)
    if not ctx.replay:  # states no channel measures and no noise covers start at the nominal state, not the truth
        nominal = np.asarray(model.initial_state(params), dtype=float).reshape(-1)
        for i, k in enumerate(model.state_names):
            if k not in first and k not in std and k not in values:
                values[k] = float(nominal[i])
    for k in model.state_names:
        p0.setdefault(k, 1e-6)
    proc = ctx.process_std
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
        q[k] = float(max(proc.get(k, 0.0) * root_dt, floor)) / root_dt  # per step, as a std per sqrt(s)
    out: dict[str, Any] = {
        "q": q, "p0": p0, "measurements": meas,
        "init": {"from": "nominal" if ctx.replay else "truth", "std": std, "values": values, "first_measurement": first},
    }
    if ctx.final_depth > 0:
        out["predict_at_depths"] = [round(PREDICTION_FRACTION * ctx.final_depth, 9)]
    return out
