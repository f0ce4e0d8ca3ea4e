"""``needle fit-em``: EM for every trial of an experiment and every model, into one fit file.

Where the trials come from is the one seam (:func:`load_trials`): a config that simulates them (truth
from its model, its sensors), or a config whose ``source: {logs: [...]}`` replays recorded ones. Other
files are refused with a message that says what to do. Everything after that point sees only the
:class:`~needlecli.observers.EstimationProblem` (inputs, measurement channels), never the truth.
"""

from __future__ import annotations

import contextlib
import logging
import multiprocessing as mp
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from needlecli import kernels, platform
from needlecli.errors import DataError
from needlecli.experiments.config.load import load_config
from needlecli.experiments.config.types import Stop
from needlecli.experiments.simulation.runner import build_problem, simulate_and_measure, truth_entry
from needlecli.experiments.simulation.truth import Truth
from needlecli.fitting.canonical import flip_negative_curvature
from needlecli.fitting.em import EMOptions, EMResult, fit_em
from needlecli.fitting.identify import Identifiability, IdentifyOptions, Quantity, fit_quantities, identify, take_trials
from needlecli.fitting.problem import System, build_system, fit_augment, own_model
from needlecli.fitting.robust import RobustInfo, fit_em_robust
from needlecli.fitting.settings import FitSettings
from needlecli.fitting.statespace import param_unit
from needlecli.io.fit import FIT_FORMAT, FIT_VERSION
from needlecli.io.results import Group, root_attrs
from needlecli.models import MODELS
from needlecli.numerics.needle_frame import AXES

if TYPE_CHECKING:
    from needlecli.experiments.config.types import ExperimentConfig

log = logging.getLogger("needlecli")

CONFIG_SUFFIXES = (".yaml", ".yml")


@dataclass
class Trials:
    """The trials to fit: the config, the truth where known (simulation), sensors and their streams."""

    cfg: object
    text: str
    source: Path
    truth: Truth
    sensors: list
    streams: dict
    simulated: bool


#: ``needle fit-em --model both``: every model of the config's fit section (``fit.models``; the magnetic needle EM paper's
#: configs fit mnm and binm, whence the word)
EVERY_MODEL = "both"


def fit_models_option(choice: str | None) -> list[str] | None:
    """The models ``needle fit-em --model`` asks for: a model name or several, comma-separated, each one
    a fit section can fit (``fit.models`` takes every registered model, built-in or a plug-in's); None
    for every model of the config's fit section (no choice, or :data:`EVERY_MODEL`).

    Raises
    ------
    ConfigError
        A name that is no registered model (the message names the accepted ones).
    """
    from needlecli.errors import ConfigError, did_you_mean

    if choice is None:
        return None
    names = [m.strip().lower() for m in choice.split(",") if m.strip()]
    if not names or names == [EVERY_MODEL]:
        return None
    known = MODELS.names()
    for m in names:
        if m not in known:
            raise ConfigError("--model", (), f"{m!r} is not a model a fit section can fit; give {', '.join(known)} "
                              f"(several comma-separated) or {EVERY_MODEL} (every model of the config's fit.models)"
                              + did_you_mean(m, known + [EVERY_MODEL]))
    return list(dict.fromkeys(names))


def load_fit_config(path: str | Path, *, overrides: list[str] | None = None):
    """Read and check the config of a fit: ``(cfg, text)``. A file that is not a config is a DataError
    saying what to do instead."""
    path = Path(path)
    if path.suffix.lower() not in CONFIG_SUFFIXES:
        raise DataError(_not_a_config(path))
    return load_config(path, overrides=overrides)


def load_trials(path: str | Path, *, overrides: list[str] | None = None, models: list[str] | None = None) -> Trials:
    """Read a config and simulate (or replay) its trials (``models``: those the fit will fit, None for the
    fit section's; what its plan for a cold kernel cache counts, :func:`plan_kernels`).

    Raises
    ------
    ConfigError for a bad config; DataError for a file that is not a config (with what to do instead).
    """
    path = Path(path)
    cfg, text = load_fit_config(path, overrides=overrides)
    plan_kernels(cfg, models)
    if cfg.source is not None:  # recorded trials through the replay machinery
        from needlecli.experiments.simulation.replay import replay_truth

        truth, sensors, streams = replay_truth(cfg, path.parent)
        return Trials(cfg, text, path, truth, sensors, streams, simulated=False)
    truth, sensors, streams, _ = simulate_and_measure(cfg)  # a control section closes its loop
    return Trials(cfg, text, path, truth, sensors, streams, simulated=True)


#: s per trial, tick and model that EM and its identifiability take more on the numpy path than compiled:
#: the magnetic needle EM paper's study (48 trials x 486 ticks x 2 models, 71.5 s against 9.0 s: docs/benchmarks.md)
NUMPY_EXTRA_S = 1.3e-3
#: processes a fit runs its models in (one per model, at most this many)
FIT_WORKERS = 2
#: the kernels a fit compiles (EM's passes, its M-step, identifiability's log-likelihoods)
FIT_KERNELS = ("kalman_filter_smoother", "rts_smoother", "transition_all", "linearise", "em_process_noise",
               "em_measurement_noise", "kalman_loglik_affine")


