"""A sweep's reports: each cell's metrics from its results file, the tidy table (one row per cell and
observer), its summary over seeds, and the plot of a metric against a swept parameter.

Like every report, this reads results files only (through :func:`cell_metrics`) and the records of
what became of each cell; it knows nothing of how cells were planned or run. A *cell* here is anything
with ``index``, ``id``, ``overrides`` (its varying overrides, ``runs.seed`` included), ``observers`` and
``n_runs``; an *outcome* anything with ``status``, ``rows`` (:func:`cell_metrics`' records), ``seconds``
and ``error`` (the sweep's ``Cell`` and ``CellOutcome``).
"""

from __future__ import annotations

import json
import re
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any, Protocol

import numpy as np
import pandas as pd

from needlecli.errors import SweepError
from needlecli.reports.tables import order_quantities, write_table

#: the config key of the experiment's seed: the replicate axis of a sweep
SEED_KEY = "runs.seed"


class CellLike(Protocol):
    index: int
    id: str
    overrides: dict
    seed: int
    observers: tuple[str, ...]
    n_runs: int
    param_info: dict  # {key: {name, description, unit}} of its override keys


class OutcomeLike(Protocol):
    status: str
    rows: list[dict]
    seconds: float
    error: str


def _json(v: Any) -> str:
    return json.dumps(v, sort_keys=True, default=str, separators=(",", ":"))


def format_value(v: Any) -> str:
    """A parameter value as labels show it: floats in ``%g``, lists and mappings as compact JSON."""
    if isinstance(v, float):
        return f"{v:g}"
    if isinstance(v, (dict, list)):
        return _json(v)
    return str(v)


# ---------------------------------------------------------------------------------------------- one cell
def _read_for_errors(path: str | Path):
    """The parts of a results file :func:`compute_errors` needs (no measurements, no covariances)."""
    import h5py

    from needlecli.io.results import Group, _decode

    def grp(g, names=None) -> Group:
        out = Group(attrs={k: _decode(v) for k, v in g.attrs.items()})
        for k, v in g.items():
            if names is not None and k not in names:
                continue
            if isinstance(v, h5py.Group):
                out.data[k] = grp(v)
            else:
                arr = v[()]
                out.data[k] = _decode(arr) if v.dtype.kind in "OS" else arr
        return out

    with h5py.File(path, "r") as f:
        res = Group(attrs={k: _decode(v) for k, v in f.attrs.items()})
        res.data["truth"] = grp(f["truth"], {"state", "status", "params"})
        est = Group()
        for name, g in f.get("estimates", {}).items():
            est.data[name] = grp(g, {"state", "status"})
        res.data["estimates"] = est
    return res


def cell_metrics(path: str | Path) -> list[dict]:
    """One record per observer of a results file: runs, runs kept and failed, and mean / std / max of each
    error quantity over the kept runs and every time step (the summary table's statistics)."""
    from needlecli.metrics import compute_errors

    res = _read_for_errors(path)
    rows = []
    for obs, es in compute_errors(res).items():
        kept = es.n_runs - sum(es.excluded.values())
        row: dict[str, Any] = {"observer": obs, "runs": es.n_runs, "runs_kept": kept, "runs_failed": es.n_runs - kept,
                               "failures": "; ".join(f"{k}: {v}" for k, v in es.excluded.items())}
        units = {}
        for q in order_quantities(es.quantities):
            qe = es.quantities[q]
            v = qe.values[np.isfinite(qe.values)]
            row[f"{q}_mean"] = float(np.mean(v)) if v.size else float("nan")
            row[f"{q}_std"] = float(np.std(v)) if v.size else float("nan")
            row[f"{q}_max"] = float(np.max(v)) if v.size else float("nan")
            units[q] = qe.unit
        row["_units"] = units
        rows.append(row)
    return rows


# ---------------------------------------------------------------------------------------------- the table
def param_columns(cells: Sequence[CellLike]) -> list[str]:
    """The override keys of a sweep, in first-seen order (``runs.seed`` last)."""
    keys = list(dict.fromkeys(k for c in cells for k in c.overrides))
    return [k for k in keys if k != SEED_KEY] + [SEED_KEY]


