"""``needle crossval``: EM-tuned observers judged on trials their fit never saw, beside the hand-tuned ones.

For each fold, ``needle fit-em``'s EM fits the config's ``fit:`` section on the training trials (measurements
only, never the truth; each trial's EM is its own, so every trial that trains some fold is fitted once and
each fold takes its training trials' fits, with their identifiability pooled anew), writes
``DIR/folds/fold<k>_fit.h5``, and the held-out trials are replayed through
every observer of the config as it is (hand-tuned) and through a copy of each observer named with
``--observer`` that takes its process noise, measurement noise and constants from that fit
(``<name>_em``, :mod:`needlecli.experiments.config.from_fit`, ``pick: median``); every observer of a fold starts
from the same initial estimate (the first hand-tuned observer's, as in ``needle compare``), so the
tuned and the hand-tuned one differ only in their parameters. Each fold's results are
``DIR/folds/fold<k>.h5``; the tables pool the held-out errors of all folds.

Trials are the replayed logs of a ``source:`` config; a simulated config is simulated once and its runs
become the trials (a log in ``DIR``). Folds: ``k`` folds of the trials (whole groups when ``group_by``
is given: leave-group-out), or leave-one-out, optionally ``within`` a group (the training trials are the
other trials of the held-out one's group: "all but one trial of a recording day"). A group is a trial's
metadata value (``group_by: run``) or, with ``id~REGEX``, the first match of the regular expression in
its id (``id~^[^-]+``: the recording day of ``9_18_15-1mm-Trial3``).

**Two parts of a held-out error.** A prediction from the start errs by the start's pose and by the model
(its curvature, its noise-free path). So that the two are told apart, each observer named to be tuned and
its tuned copy are also run from the held-out trial's own pose at chosen depths (``from_depths``, in the model's
length unit), with no measurement after it (:func:`pose_predictions`): the pose is the recorded one
(``pose_from: [truth]``, the trial's truth at its first sample at or past the depth) or another observer's
estimate there (``NAME``, e.g. a smoother tuned by the fold's fit, whose orientation comes from the
positions), or each of several. The error from the pose, by the distance predicted ahead, is the model's part; beside the
error from the start over the same distance, the rest is the start's pose (``/crossval/from_pose`` of each
fold, the table ``from_pose`` of :mod:`needlecli.reports.crossval`).
"""

from __future__ import annotations

import copy
import dataclasses
import re
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import yaml

from needlecli.errors import ConfigError, DataError, shown
from needlecli.io.tree import Group

if TYPE_CHECKING:
    from needlecli.experiments.config.types import ExperimentConfig

#: inserted depths (model length unit) from whose pose ``needle crossval`` also predicts, by default
FROM_DEPTHS = (0.0, 20.0, 40.0)
#: at most this many time steps of each prediction from a pose are kept (every k-th where the truth exists)
POSE_STEPS = 2000

#: keys of a simulated config that a replay of its runs does not have
_SIMULATION_ONLY = ("inputs", "sensors", "tissue", "stop", "process_noise", "control")


@dataclass
class Fold:
    index: int
    train: list[str]
    test: list[str]


@dataclass
class CrossvalResult:
    folds: list[Fold]
    results: list[Path]  # per fold, the held-out trials' results file
    fits: list[Path]  # per fold, the training fit file
    tuned: dict[str, str]  # tuned observer -> the hand-tuned one it copies
    observers: list[str]
    model: str
    out_dir: Path


def group_of(trial_id: str, meta: dict, spec: str | None, where: str = "") -> str:
    """A trial's group under ``spec``: ``id~REGEX`` (first match in the id) or a metadata key (``where``:
    the file the trials come from, for the message when a trial lacks it)."""
    if spec is None:
        return trial_id
    if spec.startswith("id~"):
        m = re.search(spec[3:], trial_id)
        return m.group(0) if m else trial_id
    if spec not in meta:
        where = f" of {shown(meta['log'])}" if isinstance(meta.get("log"), str) else f" of {shown(where)}" if where else ""
        raise ConfigError("--group-by", (), f"trial {trial_id!r}{where} has no metadata {spec!r}; it has "
                          f"{', '.join(sorted(k for k in meta if k != 'log')) or 'none'} (or use id~REGEX)")
    return str(meta[spec])


