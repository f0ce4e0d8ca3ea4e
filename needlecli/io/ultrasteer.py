r"""Import of the recorded insertions of the public ``josephgreer/ultrasteer`` data set (Stanford CHARM lab:
2D transverse ultrasound following a bevel-tip needle, an electromagnetic tracker in the needle as ground
truth) into the project's log format. The data stay outside the repository (``../shared/real-data/
ultrasteer``, or ``NEEDLECLI_REAL_DATA``); this module only reads them.

Layout read (ASCII, whitespace-separated)::

    trials/<M_D_YY>/<speed>/Trial<k>/FullStateGroundTruthPos.dat   N x 3 tracker tip position, mm
    trials/<M_D_YY>/<speed>/Trial<k>/FullStateGroundTruthRs.dat    9 x N tracker rotation
    resultsOrig/   the same files plus FullStateGroundTruthRho.dat (N x 1, radius setting, mm), V.dat,
                   Thetas.dat, dts.dat (1 x N), MeasPos.dat (3 x N ultrasound tip), MeasUv.dat (2 x N image
                   coordinates), MeasDoppler.dat (1 x N), MeasFul/Fur/Fbl.dat (3 x N image corners),
                   MeasBx/By.dat (3 x N image axes), paramsFullState.dat (its ``lutBasePath`` names the trial: 9_18_15/1mm/Trial3)

Conventions found in the data (``tests/test_real_data.py`` checks them on every trial):

* ``Rs`` is flattened **by column** (``Rs[:, k] = R11, R21, R31, R12, ...``): with that reading the
  third column is the axis that follows the positions' direction of motion (mean cosine with 5 mm chords
  0.97-0.98 on the 1_7_16 trials, 0.91-0.94 on 9_18_15); read by row, the 1_7_16 trials give 0.43-0.47,
  and the first two columns are never the tangent (the 9_18_15 rotations are nearly symmetric: only
  1_7_16 tells the readings apart). The tracker's frame thus already has the tangent on ``e3``.
* The last frame of 16 of the 18 trials (and one interior frame of 9_18_15/2mm/Trial5) is not a
  measurement: an all-zero rotation and a position jump, or (1_7_16 Trials 3-5) a fixed pose 35 mm away. Frames
  whose rotation is not orthonormal to 0.02 (or not finite), frames more than 10 mm or 20 deg away from
  both valid neighbours (the last: from the one before) and frames identical to the previous one (the
  tracker did not update: stale) are not ground truth. Leading and trailing frames without a valid
  tracker sample are cut from every stream; inside a trial they are invalid samples. The valid rotations
  (``|R^T R - I|`` about 3e-4 as recorded) are replaced by the nearest rotation (polar factor).
* The tracker's tangent is tilted against the direction of motion by a constant angle in the plane of the
  (planar, circular) path: 20.8 deg (median) on 9_18_15, 12.1 deg on 1_7_16. With ``align`` (default) a
  constant rotation ``W`` per recording session, fitted by least squares (Kabsch) between the tracker's
  tangents and the unit chords of about 3 mm of path, registers the tracker's rotations to its positions
  (a fixed-frame rotation fits better than a body-frame tilt on the trials that turn 30-60 deg); the
  residual is 3.7 deg (9_18_15) and 8.1 deg (1_7_16, about 1 mm of position jitter).
* Bending direction (the frame maths shared with the CSV import: :mod:`needlecli.io.frames`): the lab's
  model (``TipState::PropagateLength``) bends toward body ``+y``; ours
  (``w = (kappa v, 0, u)``) toward ``-y``. With ``align`` a roll ``Rz(psi)`` per session, ``psi`` from the
  mean body-frame direction of ``dt/ds`` in the session, maps the bending direction onto ``-y`` (with
  ``--no-align`` the lab's convention is mapped: ``psi = pi``). The tracker's frame also rolls about the
  tangent by 0.4-0.6 deg per mm on 9_18_15 while the path stays planar: reported, not corrected.

Our rotation is therefore ``R = G W R_tracker Rz(psi)`` and the position ``p = G (p_tracker - p0)``, where
``frame: trial`` (default) puts the origin at the first valid tracker frame and the axes along that
frame's ``W R Rz(psi)`` (each trial starts at the model's default pose: alpha = beta = gamma = 0, z the
insertion direction), and ``frame: tracker`` keeps the tracker's coordinates (``G = I``, ``p0 = 0``).
The ultrasound positions go through the same ``G``, ``p0``.

Each trial becomes one log trial with

* truth (``ground truth``): ``x, y, z`` (mm), ``alpha, beta, gamma`` (rad, ``R = Rx Ry Rz``) and
  ``R11 .. R33`` (row by row, for the SO(3) evaluation), at the valid tracker frames;
* sensor ``tracker`` (``position``, x y z): the tracker positions (invalid where the frame is not);
* sensor ``tangent`` (``tangent``): ``R e3`` of the tracker (aligned), for the SO(3) observer;
* sensor ``us`` (``position``, resultsOrig only): ``MeasPos`` with its outliers; frames whose image
  coordinates fall outside the image (the detector found no needle: Doppler 0 there), all-zero or
  non-finite rows are lost: kept in the file, marked invalid;
* sensor ``plane`` (``image_plane``, resultsOrig only): the ultrasound's image plane at every frame, its
  unit normal ``nx, ny, nz`` (``MeasBx x MeasBy``, turned along the insertion), its signed position along
  it ``d = n . MeasFul`` (mm) and ``seen`` (1 where ``us`` is valid, 0 where lost): a one-sided bound on
  the tip (:mod:`needlecli.sensors.plane`), valid wherever the plane's axes are;
* sensor ``transverse`` (``transverse``, resultsOrig only): the same ultrasound frames as a transverse
  image plane that sees the shaft (:mod:`needlecli.sensors.transverse`): the needle's crossing in the
  image's coordinates ``u, v`` (mm, ``MeasPos`` projected on the image axes: it lies in the plane) and the
  plane's pose of every frame, origin ``ox, oy, oz`` (``MeasFul``) and unit axes ``ux .. uz``, ``vx .. vz``
  (``MeasBx``, ``MeasBy``); valid where ``us`` is;
* sensor ``inserted`` (``insertion``, resultsOrig only): the inserted length since the first ultrasound frame
  that saw the needle, the commanded speed ``V.dat`` over the frame intervals
  (:mod:`needlecli.sensors.insertion`), its reference pose that frame's ultrasound point and the trial's
  initial insertion direction (``z`` of the trial frame); valid from that frame on; ``inserted_edge``, the
  same length from where the first sweep's Doppler power (``MeasDoppler``) fell to half its maximum so far
  (:func:`doppler_edge`: the plane passing the tip), its reference the needle's crossing there, valid from
  the frame that showed the edge (1.24 s into resultsOrig); and ``inserted_from_start``,
  the same length from the trial's start with the tip's pose at ``t = 0`` as its reference (what a robot's
  needle guide gives; in this recording the tracker's first frame);
* input ``v`` (mm/s): ``V.dat`` where present (``V[k]`` drives ``(t_{k-1}, t_k]``), else the folder's
  speed (``05mm`` -> 0.5, ``1mm`` -> 1, ...); input ``u`` (rad/s) from the differences of ``Thetas.dat``
  over ``dts`` where present; the trials have no rotation record (``u`` absent: zero in replay);
* times: ``cumsum(dts)`` where ``dts.dat`` exists, else ``k * 0.177`` s (5.65 Hz nominal);
* metadata: date, session, speed, trial, folder, radius setting (``FullStateGroundTruthRho``), what was
  dropped and why, the alignment and its residual, the tracker path's fitted circle radius and plane
  rms, the tracker's own summed roll about the tangent and bending.
"""

