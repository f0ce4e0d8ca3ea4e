"""The high-gain observer and SO(3) observer papers: Table I of the first (x, pitch and roll errors of the
high-gain observer); the second's rotation error against insertion distance (a convergence table, the reduction per half turn of
the arc, and the Fig. 3 plot of the error against distance per input case)."""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import pandas as pd

from needlecli.io.results import Group
from needlecli.metrics import ErrorSet, depth_axis
from needlecli.reports.plots import (
    PLOTS,
    PlotSkipped,
    curve_against_depth,
    observer_style,
    outside_legend,
    plt,
    run_depths,
    save_figure,
    subplots,
)
from needlecli.reports.tables import TABLES, count_cell

_TABLE1_STATS = ("Average Absolute Estimation Error", "RMSE", "Standard Deviation")


def _kept(res: Group, obs: str) -> np.ndarray:
    truth = res.data["truth"]
    g = res.data["estimates"].data[obs]
    return np.nonzero((truth.data["status"] == "ok") & (g.data["status"] == "ok"))[0]


def _x_error(res: Group, obs: str) -> np.ndarray | None:
    """``|x_hat - x|`` ``(N_kept, T)`` in the model's length unit, when both carry x."""
    truth = res.data["truth"]
    g = res.data["estimates"].data[obs]
    tn, en = list(truth.attrs["names"]), list(g.attrs["names"])
    if "x" not in tn or "x" not in en:
        return None
    keep = _kept(res, obs)
    return np.abs(g.data["state"][keep, :, en.index("x")] - truth.data["state"][keep, :, tn.index("x")])


@TABLES.register("x_pitch_roll_error")
def x_pitch_roll_error(res: Group, errors: dict[str, ErrorSet]) -> pd.DataFrame:
    """The high-gain observer paper's Table I: average absolute estimation error, RMSE and standard deviation (of the absolute
    error) of x [mm], beta and gamma [rad], over all kept runs and time steps; Max: the largest absolute
    error (the high-gain observer paper's simulation states maxima); Final: mean absolute error at the last step. Paper
    (experiments): e_x 2e-14 / 5e-13 / 5e-13 mm, e_beta 0.02 / 0.04 / 0.037 rad; (simulation) maxima of
    1e-14 mm (x) and 0.05 rad (gamma)."""
    unit = res.attrs.get("length_unit", "mm")
    rows = []
    for obs, es in errors.items():
        items = []
        ex = _x_error(res, obs)
        if ex is not None:
            items.append((f"e_x [{unit}]", ex, len(_kept(res, obs))))
        for q, label in (("E_beta", "e_beta [rad]"), ("E_gamma", "e_gamma [rad]")):
            if q in es.quantities:
                qe = es.quantities[q]
                items.append((label, np.deg2rad(qe.values), len(qe.runs)))
        for label, v, kept in items:
            finite = v[np.isfinite(v)]
            last = v[:, -1][np.isfinite(v[:, -1])] if v.ndim == 2 and v.shape[1] else finite
            row = {"Observer": obs, "Error": label}
            if finite.size:
                row.update({_TABLE1_STATS[0]: float(np.mean(finite)), _TABLE1_STATS[1]: float(np.sqrt(np.mean(finite**2))),
                            _TABLE1_STATS[2]: float(np.std(finite)), "Max": float(np.max(finite))})
            else:
                row.update({k: np.nan for k in (*_TABLE1_STATS, "Max")})
            row["Final"] = float(np.mean(last)) if last.size else np.nan
            row["Runs"] = count_cell(kept, es.n_runs)
            rows.append(row)
    df = pd.DataFrame(rows, columns=["Observer", "Error", *_TABLE1_STATS, "Max", "Final", "Runs"])
    note = _convergence_note(res)
    if note:
        df.attrs["note"] = note
    return df