def plan_kernels(cfg: ExperimentConfig, models: list[str] | None = None) -> None:
    """The fit's plan for a cold kernel cache (:func:`needlecli.kernels.on_cold`): the numpy path for the
    whole command while a process of its own compiles the kernels on a short copy of the fit
    (:func:`_fit_briefly`), where that is quicker than compiling first (small fits); otherwise the
    compilation first, said once. Simulated trials only (recorded ones: the compilation first)."""
    if cfg.fit is None or kernels.requested(cfg.simulation.kernels) == "numpy" or not kernels.numba_available():
        return
    from needlecli.experiments.config.budget import estimate

    truth, *entries = fit_entries(cfg)
    if cfg.source is not None:
        kernels.on_cold(entries=entries)
        return
    size = estimate(cfg)
    rate = max([getattr(s, "rate", 0.0) or 0.0 for s in cfg.sensors], default=0.0)
    ticks = max(2.0, rate * (size.steps - 1) * cfg.simulation.dt) if rate else float(size.steps)
    n_models = len(models or cfg.fit.models)
    # the numpy path would share the cores with the background compilation: the models' processes (one per
    # model, at most FIT_WORKERS) and the compiler on the usable cores slow it by their ratio when they
    # outnumber the cores (the magnetic needle EM paper's fit on 2 cores: 84 s on numpy beside the
    # compiler, 60 s alone)
    busy = min(n_models, FIT_WORKERS) + 1
    shared = max(1.0, busy / platform.usable_cores())
    kernels.on_cold(entries=[truth, *entries], numpy_seconds=NUMPY_EXTRA_S * size.runs * ticks * n_models * shared,
                    compile_for_next_run=_fit_briefly, args=(brief_fit(cfg), models))


def fit_entries(cfg: ExperimentConfig) -> list[tuple[str, str] | None]:
    """The entry kernels a fit of ``cfg`` compiles: the truth's first (:func:`truth_entry`), then EM's and
    identifiability's."""
    return [truth_entry(cfg), *(kernels.TWINS[t].entry for t in FIT_KERNELS)]


def brief_fit(cfg: ExperimentConfig) -> ExperimentConfig:
    """``cfg`` shortened to two trials of 2 s and two EM iterations, taken as converged (so that
    identifiability assesses them): what compiles every kernel of its fit with their argument types
    (:func:`_fit_briefly`)."""
    return cfg.model_copy(update={
        "runs": cfg.runs.model_copy(update={"count": min(2, cfg.runs.count)}), "stop": Stop(time=2.0),
        "fit": cfg.fit.model_copy(update={"em": cfg.fit.em.model_copy(update={"max_iter": 2, "tol": 1e300})})})


def _fit_briefly(cfg: ExperimentConfig, models: list[str] | None) -> None:
    """The fit of ``cfg`` (a short copy of the command's), nothing written: every kernel the fit compiles,
    with its argument types (:func:`plan_kernels`)."""
    truth, sensors, streams, _ = simulate_and_measure(cfg)
    fit_trials(Trials(cfg, "", Path("brief.yaml"), truth, sensors, streams, simulated=True), models=models, workers=1)


def _not_a_config(path: Path) -> str:
    from needlecli.errors import shown
    from needlecli.io.inputs import describe, root_format

    if not (path.exists() or path.is_symlink()):
        return f"{shown(path)}: no such file (fit-em takes experiment configs, .yaml)"
    kind = root_format(path) or ""
    if kind == "log":
        return (f"{shown(path)}: is a log file; fit-em takes a config: write one with `source: {{logs: [{path.name}]}}`, "
                "the model and a `fit:` section (see configs/replay/em-magnetic-pratt2022_like.yaml) and pass that")
    if kind == "results":
        return f"{shown(path)}: is a results file; fit-em takes the experiment's config (.yaml)"
    if kind == "fit":
        return f"{shown(path)}: is a fit file already; evaluate it with `needle evaluate {path}`"
    return (f"{shown(path)}: is {describe(path)}, not an experiment config (.yaml); fit-em takes configs (recorded "
            "trials through `source: logs`)")


def em_options(fit: FitSettings, system: System) -> EMOptions:
    e = fit.em
    return EMOptions(
        max_iter=e.max_iter, tol=e.tol, estep_max=e.estep_max, estep_tol=e.estep_tol, update_x0=e.update_x0,
        q_index=system.q_index, q_floor=e.q_floor, r_floor=tuple(system.floors), ll_noise=e.ll_noise,
        accelerate=e.accelerate, relin_tol=e.relin_tol,
        q_hold=tuple(i for i, s in enumerate(system.names) if s in fit.hold and i in system.q_index),
        q_isotropic=isotropic_groups(fit, system),
    )


def isotropic_groups(fit: FitSettings, system: System) -> tuple[tuple[int, ...], ...]:
    """The state indices of each block of ``fit.isotropic`` that this system has, its states with process
    noise only (a model without the block: none)."""
    from needlecli.models.base import state_blocks

    blocks = state_blocks(system.names, skip=system.dm.augment)
    out = []
    for stem in fit.isotropic:
        idx = tuple(i for i in blocks.get(stem, []) if i in system.q_index)
        if len(idx) > 1:
            out.append(idx)
    return tuple(out)


