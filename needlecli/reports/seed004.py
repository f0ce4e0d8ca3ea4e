"""The tables and figures of a fit file of ``needle fit-em``: the magnetic needle EM paper's and their generic forms.

* ``fit_parameters``: for any fitted model, each constant, tr(Q) per block and tr(R_j) per channel: mean,
  SD and the SD as trajectory error, one row per model and quantity (Tables 1 and 2 below in long form);
* ``mnm_parameters`` (MNM) and ``binm_parameters`` (BiNM): the constant (``c``, ``l_inv``) per parameter case
  (field strength), ``tr(Q_p)``, ``tr(Q_h)``, ``tr(Q_B)`` and ``tr(R_j)`` of every channel, each trace
  divided by its dimension as the paper reports them; rows Mean, SD and "SD as Traj. Err. (mm)": the
  input cases (T1, T2, mirrored) re-simulated with the mean parameters and with each parameter moved by
  one SD up and down, ``repeats`` times with the same process noise for nominal and moved, the RMS
  distance of the tip path to the nominal one averaged (R does not enter the path: 0).
* ``binm_vs_mnm``: % difference of the BiNM from the MNM, by the mean trace and block-wise by the
  Frobenius norm of the difference of the element-wise median matrices.
* ``fit_recovery``: the fits against the truth of a
  simulated study, for any model.
* ``fit_status``: statuses, reasons, iterations, log-likelihood decreases.

``needle evaluate FIT.h5`` writes the magnetic needle EM paper's own tables (``mnm_parameters`` to ``3``) by default only for a fit
of the models they are about (:data:`PAPER_TABLE_MODELS`); a fit of a unicycle gets ``fit_parameters``.

Trials whose fit failed for any model (singular, diverged) are left out for every model (the magnetic needle EM paper: 3 of
44 trials). Figures: ``fit_paths`` (a trial's paths and measurements, both models), ``binm_singularity``
(``h . B`` against time through the BiNM singularity).
"""

from __future__ import annotations

import logging
import re
from pathlib import Path

import numpy as np
import pandas as pd

from needlecli.errors import DataError
from needlecli.io.results import Group
from needlecli.models import MODELS
from needlecli.models.base import state_blocks
from needlecli.reports import FIT_DEFAULT, FIT_TABLE_NAMES
from needlecli.reports.identify import MARK, mark_label, weak_note, weak_quantities
from needlecli.reports.plots import PLOTS, beside_legend, draw_plots, observer_style, save_figure, subplots
from needlecli.reports.tables import TABLES, count_cell, table_caption, write_table

log = logging.getLogger("needlecli")

FIT_TABLES = FIT_DEFAULT  # written by default (the tables of a fit file: needlecli.reports.FIT_TABLE_NAMES)
#: the magnetic needle EM paper's paper tables and the models each is about: written by default only for a fit of those models
#: (the others' fits get the same content from fit_parameters, under a name that says what it holds)
PAPER_TABLE_MODELS = {"mnm_parameters": ("mnm",), "binm_parameters": ("binm",), "binm_vs_mnm": ("mnm", "binm")}
#: every table of a fit file: :data:`FIT_TABLES` (written by default) and those asked for by name
ALL_FIT_TABLES = FIT_TABLE_NAMES
FIT_PLOTS = ("fit_paths", "binm_singularity", "fit_regression")
FAILED = ("singular", "diverged")
_TO_MM = {"m": 1000.0, "mm": 1.0, "cm": 10.0}


def is_fit(res: Group) -> bool:
    return res.attrs.get("format") == "needlecli-fit" and "fit" in res.data


def kept_trials(res: Group) -> np.ndarray:
    """Trials no model failed on (``(N,)`` bool): compared for every model, as in the magnetic needle EM paper."""
    fits = res.data["fit"].data
    keep = None
    for g in fits.values():
        ok = ~np.isin(np.asarray(g.data["status"]).astype(str), FAILED)
        keep = ok if keep is None else keep & ok
    return keep


def _cases(res: Group):
    """``(index (N,), labels)`` of the parameter cases, or one case for all."""
    tr = res.data.get("truth", Group())
    if "param_case" in tr.data:
        labels = [str(x) for x in np.atleast_1d(tr.attrs.get("param_case_labels", []))]
        idx = np.asarray(tr.data["param_case"])
        if not labels:
            labels = [f"case {i}" for i in range(int(idx.max()) + 1)]
        return idx, labels
    N = int(res.attrs.get("runs", 0))
    return np.zeros(N, dtype=int), ["all"]