def _convergence_note(res: Group) -> str:
    """What each high-gain observer's linear error dynamics allow within the run: its slowest error pole
    (``theta * eig(A + L C)``, recorded by the observer), the time constant and the time to 1 % of an
    initial error, against the run's duration."""
    duration = float(res.data["time"][-1])
    parts = []
    for obs, g in res.data.get("estimates", Group()).data.items():
        poles = g.attrs.get("error_poles")
        if poles is None or not len(np.atleast_1d(poles)):
            continue
        slow = -float(np.max(np.atleast_1d(poles)))
        if slow <= 0:
            parts.append(f"{obs} (theta {float(g.attrs.get('theta', np.nan)):g}): not stable")
            continue
        t1 = np.log(100.0) / slow
        verdict = f"within the {duration:.0f} s run" if t1 <= duration else f"not within the {duration:.0f} s run"
        parts.append(f"{obs} (theta {float(g.attrs.get('theta', np.nan)):g}): slowest error pole {slow:.3g} /s, "
                     f"time constant {1 / slow:.3g} s, 1 % of an initial error after {t1:.3g} s, {verdict}")
    return ("Convergence of the linear error dynamics: " + "; ".join(parts) + ".") if parts else ""


# ---------------------------------------------------------------------------------------------- the SO(3) observer paper
def _cases(res: Group, runs: np.ndarray) -> list[tuple[str, np.ndarray]]:
    """Positions in ``runs`` grouped by input case (all together when the inputs have no cases)."""
    inputs = res.data.get("inputs", Group())
    labels = inputs.attrs.get("case_labels")
    case = inputs.data.get("case")
    if labels is None or case is None:
        return [("all runs", np.arange(len(runs)))]
    out = []
    for i, lbl in enumerate(labels):
        sel = np.nonzero(np.asarray(case)[runs] == i)[0]
        if sel.size:
            out.append((str(lbl), sel))
    return out


def _half_turn(res: Group) -> float | None:
    """Insertion distance of half a turn of the arc, ``pi / kappa`` (truth's mean curvature)."""
    k = res.data["truth"].data.get("params", Group()).data.get("kappa")
    if k is None:
        return None
    k = float(np.nanmean(k))
    return float(np.pi / k) if k > 0 else None


def _rotation_groups(res: Group, errors: dict[str, ErrorSet], with_runs: bool = False):
    """``(observer, case label, E_R (n, T) deg, number of runs)`` for every observer with a rotation
    error (and the runs' indices ``(n,)`` last, ``with_runs``)."""
    for obs, es in errors.items():
        qe = es.quantities.get("E_R")
        if qe is None or qe.values.shape[0] == 0:
            continue
        for label, sel in _cases(res, qe.runs):
            yield (obs, label, qe.values[sel], es.n_runs) + ((qe.runs[sel],) if with_runs else ())


def _first_below(depth: np.ndarray, curve: np.ndarray, level: float) -> float:
    """Depth from which ``curve`` stays below ``level`` (NaN if it does not end below it)."""
    above = np.nonzero(~(curve < level))[0]
    if above.size == 0:
        return float(depth[0])
    if above[-1] == len(curve) - 1:
        return np.nan
    return float(depth[above[-1] + 1])


@TABLES.register("rotation_convergence")
def rotation_convergence(res: Group, errors: dict[str, ErrorSet]) -> pd.DataFrame:
    """The SO(3) observer paper: rotation error E_R (mean over the case's kept runs, deg) against insertion distance, and
    the distance from which it stays under 10 and 5 deg. Paper: about 7 cm of insertion for an adequate
    estimate from 90 deg, and about 80 % less error per half turn of the arc."""
    depth = depth_axis(res)
    unit = res.attrs.get("length_unit", "mm")
    marks = [d for d in (50.0, 70.0, 100.0, 150.0, 200.0, 300.0) if d <= depth[-1] + 1e-9]
    rows = []
    for obs, label, e, n_runs in _rotation_groups(res, errors):
        with warnings.catch_warnings():  # steps without truth (replays): NaN
            warnings.simplefilter("ignore", RuntimeWarning)
            m = np.nanmean(e, 0)
        row = {"Observer": obs, "Case": label, "Runs": count_cell(e.shape[0], n_runs), "E_R at 0 [deg]": float(m[0])}
        for d in marks:
            row[f"at {d:g} {unit}"] = float(m[min(np.searchsorted(depth, d - 1e-9), len(m) - 1)])
        row["final [deg]"] = float(m[-1])
        row[f"under 10 deg from [{unit}]"] = _first_below(depth, m, 10.0)
        row[f"under 5 deg from [{unit}]"] = _first_below(depth, m, 5.0)
        rows.append(row)
    df = pd.DataFrame(rows)
    note = _radius_reading_note(res, errors)
    if note:
        df.attrs["note"] = note
    return df