@dataclass
class ModelFit:
    name: str
    system: System
    result: EMResult
    seconds: float = 0.0
    identifiability: Identifiability | None = None
    robust: RobustInfo | None = None


@dataclass
class FitOutput:
    trials: Trials
    fits: dict[str, ModelFit] = field(default_factory=dict)


def fit_trials(
    trials: Trials,
    *,
    models: list[str] | None = None,
    progress: Callable[[str, int, int], None] | None = None,
    workers: int = FIT_WORKERS,
) -> FitOutput:
    """EM (the magnetic needle EM paper, Algorithm 1) on every trial for each model, all trials of a model at once; with
    ``workers > 1`` the models run in parallel processes (one per model, at most ``workers``)."""
    import time

    cfg = trials.cfg
    if cfg.fit is None:
        raise DataError(f"{trials.source}: [fit] required key is missing: fit-em needs the initial guesses of "
                        "Q, R and the constant (see configs/em-magnetic-pratt2022/study.yaml)")
    fit = cfg.fit
    names = models or list(fit.models)
    problem = build_problem(cfg, trials.truth, trials.sensors, trials.streams)
    out = FitOutput(trials)
    systems = {}
    for name in names:
        if name not in MODELS:
            raise DataError(f"unknown model {name!r}; known: {', '.join(MODELS.names())}")
        model = own_model(fit, trials.truth.model, name)
        try:
            # a held constant stays a parameter of the model (not a state the smoother could move)
            systems[name] = build_system(problem, fit, model,
                                         [c for c in fit_augment(type(model), fit.constants) if c not in fit.hold])
        except ValueError as e:
            raise DataError(f"{trials.source}: [fit] {e}") from None
        S = systems[name]  # a state held at zero process noise has none (not a block of Q that EM fits)
        S.q_index = tuple(i for i in S.q_index if not (S.names[i] in fit.hold and S.Qc[i, i] == 0.0))
        for line in axis_warnings(problem, S, name, trials.truth.trial_ids):
            log.warning("warning: %s", line)

    def run(name, cb):
        S = systems[name]
        t0 = time.perf_counter()
        dof = [fit.measurements[m.name].student_t if m.name in fit.measurements else None for m in S.meas]
        if any(d is not None for d in dof):  # Student-t channels: iteratively reweighted EM
            res, rob, meas = fit_em_robust(S.dm, S.meas, S.m0, S.P0, S.Qc, S.R, em_options(fit, S), dof,
                                           max_passes=fit.em.reweight_max, tol=fit.em.reweight_tol, progress=cb)
        else:
            res, rob, meas = fit_em(S.dm, S.meas, S.m0, S.P0, S.Qc, S.R, em_options(fit, S), progress=cb), None, S.meas
        res.roll_flipped = flip_negative_curvature(S.dm.names, type(S.dm.model), res)  # kappa < 0 = roll + pi
        return res, assess(S, res, fit, meas, trials=trials, groups=groups), time.perf_counter() - t0, rob

    groups = design_groups(trials.truth, cfg)
    # models are independent: all but the first go to child processes (forked, so nothing is pickled
    # but the results), the first runs here; the children report progress through a queue. Where
    # processes cannot be forked (macOS, Windows) the models run here one after another, on every core
    parallel = workers > 1 and len(names) > 1 and platform.fork_available()
    with platform.single_blas_thread() if parallel else contextlib.nullcontext(), \
            kernels.threads(1 if parallel else None):  # a process per model: one kernel thread each
        _run_models(names, workers if parallel else 1, run, systems, out, progress)
    out.fits = {name: out.fits[name] for name in names}
    for mf in out.fits.values():
        add_data_hints(mf.result, problem)
        for line in outside_warnings(mf, trials.truth.trial_ids):
            log.warning("warning: %s", line)
    return out


def _trial_name(ids, i: int) -> str:
    return str(ids[i]) if ids is not None else f"run {i}"


def axis_warnings(problem, S: System, model: str, ids=None) -> list[str]:
    """One line per trial and position channel (x, y, z) whose recorded path starts more than
    :data:`~needlecli.io.frames.AXIS_WARNING_DEG` from the model's insertion axis at the fit's start (the
    tangent of each trial's initial state ``S.m0``), all trials at once."""
    from needlecli.io.frames import AXIS_WARNING_DEG, axis_angles, initial_directions

    dm = S.dm
    if not type(dm.model).provides("tangent"):
        return []
    with np.errstate(all="ignore"):
        axis = dm.model.tangent(np.asarray(S.m0, dtype=float)[:, : dm.model.n])  # (N, 3)
    out = []
    for ch in problem.channels.values():
        if ch.sensor_type != "position" or not {"x", "y", "z"} <= set(ch.names):
            continue
        pos = ch.value[..., [list(ch.names).index(a) for a in "xyz"]]
        ang = axis_angles(initial_directions(pos, ch.valid), axis)
        for i in np.flatnonzero(ang > AXIS_WARNING_DEG):
            out.append(f"{model}: trial {_trial_name(ids, i)}: the path of {ch.name} starts {ang[i]:.0f} deg from the "
                       f"model's insertion axis at the fit's start (more than {AXIS_WARNING_DEG:g} deg): the data are "
                       "not in the model's frame; what EM fits is not the needle's (express the trial in its own frame)")
    return out


