"""Per-trial fits by the experiment's design, from a fit file of ``needle fit-em``: the table a study of a
lab's own insertions publishes.

* ``fit_by_design``: each fitted constant (``kappa``, ``speed_scale``, ``c``, ...) per level of a trial
  metadata key (a design factor of the CSV mapping, a data set's speed, ...): trials, converged, mean,
  SD, standard error of the mean, median.
* ``fit_regression`` (table and plot): ordinary least squares of a fitted constant on a numeric design
  factor, ``constant = intercept + slope * factor``, over the trials whose fit did not fail: slope and
  intercept with standard errors, R^2, the residual SD. The fit file holds no standard error per trial
  yet, so the standard errors come from the spread of the per-trial estimates about the line (the OLS
  covariance ``s^2 (X^T X)^-1``); the table says so.
* ``fit_warnings``: per model and trial, what a reader must know before citing a fit: a measurement noise
  on its floor, a nearly singular process noise (and its flattest direction), a negative curvature
  reported as the roll + pi, a fit that did not converge.

Which keys and regressions: ``fit.design`` of the fit's config (``group_by``, ``regress: [{constant,
factor}]``), else every design factor the trials list (and every fitted constant on each numeric one);
``needle evaluate FIT --group-by KEY --regress CONST:FACTOR`` overrides.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import yaml

from needlecli.io.results import Group
from needlecli.reports.plots import PLOTS, beside_legend, observer_colour, save_figure, subplots
from needlecli.reports.tables import TABLES

FAILED = ("singular", "diverged")
SE_SOURCE = "spread of the per-trial estimates about the line (OLS; the fit file has no per-trial SE)"
#: a fitted Q block whose smallest eigenvalue is below this fraction of its largest is reported
Q_SINGULAR = 1e-6
#: an R_j within this relative distance of its floor is on it
FLOOR_TOL = 1e-3


def _is_fit(res: Group) -> bool:
    return res.attrs.get("format") == "needlecli-fit" and "fit" in res.data


def trial_ids(res: Group) -> np.ndarray:
    tr = res.data.get("truth", Group())
    ids = tr.data.get("trial_id")
    if ids is not None:
        return np.asarray(ids).astype(str)
    n = int(res.attrs.get("runs", 0))
    return np.array([f"run {i}" for i in range(n)])


def metadata(res: Group) -> tuple[dict[str, np.ndarray], list[str]]:
    """The trials' metadata columns of a fit file (``/truth/meta``) and its design factors."""
    meta = res.data.get("truth", Group()).data.get("meta")
    if not isinstance(meta, Group):
        return {}, []
    factors = [str(x) for x in np.atleast_1d(meta.attrs.get("design_factors", [])) if str(x)]
    return {k: np.asarray(v) for k, v in meta.data.items()}, factors


def design_settings(res: Group) -> dict:
    """``fit.design`` of the fit's config (``{"group_by": [...], "regress": [(constant, factor), ...]}``)."""
    try:
        cfg = yaml.safe_load(res.attrs.get("config", "")) or {}
    except yaml.YAMLError:
        cfg = {}
    d = ((cfg.get("fit") or {}).get("design") or {}) if isinstance(cfg, dict) else {}
    return {"group_by": [str(k) for k in d.get("group_by", []) or []],
            "regress": [(str(r.get("constant")), str(r.get("factor"))) for r in d.get("regress", []) or []
                        if isinstance(r, dict)]}


def _numeric(v: np.ndarray) -> bool:
    return np.asarray(v).dtype.kind in "fiub"


def constants(res: Group) -> pd.DataFrame:
    """One row per model and trial: status, each fitted constant, each metadata column."""
    ids = trial_ids(res)
    meta, _ = metadata(res)
    frames = []
    for model, g in res.data["fit"].data.items():
        df = pd.DataFrame({"Model": model, "Trial": ids, "Status": np.asarray(g.data["status"]).astype(str)})
        for c, v in g.data["constant"].data.items():
            df[c] = np.asarray(v, dtype=float)
        for k, v in meta.items():
            df[k] = v
        frames.append(df)
    return pd.concat(frames, ignore_index=True) if frames else pd.DataFrame()


def _const_names(res: Group) -> dict[str, str]:
    """Fitted constant -> unit, over the models."""
    out = {}
    for g in res.data["fit"].data.values():
        names = [str(n) for n in g.attrs["names"]]
        units = [str(u) for u in g.attrs.get("units", [""] * len(names))]
        for c in g.data["constant"].data:
            out.setdefault(c, units[names.index(c)] if c in names else "")
    return out


