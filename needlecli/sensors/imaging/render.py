"""Rendering helpers shared by the imaging devices: the needle's shape from the truth, speckle, blurs,
log compression, and the frames kept for a person to look at.

Everything here works in **millimetres** whatever the model's length unit (imaging hardware is specified
in mm and pixels); :func:`to_mm` converts at the edge. Arrays are batched over runs in front.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

_TO_MM = {"mm": 1.0, "m": 1000.0, "cm": 10.0}


def to_mm(length_unit: str) -> float:
    """Millimetres per model length unit."""
    try:
        return _TO_MM[length_unit]
    except KeyError:
        raise ValueError(f"imaging cannot convert length unit {length_unit!r} to mm") from None


# ---------------------------------------------------------------------------------------------- geometry
@dataclass(frozen=True)
class NeedleGeometry:
    """The needle of every run at one sample, in mm, world frame.

    Attributes
    ----------
    shaft : (B, K, 3) points along the needle from the tip (``shaft[:, 0]``) backwards, ``ds`` apart in arc
        length (a bevel-tip or magnetic needle follows its tip's path, so the shaft is the path behind it)
    visible : (B, K) bool, the points inside the tissue (or pre-inserted, see ``visible_from``)
    tangent : (B, 3) unit vector, the direction of motion at the tip
    ds : spacing of the shaft points, mm
    """

    shaft: np.ndarray
    visible: np.ndarray
    tangent: np.ndarray
    ds: float

    @property
    def tip(self) -> np.ndarray:
        return self.shaft[:, 0]

    def take(self, rows: np.ndarray) -> NeedleGeometry:
        """The runs ``rows`` only."""
        return NeedleGeometry(self.shaft[rows], self.visible[rows], self.tangent[rows], self.ds)

    @staticmethod
    def straight(tip: np.ndarray, direction: np.ndarray, length: float, ds: float = 0.5) -> NeedleGeometry:
        """A straight needle of ``length`` mm ending at ``tip (B, 3)``, pointing along ``direction (B, 3)``
        (used to measure a pipeline on chosen poses)."""
        tip = np.atleast_2d(np.asarray(tip, dtype=float))
        d = np.atleast_2d(np.asarray(direction, dtype=float))
        d = d / np.linalg.norm(d, axis=-1, keepdims=True)
        d = np.broadcast_to(d, tip.shape)
        k = int(np.ceil(length / ds)) + 1
        s = ds * np.arange(k)
        shaft = tip[:, None, :] - s[None, :, None] * d[:, None, :]
        return NeedleGeometry(shaft, np.ones(shaft.shape[:2], dtype=bool), np.ascontiguousarray(d), ds)


class TruthPath:
    """The true tip path of every run in mm, from which the needle's shape at any sample is read.

    Parameters
    ----------
    truth : the simulated insertions; ``truth.depth`` (T,) is the inserted arc length of the tip
    visible_from : arc length (mm) from which the shaft is visible; negative values extend the shaft
        behind the starting point along the initial tangent (a needle pre-inserted that far, as for the
        initialisation volume of the multi-rate UKF paper)
    """

    def __init__(self, truth, visible_from: float = 0.0) -> None:
        model = truth.model
        self.scale = to_mm(model.length_unit)
        self.p = model.tip_position(truth.states) * self.scale  # (N, T, 3)
        if model.provides("tangent"):
            t = model.tangent(truth.states)
        else:  # direction of motion from the path
            t = np.gradient(self.p, axis=1)
        self.t = t / np.maximum(np.linalg.norm(t, axis=-1, keepdims=True), 1e-12)
        self.depth = np.asarray(truth.depth, dtype=float) * self.scale  # (T,)
        self.visible_from = float(visible_from)

    @property
    def n_runs(self) -> int:
        return self.p.shape[0]

    def points(self, i: np.ndarray | slice) -> np.ndarray:
        """Tip positions ``(N, ..., 3)`` mm at grid indices ``i``."""
        return self.p[:, i]

    def tangents(self, i: np.ndarray | slice) -> np.ndarray:
        """Unit tangents ``(N, ..., 3)`` at grid indices ``i``."""
        return self.t[:, i]

    def geometry(self, k: int, length: float, ds: float) -> NeedleGeometry:
        """The needle at grid index ``k``: the last ``length`` mm of the path, every ``ds`` mm."""
        n = int(np.ceil(length / ds)) + 1
        s = self.depth[k] - ds * np.arange(n)  # arc length of each shaft point along the insertion
        fi = np.interp(s, self.depth[: k + 1], np.arange(k + 1, dtype=float))
        i0 = np.clip(np.floor(fi).astype(np.int64), 0, max(k - 1, 0))
        f = np.clip(fi - i0, 0.0, 1.0)[None, :, None]
        i1 = np.minimum(i0 + 1, k)
        pts = self.points(i0) * (1.0 - f) + self.points(i1) * f
        before = s < 0  # behind the start: along the initial tangent
        if before.any():
            pts[:, before] = self.points(slice(0, 1)) + s[before][None, :, None] * self.tangents(slice(0, 1))
        visible = np.broadcast_to(s >= self.visible_from - 1e-9, pts.shape[:2])
        return NeedleGeometry(pts, np.ascontiguousarray(visible), self.tangents(k).copy(), ds)


class LiveTruthPath(TruthPath):
    """A :class:`TruthPath` over a simulation still running: ``geometry(k)`` first calls ``ready(k)``
    (which simulates until the state at grid index ``k`` exists) and reads only states up to ``k``.
    Its geometry equals :class:`TruthPath`'s on the finished truth, bit for bit.

    Parameters
    ----------
    model : the truth's model (must define the tangent: the path's gradient would need later states)
    states : (N, T, n) the array the simulation fills
    depth : (T,) inserted length, model unit (known before the simulation)
    ready : ``ready(k)`` makes ``states[:, : k + 1]`` valid
    """

    def __init__(self, model, states: np.ndarray, depth: np.ndarray, ready, visible_from: float = 0.0) -> None:
        if not model.provides("tangent"):
            raise ValueError(f"model {model.registered_name!r} has no tangent: its path cannot be imaged while it runs")
        self.model = model
        self.states = states
        self.ready = ready
        self.scale = to_mm(model.length_unit)
        self.depth = np.asarray(depth, dtype=float) * self.scale
        self.visible_from = float(visible_from)

    @property
    def n_runs(self) -> int:
        return self.states.shape[0]

    def points(self, i):
        return self.model.tip_position(self.states[:, i]) * self.scale

    def tangents(self, i):
        t = self.model.tangent(self.states[:, i])
        return t / np.maximum(np.linalg.norm(t, axis=-1, keepdims=True), 1e-12)

    def geometry(self, k: int, length: float, ds: float) -> NeedleGeometry:
        self.ready(k)
        return super().geometry(k, length, ds)


# ---------------------------------------------------------------------------------------------- speckle
def periodic_speckle(rng: np.random.Generator, shape: tuple[int, ...], sigma_px: tuple[float, ...]) -> np.ndarray:
    """Fully developed speckle: the envelope of a circular complex Gaussian field low-passed by a
    Gaussian point-spread function of std ``sigma_px`` (pixels, per axis), periodic in every axis so that
    it tiles without seams. Rayleigh distributed, mean 1, float32, of ``shape``."""
    z = rng.standard_normal(shape) + 1j * rng.standard_normal(shape)
    spec = np.fft.fftn(z)
    for ax, (n, s) in enumerate(zip(shape, sigma_px)):
        f = np.fft.fftfreq(n)
        g = np.exp(-2.0 * (np.pi * f * s) ** 2)  # Fourier transform of a Gaussian of std s
        spec *= g.reshape([-1 if i == ax else 1 for i in range(len(shape))])
    env = np.abs(np.fft.ifftn(spec))
    return (env / env.mean()).astype(np.float32)


def block_max(a: np.ndarray, factor: int) -> np.ndarray:
    """Maximum over ``factor``-sized blocks along every axis (sizes must be multiples of ``factor``)."""
    shape = []
    for n in a.shape:
        shape += [n // factor, factor]
    return a.reshape(shape).max(axis=tuple(range(1, 2 * a.ndim, 2)))


def tile_take(bank: np.ndarray, start: np.ndarray, size: tuple[int, ...]) -> np.ndarray:
    """Windows of a periodic ``bank`` (D axes): ``out[b] = bank[start[b] + arange(size)]`` modulo the
    bank's shape, for every row of ``start (B, D)``; one fancy-index gather for the whole batch."""
    idx = []
    D = bank.ndim
    for ax in range(D):
        i = (start[:, ax, None] + np.arange(size[ax])[None, :]) % bank.shape[ax]  # (B, size)
        shape = [start.shape[0]] + [1] * D
        shape[ax + 1] = size[ax]
        idx.append(i.reshape(shape))
    return bank[tuple(idx)]