def outside_warnings(mf: ModelFit, ids=None) -> list[str]:
    """One line per fitted constant whose value lies outside the bounds its model declares
    (:func:`needlecli.fitting.identify.parameter_bounds`; the verdict ``outside its bounds`` of the trials
    assessed), in the trials whose fit did not fail (those that stopped at the iteration limit too)."""
    from needlecli.fitting.em import STATUS_DIVERGED, STATUS_SINGULAR
    from needlecli.fitting.identify import parameter_bounds

    r, dm = mf.result, mf.system.dm
    use = ~np.isin(np.asarray(r.status).astype(str), (STATUS_SINGULAR, STATUS_DIVERGED))
    out = []
    for i, c in enumerate(dm.augment):
        b = parameter_bounds(type(dm.model), c)
        if b is None:
            continue
        v = r.x0[:, dm.nx + i]
        bad = np.flatnonzero(use & b.outside(v))
        if bad.size:
            trials = ", ".join(f"{_trial_name(ids, j)} ({v[j]:.4g})" for j in bad[:5])
            out.append(f"{mf.name}: {c} is outside its bounds {b} in {bad.size} of {len(v)} trial(s): {trials}"
                       f"{', ...' if bad.size > 5 else ''}; never identified (not a value of the model's constant)")
    return out


def assess(S: System, res: EMResult, fit: FitSettings, meas=None, *, trials: Trials | None = None,
           groups: tuple[np.ndarray, list[str]] | None = None) -> Identifiability | None:
    """What the data identify in each trial's fit (None when ``fit.identify.enabled`` is off); ``meas``:
    the channels as fitted (with their robust weights), default the system's; ``trials``: where they are
    simulated, the truth each quantity is checked against (the recovery check of the verdicts);
    ``groups``: ``(group (N,), labels)`` the trials' design groups (:func:`design_groups`), pooled apart."""
    s = fit.identify
    if not s.enabled:
        return None
    meas = S.meas if meas is None else meas
    sd = np.sqrt(np.maximum(np.diagonal(res.P[:, 0], axis1=-2, axis2=-1), 0.0))[:, S.dm.nx:]
    truth = None
    if trials is not None and trials.simulated:
        truth = true_quantities(fit_quantities(S.dm, meas, res.Qc, tuple(fit.hold)), S, trials)
    group, labels = groups if groups is not None else (None, None)
    return identify(S.dm, meas, res.x0, S.P0, res.Qc, res.R, res.status == "ok",
                    const_sd=sd, options=identify_options(fit), zbar=res.m, held=tuple(fit.hold),
                    truth=truth, group=group, group_labels=labels, floors=S.floors, tied=tuple(fit.isotropic))


def identify_options(fit: FitSettings) -> IdentifyOptions:
    s = fit.identify
    return IdentifyOptions(rse_max=s.rse_max, nats=s.nats, z_max=s.z_max)


def true_quantities(qs: list[Quantity], S: System, trials: Trials) -> np.ndarray:
    """``(N, d)``: the true value of each quantity of a fit of simulated trials (NaN where there is none to
    compare with). A constant and a Q block only for the model that made the truth (another model's
    constants and process noise are its own): the truth's parameter per trial, and the trace of its
    process noise per second over the block, ``sum q_std^2`` (the truth adds ``q_std sqrt(dt)`` noise per
    grid step). R of a channel whose samples have one Gaussian sigma per component (``pipeline:
    gaussian``): the trace of ``diag(sigma^2)`` over the components fitted (a measured direction: its two
    components across it, each the mean sigma^2; a needle-frame block when the axes share one sigma)."""
    truth = trials.truth
    N = len(S.m0)
    out = np.full((N, len(qs)), np.nan)
    same = type(S.dm.model) is type(truth.model)
    qstd = trials.cfg.process_noise.std
    for k, q in enumerate(qs):
        if q.kind == "constant" and same:
            p = np.asarray(truth.params.get(q.name, np.full((N, 1), np.nan)), dtype=float).reshape(N, -1)
            out[:, k] = np.where(np.ptp(p, axis=1) == 0, p[:, 0], np.nan)  # a schedule in time: no one truth
        elif q.kind == "Q" and same:
            out[:, k] = sum(float(qstd.get(S.dm.names[i], 0.0)) ** 2 for i in q.index)
        elif q.kind == "R":
            j, comps = q.index if isinstance(q.index, tuple) else (q.index, None)
            out[:, k] = _true_trace_r(S.meas[j], trials.streams.get(S.meas[j].name), comps)
    return out


