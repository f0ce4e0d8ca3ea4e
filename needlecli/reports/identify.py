"""What the data identify in a fit file (``needle evaluate FIT.h5 --tables identifiability``), and the
marks the magnetic needle EM paper's tables put on rows the data do not determine. Reads ``/fit/<model>/identifiability`` only
(:mod:`needlecli.fitting.identify` made it and decided every verdict; this module only shows them): per
design group of trials (the magnetic needle EM paper's field strengths, a real export's speeds), with the trials behind each
count named."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pandas as pd

from needlecli.io.fit import IDENTIFIED, VERDICTS, verdict_text
from needlecli.io.results import Group
from needlecli.numerics.recovery import recovery
from needlecli.reports import TABLES

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


@dataclass
class Groups:
    """The figures of an identifiability group per design group, as the file holds them (a file older than
    the groups: its pooled figures as one group of every trial, without truth).

    labels (G,); group (N,) each trial's; trials (G,) assessed per group; estimate, se, rse, truth, z
    (G, d); verdict, reason (G, d) strings."""

    names: list[str]
    units: list[str]
    labels: list[str]
    group: np.ndarray
    trials: np.ndarray
    estimate: np.ndarray
    se: np.ndarray
    rse: np.ndarray
    truth: np.ndarray
    z: np.ndarray
    verdict: np.ndarray
    reason: np.ndarray

    def text(self, g: int, k: int) -> str:
        """The verdict of quantity ``k`` in group ``g`` as tables print it."""
        return verdict_text(self.verdict[g, k], self.z[g, k])


def groups(ig: Group) -> Groups:
    """The per-group figures of an identifiability group (:class:`Groups`)."""
    names, units = [str(x) for x in _strs(ig.attrs["quantities"])], [str(x) for x in _strs(ig.attrs["units"])]
    used = np.asarray(ig.data["used"], dtype=bool)
    d = len(names)
    if "group_verdict" in ig.data:
        f = {k: np.asarray(ig.data[f"group_{k}"], dtype=float) for k in ("estimate", "se", "rse", "truth", "z")}
        return Groups(names, units, [str(x) for x in _strs(np.atleast_1d(ig.attrs["group_labels"]))],
                      np.asarray(ig.data["group"], dtype=np.int64), np.asarray(ig.data["group_trials"], dtype=np.int64),
                      f["estimate"], f["se"], f["rse"], f["truth"], f["z"], _strs(ig.data["group_verdict"]),
                      _strs(ig.data["group_reason"]))
    est = np.asarray(ig.data["estimate"], dtype=float)[used]
    med = np.median(est, axis=0) if est.size else np.full(d, np.nan)
    nan = np.full((1, d), np.nan)
    return Groups(names, units, ["all trials"], np.zeros(len(used), dtype=np.int64), np.array([used.sum()]),
                  med[None], np.asarray(ig.data["pooled_se"], dtype=float)[None],
                  np.asarray(ig.data["pooled_rse"], dtype=float)[None], nan, nan.copy(),
                  _strs(ig.data["pooled_verdict"])[None], _strs(ig.data["pooled_reason"])[None])


def weak_quantities(res: Group, model: str) -> dict[str, str]:
    """Quantity -> what the assessment says, for each quantity of a model that some design group does not
    call identified: ``"<verdict> (<groups>): <reason>"`` (the groups named where not all of them)."""
    ig = assessed(res, model)
    if ig is None:
        return {}
    gs = groups(ig)
    out = {}
    for k, q in enumerate(gs.names):
        bad = [g for g in range(len(gs.labels)) if gs.trials[g] and gs.verdict[g, k] != IDENTIFIED]
        if not bad:
            continue
        texts = list(dict.fromkeys(gs.text(g, k) for g in bad))
        where = "" if len(bad) == sum(1 for g in range(len(gs.labels)) if gs.trials[g]) or len(gs.labels) == 1 else \
            f" in {', '.join(gs.labels[g] for g in bad)}"
        why = gs.reason[bad[0], k]
        out[q] = f"{'; '.join(texts)}{where}" + (f": {why}" if why else "")
    return out


def mark_label(label: str, quantity: str, weak: dict[str, str]) -> str:
    """``label`` with the mark when its quantity is not identified (weakly, not, EM stopped short, biased)."""
    return f"{label} {MARK}" if quantity in weak else label


def weak_note(weak_by_model: dict[str, dict[str, str]]) -> str:
    """The caption's sentence on marked rows (empty when every quantity is identified)."""
    parts = []
    for m, w in weak_by_model.items():
        if w:
            parts.append(f"{m}: " + ", ".join(f"{q} ({v.split(': ', 1)[0]})" for q, v in w.items()))
    if not parts:
        return ""
    return (f"{MARK} not determined by these data as fitted (see table identifiability for why): {'; '.join(parts)}.")


def trial_counts(verdict: np.ndarray, ids: np.ndarray) -> str:
    """Per-trial verdicts of one group as a count with the trials named: ``identified 15/16; weakly
    identified 1/16: run 12`` (the most common verdict without names: the group's other trials)."""
    n = len(verdict)
    if not n:
        return "no trial assessed"
    counts = {v: int((verdict == v).sum()) for v in VERDICTS if (verdict == v).any()}
    counts.update({v: int((verdict == v).sum()) for v in np.unique(verdict) if v not in counts})
    top = max(counts, key=lambda v: counts[v])
    parts = [f"{top} {counts[top]}/{n}"]
    for v, c in counts.items():
        if v != top:
            parts.append(f"{v} {c}/{n}: {', '.join(str(t) for t in ids[verdict == v])}")
    return "; ".join(parts)