from __future__ import annotations

import json
import os
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from needlecli.errors import DataError
from needlecli.io.frames import bend_roll, body_bend, chord_pairs, express, pose_axes, rolled
from needlecli.io.logs import InputStream, Log, SensorStream, Trial, TruthStream
from needlecli.numerics import matrix_to_euler_xyz, project_to_so3

NOMINAL_DT = 0.177  # s between tracker/ultrasound frames (5.65 Hz), resultsOrig/dts.dat
ORTHO_TOL = 0.02  # max |R^T R - I| of a valid tracker rotation
CHORD_MM = 3.0  # length of the chords the alignment compares with the tangents
JUMP_MM, JUMP_DEG = 10.0, 20.0  # a tracker frame this far from its neighbours is not a measurement
ENV_VAR = "NEEDLECLI_REAL_DATA"
R_NAMES = tuple(f"R{i}{j}" for i in range(1, 4) for j in range(1, 4))
TRUTH_NAMES = ("x", "y", "z", "alpha", "beta", "gamma", *R_NAMES)
TRUTH_UNITS = ("mm", "mm", "mm", "rad", "rad", "rad", *(("1",) * 9))


def default_data_dir() -> Path | None:
    """The data set's folder: ``$NEEDLECLI_REAL_DATA`` if set, else ``shared/real-data/ultrasteer`` beside
    the checkout (``/work/shared/...`` for ``/work/main``); None if it does not exist."""
    env = os.environ.get(ENV_VAR)
    p = Path(env) if env else Path(__file__).resolve().parents[3] / "shared" / "real-data" / "ultrasteer"
    return p if p.is_dir() else None


# ---------------------------------------------------------------------------------------------- reading
def read_numbers(path: Path, *, finite: bool = False) -> np.ndarray:
    """A whitespace-separated numeric file as a 2D array (a single row or column stays 2D); with
    ``finite``, a NaN or infinite entry is an error naming its row and column (times, speeds, angles)."""
    from needlecli.io.inputs import check_kind

    check_kind(path, "a file of numbers", missing="no such file")  # a regular file, never a FIFO
    try:
        a = np.loadtxt(path, ndmin=2)
    except (OSError, ValueError, UnicodeDecodeError) as e:
        raise DataError(f"{path}: cannot read the numbers ({' '.join(str(e).split())[:200]})") from None
    if finite:
        bad = np.argwhere(~np.isfinite(a))
        if bad.size:
            r, c = bad[0]
            raise DataError(f"{path}: [row {r + 1}, column {c + 1}] {a[r, c]} is not a finite number")
    return a


def _rows(path: Path, m: int) -> np.ndarray:
    """``(N, m)`` from a file stored ``m x N`` (or ``N x m``)."""
    a = read_numbers(path)
    if a.shape[0] == m and a.shape[1] != m:
        return a.T
    if a.shape[1] == m:
        return a
    raise DataError(f"{path}: expected {m} rows or columns, found shape {a.shape}")


def rotations_from_columns(rs: np.ndarray) -> np.ndarray:
    """``(N, 3, 3)`` from the ``9 x N`` file, each column ``R11, R21, R31, R12, R22, R32, R13, R23, R33``
    (flattened by column, as the data show)."""
    return np.swapaxes(np.asarray(rs, dtype=float).T.reshape(-1, 3, 3), -1, -2)