def _true_trace_r(mm, stream, comps) -> np.ndarray | float:
    """The true ``tr(R)`` of one channel per trial ``(N,)`` (NaN where the sigma is not one per component)."""
    if stream is None or str(stream.attrs.get("pipeline", "gaussian")) != "gaussian" or getattr(stream, "sigma", None) is None:
        return np.nan
    sig = np.asarray(stream.sigma, dtype=float)  # (N, M, m)
    valid = np.asarray(stream.valid, dtype=bool)
    with np.errstate(all="ignore"):
        lo = np.where(valid[..., None], sig, np.inf).min(1)
        hi = np.where(valid[..., None], sig, -np.inf).max(1)
    one = np.isfinite(lo).all(-1) & (hi - lo <= 1e-12 * np.maximum(np.abs(hi), 1e-300)).all(-1)
    var = np.where(one[:, None], lo, np.nan) ** 2  # (N, m)
    if mm.tangent:
        return 2.0 * var.mean(-1)
    if mm.frame == "needle":
        same = np.where(np.ptp(var, axis=-1) == 0, var[:, 0], np.nan)
        return same * len(comps)
    return var.sum(-1)


def add_data_hints(result: EMResult, problem) -> None:
    """Where a trial fails at the singularity in the first EM iterations, say what in the data is the likely
    cause (in place, on its reason): position samples marked valid that are exactly zero (a tracker's rows
    of zeros for a lost tip), or a path that runs far from the model's +z (an insertion along another
    axis: the bevel-tip models are singular at beta = +-90 deg)."""
    early = np.array([s == "singular" and (" (EM iteration 1)" in r or " (EM iteration 2)" in r)
                      for s, r in zip(result.status, result.reason)])
    if not early.any():
        return
    reasons = result.reason.tolist()
    for ch in problem.channels.values():
        if ch.sensor_type != "position" or not {"x", "y", "z"} <= set(ch.names):
            continue
        xyz = ch.value[..., [list(ch.names).index(a) for a in "xyz"]]
        zero = (ch.valid & (xyz == 0).all(-1)).sum(1)
        for i in np.nonzero(early)[0]:
            ok = np.nonzero(ch.valid[i] & ~(xyz[i] == 0).all(-1))[0]
            hints = []
            if zero[i] > 1:
                hints.append(f"{int(zero[i])} samples of {ch.name} are exactly zero and marked valid: lost samples? "
                             "(a CSV mapping's missing: {zero_rows: true})")
            if ok.size > 1:
                d = xyz[i, ok[-1]] - xyz[i, ok[0]]
                ang = float(np.degrees(np.arccos(np.clip(d[2] / max(np.linalg.norm(d), 1e-300), -1, 1))))
                if ang > 60.0:
                    hints.append(f"the {ch.name} path runs {ang:.0f} deg from the model's +z: express the trial in "
                                 "its own frame (a CSV mapping's frame: {reference: ...})")
            if hints:
                reasons[i] = f"{reasons[i]}; in the data: {'; '.join(hints)}"
    result.reason = np.array(reasons)


def _run_models(names, workers, run, systems, out, progress) -> None:
    children = {}
    if workers > 1 and len(names) > 1:  # (forked: only where platform.fork_available())
        ctx = mp.get_context("fork")
        queue = ctx.Queue()
        for name in names[1 : workers]:
            conn, child_conn = ctx.Pipe(duplex=False)

            def child(name=name, child_conn=child_conn):
                try:
                    res = run(name, lambda k, n, _m=name: queue.put((f"EM {_m}", k, n)))
                    child_conn.send(("ok", res))
                except BaseException as e:  # noqa: BLE001  (reported in the parent)
                    child_conn.send(("error", repr(e)))
                finally:
                    child_conn.close()

            p = ctx.Process(target=child, daemon=True)
            p.start()
            children[name] = (p, conn)

        def drain():
            while True:
                try:
                    msg = queue.get_nowait()
                except Exception:  # noqa: BLE001  (queue.Empty)
                    return
                if progress is not None:
                    progress(*msg)
    else:
        def drain():
            return None

    try:
        for name in names:
            if name in children:
                continue
            def cb(k, n, _m=name):
                if progress is not None:
                    progress(f"EM {_m}", k, n)
                drain()
            res, idf, secs, rob = run(name, cb)
            out.fits[name] = ModelFit(name, systems[name], res, secs, idf, rob)
        for name, (p, conn) in children.items():
            while not conn.poll(0.2):
                drain()
                if not p.is_alive() and not conn.poll(0.0):
                    raise RuntimeError(f"the EM of model {name!r} stopped without a result (exit code {p.exitcode})")
            kind, payload = conn.recv()
            p.join()
            drain()
            if kind != "ok":
                raise RuntimeError(f"the EM of model {name!r} failed: {payload}")
            res, idf, secs, rob = payload
            out.fits[name] = ModelFit(name, systems[name], res, secs, idf, rob)
    finally:
        for p, _ in children.values():
            if p.is_alive():
                p.terminate()