def make_folds(ids: list[str], groups: list[str], *, k: int | None, leave_one_out: bool, within: bool,
               k_given: bool = True) -> list[Fold]:
    """The folds: leave-one-out (training: every other trial, or with ``within`` the other trials of its
    group), or ``k`` folds of whole groups (round-robin over the groups in order of appearance). A problem
    names the option that was given (``k_given``: whether ``k`` came from ``--folds`` or is its default)."""
    if leave_one_out:
        out = []
        for i, t in enumerate(ids):
            train = [u for j, u in enumerate(ids) if j != i and (not within or groups[j] == groups[i])]
            if not train and within:
                raise ConfigError("--within", (), f"trial {t!r} is alone in its group {groups[i]!r}: nothing to fit on")
            if not train:
                raise ConfigError("--leave-one-out", (), f"trial {t!r} is the only trial: nothing to fit on when it "
                                  "is held out")
            out.append(Fold(i, train, [t]))
        return out
    order = list(dict.fromkeys(groups))
    option = "--folds" if k_given else f"--folds (default {k}, not given)"
    if k is None or k < 2:
        raise ConfigError(option, (), "needs at least 2 folds")
    what = "group(s) of trials" if len(set(groups)) < len(groups) else "trial(s)"
    if len(order) < 2:
        raise ConfigError(option, (), f"{len(order)} {what}: folds need at least 2")
    if k > len(order):
        raise ConfigError(option, (), f"{k} folds for {len(order)} {what}: give --folds {len(order)} or fewer"
                          + (" (or --leave-one-out)" if not k_given else ""))
    fold_of = {g: i % k for i, g in enumerate(order)}
    return [Fold(f, [t for t, g in zip(ids, groups) if fold_of[g] != f], [t for t, g in zip(ids, groups) if fold_of[g] == f])
            for f in range(k)]


def _replay_base(cfg_path: Path, data: dict, out_dir: Path, progress):
    """The replay config every fold derives from (absolute log paths), the trials ``(id, meta)``, the
    config's folder and, for a simulated config, the log of its runs still to be written (at
    ``base["source"]["logs"][0]``, once the folds are known to be possible)."""
    from needlecli.io.logs import read_log

    base_dir = cfg_path.parent
    if data.get("source"):
        logs = [str((base_dir / p).resolve()) if not Path(p).is_absolute() else p for p in data["source"]["logs"]]
        wanted = data["source"].get("trials")
        trials = []
        for p in logs:
            for tr in read_log(p).trials:
                trials.append((tr.id, {**tr.meta, "log": p}))
        if wanted:
            have = {t for t, _ in trials}
            missing = [t for t in wanted if t not in have]
            if missing:
                raise ConfigError(str(cfg_path), ("source", "trials"), f"no trial {missing[0]!r} in the logs")
            meta = dict(trials)
            trials = [(t, meta[t]) for t in dict.fromkeys(wanted)]
        base = copy.deepcopy(data)
        base["source"] = {**base["source"], "logs": logs}
        return base, trials, base_dir, None
    # a simulated config: simulate once, its runs become the trials of a log
    from needlecli.experiments.config.load import load_config
    from needlecli.experiments.simulation.runner import run_experiment
    from needlecli.io.logs import log_from_results
    from needlecli.io.results import read_results

    sim = copy.deepcopy(data)
    sim["observers"] = []
    cfg, text = load_config(cfg_path, text=yaml.safe_dump(sim, sort_keys=False))
    res_path = run_experiment(cfg, text, out=out_dir / "trials.h5", base_dir=base_dir,
                              progress=progress).path
    log = log_from_results(read_results(res_path), description=f"{cfg.name}: the simulated trials of crossval",
                           prefix="run")
    log_path = out_dir / "trials.log.h5"
    base = {k: v for k, v in copy.deepcopy(data).items() if k not in _SIMULATION_ONLY}
    model = dict(base.get("model") or {})
    for k in ("param_cases", "param_std", "initial_std"):
        model.pop(k, None)
    base["model"] = model
    base["source"] = {"logs": [str(log_path.resolve())]}
    return base, [(t.id, dict(t.meta)) for t in log.trials], base_dir, log


