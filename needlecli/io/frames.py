r"""Trial frames: a recorded insertion expressed where the kinematic models expect it.

The bevel-tip models start at the origin pointing along ``+z`` with ``alpha = beta = gamma = 0`` and
bend toward body ``-y`` (``w = (kappa v, 0, u)``). A tracker records the tip in its own coordinates:
insertions along another axis (the unicycle is singular at ``beta = +-pi/2``), an origin anywhere, a
sensor rolled in the needle. A *trial frame* is the rigid change of coordinates

.. math:: p' = G (p - p_0),\qquad R' = G R\, R_z(\psi)

with ``p_0`` the first valid pose, ``G`` the axes of that pose (its rotated tangent on ``z``) and ``psi``
the roll that turns the needle's measured bending direction onto body ``-y``. Shared by the importers
(``io/ultrasteer.py`` for its data set, ``io/csv_import.py`` for a lab's exports); pure array functions.

Without orientations (a position-only tracker) the frame comes from the path alone
(:func:`path_frame`): ``z`` along the first chord of a few millimetres, ``-y`` toward the side the path
bends to.
"""

from __future__ import annotations

import numpy as np

from needlecli.numerics import rot_z


def chord_pairs(pos: np.ndarray, ok: np.ndarray, k: int, min_length: float):
    """Pairs of valid samples ``k`` valid samples apart: ``(i, j, unit chord (K, 3), chord length (K,))``
    (indices into the samples), keeping chords longer than ``min_length``."""
    idx = np.nonzero(ok)[0]
    if len(idx) <= k:
        return idx[:0], idx[:0], np.zeros((0, 3)), np.zeros(0)
    i, j = idx[:-k], idx[k:]
    d = pos[j] - pos[i]
    n = np.linalg.norm(d, axis=-1)
    good = n > min_length
    return i[good], j[good], d[good] / n[good, None], n[good]


def chord_step(pos: np.ndarray, ok: np.ndarray, length: float) -> int:
    """How many valid samples apart two samples are about ``length`` of path apart (at least 3)."""
    p = pos[ok]
    if len(p) < 2:
        return 3
    step = float(np.median(np.linalg.norm(np.diff(p, axis=0), axis=-1)))
    return max(3, int(round(length / max(step, 1e-9))))


def body_bend(rot_i: np.ndarray, rot_j: np.ndarray, length: np.ndarray) -> np.ndarray:
    """Body-frame change of the tangent per unit length between rotations ``rot_i``, ``rot_j (K, 3, 3)``
    a path ``length (K,)`` apart: ``R_i^T (t_j - t_i) / length`` (``(K, 3)``; its norm is the
    curvature, its direction in the body x-y plane the bending direction)."""
    return np.einsum("kji,kj->ki", rot_i, rot_j[:, :, 2] - rot_i[:, :, 2]) / length[:, None]


def bend_roll(bend: np.ndarray) -> tuple[float, float]:
    """``(psi, direction)``: the roll ``psi`` such that ``R Rz(psi)`` bends toward body ``-y``, from
    body-frame bending vectors ``bend (K, 3)`` (:func:`body_bend`; their mean direction in the x-y plane,
    ``direction`` in rad from body ``+x``). ``psi`` is wrapped to ``(-pi, pi]``."""
    cm = bend.mean(0)
    direction = float(np.arctan2(cm[1], cm[0]))
    psi = direction + np.pi / 2.0  # Rz(psi)^T turns the bending direction onto -e2
    return float(np.arctan2(np.sin(psi), np.cos(psi))), direction


def rolled(rot: np.ndarray, psi: float) -> np.ndarray:
    """``R Rz(psi)``: the body frame rolled about the tangent."""
    return rot @ rot_z(psi)


def pose_axes(rot0: np.ndarray) -> np.ndarray:
    """``G``: the axes of the trial frame given the (rolled) orientation at its first pose, ``G = R0^T``
    (so that ``G R0 = I``: the first pose is the model's default pose)."""
    return np.asarray(rot0).T


def express(G: np.ndarray, p0: np.ndarray, pos: np.ndarray | None = None, rot: np.ndarray | None = None):
    """Positions ``G (p - p0)`` and rotations ``G R`` in the trial frame (either may be None)."""
    p = None if pos is None else (np.asarray(pos) - p0) @ G.T
    r = None if rot is None else G @ np.asarray(rot)
    return p, r


