"""Tables for recorded insertions (replayed logs with a tracker as ground truth, issue 8): the raw
measurements' error beside the observers' at the same frames, how each observer used (or gated) each
channel per trial, and per-trial error summaries."""

from __future__ import annotations

import numpy as np
import pandas as pd

from needlecli.io.results import Group
from needlecli.metrics import ErrorSet
from needlecli.reports.tables import TABLES, count_cell, order_quantities

_LENGTH_TO_MM = {"mm": 1.0, "m": 1000.0, "cm": 10.0}
_AXES = (("x", "y", "z"), ("px", "py", "pz"))


def _trial_ids(res: Group) -> np.ndarray:
    """Trial ids of replayed logs, else ``run <i>`` (results and fit files)."""
    truth = res.data["truth"]
    ids = truth.data.get("trial_id")
    if ids is not None:
        return np.asarray(ids).astype(str)
    n = int(res.attrs.get("runs", truth.data["state"].shape[0] if "state" in truth.data else 0))
    return np.array([f"run {i}" for i in range(n)])


def _stats(v: np.ndarray) -> dict[str, float]:
    v = v[np.isfinite(v)]
    if not v.size:
        return {"Mean": np.nan, "Std": np.nan, "Median": np.nan, "RMSE": np.nan, "Max": np.nan}
    return {"Mean": float(np.mean(v)), "Std": float(np.std(v)), "Median": float(np.median(v)),
            "RMSE": float(np.sqrt(np.mean(v**2))), "Max": float(np.max(v))}


def _position_streams(res: Group):
    """``(name, axes, value (N, M, k), valid (N, M), index (M,))`` of every position measurement stream."""
    for name, g in res.data.get("measurements", Group()).data.items():
        if str(g.attrs.get("type", "")) != "position":
            continue
        names = [str(n) for n in g.attrs["names"]]
        yield name, names, g.data["value"], g.data["valid"], np.asarray(g.data["index"])


@TABLES.register("real_tip_error")
def real_tip_error(res: Group, errors: dict[str, ErrorSet]) -> pd.DataFrame:
    """Tip position error [mm] against the reference (on recorded data the EM tracker): each position
    sensor's raw measurements at its valid frames, each observer at the same frames, and each observer at
    every frame with a reference sample (the multi-rate UKF paper's instantaneous error). A stream identical to the
    reference (the tracker's own positions) is left out."""
    truth = res.data["truth"]
    t_names = list(truth.attrs["names"])
    axes = next((ax for ax in _AXES if all(a in t_names for a in ax)), None)
    if axes is None:
        return pd.DataFrame(columns=["Source", "Compared at", "Frames", "Mean", "Std", "Median", "RMSE", "Max", "Runs"])
    scale = _LENGTH_TO_MM.get(str(res.attrs.get("length_unit", "mm")), 1.0)
    state = truth.data["state"]
    t_ok = truth.data["status"] == "ok"
    estimates = res.data.get("estimates", Group()).data
    rows = []

    def row(source, at, err, runs, n_runs):
        fin = np.isfinite(err)
        rows.append({"Source": source, "Compared at": at, "Frames": int(fin.sum()), **_stats(err),
                     "Runs": count_cell(runs, n_runs)})

    n_runs = state.shape[0]
    for name, names, value, valid, index in _position_streams(res):
        cols = [a for a in axes if a in names]
        if not cols:
            continue
        ref = state[:, index][..., [t_names.index(a) for a in cols]]  # (N, M, k)
        meas = value[..., [names.index(a) for a in cols]]
        err = scale * np.linalg.norm(meas - ref, axis=-1)
        use = valid & t_ok[:, None] & np.isfinite(err)
        if use.any() and np.nanmax(np.where(use, err, np.nan)) < 1e-9:
            continue  # the reference's own stream
        label = "E_" + "".join(c[-1] for c in cols)
        row(f"{name} (raw measurements)", f"valid {name} frames ({label})", np.where(use, err, np.nan),
            int(use.any(axis=1).sum()), n_runs)
        for obs, g in estimates.items():
            e_names = list(g.attrs["names"])
            if not all(a in e_names for a in cols):
                continue
            e_ok = g.data["status"] == "ok"
            est = g.data["state"][:, index][..., [e_names.index(a) for a in cols]]
            e = scale * np.linalg.norm(est - ref, axis=-1)
            keep = use & e_ok[:, None]
            row(obs, f"valid {name} frames ({label})", np.where(keep, e, np.nan), int(keep.any(axis=1).sum()), n_runs)
    for obs, es in errors.items():
        qe = es.quantities.get("E_xyz")
        if qe is not None:
            row(obs, "every reference frame (E_xyz)", qe.values, len(qe.runs), es.n_runs)
    return pd.DataFrame(rows, columns=["Source", "Compared at", "Frames", "Mean", "Std", "Median", "RMSE", "Max", "Runs"])