def _tuned_copy(obs: dict, fit_file: Path, model: str) -> dict:
    """A copy of a hand-tuned observer's settings with its parameters from the fit instead."""
    out = {k: v for k, v in copy.deepcopy(obs).items() if k not in ("q", "params", "from_fit")}
    meas = out.get("measurements")
    if isinstance(meas, dict):
        out["measurements"] = {ch: {k: v for k, v in (spec or {}).items() if k != "sigma"} for ch, spec in meas.items()}
    out["name"] = f"{obs.get('name') or obs['type']}_em"
    out["from_fit"] = {"file": str(Path(fit_file).resolve()), "model": model, "pick": "median"}  # a relative --out too
    return out


def crossval(
    config: str | Path,
    *,
    observers: list[str],
    model: str | None = None,
    folds: int | None = None,
    leave_one_out: bool = False,
    group_by: str | None = None,
    within: bool = False,
    out_dir: str | Path | None = None,
    overrides: list[str] | None = None,
    progress: Callable[[str, int, int], None] | None = None,
    from_depths: tuple[float, ...] | list[float] = FROM_DEPTHS,
    pose_from: tuple[str, ...] | list[str] = ("truth",),
) -> CrossvalResult:
    """Cross-validate EM-tuned copies of ``observers`` against the config's hand-tuned observers (module
    docstring). ``folds``: None is 5 (an error then says the default was taken); with ``from_depths``, also predict from
    each held-out trial's pose at those depths (``pose_from``: ``truth``, the recorded pose, or observers'
    estimates; :func:`pose_predictions`). Every option is checked
    before anything is read, every setting before the first fit, the folds before anything is written;
    everything is written into ``out_dir`` by :func:`~needlecli.io.atomic.atomic_path`, so that the
    command's set of outputs (:func:`~needlecli.io.atomic.output_set`) is renamed into place when complete."""
    from needlecli.experiments.config.load import load_config
    from needlecli.experiments.config.overrides import apply_overrides
    from needlecli.experiments.studies.fit import fit_tree, fit_trials, load_trials, take_fit
    from needlecli.io.atomic import check_output_dir, write_text_atomic
    from needlecli.io.logs import write_log
    from needlecli.io.results import write_atomic
    from needlecli.io.yamlfile import parse_yaml, read_text

    check_args(leave_one_out, within, folds, group_by)
    cfg_path = Path(config)
    source = str(cfg_path)
    text = read_text(cfg_path)  # a config: a regular file of YAML text (a results file or a log is named as such)
    data = parse_yaml(text, source)
    apply_overrides(data, overrides, source)
    cfg0, _ = load_config(cfg_path, text=yaml.safe_dump(data, sort_keys=False))  # the whole config, checked
    if cfg0.fit is None:
        raise ConfigError(source, ("fit",), "required key is missing: crossval fits the fit section on each fold")
    raw_obs = list(data.get("observers") or [])
    names = [o.get("name") or o.get("type") for o in raw_obs]
    for o in observers:
        if o not in names:
            raise ConfigError("--observer", (), f"no observer {o!r} in {source}; observers: {', '.join(names) or 'none'}")
    fit_model = model or (cfg0.fit.models[0] if len(cfg0.fit.models) == 1 else None)
    if fit_model is None:
        raise ConfigError("--model", (), f"the fit section fits {', '.join(cfg0.fit.models)}: name the model to tune with")
    if fit_model not in cfg0.fit.models:
        raise ConfigError("--model", (), f"{fit_model!r} is not one of the fit section's models ({', '.join(cfg0.fit.models)})")
    depths = check_pose_args(from_depths, pose_from, names + [f"{o}_em" for o in observers])
    pose_from = tuple(dict.fromkeys(pose_from))
    out = Path(out_dir) if out_dir is not None else Path("results") / f"{cfg0.name}_crossval"
    check_output_dir(out, what="the cross-validation")
    # the folds are checked before anything is written (a simulated config's runs are simulated first, in
    # memory and in the command's set of outputs, which is renamed into place only when all of it succeeded)
    base, trials, base_dir, sim_log = _replay_base(cfg_path, data, out, progress)
    ids = [t for t, _ in trials]
    groups = [group_of(t, m, group_by, source) for t, m in trials]
    plan = make_folds(ids, groups, k=None if leave_one_out else (folds if folds is not None else 5),
                      leave_one_out=leave_one_out, within=within, k_given=folds is not None)
    if sim_log is not None:
        write_log(Path(base["source"]["logs"][0]), sim_log)
    results, fits = [], []
    tuned = {f"{o}_em": o for o in observers}
    group_of_id = dict(zip(ids, groups))
    # every trial's EM is its own: fit each training trial once, and give each fold its training trials' fits
    fitted = [t for t in ids if any(t in fd.train for fd in plan)]
    every = copy.deepcopy(base)
    every["source"]["trials"] = fitted
    every["observers"] = []
    every_path = out / "folds" / "all_train.yaml"
    write_text_atomic(every_path, yaml.safe_dump(every, sort_keys=False))
    em_cb = (lambda ph, k, n: progress(f"EM of {len(fitted)} training trials", k, n)) if progress else None
    fo_all = fit_trials(load_trials(every_path), models=[fit_model], progress=em_cb)
    for fd in plan:
        train = copy.deepcopy(base)
        train["source"]["trials"] = fd.train
        train["observers"] = []
        train_path = out / "folds" / f"fold{fd.index}_train.yaml"
        write_text_atomic(train_path, yaml.safe_dump(train, sort_keys=False))
        fo = take_fit(fo_all, load_trials(train_path), [fitted.index(t) for t in fd.train])
        fit_path = write_atomic(out / "folds" / f"fold{fd.index}_fit.h5", fit_tree(fo))
        fits.append(fit_path)
        mf = fo.fits[fit_model]
        ok = mf.result.status == "ok"
        medians, ses = [], []
        for i, c in enumerate(mf.system.dm.augment):
            v = mf.result.x0[ok, mf.system.dm.nx + i]
            se = np.nan
            if mf.identifiability is not None and c in mf.identifiability.names:
                se = float(mf.identifiability.pooled_se[mf.identifiability.names.index(c)])
            medians.append(float(np.median(v)) if v.size else np.nan)
            ses.append(se)
        constants = Group(data={"name": np.array(list(mf.system.dm.augment), dtype=object),
                                "median": np.array(medians, dtype=float), "se": np.array(ses, dtype=float)},
                          attrs={"trials_ok": int(ok.sum()), "trials": len(ok)})
        test = copy.deepcopy(base)
        test["source"]["trials"] = fd.test
        test["observers"] = raw_obs + [_tuned_copy(o, fit_path, fit_model) for o in raw_obs
                                       if (o.get("name") or o.get("type")) in observers]
        test_text = yaml.safe_dump(test, sort_keys=False)
        tcfg, ttext = load_config(out / "folds" / f"fold{fd.index}.yaml", text=test_text)
        fold = Group(data={"constants": constants},
                     attrs={"fold": fd.index, "model": fit_model, "train": list(fd.train), "test": list(fd.test),
                            "tuned": list(tuned), "group_by": group_by or ""})
        if group_by:
            fold.data["group"] = np.array([group_of_id[t] for t in fd.test], dtype=object)
        results.append(_run_common_start(tcfg, ttext, out / "folds" / f"fold{fd.index}.h5", base_dir, progress, fd,
                                         fold, depths=depths, pose_from=pose_from, predict=[*observers, *tuned]))
    return CrossvalResult(plan, results, fits, tuned, [n for n in names] + list(tuned), fit_model, out)