# ---------------------------------------------------------------------------------------------- filters
def gaussian_kernel(sigma: float, truncate: float = 3.0) -> np.ndarray:
    r = max(1, int(np.ceil(truncate * sigma)))
    x = np.arange(-r, r + 1, dtype=float)
    k = np.exp(-0.5 * (x / max(sigma, 1e-6)) ** 2)
    return (k / k.sum()).astype(np.float32)


def blur_axis(a: np.ndarray, axis: int, sigma: float) -> np.ndarray:
    """Gaussian blur of a batch along one axis (edges replicated): a few shifted multiply-adds over the
    whole array, so a batch of frames costs one pass per tap."""
    if sigma <= 0:
        return a
    k = gaussian_kernel(sigma)
    r = len(k) // 2
    pad = [(0, 0)] * a.ndim
    pad[axis] = (r, r)
    p = np.pad(a, pad, mode="edge")
    n = a.shape[axis]
    out = np.zeros_like(a, dtype=np.float32)
    for i, w in enumerate(k):
        sl = [slice(None)] * a.ndim
        sl[axis] = slice(i, i + n)
        out += w * p[tuple(sl)]
    return out


def log_compress(intensity: np.ndarray, reference: float, dynamic_range_db: float) -> np.ndarray:
    """B-mode display: ``255 (1 + 20 log10(I / reference) / DR)`` clipped to 0..255, uint8."""
    with np.errstate(divide="ignore"):
        db = 20.0 * np.log10(np.maximum(intensity, 1e-12) / reference)
    return np.clip(np.rint(255.0 * (1.0 + db / dynamic_range_db)), 0, 255).astype(np.uint8)