@TABLES.register("measurement_use")
def measurement_use(res: Group, errors: dict[str, ErrorSet]) -> pd.DataFrame:
    """Per observer, channel and trial: the channel's samples, how many were valid (the rest lost:
    missing measurements), used in an update, and rejected by the chi-square gate; runs of the same trial
    with the same counts share one row (Runs: how many of the observer's runs it stands for)."""
    ids = _trial_ids(res)
    meas = res.data.get("measurements", Group()).data
    frames = []
    for obs, g in res.data.get("estimates", Group()).data.items():
        used = g.data.get("used")
        gated = g.data.get("gated")
        if not isinstance(used, Group):
            continue
        for ch, u in used.data.items():
            gt = gated.data.get(ch) if isinstance(gated, Group) else None
            gt = np.asarray(gt) if gt is not None else np.zeros_like(u)
            valid = meas[ch].data["valid"].sum(axis=1) if ch in meas else np.full(len(u), -1)
            samples = meas[ch].data["valid"].shape[1] if ch in meas else -1
            with np.errstate(invalid="ignore", divide="ignore"):
                pct = np.where(valid > 0, 100.0 * gt / np.maximum(valid, 1), np.nan)
            per_run = pd.DataFrame({"Observer": obs, "Channel": ch, "Trial": ids, "Samples": samples,
                                    "Valid": valid, "Used": np.asarray(u), "Gated": gt,
                                    "Gated [% of valid]": pct.astype(float)})
            keys = ["Observer", "Channel", "Trial", "Samples", "Valid", "Used", "Gated"]
            rows = per_run.groupby(keys, sort=False, dropna=False).agg(
                pct=("Gated [% of valid]", "first"), n=("Trial", "size")).reset_index()
            rows["Runs"] = [count_cell(k, len(ids)) for k in rows["n"]]
            frames.append(rows.rename(columns={"pct": "Gated [% of valid]"}).drop(columns="n"))
    cols = ["Observer", "Channel", "Trial", "Samples", "Valid", "Used", "Gated", "Gated [% of valid]", "Runs"]
    return pd.concat(frames, ignore_index=True)[cols] if frames else pd.DataFrame(columns=cols)


