"""The tables of ``needle compare``, from its results file alone: every observer on the same insertions,
in the form of seed 003's appendix A (Table A.3).

The comparison records what it decided per observer in the results file's ``/compare`` group (settings
origin, start, causal, the observer's model, runtime, the exception that ended a run; the observers it
skipped and why; the common start's recipe; docs/reference/results-file.md); the errors, predictions,
curvature and statuses come from the file's estimates as in every other table. A results file without
the group (not written by ``needle compare``) gives empty tables.
"""

from __future__ import annotations

import textwrap

import numpy as np
import pandas as pd

from needlecli.io.results import Group
from needlecli.metrics import ErrorSet
from needlecli.reports.tables import TABLES, _float_format, order_quantities

COLUMNS = ["observer", "type", "settings", "start", "causal", "sensors", "sensor_rates", "model", "online_curvature",
           "insertion_length", "runs", "inst_quantity", "inst_unit", "inst_mean", "inst_std", "kappa_mean", "kappa_std",
           "pred_depth", "pred_mean_mm", "pred_std_mm", "runs_failed", "failure_reasons", "seconds", "ms_per_step",
           "us_per_run_step"]


def _texts(values) -> list[str]:
    return [v.decode() if isinstance(v, bytes) else str(v) for v in np.atleast_1d(values)]


def _number(v):
    return v.item() if isinstance(v, np.generic) else v


def comparison(res: Group) -> Group | None:
    """The ``/compare`` group of a results file of ``needle compare`` (None: another results file)."""
    g = res.data.get("compare")
    return g if isinstance(g, Group) else None


def final_depth(res: Group) -> float:
    """The mean inserted length at the end of the runs (what the comparison's 25 % refers to)."""
    depth = np.asarray(res.data["depth"], dtype=float)
    return float(np.nanmean(depth[..., -1])) if depth.size else 0.0


def prediction_fraction(res: Group) -> float:
    g = comparison(res)
    return float(g.attrs.get("prediction_fraction", 0.25)) if g is not None else 0.25


def _sensors(res: Group) -> list[tuple[str, str, list[str], object]]:
    """``(name, type, components, rate)`` of every sensor, in the experiment's order."""
    meas = res.data.get("measurements", Group()).data
    g = comparison(res)
    order = _texts(g.attrs.get("sensors", [])) if g is not None and "sensors" in g.attrs else list(meas)
    out = []
    for name in order:
        s = meas.get(name)
        if s is None:
            continue
        out.append((name, str(s.attrs.get("type", "?")), _texts(s.attrs.get("names", [])), _number(s.attrs.get("rate"))))
    return out


def _sensor_text(res: Group) -> tuple[str, str]:
    parts, rates = [], []
    for name, kind, comps, rate in _sensors(res):
        parts.append(f"{name}: {kind} ({', '.join(comps)})")
        rates.append(f"{rate:g} Hz" if isinstance(rate, (int, float)) else "?")
    return "; ".join(parts), " & ".join(rates)


def _instantaneous(es) -> tuple[str, str, float, float]:
    """(quantity, unit, mean, std) of the main error after initialisation: E_xyz, else E_R, else the first."""
    qs = order_quantities(es.quantities) if es is not None else []
    if not qs:
        return "", "", float("nan"), float("nan")
    q = "E_xyz" if "E_xyz" in qs else "E_R" if "E_R" in qs else qs[0]
    qe = es.quantities[q]
    v = qe.values[:, 1:]
    v = v[np.isfinite(v)]
    return q, qe.unit, (float(np.mean(v)) if v.size else float("nan")), (float(np.std(v)) if v.size else float("nan"))


def _online_curvature(est: Group, curvature: str | None) -> str:
    names = _texts(est.attrs.get("names", []))
    if curvature is None or curvature not in names:
        return "no (not estimated)"
    v = np.asarray(est.data["state"])[..., names.index(curvature)]
    spread = np.nanmax(np.abs(v - v[:, :1])) if v.size else 0.0
    return "yes" if np.isfinite(spread) and spread > 1e-12 else "no (held at its initial value)"