def rotation_valid(r: np.ndarray, tol: float = ORTHO_TOL) -> np.ndarray:
    """``(N,)`` True where ``r`` is a finite rotation: ``|R^T R - I| <= tol`` and ``det R > 0``."""
    finite = np.isfinite(r).all(axis=(-2, -1))
    rr = np.where(finite[..., None, None], r, 0.0)
    err = np.abs(np.swapaxes(rr, -1, -2) @ rr - np.eye(3)).max(axis=(-2, -1))
    return finite & (err <= tol) & (np.linalg.det(rr) > 0)


def speed_from_folder(name: str) -> float | None:
    """Insertion speed in mm/s from a folder name: ``05mm`` -> 0.5, ``1mm`` -> 1, ``15mm`` -> 15."""
    m = re.fullmatch(r"(\d+)mm", name)
    if not m:
        return None
    digits = m.group(1)
    if len(digits) > 1 and digits[0] == "0":
        return float(f"0.{digits[1:]}")
    return float(digits)


def session_date(session: str) -> str:
    """ISO date of a ``M_D_YY`` folder name (``9_18_15`` -> ``2015-09-18``); the name if it is not one."""
    m = re.fullmatch(r"(\d{1,2})_(\d{1,2})_(\d{2})", session)
    if not m:
        return session
    return f"20{m.group(3)}-{int(m.group(1)):02d}-{int(m.group(2)):02d}"


@dataclass
class RawTrial:
    """One folder as read, in the tracker's frame, before any alignment. Arrays over the N frames."""

    id: str
    folder: Path
    session: str
    speed: float
    trial: int | None
    t: np.ndarray  # (N,) s
    pos: np.ndarray  # (N, 3) mm
    rot: np.ndarray  # (N, 3, 3) tracker rotation
    ok: np.ndarray  # (N,) valid tracker frame
    reasons: dict[str, int]
    v: tuple[np.ndarray, np.ndarray]  # times, values (mm/s) held from each time on
    u: tuple[np.ndarray, np.ndarray] | None = None
    us: np.ndarray | None = None  # (N, 3) ultrasound tip, mm
    us_lost: np.ndarray | None = None  # (N,) bool
    us_reasons: dict[str, int] = field(default_factory=dict)
    plane: tuple[np.ndarray, np.ndarray] | None = None  # (N, 3) a corner, (N, 3) unit normal along the insertion
    image_axes: tuple[np.ndarray, np.ndarray] | None = None  # (N, 3) unit MeasBx, MeasBy (NaN where not usable)
    doppler: np.ndarray | None = None  # (N,) MeasDoppler: the needle's Doppler power in the image, per frame
    rho: float | None = None
    dt_source: str = "nominal 0.177 s"
    same_as: str | None = None  # a trial of trials/ holding the same tracker record


def _tracker_validity(pos: np.ndarray, rot: np.ndarray) -> tuple[np.ndarray, dict[str, int]]:
    rot_ok = rotation_valid(rot)
    pos_ok = np.isfinite(pos).all(-1) & ~(pos == 0).all(-1)
    stale = np.zeros(len(pos), dtype=bool)
    if len(pos) > 1:
        stale[1:] = (pos[1:] == pos[:-1]).all(-1) & (rot[1:] == rot[:-1]).all(axis=(-2, -1))
    ok = rot_ok & pos_ok & ~stale
    # a jump: a frame far from both valid neighbours (the first or last: from its one neighbour)
    idx = np.nonzero(ok)[0]
    jump = np.zeros(len(pos), dtype=bool)
    if idx.size > 2:
        p, r = pos[idx], rot[idx]
        step = np.linalg.norm(np.diff(p, axis=0), axis=-1)
        turn = np.degrees(np.arccos(np.clip((np.trace(np.swapaxes(r[:-1], -1, -2) @ r[1:], axis1=-2, axis2=-1) - 1) / 2,
                                            -1.0, 1.0)))
        far = (step > JUMP_MM) | (turn > JUMP_DEG)
        isolated = np.concatenate([[far[0]], far[:-1] & far[1:], [far[-1]]])
        jump[idx[isolated]] = True
    ok &= ~jump
    reasons = {"rotation not orthonormal or zero": int((~rot_ok).sum()),
               "position zero or not finite": int((rot_ok & ~pos_ok).sum()),
               "stale (repeats the previous frame)": int((rot_ok & pos_ok & stale).sum()),
               f"jump (more than {JUMP_MM:g} mm or {JUMP_DEG:g} deg from its neighbours)": int(jump.sum())}
    return ok, {k: v for k, v in reasons.items() if v}


def _lut_base(folder: Path) -> tuple[str, str, int | None] | None:
    """``(session, speed folder, trial)`` from ``paramsFullState.dat``'s ``lutBasePath``, if it names one."""
    p = folder / "paramsFullState.dat"
    if not p.is_file():
        return None
    for line in p.read_text(errors="replace").splitlines():
        if line.startswith("lutBasePath"):
            parts = [s for s in re.split(r"[\\/]", line.split(None, 1)[-1].strip()) if s]
            for i in range(len(parts) - 2):
                if speed_from_folder(parts[i + 1]) is not None and re.fullmatch(r"Trial\d+", parts[i + 2]):
                    return parts[i], parts[i + 1], int(parts[i + 2][5:])
    return None