def param_info(cells: Sequence[CellLike]) -> dict[str, dict[str, str]]:
    """What each swept key is (name, description, unit), as the first cell that sets it says."""
    out: dict[str, dict[str, str]] = {}
    for c in cells:
        for k, v in getattr(c, "param_info", {}).items():
            out.setdefault(k, dict(v))
    return out


def _cell_value(v: Any) -> Any:
    return v if isinstance(v, (int, float, str, bool)) or v is None else _json(v)


def sweep_table(cells: Sequence[CellLike], outcomes: Mapping[str, OutcomeLike]) -> tuple[pd.DataFrame, dict[str, str]]:
    """One row per cell and observer: the cell's override values, status, runs, and the metrics."""
    params = param_columns(cells)
    rows, units = [], {}
    for c in sorted(cells, key=lambda c: c.index):
        out = outcomes.get(c.id)
        base = {"cell": c.id, **{k: _cell_value(c.overrides.get(k)) for k in params}}
        if base[SEED_KEY] is None:  # the seed came from fixed (or --set): the table still says which
            base[SEED_KEY] = c.seed
        status = "not run" if out is None else "ok" if out.status in ("ok", "skipped") else out.status
        seconds = out.seconds if out is not None else 0.0
        if out is not None and out.rows:
            for r in out.rows:
                units.update(r.get("_units", {}))
                rows.append({**base, "status": status, **{k: v for k, v in r.items() if k != "_units"},
                             "seconds": seconds, "error": ""})
        else:
            for obs in c.observers or ("",):
                rows.append({**base, "status": status, "observer": obs, "runs": c.n_runs, "runs_kept": 0,
                             "runs_failed": c.n_runs, "seconds": seconds, "error": out.error if out else ""})
    df = pd.DataFrame(rows)
    lead = ["cell", *params, "status", "observer", "runs", "runs_kept", "runs_failed"]
    metrics = [k for k in df.columns if k.endswith(("_mean", "_std", "_max")) and k not in lead]
    tail = ["failures", "seconds", "error"]
    for col in lead + tail:
        if col not in df.columns:
            df[col] = np.nan if col not in ("failures", "error") else ""
    df = df[[*lead, *metrics, *tail]]
    df["failures"] = df["failures"].fillna("")
    df.attrs["params"] = params
    df.attrs["param_info"] = param_info(cells)
    return df, units


def seed_summary(df: pd.DataFrame) -> pd.DataFrame | None:
    """Over the seeds: one row per observer and combination of the other parameters, with the mean and the
    std across seeds (cells) of each ``*_mean`` metric and the runs that failed. None when the sweep has a
    single seed per combination."""
    params = [k for k in df.attrs.get("params", []) if k != SEED_KEY]
    ok = df[df["status"] == "ok"]
    if ok.empty or SEED_KEY not in ok or ok.groupby(["observer", *params], dropna=False)[SEED_KEY].nunique().max() < 2:
        return None
    metrics = [c for c in ok.columns if c.endswith("_mean")]
    rows = []
    for key, g in ok.groupby([*params, "observer"], dropna=False, sort=True):
        key = key if isinstance(key, tuple) else (key,)
        row = dict(zip([*params, "observer"], key))
        row["cells"] = len(g)
        row["runs"] = int(g["runs"].sum())
        row["runs_failed"] = int(g["runs_failed"].sum())
        for m in metrics:
            row[m] = float(g[m].mean())
            row[m[: -len("_mean")] + "_mean_std"] = float(g[m].std(ddof=1)) if len(g) > 1 else float("nan")
        rows.append(row)
    failed = {}
    for _, r in df[df["status"] != "ok"].iterrows():
        k = tuple(r[c] for c in [*params, "observer"])
        failed[k] = failed.get(k, 0) + 1
    out = pd.DataFrame(rows)
    out.insert(len(params) + 2, "cells_failed", [failed.get(tuple(r[c] for c in [*params, "observer"]), 0)
                                                 for _, r in out.iterrows()])
    return out


