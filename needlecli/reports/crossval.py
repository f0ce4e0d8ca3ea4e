"""The tables and the plot of ``needle crossval``, from its folds' results files alone.

Each fold's results file (``DIR/folds/fold<k>.h5``) holds the held-out trials run through every observer
and a ``/crossval`` group saying which trials trained the fold's fit and which were held out, which
observers are the EM-tuned copies, each held-out trial's group (with ``--group-by``) and the constants
the fold's fit gave (docs/reference/results-file.md). The tables pool the held-out errors of all folds.

With ``/crossval/from_pose`` (the held-out trials predicted again from their own pose at chosen depths),
the table ``from_pose`` sets the error from each pose beside the error from the common start over the same
distance predicted ahead: the first is the model's part of a held-out error, the difference the start's.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

from needlecli.errors import DataError
from needlecli.io.tree import Group

DEPTH_BINS = (0.0, 10.0, 20.0, 30.0, 40.0, 60.0, 80.0, 120.0, 200.0)
_TO_MM = {"mm": 1.0, "m": 1000.0, "cm": 10.0}
_POSITION_AXES = (("x", "y", "z"), ("px", "py", "pz"))


def _texts(values) -> list[str]:
    return [v.decode() if isinstance(v, bytes) else str(v) for v in np.atleast_1d(values)]


def crossval_tables(paths: list[Path]) -> dict[str, pd.DataFrame]:
    """From the folds' results files ``paths``: ``summary``: per observer, the position error over every
    held-out trial and time (mean, std, final); ``by_depth``: the mean position error per depth bin (what
    a planner needs), over all held-out trials and, with groups, per group of the held-out trials;
    ``constants``: each fold's fitted constants; ``from_pose`` (folds that predicted from poses): the mean
    position error per distance predicted ahead, from the common start and from the pose at each start
    depth (:func:`from_pose_table`).

    Raises
    ------
    DataError
        A file that is not a fold's results file of needle crossval (no ``/crossval`` group).
    """
    from needlecli.io.results import read_results
    from needlecli.metrics import compute_errors

    per_obs: dict[str, list[np.ndarray]] = {}
    depth_obs: dict[tuple[str, str], list[np.ndarray]] = {}  # (observer, group or "all")
    final: dict[str, list[np.ndarray]] = {}
    tuned: set[str] = set()
    grouped = False
    rows = []
    unit = "mm"
    for path in paths:
        res = read_results(path)
        cv = res.data.get("crossval")
        if cv is None:
            raise DataError(f"{path}: not a fold of needle crossval (no /crossval group)")
        tuned |= set(_texts(cv.attrs.get("tuned", [])))
        test = _texts(cv.attrs["test"])
        groups = dict(zip(test, _texts(cv.data["group"]))) if "group" in cv.data else {}
        grouped = grouped or bool(groups)
        const = cv.data.get("constants")
        if const is not None:
            for c, med, se in zip(_texts(const.data["name"]), np.atleast_1d(const.data["median"]),
                                  np.atleast_1d(const.data["se"])):
                rows.append({"Fold": int(cv.attrs["fold"]), "Held out": ", ".join(test),
                             "Trained on": len(_texts(cv.attrs["train"])), "Constant": c, "Median": float(med),
                             "SE (pooled)": float(se),
                             "Trials ok": f"{int(const.attrs['trials_ok'])}/{int(const.attrs['trials'])}"})
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
            if groups:  # and per group of the held-out trials (a recording day)
                ids = np.asarray(res.data["truth"].data.get("trial_id", [])).astype(str)[q.runs]
                for g in dict.fromkeys(groups.get(t, t) for t in ids):
                    sel = np.array([groups.get(t, t) == g for t in ids])
                    depth_obs.setdefault((name, g), []).append(np.stack([d[sel].ravel(), v[sel].ravel()], -1))
            fin = np.isfinite(v)
            k_last = np.where(fin, np.arange(v.shape[1]), -1).max(axis=1)  # the last time with an error
            final.setdefault(name, []).append(np.where(k_last >= 0, v[np.arange(len(v)), np.maximum(k_last, 0)], np.nan))
    out = []
    for name, parts in per_obs.items():
        v = np.concatenate(parts)
        v = v[np.isfinite(v)]
        f = np.concatenate(final[name])
        f = f[np.isfinite(f)]
        out.append({"Observer": name, "Parameters": ("EM on the other trials" if name in tuned
                                                     else "config (hand-tuned)"),
                    f"E_xyz mean [{unit}]": float(v.mean()) if v.size else np.nan,
                    f"E_xyz std [{unit}]": float(v.std()) if v.size else np.nan,
                    f"E_xyz final mean [{unit}]": float(f.mean()) if f.size else np.nan,
                    "Held-out trials": int(f.size)})
    summary = pd.DataFrame(out)
    brow = []
    for (name, group), parts in sorted(depth_obs.items(), key=lambda kv: (kv[0][1] != "all", kv[0][1], kv[0][0])):
        a = np.concatenate(parts)
        row = {"Observer": name, **({"Held-out group": group} if grouped else {})}
        for lo, hi in zip(DEPTH_BINS[:-1], DEPTH_BINS[1:]):
            sel = (a[:, 0] >= lo) & (a[:, 0] < hi) & np.isfinite(a[:, 1])
            row[f"{lo:g}-{hi:g} mm"] = float(a[sel, 1].mean()) if sel.any() else np.nan
        brow.append(row)
    by_depth = pd.DataFrame(brow)
    by_depth = by_depth.loc[:, [c for c in by_depth.columns if c in ("Observer", "Held-out group") or by_depth[c].notna().any()]]
    out = {"summary": summary, "by_depth": by_depth, "constants": pd.DataFrame(rows)}
    fp = from_pose_table(paths)
    if not fp.empty:
        out["from_pose"] = fp
    return out


def _positions(names, state: np.ndarray) -> np.ndarray | None:
    """The position ``(..., 3)`` of ``state (..., n)`` by its state ``names`` (x, y, z or px, py, pz)."""
    names = _texts(names)
    axes = next((ax for ax in _POSITION_AXES if all(a in names for a in ax)), None)
    return None if axes is None else state[..., [names.index(a) for a in axes]]


def from_pose_table(paths: list[Path]) -> pd.DataFrame:
    """The two parts of the held-out error, from the folds' results files ``paths``: per observer that
    predicted from poses (and per group of the held-out trials, with groups), the mean position error (mm)
    per distance predicted ahead (:data:`DEPTH_BINS`), from the common start (row ``common start``: the
    error at each inserted depth) and from the pose at each start depth (rows ``<pose> at <d>``: the error
    that distance past the start), at the steps where the truth exists; ``Trials``: held-out trials
    predicted from there. Empty when no fold predicted from poses."""
    from needlecli.io.results import read_results

    acc: dict[tuple[str, str, str], list[np.ndarray]] = {}  # (group, observer, start) -> [(ahead, error)]
    trials: dict[tuple[str, str, str], int] = {}
    order: list[str] = []
    for path in paths:
        res = read_results(path)
        cv = res.data.get("crossval")
        if cv is None:
            raise DataError(f"{path}: not a fold of needle crossval (no /crossval group)")
        for i, fp in enumerate(cv.data.get("from_pose", Group()).data.values()):
            _pose_errors(res, cv, fp, acc, trials, order, with_start=i == 0)
    if not acc:
        return pd.DataFrame()
    grouped = any(k[0] != "all" for k in acc)
    obs_order = list(dict.fromkeys(order))
    rows = []
    def rank(start: str) -> int:  # the start first, then the recorded poses, then observers' (by depth within)
        return 0 if start == "common start" else 1 if start.startswith("recorded") else 2

    for (grp, obs, start), parts in sorted(acc.items(), key=lambda kv: (kv[0][0] != "all", kv[0][0],
                                                                          obs_order.index(kv[0][1]), rank(kv[0][2]))):
        a = np.concatenate(parts)
        row = {"Observer": obs, "From": start, **({"Held-out group": grp} if grouped else {}),
               "Trials": trials[(grp, obs, start)]}
        for lo, hi in zip(DEPTH_BINS[:-1], DEPTH_BINS[1:]):
            sel = (a[:, 0] >= lo) & (a[:, 0] < hi) & np.isfinite(a[:, 1])
            row[f"{lo:g}-{hi:g} mm"] = float(a[sel, 1].mean()) if sel.any() else np.nan
        rows.append(row)
    df = pd.DataFrame(rows)
    keep = [c for c in df.columns if not c.endswith(" mm") or df[c].notna().any()]
    return df.loc[:, keep]


def crossval_plot(by_depth: pd.DataFrame, path: Path, title: str) -> Path | None:
    """Mean held-out position error against inserted depth (the by-depth table, drawn at each bin's
    centre): one colour per observer, one line style per held-out group (solid: all trials)."""
    from needlecli.reports.plots import CASE_STYLES, observer_style, outside_legend, save_figure, subplots

    if by_depth.empty:
        return None
    bins = [c for c in by_depth.columns if c.endswith(" mm")]
    centres = np.array([np.mean([float(x) for x in c[:-3].split("-")]) for c in bins])
    groups = list(dict.fromkeys(by_depth["Held-out group"])) if "Held-out group" in by_depth else ["all"]
    fig, ax = subplots(1, 1, figsize=(7.5, 4.2))
    for _, row in by_depth.iterrows():
        g = row.get("Held-out group", "all")
        v = row[bins].to_numpy(dtype=float)
        fin = np.isfinite(v)
        st = observer_style(row["Observer"], line=False)
        ax.plot(centres[fin], v[fin], ms=3.5, lw=1.4 if g == "all" else 1.0,
                ls=CASE_STYLES[groups.index(g) % len(CASE_STYLES)], label=f"{row['Observer']} ({g})", **st)
    ax.set_xlabel("inserted depth [mm] (bin centres)")
    ax.set_ylabel("mean position error, held out [mm]")
    ax.grid(alpha=0.3)
    outside_legend(fig, *ax.get_legend_handles_labels(), ncol=3)
    ax.set_title(title, fontsize=9)
    return save_figure(fig, path)


def _pose_errors(res, cv, fp, acc: dict, trials: dict, order: list, with_start: bool) -> None:
    """Add one fold's errors from one pose source (``fp``, a ``/crossval/from_pose/<source>`` group) and,
    ``with_start``, from the common start to ``acc``, keyed ``(group, observer, start)``: ``(M, 2)`` arrays of the distance
    predicted ahead (mm) and the position error (mm)."""
    scale = _TO_MM.get(str(res.attrs.get("length_unit", "mm")), 1.0)
    truth = res.data["truth"]
    index = np.asarray(fp.data["index"], dtype=np.int64)
    starts = np.asarray(fp.data["start_index"], dtype=np.int64)  # (N, D)
    depths = np.atleast_1d(np.asarray(fp.attrs["depths"], dtype=float))
    source = str(fp.attrs.get("pose_from", "truth"))
    what = "recorded pose" if source == "truth" else f"pose of {source}"
    p_true = _positions(truth.attrs["names"], np.asarray(truth.data["state"])[:, index])  # (N, K, 3)
    depth_all = np.broadcast_to(np.asarray(res.data["depth"], dtype=float) * scale,
                                (p_true.shape[0], len(res.data["time"])))  # (N, T)
    depth = depth_all[:, index]  # (N, K)
    ids = _texts(truth.data.get("trial_id", [f"run{i}" for i in range(p_true.shape[0])]))
    test = _texts(cv.attrs["test"])
    groups = dict(zip(test, _texts(cv.data["group"]))) if "group" in cv.data else {}
    names = [g for g in ["all", *dict.fromkeys(groups.get(t, t) for t in ids)] if g == "all" or groups]
    member = {g: np.array([g == "all" or groups.get(t, t) == g for t in ids]) for g in names}
    estimates = res.data["estimates"].data
    for obs, g in fp.data.items():
        if obs in ("start_index", "index") or "state" not in g.data:
            continue
        order.append(obs)
        ok = np.asarray(g.data["status"]).astype(str) == "ok"  # (N, D)
        pred = _positions(g.attrs["names"], np.asarray(g.data["state"]))  # (N, D, K, 3)
        err = scale * np.linalg.norm(pred - p_true[:, None], axis=-1)  # (N, D, K)
        start_depth = np.take_along_axis(depth_all, np.clip(starts, 0, None), axis=1)  # (N, D)
        ahead = depth[:, None, :] - start_depth[:, :, None]
        e0 = estimates[obs]
        run_ok = np.asarray(e0.data["status"]).astype(str) == "ok"
        e_start = scale * np.linalg.norm(_positions(e0.attrs["names"], np.asarray(e0.data["state"])[:, index])
                                         - p_true, axis=-1)  # (N, K): from the common start
        for grp, sel in member.items():
            key = (grp, obs, "common start")
            r = sel & run_ok
            if with_start:
                acc.setdefault(key, []).append(np.stack([(depth - depth_all[:, :1])[r].ravel(), e_start[r].ravel()], -1))
                trials[key] = trials.get(key, 0) + int(r.sum())
            for j, d in enumerate(depths):
                key = (grp, obs, f"{what} at {d:g} mm")
                r = sel & ok[:, j] & (starts[:, j] >= 0)
                acc.setdefault(key, []).append(np.stack([ahead[r, j].ravel(), err[r, j].ravel()], -1))
                trials[key] = trials.get(key, 0) + int(r.sum())