def _run_common_start(cfg: ExperimentConfig, text, path: Path, base_dir: Path, progress, fd: Fold,
                      fold: Group, depths: tuple[float, ...] = (), pose_from: tuple[str, ...] = ("truth",),
                      predict: list[str] | None = None) -> Path:
    """Replay a fold's held-out trials through every observer from one common start; write its results,
    with the fold's ``/crossval`` group (``fold``: which trials trained and which were held out, the tuned
    observers, the held-out trials' groups, the fitted constants)."""
    from needlecli.experiments.simulation import components
    from needlecli.experiments.simulation.replay import replay_truth
    from needlecli.experiments.simulation.runner import build_problem, results_tree, shared_start
    from needlecli.experiments.simulation.truth import stream
    from needlecli.io.results import write_atomic

    truth, sensors, streams = replay_truth(cfg, base_dir)
    problem = build_problem(cfg, truth, sensors, streams)
    seed = cfg.runs.seed
    shared = shared_start(cfg, problem)  # runs.common_start: by default the first observer's that gives one
    estimates = {}
    for o in cfg.observers:  # each guarded and checked: a failure ends the study before this fold is written
        obs = components.build_observer(o)
        cb = (lambda k, n, _n=obs.name: progress(f"fold {fd.index + 1}: {_n}", k, n)) if progress else None
        estimates[obs.name] = components.run_observer(obs, o, shared.problem_of(obs.name, problem),
                                                      stream(seed, f"observer/{obs.name}"), progress=cb)
    if depths:  # the held-out trials again, from their pose at each depth (the model's part of the error)
        fold.data["from_pose"] = pose_predictions(cfg, problem, truth.states, estimates, depths=depths,
                                                  pose_from=tuple(pose_from), predict=list(predict or []), seed=seed,
                                                  progress=progress)
    tree = results_tree(cfg, text, truth, streams, estimates, sensors, starts=shared.starts())
    tree.data["crossval"] = fold
    return write_atomic(path, tree)