def _stats(res: Group, model: str, keep: np.ndarray) -> dict:
    g = res.data["fit"].data[model]
    names = [str(x) for x in g.attrs["names"]]
    consts = [str(x) for x in np.atleast_1d(g.attrs.get("constants", []))]
    Q = np.asarray(g.data["Q"])[keep]
    out = {"names": names, "constants": consts, "Q": Q, "R": {}, "const": {}}
    for c in consts:
        out["const"][c] = np.asarray(g.data["constant"].data[c])[keep]
    for ch, R in g.data["R"].data.items():
        if not ch.endswith("_guess"):
            out["R"][ch] = np.asarray(R)[keep]
    out["blocks"] = state_blocks(names, skip=consts)
    out["x0"] = np.asarray(g.data["x0"])[keep]
    return out


def _trace(M: np.ndarray, idx) -> np.ndarray:
    sub = M[:, idx][:, :, idx]
    return np.trace(sub, axis1=-2, axis2=-1) / len(idx)


def _mean_sd(v: np.ndarray) -> tuple[float, float]:
    v = v[np.isfinite(v)]
    if not v.size:
        return np.nan, np.nan
    return float(v.mean()), float(v.std(ddof=1)) if v.size > 1 else np.nan


# ---------------------------------------------------------------------------------------------- Tables 1, 2
def parameter_table(res: Group, model: str) -> pd.DataFrame:
    """The magnetic needle EM paper's Table 1 (MNM) / Table 2 (BiNM) for ``model``."""
    if not is_fit(res) or model not in res.data["fit"].data:
        return pd.DataFrame()
    keep = kept_trials(res)
    st = _stats(res, model, keep)
    case, labels = _cases(res)
    case = case[keep]
    cols, mean, sd, moves = [], [], [], []
    for c in st["constants"]:
        for k, lbl in enumerate(labels):
            m, s = _mean_sd(st["const"][c][case == k])
            cols.append(f"{c} @ {lbl}" if len(labels) > 1 else c)
            mean.append(m)
            sd.append(s)
            moves.append(("const", c, k, m, s))
    for b, idx in st["blocks"].items():
        if not np.any(st["Q"][:, idx][:, :, idx]):
            continue  # a block without process noise (not fitted)
        m, s = _mean_sd(_trace(st["Q"], idx))
        cols.append(f"tr(Q_{b})")
        mean.append(m)
        sd.append(s)
        moves.append(("Q", b, idx, m, s))
    for ch, R in st["R"].items():
        m, s = _mean_sd(np.trace(R, axis1=-2, axis2=-1) / R.shape[-1])
        cols.append(f"tr(R_{ch})")
        mean.append(m)
        sd.append(s)
        moves.append(("R", ch, None, m, s))
    err = trajectory_errors(res, model, st, moves, case)
    weak = weak_quantities(res, model)
    quantity = [mv[1] if mv[0] == "const" else f"tr({mv[0]}_{mv[1]})" for mv in moves]
    df = pd.DataFrame([mean, sd, err], columns=[mark_label(c, q, weak) for c, q in zip(cols, quantity)])
    df.insert(0, "", ["Mean", "SD", "SD as Traj. Err. (mm)"])
    df.attrs["kept"] = int(keep.sum())
    note = weak_note({model: {q: w for q, w in weak.items() if q in quantity}})
    if note:
        df.attrs["note"] = note
    return df


@TABLES.register("mnm_parameters")
def table1(res: Group, errors=None) -> pd.DataFrame:
    """The magnetic needle EM paper's Table 1, MNM parameterization: c per field strength, tr(Q_p), tr(Q_h), tr(Q_B) (per second)
    and tr(R_j) of each channel, traces divided by their dimension; mean, SD and the SD as trajectory
    error. Paper (experiments): c 5.3/9.5/11.9 (SD 3.2/4.8/5.6) 1/m; tr(Q_p) 1.10e-7, tr(Q_h) 6.65e-4,
    tr(Q_B) 7.32e-9, tr(R_p) 2.70e-9, tr(R_B) 5.6e-12; SD as error 0.002/0.022/0.003, 0.052, 2e-13 mm."""
    return parameter_table(res, "mnm")


@TABLES.register("binm_parameters")
def table2(res: Group, errors=None) -> pd.DataFrame:
    """The magnetic needle EM paper's Table 2, BiNM parameterization (l_inv per field strength; as Table 1). Paper: l_inv
    1.6/3.5/4.9 (SD 1.6/3.0/3.4) 1/m; tr(Q_p) 1.10e-7, tr(Q_h) 6.40e-3, tr(Q_B) 7.37e-9, tr(R_p) 2.72e-9;
    SD as error 0.114/0.302/0.360, 0.200, 0.001 mm."""
    return parameter_table(res, "binm")


