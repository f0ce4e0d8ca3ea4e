"""The multi-rate UKF paper's tables and figures: Table 1 (instantaneous error), Fig. 6 (final-position prediction error
against the depth observed), Figs. 7 and 8 (curvature estimate and its variance against time)."""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import pandas as pd

from needlecli.io.results import Group
from needlecli.metrics import ErrorSet
from needlecli.reports.plots import (
    CASE_STYLES,
    PLOTS,
    TRUTH_COLOUR,
    PlotSkipped,
    observer_style,
    outside_legend,
    plt,
    save_figure,
    subplots,
)
from needlecli.reports.tables import TABLES, count_cell

_LENGTH_TO_MM = {"mm": 1.0, "m": 1000.0}


@TABLES.register("pose_curvature_error")
def table1(res: Group, errors: dict[str, ErrorSet]) -> pd.DataFrame:
    """The multi-rate UKF paper's Table 1: instantaneous state estimation error over all runs and the time steps after
    initialisation (Mean, Std, Max); paper: E_xyz 0.3/0.1/1.3 mm, E_alpha 0.6/1.1/16.4 deg,
    E_beta 0.9/1.1/11.5 deg, E_kappa 0.0007/0.0006/0.0136 1/mm."""
    rows = []
    for obs, es in errors.items():
        for q, label in (("E_xyz", "E_x,y,z (mm)"), ("E_alpha", "E_alpha (deg)"), ("E_beta", "E_beta (deg)"),
                         ("E_kappa", "E_kappa (1/mm)")):
            if q not in es.quantities:
                continue
            v = es.quantities[q].values[:, 1:]  # after initialisation
            v = v[np.isfinite(v)]
            rows.append({"Observer": obs, "Error": label, "Mean": float(np.mean(v)) if v.size else np.nan,
                         "Std": float(np.std(v)) if v.size else np.nan, "Max": float(np.max(v)) if v.size else np.nan,
                         "Runs": count_cell(len(es.quantities[q].runs), es.n_runs)})
    return pd.DataFrame(rows, columns=["Observer", "Error", "Mean", "Std", "Max", "Runs"])