# ---------------------------------------------------------------------------------------------- grouped
@TABLES.register("fit_by_design")
def fit_by_design(res: Group, errors=None, *, group_by: list[str] | None = None) -> pd.DataFrame:
    """Fitted constants per level of a design factor (a fit file of needle fit-em; trials whose fit failed,
    singular or diverged, left out): trials, converged, mean, SD, standard error of the mean (SD /
    sqrt(n)) and median of each constant over the trials of each level."""
    cols = ["Model", "Factor", "Level", "Trials", "Converged", "Constant", "Mean", "SD", "SE of mean", "Median"]
    if not _is_fit(res):
        return pd.DataFrame(columns=cols)
    meta, factors = metadata(res)
    keys = group_by or design_settings(res)["group_by"] or factors
    keys = [k for k in keys if k in meta]
    per = constants(res)
    units = _const_names(res)
    rows = []
    for key in keys:
        for (model, level), d in per.groupby(["Model", key], dropna=False, sort=True):
            kept = d[~d["Status"].isin(FAILED)]
            for c, unit in units.items():
                if c not in d:
                    continue
                v = kept[c].to_numpy(dtype=float)
                v = v[np.isfinite(v)]
                sd = float(np.std(v, ddof=1)) if v.size > 1 else np.nan
                rows.append({"Model": model, "Factor": key, "Level": level, "Trials": len(d),
                             "Converged": int((d["Status"] == "ok").sum()), "Constant": f"{c} [{unit}]",
                             "Mean": float(np.mean(v)) if v.size else np.nan, "SD": sd,
                             "SE of mean": sd / np.sqrt(v.size) if v.size > 1 else np.nan,
                             "Median": float(np.median(v)) if v.size else np.nan})
    return pd.DataFrame(rows, columns=cols)


# ---------------------------------------------------------------------------------------------- regression
def ols(x: np.ndarray, y: np.ndarray) -> dict:
    """``y = a + b x`` by ordinary least squares: slope, intercept, their standard errors and covariance
    from the residual spread (``s^2 (X^T X)^-1``, ``s^2`` the residual variance with n - 2 degrees of
    freedom), R^2, residual SD, n."""
    x, y = np.asarray(x, dtype=float), np.asarray(y, dtype=float)
    n = len(x)
    out = {"n": n, "slope": np.nan, "intercept": np.nan, "slope_se": np.nan, "intercept_se": np.nan,
           "cov": np.full((2, 2), np.nan), "r2": np.nan, "resid_sd": np.nan}
    if n < 2 or np.ptp(x) == 0:
        return out
    X = np.c_[np.ones(n), x]
    coef, *_ = np.linalg.lstsq(X, y, rcond=None)
    r = y - X @ coef
    out.update(intercept=float(coef[0]), slope=float(coef[1]))
    ss_tot = float(((y - y.mean()) ** 2).sum())
    out["r2"] = 1.0 - float(r @ r) / ss_tot if ss_tot > 0 else np.nan
    if n > 2:
        s2 = float(r @ r) / (n - 2)
        cov = s2 * np.linalg.inv(X.T @ X)
        out.update(cov=cov, intercept_se=float(np.sqrt(cov[0, 0])), slope_se=float(np.sqrt(cov[1, 1])),
                   resid_sd=float(np.sqrt(s2)))
    return out


def _pairs(res: Group, regress) -> list[tuple[str, str]]:
    meta, factors = metadata(res)
    pairs = list(regress or design_settings(res)["regress"])
    if not pairs:
        numeric = [f for f in factors if f in meta and _numeric(meta[f])]
        pairs = [(c, f) for f in numeric for c in _const_names(res)]
    return pairs


def regressions(res: Group, regress=None) -> list[dict]:
    """Each (model, constant, factor) regression with its data: ``x``, ``y``, ``trials``, ``status`` and
    the :func:`ols` result. A pair a model lacks, or a factor without numbers, gives a row that says so."""
    if not _is_fit(res):
        return []
    meta, _ = metadata(res)
    ids = trial_ids(res)
    out = []
    for model, g in res.data["fit"].data.items():
        status = np.asarray(g.data["status"]).astype(str)
        for c, f in _pairs(res, regress):
            item = {"model": model, "constant": c, "factor": f}
            if c not in g.data["constant"].data:
                item["why"] = f"model {model} has no fitted constant {c!r}"
            elif f not in meta:
                item["why"] = f"no trial metadata {f!r} (metadata: {', '.join(meta) or 'none'})"
            elif not _numeric(meta[f]):
                item["why"] = f"{f!r} is not a number"
            if "why" in item:
                out.append(item)
                continue
            x = np.asarray(meta[f], dtype=float)
            y = np.asarray(g.data["constant"].data[c], dtype=float)
            use = np.isfinite(x) & np.isfinite(y) & ~np.isin(status, FAILED)
            item.update(x=x[use], y=y[use], trials=ids[use], status=status[use], fit=ols(x[use], y[use]),
                        excluded=int((~use).sum()))
            out.append(item)
    return out


