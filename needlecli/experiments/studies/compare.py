"""Every observer on the same insertions: the experiment is simulated (or its logs replayed) once, then
each applicable observer runs on the same :class:`~needlecli.observers.EstimationProblem`.

Which observers, with which settings:

* each observer of the config runs with its own settings (``settings: config``);
* every other registered observer type, built-in or a plug-in, runs with the settings it derives itself
  from the experiment (``settings: defaults``): ``Observer.derived_settings`` with a
  :class:`~needlecli.observers.defaults.ComparisonContext` (sensors, nominal sigmas, process noise), under
  its registered name as ``type``; a type that derives none gets the schema's defaults;
* an observer is applicable when its settings pass its schema and its ``check(settings, model,
  sensors)``; otherwise it is skipped and the reason (the first problem) is reported.

Every observer starts from the same information: the **common start** is the initial estimate of the
reference observer (the config's first observer that can give one, else the first observer type that
declares ``default_reference``, with its derived settings: built-in types before plug-ins) -- its initial
mean of every run, drawn once from its random stream, and its initial covariance -- and every observer
that can take it (``Observer.takes_common_start``) starts from it, whatever its own ``init`` says, the
open-loop reference included. Where an observer's settings prescribe their own start in terms of the
common one (``Observer.prescribed_start``: the high-gain observer (`highgain-us2d`), x_hat0 = beta_hat0 = 0), that
applies on top. No observer starts from a run's own truth unless the reference does, and the table
names, per observer, where it started (``start``) and the common start's recipe (footnote), flagging
any state taken exactly from the truth.

Observers with a ``predict_at_depths`` setting also predict the final tip position from 25 % of the
insertion length (added to the depths they already have), the prediction error of the multi-rate UKF paper's
appendix A.

What the comparison decided per observer (settings origin, start, causal, runtime, the observers skipped
and why, the common start's recipe) goes into the results file's ``/compare`` group
(:func:`comparison_group`, docs/reference/results-file.md); the tables are built from the file
(:mod:`needlecli.reports.compare`).
"""

from __future__ import annotations

import copy
import dataclasses
import logging
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import yaml
from pydantic import ValidationError

from needlecli.errors import ComponentError, ConfigError, DataError, NeedleError, shown
from needlecli.observers.defaults import PREDICTION_FRACTION, ComparisonContext, NotApplicable

if TYPE_CHECKING:
    from needlecli.experiments.config.types import ExperimentConfig
    from needlecli.io.results import Group

Progress = Callable[[str, int, int], None]
log = logging.getLogger("needlecli")


# ---------------------------------------------------------------------------------------------- config
def is_log(path: str | Path) -> bool:
    """Whether ``path`` is an HDF5 log file (format needlecli-log)."""
    from needlecli.io.inputs import root_format

    return root_format(path) == "log"


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
    from needlecli.experiments.config.load import load_config
    from needlecli.io.inputs import describe, root_format
    from needlecli.models import MODELS

    path = Path(path)
    if not is_log(path):
        if root_format(path) is not None:
            raise DataError(f"{shown(path)}: is {describe(path)}, not a log (format needlecli-log); give a config or a log")
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
    model_only: bool = False  # the model alone from its start (the reference a filter must beat)


@dataclass
class ObserverRun:
    candidate: Candidate
    seconds: float = float("nan")
    error: str = ""


@dataclass
class CompareResult:
    """What ``needle compare`` did: the config as it ran (every observer's settings written out), where
    the results file went (its ``/compare`` group holds the rest of this, for the tables), the observers
    that ran and those skipped, and the common start's recipe (or why there is none)."""

    cfg: ExperimentConfig
    source: str
    path: Path
    runs: list[ObserverRun]
    skipped: list[Candidate]
    start: str = ""


def _with_prediction(settings: dict, cls, depth: float) -> dict:
    if "predict_at_depths" not in cls.Settings.model_fields or depth <= 0:
        return settings
    d = round(PREDICTION_FRACTION * depth, 9)
    have = [float(x) for x in settings.get("predict_at_depths") or []]
    if not any(abs(x - d) <= 1e-9 * max(1.0, d) for x in have):
        settings = {**settings, "predict_at_depths": sorted(have + [d])}
    return settings


def derived_settings(cls, type_: str, name: str, ctx: ComparisonContext) -> dict:
    """The settings observer class ``cls`` derives from the experiment, registered as ``type_``, named
    ``name`` (:meth:`~needlecli.observers.base.Observer.derived_settings`; ``type`` first, as a config
    writes it). Raises :class:`~needlecli.observers.defaults.NotApplicable`."""
    own = {k: v for k, v in cls.derived_settings(ctx).items() if k not in ("type", "name")}
    return {"type": type_, **own, "name": name}


