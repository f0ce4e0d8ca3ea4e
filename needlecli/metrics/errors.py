"""Estimation errors per observer and quantity, computed from a results file only.

Quantities, each present when both the truth and the estimate carry it (matched by state names):

``E_xyz``    tip position error norm, mm (metres of the magnetic models converted here, at the edge)
``E_x``, ``E_y``, ``E_z``  absolute error of each position axis, mm (an axis no sensor observes shows
             here: a 2D probe's z); for every axis both the truth and the estimate have
``E_lat``, ``E_ax``  the position error across and along the true needle axis, mm, where the results
             file's model has a tangent: with ``e = p_est - p_true`` and the truth's unit tangent ``t``,
             ``E_ax = |e . t|`` (axial: where along the needle) and ``E_lat = |e - (e . t) t|`` (lateral)
``E_<a>``    absolute wrapped error of each angle state (alpha, beta, gamma), deg
``E_R``      angle of the rotation error ``R_true^T R_est``, deg, for estimates with a full orientation
``E_h``, ``E_B``  angle between true and estimated unit vectors (magnetic models), deg
``E_<s>``    absolute error of any other common scalar state (e.g. kappa, 1/mm), in its unit; a truth
             parameter (e.g. kappa of the plain unicycle, which follows the tissue layers) counts as truth
Runs whose truth or estimate is not ``ok`` are excluded and counted.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import pandas as pd

from needlecli.io.results import Group
from needlecli.kernels import twin
from needlecli.numerics import angle_diff, euler_xyz_to_matrix, rotation_angle

_LENGTH_TO_MM = {"mm": 1.0, "m": 1000.0, "cm": 10.0}
_R = tuple(f"R{i}{j}" for i in range(1, 4) for j in range(1, 4))
_POSITIONS = (("x", "y", "z"), ("px", "py", "pz"))
#: the per-axis position errors (named by axis whatever the model calls its position states)
AXIS_QUANTITIES = ("E_x", "E_y", "E_z")
#: the position error across and along the true needle axis
NEEDLE_QUANTITIES = ("E_lat", "E_ax")


def _strs(v) -> list[str]:
    return [x.decode() if isinstance(x, bytes) else str(x) for x in np.atleast_1d(v)]


def reference_tangent(res: Group) -> np.ndarray | None:
    """Unit tangents ``(N, T, 3)`` of the truth's (or a replay's reference's) states, NaN where there is
    none, from the ``tangent`` of the results file's model; None when that model has no tangent or the
    truth does not hold its states."""
    from needlecli.models import MODELS

    name = str(res.attrs.get("model", ""))
    if name not in MODELS:
        return None
    cls = MODELS.get(name)
    names = _strs(res.data["truth"].attrs.get("names", cls.state_names))
    if not cls.provides("tangent") or tuple(names) != tuple(cls.state_names):
        return None
    with np.errstate(all="ignore"):
        t = cls().tangent(np.asarray(res.data["truth"].data["state"], dtype=float))
        return t / np.linalg.norm(t, axis=-1, keepdims=True)


def split(err: np.ndarray, tangent: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(along (...), across (...))`` of position errors ``(..., 3)`` against unit tangents ``(..., 3)``:
    ``along = e . t`` (signed), ``across = |e - along t|``."""
    along = np.einsum("...i,...i->...", err, tangent)
    across = np.linalg.norm(err - along[..., None] * tangent, axis=-1)
    return along, across


@dataclass
class QuantityError:
    """Errors ``(N_kept, T)`` of one quantity, with its unit and the kept runs."""

    name: str
    unit: str
    values: np.ndarray
    runs: np.ndarray


@dataclass
class ErrorSet:
    observer: str
    quantities: dict[str, QuantityError] = field(default_factory=dict)
    n_runs: int = 0
    excluded: dict[str, int] = field(default_factory=dict)  # reason -> count
    not_estimated: list[str] = field(default_factory=list)
    not_computable: dict[str, str] = field(default_factory=dict)  # quantity -> why (e.g. no ground truth)

    def tidy(self, time: np.ndarray, every: int = 1) -> pd.DataFrame:
        """Tidy records ``(observer, run, quantity, unit, t, value)``, every k-th time step."""
        frames = []
        for q in self.quantities.values():
            v = q.values[:, ::every]
            tt = np.broadcast_to(time[::every], v.shape)
            rr = np.broadcast_to(q.runs[:, None], v.shape)
            frames.append(
                pd.DataFrame({"observer": self.observer, "run": rr.ravel(), "quantity": q.name,
                              "unit": q.unit, "t": tt.ravel(), "value": v.ravel()})
            )
        return pd.concat(frames, ignore_index=True) if frames else pd.DataFrame()


