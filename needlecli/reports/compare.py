"""The tables of ``needle compare``, from its results file alone: every observer on the same insertions,
in the form of the multi-rate UKF paper's appendix A (Table A.3).

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

#: the columns of :func:`compare_table` before and after the error columns, which depend on the experiment:
#: ``<quantity>_mean`` and ``<quantity>_std`` for every quantity of :func:`quantities` (NaN: not estimated)
HEAD = ["observer", "type", "settings", "start", "causal", "model_only", "sensors", "sensor_rates", "model",
        "online_curvature", "insertion_length", "runs"]
TAIL = ["pred_depth", "pred_mean_mm", "pred_std_mm", "runs_failed", "failure_reasons", "seconds", "ms_per_step",
        "us_per_run_step"]
COLUMNS = HEAD + TAIL  # (an empty table: no quantity)
_AXES = (("x", "y", "z"), ("px", "py", "pz"))
_LENGTH_TO_MM = {"mm": 1.0, "m": 1000.0, "cm": 10.0}


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


def with_axis_errors(res: Group, errors: dict[str, ErrorSet]) -> dict[str, ErrorSet]:
    """The errors of :func:`~needlecli.metrics.compute_errors` (the tip position's norm, each angle, the
    rotation, unit vectors, curvature, any other common state) with each position axis an observer
    estimates on its own, in mm (``E_x``, ``E_y``, ``E_z``; ``E_px``, ... of the magnetic models), over the
    runs whose truth and estimate are ok: a position error that an observer of fewer axes also has
    (the high-gain observer paper's E_x), beside every other's. New :class:`~needlecli.metrics.ErrorSet` objects; ``errors`` is
    left as it is."""
    import dataclasses

    from needlecli.metrics import QuantityError

    truth = res.data["truth"]
    t_names = list(truth.attrs["names"])
    axes = next((ax for ax in _AXES if all(a in t_names for a in ax)), None)
    scale = _LENGTH_TO_MM.get(str(res.attrs.get("length_unit", "mm")), 1.0)
    t_state = np.asarray(truth.data["state"])
    t_ok = np.asarray(truth.data["status"]).astype(str) == "ok"
    estimates = res.data.get("estimates", Group()).data
    out = {}
    for name, es in errors.items():
        es = dataclasses.replace(es, quantities=dict(es.quantities))
        g = estimates.get(name)
        if axes is not None and g is not None:
            e_names = list(g.attrs["names"])
            keep = np.nonzero(t_ok & (np.asarray(g.data["status"]).astype(str) == "ok"))[0]
            est = np.asarray(g.data["state"])
            for a in axes:
                if a in e_names:
                    v = scale * np.abs(est[keep][..., e_names.index(a)] - t_state[keep][..., t_names.index(a)])
                    if np.isfinite(v).any():
                        es.quantities[f"E_{a}"] = QuantityError(f"E_{a}", "mm", v, keep)
        out[name] = es
    return out


def _stats(values: np.ndarray) -> tuple[float, float]:
    """Mean and std over runs and the steps after initialisation (NaN when there is none)."""
    v = np.asarray(values)[:, 1:]
    v = v[np.isfinite(v)]
    return (float(np.mean(v)), float(np.std(v))) if v.size else (float("nan"), float("nan"))


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
    """Every observer of needle compare on the same insertions, one row each (tidy, numeric), the same
    columns for all: sensors and rates, model, observer, where its settings and its start came from,
    online curvature estimation, insertion length, the mean and std after initialisation of every error
    quantity any observer has (each position axis, the tip position, each angle, the rotation, the
    curvature...; NaN where the observer does not estimate it), prediction error after 25 % of the insertion
    (NaN when the observer does not predict), runs, failed runs, runtime per step (the batch of all runs)
    and per run-step. Empty for a results file of another command."""
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
    qs = {n: {q: (qe.values, qe.unit) for q, qe in es.quantities.items()}
          for n, es in with_axis_errors(res, errors).items()}
    units: dict[str, str] = {}
    for per in qs.values():
        for q, (_, unit) in per.items():
            units.setdefault(q, unit)
    axes = [q for a in _AXES for q in (f"E_{x}" for x in a) if q in units]
    order = [q for q in order_quantities(units) if q == "E_xyz"] + axes + [
        q for q in order_quantities(units) if q != "E_xyz" and q not in axes]
    model_only = (np.asarray(g.data["model_only"], dtype=bool) if "model_only" in g.data
                  else np.zeros(len(g.data["observer"]), dtype=bool))
    rows = []
    for i, name in enumerate(_texts(g.data["observer"])):
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
        row = {
            "observer": name, "type": _texts(g.data["type"])[i], "settings": _texts(g.data["settings"])[i],
            "start": _texts(g.data["start"])[i], "causal": bool(g.data["causal"][i]),
            "model_only": bool(model_only[i]), "sensors": sensors, "sensor_rates": rates,
            "model": _texts(g.data["model"])[i],
            "online_curvature": _online_curvature(estimates[name], curvature) if name in estimates else "n/a",
            "insertion_length": depth, "runs": n_runs,
        }
        own = qs.get(name, {})
        for q in order:
            row[f"{q}_mean"], row[f"{q}_std"] = _stats(own[q][0]) if q in own else (float("nan"), float("nan"))
        row.update({
            "pred_depth": pred_depth, "pred_mean_mm": pm, "pred_std_mm": ps,
            "runs_failed": failed if not error else n_runs, "failure_reasons": reasons if not error else error,
            "seconds": seconds, "ms_per_step": 1e3 * seconds / n_steps,
            "us_per_run_step": 1e6 * seconds / (n_steps * max(n_runs, 1)),
        })
        rows.append(row)
    df = pd.DataFrame(rows, columns=HEAD + [f"{q}_{s}" for q in order for s in ("mean", "std")] + TAIL)
    df.attrs["units"] = {q: units[q] for q in order}
    return df


def error_quantities(df: pd.DataFrame) -> list[tuple[str, str]]:
    """``(quantity, unit)`` of every error column pair of a :func:`compare_table` (in the table's order; the
    unit from the table's attributes, or the quantity's usual one for a table read back from CSV)."""
    units = df.attrs.get("units", {})
    out = []
    for c in df.columns:
        if c.startswith("E_") and c.endswith("_mean"):
            q = c[: -len("_mean")]
            out.append((q, units.get(q, _usual_unit(q))))
    return out


def _usual_unit(q: str) -> str:
    if q in ("E_alpha", "E_beta", "E_gamma", "E_R", "E_h", "E_B"):
        return "deg"
    if q in ("E_xyz", "E_x", "E_y", "E_z", "E_px", "E_py", "E_pz"):
        return "mm"
    return ""


def _position_quantities(df: pd.DataFrame) -> list[str]:
    """The tip-position quantities of a table: the norm, else each axis."""
    qs = [q for q, _ in error_quantities(df)]
    if "E_xyz" in qs:
        return ["E_xyz"]
    return [q for q in qs if q in ("E_x", "E_y", "E_z", "E_px", "E_py", "E_pz")]


def worse_than_model(df: pd.DataFrame) -> list[str]:
    """Warnings, one per observer and model-only reference: an observer whose mean tip-position error after
    initialisation (``E_xyz``; each axis where one of the two has fewer) is larger than that of an
    observer running the model alone (``model_only``: the open loop) from the same common start -- the
    measurements made it worse, and its settings do not suit the data."""
    if df.empty or "model_only" not in df.columns:
        return []
    refs = df[df["model_only"].astype(bool) & df["start"].astype(str).str.startswith("common")]
    out = []
    for _, r in df.iterrows():
        if bool(r["model_only"]) or not str(r["start"]).startswith("common"):
            continue
        for _, ref in refs.iterrows():
            both = [q for q in _position_quantities(df)
                    if np.isfinite(r[f"{q}_mean"]) and np.isfinite(ref[f"{q}_mean"])]
            if not both:  # the observer has fewer axes than the norm: compare the axes it has
                both = [q for q in ("E_x", "E_y", "E_z", "E_px", "E_py", "E_pz") if f"{q}_mean" in df.columns
                        and np.isfinite(r[f"{q}_mean"]) and np.isfinite(ref[f"{q}_mean"])]
            worse = [q for q in both if r[f"{q}_mean"] > ref[f"{q}_mean"]]
            if worse:
                what = ", ".join(f"{q} {_short(r[f'{q}_mean'])} against {_short(ref[f'{q}_mean'])} mm" for q in worse)
                out.append(f"{r['observer']} does worse than {ref['observer']}, the model alone from the same start "
                           f"({what}): its settings do not suit these data")
    return out


def _pm(m: float, s: float, unit: str = "") -> str:
    if not np.isfinite(m):
        return "n/a"
    return f"{_float_format(m)} ± {_float_format(s)}" + (f" {unit}" if unit else "")


def _num(v: float) -> str:
    return f"{v:.0f}" if abs(v) >= 100 else f"{v:.3g}"


def appendix_form(df: pd.DataFrame, res: Group) -> pd.DataFrame:
    """The table in the form of the multi-rate UKF paper's appendix A (Table A.3): one column per observer, one row per
    property, one per error quantity (mean ± std after initialisation; n/a: not estimated) (``df``:
    :func:`compare_table`)."""
    length_unit = str(res.attrs.get("length_unit", "mm"))
    errs = error_quantities(df)
    rows: dict[str, list[str]] = {
        "Sensor": [], "Sensor frequency": [], "Model": [], "Observer": [], "Settings": [], "Start": [],
        "Online curvature estimation": [], f"Length of insertion ({length_unit})": [],
        **{f"{q} ({u})" if u else q: [] for q, u in errs},
        "Prediction error* (mm)": [], "Number of insertions": [], "Runs that failed": [], "Runtime per step": [],
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
        for q, u in errs:
            rows[f"{q} ({u})" if u else q].append(_pm(r[f"{q}_mean"], r[f"{q}_std"]))
        rows["Prediction error* (mm)"].append(_pm(r["pred_mean_mm"], r["pred_std_mm"]))
        rows["Number of insertions"].append(str(r["runs"]))
        failed = f"{r['runs_failed']}/{r['runs']}" + (f" ({r['failure_reasons']})" if r["failure_reasons"] else "")
        rows["Runs that failed"].append(failed)
        rows["Runtime per step"].append(f"{_num(r['ms_per_step'])} ms ({_num(r['us_per_run_step'])} µs per run-step)")
    return pd.DataFrame([{"": k, **dict(zip(df["observer"], v))} for k, v in rows.items()])


@TABLES.register("compare_appendix")
def compare_appendix_table(res: Group, errors: dict[str, ErrorSet]) -> pd.DataFrame:
    """The comparison of needle compare in the form of the multi-rate UKF paper's appendix A (Table A.3): one column per
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
            "Errors: mean and std over every kept run and time step after initialisation, each quantity for "
            "every observer (n/a: it does not estimate it); runtime per step: wall time of one grid step for all "
            "runs at once.")


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


