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
"""

from __future__ import annotations

import copy
import dataclasses
import re
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import pandas as pd
import yaml

from needlecli.errors import ConfigError, DataError

if TYPE_CHECKING:
    from needlecli.experiments.config.types import ExperimentConfig

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
    constants: pd.DataFrame = field(default_factory=pd.DataFrame)
    groups: dict[str, str] = field(default_factory=dict)  # trial id -> its group (with group_by)


def group_of(trial_id: str, meta: dict, spec: str | None) -> str:
    """A trial's group under ``spec``: ``id~REGEX`` (first match in the id) or a metadata key."""
    if spec is None:
        return trial_id
    if spec.startswith("id~"):
        m = re.search(spec[3:], trial_id)
        return m.group(0) if m else trial_id
    if spec not in meta:
        raise ConfigError("--group-by", (), f"trial {trial_id!r} has no metadata {spec!r}; it has "
                          f"{', '.join(sorted(meta)) or 'none'} (or use id~REGEX)")
    return str(meta[spec])


def make_folds(ids: list[str], groups: list[str], *, k: int | None, leave_one_out: bool, within: bool) -> list[Fold]:
    """The folds: leave-one-out (training: every other trial, or with ``within`` the other trials of its
    group), or ``k`` folds of whole groups (round-robin over the groups in order of appearance)."""
    if leave_one_out:
        out = []
        for i, t in enumerate(ids):
            train = [u for j, u in enumerate(ids) if j != i and (not within or groups[j] == groups[i])]
            if not train:
                raise ConfigError("--within", (), f"trial {t!r} is alone in its group {groups[i]!r}: nothing to fit on")
            out.append(Fold(i, train, [t]))
        return out
    order = list(dict.fromkeys(groups))
    if k is None or k < 2:
        raise ConfigError("--folds", (), "needs at least 2 folds")
    if k > len(order):
        raise ConfigError("--folds", (), f"{k} folds for {len(order)} group(s) of trials: at most {len(order)}")
    fold_of = {g: i % k for i, g in enumerate(order)}
    return [Fold(f, [t for t, g in zip(ids, groups) if fold_of[g] != f], [t for t, g in zip(ids, groups) if fold_of[g] == f])
            for f in range(k)]