def check_args(leave_one_out: bool, within: bool, folds: int | None, group_by: str | None = None) -> None:
    """The options of ``needle crossval`` alone, before anything is read or written: each problem names the
    option given."""
    if within and not leave_one_out:
        raise ConfigError("--within", (), "is for --leave-one-out (the training trials: the others of the held-out one's group)")
    if folds is not None and leave_one_out:
        raise ConfigError("--folds", (), "and --leave-one-out both given: give one of them")
    if folds is not None and folds < 2:
        raise ConfigError("--folds", (), f"{folds}: needs at least 2 folds")
    if group_by is not None:
        if not group_by.strip():
            raise ConfigError("--group-by", (), "is empty: give a metadata key of the trials, or id~REGEX")
        if group_by.startswith("id~"):
            if not group_by[3:]:
                raise ConfigError("--group-by", (), "id~ needs a regular expression after it (e.g. 'id~^[^-]+')")
            try:
                re.compile(group_by[3:])
            except re.error as e:
                raise ConfigError("--group-by", (), f"{group_by[3:]!r} is not a regular expression: {e}") from None


# ---------------------------------------------------------------------------------------------- from a pose
def check_pose_args(from_depths, pose_from, names: list[str]) -> tuple[float, ...]:
    """The start depths (sorted, unique, finite and non-negative) and the pose sources (each ``truth`` or
    one of ``names``, the observers of every fold), checked before the first fit."""
    depths = tuple(sorted({float(d) for d in from_depths}))
    bad = [d for d in depths if not np.isfinite(d) or d < 0]
    if bad:
        raise ConfigError("--from-depths", (), f"{bad[0]:g} is not a depth: give non-negative numbers, e.g. 0,20,40")
    for src in pose_from:
        if src != "truth" and src not in names:
            raise ConfigError("--pose-from", (), f"{src!r} is neither 'truth' (the recorded pose) nor an observer of "
                              f"the folds ({', '.join(names)})")
    return depths


def pose_starts(problem, source: np.ndarray, depths: tuple[float, ...]) -> np.ndarray:
    """``(N, D)`` grid index of each run's first step at or past each depth where the truth and the pose
    ``source (N, T, n)`` are both finite (the recorded pose of a replay exists at its frames only); -1
    where the run never gets there."""
    have = np.isfinite(source).all(-1)  # (N, T)
    out = np.full((problem.n_runs, len(depths)), -1, dtype=np.int64)
    for j, d in enumerate(depths):
        ok = have & (problem.depth >= d - 1e-9)
        first = np.argmax(ok, axis=1)
        out[:, j] = np.where(ok.any(axis=1), first, -1)
    return out