# ---------------------------------------------------------------------------------------------- SD as error
def trajectory_errors(res: Group, model: str, st: dict, moves: list, case: np.ndarray) -> list[float]:
    """The "SD as Traj. Err. (mm)" row: per column, the mean RMS distance (mm) between tip paths simulated
    with the mean parameters and with that one parameter moved by +-SD (same process noise), over every
    input case of the study and ``repeats`` noise draws."""
    repeats = int(res.attrs.get("repeats", 100))
    mcls = MODELS.get(model)
    nx = len(mcls.state_names)
    time = np.asarray(res.data["time"])
    if len(time) < 2 or not st["Q"].shape[0]:
        return [np.nan] * len(moves)
    dt = float(time[1] - time[0])
    k = max(1, int(round(0.05 / dt)))
    inputs = res.data["inputs"]
    N = len(np.asarray(inputs.data[mcls.input_names[0]]))
    in_case = np.asarray(inputs.data["case"]) if "case" in inputs.data else np.zeros(N, dtype=int)
    cases = np.unique(in_case)
    first = [int(np.nonzero(in_case == c)[0][0]) for c in cases]
    us = []
    for name in mcls.input_names:
        a = np.asarray(inputs.data[name], dtype=float)
        us.append(a[..., None] if a.ndim == 2 else a)
    u = np.concatenate(us, -1)[first]  # (C, T, m)
    T = (u.shape[1] - 1) // k
    u = u[:, : T * k].reshape(len(first), T, k, -1).mean(2)  # (C, T', m)
    h = dt * k
    x0 = st["x0"][:, :nx].mean(0)
    Qm = st["Q"][:, :nx, :nx].mean(0)
    const_all = {c: float(np.nanmean(v)) for c, v in st["const"].items()}
    # variants: (constants, Q) for nominal and moved parameters
    variants, pairs = [], []

    def add(consts, Q):
        variants.append((consts, Q))
        return len(variants) - 1

    base_all = add(const_all, Qm)
    out_idx = []
    for kind, name, where, m, s in moves:
        if kind == "R" or not np.isfinite(s) or not np.isfinite(m) or m == 0:
            out_idx.append(None if kind != "R" else "R")
            continue
        if kind == "const":
            consts = dict(const_all)
            consts[name] = m
            nom = add(consts, Qm)
            ups = [add({**consts, name: m + sg * s}, Qm) for sg in (1.0, -1.0)]
        else:
            nom = base_all
            ups = []
            for sg in (1.0, -1.0):
                scale = max(1.0 + sg * s / m, 0.0)
                D = np.ones(nx)
                D[where] = np.sqrt(scale)
                ups.append(add(const_all, Qm * D[:, None] * D[None, :]))
        out_idx.append((nom, ups))
        pairs.extend((nom, up) for up in ups)
    V, C, n = len(variants), len(first), nx
    roots = []
    for _, Q in variants:
        w, vec = np.linalg.eigh(0.5 * (Q + Q.T))
        roots.append(vec * np.sqrt(np.clip(w, 0.0, None)))
    roots = np.stack(roots)  # (V, n, n)
    consts = {c: np.array([v[0][c] for v in variants])[:, None, None] for c in st["const"]}
    params = {**{kk: np.asarray(v, dtype=float) for kk, v in mcls().param_arrays().items()}, **consts}
    rng = np.random.default_rng([int(res.attrs.get("seed", 0)), 4004])
    x = np.broadcast_to(x0, (V, repeats, C, n)).copy()
    acc = np.zeros((len(pairs), repeats, C))
    pa = np.array([p for p, _ in pairs], dtype=int)
    pb = np.array([q for _, q in pairs], dtype=int)
    model_obj = mcls()
    scale = _TO_MM.get(str(res.attrs.get("length_unit", "m")), 1.0)
    with np.errstate(all="ignore"):
        for j in range(T):
            x = model_obj.step(x, u[None, None, :, j], params, h)
            xi = rng.standard_normal((repeats, C, n))
            x = x + np.sqrt(h) * np.einsum("vij,rcj->vrci", roots, xi)
            d = x[pa, ..., :3] - x[pb, ..., :3]
            acc += (d**2).sum(-1)
    rms = scale * np.sqrt(acc / T)  # (pairs, repeats, C)
    out = []
    pi = 0
    for item in out_idx:
        if item is None:
            out.append(np.nan)
        elif item == "R":
            out.append(0.0)
        else:
            _, ups = item
            out.append(float(np.nanmean(rms[pi : pi + len(ups)])))
            pi += len(ups)
    return out