def _replay_base(cfg_path: Path, data: dict, out_dir: Path, progress) -> tuple[dict, list[tuple[str, dict]], Path]:
    """The replay config every fold derives from (absolute log paths), and the trials ``(id, meta)``."""
    from needlecli.io.logs import read_log

    base_dir = cfg_path.parent
    if data.get("source"):
        logs = [str((base_dir / p).resolve()) if not Path(p).is_absolute() else p for p in data["source"]["logs"]]
        wanted = data["source"].get("trials")
        trials = []
        for p in logs:
            for tr in read_log(p).trials:
                trials.append((tr.id, dict(tr.meta)))
        if wanted:
            have = {t for t, _ in trials}
            missing = [t for t in wanted if t not in have]
            if missing:
                raise ConfigError(str(cfg_path), ("source", "trials"), f"no trial {missing[0]!r} in the logs")
            meta = dict(trials)
            trials = [(t, meta[t]) for t in dict.fromkeys(wanted)]
        base = copy.deepcopy(data)
        base["source"] = {**base["source"], "logs": logs}
        return base, trials, base_dir
    # a simulated config: simulate once, its runs become the trials of a log
    from needlecli.experiments.config.load import load_config
    from needlecli.experiments.simulation.runner import run_experiment
    from needlecli.io.logs import log_from_results, write_log
    from needlecli.io.results import read_results

    sim = copy.deepcopy(data)
    sim["observers"] = []
    cfg, text = load_config(cfg_path, text=yaml.safe_dump(sim, sort_keys=False))
    res_path = run_experiment(cfg, text, out=out_dir / "trials.h5", base_dir=base_dir,
                              progress=progress).path
    log = log_from_results(read_results(res_path), description=f"{cfg.name}: the simulated trials of crossval",
                           prefix="run")
    log_path = write_log(out_dir / "trials.log.h5", log)
    base = {k: v for k, v in copy.deepcopy(data).items() if k not in _SIMULATION_ONLY}
    model = dict(base.get("model") or {})
    for k in ("param_cases", "param_std", "initial_std"):
        model.pop(k, None)
    base["model"] = model
    base["source"] = {"logs": [str(log_path.resolve())]}
    return base, [(t.id, dict(t.meta)) for t in log.trials], base_dir


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
    folds: int | None = 5,
    leave_one_out: bool = False,
    group_by: str | None = None,
    within: bool = False,
    out_dir: str | Path | None = None,
    overrides: list[str] | None = None,
    progress: Callable[[str, int, int], None] | None = None,
) -> CrossvalResult:
    """Cross-validate EM-tuned copies of ``observers`` against the config's hand-tuned observers (module
    docstring). Every setting is checked before the first fit."""
    from needlecli.experiments.config.load import load_config
    from needlecli.experiments.config.overrides import apply_overrides
    from needlecli.experiments.studies.fit import fit_tree, fit_trials, load_trials, take_fit
    from needlecli.io.results import write_atomic
    from needlecli.io.yamlfile import parse_yaml

    cfg_path = Path(config)
    source = str(cfg_path)
    try:
        text = cfg_path.read_text(encoding="utf-8")
    except OSError as e:
        raise ConfigError(source, (), f"cannot read the file: {e}") from None
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
    out = Path(out_dir) if out_dir is not None else Path("results") / f"{cfg0.name}_crossval"
    (out / "folds").mkdir(parents=True, exist_ok=True)
    base, trials, base_dir = _replay_base(cfg_path, data, out, progress)
    ids = [t for t, _ in trials]
    groups = [group_of(t, m, group_by) for t, m in trials]
    plan = make_folds(ids, groups, k=None if leave_one_out else folds, leave_one_out=leave_one_out, within=within)
    results, fits = [], []
    tuned = {f"{o}_em": o for o in observers}
    rows = []
    # every trial's EM is its own: fit each training trial once, and give each fold its training trials' fits
    fitted = [t for t in ids if any(t in fd.train for fd in plan)]
    every = copy.deepcopy(base)
    every["source"]["trials"] = fitted
    every["observers"] = []
    every_path = out / "folds" / "all_train.yaml"
    every_path.write_text(yaml.safe_dump(every, sort_keys=False))
    em_cb = (lambda ph, k, n: progress(f"EM of {len(fitted)} training trials", k, n)) if progress else None
    fo_all = fit_trials(load_trials(every_path), models=[fit_model], progress=em_cb)
    for fd in plan:
        train = copy.deepcopy(base)
        train["source"]["trials"] = fd.train
        train["observers"] = []
        train_path = out / "folds" / f"fold{fd.index}_train.yaml"
        train_path.write_text(yaml.safe_dump(train, sort_keys=False))
        fo = take_fit(fo_all, load_trials(train_path), [fitted.index(t) for t in fd.train])
        fit_path = write_atomic(out / "folds" / f"fold{fd.index}_fit.h5", fit_tree(fo))
        fits.append(fit_path)
        mf = fo.fits[fit_model]
        ok = mf.result.status == "ok"
        for i, c in enumerate(mf.system.dm.augment):
            v = mf.result.x0[ok, mf.system.dm.nx + i]
            se = np.nan
            if mf.identifiability is not None and c in mf.identifiability.names:
                se = float(mf.identifiability.pooled_se[mf.identifiability.names.index(c)])
            rows.append({"Fold": fd.index, "Held out": ", ".join(fd.test), "Trained on": len(fd.train),
                         "Constant": c, "Median": float(np.median(v)) if v.size else np.nan, "SE (pooled)": se,
                         "Trials ok": f"{int(ok.sum())}/{len(ok)}"})
        test = copy.deepcopy(base)
        test["source"]["trials"] = fd.test
        test["observers"] = raw_obs + [_tuned_copy(o, fit_path, fit_model) for o in raw_obs
                                       if (o.get("name") or o.get("type")) in observers]
        test_text = yaml.safe_dump(test, sort_keys=False)
        tcfg, ttext = load_config(out / "folds" / f"fold{fd.index}.yaml", text=test_text)
        results.append(_run_common_start(tcfg, ttext, out / "folds" / f"fold{fd.index}.h5", base_dir, progress, fd))
    return CrossvalResult(plan, results, fits, tuned, [n for n in names] + list(tuned), fit_model, out,
                          constants=pd.DataFrame(rows), groups=dict(zip(ids, groups)) if group_by else {})