def write_sweep_table(df: pd.DataFrame, out_dir: Path, units: dict[str, str]) -> list[Path]:
    """``DIR/sweep.{csv,md}``, and ``DIR/sweep_over_seeds.{csv,md}`` when runs.seed is a sweep axis."""
    unit_text = ", ".join(f"{q} in {u}" for q, u in units.items())
    units_note = f" ({unit_text})" if unit_text else ""
    info = df.attrs.get("param_info", {})
    swept = "; ".join(f"`{k}`: {axis_label(k, info.get(k))}" for k in df.attrs.get("params", []) if k != SEED_KEY)
    caption = ("Sweep: one row per cell and observer" + (f"; parameters {swept}" if swept else "") +
               f"; `{SEED_KEY}` the cell's seed (cells with the same seed share every random stream: common random "
               "numbers); mean / std / max of each error over the kept runs and all time steps" + units_note + ".")
    paths = write_table(df, out_dir / "sweep", ["csv", "md"], caption=caption)
    summary = seed_summary(df)
    if summary is not None:
        paths += write_table(summary, out_dir / "sweep_over_seeds", ["csv", "md"], caption=(
            "Sweep over seeds: per observer and parameter values, the mean over the cells (seeds) of each "
            "error's mean, and its std across seeds (`*_mean_std`)" + units_note + "."))
    return paths


# ---------------------------------------------------------------------------------------------- plot
def default_plot_choice(df: pd.DataFrame, metric: str | None, param: str | None) -> tuple[str | None, str | None]:
    """The metric (default ``E_xyz_mean``, else the first) and the parameter (default the first varying
    numeric one that is not ``runs.seed``) to plot."""
    metrics = [c for c in df.columns if c.endswith(("_mean", "_std", "_max"))]
    if metric is None:
        metric = "E_xyz_mean" if "E_xyz_mean" in metrics else (metrics[0] if metrics else None)
    if param is None:
        for k in df.attrs.get("params", []):
            if k == SEED_KEY:
                continue
            vals = df[k].dropna().unique()
            if len(vals) > 1:
                param = k
                break
    return metric, param


def axis_label(key: str, info: Mapping[str, str] | None) -> str:
    """A parameter as an axis shows it: its name, description and unit, e.g. ``ukf: q.kappa (process noise
    std per state per tick) [1/mm]``; the key itself where nothing is known of it."""
    info = info or {}
    desc, unit = info.get("description", ""), info.get("unit", "")
    return (info.get("name") or key) + (f" ({desc})" if desc else "") + (f" [{unit}]" if unit else "")