@TABLES.register("identifiability")
def identifiability_table(res: Group, errors=None) -> pd.DataFrame:
    """What the data identify, per fitted model, design group of trials (the magnetic needle EM paper's field strengths, a
    real export's speeds: the information of one group's trials is pooled, never across groups) and
    quantity: the median estimate, the truth where the trials are simulated, the standard error from the
    group's summed observed information and the median of the per-trial ones, the relative SE, the
    recovery check (estimate - truth in standard errors of the group's mean), the verdict (identified,
    weakly identified, EM stopped short of the maximum, not identified, biased, outside its bounds: a value
    the quantity cannot take) with its reason, and the
    per-trial verdicts with the trials behind each count named. Traces are not divided by their
    dimension."""
    from needlecli.reports.design import trial_ids

    rows = []
    fit = res.data.get("fit")
    ids = trial_ids(res)
    for model in (fit.data if isinstance(fit, Group) else {}):
        ig = assessed(res, model)
        if ig is None:
            rows.append({"Model": model, "Quantity": "(all)", "Verdict": "not assessed",
                         "Reason": "the fit file has no identifiability group (fit.identify.enabled: false)"})
            continue
        gs = groups(ig)
        used = np.asarray(ig.data["used"], dtype=bool)
        se = np.asarray(ig.data["se"], dtype=float)
        verdict = _strs(ig.data["verdict"])
        for g, label in enumerate(gs.labels):
            if not (gs.group == g).any():  # a level of the design no trial of this file has
                continue
            if not gs.trials[g]:  # one row: every fit of the group failed
                rows.append({"Model": model, "Quantity": "(all)", "Group": label, "Trials": 0, "Verdict": "not assessed",
                             "Per trial": f"{int((gs.group == g).sum())} trial(s), none assessed",
                             "Reason": "no trial of this group assessed: its fits failed (table fit_status)"})
                continue
            sel = used & (gs.group == g)
            for k, (q, u) in enumerate(zip(gs.names, gs.units)):
                s = se[sel, k]
                rows.append({
                    "Model": model, "Quantity": q, "Group": label, "Unit": u, "Trials": int(gs.trials[g]),
                    "Estimate (median)": gs.estimate[g, k], "Truth": gs.truth[g, k],
                    "SE (pooled)": gs.se[g, k], "Rel. SE (pooled)": gs.rse[g, k],
                    "SE per trial (median)": float(np.nanmedian(s)) if np.isfinite(s).any() else np.nan,
                    "z (estimate - truth)": gs.z[g, k], "Verdict": gs.text(g, k) if gs.trials[g] else "not assessed",
                    "Per trial": trial_counts(verdict[sel, k], ids[sel]), "Reason": gs.reason[g, k],
                })
    df = pd.DataFrame(rows)
    if rows:
        weak = list(dict.fromkeys(f"{r['Model']} {r['Quantity']}" for r in rows
                                  if r.get("Verdict") not in (IDENTIFIED, "not assessed")))
        df.attrs["note"] = (f"Not identified as fitted in some design group: {', '.join(weak)}." if weak
                            else "Every quantity is identified by these data in every design group.")
    return df


def recovery_over(results: list[Group], model: str) -> pd.DataFrame:
    """The recovery check over several fit files of one study (seeds): per design group (by label) and
    quantity, the trials of every file pooled (:func:`~needlecli.numerics.recovery.recovery`): mean truth,
    mean estimate per file and over all, z. The verdicts of each file stay its own (read them with
    :func:`groups`); this is the check across seeds."""
    rows: dict[tuple[str, str], dict] = {}
    for r, res in enumerate(results):
        ig = assessed(res, model)
        if ig is None or "truth" not in ig.data:
            continue
        gs = groups(ig)
        used = np.asarray(ig.data["used"], dtype=bool)
        est, se, tr = (np.asarray(ig.data[k], dtype=float) for k in ("estimate", "se", "truth"))
        for g, label in enumerate(gs.labels):
            sel = used & (gs.group == g)
            for k, q in enumerate(gs.names):
                item = rows.setdefault((label, q), {"est": [], "se": [], "truth": [], "per_file": {}})
                item["est"].append(est[sel, k])
                item["se"].append(se[sel, k])
                item["truth"].append(tr[sel, k])
                item["per_file"][r] = float(np.mean(est[sel, k])) if sel.any() else np.nan
    out = []
    for (label, q), item in rows.items():
        e, s, t = (np.concatenate(item[k])[:, None] for k in ("est", "se", "truth"))
        mean_truth, miss, sem, z = (float(x[0]) for x in recovery(e, s, t))
        out.append({"Model": model, "Group": label, "Quantity": q, "Truth": mean_truth,
                    **{f"Estimate (file {r + 1})": v for r, v in item["per_file"].items()},
                    "Estimate (all)": mean_truth + miss if np.isfinite(miss) else np.nan, "SE of mean": sem,
                    "z (estimate - truth)": z, "Trials": int(np.isfinite(e - t).sum())})
    return pd.DataFrame(out)