def depth_axis(res: Group) -> np.ndarray:
    """The inserted depth ``(T,)`` of a results file; for replayed trials, whose depths differ (``(N, T)``),
    their mean."""
    depth = np.asarray(res.data["depth"], dtype=float)
    return np.nanmean(depth, 0) if depth.ndim == 2 else depth


def _rotation(names: list[str], state: np.ndarray) -> np.ndarray | None:
    if all(a in names for a in ("alpha", "beta", "gamma")):
        i = [names.index(a) for a in ("alpha", "beta", "gamma")]
        return euler_xyz_to_matrix(state[..., i[0]], state[..., i[1]], state[..., i[2]])
    if all(r in names for r in _R):
        i = [names.index(r) for r in _R]
        return state[..., i].reshape(*state.shape[:-1], 3, 3)
    return None


def recorded_kernels(res: Group) -> str:
    """The kernels setting a results file was made with: ``simulation.kernels`` of the config it records
    (``auto``, the default, where it records no config or the config names none)."""
    text = str(res.attrs.get("config", "") or "")
    if not text.strip():
        return "auto"
    from needlecli.io.yamlfile import parse_yaml

    sim = parse_yaml(text, "the results file's config").get("simulation")
    return str(sim.get("kernels", "auto")) if isinstance(sim, dict) else "auto"


def _compiled_errors(state_errors, t_names, e_names, t_angles, e_angles, pos_t, scale, t_state, est,
                     keep) -> dict[str, np.ndarray]:
    """The position norm and the per-state errors that :func:`compute_errors` computes from states (not
    from truth parameters), by ``state_errors`` (the compiled twin, :func:`needlecli.kernels.metrics.state_errors`)
    in one pass: the same numbers, without the column copies and temporaries."""
    from needlecli.kernels.metrics import ABS, ANGLE, NORM

    plan: list[tuple[str, tuple]] = []
    if pos_t and all(a in e_names for a in pos_t):
        plan.append(("E_xyz", (NORM, [t_names.index(a) for a in pos_t], [e_names.index(a) for a in pos_t], scale)))
    skip = set(pos_t or ()) | set(_R)
    for k in e_names:
        if k in skip or k not in t_names or (k in ("hx", "hy", "hz", "Bx", "By", "Bz")):
            continue
        kind = ANGLE if (k in e_angles or k in t_angles) else ABS
        plan.append((f"E_{k}", (kind, [t_names.index(k)], [e_names.index(k)], 1.0)))
    if not plan or np.asarray(t_state).ndim != 3:
        return {}
    out = state_errors(np.asarray(t_state), np.asarray(est), keep, [q for _, q in plan])
    return {name: out[i] for i, (name, _) in enumerate(plan)}


