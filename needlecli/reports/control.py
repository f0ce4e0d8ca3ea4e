"""Reports of closed loops (config section ``control:``): how planar the insertions stayed (table
``planar_control``). It reads the truth, so it tabulates open-loop results files too (the runs' own drift,
without commands): run the same config with and without ``control:`` and compare."""

from __future__ import annotations

import numpy as np
import pandas as pd

from needlecli.io.results import Group
from needlecli.metrics import ErrorSet
from needlecli.reports.tables import TABLES

_LENGTH_TO_MM = {"mm": 1.0, "m": 1000.0, "cm": 10.0}
_COLUMNS = ["Control", "Run", "Status", "Mean |dz| [mm]", "Std |dz| [mm]", "Max |dz| [mm]", "Final |dz| [mm]",
            "Mean |B_z| [mT]", "Saturated [%]", "Frames held [%]"]


def _stats(dz: np.ndarray) -> dict:
    a = np.abs(dz[np.isfinite(dz)])
    if not a.size:
        return {"Mean |dz| [mm]": np.nan, "Std |dz| [mm]": np.nan, "Max |dz| [mm]": np.nan}
    return {"Mean |dz| [mm]": float(a.mean()), "Std |dz| [mm]": float(a.std()), "Max |dz| [mm]": float(a.max())}


def _command_stats(cmd: np.ndarray | None, limit: float, held: np.ndarray | None) -> dict:
    """``cmd`` the applied B_z (NaN outside the runs), ``held`` the samples without a detection."""
    if cmd is None:
        return {"Mean |B_z| [mT]": np.nan, "Saturated [%]": np.nan, "Frames held [%]": np.nan}
    c = np.abs(cmd[np.isfinite(cmd)])
    return {"Mean |B_z| [mT]": float(c.mean()) if c.size else np.nan,
            "Saturated [%]": 100.0 * float(np.mean(c >= limit * (1 - 1e-12))) if c.size else np.nan,
            "Frames held [%]": 100.0 * float(held.mean()) if held.size else np.nan}


@TABLES.register("planar_control")
def planar_control_table(res: Group, errors: dict[str, ErrorSet]) -> pd.DataFrame:
    """Out-of-plane deviation of the true tip from its starting height, |dz| = |pz - pz0| in mm, over each
    run's insertion (the magnetic needle EM paper's sec. 2.3.6: within 3 mm under control): Mean, Std, Max, at the end; with a
    controller, the mean |B_z| it applied (mT), the share of time it was saturated and the share of its
    sensor's frames without a detection (command held). First row per controller: all runs whose truth
    is ok, pooled; then one row per run."""
    truth = res.data["truth"]
    names = list(truth.attrs["names"])
    if "pz" not in names:
        return pd.DataFrame(columns=_COLUMNS)
    scale = _LENGTH_TO_MM.get(str(res.attrs.get("length_unit", "mm")), 1.0)
    time = np.asarray(res.data["time"], dtype=float)
    z = truth.data["state"][..., names.index("pz")] * scale  # (N, T)
    N = z.shape[0]
    end = np.asarray(truth.data.get("end_time", np.full(N, time[-1])), dtype=float)
    event = np.asarray(truth.data.get("event_time", np.full(N, np.nan)), dtype=float)
    stop = np.where(np.isfinite(event), event, end)
    inside = time[None, :] <= stop[:, None] + 1e-12  # (N, T): the run's own insertion (a prefix)
    dz = np.where(inside, z - z[:, :1], np.nan)
    final = np.abs(dz[np.arange(N), np.maximum(inside.sum(1) - 1, 0)])
    status = np.asarray(truth.data["status"]).astype(str)
    ok = status == "ok"
    controls = [(name, g) for name, g in res.data.get("control", Group()).data.items() if isinstance(g, Group)]
    rows = []
    for name, g in controls or [("none (open loop)", None)]:
        cmd = held = None
        limit = np.inf
        if g is not None:
            cmd = np.where(inside, np.asarray(g.data["command"], dtype=float), np.nan)
            limit = float(g.attrs.get("limit", np.inf))
            held = ~np.isfinite(np.asarray(g.data["sample_command"], dtype=float))  # (N, M)
        rows.append({"Control": name, "Run": f"all ok ({int(ok.sum())}/{N})", "Status": "ok", **_stats(dz[ok]),
                     "Final |dz| [mm]": float(final[ok].mean()) if ok.any() else np.nan,
                     **_command_stats(None if cmd is None else cmd[ok], limit, None if held is None else held[ok])})
        for i in range(N):  # one row each
            rows.append({"Control": name, "Run": str(i), "Status": status[i], **_stats(dz[i]),
                         "Final |dz| [mm]": float(final[i]),
                         **_command_stats(None if cmd is None else cmd[i], limit, None if held is None else held[i])})
    return pd.DataFrame(rows, columns=_COLUMNS)
