"""Tip position error split along the needle and across it: what a 2D transverse ultrasound cannot tell
(where its image plane is relative to the tip) apart from what it measures (the shaft's cross section).

At every frame with a reference (a recorded trial's tracker, or a simulation's truth) the error
``e = p_hat - p`` of a position sensor's raw samples and of each observer is split with the reference's
own tangent ``t`` (the model's ``tangent`` of the reference state): ``e_along = e . t`` (signed: positive
ahead of the tip) and ``e_across = |e - e_along t|``. Table ``real_error_along_across`` and plot
``error_along_across`` (replayed results files: the reference is the logs' ground truth).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

from needlecli.io.results import Group
from needlecli.metrics import reference_tangent, split
from needlecli.reports import PLOTS
from needlecli.reports.tables import TABLES, count_cell

_AXES = ("x", "y", "z")


def _strs(v) -> list[str]:
    return [x.decode() if isinstance(x, bytes) else str(x) for x in np.atleast_1d(v)]


def sources(res: Group) -> list[tuple[str, str, np.ndarray, np.ndarray, np.ndarray]]:
    """``(label, kind, depth (N, M), along (N, M), across (N, M))`` per position sensor (its valid samples;
    kind ``sensor``) and per observer that estimates x, y, z (every reference frame; kind ``observer``);
    NaN where not compared. A sensor identical to the reference (the tracker itself) is left out."""
    truth = res.data["truth"]
    names = _strs(truth.attrs["names"])
    t = reference_tangent(res) if all(a in names for a in _AXES) else None
    if t is None:
        return []
    cols = [names.index(a) for a in _AXES]
    ref = np.asarray(truth.data["state"], dtype=float)[..., cols]
    ok_run = (np.asarray(truth.data["status"]).astype(str) == "ok")[:, None]
    depth = np.asarray(res.data["depth"], dtype=float)
    depth = np.broadcast_to(depth, ref.shape[:2]) if depth.ndim == 1 else depth
    have = np.isfinite(ref).all(-1) & np.isfinite(t).all(-1) & ok_run
    out = []
    for name, g in res.data.get("measurements", Group()).data.items():
        if str(g.attrs.get("type", "")) != "position":
            continue
        ch = _strs(g.attrs["names"])
        if not all(a in ch for a in _AXES):
            continue
        idx = np.asarray(g.data["index"])
        val = np.asarray(g.data["value"], dtype=float)[..., [ch.index(a) for a in _AXES]]
        use = np.asarray(g.data["valid"]) & have[:, idx]
        err = val - ref[:, idx]
        if use.any() and np.nanmax(np.where(use, np.linalg.norm(err, axis=-1), np.nan)) < 1e-9:
            continue  # the reference's own stream
        al, ac = split(err, t[:, idx])
        out.append((f"{name} (raw measurements)", "sensor", depth[:, idx], np.where(use, al, np.nan), np.where(use, ac, np.nan)))
    for obs, g in res.data.get("estimates", Group()).data.items():
        st_names = _strs(g.attrs.get("names", []))
        if not all(a in st_names for a in _AXES):
            continue
        est = np.asarray(g.data["state"], dtype=float)[..., [st_names.index(a) for a in _AXES]]
        ok = have & (np.asarray(g.data["status"]).astype(str) == "ok")[:, None]
        al, ac = split(est - ref, t)
        frames = have.any(0)  # the reference's frames only (replayed trials: the tracker's)
        out.append((obs, "observer", depth[:, frames], np.where(ok, al, np.nan)[:, frames], np.where(ok, ac, np.nan)[:, frames]))
    return out


def _mean(v: np.ndarray) -> float:
    v = v[np.isfinite(v)]
    return float(v.mean()) if v.size else float("nan")


@TABLES.register("real_error_along_across")
def real_error_along_across(res: Group, errors=None) -> pd.DataFrame:
    """Tip position error [mm] split along the needle (the reference's tangent: signed, positive ahead
    of the tip; and its magnitude) and across it: each position sensor's raw samples at their valid
    frames and each observer at every reference frame (on recorded data the EM tracker), with the
    error's magnitude beside them; the mean over frames, and per 20 mm of inserted depth the mean along
    and across."""
    from needlecli.reports.plots import length_scale

    scale = length_scale(res)
    rows = []
    n_runs = res.data["truth"].data["state"].shape[0]
    for label, _kind, depth, al, ac in sources(res):
        al, ac = scale * al, scale * ac
        row = {"Source": label, "Frames": int(np.isfinite(al).sum()), "E_xyz mean": _mean(np.hypot(al, ac)),
               "Along mean (signed)": _mean(al), "Along mean, magnitude": _mean(np.abs(al)), "Across mean": _mean(ac)}
        d = scale * depth
        for lo in (0, 20, 40, 60):
            m = (d >= lo) & (d < lo + 20)
            row[f"{lo}-{lo + 20} mm along / across"] = (f"{_mean(np.where(m, al, np.nan)):.2f} / "
                                                         f"{_mean(np.where(m, ac, np.nan)):.2f}")
        row["Runs"] = count_cell(int(np.isfinite(al).any(1).sum()), n_runs)
        rows.append(row)
    return pd.DataFrame(rows)


@PLOTS.register("error_along_across")
def error_along_across(res: Group, errors, path_stem: Path) -> Path | None:
    """Along-needle (signed) and across-needle tip error against inserted depth: each observer's mean
    over runs at the reference frames (one colour per observer), each position sensor's raw samples as
    grey points; replayed results files only (None otherwise)."""
    from needlecli.reports.plots import (
        PlotSkipped,
        curve_against_depth,
        length_scale,
        observer_style,
        outside_legend,
        save_figure,
        subplots,
    )

    if str(res.attrs.get("truth_kind", "simulation")) == "simulation" or "estimates" not in res.data:
        return None
    src = sources(res)
    if not src:
        raise PlotSkipped("no position sensor or observer to compare with a reference tangent")
    scale = length_scale(res)
    fig, axes = subplots(2, 1, figsize=(7.5, 6.0), sharex=True)
    handles = {}
    for label, kind, depth, al, ac in src:
        for ax, v in zip(axes, (al, ac)):
            if kind == "sensor":
                fin = np.isfinite(v[0])
                (h,) = ax.plot(scale * depth[0][fin], scale * v[0][fin], ".", ms=3, color="0.55", label=label,
                               gid=f"sensor:{label}")
            else:
                d, m, lo, hi, _ = curve_against_depth(scale * depth, scale * v)
                st = observer_style(label, n=d.size)
                (h,) = ax.plot(d, m, lw=1.4, label=label, **st)
                ax.fill_between(d, lo, hi, alpha=0.15, color=st["color"], lw=0)
            handles.setdefault(label, h)
    axes[0].axhline(0.0, color="k", lw=0.6)
    axes[0].set_ylabel("error along the needle [mm]\n(+: ahead of the tip)")
    axes[1].set_ylabel("error across the needle [mm]")
    axes[1].set_xlabel("inserted depth [mm]")
    for ax in axes:
        ax.grid(alpha=0.3)
    outside_legend(fig, handles.values(), handles.keys(), ncol=3)
    fig.suptitle(f"{res.attrs.get('name', '')}: tip error along and across the needle "
                 "(observers: mean and 5-95 % over runs; sensor: the first run's samples)", fontsize=9)
    return save_figure(fig, Path(f"{path_stem}_error_along_across.png"))