def candidates(ctx: ComparisonContext, raw_observers: list[dict], wanted: list[str] | None) -> list[Candidate]:
    """The observers to try: the config's own, then one per other registered type with the settings it
    derives; each checked (schema and ``check``); ``wanted`` filters by name or type. A type that cannot
    derive settings for this experiment, or a plug-in that cannot be imported, is skipped with the reason."""
    from needlecli.observers import OBSERVERS
    from needlecli.registry import PluginError

    out: list[Candidate] = []
    types_in_config = set()
    for raw in raw_observers:
        t = raw.get("type")
        types_in_config.add(t)
        out.append(Candidate(name=raw.get("name") or t, type=t, origin="config", settings=copy.deepcopy(raw)))
    used = {c.name for c in out}
    for t in OBSERVERS.names():
        if t not in types_in_config:
            out.append(Candidate(name=t if t not in used else f"{t}_defaults", type=t, origin="defaults"))
    if wanted:
        known = {c.name for c in out} | {c.type for c in out}
        bad = [w for w in wanted if w not in known]
        if bad:
            raise ConfigError("--observers", (), f"unknown observer {bad[0]!r}; known: {', '.join(sorted(known))}")
        out = [c for c in out if c.name in wanted or c.type in wanted]
    for c in out:
        try:
            cls = OBSERVERS.get(c.type)
            if c.origin == "defaults":
                c.settings = derived_settings(cls, c.type, c.name, ctx)
        except (NotApplicable, PluginError) as e:
            c.skip = str(e)
            continue
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


@dataclass
class Comparison:
    """A comparison set up and ready to run (:func:`prepare_comparison`): the config as it will run (every
    chosen observer's settings written out, ``cfg``, ``text``), the insertions simulated or replayed once
    (``truth``, ``sensors``, ``streams``, ``control``), what derived settings were given
    (``context``), the observers chosen and skipped, and the problem every observer runs on, carrying the
    common start (``problem.start``; ``start`` its recipe)."""

    cfg: ExperimentConfig
    text: str
    source: str
    truth: Any
    sensors: list
    streams: dict
    control: dict
    context: ComparisonContext
    chosen: list[Candidate]
    skipped: list[Candidate]
    problem: Any
    start: str


def comparison_context(cfg: ExperimentConfig, truth, sensors, problem) -> ComparisonContext:
    """What the observers' derived settings may use (:class:`ComparisonContext`): the config's nominal
    start and spreads (a simulation), the recorded samples and whether the truth's start was recorded (a
    replay)."""
    depth = np.asarray(truth.depth, dtype=float)
    replay = cfg.source is not None
    first = np.asarray(truth.states[:, 0], dtype=float)
    return ComparisonContext(
        model=truth.model, sensors={s.name: s for s in sensors}, replay=replay,
        final_depth=float(np.nanmean(depth[..., -1])) if depth.size else 0.0, dt=float(cfg.simulation.dt),
        process_std={} if replay else dict(cfg.process_noise.std),
        param_std={} if replay else parameter_spread(cfg),
        initial_state=dict(cfg.model.initial_state),
        initial_std={} if replay else dict(cfg.model.initial_std),
        time=np.asarray(truth.time, dtype=float), inputs=np.asarray(truth.inputs, dtype=float),
        channels=problem.channels if replay else None,
        initial_truth_recorded=bool(first.size and np.isfinite(first).all()),
    )


