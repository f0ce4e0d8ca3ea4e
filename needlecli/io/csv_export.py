"""``needle log export-csv``: a log written the way a lab's tracker software exports insertions, with the
mapping that imports it back (``needle log import-csv``). Made to test a mapping and the whole path from
exports to fits on data whose truth is known (docs/tutorials/own-data.md).

Per trial, in the output folder:

* ``<id>_pose.csv``: one row per sample of the position sensor, indexed by step (``step`` = 0, 1, ...; no
  time column): the tip position ``px, py, pz`` (mm) and orientation ``qw, qx, qy, qz`` (a unit
  quaternion, from the log's truth orientation at that time) in the *tracker's* coordinates (the model
  frame moved by ``--tracker-pose``: an insertion along another axis, an origin elsewhere; the coil rolled
  in the needle by ``--sensor-roll``), and ``rms``,
  the sample's noise std (mm). A lost sample is a row of zeros, as trackers write them.
* ``<id>_cmd.csv``: the command file, ``name,value`` lines: ``step_mm`` (commanded advance per sample),
  ``speed_mm_s``, ``rotation_speed_deg_s`` and each design factor of the trial.
* ``mapping.yaml``: the import mapping (time ``row * step_mm / speed_mm_s``, all-zero rows lost,
  quaternions, ``rms`` as each sample's sigma, trial frames, the design factors).

The commanded values are what the log's inputs say; if the simulated needle slipped (``speed_scale`` < 1)
the positions advance less than ``step_mm`` per row, as in a real export.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import yaml

from needlecli.errors import DataError
from needlecli.io.atomic import write_text_atomic
from needlecli.io.logs import Log, design_factors
from needlecli.numerics import euler_xyz_to_matrix, matrix_to_quaternion, rot_z, so3_exp


def tracker_pose(text: str | None) -> tuple[np.ndarray, np.ndarray]:
    """``(A, b)`` from ``"rx,ry,rz,tx,ty,tz"`` (a rotation vector in deg and a translation in mm): a point
    ``p`` of the model frame is ``A p + b`` in the tracker's coordinates. None: the identity."""
    if not text:
        return np.eye(3), np.zeros(3)
    try:
        v = [float(x) for x in text.split(",")]
    except ValueError:
        raise DataError(f"--tracker-pose {text!r}: expected six numbers rx,ry,rz,tx,ty,tz") from None
    if len(v) != 6 or not np.isfinite(v).all():
        raise DataError(f"--tracker-pose {text!r}: expected six finite numbers rx,ry,rz,tx,ty,tz (deg, mm)")
    return so3_exp(np.radians(v[:3])), np.array(v[3:])