def notes(res: Group, df: pd.DataFrame | None = None) -> str:
    """What the file form of the table says under it: the footnote, the common start, what differs between
    the filters' settings (``settings_note``), the warnings of :func:`worse_than_model` (``df``: the
    table), the skipped observers."""
    out = footnote(res) + f"\n\nStart: {common_start(res)}."
    diff = settings_note(res)
    if diff:
        out += f"\n\n{diff}"
    warn = worse_than_model(df) if df is not None else []
    if warn:
        out += "\n\nWarning:\n" + "\n".join(f"- {w}" for w in warn)
    sk = skipped(res)
    return out + ("\n\nSkipped:\n" + "\n".join(f"- {s}" for s in sk) if sk else "")


def settings_note(res: Group) -> str:
    """Whether the compared observers that weigh measurements (those whose settings name
    ``measurements``: the config's own and the derived ones) weigh them alike, or what differs: the
    channels each uses and the noise law of each (sigma, a distance growth of R, a gate), from the
    settings the results file's config records; empty with fewer than two such observers."""
    from needlecli.io.yamlfile import parse_yaml

    g = comparison(res)
    if g is None:
        return ""
    try:
        cfg = parse_yaml(str(res.attrs.get("config", "")), "the results file's config")
    except Exception:  # noqa: BLE001 (a config that cannot be read: nothing to say)
        return ""
    compared = set(_texts(g.data["observer"]))
    laws: dict[str, dict[str, str]] = {}  # observer -> channel -> its law
    for o in cfg.get("observers") or []:
        name = o.get("name") or o.get("type")
        meas = o.get("measurements")
        if name in compared and isinstance(meas, dict) and meas:
            laws[name] = {c: f"sigma {m.get('sigma')}" + (" with growth" if m.get("growth") else "")
                          + (f", gate {m['gate']}" if m.get("gate") else "")
                          for c, m in sorted(meas.items()) if isinstance(m, dict)}
    if len(laws) < 2:
        return ""
    channels = sorted({c for law in laws.values() for c in law})
    differ = [c for c in channels if len({law.get(c, "not used") for law in laws.values()}) > 1]
    if not differ:
        return f"Measurements weighed alike by {', '.join(sorted(laws))}."
    parts = []
    for c in differ:
        by: dict[str, list[str]] = {}
        for n, law in sorted(laws.items()):
            by.setdefault(law.get(c, "not used"), []).append(n)
        parts.append(f"{c}: " + "; ".join(f"{w} ({', '.join(ns)})" for w, ns in by.items()))
    return "Measurements weighed differently: " + " | ".join(parts) + "."