def _run_common_start(cfg: ExperimentConfig, text, path: Path, base_dir: Path, progress, fd: Fold) -> Path:
    """Replay a fold's held-out trials through every observer from one common start; write its results."""
    from needlecli.experiments.simulation import components
    from needlecli.experiments.simulation.replay import replay_truth
    from needlecli.experiments.simulation.runner import build_problem, results_tree
    from needlecli.experiments.simulation.truth import stream
    from needlecli.io.results import write_atomic

    truth, sensors, streams = replay_truth(cfg, base_dir)
    problem = build_problem(cfg, truth, sensors, streams)
    seed = cfg.runs.seed
    start = None
    for o in cfg.observers:
        start = components.initial_estimate(o, problem, stream(seed, f"observer/{o.name or o.type}"))
        if start is not None:
            break
    problem = dataclasses.replace(problem, start=start)
    estimates = {}
    for o in cfg.observers:  # each guarded and checked: a failure ends the study before this fold is written
        obs = components.build_observer(o)
        cb = (lambda k, n, _n=obs.name: progress(f"fold {fd.index + 1}: {_n}", k, n)) if progress else None
        estimates[obs.name] = components.run_observer(obs, o, problem, stream(seed, f"observer/{obs.name}"), progress=cb)
    return write_atomic(path, results_tree(cfg, text, truth, streams, estimates, sensors))


# ---------------------------------------------------------------------------------------------- tables
DEPTH_BINS = (0.0, 10.0, 20.0, 30.0, 40.0, 60.0, 80.0, 120.0, 200.0)


