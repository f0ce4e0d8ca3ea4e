"""What the data identify in a fit file (``needle evaluate FIT.h5 --tables identifiability``), and the
marks seed 004's tables put on weakly identified rows. Reads ``/fit/<model>/identifiability`` only
(:mod:`needlecli.fitting.identify` made it)."""

from __future__ import annotations

import numpy as np
import pandas as pd

from needlecli.io.results import Group
from needlecli.reports import TABLES
from needlecli.reports.tables import count_cell

IDENTIFIED = "identified"
OUTSIDE = "outside its bounds"  # needlecli.fitting.identify.OUTSIDE: a value the quantity cannot take
MARK = "†"


def assessed(res: Group, model: str) -> Group | None:
    """The identifiability group of a fitted model, or None (not assessed: ``fit.identify.enabled`` off,
    or a fit file older than the assessment)."""
    fit = res.data.get("fit")
    g = fit.data.get(model) if isinstance(fit, Group) else None
    ig = g.data.get("identifiability") if isinstance(g, Group) else None
    return ig if isinstance(ig, Group) else None


def _strs(v) -> np.ndarray:
    """Strings of any shape (HDF5 gives bytes)."""
    a = np.asarray(v, dtype=object)
    return np.array([x.decode() if isinstance(x, bytes) else str(x) for x in a.ravel()], dtype=object).reshape(a.shape)


def weak_quantities(res: Group, model: str) -> dict[str, str]:
    """Quantity -> why, for each quantity of a model the pooled assessment does not call identified."""
    ig = assessed(res, model)
    if ig is None:
        return {}
    names = _strs(ig.attrs["quantities"])
    verdict = _strs(ig.data["pooled_verdict"])
    reason = _strs(ig.data["pooled_reason"])
    return {n: f"{v}: {r}" if r else v for n, v, r in zip(names, verdict, reason) if v != IDENTIFIED}  # noqa: B905


def mark_label(label: str, quantity: str, weak: dict[str, str]) -> str:
    """``label`` with the weak-identification mark when its quantity is weakly (or not) identified."""
    return f"{label} {MARK}" if quantity in weak else label


def weak_note(weak_by_model: dict[str, dict[str, str]]) -> str:
    """The caption's sentence on marked rows (empty when every quantity is identified)."""
    parts = [f"{m}: {', '.join(w)}" for m, w in weak_by_model.items() if w]
    if not parts:
        return ""
    return (f"{MARK} weakly identified (the data hardly move the likelihood: a value near its starting guess, "
            f"not a measurement; see table identifiability): {'; '.join(parts)}.")


@TABLES.register("identifiability")
def identifiability_table(res: Group, errors=None) -> pd.DataFrame:
    """What the data identify, per fitted model and quantity: the median estimate over the assessed trials,
    its standard error from the trials' summed observed information (pooled) and the median of the
    per-trial ones, the relative SE, the pooled verdict (identified / weakly identified / not identified /
    outside its bounds: a value the quantity cannot take, counted with the not identified) with its reason,
    and in how many trials each verdict holds. Traces are not divided by their dimension."""
    rows = []
    fit = res.data.get("fit")
    for model in (fit.data if isinstance(fit, Group) else {}):
        ig = assessed(res, model)
        if ig is None:
            rows.append({"Model": model, "Quantity": "(all)", "Verdict": "not assessed",
                         "Reason": "the fit file has no identifiability group (fit.identify.enabled: false)"})
            continue
        names, units = _strs(ig.attrs["quantities"]), _strs(ig.attrs["units"])
        used = np.asarray(ig.data["used"], dtype=bool)
        est, se = np.asarray(ig.data["estimate"], dtype=float), np.asarray(ig.data["se"], dtype=float)
        verdict = _strs(ig.data["verdict"])
        pv, pr = _strs(ig.data["pooled_verdict"]), _strs(ig.data["pooled_reason"])
        pse, prse = np.asarray(ig.data["pooled_se"], dtype=float), np.asarray(ig.data["pooled_rse"], dtype=float)
        n = int(used.sum())
        for k, (q, u) in enumerate(zip(names, units)):
            e = est[used, k]
            s = se[used, k]
            v = verdict[used, k]
            rows.append({
                "Model": model, "Quantity": q, "Unit": u,
                "Estimate (median)": float(np.median(e)) if e.size else np.nan,
                "SE (pooled)": float(pse[k]), "Rel. SE (pooled)": float(prse[k]),
                "SE per trial (median)": float(np.nanmedian(s)) if np.isfinite(s).any() else np.nan,
                "Verdict": pv[k],
                "Identified": count_cell((v == IDENTIFIED).sum(), n),
                "Weakly": count_cell((v == "weakly identified").sum(), n),
                "Not": count_cell(np.isin(v, ("not identified", OUTSIDE)).sum(), n),  # outside: never identified
                "Reason": pr[k],
            })
    df = pd.DataFrame(rows)
    if rows:
        weak = [f"{r['Model']} {r['Quantity']}" for r in rows if r.get("Verdict") not in (IDENTIFIED, "not assessed")]
        df.attrs["note"] = (f"Weakly or not identified by these data: {', '.join(weak)}." if weak
                            else "Every quantity is identified by these data.")
    return df