def compute_errors(res: Group, *, kernels: str | None = None) -> dict[str, ErrorSet]:
    """Errors of every observer in a results file against its truth.

    ``kernels``: the kernels setting (``auto``, ``numba``, ``numpy``; :func:`needlecli.kernels.resolve`) of
    the compiled twins ``state_errors`` and ``rotation_error``; default: the one the results file's config
    records (:func:`recorded_kernels`), so that ``needle evaluate`` computes as the run did.
    """
    setting = recorded_kernels(res) if kernels is None else kernels
    state_errors = twin("state_errors", setting)  # the errors straight from the state arrays, or None: numpy
    rotation_error = twin("rotation_error", setting)  # (needlecli.kernels.metrics)
    truth = res.data["truth"]
    t_names = list(truth.attrs["names"])
    t_units = list(truth.attrs["units"])
    t_state = truth.data["state"]
    t_angles = set(truth.attrs.get("angles", []))
    params = truth.data.get("params", Group()).data
    scale = _LENGTH_TO_MM.get(str(res.attrs.get("length_unit", "mm")), 1.0)
    tangent = reference_tangent(res)  # (N, T, 3) or None: no needle axis
    out: dict[str, ErrorSet] = {}
    for name, grp in res.data.get("estimates", Group()).data.items():
        e_names = list(grp.attrs["names"])
        e_units = list(grp.attrs.get("units", [""] * len(e_names)))
        e_angles = set(grp.attrs.get("angles", []))
        est = grp.data["state"]
        n_runs = est.shape[0]
        t_ok = truth.data["status"] == "ok"
        e_ok = grp.data["status"] == "ok"
        keep = np.nonzero(t_ok & e_ok)[0]
        es = ErrorSet(observer=name, n_runs=n_runs)
        if (~t_ok).any():
            for st in np.unique(truth.data["status"][~t_ok]):
                es.excluded[f"truth {st}"] = int((truth.data["status"] == st).sum())
        if (t_ok & ~e_ok).any():
            for st in np.unique(grp.data["status"][t_ok & ~e_ok]):
                es.excluded[f"estimate {st}"] = int(((grp.data["status"] == st) & t_ok).sum())
        ts, xs = (t_state, est) if keep.size == n_runs else (t_state[keep], est[keep])  # no copy when all are kept
        pos_t = next((ax for ax in _POSITIONS if all(a in t_names for a in ax)), None)
        pre = ({} if state_errors is None else
               _compiled_errors(state_errors, t_names, e_names, t_angles, e_angles, pos_t, scale, t_state, est, keep))

        def col(names, arr, k):
            return arr[..., names.index(k)]

        used: set[str] = set()
        if pos_t and all(a in e_names for a in pos_t):
            d = np.stack([col(e_names, xs, a) - col(t_names, ts, a) for a in pos_t], -1)  # (N_kept, T, 3)
            err = pre["E_xyz"] if "E_xyz" in pre else scale * np.linalg.norm(d, axis=-1)
            es.quantities["E_xyz"] = QuantityError("E_xyz", "mm", err, keep)
            if tangent is not None:
                along, across = split(d, tangent if keep.size == n_runs else tangent[keep])
                es.quantities["E_lat"] = QuantityError("E_lat", "mm", scale * across, keep)
                es.quantities["E_ax"] = QuantityError("E_ax", "mm", scale * np.abs(along), keep)
            used.update(pos_t)
        for a in pos_t or ():  # per axis, also where the estimate has some of the axes only (the high-gain observer paper's x)
            if a in e_names:
                es.quantities[f"E_{a[-1]}"] = QuantityError(
                    f"E_{a[-1]}", "mm", scale * np.abs(col(e_names, xs, a) - col(t_names, ts, a)), keep)
                used.add(a)
        euler = ("alpha", "beta", "gamma")
        if all(a in t_names for a in euler) and all(a in e_names for a in euler) and rotation_error is not None:
            err = rotation_error(t_state, est, keep, [t_names.index(a) for a in euler],  # without the (N, T, 3, 3)
                                 [e_names.index(a) for a in euler])  # matrices
            es.quantities["E_R"] = QuantityError("E_R", "deg", np.rad2deg(err, out=err), keep)
            used.update(_R)
        elif (r_t := _rotation(t_names, ts)) is not None and (r_e := _rotation(e_names, xs)) is not None:
            err = rotation_angle(np.swapaxes(r_t, -1, -2) @ r_e)
            es.quantities["E_R"] = QuantityError("E_R", "deg", np.rad2deg(err), keep)
            used.update(_R)
        for vec, cols in (("h", ("hx", "hy", "hz")), ("B", ("Bx", "By", "Bz"))):
            if all(c in t_names for c in cols) and all(c in e_names for c in cols):
                a = np.stack([col(t_names, ts, c) for c in cols], -1)
                b = np.stack([col(e_names, xs, c) for c in cols], -1)
                cos = np.sum(a * b, -1) / (np.linalg.norm(a, axis=-1) * np.linalg.norm(b, axis=-1))
                es.quantities[f"E_{vec}"] = QuantityError(
                    f"E_{vec}", "deg", np.rad2deg(np.arccos(np.clip(cos, -1, 1))), keep
                )
                used.update(cols)
        for k in e_names:
            if k in used:
                continue
            if k in t_names:
                tv, unit = col(t_names, ts, k), t_units[t_names.index(k)]
            elif k in params:
                tv, unit = params[k][keep], e_units[e_names.index(k)]
            else:
                continue
            if f"E_{k}" in pre:
                unit = "deg" if (k in e_angles or k in t_angles) else unit
                es.quantities[f"E_{k}"] = QuantityError(f"E_{k}", unit, pre[f"E_{k}"], keep)
            elif k in e_angles or k in t_angles:
                err = np.rad2deg(np.abs(angle_diff(col(e_names, xs, k), tv)))
                es.quantities[f"E_{k}"] = QuantityError(f"E_{k}", "deg", err, keep)
            else:
                es.quantities[f"E_{k}"] = QuantityError(f"E_{k}", unit, np.abs(col(e_names, xs, k) - tv), keep)
        es.not_estimated = [k for k in t_names if k not in e_names and k not in used]
        kind = str(res.attrs.get("truth_kind", "simulation"))
        for q in list(es.quantities):
            if not np.isfinite(es.quantities[q].values).any():
                if kind == "none":
                    es.not_computable[q] = "the logs have no ground truth"
                elif keep.size == 0:
                    why = ", ".join(f"{k}: {v}" for k, v in es.excluded.items())
                    es.not_computable[q] = f"no run kept ({why})"
                elif kind in ("simulation", "ground truth", "manual segmentation"):
                    es.not_computable[q] = "no truth sample where it was estimated"
                else:
                    es.not_computable[q] = f"not given by the reference, a {kind}"
                del es.quantities[q]
        out[name] = es
    return out
