"""Fitted parameters in an observer: ``from_fit`` takes an observer's process noise, each channel's
measurement noise and the model's constants from a fit file of ``needle fit-em``.

.. code-block:: yaml

    observers:
      - name: ukf_em
        type: ukf                       # any type whose class declares fit_takes (needle explain observers)
        from_fit: {file: ../results/study_fit.h5, model: mnm, pick: median}   # pick: median | mean | trial
        p0: {...}                        # everything else as usual

What an observer takes is what its class declares (``Observer.fit_takes``, a
:class:`~needlecli.observers.base.FitTakes` read through the registry: the built-in UKF, EKF, EKS and
open loop, and any plug-in that declares it; a subclass takes what its parent takes). What it sets, from
the trials whose fit is ``ok`` (``pick: median`` / ``mean`` element-wise over them, or ``pick: trial``
with ``trial:`` an index or a trial id):

* ``q``: the standard deviation of each state's process noise per square-root second, ``sqrt(Q_ii)`` (the
  meaning of ``q`` in every observer); the fit's correlations are dropped (these observers take a
  diagonal ``Q``);
* ``measurements.<channel>.sigma``: ``sqrt(diag R_j)`` of each fitted channel the observer has a sensor
  for (``FitTakes.measurements``; not the open loop); a measured direction's R is in its tangent plane
  and is not taken;
* ``params``: each fitted constant (``c`` of the MNM, a curvature, ...);
* a channel's fitted offset along the needle (a sensor state, ``along_offset``): for an observer with
  sensor states (``FitTakes.sensor_states``: the EKF and EKS) that state
  (``measurements.<channel>.along_offset`` with the fitted ``tau`` and ``sigma``); for the others its
  variance joins the channel's sigma along the needle (``offset``: :func:`offset_variance`).

Checked before any work, with the key path, whatever the observer takes from the fit: the observer's
type can take a fit, the file is a fit file whose values hold (:func:`needlecli.io.fit.check_fit_values`:
``Q`` and each ``R`` finite, symmetric and positive semi-definite, each R of its channel's shape), it
fitted ``model``, that model is the observer's (its ``model`` key, else the experiment's) and the fit's
states are that model's (:func:`check_fit_model`), every channel of the fit is a sensor of the config (of
its logs, for a replay) measuring the same components (:func:`check_fit_channels`), the picked trial exists
and is ``ok``, and the observer does not also set what ``from_fit`` sets. A fit section's ``from_fit``
takes only ``q`` and the constants: its channels may be other sensors (the needle's motion fitted on a
tracker, held while EM fits an ultrasound's noise), so they are not checked against the config. A weakly
identified quantity (the fit's identifiability) is taken but named in the log.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

import numpy as np
from pydantic import Field, ValidationError

from needlecli.errors import ConfigError, DataError
from needlecli.schema import Strict, validation_error

if TYPE_CHECKING:
    from needlecli.observers.base import FitTakes

log = logging.getLogger("needlecli")

class FromFit(Strict):
    """Where an observer's fitted parameters come from (``from_fit:``)."""

    file: str = Field(description="fit file of needle fit-em (relative to the config)")
    model: str = Field(description="the fitted model to take (a model the fit file fitted)")
    pick: Literal["median", "mean", "trial"] = Field("median", description="over the trials whose fit is ok, or one trial")
    trial: int | str | None = Field(None, description="with pick: trial, its index or its trial id")
    trials: list[int | str] | None = Field(
        None, min_length=1, description="with pick: median or mean, over these trials only (indices or ids; e.g. "
                                        "the trials recorded at the same insertion speed)")
    offset: Literal["stationary", "white"] = Field(
        "stationary", description="a fitted offset of a channel along the needle (an Ornstein-Uhlenbeck sensor "
        "state) in an observer without that state (the UKF, the open loop; the EKF and EKS take the state itself) joins the "
        "channel's noise along the needle: stationary, its variance sigma^2 (what one sample sees), or white, as "
        "white noise of the same power at low frequencies, 2 sigma^2 tau / dt (dt the mean interval between the "
        "channel's valid samples: what a filter averaging over more than tau sees)")