def prediction_errors(res: Group) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Per observer with predictions: ``(depths (D,), errors (N_kept, D) in mm)`` of the predicted
    final tip position against the true final position (of a replayed trial: its last truth frame)."""
    truth = res.data["truth"]
    names = list(truth.attrs["names"])
    axes = next((ax for ax in (("x", "y", "z"), ("px", "py", "pz")) if all(a in names for a in ax)), None)
    if axes is None:
        return {}
    scale = _LENGTH_TO_MM.get(str(res.attrs.get("length_unit", "mm")), 1.0)
    pos = truth.data["state"][..., [names.index(a) for a in axes]]  # (N, T, 3)
    fin = np.isfinite(pos).all(-1)
    last = pos.shape[1] - 1 - np.argmax(fin[:, ::-1], axis=1)  # each run's last truth sample (replays: a frame)
    final_true = np.where(fin.any(1)[:, None], pos[np.arange(pos.shape[0]), last], np.nan)
    out = {}
    for obs, g in res.data.get("estimates", Group()).data.items():
        pred = g.data.get("prediction")
        if not isinstance(pred, Group) or "final_state" not in pred.data:
            continue
        en = list(g.attrs["names"])
        if not all(a in en for a in axes):
            continue
        fs = pred.data["final_state"][..., [en.index(a) for a in axes]]  # (N, D, 3)
        keep = (truth.data["status"] == "ok") & (g.data["status"] == "ok")
        err = scale * np.linalg.norm(fs[keep] - final_true[keep][:, None, :], axis=-1)
        out[obs] = (np.asarray(pred.data["depth"], dtype=float), err)
    return out


@TABLES.register("prediction")
def prediction_table(res: Group, errors: dict[str, ErrorSet]) -> pd.DataFrame:
    """Final tip position prediction error against the depth observed (the multi-rate UKF paper's Fig. 6 as a table;
    paper: under 2 mm once 40 mm are observed)."""
    rows = []
    unit = res.attrs.get("length_unit", "mm")
    n_runs = res.data["truth"].data["state"].shape[0]
    for obs, (depths, err) in prediction_errors(res).items():
        for j, d in enumerate(depths):
            e = err[:, j]
            e = e[np.isfinite(e)]
            rows.append({"Observer": obs, f"Depth observed ({unit})": d,
                         "Mean (mm)": float(np.mean(e)) if e.size else np.nan,
                         "Std (mm)": float(np.std(e)) if e.size else np.nan,
                         "Max (mm)": float(np.max(e)) if e.size else np.nan, "Runs": count_cell(e.size, n_runs)})
    df = pd.DataFrame(rows, columns=["Observer", f"Depth observed ({unit})", "Mean (mm)", "Std (mm)", "Max (mm)", "Runs"])
    df.attrs["keys"] = ["Observer", f"Depth observed ({unit})"]
    return df


@PLOTS.register("prediction")
def prediction_plot(res: Group, errors, path_stem: Path) -> Path | None:
    """Fig. 6: mean and std of the final-position prediction error against the depth observed; not drawn
    for a single observation depth (one point per observer on a depth axis says nothing a table line does
    not: table prediction)."""
    data = prediction_errors(res)
    if not data:
        return None
    n_depths = {d for depths, _ in data.values() for d in np.atleast_1d(depths).tolist()}
    if len(n_depths) < 2:
        raise PlotSkipped(f"a single observation depth ({', '.join(f'{d:g}' for d in sorted(n_depths))}): "
                          "table prediction gives it")
    fig, ax = subplots(figsize=(6.5, 3.8))
    drawn = 0
    for obs, (depths, err) in data.items():
        with warnings.catch_warnings():  # a depth without any run: NaN, left out below
            warnings.simplefilter("ignore", RuntimeWarning)
            m, s = np.nanmean(err, 0), np.nanstd(err, 0)
        ok = np.isfinite(m)
        if not ok.any():
            continue
        ax.errorbar(depths[ok], m[ok], yerr=s[ok], capsize=3, label=obs, **observer_style(obs, line=False))
        drawn += 1
    if not drawn:
        plt.close(fig)
        raise PlotSkipped("no run has both a prediction and a true final position")
    ax.axhline(2.0, color="grey", ls=":", label="2 mm (the multi-rate UKF paper's probe resolution)")
    ax.set_xlabel(f"depth observed [{res.attrs.get('length_unit', 'mm')}]")
    ax.set_ylabel("final position prediction error [mm]")
    ax.grid(alpha=0.3)
    outside_legend(fig, *ax.get_legend_handles_labels(), ncol=3)
    ax.set_title(f"{res.attrs.get('name', '')}: prediction of the final tip position (mean, std over runs)", fontsize=10)
    return save_figure(fig, Path(f"{path_stem}_prediction.png"))


def _variance_unit(unit: str) -> str:
    return f"{unit}^2" if "/" not in unit else f"({unit})^2"


@PLOTS.register("curvature")
def curvature_plot(res: Group, errors, path_stem: Path) -> Path | None:
    """Figs. 7 and 8: curvature estimate (with the truth where it exists) and its variance P_kappa_kappa
    against time, per input case (runs grouped by their input schedule: one line style each) or the mean
    over runs; one colour per observer."""
    truth = res.data["truth"]
    est = {o: g for o, g in res.data.get("estimates", Group()).data.items() if "kappa" in list(g.attrs["names"])}
    if not est:
        return None
    time = np.asarray(res.data["time"])
    tnames = list(truth.attrs["names"])
    params = truth.data.get("params", Group()).data
    if "kappa" in tnames:
        k_true = np.asarray(truth.data["state"][..., tnames.index("kappa")], dtype=float)
    elif "kappa" in params and res.attrs.get("source") != "replay":  # a replay's parameters are the config's
        k_true = np.asarray(params["kappa"], dtype=float)
    else:
        k_true = None
    if k_true is not None and not np.isfinite(k_true).any():
        k_true = None
    cases = res.data["inputs"].attrs.get("case_labels")
    case_of = res.data["inputs"].data.get("case")
    if cases is not None and case_of is not None:
        groups = [(str(lbl), np.nonzero(np.asarray(case_of) == i)[0]) for i, lbl in enumerate(np.atleast_1d(cases))]
        groups = [(lbl, r) for lbl, r in groups if r.size]
    else:
        groups = [("mean over runs", np.arange(truth.data["state"].shape[0]))]
    with_cov = {o: g for o, g in est.items() if g.data.get("cov") is not None}
    fig, axs = subplots(2 if with_cov else 1, 1, figsize=(7, 6.2 if with_cov else 3.6), sharex=True, squeeze=False)
    axs = axs[:, 0]
    unit = ""
    for obs, g in est.items():
        en = list(g.attrs["names"])
        ki = en.index("kappa")
        unit = list(g.attrs.get("units", [""] * len(en)))[ki]
        ok = np.asarray(g.data["status"]).astype(str) == "ok"
        for c, (_, runs) in enumerate(groups):
            runs = runs[ok[runs]]
            if runs.size == 0:
                continue
            st = observer_style(obs, ls=CASE_STYLES[c % len(CASE_STYLES)] if len(groups) > 1 else None, n=len(time))
            axs[0].plot(time, g.data["state"][runs, :, ki].mean(0), lw=1.4, **st)
            if obs in with_cov:
                cov = g.data["cov"]
                idx = np.asarray(g.data["cov_index"])
                pk = cov[runs, :, ki, ki] if cov.ndim == 4 else cov[runs, :, ki]
                axs[1].semilogy(time[idx], pk.mean(0), lw=1.4, **st)
    if k_true is not None:
        for c, (_, runs) in enumerate(groups):
            kt = k_true[runs]
            has = np.isfinite(kt)
            m = np.where(has, kt, 0.0).sum(0) / np.maximum(has.sum(0), 1)
            fin = has.any(0)
            if fin.sum() >= 2:
                axs[0].plot(time[fin], m[fin], ls=CASE_STYLES[c % len(CASE_STYLES)], color=TRUTH_COLOUR, lw=0.8, gid="truth")
    from matplotlib.lines import Line2D

    handles = [Line2D([], [], lw=1.4, **observer_style(o, ls="-" if len(groups) > 1 else None)) for o in est]
    labels = list(est)
    if k_true is not None:
        handles.append(Line2D([], [], color=TRUTH_COLOUR, lw=0.8))
        labels.append("truth")
    if len(groups) > 1:
        handles += [Line2D([], [], color="0.3", ls=CASE_STYLES[c % len(CASE_STYLES)]) for c in range(len(groups))]
        labels += [lbl for lbl, _ in groups]
    outside_legend(fig, handles, labels)
    axs[0].set_ylabel(f"curvature [{unit}]")
    if with_cov:
        axs[1].set_ylabel(f"P_kappa_kappa [{_variance_unit(unit)}]")
    axs[-1].set_xlabel("time [s]")
    for ax in axs:
        ax.grid(alpha=0.3)
    what = "mean over the runs of each input case" if len(groups) > 1 else "mean over runs"
    title = "curvature estimate" + (" against the truth" if k_true is not None else " (no true curvature in the file)")
    title += " and its variance" if with_cov else ""
    fig.suptitle(f"{res.attrs.get('name', '')}: {title} ({what})", fontsize=10)
    return save_figure(fig, Path(f"{path_stem}_curvature.png"))