def _radius_reading_note(res: Group, errors: dict[str, ErrorSet]) -> str:
    """What this file says about the SO(3) observer paper's two claims, for every observer and case starting about 90 deg
    off: the error at 7 cm, after one half turn and the reduction over the second, and whether "about
    7 cm from 90 deg" holds (under 10 deg, an adequate estimate, by 8 cm at the latest)."""
    depth = depth_axis(res)
    half = _half_turn(res)
    unit = res.attrs.get("length_unit", "mm")
    if depth[-1] < 70.0 - 1e-9:
        return ""
    parts = []
    with warnings.catch_warnings():  # steps without truth (replays): NaN
        warnings.simplefilter("ignore", RuntimeWarning)
        for obs, label, e, _ in _rotation_groups(res, errors):
            m = np.nanmean(e, 0)
            if not (80.0 <= m[0] <= 100.0):
                continue

            def at(d, m=m):
                return float(m[min(np.searchsorted(depth, d - 1e-9), len(m) - 1)])

            text = f"{obs}, {label}: E_R {m[0]:.0f} deg at 0, {at(70.0):.0f} deg at 70 {unit}"
            if half is not None and 2 * half <= depth[-1] + 1e-9:
                e1, e2 = at(half), at(2 * half)
                text += f", {e1:.0f} deg after one half turn ({half:.0f} {unit}), {100 * (1 - e2 / e1):.0f} % less over the second"
            below = _first_below(depth, m, 10.0)
            held = np.isfinite(below) and below <= 80.0 + 1e-9  # "about 7 cm": by 8 cm at the latest
            text += (f": the SO(3) observer paper's about 7 cm from 90 deg holds (under 10 deg from {below:.0f} {unit})" if held else
                     ": the SO(3) observer paper's about 7 cm from 90 deg is not reproduced" +
                     (f" (under 10 deg from {below:.0f} {unit})" if np.isfinite(below) else " (never under 10 deg)"))
            parts.append(text)
    k = res.data["truth"].data.get("params", Group()).data.get("kappa")
    radius = f" (arc radius {1.0 / float(np.nanmean(k)):.1f} {unit})" if k is not None and np.nanmean(k) > 0 else ""
    return (f"Here{radius}: " + "; ".join(parts) + ".") if parts else ""