def _strs(v) -> list[str]:
    return [x.decode() if isinstance(x, bytes) else str(x) for x in np.atleast_1d(v)]


def expand_from_fit(data: dict, source: str, base_dir: Path) -> list[str]:
    """Replace every observer's ``from_fit`` in a parsed config by the values it takes (in place).
    Returns one line per observer saying what came from where (the results file keeps them as comments
    above the expanded config)."""
    changed = []
    fit = data.get("fit") if isinstance(data, dict) else None
    if isinstance(fit, dict) and "from_fit" in fit:
        changed.append(_apply_to_fit(fit, source, base_dir))
    observers = data.get("observers") if isinstance(data, dict) else None
    if not isinstance(observers, list):
        return changed
    channels = None
    for i, obs in enumerate(observers):
        if not isinstance(obs, dict) or "from_fit" not in obs:
            continue
        loc = ("observers", i, "from_fit")
        takes = fit_takes(obs.get("type"), source, ("observers", i, "type"))
        try:
            spec = FromFit.model_validate(obs["from_fit"])
        except ValidationError as e:
            raise validation_error(e, obs["from_fit"], source, prefix=loc, schema=FromFit) from None
        if channels is None:
            channels = config_channels(data, base_dir)
        values = fitted_values(spec, base_dir, source, loc, channels=channels, replay=data.get("source") is not None)
        changed.append(_apply(obs, takes, values, data, source, ("observers", i)))
        del obs["from_fit"]
    return changed


def fit_takes(kind, source: str, loc: tuple) -> FitTakes:
    """What ``from_fit`` may set on an observer of type ``kind``, as the observer class declares it
    (``Observer.fit_takes``, read through the registry). A ConfigError at ``loc`` for an unknown type, a
    plug-in that cannot be loaded, or a type that cannot take a fit (saying why, and which types can)."""
    from needlecli.observers import OBSERVERS
    from needlecli.registry import PluginError

    if not isinstance(kind, str):
        raise ConfigError(source, loc, "required key is missing: from_fit needs the observer's type")
    try:
        cls = OBSERVERS.get(kind)
    except KeyError as e:
        raise ConfigError(source, loc, str(e.args[0])) from None
    except PluginError as e:
        raise ConfigError(source, loc, str(e)) from None
    if cls.fit_takes is None:
        can = [n for n, c in OBSERVERS.loaded().items() if c.fit_takes is not None]
        raise ConfigError(source, loc, f"observer type {kind!r} cannot take a fit: it declares no process noise q, "
                          f"measurement noise or model constants that a fit sets (fit_takes); from_fit works for "
                          f"{', '.join(can)}")
    return cls.fit_takes


def _apply_to_fit(fit: dict, source: str, base_dir: Path) -> str:
    """A ``fit:`` section's ``from_fit``: its initial guesses of the process noise (``q``, per square-root
    second) and of the constants (``params``) from another fit, e.g. to hold them (``hold``) while EM fits
    a sensor's noise. Keys the section sets itself are kept; R is not taken (the section fits its own)."""
    loc = ("fit", "from_fit")
    try:
        spec = FromFit.model_validate(fit["from_fit"])
    except ValidationError as e:
        raise validation_error(e, fit["from_fit"], source, prefix=loc) from None
    models = fit.get("models") or []
    if models and spec.model not in models:
        raise ConfigError(source, loc + ("model",), f"the fit section fits {', '.join(map(str, models))}, not {spec.model!r}")
    v = fitted_values(spec, base_dir, source, loc)
    q = fit.setdefault("q", {})
    if not isinstance(q, dict):
        raise ConfigError(source, ("fit", "q"), "should be a mapping")
    taken = [k for k in v["q_var"] if k not in q]
    for k in taken:
        q[k] = float(np.sqrt(max(v["q_var"][k], 0.0)))
    params = fit.setdefault("params", {})
    for c, val in v["params"].items():
        if c in params:
            raise ConfigError(source, ("fit", "params", c), "from_fit sets it: give one of them")
        if c in ((fit.get("init") or {}).get("values") or {}):
            raise ConfigError(source, ("fit", "init", "values", c), "from_fit sets the constant's initial value: give one of them")
        params[c] = val
    del fit["from_fit"]
    what = (f"fit: q of {', '.join(taken) or 'no state'}; params {', '.join(v['params']) or 'none'} from_fit {v['path']} "
            f"(model {v['model']}, {v['pick']} of {v['trials']} trial(s))")
    log.info(what)
    if v["weak"]:
        log.warning("fit: from_fit takes quantities the fit did not identify: %s", "; ".join(f"{q} ({w})" for q, w in v["weak"].items()))
    return what