@TABLES.register("per_trial")
def per_trial(res: Group, errors: dict[str, ErrorSet]) -> pd.DataFrame:
    """Per observer, quantity and trial: mean, maximum and final error (the last frame with a reference
    sample) over the trial."""
    ids = _trial_ids(res)
    frames = []
    for obs, es in errors.items():
        for q in order_quantities(es.quantities):
            qe = es.quantities[q]
            v = qe.values
            if v.size == 0:
                continue
            fin = np.isfinite(v)
            has = fin.any(axis=1)
            last = v.shape[1] - 1 - np.argmax(fin[:, ::-1], axis=1)
            with np.errstate(invalid="ignore"):
                mean = np.where(has, np.nanmean(np.where(fin, v, np.nan), axis=1), np.nan) if has.any() else np.full(len(v), np.nan)
                mx = np.where(has, np.nanmax(np.where(fin, v, -np.inf), axis=1), np.nan)
            final = np.where(has, v[np.arange(len(v)), last], np.nan)
            frames.append(pd.DataFrame({"Observer": obs, "Quantity": f"{q} [{qe.unit}]", "Trial": ids[qe.runs],
                                        "Mean": mean, "Max": mx, "Final": final}))
    cols = ["Observer", "Quantity", "Trial", "Mean", "Max", "Final"]
    return pd.concat(frames, ignore_index=True)[cols] if frames else pd.DataFrame(columns=cols)


_DEPTH_MARKS = (0.0, 5.0, 10.0, 20.0, 30.0, 40.0, 50.0, 60.0, 80.0, 100.0)


@TABLES.register("real_error_vs_depth")
def real_error_vs_depth(res: Group, errors: dict[str, ErrorSet]) -> pd.DataFrame:
    """Error against inserted depth, each trial at its own depth (replayed trials differ in speed and
    length): per observer and quantity the mean over the trials of the error at the first reference frame
    at or after each depth, and at each trial's last reference frame ("final"). Depths that fewer than
    half of the trials reached are not shown; a trial that did not reach a depth does not count there."""
    depth = np.asarray(res.data["depth"], dtype=float)
    unit = res.attrs.get("length_unit", "mm")
    rows = []
    for obs, es in errors.items():
        for q in order_quantities(es.quantities):
            qe = es.quantities[q]
            v = qe.values
            if v.size == 0:
                continue
            d = np.broadcast_to(depth, (es.n_runs, v.shape[1]))[qe.runs] if depth.ndim == 2 else np.broadcast_to(depth, v.shape)
            fin = np.isfinite(v)
            row = {"Observer": obs, "Quantity": f"{q} [{qe.unit}]"}
            for mark in _DEPTH_MARKS:
                at = fin & (d >= mark - 1e-9)
                has = at.any(axis=1)
                if 2 * has.sum() < len(v):
                    break
                i = np.argmax(at, axis=1)
                val = v[np.arange(len(v)), i][has]
                row[f"at {mark:g} {unit}"] = float(np.mean(val)) if val.size else np.nan
            has = fin.any(axis=1)
            last = v.shape[1] - 1 - np.argmax(fin[:, ::-1], axis=1)
            final = v[np.arange(len(v)), last][has]
            row["final"] = float(np.mean(final)) if final.size else np.nan
            row["Trials"] = count_cell(has.sum(), es.n_runs)
            rows.append(row)
    return pd.DataFrame(rows)


# ---------------------------------------------------------------------------------------------- EM fits
_POSITION_STATES = ("x", "y", "z", "px", "py", "pz")


def _fit_models(res: Group):
    fit = res.data.get("fit")
    return fit.data.items() if isinstance(fit, Group) else []


def _fit_speed(res: Group) -> np.ndarray:
    """Each trial's insertion speed: the median of its nonzero commanded speed (NaN without ``v``)."""
    v = res.data.get("inputs", Group()).data.get("v")
    if v is None:
        return np.full(len(_trial_ids(res)), np.nan)
    v = np.asarray(v, dtype=float)
    v = v.reshape(v.shape[0], -1)
    with np.errstate(invalid="ignore"):
        return np.nanmedian(np.where(v != 0, v, np.nan), axis=1)


def _last_finite(h: np.ndarray) -> np.ndarray:
    fin = np.isfinite(h)
    last = h.shape[1] - 1 - np.argmax(fin[:, ::-1], axis=1)
    return np.where(fin.any(axis=1), h[np.arange(len(h)), last], np.nan)