def read_trial(folder: Path, *, trial_id: str, session: str, speed_folder: str | None, trial: int | None) -> RawTrial:
    """Read one folder (a ``trials/.../TrialN`` or ``resultsOrig``)."""
    pos = _rows(folder / "FullStateGroundTruthPos.dat", 3)
    rs = read_numbers(folder / "FullStateGroundTruthRs.dat")
    if rs.shape[0] != 9 and rs.shape[1] == 9:
        rs = rs.T
    if rs.shape[0] != 9:
        raise DataError(f"{folder / 'FullStateGroundTruthRs.dat'}: expected 9 rows, found shape {rs.shape}")
    N = len(pos)
    if rs.shape[1] != N:
        raise DataError(f"{folder}: {N} positions but {rs.shape[1]} rotations")
    rot = rotations_from_columns(rs)
    ok, reasons = _tracker_validity(pos, rot)
    rot[ok] = project_to_so3(rot[ok])  # |R^T R - I| is about 3e-4 as recorded: the nearest rotation
    # times
    dts_path = folder / "dts.dat"
    if dts_path.exists():
        dts = read_numbers(dts_path, finite=True).ravel()
        if dts.size != N:
            raise DataError(f"{dts_path}: {dts.size} entries for {N} frames")
        if (dts[1:] <= 0).any():
            raise DataError(f"{dts_path}: time step {int(np.argmax(dts[1:] <= 0)) + 1} is not positive")
        t = np.cumsum(np.concatenate([[0.0], dts[1:]]))
        dt_source = "dts.dat"
    else:
        dts = np.full(N, NOMINAL_DT)
        t = NOMINAL_DT * np.arange(N)
        dt_source = f"nominal {NOMINAL_DT} s"
    # insertion speed: V[k] drives (t_{k-1}, t_k]
    speed = speed_from_folder(speed_folder) if speed_folder else None
    v_path = folder / "V.dat"
    if v_path.exists():
        V = read_numbers(v_path, finite=True).ravel()
        if V.size != N:
            raise DataError(f"{v_path}: {V.size} entries for {N} frames")
        v = (t[:-1], V[1:])
        speed = float(np.median(V[1:])) if speed is None else speed
    elif speed is not None:
        v = (t[:1], np.array([speed]))
    else:
        raise DataError(f"{folder}: no V.dat and no speed in the folder name")
    u = None
    th_path = folder / "Thetas.dat"
    if th_path.exists():
        th = read_numbers(th_path, finite=True).ravel()
        if th.size != N:
            raise DataError(f"{th_path}: {th.size} entries for {N} frames")
        u = (t[:-1], np.diff(th) / dts[1:])
    raw = RawTrial(id=trial_id, folder=folder, session=session, speed=float(speed), trial=trial, t=t, pos=pos,
                   rot=rot, ok=ok, reasons=reasons, v=v, u=u, dt_source=dt_source)
    rho_path = folder / "FullStateGroundTruthRho.dat"
    if rho_path.exists():
        rho = read_numbers(rho_path).ravel()
        raw.rho = float(np.median(rho[np.isfinite(rho)])) if np.isfinite(rho).any() else None
    meas = folder / "MeasPos.dat"
    if meas.exists():
        us = _rows(meas, 3)
        if len(us) != N:
            raise DataError(f"{meas}: {len(us)} frames, the tracker has {N}")
        raw.us, raw.us_lost, raw.us_reasons = us, *_us_lost(folder, us)
        raw.plane = _image_plane(folder, N)
        raw.image_axes = _image_axes(folder, N) if raw.plane is not None else None
        dop = folder / "MeasDoppler.dat"
        if dop.exists():
            d = read_numbers(dop).ravel()
            raw.doppler = d if d.size == N else None
    return raw


def _image_axes(folder: Path, N: int) -> tuple[np.ndarray, np.ndarray]:
    """The image's unit axes ``MeasBx``, ``MeasBy`` of each frame ``(N, 3)`` each (NaN where not finite or
    of no length); the plane's origin is ``MeasFul`` (:func:`_image_plane`)."""
    out = []
    for f in ("MeasBx.dat", "MeasBy.dat"):
        a = _rows(folder / f, 3)
        with np.errstate(all="ignore"):
            norm = np.linalg.norm(a, axis=-1, keepdims=True)
            out.append(np.where(np.isfinite(a).all(-1, keepdims=True) & (norm > 0), a / norm, np.nan))
    return out[0], out[1]


def _image_plane(folder: Path, N: int) -> tuple[np.ndarray, np.ndarray] | None:
    """The image plane of each frame from ``MeasFul`` (its upper-left corner) and ``MeasBx``, ``MeasBy``
    (its axes): the corner and the unit normal ``Bx x By``, turned to point along the insertion (the way
    the plane travels: ``n . (c_last - c_first) > 0``, the plane's own record). Frames whose axes are not
    finite or (nearly) parallel get a NaN normal. None if the files are absent."""
    paths = [folder / f for f in ("MeasFul.dat", "MeasBx.dat", "MeasBy.dat")]
    if not all(p.exists() for p in paths):
        return None
    c, bx, by = (_rows(p, 3) for p in paths)
    for p, a in zip(paths, (c, bx, by)):
        if len(a) != N:
            raise DataError(f"{p}: {len(a)} frames, the tracker has {N}")
    with np.errstate(all="ignore"):
        n = np.cross(bx, by)
        norm = np.linalg.norm(n, axis=-1, keepdims=True)
        ok = np.isfinite(n).all(-1) & np.isfinite(c).all(-1) & (norm[:, 0] > 0.5 * np.linalg.norm(bx, axis=-1)
                                                                 * np.linalg.norm(by, axis=-1))
        n = np.where(ok[:, None], n / norm, np.nan)
    idx = np.nonzero(ok)[0]
    if idx.size >= 2 and np.dot(np.nanmean(n[idx], 0), c[idx[-1]] - c[idx[0]]) < 0:
        n = -n
    return c, n