def offset_variance(q2: float, tau: float, how: str, meas, sel: np.ndarray, source: str, loc: tuple) -> float:
    """The variance an offset state of the fit (Ornstein-Uhlenbeck: ``d e = -e / tau dt + q dW``, stationary
    variance ``sigma^2 = q^2 tau / 2``) adds to its channel's white noise along the needle in an observer
    without the state: ``sigma^2`` (``stationary``), or ``2 sigma^2 tau / dt = q^2 tau^2 / dt`` (``white``:
    the same spectral density at frequency 0, ``2 sigma^2 tau``, as white samples of variance ``r`` every
    ``dt`` have, ``r dt``), ``dt`` the mean interval between the channel's valid samples (median over the
    picked trials). A random-walk offset (``tau`` infinite) has neither."""
    if not np.isfinite(tau):
        raise ConfigError(source, loc + ("file",), "the fit's offset along the needle is a random walk (no tau): it "
                          "has no stationary variance to add to an observer's noise")
    var = q2 * tau / 2.0
    if how == "stationary":
        return var
    t = np.asarray(meas.data["t"], dtype=float)
    valid = np.asarray(meas.data["valid"], dtype=bool)
    dts = []
    for v in valid[sel]:
        tv = t[v]
        if tv.size > 1:
            dts.append((tv[-1] - tv[0]) / (tv.size - 1))
    if not dts:
        raise ConfigError(source, loc + ("file",), "the channel with an offset has fewer than 2 valid samples")
    return 2.0 * var * tau / float(np.median(dts))


def config_channels(data: dict, base_dir: Path) -> dict[str, tuple[str, ...] | None] | None:
    """The sensors of a parsed config by name, each with the components it measures: a simulation's
    ``sensors`` (None for a sensor whose settings cannot be built yet: the config's own checks name what is
    wrong), or for a replay the sensors its logs recorded. None when the logs cannot be read (their reader
    says why, later)."""
    from needlecli.experiments.config.logs import _read_log
    from needlecli.models import MODELS
    from needlecli.sensors import SENSORS

    src = data.get("source")
    if src is not None:
        logs = src.get("logs") if isinstance(src, dict) else None
        out: dict[str, tuple[str, ...] | None] = {}
        for p in logs if isinstance(logs, list) else []:
            path = Path(str(p))
            try:
                log = _read_log(path if path.is_absolute() else base_dir / path)
            except (DataError, OSError):
                return None
            for tr in log.trials:
                for name, st in tr.sensors.items():
                    out.setdefault(name, tuple(st.names))
        return out
    model_spec = data.get("model") if isinstance(data.get("model"), dict) else {}
    try:
        mcls = MODELS.get(model_spec.get("type"))
        model = mcls(mcls.Params.model_validate(model_spec.get("params") or {}))
    except Exception:  # noqa: BLE001  (a model the config's checks will name; the components stay unknown)
        model = None
    out = {}
    for s in data.get("sensors") or []:
        if not isinstance(s, dict):
            continue
        name = s.get("name") or s.get("type")
        comps = None
        if model is not None and s.get("type") in SENSORS:
            try:
                cls = SENSORS.get(s["type"])
                comps = tuple(cls(cls.Settings.model_validate(s), model).channel_names)
            except Exception:  # noqa: BLE001  (settings the config's checks will name)
                comps = None
        out[str(name)] = comps
    return out