def _curvature_param(res: Group) -> str | None:
    from needlecli.models import MODELS

    name = str(res.attrs.get("model", ""))
    return MODELS.get(name).curvature_param if name in MODELS else None


@TABLES.register("compare")
def compare_table(res: Group, errors: dict[str, ErrorSet]) -> pd.DataFrame:
    """Every observer of needle compare on the same insertions, one row each (tidy, numeric): sensors and
    rates, model, observer, where its settings and its start came from, online curvature estimation,
    insertion length, instantaneous error (mean, std after initialisation), curvature error, prediction
    error after 25 % of the insertion (NaN when the observer does not predict), runs, failed runs, runtime
    per step (the batch of all runs) and per run-step. Empty for a results file of another command."""
    from needlecli.reports.seed003 import prediction_errors

    g = comparison(res)
    if g is None:
        return pd.DataFrame(columns=COLUMNS)
    sensors, rates = _sensor_text(res)
    truth_status = np.asarray(res.data["truth"].data["status"]).astype(str)
    n_runs = int(truth_status.shape[0])
    t_ok = truth_status == "ok"
    n_steps = max(len(res.data["time"]) - 1, 1)
    depth = final_depth(res)
    fraction = prediction_fraction(res)
    preds = prediction_errors(res)
    estimates = res.data.get("estimates", Group()).data
    curvature = _curvature_param(res)
    rows = []
    for i, name in enumerate(_texts(g.data["observer"])):
        es = errors.get(name)
        q, unit, m, s = _instantaneous(es)
        kq = es.quantities.get("E_kappa") if es is not None else None
        kv = kq.values[:, 1:][np.isfinite(kq.values[:, 1:])] if kq is not None else np.zeros(0)
        pm = ps = float("nan")
        pred_depth = float("nan")
        if name in preds:
            depths, err = preds[name]
            d = fraction * depth
            j = int(np.argmin(np.abs(depths - d))) if len(depths) else -1
            if j >= 0 and abs(depths[j] - d) <= 1e-6 * max(1.0, d):
                e = err[:, j]
                e = e[np.isfinite(e)]
                pred_depth = float(depths[j])
                if e.size:
                    pm, ps = float(np.mean(e)), float(np.std(e))
        error = _texts(g.data["error"])[i]
        if name in estimates:
            st = np.asarray(estimates[name].data["status"]).astype(str)
            bad = t_ok & (st != "ok")
            failed, reasons = int(bad.sum()), ", ".join(sorted({f"{x}" for x in st[bad]}))
        else:
            failed, reasons = n_runs - int((~t_ok).sum()), "raised"
        seconds = float(g.data["seconds"][i])
        rows.append({
            "observer": name, "type": _texts(g.data["type"])[i], "settings": _texts(g.data["settings"])[i],
            "start": _texts(g.data["start"])[i], "causal": bool(g.data["causal"][i]),
            "sensors": sensors, "sensor_rates": rates,
            "model": _texts(g.data["model"])[i],
            "online_curvature": _online_curvature(estimates[name], curvature) if name in estimates else "n/a",
            "insertion_length": depth, "runs": n_runs,
            "inst_quantity": q, "inst_unit": unit, "inst_mean": m, "inst_std": s,
            "kappa_mean": float(np.mean(kv)) if kv.size else float("nan"),
            "kappa_std": float(np.std(kv)) if kv.size else float("nan"),
            "pred_depth": pred_depth, "pred_mean_mm": pm, "pred_std_mm": ps,
            "runs_failed": failed if not error else n_runs, "failure_reasons": reasons if not error else error,
            "seconds": seconds, "ms_per_step": 1e3 * seconds / n_steps,
            "us_per_run_step": 1e6 * seconds / (n_steps * max(n_runs, 1)),
        })
    return pd.DataFrame(rows, columns=COLUMNS)


def _pm(m: float, s: float, unit: str = "") -> str:
    if not np.isfinite(m):
        return "n/a"
    return f"{_float_format(m)} ± {_float_format(s)}" + (f" {unit}" if unit else "")


def _num(v: float) -> str:
    return f"{v:.0f}" if abs(v) >= 100 else f"{v:.3g}"


