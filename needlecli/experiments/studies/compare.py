"""Every observer on the same insertions: the experiment is simulated (or its logs replayed) once, then
each applicable observer runs on the same :class:`~needlecli.observers.EstimationProblem`.

Which observers, with which settings:

* each observer of the config runs with its own settings (``settings: config``);
* every other registered observer type runs with settings derived here (``settings: defaults``):
  :data:`DEFAULTS` holds a function per type that derives them from the experiment (sensors, nominal
  sigmas, process noise); a type without one gets ``{type: <type>}`` and the schema's defaults;
* an observer is applicable when its settings pass its schema and its ``check(settings, model,
  sensors)``; otherwise it is skipped and the reason (the first problem) is reported.

Every observer starts from the same information: the **common start** is the initial estimate of the
reference observer (the config's first observer that can give one, else the UKF with derived settings)
-- its initial mean of every run, drawn once from its random stream, and its initial covariance -- and
every observer that can take it (``Observer.takes_common_start``) starts from it, whatever its own
``init`` says, the open-loop reference included. Where a paper prescribes its own start in terms of the
common one (seed 000's high-gain observer: x_hat0 = beta_hat0 = 0), that applies on top. No observer
starts from a run's own truth unless the reference does, and the table names, per observer, where it
started (``start``) and the common start's recipe (footnote), flagging any state taken exactly from
the truth.

Observers with a ``predict_at_depths`` setting also predict the final tip position from 25 % of the
insertion length (added to the depths they already have), the prediction error of seed 003's
appendix A.
"""

from __future__ import annotations

import copy
import dataclasses
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import pandas as pd
import yaml
from pydantic import ValidationError

from needlecli.errors import ComponentError, ConfigError, DataError, NeedleError
from needlecli.models import NotMeasurable

if TYPE_CHECKING:
    from needlecli.experiments.config.types import ExperimentConfig

PREDICTION_FRACTION = 0.25
INIT_ANGLE_STD = 0.0873  # 5 deg: seed 003's initial error on the angles no sensor measures directly
Progress = Callable[[str, int, int], None]


class NotApplicable(Exception):
    """Raised by a defaults function when it cannot derive settings for this experiment (the reason)."""


@dataclass(frozen=True)
class Context:
    """What a defaults function may use: the validated config, the experiment's model, its sensors
    (name -> Sensor), whether the insertions are replayed logs, the mean final depth and the grid step."""

    cfg: ExperimentConfig
    model: Any
    sensors: dict
    replay: bool
    final_depth: float
    dt: float


# ---------------------------------------------------------------------------------------------- defaults
def _nominal_sigma(sensor) -> np.ndarray | None:
    s = getattr(sensor.settings, "sigma", None)
    if s is None:
        return None
    try:
        return np.broadcast_to(np.asarray(s, dtype=float), (len(sensor.channel_names),)).copy()
    except ValueError:
        return None


def direct_components(sensor, model) -> dict[str, tuple[int, str]]:
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


def _length_scale(model) -> float:
    return {"mm": 1.0, "m": 1e-3, "cm": 0.1}.get(model.length_unit, 1.0)