def check_fit_model(g, model: str, where: str) -> str | None:
    """The fit of ``model`` (its group ``g``) has the model's states, in order, then only fitted constants
    (parameters of the model) and sensor states: None, or what is wrong (``where``: its HDF5 path)."""
    from needlecli.models import MODELS

    if model not in MODELS:
        return f"[{where}] fitted model {model!r}, which is not a model of this needlecli ({', '.join(MODELS.names())})"
    cls = MODELS.get(model)
    names = _strs(g.attrs["names"])
    states = list(cls.state_names)
    if names[: len(states)] != states:
        return (f"[{where} attribute names] the fit's states are {', '.join(names[: len(states)])}; model {model!r} has "
                f"{', '.join(states)}")
    consts = set(_strs(g.attrs.get("constants", [])))
    sensor = set(_strs(g.attrs.get("sensor_states", [])))
    for n in names[len(states):]:
        if n in sensor:
            continue
        if n not in consts or n not in cls.Params.model_fields:
            return (f"[{where} attribute names] {n!r} is neither a state nor a constant of model {model!r} "
                    f"(constants: {', '.join(cls.Params.model_fields)})")
    return None


def check_fit_channels(res, g, model: str, channels: dict[str, tuple[str, ...] | None], replay: bool) -> str | None:
    """Every channel the fit of ``model`` (its group ``g``) has an R for is a sensor in ``channels`` (the
    config's, :func:`config_channels`) measuring the same components: None, or what is wrong."""
    meas = res.data["measurements"].data if "measurements" in res.data else {}
    for ch in g.data["R"].data if "R" in g.data else {}:
        if ch.endswith("_guess"):
            continue
        where = f"/fit/{model}/R/{ch}"
        if ch not in channels:
            whose = "the logs of this config" if replay else "this config"
            return (f"[{where}] the fit's channel {ch!r} is no sensor of {whose} (sensors: "
                    f"{', '.join(channels) or 'none'})")
        have = tuple(_strs(meas[ch].attrs.get("names", []))) if ch in meas else None
        if channels[ch] is not None and have is not None and have != channels[ch]:
            return (f"[{where}] the fit's channel {ch!r} measured {', '.join(have)}; sensor {ch!r} of "
                    f"{'the logs' if replay else 'this config'} measures {', '.join(channels[ch])}")
    return None