@TABLES.register("fit_parameters")
def fit_parameters_table(res: Group, errors=None) -> pd.DataFrame:
    """What EM fitted, for every model of the fit file: each constant (per parameter case), tr(Q) per state
    block and tr(R_j) per channel, traces divided by their dimension (Q per second); mean and SD over the
    kept trials and the SD as trajectory error (the input cases re-simulated with each quantity moved by one
    SD; mm). The magnetic needle EM paper's Tables 1 and 2 (tables mnm_parameters, binm_parameters) in long form, for any model."""
    if not is_fit(res):
        return pd.DataFrame()
    rows, notes = [], []
    for model in res.data["fit"].data:
        wide = parameter_table(res, model)
        for col in wide.columns[1:]:
            rows.append({"Model": model, "Quantity": col, "Mean": wide[col].iloc[0], "SD": wide[col].iloc[1],
                         "SD as Traj. Err. (mm)": wide[col].iloc[2]})
        if wide.attrs.get("note"):
            notes.append(wide.attrs["note"])
    df = pd.DataFrame(rows, columns=["Model", "Quantity", "Mean", "SD", "SD as Traj. Err. (mm)"])
    keep = kept_trials(res)
    df["Trials"] = count_cell(keep.sum(), len(keep))
    if notes:
        df.attrs["note"] = " ".join(notes)
    return df


# ---------------------------------------------------------------------------------------------- Table 3
@TABLES.register("binm_vs_mnm")
def table3(res: Group, errors=None) -> pd.DataFrame:
    """The magnetic needle EM paper's Table 3: % difference of the BiNM from the MNM, by the mean trace and block-wise (Frobenius
    norm of the difference of the element-wise median matrices over the norm of the MNM's). Paper: Q_p
    0.0 %, Q_h 863 %, Q_B 0.6 %, R_p 0.7 % (trace); 5.9 %, 369 %, 2.6 %, 0.0 % (block-wise)."""
    if not is_fit(res) or not {"mnm", "binm"} <= set(res.data["fit"].data):
        return pd.DataFrame()
    keep = kept_trials(res)
    a, b = _stats(res, "mnm", keep), _stats(res, "binm", keep)
    cols, trace, block = [], [], []

    def pct(x, y):
        return 100.0 * (y - x) / x if x else np.nan

    for name, idx in a["blocks"].items():
        if name not in b["blocks"] or not np.any(a["Q"][:, idx][:, :, idx]):
            continue
        ma, mb = a["Q"][:, idx][:, :, idx], b["Q"][:, idx][:, :, idx]
        cols.append(f"Q_{name}")
        trace.append(pct(np.mean(_trace(a["Q"], idx)), np.mean(_trace(b["Q"], idx))))
        block.append(_blockwise(ma, mb))
    allq = [i for idx in a["blocks"].values() for i in idx]
    cols.append("Q overall")
    trace.append(pct(np.mean(_trace(a["Q"], allq)), np.mean(_trace(b["Q"], allq))))
    block.append(_blockwise(a["Q"][:, allq][:, :, allq], b["Q"][:, allq][:, :, allq]))
    for ch in a["R"]:
        if ch in b["R"]:
            cols.append(f"R_{ch}")
            trace.append(pct(np.mean(np.trace(a["R"][ch], axis1=-2, axis2=-1)),
                             np.mean(np.trace(b["R"][ch], axis1=-2, axis2=-1))))
            block.append(_blockwise(a["R"][ch], b["R"][ch]))
    weak = {m: weak_quantities(res, m) for m in ("mnm", "binm")}
    quantity = [f"tr({c})" if c != "Q overall" else c for c in cols]
    either = {q for w in weak.values() for q in w}
    df = pd.DataFrame([trace, block], columns=[mark_label(c, q, either) for c, q in zip(cols, quantity)])
    df.insert(0, "% difference", ["Trace", "Blockwise"])
    marked = [c for c, q in zip(cols, quantity) if q in either]
    if marked:
        df.attrs["note"] = (f"{MARK} {', '.join(marked)}: not identified as fitted in at least one of the fits "
                            f"({'; '.join(f'{m}: ' + ', '.join(w) for m, w in weak.items() if w)}), so their % "
                            "difference compares values the data do not determine (EM stopped short of the "
                            "likelihood's maximum, a flat direction, or a bias), not two measurements; see table "
                            "identifiability.")
    return df


