"""Seed 003's tables and figures: Table 1 (instantaneous error), Fig. 6 (final-position prediction error
against the depth observed), Figs. 7 and 8 (curvature estimate and its variance against time)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

from needlecli.io.results import Group
from needlecli.metrics import ErrorSet
from needlecli.reports.plots import PLOTS, plt, save_figure
from needlecli.reports.tables import TABLES

_LENGTH_TO_MM = {"mm": 1.0, "m": 1000.0}


@TABLES.register("seed003_table1")
def table1(res: Group, errors: dict[str, ErrorSet]) -> pd.DataFrame:
    """Seed 003 Table 1: instantaneous state estimation error over all runs and the time steps after
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
                         "Runs": f"{len(es.quantities[q].runs)}/{es.n_runs}"})
    return pd.DataFrame(rows, columns=["Observer", "Error", "Mean", "Std", "Max", "Runs"])


def prediction_errors(res: Group) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Per observer with predictions: ``(depths (D,), errors (N_kept, D) in mm)`` of the predicted final
    tip position against the true final position."""
    truth = res.data["truth"]
    names = list(truth.attrs["names"])
    axes = next((ax for ax in (("x", "y", "z"), ("px", "py", "pz")) if all(a in names for a in ax)), None)
    if axes is None:
        return {}
    scale = _LENGTH_TO_MM.get(str(res.attrs.get("length_unit", "mm")), 1.0)
    final_true = truth.data["state"][:, -1, [names.index(a) for a in axes]]
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
    """Final tip position prediction error against the depth observed (seed 003 Fig. 6 as a table;
    paper: under 2 mm once 40 mm are observed)."""
    rows = []
    unit = res.attrs.get("length_unit", "mm")
    for obs, (depths, err) in prediction_errors(res).items():
        for j, d in enumerate(depths):
            e = err[:, j]
            e = e[np.isfinite(e)]
            rows.append({"Observer": obs, f"Depth observed ({unit})": d,
                         "Mean (mm)": float(np.mean(e)) if e.size else np.nan,
                         "Std (mm)": float(np.std(e)) if e.size else np.nan,
                         "Max (mm)": float(np.max(e)) if e.size else np.nan, "Runs": int(e.size)})
    df = pd.DataFrame(rows, columns=["Observer", f"Depth observed ({unit})", "Mean (mm)", "Std (mm)", "Max (mm)", "Runs"])
    df.attrs["keys"] = ["Observer", f"Depth observed ({unit})"]
    return df


@PLOTS.register("prediction")
def prediction_plot(res: Group, errors, path_stem: Path) -> Path | None:
    """Fig. 6: mean and std of the final-position prediction error against the depth observed."""
    data = prediction_errors(res)
    if not data:
        return None
    fig, ax = plt.subplots(figsize=(6.5, 3.6))
    for obs, (depths, err) in data.items():
        m, s = np.nanmean(err, 0), np.nanstd(err, 0)
        ax.errorbar(depths, m, yerr=s, marker="o", capsize=3, label=obs)
    ax.axhline(2.0, color="grey", ls=":", label="2 mm")
    ax.set_xlabel(f"depth observed [{res.attrs.get('length_unit', 'mm')}]")
    ax.set_ylabel("final position prediction error [mm]")
    ax.grid(alpha=0.3)
    ax.legend(fontsize="small")
    ax.set_title(f"{res.attrs.get('name', '')}: prediction of the final tip position")
    return save_figure(fig, Path(f"{path_stem}_prediction.png"))


@PLOTS.register("curvature")
def curvature_plot(res: Group, errors, path_stem: Path) -> Path | None:
    """Figs. 7 and 8: curvature estimate (with the truth) and its variance P_kappa_kappa against time,
    one curve per input case (runs grouped by their input schedule) or the mean over runs."""
    truth = res.data["truth"]
    params = truth.data.get("params", Group()).data
    est = {o: g for o, g in res.data.get("estimates", Group()).data.items() if "kappa" in list(g.attrs["names"])}
    if not est:
        return None
    time = res.data["time"]
    tnames = list(truth.attrs["names"])
    k_true = truth.data["state"][..., tnames.index("kappa")] if "kappa" in tnames else params.get("kappa")
    cases = res.data["inputs"].attrs.get("case_labels")
    case_of = res.data["inputs"].data.get("case")
    if cases is not None and case_of is not None:
        groups = [(str(lbl), np.nonzero(case_of == i)[0]) for i, lbl in enumerate(cases)]
    else:
        groups = [("mean over runs", np.arange(truth.data["state"].shape[0]))]
    fig, axs = plt.subplots(2, 1, figsize=(7, 6), sharex=True)
    for j, (obs, g) in enumerate(est.items()):
        en = list(g.attrs["names"])
        ki = en.index("kappa")
        for c, (label, runs) in enumerate(groups):
            if runs.size == 0:
                continue
            color = f"C{(c + j * len(groups)) % 10}"
            tag = f"{obs}, {label}" if len(est) > 1 or len(groups) > 1 else obs
            axs[0].plot(time, g.data["state"][runs, :, ki].mean(0), ls="--", color=color, label=tag)
            if k_true is not None:
                axs[0].plot(time, np.asarray(k_true)[runs].mean(0), color=color, lw=0.8)
            cov = g.data.get("cov")
            if cov is not None:
                idx = g.data["cov_index"]
                pk = cov[runs, :, ki, ki] if cov.ndim == 4 else cov[runs, :, ki]
                axs[1].semilogy(time[idx], pk.mean(0), color=color, label=tag)
    axs[0].set_ylabel("curvature [1/mm] (truth solid, estimate dashed)")
    axs[1].set_ylabel("P_kappa_kappa")
    axs[1].set_xlabel("time [s]")
    for ax in axs:
        ax.grid(alpha=0.3)
    axs[0].legend(fontsize="x-small", ncol=2)
    fig.suptitle(f"{res.attrs.get('name', '')}: curvature estimate and its variance")
    return save_figure(fig, Path(f"{path_stem}_curvature.png"))