def fitted_values(spec: FromFit, base_dir: Path, source: str, loc: tuple,
                  channels: dict[str, tuple[str, ...] | None] | None = None, replay: bool = False) -> dict[str, Any]:
    """What the fit file gives: ``{"model", "names", "q_var" (state -> Q_ii per second), "r_var" (channel ->
    (m,) variances or None for a direction), "params" (constant -> value), "trials", "weak"}``. The file is
    checked first (module docstring); ``channels``, the config's sensors (:func:`config_channels`), for an
    observer (None: a fit section's, whose channels are not checked), ``replay``: they are a replay's logs'."""
    from needlecli.io.fit import read_fit

    path = Path(spec.file)
    path = path if path.is_absolute() else base_dir / path
    try:
        res = read_fit(path)
    except DataError as e:
        raise ConfigError(source, loc + ("file",), str(e)) from None
    fits = res.data["fit"].data
    if spec.model not in fits:
        raise ConfigError(source, loc + ("model",), f"{path} fitted {', '.join(fits) or 'no model'}, not {spec.model!r}")
    g = fits[spec.model]
    problem = check_fit_model(g, spec.model, f"/fit/{spec.model}")
    if problem is None and channels is not None:
        problem = check_fit_channels(res, g, spec.model, channels, replay)
    if problem is not None:
        raise ConfigError(source, loc + ("file",), f"{path}: {problem}")
    status = np.asarray(_strs(g.data["status"]))
    N = len(status)
    if spec.trials is not None and spec.pick == "trial":
        raise ConfigError(source, loc + ("trials",), "is used with pick: median or mean (pick: trial takes trial)")
    if spec.pick == "trial":
        if spec.trial is None:
            raise ConfigError(source, loc + ("trial",), "required key is missing (pick: trial)")
        ids = _strs(res.data["truth"].data.get("trial_id", np.arange(N)))
        k = spec.trial if isinstance(spec.trial, int) else (ids.index(spec.trial) if spec.trial in ids else -1)
        if not 0 <= k < N:
            raise ConfigError(source, loc + ("trial",), f"no trial {spec.trial!r}; the fit has {N} (ids {', '.join(ids[:5])}"
                              + (", ..." if N > 5 else "") + ")")
        if status[k] != "ok":
            raise ConfigError(source, loc + ("trial",), f"the fit of trial {spec.trial!r} is {status[k]!r}, not ok")
        sel = np.zeros(N, dtype=bool)
        sel[k] = True
    else:
        sel = status == "ok"
        if spec.trials is not None:
            ids = _strs(res.data["truth"].data.get("trial_id", np.arange(N)))
            chosen = np.zeros(N, dtype=bool)
            for i, t in enumerate(spec.trials):
                k = t if isinstance(t, int) else (ids.index(t) if t in ids else -1)
                if not 0 <= k < N:
                    raise ConfigError(source, loc + ("trials", i), f"no trial {t!r}; the fit has {N} (ids {', '.join(ids[:5])}"
                                      + (", ..." if N > 5 else "") + ")")
                chosen[k] = True
            sel &= chosen
        if not sel.any():
            raise ConfigError(source, loc + ("file",), f"no trial of {spec.model!r} in {path} was fitted ok"
                              + (" among the trials listed" if spec.trials is not None else ""))
    reduce = np.median if spec.pick == "median" else np.mean
    names = _strs(g.attrs["names"])
    consts = _strs(g.attrs.get("constants", []))
    Q = reduce(np.asarray(g.data["Q"], dtype=float)[sel], axis=0)
    q_states = set(_strs(g.attrs.get("q_states", names)))
    sensor = _strs(g.attrs.get("sensor_states", []))
    q_var = {s: float(Q[j, j]) for j, s in enumerate(names) if s in q_states and s not in consts and s not in sensor}
    # a sensor's offset along the needle (an Ornstein-Uhlenbeck state of the fit): these observers have no
    # such state, so it joins the channel's noise along the needle (FromFit.offset)
    offset_var, offsets = {}, {}
    for s_name, ch, tau in zip(sensor, _strs(g.attrs.get("sensor_state_channels", [])), np.atleast_1d(g.attrs.get("sensor_state_tau", []))):
        q2 = float(Q[names.index(s_name), names.index(s_name)])
        offset_var[ch] = offset_variance(q2, float(tau), spec.offset, res.data["measurements"].data.get(ch), sel,
                                         source, loc)
        offsets[ch] = {"tau": float(tau), "sigma": float(np.sqrt(max(q2, 0.0) * float(tau) / 2.0))}
    r_var = {}
    wg = g.data.get("weights")  # Student-t channels: R is the scale; its variance is nu / (nu - 2) R
    dof = dict(zip(_strs(wg.attrs.get("student_t", [])), np.atleast_1d(wg.attrs.get("dof", [])))) if wg is not None else {}
    Rg = g.data["R"]
    frames = dict(zip(_strs(Rg.attrs.get("needle_frame", [])), _strs(Rg.attrs.get("needle_axis", []))))
    for ch, R in Rg.data.items():
        if ch.endswith("_guess"):
            continue
        Rm = reduce(np.asarray(R, dtype=float)[sel], axis=0)
        meas = res.data["measurements"].data.get(ch)
        m_raw = np.asarray(meas.data["value"]).shape[-1] if meas is not None else Rm.shape[-1]
        # a direction: R in its tangent plane, one component fewer (the file's check holds it to that)
        r_var[ch] = None if Rm.shape[-1] == m_raw - 1 else np.diag(Rm).copy()
        if ch in dof and r_var[ch] is not None:  # the Gaussian of the Student-t's variance (infinite for nu <= 2)
            nu = float(dof[ch])
            r_var[ch] = r_var[ch] * (nu / (nu - 2.0) if nu > 2.0 else np.inf)
        if ch in offset_var and r_var[ch] is not None and ch not in frames:
            raise ConfigError(source, loc + ("file",), f"the fit's offset of {ch!r} along the needle needs its R "
                              "in needle coordinates (frame: needle) to be taken")
    params = {c: float(reduce(np.asarray(g.data["constant"].data[c], dtype=float)[sel])) for c in consts}
    from needlecli.reports.identify import weak_quantities

    weak = weak_quantities(res, spec.model)
    return {"model": spec.model, "names": names, "q_var": q_var, "r_var": r_var, "needle": frames, "params": params,
            "offsets": offsets, "offset_var": offset_var,
            "trials": int(sel.sum()), "weak": weak, "path": str(path), "pick": spec.pick}