def _blockwise(ma: np.ndarray, mb: np.ndarray) -> float:
    if not ma.shape[0]:
        return np.nan
    da, db = np.median(ma, 0), np.median(mb, 0)
    den = np.linalg.norm(da)
    return float(100.0 * np.linalg.norm(db - da) / den) if den else np.nan


# ---------------------------------------------------------------------------------------------- recovery
@TABLES.register("fit_recovery")
def recovery_table(res: Group, errors=None) -> pd.DataFrame:
    """Fitted against true values of a simulated study, per design group of trials (the magnetic needle EM paper: field
    strength): each fitted constant (of the model that made the truth), tr(Q) per block (that model) and
    tr(R) per channel (every model), traces divided by their dimension; mean and SD over the kept trials,
    the error of the mean, and the fit's recovery check and verdict (table identifiability: estimate -
    truth in standard errors of the group's mean; "biased" beyond 2); any model (seed004_recovery is its
    former name)."""
    from needlecli.reports.identify import assessed, groups

    if not is_fit(res) or "params" not in res.data.get("truth", Group()).data:
        return pd.DataFrame()
    truth = res.data["truth"]
    true_model = str(res.attrs.get("model", ""))
    keep = kept_trials(res)
    rows = []
    for model in res.data["fit"].data:
        st = _stats(res, model, keep)
        same = model == true_model
        ig = assessed(res, model)
        gs = groups(ig) if ig is not None else None
        if gs is not None:
            labels, case = gs.labels, gs.group[keep]
        else:
            case, labels = _cases(res)
            case = case[keep]

        def verdict(q: str, g: int, gs=gs) -> tuple[float, str]:
            if gs is None or q not in gs.names:
                return np.nan, "not assessed"
            k = gs.names.index(q)
            return float(gs.z[g, k]), gs.text(g, k) if gs.trials[g] else "not assessed"

        q_std = np.asarray(truth.data.get("q_std", np.zeros(0)))
        sig = truth.data.get("sigma", Group()).data
        for g, lbl in enumerate(labels):
            sel = case == g
            n = int(sel.sum())
            if not n and (gs is None or not (gs.group == g).any()):  # a level no trial of this file has
                continue
            for c in st["constants"]:
                tv = np.asarray(truth.data["params"].data.get(c, np.full(len(keep), np.nan)))[keep] if same else None
                m, s = _mean_sd(st["const"][c][sel])
                t = float(np.mean(tv[sel])) if tv is not None and sel.any() else np.nan
                rows.append((model, c, lbl, t, m, s, *verdict(c, g), n))
            for b, idx in st["blocks"].items():
                if not np.any(st["Q"][:, idx][:, :, idx]):
                    continue
                m, s = _mean_sd(_trace(st["Q"][sel], idx))
                t = float(np.mean(q_std[idx] ** 2)) if same and q_std.size >= max(idx) + 1 else np.nan
                rows.append((model, f"tr(Q_{b})", lbl, t, m, s, *verdict(f"tr(Q_{b})", g), n))
            for ch, R in st["R"].items():
                m, s = _mean_sd(np.trace(R[sel], axis1=-2, axis2=-1) / R.shape[-1])
                t = float(np.mean(np.asarray(sig[ch]) ** 2)) if ch in sig else np.nan
                rows.append((model, f"tr(R_{ch})", lbl, t, m, s, *verdict(f"tr(R_{ch})", g), n))
    df = pd.DataFrame(rows, columns=["Model", "Quantity", "Group", "Truth", "Fitted mean", "Fitted SD",
                                     "z (estimate - truth)", "Verdict", "Trials"])
    with np.errstate(all="ignore"):
        df.insert(6, "Error of mean (%)", 100.0 * (df["Fitted mean"] - df["Truth"]) / df["Truth"])
    df["Trials"] = [count_cell(n, len(keep)) for n in df["Trials"]]
    biased = [f"{r.Model} {r.Quantity} ({r.Group})" for r in df.itertuples() if str(r.Verdict).startswith("biased")]
    df.attrs["note"] = (f"Biased (the mean misses its truth by more than 2 standard errors; the cause: table "
                        f"identifiability): {', '.join(biased)}." if biased else
                        "Every quantity with a truth is recovered within 2 standard errors in every group.")
    return df