def ukf_defaults(ctx: Context) -> dict:
    """The UKF from the experiment alone.

    * ``measurements``: every sensor whose measurement the model predicts and that has a nominal
      ``sigma``, with that sigma (and its ``growth`` with distance, if any);
    * ``init``: from the truth's initial state (from the model's nominal one for replayed logs), the
      states a channel measures directly from that channel's first sample (``first_measurement``), angle
      states no channel measures with 5 deg std, a curvature state no channel measures at the nominal
      parameter;
    * ``p0``: sigma^2 of the first measurement (times (1 + a)^2 with growth), the init std^2, for the
      curvature (param_std or 25 % of the nominal value)^2, else 1e-6;
    * ``q`` per tick of the grid: the config's truth process noise times sqrt(dt), at least 1e-3 mm for
      positions, 1e-5 rad for angles, 4e-4 times the nominal curvature, 1e-4 for other states;
    * ``predict_at_depths``: [25 % of the insertion length].
    """
    model = ctx.model
    meas, first, p0 = {}, {}, {}
    for name, sensor in ctx.sensors.items():
        sigma = _nominal_sigma(sensor)
        if sigma is None:
            continue
        direct = direct_components(sensor, model)
        from needlecli.sensors.base import measurement_function

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
        spread = ctx.cfg.model.param_std.get(kappa) if ctx.cfg.source is None else None
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
    proc = ctx.cfg.process_noise.std if ctx.cfg.source is None else {}
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
        q[k] = float(max(proc.get(k, 0.0) * root_dt, floor))
    out: dict[str, Any] = {
        "type": "ukf", "q": q, "p0": p0, "measurements": meas,
        "init": {"from": "nominal" if ctx.replay else "truth", "std": std, "values": values, "first_measurement": first},
    }
    if ctx.final_depth > 0:
        out["predict_at_depths"] = [round(PREDICTION_FRACTION * ctx.final_depth, 9)]
    return out


def open_loop_defaults(ctx: Context) -> dict:
    """The open-loop prediction from what is known before the insertion: the model's nominal initial state
    (nominal curvature, not the run's true one) with 5 deg std on the angle states."""
    std = {a: INIT_ANGLE_STD for a in ctx.model.angle_states}
    return {"type": "open_loop", "init": {"from": "nominal", "std": std}}


def kalman_defaults(ctx: Context) -> dict:
    """The EKF / EKS tuned as :func:`ukf_defaults` tunes the UKF: the same measurement sigmas (no distance
    growth: the EKF has none), the same process noise as a std per square-root second (the UKF's per tick
    over sqrt(dt)), the same init and initial variances (which the common start replaces anyway)."""
    u = ukf_defaults(ctx)
    root_dt = float(np.sqrt(ctx.dt))
    return {"q": {k: v / root_dt for k, v in u["q"].items()}, "p0": u["p0"], "init": u["init"],
            "measurements": {n: {"sigma": m["sigma"]} for n, m in u["measurements"].items()}}


def high_gain_defaults(ctx: Context) -> dict:
    """Seed 000's start, x_hat0 = beta_hat0 = 0 (the roll from the common start)."""
    return {"type": "high_gain", "init": {"from": "nominal", "values": {"x": 0.0, "beta": 0.0}}}


#: observer type -> function deriving its settings from the experiment (a type not here: schema defaults)
DEFAULTS: dict[str, Callable[[Context], dict]] = {
    "ukf": ukf_defaults, "open_loop": open_loop_defaults, "high_gain": high_gain_defaults,
    "ekf": lambda ctx: {"type": "ekf", **kalman_defaults(ctx)}, "eks": lambda ctx: {"type": "eks", **kalman_defaults(ctx)},
}


# ---------------------------------------------------------------------------------------------- config
def is_log(path: str | Path) -> bool:
    """Whether ``path`` is an HDF5 log file (format needlecli-log)."""
    import h5py

    p = Path(path)
    if not p.is_file() or not h5py.is_hdf5(p):
        return False
    try:
        with h5py.File(p, "r") as f:
            fmt = f.attrs.get("format")
        fmt = fmt.decode() if isinstance(fmt, bytes) else fmt
        return fmt == "needlecli-log"
    except OSError:
        return False