@TABLES.register("fit_regression")
def fit_regression(res: Group, errors=None, *, regress=None) -> pd.DataFrame:
    """Regression of a fitted constant on a design factor (a fit file of needle fit-em): constant = intercept
    + slope * factor by ordinary least squares over the trials whose fit did not fail; slope and intercept
    with standard errors from the spread of the per-trial estimates about the line (the fit file has no
    per-trial standard errors), R^2 and the residual SD."""
    cols = ["Model", "Constant", "Factor", "Trials", "Not converged", "Slope", "Slope SE", "Intercept",
            "Intercept SE", "R^2", "Residual SD", "SE from"]
    units = _const_names(res) if _is_fit(res) else {}
    rows = []
    for it in regressions(res, regress):
        row = {"Model": it["model"], "Constant": f"{it['constant']} [{units.get(it['constant'], '')}]",
               "Factor": it["factor"]}
        if "why" in it:
            row["SE from"] = f"not computable: {it['why']}"
            rows.append(row)
            continue
        f = it["fit"]
        row.update({"Trials": f["n"], "Not converged": int((it["status"] != "ok").sum()), "Slope": f["slope"],
                    "Slope SE": f["slope_se"], "Intercept": f["intercept"], "Intercept SE": f["intercept_se"],
                    "R^2": f["r2"], "Residual SD": f["resid_sd"],
                    "SE from": SE_SOURCE if f["n"] > 2 else "not computable: fewer than 3 trials"})
        rows.append(row)
    return pd.DataFrame(rows, columns=cols)


@PLOTS.register("fit_regression")
def regression_plot(res: Group, errors, path_stem: Path, *, regress=None) -> Path | None:
    """Each regression of ``fit_regression``: the per-trial estimates against the factor (filled:
    converged; open: stopped at the iteration limit), the fitted line and its band of one standard error,
    one colour per model."""
    items = [it for it in regressions(res, regress) if "why" not in it and it["fit"]["n"] >= 2]
    if not items:
        return None
    pairs = list(dict.fromkeys((it["constant"], it["factor"]) for it in items))
    units = _const_names(res)
    fig, axs = subplots(1, len(pairs), figsize=(7.5 * len(pairs), 4.2), squeeze=False)
    for ax, (c, f) in zip(axs[0], pairs):
        for it in items:
            if (it["constant"], it["factor"]) != (c, f):
                continue
            col = observer_colour(it["model"])
            ok = it["status"] == "ok"
            ax.plot(it["x"][ok], it["y"][ok], "o", color=col, ms=5, label=f"{it['model']}: trials (converged)")
            if (~ok).any():
                ax.plot(it["x"][~ok], it["y"][~ok], "o", mfc="none", color=col, ms=5, label=f"{it['model']}: not converged")
            fit = it["fit"]
            xs = np.linspace(it["x"].min(), it["x"].max(), 50)
            line = fit["intercept"] + fit["slope"] * xs
            X = np.c_[np.ones_like(xs), xs]
            band = np.sqrt(np.einsum("ki,ij,kj->k", X, fit["cov"], X)) if np.isfinite(fit["cov"]).all() else 0 * xs
            ax.plot(xs, line, "-", color=col, lw=1.5,
                    label=f"{it['model']}: {fit['intercept']:.4g} + ({fit['slope']:.4g}) x, R^2 {fit['r2']:.3f}")
            ax.fill_between(xs, line - band, line + band, color=col, alpha=0.2, lw=0, label=f"{it['model']}: +- 1 SE")
        ax.set_xlabel(f)
        ax.set_ylabel(f"{c} [{units.get(c, '')}]")
        ax.grid(alpha=0.3)
        beside_legend(ax, fontsize="x-small")
    fig.suptitle(f"{res.attrs.get('name', '')}: fitted constants against the design (OLS, SE from the spread)")
    return save_figure(fig, Path(f"{path_stem}_fit_regression.png"))


