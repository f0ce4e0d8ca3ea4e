"""Measuring an image pipeline's error the way the multi-rate UKF paper characterised its segmentation: repeated
measurements of the same pose (the multi-rate UKF paper: 20), their bias and standard deviation per axis, and how often a
frame gives no measurement (lost) or a measurement far from the truth (outlier), against the quantities
the device's quality depends on (distance from the transducer and needle angle; depth in the agar and
heading; depth below the probe and tilt).

The result sets the Gaussian sensors' ``sigma`` from the image pipeline: :func:`fit_growth` fits the multi-rate UKF paper's
``sigma = (1 + a d / d_max) sigma_c`` to the 3D ultrasound's standard deviations.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import pandas as pd

from needlecli.errors import ConfigError, did_you_mean
from needlecli.sensors.imaging.base import DEVICES, Device, Pose
from needlecli.sensors.imaging.render import NeedleGeometry

if TYPE_CHECKING:  # the config is the experiments layer's; only its type is named here
    from needlecli.experiments.config.types import ExperimentConfig

_AXES = ("x", "y", "z")


@dataclass
class Characterization:
    """The error table of one sensor and what it suggests for its Gaussian twin.

    table : one row per pose group: the group's labels, ``N`` frames, ``Lost [%]``, ``Outliers [%]``,
        ``Bias <a> [mm]`` and ``Std <a> [mm]`` per measured axis (over the frames that are not outliers),
        ``RMS [mm]`` (error norm, same frames)
    suggestion : Gaussian settings that reproduce the pipeline's spread (``sigma``, and ``growth`` for the
        3D ultrasound), in the model's length unit, or empty
    """

    sensor: str
    device: str
    table: pd.DataFrame
    suggestion: dict


def characterize_device(
    device: Device,
    *,
    repeats: int = 20,
    seed: int = 0,
    outlier: float | None = None,
    mode: str = "tracking",
    poses: list[Pose] | None = None,
    axes: tuple[str, ...] | None = None,
    chunk: int = 256,
    progress=None,
) -> pd.DataFrame:
    """Measure ``repeats`` independent frames of every pose (default: the device's own grid), each repeat
    moved by a random offset within one pixel (voxel) so that the spread includes the quantisation.

    Parameters
    ----------
    outlier : error norm (mm) above which a detection counts as an outlier (default: 5 pixels / voxels)
    mode : ``tracking`` or ``search`` (how the 3D ultrasound places its region; see ``measure_once``)
    axes : axes to report (default: the device's)
    progress : ``progress(frames done, frames)`` after each chunk of frames, if given
    """
    poses = poses if poses is not None else device.poses()
    axes = axes or device.axes
    cols = [_AXES.index(a) for a in axes]
    outlier = outlier if outlier is not None else 5.0 * device.pixel
    rng = np.random.default_rng(seed)
    tips = np.repeat(np.array([p.tip for p in poses], dtype=float), repeats, axis=0)
    # each repeat at a random offset within one pixel (voxel): the spread includes the lattice's quantisation
    tips += rng.uniform(-0.5, 0.5, tips.shape) * device.pixel
    dirs = np.repeat(np.array([p.direction for p in poses], dtype=float), repeats, axis=0)
    lengths = np.repeat(np.array([p.length for p in poses], dtype=float), repeats)
    found = np.full((len(tips), 3), np.nan)
    valid = np.zeros(len(tips), dtype=bool)
    for lo in range(0, len(tips), chunk):
        sl = slice(lo, lo + chunk)
        g = NeedleGeometry.straight(tips[sl], dirs[sl], float(lengths[sl].max()), 0.5 if device.pixel < 1 else 1.0)
        res = device.measure_once(g, rng, mode)
        found[sl] = res.tip[:, 0]
        valid[sl] = res.valid[:, 0]
        if progress is not None:
            progress(min(lo + chunk, len(tips)), len(tips))
    err = (found - tips)[:, cols]
    norm = np.linalg.norm(err, axis=1)
    rows = []
    labels = [p.labels for p in poses]
    keys = list(dict.fromkeys(tuple(sorted(lab.items())) for lab in labels))
    group = np.repeat([keys.index(tuple(sorted(lab.items()))) for lab in labels], repeats)
    for k, key in enumerate(keys):
        sel = group == k
        n = int(sel.sum())
        det = sel & valid
        out = det & (norm > outlier)
        good = det & ~out
        row = dict(key)
        row.update({"N": n, "Lost [%]": 100.0 * (n - det.sum()) / n,
                    "Outliers [%]": 100.0 * out.sum() / max(det.sum(), 1)})
        for i, a in enumerate(axes):
            row[f"Bias {a} [mm]"] = float(np.mean(err[good, i])) if good.any() else np.nan
        for i, a in enumerate(axes):
            row[f"Std {a} [mm]"] = float(np.std(err[good, i])) if good.sum() > 1 else np.nan
        row["RMS [mm]"] = float(np.sqrt(np.mean(norm[good] ** 2))) if good.any() else np.nan
        rows.append(row)
    first = list(labels[0])
    df = pd.DataFrame(rows)
    return df[first + [c for c in df.columns if c not in first]]


def fit_growth(table: pd.DataFrame, d_max: float) -> tuple[float, float]:
    """Fit ``sigma = (1 + a d / d_max) sigma_c`` (the multi-rate UKF paper) to the mean per-axis standard deviation against
    ``Distance [mm]`` at the best needle angle; returns ``(sigma_c, a)`` (``a >= 0``)."""
    best = table["Angle [deg]"].max()
    t = table[(table["Angle [deg]"] == best)].dropna()
    std_cols = [c for c in t.columns if c.startswith("Std ")]
    d = t["Distance [mm]"].to_numpy(float)
    sd = t[std_cols].to_numpy(float).mean(1)
    if len(d) < 2:
        return (float(sd.mean()) if len(sd) else float("nan")), 0.0
    A = np.column_stack([np.ones_like(d), d / d_max])
    (c0, c1), *_ = np.linalg.lstsq(A, sd, rcond=None)
    if c0 <= 0:
        return float(sd.mean()), 0.0
    return float(c0), float(max(c1 / c0, 0.0))


def characterize_sensors(
    cfg: ExperimentConfig, *, sensor: str | None = None, repeats: int = 20, seed: int = 0, outlier: float | None = None,
    mode: str = "tracking", source: str = "<config>", progress=None,
) -> list[Characterization]:
    """Characterise every sensor of an experiment config that uses ``pipeline: image`` (or the one named);
    ``progress(phase, done, total)`` hears each sensor's frames.

    Raises
    ------
    ConfigError
        No such sensor, or it does not use an image pipeline.
    """
    picked = []
    for i, s in enumerate(cfg.sensors):
        name = s.name or s.type
        if sensor is not None and name != sensor:
            continue
        if getattr(s, "pipeline", "") != "image" or getattr(s, "image", None) is None:
            if sensor is not None:
                raise ConfigError(source, ("sensors", i, "pipeline"), f"sensor {name!r} does not use pipeline: image")
            continue
        picked.append((name, s))
    if not picked:
        names = [s.name or s.type for s in cfg.sensors]
        what = (f"no sensor named {sensor!r} (sensors: {', '.join(names)})" + did_you_mean(sensor, names)
                if sensor else "no sensor uses pipeline: image")
        raise ConfigError(source, ("sensors",), what)
    from needlecli.models import MODELS
    from needlecli.sensors.imaging.render import to_mm

    unit = MODELS.get(cfg.model.type).length_unit
    scale = to_mm(unit)
    out = []
    for name, s in picked:
        device = DEVICES.get(s.image.device)(s.image)
        table = characterize_device(device, repeats=repeats, seed=seed, outlier=outlier, mode=mode,
                                    axes=tuple(a for a in s.axes if a in device.axes),
                                    progress=(lambda k, n, _n=name: progress(f"sensor {_n}", k, n)) if progress else None)
        suggestion: dict = {}
        std_cols = [c for c in table.columns if c.startswith("Std ")]
        if s.image.device == "us3d":
            sig, a = fit_growth(table, s.image.max_depth)
            suggestion = {"sigma": float(f"{sig / scale:.3g}"), "growth": {
                "transducer": [v / scale for v in s.image.transducer], "a": round(a, 3),
                "d_max": s.image.max_depth / scale}}
        elif std_cols:
            suggestion = {"sigma": float(f"{np.nanmean(table[std_cols].to_numpy(float)) / scale:.3g}")}
        out.append(Characterization(sensor=name, device=s.image.device, table=table, suggestion=suggestion))
    return out