def load_compare_config(
    path: str | Path,
    *,
    model: str | None = None,
    runs: int | None = None,
    seed: int | None = None,
    overrides: list[str] | None = None,
):
    """The experiment to compare on: a config (``runs``, ``seed``, ``overrides`` as in ``needle
    simulate``), or a log file replayed with ``model`` (``runs``: its first trials). Returns
    ``(config, text, source)``."""
    import h5py

    from needlecli.experiments.config.load import load_config
    from needlecli.models import MODELS

    path = Path(path)
    if not is_log(path):
        if path.is_file() and h5py.is_hdf5(path):
            raise DataError(f"{path}: an HDF5 file that is not a log (format needlecli-log); give a config or a log")
        if model is not None:
            raise ConfigError(str(path), (), "--model is for log files; a config names its model")
        cfg, text = load_config(path, overrides=overrides, runs=runs, seed=seed)
        return cfg, text, str(path)
    if model is None:
        raise ConfigError(str(path), (), f"a log needs --model TYPE to replay it with; models: {', '.join(MODELS.names())}")
    data: dict[str, Any] = {
        "name": f"{path.stem}_compare",
        "description": f"replay of {path.name} for needle compare",
        "source": {"logs": [str(path.resolve())]},
        "model": {"type": model},
        "runs": {"seed": int(seed or 0)},
    }
    if runs is not None:
        from needlecli.io.logs import read_log

        data["source"]["trials"] = [t.id for t in read_log(path).trials][:runs]
    source = f"{path} (replay config)"
    cfg, text = load_config(source, text=yaml.safe_dump(data, sort_keys=False), overrides=overrides)
    return cfg, text, source


# ---------------------------------------------------------------------------------------------- comparing
@dataclass
class Candidate:
    name: str
    type: str
    origin: str  # "config" or "defaults"
    settings: dict | None = None  # the settings mapping (YAML form), None when skipped
    skip: str = ""  # why it does not run
    start: str = ""  # where it starts: "common (reference)", "common", "common; x, beta = 0", "own settings"
    causal: bool = True  # an estimate at t uses samples up to t only (False: a smoother)


@dataclass
class ObserverRun:
    candidate: Candidate
    seconds: float = float("nan")
    error: str = ""


@dataclass
class CompareResult:
    cfg: ExperimentConfig
    source: str
    path: Path | None
    runs: list[ObserverRun]
    skipped: list[Candidate]
    n_runs: int
    n_steps: int
    final_depth: float
    truth_failed: int
    sensors: list
    length_unit: str = "mm"
    errors: dict = field(default_factory=dict)  # observer -> ErrorSet
    predictions: dict = field(default_factory=dict)  # observer -> (depths, errors)
    curvature: dict = field(default_factory=dict)  # observer -> "yes" / "no (...)"
    status: dict = field(default_factory=dict)  # observer -> (failed runs, reasons)
    start: str = ""  # the common start's recipe (which observer, how), or why there is none


def _with_prediction(settings: dict, cls, depth: float) -> dict:
    if "predict_at_depths" not in cls.Settings.model_fields or depth <= 0:
        return settings
    d = round(PREDICTION_FRACTION * depth, 9)
    have = [float(x) for x in settings.get("predict_at_depths") or []]
    if not any(abs(x - d) <= 1e-9 * max(1.0, d) for x in have):
        settings = {**settings, "predict_at_depths": sorted(have + [d])}
    return settings