def path_frame(pos: np.ndarray, ok: np.ndarray, chord: float = 3.0) -> tuple[np.ndarray, np.ndarray, dict]:
    """``(G, p0, info)`` from positions only: the origin at the first valid sample, ``z`` along the chord
    to the first valid sample at least ``chord`` away (the initial insertion direction), ``-y`` toward the
    mean deviation of the rest of the path from that line (the bending direction; a straight path keeps
    the recorded ``x`` as close to ``x`` as it can). Raises ValueError with fewer than two valid samples
    or a path shorter than ``chord``."""
    idx = np.nonzero(ok)[0]
    if idx.size < 2:
        raise ValueError("fewer than two valid samples")
    p0 = pos[idx[0]]
    dist = np.linalg.norm(pos[idx] - p0, axis=-1)
    far = np.nonzero(dist >= chord)[0]
    if not far.size:
        raise ValueError(f"the path never gets {chord:g} from its first valid sample (max {dist.max():.3g})")
    z = (pos[idx[far[0]]] - p0) / dist[far[0]]
    d = pos[idx] - p0
    dev = d - (d @ z)[:, None] * z
    b = dev.mean(0)
    info = {"z_from": f"chord to the first valid sample {chord:g} away", "bend_deviation": float(np.linalg.norm(b))}
    if np.linalg.norm(b) < 1e-9:
        ref = np.eye(3)[int(np.argmin(np.abs(z)))]
        b = ref - (ref @ z) * z
        info["bend_from"] = "none (a straight path): x kept close to the recorded axis"
    else:
        info["bend_from"] = "mean deviation of the path from the initial line"
    y = -b / np.linalg.norm(b)
    x = np.cross(y, z)
    return np.stack([x, y, z]), p0, info


#: A trial whose recorded path starts more than this many degrees from the model's insertion axis is
#: warned about (``needle log info``, ``needle fit-em``). In a trial frame a path starts along the axis to
#: within the guide's misalignment, the tracker's noise over the chord and the bending of its first tenth
#: (:func:`initial_directions`): at most 20 deg in the 19 recorded ultrasteer insertions (their tracker),
#: under 10 deg in the synthetic lab exports of ``make owndata``. 30 deg is beyond that, and far short of
#: where the bevel-tip models' coordinates fail (90 deg, beta = +-pi/2): a path this far off was recorded in
#: another frame (an insertion along the tracker's x, a frame taken from a flipped pose), and EM fits it
#: with values outside the model's (a negative speed scale for a path run backwards) rather than failing.
AXIS_WARNING_DEG = 30.0


def initial_directions(pos: np.ndarray, ok: np.ndarray, fraction: float = 0.1) -> np.ndarray:
    """The direction each path starts in, ``(N, 3)`` unit vectors (NaN for a path with fewer than two valid
    samples apart): from its first valid sample to the first valid sample at least ``fraction`` of the
    path's extent (its largest distance from the first valid sample) away, for paths ``pos (N, M, 3)``
    with valid samples ``ok (N, M)``; all paths at once. Scale-free: the chord is a tenth of the path in
    any length unit."""
    pos = np.asarray(pos, dtype=float)
    ok = np.asarray(ok, dtype=bool) & np.isfinite(pos).all(-1)
    N = pos.shape[0]
    out = np.full((N, 3), np.nan)
    if pos.shape[1] == 0:
        return out
    rows = np.arange(N)
    first = np.argmax(ok, axis=1)
    d = pos - pos[rows, first][:, None, :]
    dist = np.where(ok, np.linalg.norm(np.where(ok[..., None], d, 0.0), axis=-1), 0.0)
    extent = dist.max(axis=1)
    far = ok & (dist >= fraction * extent[:, None]) & (dist > 0)
    has = far.any(axis=1) & (extent > 0)
    j = np.argmax(far, axis=1)
    out[has] = d[rows[has], j[has]] / dist[rows[has], j[has]][:, None]
    return out


def axis_angles(directions: np.ndarray, axis: np.ndarray) -> np.ndarray:
    """Angles in degrees ``(N,)`` between unit vectors ``directions (N, 3)`` and ``axis`` ``(3,)`` or ``(N, 3)``
    (NaN where a direction is NaN)."""
    a = np.asarray(axis, dtype=float)
    a = a / np.linalg.norm(a, axis=-1, keepdims=True)
    with np.errstate(invalid="ignore"):
        return np.degrees(np.arccos(np.clip(np.sum(directions * a, axis=-1), -1.0, 1.0)))
