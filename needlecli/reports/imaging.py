"""Reports of the imaging sensors (``pipeline: image``): a kept frame per sensor with the detected and the
true tip drawn on it (plot ``imaging_frames``), and the raw measurement error of every position sensor
beside each other, image and Gaussian pipelines alike (table ``measurements``)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

from needlecli.io.results import Group
from needlecli.metrics import ErrorSet
from needlecli.reports.plots import PLOTS, save_figure, subplots
from needlecli.reports.tables import TABLES, count_cell

_LENGTH_TO_MM = {"mm": 1.0, "m": 1000.0, "cm": 10.0}


def _pick_frame(g: Group) -> int:
    """The kept frame to show: the last one of the first run with a detection, else the last one."""
    tip = g.data["frame_tip"]
    ok = np.all(np.isfinite(tip), -1)
    runs = g.data["frame_run"]
    if ok.any():
        first_run = runs[ok].min()
        return int(np.nonzero(ok & (runs == first_run))[0][-1])
    return len(runs) - 1


@PLOTS.register("imaging_frames")
def imaging_frames(res: Group, errors: dict[str, ErrorSet], path_stem: Path) -> Path | None:
    """One kept frame per imaging sensor; volumes as two maximum-intensity projections. Red +: the
    detected tip; green x: the true tip (for the 2D ultrasound, the shaft's cross-section in the plane)."""
    sensors = [(name, g) for name, g in res.data.get("measurements", Group()).data.items()
               if isinstance(g, Group) and "frames" in g.data and len(g.data["frames"])]
    if not sensors:
        return None
    panels = sum(2 if g.data["frames"].ndim == 4 else 1 for _, g in sensors)
    fig, axes = subplots(1, panels, figsize=(4.2 * panels, 4.4), squeeze=False)
    k = 0
    for name, g in sensors:
        i = _pick_frame(g)
        img = g.data["frames"][i]
        tip, truth = g.data["frame_tip"][i], g.data["frame_truth"][i]
        run, sample = int(g.data["frame_run"][i]), int(g.data["frame_sample"][i])
        t = g.data["t"][sample] if "t" in g.data else np.nan
        if img.ndim == 3:  # a volume (x, y, z): project along x and along y
            for drop in (0, 1):
                ax = axes[0, k]
                ax.imshow(img.max(axis=drop), cmap="gray", origin="lower", vmin=0, vmax=255)
                labels = "xyz"
                keep = [j for j in range(3) if j != drop]
                ax.plot(truth[keep[1]], truth[keep[0]], "x", color="lime", ms=9, mew=2, label="truth")
                if np.all(np.isfinite(tip)):
                    ax.plot(tip[keep[1]], tip[keep[0]], "+", color="red", ms=11, mew=2, label="detected")
                ax.set_xlabel(f"{labels[keep[1]]} [voxel]")
                ax.set_ylabel(f"{labels[keep[0]]} [voxel]")
                ax.set_title(f"{name}: max. projection along {labels[drop]}\nrun {run}, t = {t:.1f} s", fontsize=9)
                k += 1
        else:
            ax = axes[0, k]
            ax.imshow(img, cmap="gray", vmin=0, vmax=255)
            ax.plot(truth[0], truth[1], "x", color="lime", ms=9, mew=2, label="truth")
            if np.all(np.isfinite(tip)):
                ax.plot(tip[0], tip[1], "+", color="red", ms=11, mew=2, label="detected")
            ax.set_xlabel("column [px]")
            ax.set_ylabel("row [px]")
            ax.set_title(f"{name} ({g.attrs.get('pipeline', '')}): run {run}, t = {t:.1f} s", fontsize=9)
            k += 1
    axes[0, 0].legend(loc="upper right", fontsize="small")
    fig.suptitle(f"{res.attrs.get('name', '')}: imaging frames with the detected tip", fontsize=10)
    return save_figure(fig, Path(f"{path_stem}_imaging_frames.png"))


@TABLES.register("measurements")
def measurement_table(res: Group, errors: dict[str, ErrorSet]) -> pd.DataFrame:
    """Raw error of every position sensor's measurements against the true tip (mm), per axis: Mean
    (bias), Std, Max |error|, and the share of samples that are valid; image and Gaussian pipelines alike."""
    truth = res.data["truth"]
    names = list(truth.attrs["names"])
    state = truth.data["state"]
    scale = _LENGTH_TO_MM.get(str(res.attrs.get("length_unit", "mm")), 1.0)
    status = truth.data.get("status")
    keep = np.ones(state.shape[0], dtype=bool) if status is None else np.asarray(status) == "ok"
    rows = []
    for name, g in res.data.get("measurements", Group()).data.items():
        if not isinstance(g, Group) or g.attrs.get("type") != "position":
            continue
        idx = g.data["index"]
        value = g.data["value"][keep]
        valid = g.data["valid"][keep]
        for j, ch in enumerate(g.attrs["names"]):
            col = next((names.index(c) for c in (ch, f"p{ch}") if c in names), None)
            if col is None:
                continue
            err = (value[..., j] - state[keep][:, idx, col]) * scale
            e = err[valid]
            rows.append({"Sensor": name, "Pipeline": g.attrs.get("pipeline", ""), "Axis": ch,
                         "Mean [mm]": float(e.mean()) if e.size else np.nan,
                         "Std [mm]": float(e.std()) if e.size else np.nan,
                         "Max [mm]": float(np.abs(e).max()) if e.size else np.nan,
                         "Valid [%]": 100.0 * valid.mean() if valid.size else np.nan,
                         "Runs": count_cell(keep.sum(), len(keep))})
    return pd.DataFrame(rows, columns=["Sensor", "Pipeline", "Axis", "Mean [mm]", "Std [mm]", "Max [mm]",
                                       "Valid [%]", "Runs"])