def candidates(ctx: Context, raw_observers: list[dict], wanted: list[str] | None) -> list[Candidate]:
    """The observers to try: the config's own, then one per other registered type with derived settings;
    each checked (schema and ``check``); ``wanted`` filters by name or type."""
    from needlecli.observers import OBSERVERS

    out: list[Candidate] = []
    types_in_config = set()
    for raw in raw_observers:
        t = raw.get("type")
        types_in_config.add(t)
        out.append(Candidate(name=raw.get("name") or t, type=t, origin="config", settings=copy.deepcopy(raw)))
    used = {c.name for c in out}
    for t in OBSERVERS.names():
        if t in types_in_config:
            continue
        name = t if t not in used else f"{t}_defaults"
        c = Candidate(name=name, type=t, origin="defaults")
        try:
            c.settings = {**(DEFAULTS[t](ctx) if t in DEFAULTS else {"type": t}), "name": name}
        except NotApplicable as e:
            c.skip = str(e)
        out.append(c)
    if wanted:
        known = {c.name for c in out} | {c.type for c in out}
        bad = [w for w in wanted if w not in known]
        if bad:
            raise ConfigError("--observers", (), f"unknown observer {bad[0]!r}; known: {', '.join(sorted(known))}")
        out = [c for c in out if c.name in wanted or c.type in wanted]
    for c in out:
        if c.skip:
            continue
        cls = OBSERVERS.get(c.type)
        c.settings = _with_prediction(c.settings, cls, ctx.final_depth)
        try:
            settings = cls.Settings.model_validate(c.settings)
        except ValidationError as e:
            err = e.errors()[0]
            where = ".".join(str(p) for p in err["loc"])
            c.skip = f"settings cannot be derived: {where}: {err['msg']}" if where else err["msg"]
            continue
        problems = cls.check(settings, ctx.model, ctx.sensors)
        if problems:
            loc, msg = problems[0]
            c.skip = (f"[{'.'.join(str(p) for p in loc)}] " if loc else "") + msg
    return out


def _online_curvature(post, model) -> str:
    k = model.curvature_param
    if k is None or k not in post.names:
        return "no (not estimated)"
    v = post.state[..., post.names.index(k)]
    spread = np.nanmax(np.abs(v - v[:, :1])) if v.size else 0.0
    return "yes" if np.isfinite(spread) and spread > 1e-12 else "no (held at its initial value)"