def crossval_tables(result: CrossvalResult) -> dict[str, pd.DataFrame]:
    """``summary``: per observer, the position error over every held-out trial and time (mean, std, final),
    its constants' error where the truth has them; ``by_depth``: the mean position error per depth bin
    (what a planner needs), over all held-out trials and, with groups, per group of the held-out trials;
    ``constants``: each fold's fitted constants."""
    from needlecli.io.results import read_results
    from needlecli.metrics import compute_errors

    per_obs: dict[str, list[np.ndarray]] = {}
    depth_obs: dict[tuple[str, str], list[np.ndarray]] = {}  # (observer, group or "all")
    final: dict[str, list[np.ndarray]] = {}
    unit = "mm"
    for path in result.results:
        res = read_results(path)
        errs = compute_errors(res)
        depth = np.asarray(res.data["depth"], dtype=float)
        for name, es in errs.items():
            q = es.quantities.get("E_xyz")
            if q is None:
                continue
            unit = q.unit
            v = q.values
            d = depth[q.runs] if depth.ndim == 2 else np.broadcast_to(depth, v.shape)
            per_obs.setdefault(name, []).append(v[:, 1:].ravel())
            depth_obs.setdefault((name, "all"), []).append(np.stack([d.ravel(), v.ravel()], -1))
            if result.groups:  # and per group of the held-out trials (a recording day)
                ids = np.asarray(res.data["truth"].data.get("trial_id", [])).astype(str)[q.runs]
                for g in dict.fromkeys(result.groups.get(t, t) for t in ids):
                    sel = np.array([result.groups.get(t, t) == g for t in ids])
                    depth_obs.setdefault((name, g), []).append(np.stack([d[sel].ravel(), v[sel].ravel()], -1))
            fin = np.isfinite(v)
            k_last = np.where(fin, np.arange(v.shape[1]), -1).max(axis=1)  # the last time with an error
            final.setdefault(name, []).append(np.where(k_last >= 0, v[np.arange(len(v)), np.maximum(k_last, 0)], np.nan))
    rows = []
    for name, parts in per_obs.items():
        v = np.concatenate(parts)
        v = v[np.isfinite(v)]
        f = np.concatenate(final[name])
        f = f[np.isfinite(f)]
        rows.append({"Observer": name, "Parameters": ("EM on the other trials" if name in result.tuned
                                                      else "config (hand-tuned)"),
                     f"E_xyz mean [{unit}]": float(v.mean()) if v.size else np.nan,
                     f"E_xyz std [{unit}]": float(v.std()) if v.size else np.nan,
                     f"E_xyz final mean [{unit}]": float(f.mean()) if f.size else np.nan,
                     "Held-out trials": int(f.size)})
    summary = pd.DataFrame(rows)
    brow = []
    for (name, group), parts in sorted(depth_obs.items(), key=lambda kv: (kv[0][1] != "all", kv[0][1], kv[0][0])):
        a = np.concatenate(parts)
        row = {"Observer": name, **({"Held-out group": group} if result.groups else {})}
        for lo, hi in zip(DEPTH_BINS[:-1], DEPTH_BINS[1:]):
            sel = (a[:, 0] >= lo) & (a[:, 0] < hi) & np.isfinite(a[:, 1])
            row[f"{lo:g}-{hi:g} mm"] = float(a[sel, 1].mean()) if sel.any() else np.nan
        brow.append(row)
    by_depth = pd.DataFrame(brow)
    by_depth = by_depth.loc[:, [c for c in by_depth.columns if c in ("Observer", "Held-out group") or by_depth[c].notna().any()]]
    return {"summary": summary, "by_depth": by_depth, "constants": result.constants}


def crossval_plot(by_depth: pd.DataFrame, path: Path, title: str) -> Path | None:
    """Mean held-out position error against inserted depth (the by-depth table, drawn at each bin's
    centre): one colour per observer, one line style per held-out group (solid: all trials)."""
    from needlecli.reports.plots import CASE_STYLES, save_figure, subplots

    if by_depth.empty:
        return None
    bins = [c for c in by_depth.columns if c.endswith(" mm")]
    centres = np.array([np.mean([float(x) for x in c[:-3].split("-")]) for c in bins])
    observers = list(dict.fromkeys(by_depth["Observer"]))
    groups = list(dict.fromkeys(by_depth["Held-out group"])) if "Held-out group" in by_depth else ["all"]
    fig, ax = subplots(1, 1, figsize=(7.5, 4.2))
    for _, row in by_depth.iterrows():
        g = row.get("Held-out group", "all")
        v = row[bins].to_numpy(dtype=float)
        fin = np.isfinite(v)
        ax.plot(centres[fin], v[fin], marker="o", ms=3.5, lw=1.4 if g == "all" else 1.0,
                color=f"C{observers.index(row['Observer']) % 10}", ls=CASE_STYLES[groups.index(g) % len(CASE_STYLES)],
                label=f"{row['Observer']} ({g})", gid=f"observer:{row['Observer']}")
    ax.set_xlabel("inserted depth [mm] (bin centres)")
    ax.set_ylabel("mean position error, held out [mm]")
    ax.grid(alpha=0.3)
    ax.legend(fontsize="small", ncol=2)
    ax.set_title(title, fontsize=9)
    return save_figure(fig, path)


def check_args(leave_one_out: bool, within: bool, folds: int | None) -> None:
    if within and not leave_one_out:
        raise ConfigError("--within", (), "is for --leave-one-out (the training trials: the others of the held-out one's group)")
    if folds is not None and leave_one_out:
        raise DataError("--folds and --leave-one-out: give one of them")