def _rms_block(M: np.ndarray, idx: list[int]) -> np.ndarray:
    """``sqrt(tr M_block / k)`` per trial for the block of ``idx`` (NaN for an empty block)."""
    if not idx:
        return np.full(M.shape[0], np.nan)
    return np.sqrt(np.trace(M[:, idx][:, :, idx], axis1=-2, axis2=-1) / len(idx))


@TABLES.register("em_per_trial")
def em_per_trial(res: Group, errors=None) -> pd.DataFrame:
    """EM fit per model and trial (a fit file of needle fit-em): status and iterations, log-likelihood at
    the first and last iteration, each fitted constant (a curvature also as the radius 1/kappa), the
    process noise as rms standard deviations per square-root second of the position and the other
    states' blocks, sqrt(tr(Q_block) / k), and each channel's measurement noise, sqrt(tr(R_j) / m)."""
    ids = _trial_ids(res)
    speed = _fit_speed(res)
    frames = []
    for model, g in _fit_models(res):
        names = [str(n) for n in g.attrs["names"]]
        units = [str(u) for u in g.attrs.get("units", [""] * len(names))]
        q_states = [str(s) for s in g.attrs.get("q_states", names)]
        Q = np.asarray(g.data["Q"])
        ll = np.asarray(g.data["history"].data["loglik"], dtype=float)
        df = pd.DataFrame({"Model": model, "Trial": ids, "Speed [mm/s]": speed,
                           "Status": np.asarray(g.data["status"]).astype(str),
                           "Iterations": np.asarray(g.data["iterations"]),
                           "Log-lik. first": ll[:, 0], "Log-lik. last": _last_finite(ll),
                           "LL decreases": np.asarray(g.data["ll_decreases"])})
        c_units = dict(zip([str(c) for c in g.attrs.get("constants", [])], [str(u) for u in g.attrs.get("constant_units", [])]))
        for c, v in g.data["constant"].data.items():
            unit = units[names.index(c)] if c in names else c_units.get(c, "")
            df[f"{c} [{unit}]"] = np.asarray(v, dtype=float)
            if unit.startswith("1/"):
                with np.errstate(divide="ignore"):
                    df[f"1/{c} [{unit[2:]}]"] = 1.0 / np.asarray(v, dtype=float)
        sensor = [str(s) for s in g.attrs.get("sensor_states", [])]
        pos = [names.index(s) for s in q_states if s in _POSITION_STATES and s in names]
        other = [names.index(s) for s in q_states if s not in _POSITION_STATES and s in names and s not in sensor]
        pos_unit = units[pos[0]] if pos else ""
        df[f"Q position rms [{pos_unit}/sqrt(s)]"] = _rms_block(Q, pos)
        df["Q other states rms [/sqrt(s)]"] = _rms_block(Q, other)
        for s_name, tau in zip(sensor, np.atleast_1d(g.attrs.get("sensor_state_tau", []))):  # a sensor's offset
            j, tau = names.index(s_name), float(tau)
            if np.isfinite(tau):  # an Ornstein-Uhlenbeck state: its stationary std sqrt(q^2 tau / 2)
                df[f"{s_name} std [{units[j]}] (tau {tau:g} s)"] = np.sqrt(Q[:, j, j] * tau / 2.0)
            else:  # a constant: its estimate
                df[f"{s_name} [{units[j]}]"] = np.asarray(g.data["x0"])[:, j]
        for ch, R in g.data["R"].data.items():
            if ch.endswith("_guess"):
                continue
            R = np.asarray(R)
            df[f"R {ch} rms"] = np.sqrt(np.trace(R, axis1=-2, axis2=-1) / R.shape[-1])
        frames.append(df)
    return pd.concat(frames, ignore_index=True) if frames else pd.DataFrame()