def compare_observers(
    config: str | Path,
    *,
    observers: list[str] | None = None,
    runs: int | None = None,
    seed: int | None = None,
    model: str | None = None,
    overrides: list[str] | None = None,
    out_dir: str | Path | None = None,
    progress: Progress | None = None,
) -> CompareResult:
    """Simulate (or replay) once, run every applicable observer on the same problem, write the results
    file ``<out_dir>/<name>_compare.h5`` and return what is needed for :func:`compare_table`."""
    from needlecli.experiments.config.load import load_config
    from needlecli.experiments.simulation import components
    from needlecli.experiments.simulation.replay import replay_truth
    from needlecli.experiments.simulation.runner import build_problem, results_tree, simulate_and_measure
    from needlecli.experiments.simulation.truth import stream
    from needlecli.io.atomic import check_output_dir, raised_signal
    from needlecli.io.results import read_results, write_atomic
    from needlecli.io.yamlfile import parse_yaml
    from needlecli.metrics import compute_errors
    from needlecli.observers import OBSERVERS
    from needlecli.reports.seed003 import prediction_errors

    cfg, text, source = load_compare_config(config, model=model, runs=runs, seed=seed, overrides=overrides)
    out = Path(out_dir) if out_dir is not None else Path("results") / f"{cfg.name}_compare"
    check_output_dir(out, what="the comparison")
    base_dir = Path(source.split(" (replay config)")[0]).parent if cfg.source is not None else Path(config).parent
    if observers:  # names checked before the simulation
        known = {o.name or o.type for o in cfg.observers} | set(OBSERVERS.names()) | {f"{t}_defaults" for t in OBSERVERS.names()}
        bad = [w for w in observers if w not in known]
        if bad:
            raise ConfigError("--observers", (), f"unknown observer {bad[0]!r}; known: {', '.join(sorted(known))}")
    seed_ = cfg.runs.seed
    control = {}
    if cfg.source is not None:
        truth, sensors, streams = replay_truth(cfg, base_dir)
    else:
        truth, sensors, streams, control = simulate_and_measure(
            cfg, progress=(lambda k, n: progress("truth", k, n)) if progress else None)
    depth = np.asarray(truth.depth, dtype=float)
    final_depth = float(np.nanmean(depth[..., -1])) if depth.size else 0.0
    ctx = Context(cfg=cfg, model=truth.model, sensors={s.name: s for s in sensors}, replay=cfg.source is not None,
                  final_depth=final_depth, dt=float(cfg.simulation.dt))
    raw = parse_yaml(text, source)
    cands = candidates(ctx, list(raw.get("observers") or []), observers)
    chosen = [c for c in cands if not c.skip]
    skipped = [c for c in cands if c.skip]
    data = copy.deepcopy(raw)
    data["observers"] = [c.settings for c in chosen]
    cfg1, text1 = load_config(source, text=yaml.safe_dump(data, sort_keys=False))
    problem = build_problem(cfg1, truth, sensors, streams)
    start, start_text = common_start(ctx, chosen, cfg1, problem, seed_)
    problem = dataclasses.replace(problem, start=start)
    estimates, runs_out = {}, []
    for c, o in zip(chosen, cfg1.observers):
        name = o.name or o.type
        cb = (lambda k, n, _name=name: progress(f"observer {_name}", k, n)) if progress else None
        r = ObserverRun(candidate=c)
        t0 = time.perf_counter()
        try:  # guarded and checked (components): one observer's failure is a row of the table, not the end
            obs = components.build_observer(o)
            estimates[name] = components.run_observer(obs, o, problem, stream(seed_, f"observer/{name}"), progress=cb)
        except NeedleError as e:  # a crash, sys.exit, a posterior that breaks the contract, a user error inside
            if raised_signal() is not None:  # a signal that the observer's code swallowed: the end after all
                raise
            r.error = e.reason if isinstance(e, ComponentError) else " ".join(str(e).split())
        r.seconds = time.perf_counter() - t0
        runs_out.append(r)
    path = write_atomic(out / f"{cfg.name}_compare.h5", results_tree(cfg1, text1, truth, streams, estimates, sensors, control))
    res = read_results(path)
    errors = compute_errors(res)
    preds = prediction_errors(res)
    t_ok = truth.status == "ok"
    status = {}
    for name, post in estimates.items():
        bad = t_ok & (post.status != "ok")
        reasons = sorted({f"{s}" for s in post.status[bad]})
        status[name] = (int(bad.sum()), ", ".join(reasons))
    return CompareResult(
        cfg=cfg1, source=source, path=path, runs=runs_out, skipped=skipped, n_runs=int(truth.states.shape[0]),
        n_steps=len(truth.time) - 1, final_depth=final_depth, truth_failed=int((~t_ok).sum()), sensors=sensors,
        length_unit=truth.model.length_unit,
        errors=errors, predictions=preds,
        curvature={n: _online_curvature(p, truth.model) for n, p in estimates.items()}, status=status,
        start=start_text,
    )


def common_start(ctx: Context, chosen: list[Candidate], cfg: ExperimentConfig, problem, seed: int):
    """The initial estimate every observer of the comparison starts from: that of the config's first
    observer that can give one, else of the UKF with derived settings (:func:`ukf_defaults`), drawn from
    the reference's own random stream. Marks each candidate's ``start``; returns ``(start, recipe)``
    (``(None, why)`` when no observer can give one)."""
    from needlecli.experiments.simulation.truth import stream
    from needlecli.observers import OBSERVERS

    by_name = {o.name or o.type: o for o in cfg.observers}
    start, ref = None, None
    # the config's own observers first (its first that gives a start), then the UKF with derived settings
    order = [c for c in chosen if c.origin == "config"] + [c for c in chosen if c.origin != "config" and c.type == "ukf"]
    for c in order:
        cls = OBSERVERS.get(c.type)
        start = cls.initial_estimate(by_name[c.name], problem, stream(seed, f"observer/{c.name}"))
        if start is not None:
            ref = c.name
            break
    if start is None:  # no chosen observer gives one: the UKF's derived settings do (it need not run)
        try:
            ukf = OBSERVERS.get("ukf")
            settings = ukf.Settings.model_validate({**ukf_defaults(ctx), "name": "ukf_reference"})
            start = ukf.initial_estimate(settings, problem, stream(seed, "observer/ukf_reference"))
            ref = "ukf_reference"
        except (NotApplicable, ValidationError, ValueError):
            start = None
    for c in chosen:
        cls = OBSERVERS.get(c.type)
        if start is None or not cls.takes_common_start:
            c.start = "own settings"
        elif c.name == ref:
            c.start = "common (reference)"
        elif c.type == "high_gain" and by_name[c.name].init.values:  # seed 000's prescribed start on top
            vals = by_name[c.name].init.values
            same = len(set(vals.values())) == 1
            c.start = "common; " + (f"{', '.join(vals)} = {next(iter(vals.values())):g}" if same
                                    else ", ".join(f"{k} = {v:g}" for k, v in vals.items()))
        else:
            c.start = "common"
        c.causal = cls.causal
    if start is None:
        return None, "no observer gives an initial estimate: each starts from its own settings"
    derived = " (derived settings; not run)" if ref == "ukf_reference" else ""
    return start, start.source + derived