@TABLES.register("fit_status")
def fit_status_table(res: Group, errors=None) -> pd.DataFrame:
    """EM outcome per model: trials per status with the reasons (each with its trials), EM iterations
    (median, max), E-step passes per iteration, log-likelihood decreases beyond numerical noise, SQUAREM
    steps rejected, and the warnings of table fit_warnings (R on its floor, Q nearly singular, negative
    curvatures reported as the roll + pi) by kind with their trials."""
    if not is_fit(res):
        return pd.DataFrame()
    from needlecli.reports.design import trial_ids, warning_summary

    ids = trial_ids(res)
    warn = warning_summary(res, statuses=False)
    rows = []
    for model, g in res.data["fit"].data.items():
        status = np.asarray(g.data["status"]).astype(str)
        reason = np.asarray(g.data["reason"]).astype(str)
        it = np.asarray(g.data["iterations"])
        for s in np.unique(status):
            sel = status == s
            by_reason: dict[str, list[str]] = {}  # each reason with the trials that gave it, in full
            for r, tid in zip(reason[sel], ids[sel]):
                if r:
                    m = re.match(r"^(.*?)\s*\(([^()]*)\)$", r)  # a trailing detail: per trial
                    base, detail = (m.group(1), f" ({m.group(2)})") if m else (r, "")
                    by_reason.setdefault(base, []).append(f"{tid}{detail}")
            reasons = [f"{r}: {', '.join(t)}" for r, t in by_reason.items()]
            rows.append({
                "Model": model, "Status": s, "Trials": count_cell(sel.sum(), len(sel)),
                "Iterations (median)": float(np.median(it[sel])), "Iterations (max)": int(it[sel].max()),
                "E-step passes / iteration": float(np.mean(np.asarray(g.data["estep_passes"])[sel] / np.maximum(it[sel], 1))),
                "LL decreases": int(np.asarray(g.data["ll_decreases"])[sel].sum()),
                "SQUAREM rejected": int(np.asarray(g.data.get("rejections", np.zeros(len(sel))))[sel].sum()),
                "Reasons": "; ".join(reasons),
                "Warnings": "" if s != np.unique(status)[0] else  # once per model, on its first row
                "; ".join(w.split(": ", 1)[1] for w in warn if w.startswith(f"{model}: ")),
            })
    return pd.DataFrame(rows)


# ---------------------------------------------------------------------------------------------- figures
def _position_channel(res: Group):
    for name, g in res.data.get("measurements", Group()).data.items():
        if str(g.attrs.get("type", "")) == "position":
            return name, g
    return None, None


def _pick_trial(res: Group, prefer: tuple[str, ...]) -> int:
    keep = kept_trials(res)
    inputs = res.data["inputs"]
    labels = [str(x) for x in np.atleast_1d(inputs.attrs.get("case_labels", []))]
    case = np.asarray(inputs.data["case"]) if "case" in inputs.data else None
    pcase, plabels = _cases(res)
    cand = np.nonzero(keep)[0] if keep.any() else np.arange(len(keep))
    if case is not None and labels:
        good = [i for i in cand if all(p in labels[case[i]] for p in prefer)]
        if good:
            last = [i for i in good if pcase[i] == pcase.max()]
            return int((last or good)[0])
    return int(cand[0])