def log_expand(value: np.ndarray, reference: float, dynamic_range_db: float) -> np.ndarray:
    """Inverse of :func:`log_compress` (linear intensity from 0..255 values)."""
    return reference * 10.0 ** ((np.asarray(value, dtype=np.float32) / 255.0 - 1.0) * dynamic_range_db / 20.0)


# ---------------------------------------------------------------------------------------------- frames
@dataclass
class FrameStore:
    """The frames kept for a person to look at: ``per_run`` evenly spaced samples of the first ``runs``
    runs. Written to the results file as ``/measurements/<sensor>/frames`` (uint8, ``(F, H, W)`` or a
    volume ``(F, X, Y, Z)``) with ``frame_run``, ``frame_sample`` (index into the sensor's samples),
    ``frame_tip`` (detected tip in pixel/voxel coordinates of the frame, NaN when there was no detection),
    ``frame_truth`` (the true tip, same coordinates) and, for volumes that follow the tip,
    ``frame_origin`` (world mm of voxel (0, 0, 0))."""

    n_samples: int
    runs: int
    per_run: int
    images: list = field(default_factory=list)
    meta: list = field(default_factory=list)

    def __post_init__(self) -> None:
        if self.per_run <= 0 or self.n_samples == 0:
            self.samples = np.zeros(0, dtype=np.int64)
        else:
            k = min(self.per_run, self.n_samples)
            # evenly spaced, the last sample included: the needle is longest there
            self.samples = np.unique(np.rint(np.linspace(0, self.n_samples - 1, k + 1)[1:]).astype(np.int64))

    def wanted(self, j: int) -> np.ndarray:
        """Runs whose frame of sample ``j`` is kept."""
        if j in self.samples:
            return np.arange(self.runs)
        return np.zeros(0, dtype=np.int64)

    def add(self, run: int, sample: int, image: np.ndarray, tip_px: np.ndarray, truth_px: np.ndarray,
            origin: np.ndarray | None = None) -> None:
        """Keep one frame; ``origin``: world position (mm) of the frame's first pixel/voxel, when it moves."""
        self.images.append(np.asarray(image, dtype=np.uint8))
        self.meta.append((run, sample, np.asarray(tip_px, dtype=float), np.asarray(truth_px, dtype=float),
                          None if origin is None else np.asarray(origin, dtype=float)))

    def extras(self) -> dict[str, np.ndarray]:
        if not self.images:
            return {}
        out = {
            "frames": np.stack(self.images),
            "frame_run": np.array([m[0] for m in self.meta], dtype=np.int64),
            "frame_sample": np.array([m[1] for m in self.meta], dtype=np.int64),
            "frame_tip": np.stack([m[2] for m in self.meta]),
            "frame_truth": np.stack([m[3] for m in self.meta]),
        }
        if any(m[4] is not None for m in self.meta):
            out["frame_origin"] = np.stack([m[4] if m[4] is not None else np.full(3, np.nan) for m in self.meta])
        return out


@dataclass
class DeviceResult:
    """What a device measured for every run and sample.

    tip : (N, M, 3) detected tip in mm, world frame (NaN where not valid or not measured by the device)
    valid : (N, M) bool, a detection was made (``False``: no measurement, never a made-up position)
    extras : further (N, M[, k]) arrays of the device (e.g. the camera's opacity), and saved frames
    """

    tip: np.ndarray
    valid: np.ndarray
    extras: dict[str, np.ndarray] = field(default_factory=dict)
