"""Filter consistency (Bar-Shalom, Li and Kirubarajan, *Estimation with Applications to Tracking and
Navigation*, sec. 5.4): does an observer's covariance describe its actual errors?

* NEES, the normalised estimation error squared ``e^T P^-1 e`` of each run at each stored covariance
  (``e = x_hat - x`` over the states the truth carries, angles wrapped), and per state ``e_i^2 / P_ii``;
* NIS, the normalised innovation squared ``nu^T S^-1 nu`` of each sample an observer used, per channel,
  as the observer recorded it (``/estimates/<observer>/nis/<channel>``).

Averaged over the ``N`` runs at one time (ANEES, ANIS), a consistent filter gives ``N`` times a chi-square
with ``N d`` degrees of freedom (``d`` the dimension): the two-sided 95 % interval is
``[chi2_0.025(N d), chi2_0.975(N d)] / N`` around ``d``. Table ``consistency`` gives the average over runs
and time after initialisation with that interval for the number of runs, the share of times outside the
per-time interval, when it was above (optimistic), and a verdict; plot ``nees_vs_depth`` the ANEES of
the full state and of each state against depth inside its interval.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd
from scipy.stats import chi2

from needlecli.io.results import Group
from needlecli.metrics import ErrorSet
from needlecli.numerics import angle_diff
from needlecli.reports.plots import PLOTS, PlotSkipped, observer_style, outside_legend, run_depths, save_figure, subplots
from needlecli.reports.tables import TABLES, count_cell

PROBABILITY = 0.95


def chi2_bounds(runs, dof, p: float = PROBABILITY) -> tuple[np.ndarray, np.ndarray]:
    """Two-sided ``p`` interval of the average over ``runs`` of chi-square(``dof``) variables: ANEES or
    ANIS of a consistent filter (NaN where ``runs`` is 0)."""
    runs = np.asarray(runs, dtype=float)
    with np.errstate(all="ignore"):
        nd = np.where(runs > 0, runs * dof, np.nan)
        return chi2.ppf(0.5 - p / 2, nd) / runs, chi2.ppf(0.5 + p / 2, nd) / runs


def verdict(value: float, lo: float, hi: float) -> str:
    """consistent inside the interval; optimistic above it (errors larger than the covariance says),
    pessimistic below it (a covariance larger than the errors)."""
    if not np.isfinite(value):
        return "n/a"
    return "optimistic" if value > hi else "pessimistic" if value < lo else "consistent"


@dataclass
class Normalised:
    """Normalised squared errors of one observer: ``values (N_kept, K)`` at times ``time (K,)`` (NaN where
    not defined), their dimension ``dof``, the kept runs ``runs`` and the depth ``depth (N_kept, K)``."""

    label: str
    values: np.ndarray
    dof: int
    time: np.ndarray
    depth: np.ndarray
    runs: np.ndarray


def _truth_columns(res: Group, g: Group) -> tuple[list[int], np.ndarray, list[str]]:
    """Indices of the estimate's states that have a truth, the truth ``(N, T, k)`` of those states, names."""
    truth = res.data["truth"]
    tn = list(truth.attrs["names"])
    en = list(g.attrs["names"])
    params = truth.data.get("params", Group()).data if res.attrs.get("source") != "replay" else {}
    cols, tv, names = [], [], []
    for i, k in enumerate(en):
        if k in tn:
            v = truth.data["state"][..., tn.index(k)]
        elif k in params:  # a truth parameter the observer estimates (kappa of the plain unicycle)
            v = np.asarray(params[k], dtype=float)
        else:
            continue
        if np.isfinite(v).any():
            cols.append(i)
            tv.append(v)
            names.append(k)
    return cols, (np.stack(tv, -1) if tv else np.zeros((0,))), names


def nees(res: Group, obs: str) -> list[Normalised] | None:
    """NEES of the full state (over the states with a truth) and of each of them, at the stored
    covariances after initialisation (the first is the initial one), or None without a covariance."""
    g = res.data["estimates"].data[obs]
    cov = g.data.get("cov")
    if cov is None:
        return None
    cols, tv, names = _truth_columns(res, g)
    if not cols:
        return []
    idx = np.asarray(g.data["cov_index"])
    after = idx > 0
    idx, cov = idx[after], np.asarray(cov)[:, after]
    truth = res.data["truth"]
    keep = np.nonzero((truth.data["status"] == "ok") & (g.data["status"] == "ok"))[0]
    angles = set(g.attrs.get("angles", [])) | set(truth.attrs.get("angles", []))
    x = g.data["state"][keep][:, idx][..., cols]
    t = tv[keep][:, idx]
    e = np.stack([angle_diff(x[..., j], t[..., j]) if names[j] in angles else x[..., j] - t[..., j]
                  for j in range(len(cols))], -1)  # (N, K, k), angles wrapped
    time = np.asarray(res.data["time"])[idx]
    depth = run_depths(res)[keep][:, idx]
    full = cov.ndim == 4
    if full:
        P = cov[keep][:, :, cols][..., cols]
        var = np.diagonal(P, axis1=-2, axis2=-1)
    else:
        var = cov[keep][..., cols]
    with np.errstate(all="ignore"):
        per_state = e**2 / var
        out = []
        if full:
            ok = np.isfinite(e).all(-1) & np.isfinite(P).all((-2, -1))
            A, b = np.where(ok[..., None, None], P, np.eye(len(cols))), np.where(ok[..., None], e, 0.0)[..., None]
            try:
                sol = np.linalg.solve(A, b)
            except np.linalg.LinAlgError:  # a singular P somewhere (a state no noise reaches): its pseudo-inverse
                sol = np.linalg.pinv(A, hermitian=True) @ b
            q = np.where(ok, np.einsum("nki,nki->nk", e, sol[..., 0]), np.nan)
            out.append(Normalised(f"all states ({', '.join(names)})", q, len(cols), time, depth, keep))
        else:  # a diagonal covariance: the states' sum, as if uncorrelated (said in the label)
            ok = np.isfinite(per_state).all(-1)
            out.append(Normalised(f"all states ({', '.join(names)}; diagonal of P only)",
                                  np.where(ok, per_state.sum(-1), np.nan), len(cols), time, depth, keep))
    for j, k in enumerate(names):
        out.append(Normalised(k, per_state[..., j], 1, time, depth, keep))
    return out