def terminal_form(df: pd.DataFrame, res: Group, width: int = 80) -> str:
    """The comparison for a terminal of ``width`` columns: what every observer shares in a few lines,
    then two narrow tables (how each observer ran; the mean of each error quantity, one row each, one
    column per observer), then the notes, wrapped."""
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
    errs = {"mean error": [f"{q} ({u})" if u else q for q, u in error_quantities(df)] + ["prediction* (mm)"]}
    for _, r in df.iterrows():
        errs[str(r["observer"])] = [_short(r[f"{q}_mean"]) for q, _ in error_quantities(df)] + [_short(r["pred_mean_mm"])]
    parts += [_narrow_markdown(how), _narrow_markdown(pd.DataFrame(errs))]
    start = common_start(res)
    notes_ = [f"Start: every observer marked 'common' starts from one initial estimate, the {start}."
              if start and not start.startswith("no ") else f"Start: {start}."]
    diff = settings_note(res)
    if diff:
        notes_.append(diff)
    online = [o for o, c in zip(df["observer"], df["online_curvature"]) if c == "yes"]
    notes_.append(f"Curvature estimated online by: {', '.join(online) or 'none'}.")
    offline = [o for o, c in zip(df["observer"], df["causal"]) if not c]
    if offline:
        notes_.append(f"Smoothers (every sample of a run, also later ones; not a filter): {', '.join(offline)}.")
    notes_.append(footnote(res) + " Mean and std of each in compare.md and compare.csv.")
    failed = [f"{o}: {r}" for o, r in zip(df["observer"], df["failure_reasons"]) if r]
    if failed:
        notes_.append("Failed runs: " + "; ".join(failed) + ".")
    parts += [textwrap.fill(n, width) for n in notes_]
    return "\n\n".join(parts)