def appendix_form(df: pd.DataFrame, res: Group) -> pd.DataFrame:
    """The table in the form of seed 003's appendix A (Table A.3): one column per observer, one row per
    property (``df``: :func:`compare_table`)."""
    length_unit = str(res.attrs.get("length_unit", "mm"))
    rows: dict[str, list[str]] = {
        "Sensor": [], "Sensor frequency": [], "Model": [], "Observer": [], "Settings": [], "Start": [],
        "Online curvature estimation": [], f"Length of insertion ({length_unit})": [],
        "Instantaneous error": [], "Curvature error": [], "Prediction error* (mm)": [],
        "Number of insertions": [], "Runs that failed": [], "Runtime per step": [],
    }
    for _, r in df.iterrows():
        rows["Sensor"].append(r["sensors"])
        rows["Sensor frequency"].append(r["sensor_rates"])
        rows["Model"].append(str(r["model"]))
        rows["Observer"].append(f"{r['observer']} ({r['type']})")
        rows["Settings"].append(r["settings"])
        rows["Start"].append(r["start"] + ("" if r["causal"] else " (smoother: every sample of the run)"))
        rows["Online curvature estimation"].append(r["online_curvature"])
        rows[f"Length of insertion ({length_unit})"].append(f"{r['insertion_length']:.3g}")
        inst = _pm(r["inst_mean"], r["inst_std"], r["inst_unit"])
        rows["Instantaneous error"].append(f"{inst} ({r['inst_quantity']})" if r["inst_quantity"] else "n/a")
        rows["Curvature error"].append(_pm(r["kappa_mean"], r["kappa_std"], f"1/{length_unit}"))
        rows["Prediction error* (mm)"].append(_pm(r["pred_mean_mm"], r["pred_std_mm"]))
        rows["Number of insertions"].append(str(r["runs"]))
        failed = f"{r['runs_failed']}/{r['runs']}" + (f" ({r['failure_reasons']})" if r["failure_reasons"] else "")
        rows["Runs that failed"].append(failed)
        rows["Runtime per step"].append(f"{_num(r['ms_per_step'])} ms ({_num(r['us_per_run_step'])} µs per run-step)")
    return pd.DataFrame([{"": k, **dict(zip(df["observer"], v))} for k, v in rows.items()])


@TABLES.register("compare_appendix")
def compare_appendix_table(res: Group, errors: dict[str, ErrorSet]) -> pd.DataFrame:
    """The comparison of needle compare in the form of seed 003's appendix A (Table A.3): one column per
    observer, one row per property (sensors, rates, model, settings, start, online curvature, errors,
    prediction error after 25 % of the insertion, runs, failures, runtime). Empty for a results file of
    another command."""
    return appendix_form(compare_table(res, errors), res)


def _short(v: float) -> str:
    """3 significant digits, scientific below 0.01 with a short exponent (``1.9e-4``)."""
    if not np.isfinite(v):
        return "n/a"
    if v == 0:
        return "0"
    if abs(v) < 1e-2:
        m, e = f"{v:.2e}".split("e")
        return f"{m}e{int(e)}"
    return f"{v:.3g}"


def _spread(m: float, s: float) -> str:
    return "n/a" if not np.isfinite(m) else f"{_short(m)} ± {_short(s)}"


def _narrow_markdown(df: pd.DataFrame) -> str:
    """A Markdown table with one space of padding (tabulate pads more): for a terminal's width."""
    cols = [str(c) for c in df.columns]
    cells = [[str(v) for v in row] for row in df.itertuples(index=False)]
    w = [max([len(c)] + [len(r[i]) for r in cells]) for i, c in enumerate(cols)]
    line = lambda vals: "| " + " | ".join(v.ljust(w[i]) for i, v in enumerate(vals)) + " |"  # noqa: E731
    return "\n".join([line(cols), "|" + "|".join("-" * (x + 2) for x in w) + "|"] + [line(r) for r in cells])


def footnote(res: Group) -> str:
    """The note on the prediction error and on what the errors and runtimes count."""
    return (f"*Prediction error of the final tip position from the estimate after observing "
            f"{100 * prediction_fraction(res):g} % of the insertion length (n/a: the observer does not predict). "
            "Errors over every kept run and time step after initialisation; runtime per step: wall time of one "
            "grid step for all runs at once.")