# ---------------------------------------------------------------------------------------------- warnings
def warnings_per_trial(res: Group) -> pd.DataFrame:
    """One row per model and trial with something to report (see :func:`fit_warnings`)."""
    cols = ["Model", "Trial", "Status", "Warning"]
    if not _is_fit(res):
        return pd.DataFrame(columns=cols + ["Kind"])
    ids = trial_ids(res)
    rows = []
    for model, g in res.data["fit"].data.items():
        names = [str(n) for n in g.attrs["names"]]
        status = np.asarray(g.data["status"]).astype(str)
        reason = np.asarray(g.data["reason"]).astype(str)
        notes: list[list[str]] = [[] for _ in ids]
        for ch, R in g.data["R"].data.items():
            if ch.endswith("_guess"):
                continue
            floor = g.data["R"].attrs.get(f"{ch}_floor")
            floor = _floor_of(res, model, ch) if floor is None else floor
            if floor is None or not floor > 0:
                continue
            R = np.asarray(R, dtype=float)
            fin = np.isfinite(R).all((-1, -2))
            w = np.full(R.shape[:-1], np.nan)
            if fin.any():
                w[fin] = np.linalg.eigvalsh(R[fin])
            at = (w <= floor * (1 + FLOOR_TOL)).sum(-1)
            for i in np.nonzero(at)[0]:
                notes[i].append(("R on its floor", f"R_{ch} on its floor ({floor:.3g}) in {at[i]} of {R.shape[-1]} "
                                 "directions: the data would put the noise lower"))
        Q = np.asarray(g.data["Q"], dtype=float)
        q_states = [str(s) for s in np.atleast_1d(g.attrs.get("q_states", names))]
        qi = [names.index(s) for s in q_states if s in names]
        if qi:
            B = Q[:, qi][:, :, qi]
            fin = np.isfinite(B).all((-1, -2))
            w = np.full((len(B), len(qi)), np.nan)
            V = np.full((len(B), len(qi), len(qi)), np.nan)
            if fin.any():
                w[fin], V[fin] = np.linalg.eigh(B[fin])
            for i in np.nonzero(fin & (w[:, 0] <= Q_SINGULAR * np.maximum(w[:, -1], 0)))[0]:
                v = V[i][:, 0]
                top = [q_states[j] for j in np.argsort(-np.abs(v))[:2] if abs(v[j]) > 0.3]
                notes[i].append(("Q nearly singular", f"Q nearly singular (smallest / largest eigenvalue "
                                 f"{w[i, 0] / w[i, -1]:.2g}, along {', '.join(top)}): no process noise fitted there"))
        flipped = g.data.get("roll_flipped")
        if flipped is not None:
            for i in np.nonzero(np.asarray(flipped))[0]:
                c0 = np.atleast_1d(g.attrs.get("constants", ["kappa"]))[0]
                notes[i].append(("negative curvature", f"negative {c0} fitted: reported as -{c0} with "
                                 f"{g.attrs.get('roll_state', 'roll')} + pi (the same path)"))
        for i, s in enumerate(status):
            if s != "ok":
                notes[i].append((f"status {s}", f"{s}: {reason[i]}"))
        for i, n in enumerate(notes):
            for kind, text in n:
                rows.append({"Model": model, "Trial": ids[i], "Status": status[i], "Kind": kind, "Warning": text})
    return pd.DataFrame(rows, columns=cols + ["Kind"])


def _floor_of(res: Group, model: str, ch: str) -> float | None:
    """The floor of R_ch (the fit file's attribute, else the config's ``fit.measurements.<ch>.floor``)."""
    try:
        cfg = yaml.safe_load(res.attrs.get("config", "")) or {}
        spec = ((cfg.get("fit") or {}).get("measurements") or {}).get(ch) or {}
        return float(spec["floor"]) if spec.get("floor") is not None else None
    except (yaml.YAMLError, AttributeError, TypeError, ValueError, KeyError):
        return None


@TABLES.register("fit_warnings")
def fit_warnings(res: Group, errors=None) -> pd.DataFrame:
    """What to know before citing a fit (a fit file of needle fit-em), per model and trial: a measurement
    noise R_j on its floor (the data would put it lower), a fitted process noise Q that is nearly singular
    (smallest over largest eigenvalue below 1e-6: the direction it names has no process noise), a negative
    curvature reported as the roll + pi, and every fit that did not converge, with its reason."""
    return warnings_per_trial(res).drop(columns="Kind")


def warning_summary(res: Group, statuses: bool = True) -> list[str]:
    """One line per model and kind of warning, ``<model>: <kind> in k of N trial(s): <ids>`` (for
    ``needle fit-em``'s output and ``fit_status``; ``statuses``: also the fits that did not converge)."""
    df = warnings_per_trial(res)
    out = []
    if df.empty:
        return out
    n = len(trial_ids(res))
    if not statuses:
        df = df[~df["Kind"].str.startswith("status ")]
    for (model, kind), d in df.groupby(["Model", "Kind"], sort=False):
        trials = list(dict.fromkeys(d["Trial"]))
        out.append(f"{model}: {kind} in {len(trials)} of {n} trial(s): {', '.join(trials)}")
    return out


#: tables and plots of this module that take the design settings (``needle evaluate --group-by/--regress``)
DESIGN_OPTIONS = {"fit_by_design": "group_by", "fit_regression": "regress"}