@TABLES.register("em_per_speed")
def em_per_speed(res: Group, errors=None) -> pd.DataFrame:
    """EM fit per model and insertion speed (a fit file of needle fit-em): trials, how many converged,
    and each fitted constant over the converged trials (median, mean, SD; a curvature also as the radius
    1/kappa) with its standard error from the summed observed information of the speed's assessed
    trials (identifiability; the radius's by the delta method at the median)."""
    per = em_per_trial(res)
    if per.empty:
        return per
    const = [c for c in per.columns if c.split(" [")[0] in {str(k) for _, g in _fit_models(res) for k in g.data["constant"].data}
             or c.startswith("1/")]
    rows = []
    info = {model: _constant_information(g) for model, g in _fit_models(res)}
    for (model, sp), d in per.groupby(["Model", "Speed [mm/s]"], dropna=False):
        ok = d[d["Status"] == "ok"]
        row = {"Model": model, "Speed [mm/s]": sp, "Converged": count_cell(len(ok), len(d))}
        for c in const:
            v = ok[c].to_numpy(dtype=float)
            row[f"{c} median"] = float(np.median(v)) if v.size else np.nan
            row[f"{c} mean"] = float(np.mean(v)) if v.size else np.nan
            row[f"{c} SD"] = float(np.std(v, ddof=1)) if v.size > 1 else np.nan
            name = c.split(" [")[0]
            trials = d.index.to_numpy() - per.index[per["Model"] == model][0]  # the speed's trials in the fit
            se = _pooled_se(info[model], name.removeprefix("1/"), trials)
            if name.startswith("1/"):  # the radius r = 1/c: SE(r) = r^2 SE(c) at the median
                se = se * row[f"{c} median"] ** 2
            row[f"{c} SE (pooled)"] = se
        rows.append(row)
    return pd.DataFrame(rows)


def _constant_information(g: Group):
    """``(names, information (N, d, d), used (N,))`` of a fit's identifiability group, or None."""
    idf = g.data.get("identifiability")
    if idf is None:
        return None
    return ([str(q) for q in idf.attrs["quantities"]], -np.asarray(idf.data["hessian"], dtype=float),
            np.asarray(idf.data["used"], dtype=bool))


def _pooled_se(info, name: str, trials: np.ndarray) -> float:
    """Standard error of quantity ``name`` from the summed observed information of ``trials`` (those
    assessed): ``sqrt((sum_i I_i)^-1)`` on its diagonal; NaN without the information."""
    if info is None or name not in info[0]:
        return np.nan
    names, I, used = info
    sel = trials[used[trials]]
    if not sel.size:
        return np.nan
    tot = np.nansum(I[sel], axis=0)
    k = names.index(name)
    with np.errstate(all="ignore"):
        try:
            cov = np.linalg.pinv(0.5 * (tot + tot.T))
        except np.linalg.LinAlgError:
            return np.nan
    return float(np.sqrt(cov[k, k])) if cov[k, k] > 0 else np.nan


_LL_AT = (1, 2, 5, 10, 20, 50, 100, 200, 500)


@TABLES.register("em_loglik")
def em_loglik(res: Group, errors=None) -> pd.DataFrame:
    """EM log-likelihood history per model and trial (a fit file of needle fit-em): the log-likelihood of
    the measurements after iterations 1, 2, 5, ... and at the last one (the whole history is in the fit
    file, /fit/<model>/history/loglik)."""
    ids = _trial_ids(res)
    frames = []
    for model, g in _fit_models(res):
        ll = np.asarray(g.data["history"].data["loglik"], dtype=float)
        df = pd.DataFrame({"Model": model, "Trial": ids})
        for k in _LL_AT:
            if k <= ll.shape[1]:
                df[f"it {k}"] = ll[:, k - 1]
        df["last"] = _last_finite(ll)
        df["Iterations"] = np.asarray(g.data["iterations"])
        frames.append(df)
    return pd.concat(frames, ignore_index=True) if frames else pd.DataFrame()


#: this module's tables of a fit file of ``needle fit-em`` (``needle evaluate FIT.h5 --tables em_per_trial``)