def prepare_comparison(
    config: str | Path,
    *,
    observers: list[str] | None = None,
    runs: int | None = None,
    seed: int | None = None,
    model: str | None = None,
    overrides: list[str] | None = None,
    progress: Progress | None = None,
    loaded: tuple | None = None,
) -> Comparison:
    """Load the experiment (``loaded``: what :func:`load_compare_config` returned, if already loaded),
    simulate (or replay) it once, choose the observers (:func:`candidates`) and make the common start
    (:func:`common_start`): everything :func:`compare_observers` runs, nothing run yet."""
    from needlecli.experiments.config.load import load_config
    from needlecli.experiments.config.types import CONFIG_FORMAT
    from needlecli.experiments.simulation.replay import replay_truth
    from needlecli.experiments.simulation.runner import build_problem, simulate_and_measure
    from needlecli.io.yamlfile import parse_yaml
    from needlecli.observers import OBSERVERS

    cfg, text, source = loaded or load_compare_config(config, model=model, runs=runs, seed=seed, overrides=overrides)
    base_dir = Path(source.split(" (replay config)")[0]).parent if cfg.source is not None else Path(config).parent
    if observers:  # names checked before the simulation
        known = {o.name or o.type for o in cfg.observers} | set(OBSERVERS.names()) | {f"{t}_defaults" for t in OBSERVERS.names()}
        bad = [w for w in observers if w not in known]
        if bad:
            raise ConfigError("--observers", (), f"unknown observer {bad[0]!r}; known: {', '.join(sorted(known))}")
    control = {}
    if cfg.source is not None:
        truth, sensors, streams = replay_truth(cfg, base_dir)
    else:
        truth, sensors, streams, control = simulate_and_measure(
            cfg, progress=(lambda k, n: progress("truth", k, n)) if progress else None)
    ctx = comparison_context(cfg, truth, sensors, build_problem(cfg, truth, sensors, streams))
    raw = parse_yaml(text, source)
    cands = candidates(ctx, list(raw.get("observers") or []), observers)
    chosen = [c for c in cands if not c.skip]
    skipped = [c for c in cands if c.skip]
    data = copy.deepcopy(raw)
    data["observers"] = [c.settings for c in chosen]
    data["format"] = CONFIG_FORMAT  # the derived settings' meaning (the config's own are converted in text)
    cfg1, text1 = load_config(source, text=yaml.safe_dump(data, sort_keys=False))
    problem = build_problem(cfg1, truth, sensors, streams)
    start, start_text = common_start(ctx, chosen, cfg1, problem, cfg.runs.seed)
    return Comparison(cfg=cfg1, text=text1, source=source, truth=truth, sensors=sensors, streams=streams,
                      control=control, context=ctx, chosen=chosen, skipped=skipped,
                      problem=dataclasses.replace(problem, start=start), start=start_text)


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
    """Simulate (or replay) once, run every applicable observer on the same problem and write the results
    file ``<out_dir>/<name>_compare.h5`` with the comparison's ``/compare`` group (the tables of
    :mod:`needlecli.reports.compare` read it)."""
    from needlecli.experiments.simulation import components
    from needlecli.experiments.simulation.observability import unobservable_states
    from needlecli.experiments.simulation.runner import results_tree
    from needlecli.experiments.simulation.truth import stream
    from needlecli.io.atomic import check_output_dir, raised_signal
    from needlecli.io.results import write_atomic

    loaded = load_compare_config(config, model=model, runs=runs, seed=seed, overrides=overrides)
    name = loaded[0].name
    for u in unobservable_states(loaded[0]):  # what no observer can estimate with these sensors, before the table
        log.warning("%s: [sensors] %s", loaded[2], u.message())
    out = Path(out_dir) if out_dir is not None else Path("results") / f"{name}_compare"
    check_output_dir(out, what="the comparison")
    cmp = prepare_comparison(config, observers=observers, progress=progress, loaded=loaded)
    cfg1, problem, seed_ = cmp.cfg, cmp.problem, cmp.cfg.runs.seed
    estimates, runs_out = {}, []
    for c, o in zip(cmp.chosen, cfg1.observers):
        oname = o.name or o.type
        cb = (lambda k, n, _name=oname: progress(f"observer {_name}", k, n)) if progress else None
        r = ObserverRun(candidate=c)
        t0 = time.perf_counter()
        try:  # guarded and checked (components): one observer's failure is a row of the table, not the end
            obs = components.build_observer(o)
            estimates[oname] = components.run_observer(obs, o, problem, stream(seed_, f"observer/{oname}"), progress=cb)
        except NeedleError as e:  # a crash, sys.exit, a posterior that breaks the contract, a user error inside
            if raised_signal() is not None:  # a signal that the observer's code swallowed: the end after all
                raise
            r.error = e.reason if isinstance(e, ComponentError) else " ".join(str(e).split())
        r.seconds = time.perf_counter() - t0
        runs_out.append(r)
    tree = results_tree(cfg1, cmp.text, cmp.truth, cmp.streams, estimates, cmp.sensors, cmp.control)
    tree.data["compare"] = comparison_group(runs_out, cmp.skipped, cmp.start, [s.name for s in cmp.sensors], cfg1)
    path = write_atomic(out / f"{name}_compare.h5", tree)
    return CompareResult(cfg=cfg1, source=cmp.source, path=path, runs=runs_out, skipped=cmp.skipped, start=cmp.start)


def parameter_spread(cfg: ExperimentConfig) -> dict[str, float]:
    """The spread over runs of each model parameter that varies between runs: ``model.param_std`` and
    the std of the values of ``model.param_cases`` (over the cases, which the runs share alike) in
    quadrature."""
    out = {k: float(v) for k, v in cfg.model.param_std.items()}
    pc = cfg.model.param_cases
    if pc is not None:
        nominal = cfg.model.params.model_dump()
        for k in {k for c in pc.cases for k in c}:
            values = np.array([c.get(k, float(nominal.get(k, 0.0))) for c in pc.cases], dtype=float)
            sd = float(np.std(values))
            if sd > 0:
                out[k] = float(np.hypot(out.get(k, 0.0), sd))
    return out