def nis(res: Group, obs: str) -> list[Normalised]:
    """NIS of every channel an observer recorded it for (the samples it used after initialisation)."""
    g = res.data["estimates"].data[obs]
    rec = g.data.get("nis")
    if not isinstance(rec, Group):
        return []
    truth = res.data["truth"]
    keep = np.nonzero((truth.data["status"] == "ok") & (g.data["status"] == "ok"))[0]
    meas = res.data.get("measurements", Group()).data
    depth = run_depths(res)
    out = []
    for ch, q in rec.data.items():
        if ch not in meas:
            continue
        m = meas[ch]
        index = np.asarray(m.data["index"])
        dof = int(np.asarray(m.data["value"]).shape[-1])
        out.append(Normalised(ch, np.asarray(q, dtype=float)[keep], dof, np.asarray(m.data["t"]),
                              depth[keep][:, np.minimum(index, depth.shape[1] - 1)], keep))
    return out


def lasting_spans(time: np.ndarray, flag: np.ndarray, limit: int = 3) -> str:
    """The time spans (s) over which ``flag`` lasts, e.g. ``0.1-5.9``: where it holds at most of the times
    within ``min_span`` around (a moving majority), for at least ``min_span`` (an average over runs leaves
    its 95 % interval at 2.5 % of the times by chance: those single times are not spans); at most
    ``limit`` spans in time order; ``min_span`` is 1 s or 2 % of the duration."""
    if not flag.any() or len(time) < 2:
        return ""
    min_span = max(1.0, 0.02 * float(time[-1] - time[0]))
    w = max(1, int(round(min_span / float(np.median(np.diff(time))))))
    c = np.concatenate([[0.0], np.cumsum(flag, dtype=float)])
    lo = np.clip(np.arange(len(flag)) - w // 2, 0, len(flag))
    hi = np.clip(np.arange(len(flag)) + w - w // 2, 0, len(flag))
    major = (c[hi] - c[lo]) / np.maximum(hi - lo, 1) > 0.5
    f = np.concatenate([[False], major, [False]])
    starts = np.nonzero(f[1:] & ~f[:-1])[0]
    ends = np.nonzero(~f[1:] & f[:-1])[0] - 1
    kept = [(a, b) for a, b in zip(starts, ends) if time[b] - time[a] >= 0.999 * min_span]
    text = ", ".join(f"{time[a]:.1f}-{time[b]:.1f}" for a, b in kept[:limit])
    return text + (f" and {len(kept) - limit} more" if len(kept) > limit else "")


def summarise(nv: Normalised) -> dict:
    """ANEES / ANIS over runs and time, its interval for the number of runs, and how the per-time
    average sits in its own interval."""
    fin = np.isfinite(nv.values)
    n_t = fin.sum(0)  # runs with a value at each time
    at = n_t > 0
    with np.errstate(all="ignore"):
        avg_t = np.where(fin, nv.values, 0.0).sum(0) / np.maximum(n_t, 1)
    lo_t, hi_t = chi2_bounds(n_t, nv.dof)
    runs = int(fin.any(1).sum())
    mean = float(nv.values[fin].mean()) if fin.any() else np.nan
    lo, hi = (float(b) for b in chi2_bounds(runs, nv.dof))
    above, below = at & (avg_t > hi_t), at & (avg_t < lo_t)
    n_at = max(int(at.sum()), 1)
    return {"Dof": nv.dof, "Mean": mean, "95% low": lo, "95% high": hi, "Verdict": verdict(mean, lo, hi),
            "Above [% of times]": 100.0 * above.sum() / n_at, "Below [% of times]": 100.0 * below.sum() / n_at,
            "Optimistic over [s]": lasting_spans(nv.time[at], above[at]), "Runs": count_cell(runs, len(nv.runs)),
            "_avg": avg_t, "_lo": lo_t, "_hi": hi_t, "_at": at}


_COLUMNS = ["Observer", "Test", "Of", "Dof", "Mean", "95% low", "95% high", "Verdict", "Above [% of times]",
            "Below [% of times]", "Optimistic over [s]", "Runs"]


@TABLES.register("consistency")
def consistency_table(res: Group, errors: dict[str, ErrorSet] | None = None) -> pd.DataFrame:
    """Consistency of every observer with a covariance: ANEES (normalised estimation error squared,
    angles wrapped, averaged over runs and the stored covariances after initialisation) of the states
    with a truth and of each state, ANIS (normalised innovation squared of the samples used; those a
    gate rejected not counted) per measurement channel, each beside the two-sided 95 % chi-square
    interval of an average over the runs (a consistent filter: Mean = Dof); optimistic above it (errors
    larger than the covariance says), pessimistic below; how often the average at one time left its own
    interval, and over which times (spans of at least 1 s or 2 % of the run) it stayed above it."""
    rows, skipped, no_nis, unused = [], [], [], []
    for obs, g in res.data.get("estimates", Group()).data.items():
        nv = nees(res, obs)
        if nv is None:
            skipped.append(obs)
            continue
        for test, items in (("ANEES", nv), ("ANIS", nis(res, obs))):
            for it in items:
                if test == "ANIS" and not np.isfinite(it.values).any():
                    unused.append(f"{obs} {it.label}")
                    continue
                s = summarise(it)
                rows.append({"Observer": obs, "Test": test, "Of": it.label,
                             **{k: v for k, v in s.items() if not k.startswith("_")}})
        if not isinstance(g.data.get("nis"), Group):
            no_nis.append(obs)
    df = pd.DataFrame(rows, columns=_COLUMNS)
    notes = []
    if skipped:
        notes.append(f"Without a covariance (not tabulated): {', '.join(skipped)}.")
    if no_nis:
        notes.append(f"Innovations not recorded (no ANIS): {', '.join(no_nis)}.")
    if unused:
        notes.append(f"No sample used after initialisation (no ANIS): {', '.join(unused)}.")
    if notes:
        df.attrs["note"] = " ".join(notes)
    df.attrs["keys"] = ["Observer", "Test", "Of"]
    return df


@PLOTS.register("nees_vs_depth")
def nees_vs_depth(res: Group, errors, path_stem: Path) -> Path | None:
    """ANEES against inserted depth, of the full state and of each state (one panel each), with the
    two-sided 95 % interval for the runs at each time (band) and the consistent value (dotted)."""
    estimates = res.data.get("estimates", Group()).data
    with_cov = [o for o, g in estimates.items() if g.data.get("cov") is not None]
    if not with_cov:
        return None
    curves: dict[str, list] = {}  # panel -> [(observer, depth, avg, lo, hi, dof)]
    for obs in with_cov:
        for i, it in enumerate(nees(res, obs) or []):
            s = summarise(it)
            at = s["_at"]
            if not at.any():
                continue
            fin = np.isfinite(it.values)
            d = np.where(fin, it.depth, 0.0).sum(0) / np.maximum(fin.sum(0), 1)  # mean depth of the runs there
            key = "all states" if i == 0 else it.label
            curves.setdefault(key, []).append((obs, d[at], s["_avg"][at], s["_lo"][at], s["_hi"][at], it.dof))
    if not curves:
        raise PlotSkipped("no stored covariance at a time with truth")
    ncol = 2 if len(curves) > 3 else 1
    nrow = int(np.ceil(len(curves) / ncol))
    fig, axs = subplots(nrow, ncol, figsize=(6.2 * ncol, 2.2 * nrow + 0.9), squeeze=False)
    unit = res.attrs.get("length_unit", "mm")
    handles = {}
    for ax, (panel, items) in zip(axs.flat, curves.items()):
        values = np.concatenate([np.concatenate([it[2], it[3], it[4]]) for it in items])
        values = values[np.isfinite(values) & (values > 0)]
        for obs, d, avg, lo, hi, _ in items:
            st = observer_style(obs, n=d.size)
            (line,) = ax.plot(d, avg, lw=1.3, **st)
            ax.fill_between(d, lo, hi, color=st["color"], alpha=0.15, lw=0)
            handles.setdefault(obs, line)
        if values.size and values.max() > 30 * values.min():  # orders of magnitude: a log axis
            ax.set_yscale("log")
        dofs = sorted({it[-1] for it in items})
        for dof in dofs:
            ax.axhline(dof, color="grey", ls=":", lw=0.8)
        ax.set_title(f"{panel} (dof {', '.join(map(str, dofs))})", fontsize=9)
        ax.set_ylabel("ANEES [-]")
        ax.set_xlabel(f"inserted depth [{unit}]")
        ax.grid(alpha=0.3, which="both")
    for ax in list(axs.flat)[len(curves):]:
        ax.remove()
    outside_legend(fig, handles.values(), handles.keys())
    fig.suptitle(f"{res.attrs.get('name', '')}: ANEES against depth (band: two-sided 95 % chi-square interval "
                 "for the runs at that time; dotted: the consistent value)", fontsize=10)
    return save_figure(fig, Path(f"{path_stem}_nees_vs_depth.png"))