# ---------------------------------------------------------------------------------------------- table
def _sensor_text(sensors) -> tuple[str, str]:
    parts, rates = [], []
    for s in sensors:
        parts.append(f"{s.name}: {s.registered_name} ({', '.join(s.channel_names)})")
        rate = getattr(s.settings, "rate", None)
        rates.append(f"{rate:g} Hz" if isinstance(rate, (int, float)) else "?")
    return "; ".join(parts), " & ".join(rates)


def _instantaneous(es) -> tuple[str, str, float, float]:
    """(quantity, unit, mean, std) of the main error after initialisation: E_xyz, else E_R, else the first."""
    from needlecli.reports.tables import order_quantities

    qs = order_quantities(es.quantities) if es is not None else []
    if not qs:
        return "", "", float("nan"), float("nan")
    q = "E_xyz" if "E_xyz" in qs else "E_R" if "E_R" in qs else qs[0]
    qe = es.quantities[q]
    v = qe.values[:, 1:]
    v = v[np.isfinite(v)]
    return q, qe.unit, (float(np.mean(v)) if v.size else float("nan")), (float(np.std(v)) if v.size else float("nan"))


def compare_table(result: CompareResult) -> pd.DataFrame:
    """One row per observer that ran (tidy, numeric): sensors and rates, model, observer, online curvature
    estimation, insertion length, instantaneous error (mean, std after initialisation), curvature error,
    prediction error after 25 % of the insertion (NaN when the observer does not predict), runs, failed
    runs, runtime per step (the batch of all runs) and per run-step."""
    sensors, rates = _sensor_text(result.sensors)
    rows = []
    for r in result.runs:
        c = r.candidate
        name = c.name
        es = result.errors.get(name)
        q, unit, m, s = _instantaneous(es)
        kq = es.quantities.get("E_kappa") if es is not None else None
        kv = kq.values[:, 1:][np.isfinite(kq.values[:, 1:])] if kq is not None else np.zeros(0)
        pm = ps = float("nan")
        pred_depth = float("nan")
        if name in result.predictions:
            depths, err = result.predictions[name]
            d = PREDICTION_FRACTION * result.final_depth
            j = int(np.argmin(np.abs(depths - d))) if len(depths) else -1
            if j >= 0 and abs(depths[j] - d) <= 1e-6 * max(1.0, d):
                e = err[:, j]
                e = e[np.isfinite(e)]
                pred_depth = float(depths[j])
                if e.size:
                    pm, ps = float(np.mean(e)), float(np.std(e))
        failed, reasons = result.status.get(name, (result.n_runs - result.truth_failed, "raised"))
        model = (c.settings or {}).get("model") or result.cfg.model.type
        steps = max(result.n_steps, 1)
        rows.append({
            "observer": name, "type": c.type, "settings": c.origin, "start": c.start, "causal": c.causal,
            "sensors": sensors, "sensor_rates": rates,
            "model": model, "online_curvature": result.curvature.get(name, "n/a"),
            "insertion_length": result.final_depth, "runs": result.n_runs,
            "inst_quantity": q, "inst_unit": unit, "inst_mean": m, "inst_std": s,
            "kappa_mean": float(np.mean(kv)) if kv.size else float("nan"),
            "kappa_std": float(np.std(kv)) if kv.size else float("nan"),
            "pred_depth": pred_depth, "pred_mean_mm": pm, "pred_std_mm": ps,
            "runs_failed": failed if not r.error else result.n_runs, "failure_reasons": reasons if not r.error else r.error,
            "seconds": r.seconds, "ms_per_step": 1e3 * r.seconds / steps,
            "us_per_run_step": 1e6 * r.seconds / (steps * max(result.n_runs, 1)),
        })
    return pd.DataFrame(rows)