def _us_lost(folder: Path, us: np.ndarray) -> tuple[np.ndarray, dict[str, int]]:
    """Lost ultrasound frames: non-finite or all-zero rows, image coordinates outside the image (the
    corners give its size), zero Doppler (no needle found)."""
    N = len(us)
    nonfinite = ~np.isfinite(us).all(-1)
    zero = (us == 0).all(-1) & ~nonfinite
    outside = np.zeros(N, dtype=bool)
    uv_path, ful, fur, fbl = (folder / f for f in ("MeasUv.dat", "MeasFul.dat", "MeasFur.dat", "MeasFbl.dat"))
    if uv_path.exists() and ful.exists() and fur.exists() and fbl.exists():
        uv = _rows(uv_path, 2)
        c_ul, c_ur, c_bl = _rows(ful, 3), _rows(fur, 3), _rows(fbl, 3)
        w = np.linalg.norm(c_ur - c_ul, axis=-1)
        h = np.linalg.norm(c_bl - c_ul, axis=-1)
        outside = ~((uv[:, 0] >= 0) & (uv[:, 0] <= w) & (uv[:, 1] >= 0) & (uv[:, 1] <= h))
    no_doppler = np.zeros(N, dtype=bool)
    dop = folder / "MeasDoppler.dat"
    if dop.exists():
        d = read_numbers(dop).ravel()
        if d.size == N:
            no_doppler = ~(d > 0)
    lost = nonfinite | zero | outside | no_doppler
    reasons = {"not finite": int(nonfinite.sum()), "all zero": int(zero.sum()),
               "image coordinates outside the image": int(outside.sum()), "no Doppler (0)": int(no_doppler.sum()),
               "lost (any of these)": int(lost.sum())}
    return lost, {k: v for k, v in reasons.items() if v}


def doppler_edge(power: np.ndarray, fraction: float = 0.5) -> tuple[int, float] | None:
    """Where the needle's Doppler power first falls below ``fraction`` of its maximum so far: the image plane
    passing the tip (the half-maximum edge of the needle's Doppler profile along the plane's sweep).

    Parameters
    ----------
    power : (K,) array
        The Doppler power per frame (``MeasDoppler``), in time order.
    fraction : float
        The edge's level against the running maximum (0.5: the half maximum).

    Returns
    -------
    ``(k, w)``: the edge lies ``w`` (0 to 1) of the way from frame ``k - 1`` to frame ``k``, the first frame
    below the level (known at frame ``k``: it reads frames up to ``k`` only); None if the power never falls
    below it after a positive maximum.
    """
    p = np.where(np.isfinite(power), power, 0.0)
    top = np.maximum.accumulate(p)
    below = np.nonzero((p < fraction * top) & (top > 0))[0]
    if not below.size:
        return None
    k = int(below[0])
    level = fraction * top[k]
    return k, float((p[k - 1] - level) / (p[k - 1] - p[k]))


def find_trials(root: Path) -> list[RawTrial]:
    """Every trial under ``root/trials/<session>/<speed>/Trial<k>`` and ``root/resultsOrig`` (if present)."""
    root = Path(root)
    if not root.is_dir():
        raise DataError(f"{root}: no such data folder")
    out: list[RawTrial] = []
    for folder in sorted((root / "trials").glob("*/*/Trial*")):
        if not (folder / "FullStateGroundTruthPos.dat").exists():
            continue
        session, speed_folder = folder.parent.parent.name, folder.parent.name
        m = re.fullmatch(r"Trial(\d+)", folder.name)
        out.append(read_trial(folder, trial_id=f"{session}-{speed_folder}-{folder.name}", session=session,
                              speed_folder=speed_folder, trial=int(m.group(1)) if m else None))
    orig = root / "resultsOrig"
    if (orig / "FullStateGroundTruthPos.dat").exists():
        lut = _lut_base(orig)
        session, speed_folder, trial = lut if lut else ("resultsOrig", None, None)
        raw = read_trial(orig, trial_id="resultsOrig", session=session, speed_folder=speed_folder, trial=trial)
        for other in out:
            if other.pos.shape == raw.pos.shape and np.array_equal(other.pos, raw.pos):
                raw.same_as = other.id
        out.append(raw)
    if not out:
        raise DataError(f"{root}: no trials (expected trials/<date>/<speed>/Trial<k>/ or resultsOrig/)")
    return out


# ---------------------------------------------------------------------------------------------- geometry
def chords(raw: RawTrial, length: float = CHORD_MM) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Pairs of valid frames about ``length`` mm of insertion apart: ``(i, j, unit chord (K, 3), chord
    length (K,))`` with ``i`` and ``j`` indices into the frames."""
    dt = float(np.median(np.diff(raw.t))) if len(raw.t) > 1 else NOMINAL_DT
    k = max(3, int(round(length / max(raw.speed * dt, 1e-9))))
    return chord_pairs(raw.pos, raw.ok, k, 0.3 * length)


def kabsch(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Rotation ``W`` minimising ``sum |b_k - W a_k|^2`` for unit vectors ``a, b (K, 3)``."""
    u, _, vt = np.linalg.svd(a.T @ b)
    d = np.sign(np.linalg.det(vt.T @ u.T))
    return vt.T @ np.diag([1.0, 1.0, d]) @ u.T