@TABLES.register("rotation_half_turns")
def rotation_half_turns(res: Group, errors: dict[str, ErrorSet]) -> pd.DataFrame:
    """The SO(3) observer paper: rotation error after each half turn of the arc (pi / kappa of insertion) and its
    reduction per half turn, 1 - E_R(j) / E_R(j - 1), from the case's mean error (at most 12 rows per
    case: with more half turns, every k-th and the mean reduction per half turn over the k). Paper:
    about 80 % per half turn with a hand-tuned gain, and about 7 cm of insertion for an adequate estimate
    from 90 deg."""
    depth = depth_axis(res)
    unit = res.attrs.get("length_unit", "mm")
    half = _half_turn(res)
    cols = ["Observer", "Case", "Half turns", f"Distance [{unit}]", "E_R mean [deg]", "E_R max [deg]",
            "Reduction [%]", "Runs"]
    if half is None:
        return pd.DataFrame(columns=cols)
    n_half = int(np.floor(depth[-1] / half + 1e-9))
    step = max(1, int(np.ceil(n_half / 12)))  # at most 12 rows per case; reductions stay per half turn
    rows = []
    for obs, label, e, n_runs in _rotation_groups(res, errors):
        prev = None
        for j in range(0, n_half + 1, step):
            i = min(np.searchsorted(depth, j * half - 1e-9), len(depth) - 1)
            with warnings.catch_warnings():  # steps without truth (replays): NaN
                warnings.simplefilter("ignore", RuntimeWarning)
                m, mx = float(np.nanmean(e[:, i])), float(np.nanmax(e[:, i]))
            red = 100.0 * (1.0 - (m / prev) ** (1.0 / step)) if prev else np.nan
            rows.append({"Observer": obs, "Case": label, "Half turns": j, f"Distance [{unit}]": float(depth[i]),
                         "E_R mean [deg]": m, "E_R max [deg]": mx,
                         "Reduction [%]": red, "Runs": count_cell(e.shape[0], n_runs)})
            prev = m
    df = pd.DataFrame(rows, columns=cols)
    note = _radius_reading_note(res, errors)
    if note:
        df.attrs["note"] = note
    return df


@PLOTS.register("rotation_error")
def rotation_error_plot(res: Group, errors: dict[str, ErrorSet], path_stem: Path, max_runs: int = 20) -> Path | None:
    """The SO(3) observer paper's Fig. 3: rotation error against insertion distance, one panel per input case, one colour
    per observer (thin: single runs, thick: mean), from the steps where truth exists; dotted verticals
    mark half turns of the arc (pi / kappa) where the insertion reaches one."""
    groups = list(_rotation_groups(res, errors, with_runs=True))
    if not groups:
        return None
    cases = list(dict.fromkeys(g[1] for g in groups))
    depth = run_depths(res)
    unit = res.attrs.get("length_unit", "mm")
    fig, axs = subplots(1, len(cases), figsize=(5.5 * len(cases), 4.0), squeeze=False, sharey=True)
    handles = {}
    kinds = set()
    for obs, label, e, _, runs in groups:
        ax = axs[0, cases.index(label)]
        st = observer_style(obs)
        thin = {k: v for k, v in st.items() if k not in ("marker", "markevery", "ms")}
        for r in range(min(e.shape[0], max_runs)):
            fin = np.isfinite(e[r]) & np.isfinite(depth[runs[r]])
            if fin.sum() >= 2:
                ax.plot(depth[runs[r], fin], e[r, fin], lw=0.5, alpha=0.4, **thin)
        d, m, _, _, kind = curve_against_depth(depth[runs], e)
        if d.size:
            kinds.add(kind)
            (line,) = ax.plot(d, m, lw=1.8, **{**st, **observer_style(obs, n=d.size)})
            handles.setdefault(obs, line)
    if not handles:
        plt.close(fig)
        raise PlotSkipped("no rotation error where the truth exists")
    half = _half_turn(res)
    reach = float(np.nanmax(depth))
    if half is not None and reach >= half:
        for ax in axs[0]:
            for j in range(1, int(reach / half) + 1):
                line = ax.axvline(j * half, color="grey", lw=0.6, ls=":")
        handles[f"half turns of the arc (pi / kappa = {half:.0f} {unit})"] = line
    for c, ax in zip(cases, axs[0]):
        ax.set_title(c, fontsize=9)
        ax.set_xlabel(f"insertion distance [{unit}]")
        ax.grid(alpha=0.3)
    axs[0, 0].set_ylabel("rotation error E_R [deg]")
    outside_legend(fig, handles.values(), handles.keys())
    what = "thick: mean over runs" + (", binned in depth" if "bins" in kinds else "") + "; thin: single runs"
    fig.suptitle(f"{res.attrs.get('name', '')}: rotation error against insertion distance ({what})", fontsize=10)
    return save_figure(fig, Path(f"{path_stem}_rotation_error.png"))