def take_fit(out: FitOutput, trials: Trials, idx) -> FitOutput:
    """The fits of the trials ``idx`` of ``out`` as the fit of ``trials`` (those trials, in that order):
    every trial's EM is its own (no parameter is shared between trials), so a subset of one fit over all
    trials is the fit of the subset, up to when the shared E-step re-linearised (below EM's tolerance);
    the pooled identifiability is recomputed from the subset's information. ``needle crossval`` fits every
    trial once this way instead of once per fold."""
    import dataclasses as dc

    idx = np.asarray(idx, dtype=np.int64)
    sub = FitOutput(trials)
    for name, mf in out.fits.items():
        S, r = mf.system, mf.result
        system = dc.replace(S, dm=S.dm.take(idx), meas=[m.take(idx) for m in S.meas], m0=S.m0[idx])
        res = dc.replace(r, **{f.name: _rows(getattr(r, f.name), idx, r.x0.shape[0]) for f in dc.fields(r)
                               if f.name not in ("R", "history")},
                         R=[x[idx] for x in r.R], history={k: v[idx] for k, v in r.history.items()})
        if getattr(r, "roll_flipped", None) is not None:
            res.roll_flipped = np.asarray(r.roll_flipped)[idx]
        system, res = _trim_ticks(system, res, len(trials.truth.time))
        idf = None
        if mf.identifiability is not None:
            idf = take_trials(mf.identifiability, idx, identify_options(trials.cfg.fit))
        rob = None
        if mf.robust is not None:
            rb = mf.robust
            rob = RobustInfo([None if w is None else w[idx] for w in rb.weights], rb.dof, rb.passes[idx], rb.last_change[idx])
        sub.fits[name] = ModelFit(name, system, res, mf.seconds, idf, rob)
    return sub


def _trim_ticks(S: System, res: EMResult, T: int) -> tuple[System, EMResult]:
    """The fit on the first ``T`` grid steps only (ticks ``< T``): the subset's own time axis when the
    trials left out ran longer (their ticks lie past its end; the subset has no samples there)."""
    import dataclasses as dc

    dm = S.dm
    keep = int(np.searchsorted(dm.ticks, T))
    if keep >= len(dm.ticks):
        return S, res
    out = object.__new__(type(dm))
    out.__dict__.update(dm.__dict__)
    out.ticks = dm.ticks[:keep]
    out.dt = dm.dt[: keep - 1]
    out.sub_dt = dm.sub_dt[: keep - 1]
    out.sub_u = dm.sub_u[:, : keep - 1]
    K1 = len(dm.ticks)
    cut = {f.name: getattr(res, f.name)[:, :keep] for f in dc.fields(res)
           if isinstance(getattr(res, f.name), np.ndarray) and getattr(res, f.name).ndim >= 2
           and getattr(res, f.name).shape[1] == K1}
    trimmed = dc.replace(res, **cut)
    if getattr(res, "roll_flipped", None) is not None:
        trimmed.roll_flipped = res.roll_flipped
    return dc.replace(S, dm=out), trimmed


def _rows(v, idx: np.ndarray, N: int):
    """Rows ``idx`` of a per-trial array ``(N, ...)``; anything else as it is."""
    return v[idx] if isinstance(v, np.ndarray) and v.ndim and v.shape[0] == N else v


# ---------------------------------------------------------------------------------------------- the file
def fit_tree(out: FitOutput) -> Group:
    """The fit file's content (docs/reference/fit-file.md)."""
    tr = out.trials
    cfg, truth = tr.cfg, tr.truth
    fit = cfg.fit if cfg.fit is not None else FitSettings()
    model0 = truth.model
    N, T = truth.states.shape[:2]
    root = Group(attrs=root_attrs(tr.text, cfg.runs.seed, {
        "format": FIT_FORMAT, "version": FIT_VERSION, "name": cfg.name, "source": str(tr.source),
        "trials_from": "simulation" if tr.simulated else "replay", "model": model0.registered_name,
        "length_unit": model0.length_unit, "runs": N, "dt": float(truth.time[1] - truth.time[0]) if T > 1 else 0.0,
        "models": list(out.fits), "repeats": fit.repeats,
    }))
    root.data["time"] = truth.time
    inputs = Group()
    for k, v in truth.input_dict().items():
        inputs.data[k] = np.ascontiguousarray(v[..., 0] if v.shape[-1] == 1 else v)
        inputs.dataset_attrs[k] = {"unit": model0.input_units[k]}
    if truth.case is not None:
        inputs.data["case"] = truth.case
        inputs.attrs["case_labels"] = truth.case_labels
    root.data["inputs"] = inputs
    tg = Group(attrs={"names": model0.state_names, "units": model0.state_units, "kind": truth.truth_kind})
    if tr.simulated:
        tg.data["state"] = truth.states
        tg.data["params"] = Group(data={k: np.ascontiguousarray(np.asarray(v)[:, 0]) for k, v in truth.params.items()})
        tg.data["status"] = truth.status
        tg.data["reason"] = truth.reason
        qstd = cfg.process_noise.std
        tg.data["q_std"] = np.array([qstd.get(s, 0.0) for s in model0.state_names])
        sig = Group()
        for s in tr.sensors:
            sig.data[s.name] = np.broadcast_to(np.asarray(getattr(s.settings, "sigma", 0.0), dtype=float),
                                               (len(s.channel_names),)).copy()
        tg.data["sigma"] = sig
    if truth.param_case is not None:
        tg.data["param_case"] = truth.param_case
        tg.attrs["param_case_labels"] = truth.param_case_labels
    if truth.trial_ids is not None:
        tg.data["trial_id"] = np.array(truth.trial_ids)
    meta = design_columns(truth, cfg)
    if meta is not None:  # an addition older readers ignore (no version bump)
        tg.data["meta"] = Group(data=meta["columns"], attrs={"design_factors": meta["design_factors"]})
    root.data["truth"] = tg
    meas = Group()
    for name, st in tr.streams.items():
        meas.data[name] = Group(data={"t": st.t, "index": st.index, "value": st.value, "valid": st.valid},
                                attrs={"names": st.names, "units": st.units, "type": st.attrs.get("type", "")})
    root.data["measurements"] = meas
    fits = Group()
    for name, mf in out.fits.items():
        fits.data[name] = _model_group(mf, fit)
    root.data["fit"] = fits
    return root