def _pm(m: float, s: float, unit: str = "") -> str:
    from needlecli.reports.tables import _float_format

    if not np.isfinite(m):
        return "n/a"
    return f"{_float_format(m)} ± {_float_format(s)}" + (f" {unit}" if unit else "")


def _num(v: float) -> str:
    return f"{v:.0f}" if abs(v) >= 100 else f"{v:.3g}"


def appendix_form(df: pd.DataFrame, result: CompareResult) -> pd.DataFrame:
    """The table in the form of seed 003's appendix A (Table A.3): one column per observer, one row per
    property."""
    length_unit = result.length_unit
    rows: dict[str, list[str]] = {
        "Sensor": [], "Sensor frequency": [], "Model": [], "Observer": [], "Settings": [], "Start": [],
        "Online curvature estimation": [], f"Length of insertion ({length_unit})": [],
        "Instantaneous error": [], "Curvature error": [], "Prediction error* (mm)": [],
        "Number of insertions": [], "Runs that failed": [], "Runtime per step": [],
    }
    for _, r in df.iterrows():
        rows["Sensor"].append(r["sensors"])
        rows["Sensor frequency"].append(r["sensor_rates"])
        rows["Model"].append(str(r["model"]))
        rows["Observer"].append(f"{r['observer']} ({r['type']})")
        rows["Settings"].append(r["settings"])
        rows["Start"].append(r["start"] + ("" if r["causal"] else " (smoother: every sample of the run)"))
        rows["Online curvature estimation"].append(r["online_curvature"])
        rows[f"Length of insertion ({length_unit})"].append(f"{r['insertion_length']:.3g}")
        inst = _pm(r["inst_mean"], r["inst_std"], r["inst_unit"])
        rows["Instantaneous error"].append(f"{inst} ({r['inst_quantity']})" if r["inst_quantity"] else "n/a")
        rows["Curvature error"].append(_pm(r["kappa_mean"], r["kappa_std"], f"1/{length_unit}"))
        rows["Prediction error* (mm)"].append(_pm(r["pred_mean_mm"], r["pred_std_mm"]))
        rows["Number of insertions"].append(str(r["runs"]))
        failed = f"{r['runs_failed']}/{r['runs']}" + (f" ({r['failure_reasons']})" if r["failure_reasons"] else "")
        rows["Runs that failed"].append(failed)
        rows["Runtime per step"].append(f"{_num(r['ms_per_step'])} ms ({_num(r['us_per_run_step'])} µs per run-step)")
    return pd.DataFrame([{"": k, **dict(zip(df["observer"], v))} for k, v in rows.items()])


def _short(v: float) -> str:
    """3 significant digits, scientific below 0.01 with a short exponent (``1.9e-4``)."""
    if not np.isfinite(v):
        return "n/a"
    if v == 0:
        return "0"
    if abs(v) < 1e-2:
        m, e = f"{v:.2e}".split("e")
        return f"{m}e{int(e)}"
    return f"{v:.3g}"