def shifted_problem(problem, runs: np.ndarray, starts: np.ndarray, start):
    """The problem of predictions that begin at grid step ``starts[b]`` of run ``runs[b]`` (both ``(B,)``):
    each row shifted to begin at step 0 (the time grid must be uniform), its inputs and depths held at
    their last values past the run's end, no measurement at all, and ``start`` (a ``CommonStart`` of ``B``
    rows) as every observer's initial estimate."""
    T = len(problem.time)
    dt = np.diff(problem.time)
    if dt.size and not np.allclose(dt, dt[0], rtol=1e-9, atol=1e-12):
        raise DataError("the predictions from a pose need a uniform time grid")
    L = T - int(starts.min())
    idx = np.minimum(starts[:, None] + np.arange(L)[None, :], T - 1)  # (B, L), held at the last step
    inputs = problem.inputs[runs[:, None], idx]
    past = (starts[:, None] + np.arange(L)[None, :]) >= T
    inputs = np.where(past[..., None], 0.0, inputs)  # past a run's end nothing moves (a replay's inputs end so)
    channels = {
        name: dataclasses.replace(
            ch, t=np.zeros(0), t_available=np.zeros(0), index=np.zeros(0, dtype=np.int64),
            value=np.zeros((len(runs), 0, len(ch.names))), valid=np.zeros((len(runs), 0), dtype=bool),
            sample_sigma=None if ch.sample_sigma is None else np.zeros((len(runs), 0, len(ch.names))),
            attrs={k: _rows(v, runs, problem.n_runs) for k, v in ch.attrs.items()})
        for name, ch in problem.channels.items()}
    return dataclasses.replace(
        problem, time=problem.time[:L] - problem.time[0], inputs=inputs, depth=problem.depth[runs[:, None], idx],
        channels=channels, params={k: _rows(v, runs, problem.n_runs) for k, v in problem.params.items()},
        initial_truth=None, start=start, cov_layout="none")


def _rows(v, runs: np.ndarray, n_runs: int):
    """``v`` with its rows taken at ``runs`` when it has one per run (a per-run array), else as it is."""
    a = np.asarray(v) if isinstance(v, np.ndarray) else None
    return a[runs] if a is not None and a.ndim >= 1 and a.shape[0] == n_runs and n_runs > 1 else v