def _model_group(mf: ModelFit, fit: FitSettings) -> Group:
    S, r = mf.system, mf.result
    dm = S.dm
    held = [c for c in fit_augment(type(dm.model), fit.constants) if c in fit.hold]  # constants held at their initial value
    consts = dm.augment + tuple(held)
    g = Group(attrs={
        "model": mf.name, "names": dm.names, "units": dm.units, "constants": consts,
        "q_states": [dm.names[i] for i in S.q_index], "channels": [m.name for m in S.meas],
        "held": [h for h in fit.hold if h in dm.names or h in fit_augment(type(dm.model), fit.constants)],
        "hold_reason": fit.hold_reason,
        "max_iter": fit.em.max_iter, "tol": fit.em.tol, "seconds": mf.seconds,
        "singular_reason": dm.model.singular_reason,
        "sensor_states": list(dm.sensor_states), "sensor_state_channels": [m.name for m in S.meas if m.offset_index is not None],
        "sensor_state_tau": [float(1.0 / d) if d > 0 else float("inf") for d in dm.decay],
    })
    g.data["ticks"] = dm.ticks
    g.data["constant"] = Group(data={
        **{c: r.x0[:, dm.nx + i] for i, c in enumerate(dm.augment)},
        **{c: np.broadcast_to(np.asarray(dm.params[c], dtype=float), (r.x0.shape[0],)).copy() for c in held}})
    g.attrs["constant_units"] = [dm.units[dm.nx + i] for i in range(len(dm.augment))] + [param_unit(dm.model, c) for c in held]
    g.data["x0"] = r.x0
    g.data["x0_guess"] = S.m0
    g.data["Q"] = r.Qc
    g.data["Q0"] = S.Qc
    Rg = Group()
    for mm, Rj, R0 in zip(S.meas, r.R, S.R):
        Rg.data[mm.name] = Rj
        Rg.data[f"{mm.name}_guess"] = R0
        Rg.dataset_attrs[mm.name] = {"coordinates": channel_coordinates(mm)}
        floor = S.floors[S.meas.index(mm)]
        if floor is not None:  # additions older readers ignore (no version bump)
            Rg.attrs[f"{mm.name}_floor"] = float(floor)
        if mm.scale is not None:
            Rg.attrs[f"{mm.name}_per_sample"] = ("sample i has diag(s_i) R diag(s_i), s_i its recorded sigma over "
                                                 "the channel's nominal sigma")
    needle = [mm for mm in S.meas if mm.frame == "needle"]
    if needle:  # group attributes (what from_fit reads): channels in needle coordinates, their across axes
        Rg.attrs["needle_frame"] = [mm.name for mm in needle]
        Rg.attrs["needle_axis"] = [AXES[mm.frame_axis] for mm in needle]
    g.data["R"] = Rg
    g.data["state"] = r.m
    g.data["var" if fit.store == "diag" else "cov"] = (np.diagonal(r.P, axis1=-2, axis2=-1).copy()
                                                     if fit.store == "diag" else r.P)
    g.data["filtered"] = r.filtered
    g.data["ekf_state"] = r.ekf
    for k in ("status", "reason", "iterations", "estep_passes", "ll_decreases", "ll_worst_drop", "floor_hits",
              "repairs", "extrapolations", "rejections"):
        v = getattr(r, k)
        if v is not None:
            g.data[k] = v
    g.data["history"] = Group(data={k.replace("/", "_"): v for k, v in r.history.items()})
    if mf.robust is not None:  # Student-t channels: the samples' final weights
        rb = mf.robust
        g.data["weights"] = Group(
            data={mm.name: w for mm, w in zip(S.meas, rb.weights) if w is not None},
            attrs={"student_t": [mm.name for mm, w in zip(S.meas, rb.weights) if w is not None],
                   "dof": [float(d) for d in rb.dof if d is not None], "reweight_tol": fit.em.reweight_tol})
        g.data["reweight_passes"] = rb.passes
        g.data["reweight_change"] = rb.last_change
    flipped = getattr(r, "roll_flipped", None)
    if flipped is not None and dm.model.curvature_roll_state is not None and dm.model.curvature_param in consts:
        g.data["roll_flipped"] = np.asarray(flipped, dtype=bool)
        g.attrs["roll_state"] = dm.model.curvature_roll_state
    if mf.identifiability is not None:
        g.data["identifiability"] = identifiability_group(mf.identifiability, fit)
    return g