@PLOTS.register("fit_paths")
def fig5(res: Group, errors, path_stem: Path) -> Path | None:
    """The magnetic needle EM paper's Fig. 5: one trial's measured positions and the EM position estimates of both models (a),
    and the distance of each estimate from the measurements with its running RMS (b)."""
    if not is_fit(res):
        return None
    ch, mg = _position_channel(res)
    if ch is None:
        return None
    i = _pick_trial(res, ("T2", "-x"))
    scale = _TO_MM.get(str(res.attrs.get("length_unit", "m")), 1.0)
    names = [str(x) for x in mg.attrs["names"]]
    y_all = np.asarray(mg.data["value"])[i] * scale
    valid = np.asarray(mg.data["valid"])[i]
    pairs = _position_pairs(res, names)  # (state stem, channel) of every measured axis the fits have
    if not pairs:
        return None
    cols = [names.index(c) for _, c in pairs]
    y = y_all[:, cols]
    shown = _two_widest(y, valid)  # the plane of the plot: the two axes the path spans most
    t_meas = np.asarray(mg.data["t"])
    fig, axs = subplots(1, 2, figsize=(13, 4.8))
    axs[0].plot(y[valid, shown[0]], y[valid, shown[1]], ".", ms=3, color="0.5", label=f"{ch} measurements")
    tr = res.data.get("truth", Group())
    if "state" in tr.data:
        tn = [str(x) for x in tr.attrs["names"]]
        ts = np.asarray(tr.data["state"])[i]
        st = [_state_of(tn, pairs[k][0]) for k in shown]
        if None not in st:
            axs[0].plot(ts[:, st[0]] * scale, ts[:, st[1]] * scale, "k--", lw=0.8, label="truth", gid="truth")
    for model, g in res.data["fit"].data.items():
        gn = [str(x) for x in g.attrs["names"]]
        idx = [_state_of(gn, s) for s, _ in pairs]
        if None in idx:
            continue
        z = np.asarray(g.data["state"])[i][:, idx] * scale
        status = str(np.asarray(g.data["status"]).astype(str)[i])
        sty = observer_style(model, n=len(z))
        plain = {k: v for k, v in sty.items() if k not in ("marker", "markevery", "ms")}
        axs[0].plot(z[:, shown[0]], z[:, shown[1]], lw=1.2, label=f"{model} EM ({status})", **sty)
        ticks = np.asarray(g.data["ticks"])
        at = np.clip(np.searchsorted(ticks, np.asarray(mg.data["index"])), 0, len(ticks) - 1)
        d = np.linalg.norm(z[at] - y, axis=-1)
        d = np.where(valid, d, np.nan)
        run = np.sqrt(np.nancumsum(d**2) / np.maximum(np.cumsum(valid), 1))
        axs[1].plot(t_meas, d, lw=0.5, alpha=0.5, **plain)
        axs[1].plot(t_meas, run, lw=1.5, label=f"{model}: running RMS {run[-1]:.3f} mm", **sty)
    axs[0].set_xlabel(f"{pairs[shown[0]][1]} [mm]")
    axs[0].set_ylabel(f"{pairs[shown[1]][1]} [mm]")
    axs[0].set_aspect("equal", adjustable="datalim")
    beside_legend(axs[0])
    axs[1].set_xlabel("time [s]")
    axs[1].set_ylabel("distance from the measurement [mm]")
    beside_legend(axs[1])
    for ax in axs:
        ax.grid(alpha=0.3)
    labels = [str(x) for x in np.atleast_1d(res.data["inputs"].attrs.get("case_labels", []))]
    case = res.data["inputs"].data.get("case")
    pcase, plabels = _cases(res)
    what = (labels[int(case[i])] + ", " if labels and case is not None else "") + plabels[int(pcase[i])]
    from needlecli.reports.design import trial_ids

    fig.suptitle(f"{res.attrs.get('name', '')}: trial {trial_ids(res)[i]} ({what}): EM estimates of each model", fontsize=10)
    return save_figure(fig, Path(f"{path_stem}_fit_paths.png"))


def _state_of(names: list[str], stem: str) -> int | None:
    """Index of a position state by its axis (``x`` is ``px`` of the magnetic models, ``x`` of the unicycle)."""
    for s in (f"p{stem}", stem):
        if s in names:
            return names.index(s)
    return None


def _position_pairs(res: Group, channels: list[str]) -> list[tuple[str, str]]:
    """``(axis, channel)`` of every measured position axis that every fitted model has as a state."""
    out = []
    for a in ("x", "y", "z"):
        if a in channels and all(_state_of([str(x) for x in g.attrs["names"]], a) is not None
                                 for g in res.data["fit"].data.values()):
            out.append((a, a))
    return out


def _two_widest(y: np.ndarray, valid: np.ndarray) -> tuple[int, int]:
    """The two columns of ``y`` with the largest range over the valid samples, in their order."""
    if y.shape[1] <= 2:
        return (0, min(1, y.shape[1] - 1))
    span = np.ptp(np.where(valid[:, None], y, np.nan)[valid], axis=0) if valid.any() else np.zeros(y.shape[1])
    return tuple(sorted(np.argsort(-span)[:2].tolist()))


def _cos_hb(z: np.ndarray, names: list[str]) -> np.ndarray:
    h = z[..., [names.index(s) for s in ("hx", "hy", "hz")]]
    b = z[..., [names.index(s) for s in ("Bx", "By", "Bz")]]
    with np.errstate(all="ignore"):
        return (h * b).sum(-1) / (np.linalg.norm(h, axis=-1) * np.linalg.norm(b, axis=-1))