def comparison_group(runs: list[ObserverRun], skipped: list[Candidate], start: str, sensors: list[str],
                     cfg: ExperimentConfig) -> Group:
    """The results file's ``/compare`` group: per observer that was run, in the table's order (``(K,)``
    each): ``observer``, ``type``, ``settings`` (``config`` or ``defaults``), ``start`` (where it started),
    ``causal``, ``model_only`` (the model alone, no measurement: ``Observer.model_only``), ``model`` (its
    own), ``seconds`` (wall time of its run over every run at once), ``error``
    (the exception that ended it, empty when it ran); ``skipped/observer``, ``skipped/type``,
    ``skipped/reason`` ``(S,)``; attributes ``start`` (the common start's recipe, or why there is none),
    ``prediction_fraction`` and ``sensors`` (their names in the experiment's order)."""
    from needlecli.io.results import Group

    def text(values) -> np.ndarray:
        return np.array([str(v) for v in values], dtype=object)

    cands = [r.candidate for r in runs]
    return Group(
        data={
            "observer": text(c.name for c in cands),
            "type": text(c.type for c in cands),
            "settings": text(c.origin for c in cands),
            "start": text(c.start for c in cands),
            "causal": np.array([bool(c.causal) for c in cands], dtype=bool),
            "model_only": np.array([bool(c.model_only) for c in cands], dtype=bool),
            "model": text((c.settings or {}).get("model") or cfg.model.type for c in cands),
            "seconds": np.array([r.seconds for r in runs], dtype=float),
            "error": text(r.error for r in runs),
            "skipped": Group(data={"observer": text(c.name for c in skipped), "type": text(c.type for c in skipped),
                                   "reason": text(c.skip for c in skipped)}),
        },
        attrs={"start": start, "prediction_fraction": PREDICTION_FRACTION, "sensors": list(sensors)},
    )


def _plugin(type_: str) -> bool:
    """Whether an observer type is a plug-in's: a reference is sought among the built-in types first, so
    that a plug-in installed beside them does not change a comparison that does not name it."""
    from needlecli.observers import OBSERVERS

    return type_ not in OBSERVERS.builtin_names()


def common_start(ctx: ComparisonContext, chosen: list[Candidate], cfg: ExperimentConfig, problem, seed: int):
    """The initial estimate every observer of the comparison starts from: that of the config's first
    observer that can give one, else of the first observer type that declares ``default_reference`` (the
    UKF), with its derived settings, drawn from the reference's own random stream. Marks each candidate's
    ``start`` (with the note of a start its settings prescribe on top, ``Observer.prescribed_start``) and
    ``causal``; returns ``(start, recipe)`` (``(None, why)`` when no observer can give one)."""
    from needlecli.experiments.simulation import components
    from needlecli.experiments.simulation.truth import stream
    from needlecli.observers import OBSERVERS
    from needlecli.registry import PluginError

    by_name = {o.name or o.type: o for o in cfg.observers}
    start, ref = None, None
    # the config's own observers first (its first that gives a start), then a reference type with derived settings
    derived = [c for c in chosen if c.origin != "config" and OBSERVERS.get(c.type).default_reference]
    order = [c for c in chosen if c.origin == "config"] + sorted(derived, key=lambda c: _plugin(c.type))
    for c in order:
        start = components.initial_estimate(by_name[c.name], problem, stream(seed, f"observer/{c.name}"))
        if start is not None:
            ref = c.name
            break
    fallback = False
    if start is None:  # no chosen observer gives one: a reference type's derived settings do (it need not run)
        for t in sorted(OBSERVERS.names(), key=lambda t: (_plugin(t), t)):
            try:
                cls = OBSERVERS.get(t)
            except PluginError:
                continue
            if not cls.default_reference:
                continue
            name = f"{t}_reference"
            try:
                settings = cls.Settings.model_validate(derived_settings(cls, t, name, ctx))
                start = cls.initial_estimate(settings, problem, stream(seed, f"observer/{name}"))
            except (NotApplicable, ValidationError, ValueError):
                start = None
            if start is not None:
                ref, fallback = name, True
                break
    for c in chosen:
        cls = OBSERVERS.get(c.type)
        if start is None or not cls.takes_common_start:
            c.start = "own settings"
        elif c.name == ref:
            c.start = "common (reference)"
        elif note := cls.prescribed_start(by_name[c.name]):  # e.g. the high-gain observer paper's start on top of the common one
            c.start = f"common; {note}"
        else:
            c.start = "common"
        c.causal = cls.causal
        c.model_only = cls.model_only
    if start is None:
        return None, "no observer gives an initial estimate: each starts from its own settings"
    return start, start.source + (" (derived settings; not run)" if fallback else "")