def export_lab_csv(log: Log, out_dir: str | Path, *, sensor: str = "tracker", pose: str | None = None,
                   roll_deg: float = 0.0) -> list[Path]:
    """Write every trial of ``log`` as a lab's exports and the mapping that reads them (module docstring);
    ``roll_deg``: the tracker coil rolled in the needle by that angle about the tangent (its quaternion is
    ``A R Rz(roll)``). Returns the files written."""
    out_dir = Path(out_dir)
    A, b = tracker_pose(pose)
    if not np.isfinite(roll_deg):
        raise DataError(f"--sensor-roll {roll_deg}: not a finite angle")
    Rroll = rot_z(np.radians(roll_deg))
    written: list[Path] = []
    prepared = []
    for tr in log.trials:  # check everything before writing anything
        where = f"{log.path}: [trial {tr.id}"
        if sensor not in tr.sensors:
            raise DataError(f"{where}] no sensor {sensor!r}; sensors: {', '.join(tr.sensors)}")
        s = tr.sensors[sensor]
        if s.settings.get("type") != "position" or not {"x", "y", "z"} <= set(s.names):
            raise DataError(f"{where} -> sensor {sensor}] must be a position sensor with x, y, z")
        if s.units[0] != "mm":
            raise DataError(f"{where} -> sensor {sensor}] positions in {s.units[0]!r}; export-csv writes mm")
        t = s.t
        d = np.diff(t)
        if len(t) < 3 or abs(t[0]) > 1e-9 or not np.allclose(d, d[0], rtol=1e-6, atol=1e-9):
            raise DataError(f"{where} -> sensor {sensor}] export-csv writes step-indexed rows: the samples must be "
                            "evenly spaced from t = 0")
        if tr.truth is None or not {"alpha", "beta", "gamma"} <= set(tr.truth.names):
            raise DataError(f"{where}] needs a truth with alpha, beta, gamma for the orientation")
        if "v" not in tr.inputs:
            raise DataError(f"{where}] needs the insertion speed input v")
        prepared.append((tr, s, float(d[0])))
    sigmas, factors = [], None
    for tr, s, period in prepared:
        names = list(s.names)
        p = s.value[:, [names.index(a) for a in "xyz"]] @ A.T + b
        tn = list(tr.truth.names)
        k = np.clip(np.searchsorted(tr.truth.t, s.t - 1e-9), 0, len(tr.truth.t) - 1)
        e = tr.truth.state[k][:, [tn.index(a) for a in ("alpha", "beta", "gamma")]]
        q = matrix_to_quaternion(A @ euler_xyz_to_matrix(e[:, 0], e[:, 1], e[:, 2]) @ Rroll)
        if s.sigma is not None:
            rms = s.sigma[:, 0]
        else:
            rms = np.full(len(s.t), float(np.mean(np.atleast_1d(s.settings.get("sigma", 0.0)))))
        ok = s.valid & np.isfinite(p).all(-1) & np.isfinite(rms)
        sigmas.append(rms[ok])
        rows = np.where(ok[:, None], np.c_[p, q, rms], 0.0)
        path = out_dir / f"{tr.id}_pose.csv"
        write_text_atomic(path, "step,px,py,pz,qw,qx,qy,qz,rms\n" + "".join(
            f"{i}," + ",".join("0" if x == 0 else f"{x:.9g}" for x in r) + "\n" for i, r in enumerate(rows)))
        written.append(path)
        v = np.asarray(tr.inputs["v"].value, dtype=float)[:, 0]
        vt = tr.inputs["v"].t
        on = (vt <= s.t[-1]) & (v != 0)
        speed = float(np.median(v[on])) if on.any() else float(np.median(v))
        u = np.asarray(tr.inputs["u"].value, dtype=float)[:, 0] if "u" in tr.inputs else np.zeros(1)
        cmd = {"step_mm": speed * period, "speed_mm_s": speed, "rotation_speed_deg_s": float(np.degrees(np.median(u)))}
        fs = design_factors(tr)
        factors = fs if factors is None else [f for f in factors if f in fs]
        for f in fs:
            cmd[f] = tr.meta[f]
        path = out_dir / f"{tr.id}_cmd.csv"
        write_text_atomic(path, "".join(f"{k},{v:.12g}\n" if isinstance(v, float) else f"{k},{v}\n"
                                        for k, v in cmd.items()))
        written.append(path)
    nominal = float(np.median(np.concatenate(sigmas))) if sigmas and np.concatenate(sigmas).size else 0.2
    mapping = {
        "description": f"lab-style exports of {log.path} (needle log export-csv): step-indexed tracker poses, "
                       "quaternions, zero rows for lost samples, a command file per trial",
        "length_unit": "mm",
        "discover": {"files": "{id}_pose.csv", "meta_file": "{id}_cmd.csv"},
        "factors": factors or [],
        "time": {"formula": "row * step_mm / speed_mm_s"},
        "missing": {"zero_rows": True},
        "leading_invalid": "start",
        "frame": {"reference": sensor},
        "inputs": {"v": {"value": "speed_mm_s", "unit": "mm/s"},
                   "u": {"value": "rotation_speed_deg_s", "unit": "deg/s"}},
        "sensors": {sensor: {"file": "{id}_pose.csv", "columns": {"x": "px", "y": "py", "z": "pz"},
                             "units": ["mm", "mm", "mm"], "quaternion": {"w": "qw", "x": "qx", "y": "qy", "z": "qz"},
                             "sigma_column": "rms",
                             "sensor": {"type": "position", "axes": ["x", "y", "z"], "sigma": round(nominal, 6)}}},
        "truth": {"file": "{id}_pose.csv", "columns": {"x": "px", "y": "py", "z": "pz"}, "units": ["mm", "mm", "mm"],
                  "quaternion": {"w": "qw", "x": "qx", "y": "qy", "z": "qz"}},
    }
    path = out_dir / "mapping.yaml"
    write_text_atomic(path, "# written by needle log export-csv: imports the exports beside it\n"
                      + yaml.safe_dump(mapping, sort_keys=False))
    written.append(path)
    return written