@PLOTS.register("binm_singularity")
def fig10(res: Group, errors, path_stem: Path) -> Path | None:
    """The magnetic needle EM paper's Fig. 10: h . B (cosine of the angle between heading and field) against time for one trial
    (the first whose BiNM fit became singular, else the one coming closest to h . B = 0): the MNM's EM
    estimate, the BiNM's first EKF pass and its EM estimate (until it failed), the truth."""
    if not is_fit(res) or not {"mnm", "binm"} <= set(res.data["fit"].data):
        return None
    fits = res.data["fit"].data
    bst = np.asarray(fits["binm"].data["status"]).astype(str)
    sing = np.nonzero(bst == "singular")[0]
    mn = [str(x) for x in fits["mnm"].attrs["names"]]
    if not all(s in mn for s in ("hx", "Bx")):
        return None
    zm = np.asarray(fits["mnm"].data["state"])
    closest = np.nanmin(np.abs(_cos_hb(zm, mn)), 1)
    i = int(sing[0]) if sing.size else int(np.nanargmin(closest))
    time = np.asarray(res.data["time"])
    fig, ax = subplots(figsize=(9.5, 4.2))
    tr = res.data.get("truth", Group())
    if "state" in tr.data:
        tn = [str(x) for x in tr.attrs["names"]]
        ax.plot(time, _cos_hb(np.asarray(tr.data["state"])[i], tn), "k--", lw=0.8, label="truth (MNM)", gid="truth")
    for model, key, style in (("mnm", "state", "-"), ("binm", "ekf_state", ":"), ("binm", "state", "-")):
        g = fits[model]
        names = [str(x) for x in g.attrs["names"]]
        ticks = np.asarray(g.data["ticks"])
        z = np.asarray(g.data[key])[i]
        lbl = {"state": "EM estimate", "ekf_state": "EKF forward pass"}[key]
        st = str(np.asarray(g.data["status"]).astype(str)[i])
        ax.plot(time[ticks], _cos_hb(z, names), lw=1.3, label=f"{model} {lbl}" + (f" ({st})" if key == "state" else ""),
                **observer_style(model, ls=style, n=len(ticks)))
    ax.axhline(0.0, color="r", lw=0.8, label="BiNM singularity (h . B = 0)")
    ax.set_xlabel("time [s]")
    ax.set_ylabel("h . B / (|h| |B|) [-]")
    ax.grid(alpha=0.3)
    beside_legend(ax)
    if sing.size:
        what = f"the BiNM fit reached the singularity ({str(fits['binm'].data['reason'][i])})"
    else:
        what = f"no trial reached the singularity; the closest, min |h . B| = {float(closest[i]):.2f} of the MNM estimate"
    ax.set_title(f"{res.attrs.get('name', '')}: trial {i}, heading against field: {what}", fontsize=9, wrap=True)
    return save_figure(fig, Path(f"{path_stem}_binm_singularity.png"))


# ---------------------------------------------------------------------------------------------- evaluate
def evaluate_fit(
    path: str | Path,
    *,
    tables: list[str] | None = None,
    out_dir: str | Path | None = None,
    formats: list[str] | None = None,
    plots: bool = False,
    design: dict | None = None,
) -> dict[str, pd.DataFrame]:
    """``needle evaluate FIT.h5``: the fit tables (default :data:`FIT_TABLES`; any of :data:`ALL_FIT_TABLES`), written to
    ``out_dir`` with the figures when asked; ``design`` (``group_by``, ``regress``) for the tables by the
    trials' design factors (``needle evaluate --group-by/--regress``)."""
    from needlecli.io.atomic import output_stem
    from needlecli.io.fit import read_fit

    path = Path(path)
    res = read_fit(path)
    names = [TABLES.canonical(n) for n in tables] if tables else default_fit_tables(res)
    for n in names:
        if n not in ALL_FIT_TABLES:
            raise DataError(f"{path}: table {n!r} needs a results file; a fit file has {', '.join(ALL_FIT_TABLES)}")
    from needlecli.reports.design import DESIGN_OPTIONS

    def opts(n):
        key = DESIGN_OPTIONS.get(n)
        return {key: design[key]} if key and design and design.get(key) else {}

    out = {n: TABLES.get(n)(res, None, **opts(n)) for n in names}
    for n, df in out.items():
        df.attrs["caption"] = table_caption(n, df, res)
    if out_dir is not None:
        out_dir = Path(out_dir)
        stem = output_stem(res.attrs.get("name"), path.stem)
        for n, df in out.items():
            write_table(df, out_dir / f"{stem}_{n}", formats or ["md", "csv", "tex"], caption=df.attrs["caption"])
        if plots:
            draw_plots(res, None, out_dir / stem, FIT_PLOTS,
                       options={"fit_regression": {"regress": design["regress"]}} if design and design.get("regress") else None)
    return out


def default_fit_tables(res: Group) -> list[str]:
    """The tables ``needle evaluate`` writes for a fit file by default: :data:`FIT_TABLES`, the magnetic needle EM paper's paper
    tables only where the fit has their models (:data:`PAPER_TABLE_MODELS`)."""
    fitted = set(res.data["fit"].data) if is_fit(res) else set()
    return [n for n in FIT_TABLES if set(PAPER_TABLE_MODELS.get(n, ())) <= fitted]