def channel_coordinates(mm) -> str:
    """What the components of a channel's R are (the fit file's ``R/<channel>`` attribute ``coordinates``;
    ``from_fit`` reads it back)."""
    if mm.tangent:
        return "tangent plane (2 components across the direction)"
    if mm.frame == "needle":
        return f"needle frame (along the tangent, across_1, across_2; across axis {AXES[mm.frame_axis]})"
    return "components " + ", ".join(mm.names)


def identifiability_group(idf: Identifiability, fit: FitSettings) -> Group:
    """``/fit/<model>/identifiability`` (docs/reference/fit-file.md)."""
    strs = {k: getattr(idf, k).astype(str) for k in ("verdict", "reason", "pooled_verdict", "pooled_reason",
                                                       "group_verdict", "group_reason")}
    return Group(
        data={
            "estimate": idf.estimate, "se": idf.se, "rse": idf.rse, "hessian": idf.hessian, "step": idf.theta_step,
            "decade": idf.decade, "verdict": strs["verdict"], "reason": strs["reason"],
            "used": idf.used, "loglik": idf.loglik, "pooled_se": idf.pooled_se, "pooled_rse": idf.pooled_rse,
            "pooled_verdict": strs["pooled_verdict"], "pooled_reason": strs["pooled_reason"],
            # additions older readers ignore: the recovery check and the design groups
            "truth": idf.truth, "z": idf.z, "along": idf.along, "floored": idf.floored, "newton": idf.newton,
            "group": idf.group, "group_trials": idf.group_trials, "group_estimate": idf.group_estimate,
            "group_se": idf.group_se, "group_rse": idf.group_rse, "group_truth": idf.group_truth, "group_z": idf.group_z,
            "group_newton": idf.group_newton, "group_newton_z": idf.group_newton_z,
            "group_verdict": strs["group_verdict"], "group_reason": strs["group_reason"],
        },
        attrs={"quantities": idf.names, "units": [q.unit for q in idf.quantities],
               "kinds": [q.kind for q in idf.quantities], "rse_max": fit.identify.rse_max, "nats": fit.identify.nats,
               "z_max": fit.identify.z_max, "group_labels": list(idf.group_labels),
               "parameters": "constants as they are; Q blocks and R_j by a log scale (tr scales by exp)"},
    )


def design_groups(truth: Truth, cfg: ExperimentConfig) -> tuple[np.ndarray, list[str]]:
    """The trials' design groups, ``(group (N,), labels)``: the combinations of the design factors
    (``fit.design.group_by`` of the config, else the trials' ``design_factors``: a real export's speed), else
    the parameter cases of a simulated study (the magnetic needle EM paper: its field strengths), else one group of every trial.
    Identifiability pools the information of one group's trials only."""
    N = truth.states.shape[0]
    meta = design_columns(truth, cfg)
    want = list(cfg.fit.design.group_by) if cfg.fit is not None else []
    keys = [k for k in (want or (meta["design_factors"] if meta else [])) if meta and k in meta["columns"]]
    if keys:
        def word(v) -> str:
            return f"{v:g}" if isinstance(v, (float, np.floating)) else str(v)

        combos = [", ".join(f"{k}={word(meta['columns'][k][i])}" for k in keys) for i in range(N)]
        order = sorted(range(N), key=lambda i: [_sort_key(meta["columns"][k][i]) for k in keys])
        labels = list(dict.fromkeys(combos[i] for i in order))
        return np.array([labels.index(c) for c in combos], dtype=np.int64), labels
    if truth.param_case is not None:
        labels = list(truth.param_case_labels or [f"case {i}" for i in range(int(np.max(truth.param_case)) + 1)])
        return np.asarray(truth.param_case, dtype=np.int64), [str(x) for x in labels]
    return np.zeros(N, dtype=np.int64), ["all trials"]


def _sort_key(v):
    return (0, float(v), "") if isinstance(v, (int, float, np.integer, np.floating)) and np.isfinite(v) else (1, 0.0, str(v))


def design_columns(truth: Truth, cfg: ExperimentConfig) -> dict | None:
    """The trials' metadata for the fit file's ``/truth/meta``: from the logs (replay), or for simulated
    trials from parameter-case labels written ``name=value, ...`` (``duty_cycle=0.25``); None without."""
    if truth.trial_meta is not None and truth.trial_meta.get("columns"):
        return truth.trial_meta
    pc = getattr(cfg.model, "param_cases", None)
    if pc is None or pc.labels is None or truth.param_case is None:
        return None
    from needlecli.io.csv_layout import factors_from_label

    per_case = [factors_from_label(lbl) for lbl in pc.labels]
    keys = [k for k in per_case[0] if all(k in c for c in per_case)] if per_case else []
    if not keys:
        return None
    cols = {}
    for k in keys:
        vals = [per_case[int(i)][k] for i in truth.param_case]
        cols[k] = (np.array(vals, dtype=float) if all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in vals)
                   else np.array([str(v) for v in vals]))
    return {"columns": cols, "design_factors": keys}


def default_fit_output(cfg: ExperimentConfig) -> Path:
    return Path("results") / f"{cfg.name}_fit.h5"