def _apply(obs: dict, takes: FitTakes, v: dict, data: dict, source: str, loc: tuple) -> str:
    kind = obs["type"]
    own = obs.get("model") or (data.get("model") or {}).get("type")
    if own != v["model"]:
        raise ConfigError(source, loc + ("from_fit", "model"),
                          f"the observer's model is {own!r}; the fit of {v['model']!r} does not apply to it")
    for key in ("q", "params"):
        if key in obs:
            raise ConfigError(source, loc + (key,), "from_fit sets it: give one of them")
    obs["q"] = {s: float(np.sqrt(max(q, 0.0))) for s, q in v["q_var"].items()}
    obs["params"] = dict(v["params"])
    taken = ["q", "params"]
    if takes.measurements:
        meas = obs.setdefault("measurements", {})
        if not isinstance(meas, dict):
            raise ConfigError(source, loc + ("measurements",), "should be a mapping")
        for ch, var in v["r_var"].items():
            if var is None:
                log.info("from_fit: channel %s of %s is a measured direction (R in its tangent plane): not taken",
                         ch, v["path"])
                continue
            spec = meas.setdefault(ch, {})
            if "sigma" in spec:
                raise ConfigError(source, loc + ("measurements", ch, "sigma"), "from_fit sets it: give one of them")
            var = np.array(var, dtype=float)
            if ch in v["offsets"] and takes.sensor_states:  # the observer has the offset state EM fitted
                if "along_offset" in spec:
                    raise ConfigError(source, loc + ("measurements", ch, "along_offset"),
                                      "from_fit sets it: give one of them")
                spec["along_offset"] = dict(v["offsets"][ch])
            elif ch in v["offsets"]:  # it has none: the offset joins the noise along the needle
                var[0] += v["offset_var"][ch]
            spec["sigma"] = [float(np.sqrt(max(x, 0.0))) for x in var]
            if ch in v.get("needle", {}):  # R fitted along and across the needle: the same coordinates here
                for key, want in (("frame", "needle"), ("across_axis", v["needle"][ch])):
                    if spec.get(key, want) != want:
                        raise ConfigError(source, loc + ("measurements", ch, key),
                                          f"the fit's R of {ch!r} is in needle coordinates ({key} {want}): "
                                          f"from_fit sets it")
                    spec[key] = want
            elif spec.get("frame", "world") != "world":
                raise ConfigError(source, loc + ("measurements", ch, "frame"),
                                  f"the fit's R of {ch!r} is in world axes; its sigma does not apply to frame {spec['frame']}")
        taken.append("R of " + ", ".join(ch for ch, var in v["r_var"].items() if var is not None))
    what = (f"observer {obs.get('name') or kind}: {'; '.join(taken)} from_fit {v['path']} (model {v['model']}, "
            f"{v['pick']} of {v['trials']} trial(s))")
    log.info(what)
    if v["weak"]:
        log.warning("observer %s: from_fit takes quantities the fit did not identify: %s", obs.get("name") or kind,
                    "; ".join(f"{q} ({w})" for q, w in v["weak"].items()))
    return what