def _spread(m: float, s: float) -> str:
    return "n/a" if not np.isfinite(m) else f"{_short(m)} ± {_short(s)}"


def _narrow_markdown(df: pd.DataFrame) -> str:
    """A Markdown table with one space of padding (tabulate pads more): for a terminal's width."""
    cols = [str(c) for c in df.columns]
    cells = [[str(v) for v in row] for row in df.itertuples(index=False)]
    w = [max([len(c)] + [len(r[i]) for r in cells]) for i, c in enumerate(cols)]
    line = lambda vals: "| " + " | ".join(v.ljust(w[i]) for i, v in enumerate(vals)) + " |"  # noqa: E731
    return "\n".join([line(cols), "|" + "|".join("-" * (x + 2) for x in w) + "|"] + [line(r) for r in cells])


def terminal_form(df: pd.DataFrame, result: CompareResult, width: int = 80) -> str:
    """The comparison for a terminal of ``width`` columns: what every observer shares in a few lines,
    then two narrow tables (how each observer ran; its errors), then the notes, wrapped."""
    import textwrap

    unit = result.length_unit
    parts = [textwrap.fill(f"Observers on the same insertions of {result.cfg.name}: {result.n_runs} run(s) of "
                           f"{result.cfg.model.type}, {result.final_depth:.3g} {unit} long.", width)]
    sens = "; ".join(f"{s.name}: {s.registered_name} ({', '.join(s.channel_names)}) {getattr(s.settings, 'rate', 0):g} Hz"
                     for s in result.sensors)
    parts.append(textwrap.fill(f"Sensors: {sens}.", width))
    how = pd.DataFrame({
        "observer": [f"{o} ({t})" if o != t else o for o, t in zip(df["observer"], df["type"])],
        "settings": df["settings"], "start": df["start"],
        "failed": [f"{f}/{n}" for f, n in zip(df["runs_failed"], df["runs"])],
        "ms/step": [_short(v) for v in df["ms_per_step"]],
    })
    errs = pd.DataFrame({
        "observer": df["observer"],
        "error after init.": [f"{_spread(m, s)} {u} {q}".strip() if q else "n/a"
                              for m, s, u, q in zip(df["inst_mean"], df["inst_std"], df["inst_unit"], df["inst_quantity"])],
        f"E_kappa (1/{unit})": [_spread(m, s) for m, s in zip(df["kappa_mean"], df["kappa_std"])],
        "prediction* (mm)": [_spread(m, s) for m, s in zip(df["pred_mean_mm"], df["pred_std_mm"])],
    })
    parts += [_narrow_markdown(how), _narrow_markdown(errs)]
    notes = [f"Start: every observer marked 'common' starts from one initial estimate, the {result.start}."
             if result.start and not result.start.startswith("no ") else f"Start: {result.start}."]
    online = [o for o, c in zip(df["observer"], df["online_curvature"]) if c == "yes"]
    notes.append(f"Curvature estimated online by: {', '.join(online) or 'none'}.")
    offline = [o for o, c in zip(df["observer"], df["causal"]) if not c]
    if offline:
        notes.append(f"Smoothers (every sample of a run, also later ones; not a filter): {', '.join(offline)}.")
    notes.append(FOOTNOTE)
    failed = [f"{o}: {r}" for o, r in zip(df["observer"], df["failure_reasons"]) if r]
    if failed:
        notes.append("Failed runs: " + "; ".join(failed) + ".")
    parts += [textwrap.fill(n, width) for n in notes]
    return "\n\n".join(parts)


FOOTNOTE = ("*Prediction error of the final tip position from the estimate after observing 25 % of the "
            "insertion length (n/a: the observer does not predict). Errors over every kept run and time step "
            "after initialisation; runtime per step: wall time of one grid step for all runs at once.")