def pose_predictions(cfg: ExperimentConfig, problem, truth_state: np.ndarray, estimates: dict, *,
                     depths: tuple[float, ...], pose_from: tuple[str, ...], predict: list[str], seed: int,
                     progress=None) -> Group:
    """The observers named in ``predict`` (those that take a common start), run again from each held-out
    run's pose at each of ``depths`` with no measurement after it (a prediction with the observer's model
    and parameters), the pose from each source of ``pose_from``: the ``/crossval/from_pose`` group of a
    fold's results file. Every source's starts are one batch: each observer runs once.

    Parameters
    ----------
    problem : the fold's problem (its common start gives the initial covariance of the pose's states)
    truth_state : (N, T, n) the truth of the experiment's model (NaN where a replay has no frame)
    estimates : the fold's posteriors by observer name (a source other than ``truth`` names one)
    depths : start depths (model length unit)

    Returns
    -------
    Group
        per source (``truth`` or an observer's name) a group of ``start_index (N, D)``, the grid step of each
        start (-1: not reached), ``index (K,)`` the grid steps kept (where the truth exists, at most
        :data:`POSE_STEPS`), and per observer ``state (N, D, K, n)`` (NaN before the start), ``status`` and
        ``reason (N, D)``; attributes ``depths``, ``pose_from``, ``skipped`` (observers that do not take a
        common start).
    """
    from needlecli.errors import ComponentError, NeedleError
    from needlecli.experiments.simulation import components
    from needlecli.experiments.simulation.truth import stream
    from needlecli.observers import OBSERVERS
    from needlecli.problem import CommonStart

    model = problem.model
    names = tuple(model.state_names)
    N, D = problem.n_runs, len(depths)
    have = np.nonzero(np.isfinite(truth_state).all(-1).any(0))[0]
    index = (have[:: max(1, int(np.ceil(len(have) / POSE_STEPS)))] if have.size else have).astype(np.int64)
    chosen = [o for o in cfg.observers if (o.name or o.type) in predict]
    skipped = [o.name or o.type for o in chosen if not OBSERVERS.get(o.type).takes_common_start]
    out, rows = Group(), []  # rows: (source, runs, which, starts of those rows, their poses)
    for src in pose_from:
        if src == "truth":
            source = truth_state
        else:
            post = estimates[src]
            pn = list(post.names)
            source = np.full(truth_state.shape, np.nan)
            for i, k in enumerate(names):
                if k in pn:
                    source[..., i] = post.state[..., pn.index(k)]
            source = np.where(np.isfinite(truth_state).all(-1, keepdims=True), source, np.nan)  # the truth's steps
        starts = pose_starts(problem, source, depths)
        runs, which = np.nonzero(starts >= 0)
        rows.append((src, runs, which, starts[runs, which], source[runs, starts[runs, which]]))
        out.data[src] = Group(data={"start_index": starts, "index": index},
                              attrs={"depths": np.asarray(depths, dtype=float), "pose_from": src, "skipped": skipped})
    b_runs = np.concatenate([r[1] for r in rows])
    if not b_runs.size:
        return out
    b_starts = np.concatenate([r[3] for r in rows])
    cov = np.zeros((len(names), len(names)))
    if problem.start is not None:
        mine = [i for i, k in enumerate(names) if problem.start.index(k) is not None]
        theirs = [problem.start.index(names[i]) for i in mine]
        cov[np.ix_(mine, mine)] = problem.start.cov[np.ix_(theirs, theirs)]
    start = CommonStart(names=names, mean=np.concatenate([r[4] for r in rows]), cov=cov,
                        source=f"the poses of {', '.join(pose_from)} at depths {', '.join(f'{d:g}' for d in depths)}")
    sub = shifted_problem(problem, b_runs, b_starts, start)
    L = len(sub.time)
    rel = index[None, :] - b_starts[:, None]  # (B, K) step of the shifted problem, <0 before the start
    inside = (rel >= 0) & (rel < L)
    for o in chosen:
        name = o.name or o.type
        if name in skipped:
            continue
        post, failed = None, ""
        try:
            obs = components.build_observer(o)
            cb = (lambda k, n, _n=name: progress(f"{_n} from the poses", k, n)) if progress else None
            post = components.run_observer(obs, o, sub, stream(seed, f"from_pose/{name}"), progress=cb)
        except (ComponentError, NeedleError) as e:  # recorded for this part; the fold itself stands
            failed = e.reason if isinstance(e, ComponentError) else " ".join(str(e).split())
        b0 = 0
        for src, runs, which, _, _ in rows:
            sel = slice(b0, b0 + len(runs))
            b0 += len(runs)
            status = np.full((N, D), "not reached", dtype=object)
            reason = np.full((N, D), "", dtype=object)
            g = Group()
            if post is None:
                status[runs, which], reason[runs, which] = "failed", failed
            else:
                val = np.full((len(runs), len(index), len(post.names)), np.nan)
                b, k = np.nonzero(inside[sel])
                val[b, k] = post.state[sel][b, rel[sel][b, k]]
                state = np.full((N, D, len(index), len(post.names)), np.nan)
                state[runs, which] = val
                status[runs, which] = np.asarray(post.status[sel]).astype(str)
                reason[runs, which] = np.asarray(post.reason[sel]).astype(str)
                g.data["state"] = state
                g.attrs.update({"names": list(post.names), "units": list(post.units)})
            g.data.update({"status": status.astype(str), "reason": reason.astype(str)})
            out.data[src].data[name] = g
    return out