def _angle_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.degrees(np.arccos(np.clip(np.sum(a * b, -1), -1.0, 1.0)))


@dataclass
class Alignment:
    """Per session: ``W`` registers the tracker's rotations to its positions (fixed frame), ``psi`` rolls the
    body frame so that the needle bends toward ``-y``."""

    W: np.ndarray
    psi: float
    trials: list[str]
    residual_deg: float  # median angle between the aligned tangent and the chords
    raw_angle_deg: float  # the same before alignment
    bend_direction_deg: float  # body-frame direction of dt/ds in the tracker's x-y plane (from +x)
    curvature: float  # median |dt/ds| from the rotations, 1/mm

    def as_meta(self) -> dict:
        from needlecli.numerics import so3_log

        return {"W_rotvec_deg": np.degrees(so3_log(self.W)).round(3).tolist(), "psi_deg": round(float(np.degrees(self.psi)), 3),
                "estimated_from": self.trials, "tangent_vs_motion_deg_raw": round(self.raw_angle_deg, 3),
                "tangent_vs_motion_deg_aligned": round(self.residual_deg, 3),
                "bend_direction_in_tracker_xy_deg": round(self.bend_direction_deg, 3),
                "curvature_from_rotations_1_per_mm": round(self.curvature, 6)}


def estimate_alignment(raws: list[RawTrial], align: bool = True) -> dict[str, Alignment]:
    """One :class:`Alignment` per session, pooled over its trials (a trial that repeats another's tracker
    record, resultsOrig, is not counted twice). Without ``align``: ``W = I``, ``psi = pi`` (the lab's
    model bends toward ``+y``)."""
    sessions: dict[str, list[RawTrial]] = {}
    for r in raws:
        if r.same_as is None:
            sessions.setdefault(r.session, []).append(r)
    for r in raws:  # a session known only from a duplicate
        if r.session not in sessions:
            sessions[r.session] = [r]
    out = {}
    for name, members in sessions.items():
        tang, chord, curv = [], [], []
        for r in members:  # gathering the pairs of each trial's frames
            i, j, c, n = chords(r)
            t = r.rot[i, :, 2] + r.rot[j, :, 2]
            tang.append(t / np.linalg.norm(t, axis=-1, keepdims=True))
            chord.append(c)
            curv.append(body_bend(r.rot[i], r.rot[j], n))
        a, b, c = np.concatenate(tang), np.concatenate(chord), np.concatenate(curv)
        if len(a) < 3:
            raise DataError(f"session {name}: too few valid tracker frames to check the orientation")
        raw_angle = float(np.median(_angle_deg(a, b)))
        psi, bend = bend_roll(c)  # Rz(psi)^T turns the bending direction onto -e2
        if align:
            W = kabsch(a, b)
        else:
            W, psi = np.eye(3), float(np.arctan2(np.sin(np.pi), np.cos(np.pi)))
        resid = float(np.median(_angle_deg(a @ W.T, b)))
        out[name] = Alignment(W=W, psi=psi, trials=[r.id for r in members],
                              residual_deg=resid, raw_angle_deg=raw_angle, bend_direction_deg=float(np.degrees(bend)),
                              curvature=float(np.median(np.linalg.norm(c, axis=-1))))
    return out


def circle_radius(p: np.ndarray) -> tuple[float, float]:
    """Radius (mm) of the circle fitted to a planar path ``p (K, 3)`` by least squares, and the path's rms
    distance from its plane (mm)."""
    c = p.mean(0)
    _, _, vt = np.linalg.svd(p - c)
    q = (p - c) @ vt[:2].T
    A = np.c_[2.0 * q, np.ones(len(q))]
    sol = np.linalg.lstsq(A, (q**2).sum(1), rcond=None)[0]
    r = float(np.sqrt(sol[2] + sol[0] ** 2 + sol[1] ** 2))
    return r, float(np.std((p - c) @ vt[2]))


def tracker_roll(raw: RawTrial) -> tuple[float, float]:
    """The tracker's own rotation over a trial, from its frame-to-frame body rotations: ``(roll, bend)`` in
    deg, the summed rotation about the tangent ``e3`` (zero for a needle without shaft rotation) and the
    summed rotation perpendicular to it (the bending, ``int kappa ds``)."""
    from needlecli.numerics import so3_log

    idx = np.nonzero(raw.ok)[0]
    w = so3_log(np.swapaxes(raw.rot[idx[:-1]], -1, -2) @ raw.rot[idx[1:]])  # (K, 3) body rotation vectors
    return float(np.degrees(w[:, 2].sum())), float(np.degrees(np.linalg.norm(w[:, :2].sum(0))))