def sweep_figure(df: pd.DataFrame, *, metric: str, param: str, units: Mapping[str, str] | None = None,
                 title: str = ""):
    """The figure of :func:`plot_sweep` (returned open, for tests and callers that add to it)."""
    from needlecli.reports.plots import beside_legend, observer_look, subplots

    if metric not in df.columns:
        known = [c for c in df.columns if c.endswith(("_mean", "_std", "_max"))]
        raise SweepError(f"--plot-metric: no metric {metric!r}; the table has {', '.join(known) or 'none'}")
    params = df.attrs.get("params", [])
    if param not in params:
        raise SweepError(f"--plot-param: {param!r} is not a swept parameter; parameters: {', '.join(params)}")
    info = df.attrs.get("param_info", {})
    ok = df[df["status"] == "ok"]
    others = [k for k in params if k not in (param, SEED_KEY)]
    groups = ["observer", *others]
    fig, ax = subplots(figsize=(9.5, 4.6))
    xs_all = pd.to_numeric(ok[param], errors="coerce")
    numeric = bool(len(ok)) and xs_all.notna().all()
    cats = list(dict.fromkeys(ok[param])) if not numeric else None
    combos: list[tuple] = []
    counts: list[int] = []
    seed_sets: set[frozenset] = set()
    for key, g in ok.groupby(groups, dropna=False, sort=True):
        key = key if isinstance(key, tuple) else (key,)
        by_x = g.groupby(param, sort=True)
        agg = by_x[metric].agg(["mean", "std", "count"])
        counts += agg["count"].tolist()
        seed_sets |= {frozenset(s) for s in by_x[SEED_KEY].agg(lambda v: tuple(v.dropna()))}
        x = agg.index.to_numpy()
        if not numeric:
            x = np.array([cats.index(v) for v in x])
        if key[1:] not in combos:
            combos.append(key[1:])
        k = combos.index(key[1:])
        label = ", ".join([str(key[0])] + [_legend_entry(o, v, info.get(o)) for o, v in zip(others, key[1:])])
        replicated = bool((agg["count"] > 1).any())
        look = observer_look(str(key[0]))  # the observer's colour in every figure; a line style per combination
        ax.errorbar(x, agg["mean"], yerr=agg["std"].where(agg["count"] > 1) if replicated else None,
                    color=look["color"], marker="osD^v<>ph"[k % 9] if others else look["marker"],
                    linestyle=["-", "--", ":", "-."][k % 4] if others else look["ls"], capsize=3, label=label,
                    gid=f"observer:{key[0]}")
    if numeric and len(xs_all) and (xs_all > 0).all() and xs_all.max() / xs_all.min() >= 20:
        ax.set_xscale("log")
    if cats is not None:
        ax.set_xticks(range(len(cats)), [str(c) for c in cats])
    q, _, stat = metric.rpartition("_")
    unit = (units or {}).get(q, "")
    ax.set_xlabel(axis_label(param, info.get(param)))
    ylabel = f"{q}, {stat} over runs and time steps" if stat in ("mean", "std", "max") and q else metric
    ax.set_ylabel(ylabel + (f" [{unit}]" if unit else ""))
    ax.grid(alpha=0.3)
    if len(ax.get_legend_handles_labels()[0]):
        beside_legend(ax)
    ax.set_title(("\n".join(filter(None, [title, f"{metric} against {info.get(param, {}).get('name') or param}"]))
                  + "\n" + _seed_note(counts, seed_sets)), fontsize="medium")
    return fig


def _legend_entry(key: str, value: Any, info: Mapping[str, str] | None) -> str:
    """``us3d: rate = 2 Hz``: a parameter's name, value and unit."""
    info = info or {}
    unit = info.get("unit", "")
    return f"{info.get('name') or key} = {format_value(value)}" + (f" {unit}" if unit else "")


def _seed_note(counts: list[int], seed_sets: set[frozenset]) -> str:
    """What a point and its error bar are: over how many seeds, and whether every point has the same."""
    same = len(seed_sets) == 1
    if not counts:
        return "no cell succeeded"
    lo, hi = min(counts), max(counts)
    if hi > 1:
        n = f"{lo}" if lo == hi else f"{lo} to {hi}"
        return (f"points: mean over {n} seeds, bars: \u00b11 std; "
                + ("the same seeds at every point" if same else "the seeds differ between points"))
    if same:
        seed = next(iter(next(iter(seed_sets))), None)
        return f"one seed per point ({format_value(seed)}), the same at every point; no replicates"
    return "one seed per point, not the same at every point: the points differ in their noise too"


def plot_sweep(df: pd.DataFrame, *, metric: str, param: str, path: str | Path, units: dict[str, str] | None = None,
               title: str = "") -> Path:
    """``metric`` against ``param``, one colour per observer and one line per observer and combination of
    the other parameters; with replicate seeds (cells that differ only in ``runs.seed``) each point is the
    mean over them and its error bar their std. The x axis names the parameter with its unit; the title
    says over which seeds the points are taken."""
    from needlecli.reports.plots import save_figure

    fig = sweep_figure(df, metric=metric, param=param, units=units, title=title)
    return save_figure(fig, Path(path))


def plot_name(metric: str, param: str) -> str:
    return "sweep_" + re.sub(r"[^A-Za-z0-9_.-]+", "_", f"{metric}_vs_{param}") + ".png"