def common_start(res: Group) -> str:
    """The common start's recipe (which observer, how), or why there is none."""
    g = comparison(res)
    return str(g.attrs.get("start", "")) if g is not None else ""


def skipped(res: Group) -> list[str]:
    """``"name (type): why"`` of every observer the comparison skipped."""
    g = comparison(res)
    if g is None or "skipped" not in g.data:
        return []
    s = g.data["skipped"].data
    return [f"{n} ({t}): {r}" for n, t, r in zip(_texts(s["observer"]), _texts(s["type"]), _texts(s["reason"]))]


def truth_failed(res: Group) -> int:
    """Runs whose truth stopped early (not counted in the tables)."""
    return int((np.asarray(res.data["truth"].data["status"]).astype(str) != "ok").sum())


def notes(res: Group) -> str:
    """What the file form of the table says under it: the footnote, the common start, the skipped observers."""
    out = footnote(res) + f"\n\nStart: {common_start(res)}."
    sk = skipped(res)
    return out + ("\n\nSkipped:\n" + "\n".join(f"- {s}" for s in sk) if sk else "")


def terminal_form(df: pd.DataFrame, res: Group, width: int = 80) -> str:
    """The comparison for a terminal of ``width`` columns: what every observer shares in a few lines,
    then two narrow tables (how each observer ran; its errors), then the notes, wrapped."""
    unit = str(res.attrs.get("length_unit", "mm"))
    n_runs = int(np.asarray(res.data["truth"].data["status"]).shape[0])
    parts = [textwrap.fill(f"Observers on the same insertions of {res.attrs.get('name', '')}: {n_runs} run(s) of "
                           f"{res.attrs.get('model', '')}, {final_depth(res):.3g} {unit} long.", width)]
    sens = "; ".join(f"{name}: {kind} ({', '.join(comps)}) {rate if rate is not None else 0:g} Hz"
                     for name, kind, comps, rate in _sensors(res))
    parts.append(textwrap.fill(f"Sensors: {sens}.", width))
    how = pd.DataFrame({
        "observer": [f"{o} ({t})" if o != t else o for o, t in zip(df["observer"], df["type"])],
        "settings": df["settings"], "start": df["start"],
        "failed": [f"{f}/{n}" for f, n in zip(df["runs_failed"], df["runs"])],
        "ms/step": [_short(v) for v in df["ms_per_step"]],
    })
    errs = pd.DataFrame({
        "observer": df["observer"],
        "error after init.": [f"{_spread(m, s)} {u} {q}".strip() if q else "n/a"
                              for m, s, u, q in zip(df["inst_mean"], df["inst_std"], df["inst_unit"], df["inst_quantity"])],
        f"E_kappa (1/{unit})": [_spread(m, s) for m, s in zip(df["kappa_mean"], df["kappa_std"])],
        "prediction* (mm)": [_spread(m, s) for m, s in zip(df["pred_mean_mm"], df["pred_std_mm"])],
    })
    parts += [_narrow_markdown(how), _narrow_markdown(errs)]
    start = common_start(res)
    notes_ = [f"Start: every observer marked 'common' starts from one initial estimate, the {start}."
              if start and not start.startswith("no ") else f"Start: {start}."]
    online = [o for o, c in zip(df["observer"], df["online_curvature"]) if c == "yes"]
    notes_.append(f"Curvature estimated online by: {', '.join(online) or 'none'}.")
    offline = [o for o, c in zip(df["observer"], df["causal"]) if not c]
    if offline:
        notes_.append(f"Smoothers (every sample of a run, also later ones; not a filter): {', '.join(offline)}.")
    notes_.append(footnote(res))
    failed = [f"{o}: {r}" for o, r in zip(df["observer"], df["failure_reasons"]) if r]
    if failed:
        notes_.append("Failed runs: " + "; ".join(failed) + ".")
    parts += [textwrap.fill(n, width) for n in notes_]
    return "\n\n".join(parts)