# ---------------------------------------------------------------------------------------------- the log
def to_trial(raw: RawTrial, al: Alignment, *, frame: str = "trial") -> Trial:
    """One log trial from a read folder and its session's alignment (module docstring for the frames)."""
    idx = np.nonzero(raw.ok)[0]
    if idx.size < 2:
        raise DataError(f"{raw.folder}: fewer than two valid tracker frames")
    a, b = int(idx[0]), int(idx[-1])
    keep = slice(a, b + 1)
    r_al = rolled(al.W @ raw.rot[keep], al.psi)  # (K, 3, 3)
    ok = raw.ok[keep]
    if frame == "trial":
        G, p0 = pose_axes(r_al[0]), raw.pos[a]
    elif frame == "tracker":
        G, p0 = np.eye(3), np.zeros(3)
    else:
        raise ValueError(f"unknown frame {frame!r} (trial or tracker)")
    t = raw.t[keep] - raw.t[a]
    pos, R = express(G, p0, raw.pos[keep], r_al)
    R = np.where(ok[:, None, None], R, np.eye(3))  # invalid frames: placeholders, never valid
    euler = matrix_to_euler_xyz(R)
    state = np.concatenate([pos, euler, R.reshape(-1, 9)], -1)
    tr = Trial(id=raw.id)
    tr.truth = TruthStream(t=t[ok], state=state[ok], names=TRUTH_NAMES, units=TRUTH_UNITS,
                           kind="ground truth")
    rate = float(1.0 / np.median(np.diff(t))) if len(t) > 1 else 1.0 / NOMINAL_DT
    tr.sensors["tracker"] = SensorStream(
        t=t, value=np.where(ok[:, None], pos, 0.0), valid=ok.copy(), names=("x", "y", "z"), units=("mm",) * 3,
        settings={"type": "position", "name": "tracker", "rate": rate, "axes": ["x", "y", "z"], "sigma": 0.2})
    tr.sensors["tangent"] = SensorStream(
        t=t, value=R[:, :, 2], valid=ok.copy(), names=("tx", "ty", "tz"), units=("1",) * 3,
        settings={"type": "tangent", "name": "tangent", "rate": rate, "sigma": 0.01})
    if raw.us is not None:
        us, _ = express(G, p0, raw.us[keep])
        lost = raw.us_lost[keep]
        tr.sensors["us"] = SensorStream(
            t=t, value=np.where(np.isfinite(us), us, 0.0), valid=~lost, names=("x", "y", "z"), units=("mm",) * 3,
            settings={"type": "position", "name": "us", "rate": rate, "axes": ["x", "y", "z"], "sigma": 2.0})
    if raw.plane is not None and raw.us is not None:
        c, _ = express(G, p0, raw.plane[0][keep])
        n = raw.plane[1][keep] @ G.T
        ok_plane = np.isfinite(n).all(-1)
        value = np.concatenate([n, np.sum(n * c, -1)[:, None], (~raw.us_lost[keep])[:, None].astype(float)], -1)
        tr.sensors["plane"] = SensorStream(
            t=t, value=np.where(ok_plane[:, None], value, 0.0), valid=ok_plane, names=("nx", "ny", "nz", "d", "seen"),
            units=("1", "1", "1", "mm", "1"), settings={"type": "image_plane", "name": "plane", "rate": rate})
    if raw.plane is not None and raw.image_axes is not None and raw.us is not None:
        o, _ = express(G, p0, raw.plane[0][keep])
        eu, ev = raw.image_axes[0][keep] @ G.T, raw.image_axes[1][keep] @ G.T
        us, _ = express(G, p0, raw.us[keep])
        d = us - o  # MeasPos lies in the image plane (to 1e-5 mm on resultsOrig): its image coordinates
        uv = np.stack([np.sum(eu * d, -1), np.sum(ev * d, -1)], -1)
        pose = np.concatenate([uv, o, eu, ev], -1)
        ok_t = np.isfinite(pose).all(-1) & ~raw.us_lost[keep]
        tr.sensors["transverse"] = SensorStream(
            t=t, value=np.where(np.isfinite(pose), pose, 0.0), valid=ok_t,
            names=("u", "v", "ox", "oy", "oz", "ux", "uy", "uz", "vx", "vy", "vz"), units=("mm",) * 5 + ("1",) * 6,
            settings={"type": "transverse", "name": "transverse", "rate": rate, "sigma": 0.5})
    if (raw.folder / "V.dat").exists() and raw.us is not None:
        # the inserted length since the first ultrasound frame that saw the needle: the commanded speed over
        # the frame intervals (V[k] drives (t_{k-1}, t_k]); the reference pose is that frame's ultrasound point
        # (no tracker) and the insertion direction of the trial's start (the trial frame's z, where every
        # filter's start takes its orientation from)
        vt, vv = raw.v
        total = np.concatenate([[0.0], np.cumsum(np.diff(raw.t) * vv[: len(raw.t) - 1])])[keep]
        us_k, _ = express(G, p0, raw.us[keep])
        seen = np.nonzero(~raw.us_lost[keep] & np.isfinite(us_k).all(-1))[0]
        f = int(seen[0]) if seen.size else 0
        entry = np.concatenate([us_k[f], (G @ r_al[0][:, 2]) if frame == "trial" else r_al[0][:, 2]])
        on = np.arange(len(t)) >= f
        tr.sensors["inserted"] = SensorStream(
            t=t, value=np.where(on[:, None], np.concatenate([(total - total[f])[:, None], np.tile(entry, (len(t), 1))],
                                                            -1), 0.0), valid=on & bool(seen.size),
            names=("length", "ex", "ey", "ez", "dx", "dy", "dz"), units=("mm",) * 4 + ("1",) * 3,
            settings={"type": "insertion", "name": "inserted", "rate": rate, "sigma": 0.2})
        # the same length from where the first sweep's Doppler power fell to half its maximum so far: the image
        # plane passing the tip; its reference point the needle's crossing there (interpolated between the two
        # frames), valid from the frame that showed the edge on (a delay: the edge is known then)
        edge = doppler_edge(raw.doppler[keep]) if raw.doppler is not None else None
        if edge is not None and not raw.us_lost[keep][edge[0] - 1: edge[0] + 1].any():
            k, w = edge
            ref = (1.0 - w) * us_k[k - 1] + w * us_k[k]
            length0 = (1.0 - w) * total[k - 1] + w * total[k]
            on = np.arange(len(t)) >= k
            tr.sensors["inserted_edge"] = SensorStream(
                t=t, value=np.where(on[:, None], np.concatenate(
                    [(total - length0)[:, None], np.tile(np.concatenate([ref, entry[3:]]), (len(t), 1))], -1), 0.0),
                valid=on, names=("length", "ex", "ey", "ez", "dx", "dy", "dz"), units=("mm",) * 4 + ("1",) * 3,
                settings={"type": "insertion", "name": "inserted_edge", "rate": rate, "sigma": 0.2})
        # the same length from the trial's start, its reference pose the tip's at t = 0 (the trial frame's
        # origin and z): what a robot's needle guide gives; in this recording only the tracker's first frame
        start = np.array([0.0, 0.0, 0.0, 0.0, 0.0, 1.0]) if frame == "trial" else np.concatenate([pos[0], R[0][:, 2]])
        tr.sensors["inserted_from_start"] = SensorStream(
            t=t, value=np.concatenate([(total - total[0])[:, None], np.tile(start, (len(t), 1))], -1),
            valid=np.ones(len(t), dtype=bool), names=("length", "ex", "ey", "ez", "dx", "dy", "dz"),
            units=("mm",) * 4 + ("1",) * 3,
            settings={"type": "insertion", "name": "inserted_from_start", "rate": rate, "sigma": 0.2})
    # inputs, cut to the kept frames and shifted to t = 0
    vt, vv = raw.v
    sel = (vt >= raw.t[a] - 1e-9) & (vt < raw.t[b] - 1e-9)
    if not sel.any():
        sel = np.zeros(len(vt), dtype=bool)
        sel[0] = True
    tr.inputs["v"] = InputStream(t=np.maximum(vt[sel] - raw.t[a], 0.0), value=vv[sel][:, None], unit="mm/s",
                                 kind="commanded")
    if raw.u is not None:
        ut, uv = raw.u
        sel = (ut >= raw.t[a] - 1e-9) & (ut < raw.t[b] - 1e-9)
        if sel.any():
            tr.inputs["u"] = InputStream(t=ut[sel] - raw.t[a], value=uv[sel][:, None], unit="rad/s", kind="commanded")
    # metadata
    dropped_interior = int((~ok).sum())
    radius, plane_rms = circle_radius(raw.pos[raw.ok])
    i, j, c, _ = chords(raw)
    tang = raw.rot[i, :, 2] + raw.rot[j, :, 2]
    tang /= np.linalg.norm(tang, axis=-1, keepdims=True)
    roll, bend = tracker_roll(raw)
    meta = {
        "source": "josephgreer/ultrasteer (Stanford CHARM lab), electromagnetic tracker in the needle",
        "folder": str(raw.folder), "session": raw.session, "date": session_date(raw.session),
        "speed_mm_s": raw.speed, "trial": raw.trial if raw.trial is not None else -1,
        "time_step": raw.dt_source, "frames_read": len(raw.t), "frames_kept": b - a + 1,
        "frames_cut_at_ends": len(raw.t) - (b - a + 1), "tracker_invalid_inside": dropped_interior,
        "tracker_invalid_reasons": raw.reasons, "frame": frame,
        "orientation": "R = G W R_tracker Rz(psi); Rs read by column, tangent R e3",
        "alignment": al.as_meta(),
        "tangent_vs_motion_deg_raw": round(float(np.median(_angle_deg(tang, c))), 3) if len(c) else -1.0,
        "tangent_vs_motion_deg_aligned": round(float(np.median(_angle_deg(tang @ al.W.T, c))), 3) if len(c) else -1.0,
        "tracker_circle_radius_mm": round(radius, 3), "tracker_plane_rms_mm": round(plane_rms, 4),
        "tracker_roll_about_tangent_deg": round(roll, 3), "tracker_bend_deg": round(bend, 3),
        "shaft_rotation": "Thetas.dat differences over dts" if raw.u is not None else
                          "not recorded (u absent: held at zero in replay)",
        "design_factors": ["session", "speed_mm_s"],  # what fit tables group by (reports/design.py)
    }
    if raw.rho is not None:
        meta["rho_setting_mm"] = raw.rho
    if raw.us is not None:
        meta["us_lost_frames"] = int(raw.us_lost[keep].sum())
        meta["us_lost_reasons"] = raw.us_reasons
    if raw.same_as is not None:
        meta["same_tracker_record_as"] = raw.same_as
    tr.meta = meta
    return tr


def import_ultrasteer(root: str | Path, *, align: bool = True, frame: str = "trial") -> Log:
    """Every trial of the data set at ``root`` as one log (module docstring for what each trial holds)."""
    root = Path(root)
    raws = find_trials(root)
    alignment = estimate_alignment(raws, align=align)
    trials = [to_trial(r, alignment[r.session], frame=frame) for r in raws]
    return Log(trials=trials, attrs={
        "description": "ultrasteer: bevel-tip needle insertions, EM tracker ground truth, 2D transverse "
                       "ultrasound tip measurements (resultsOrig)",
        "synthetic": False,
        "source": f"needle import ultrasteer {root}",
        "alignment": json.dumps({k: v.as_meta() for k, v in alignment.items()}),
        "aligned": bool(align), "frame": frame,
    })
