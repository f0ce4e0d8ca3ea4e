"""2D transverse ultrasound following the tip (the high-gain observer paper), rendered as B-mode images; tip by RANSAC.

Geometry: the probe sits on the phantom with its face centre at world ``(x, y) = face`` and images the
plane ``z = z_tip - plane_offset`` (it rides on a stage that follows the tip). Image columns are the
lateral axis (world x), rows the depth below the face along the beam (world -y); pixels are square.

Rendering, per frame (a batch of frames is one array operation): tissue speckle (a periodic speckle
texture, a random window per frame), the needle's cross-section where the shaft crosses the plane (a
bright echo of its near wall, of the point-spread function's size) with its reverberation tail (rings
every needle diameter deeper, decaying), depth attenuation of every echo, electronic noise, envelope,
log compression to 8 bit.

Measurement (the high-gain observer paper finds the tip "using RANSAC"): candidate pixels brighter than their row's median by
``threshold_db``; RANSAC fits the line of the needle's echo and its tail, which runs along the beam;
the near-wall echo is the brightest point on that line (sub-pixel by a parabola), and the needle's centre
lies one radius deeper. Fewer inliers than ``min_inliers``: no measurement. Vectorised over frames
(hypotheses of every frame scored in one array operation). Where speckle weakens the wall echo, the first
reverberation ring (one diameter deeper) can win: a rare error of one diameter in depth. The reported
position is the shaft's cross-section in the plane, ``plane_offset tan(tilt)`` from the tip's.
"""

from __future__ import annotations

from typing import Literal

import numpy as np
from pydantic import Field

from needlecli.schema import NonNeg, Positive
from needlecli.sensors.imaging.base import DEVICES, Device, ImageSettings, Pose
from needlecli.sensors.imaging.render import (
    DeviceResult,
    FrameStore,
    NeedleGeometry,
    blur_axis,
    log_compress,
    periodic_speckle,
)


class TransverseUltrasoundSettings(ImageSettings):
    """2D transverse B-mode ultrasound (the high-gain observer paper: SonixTouch, 18 G needle in gelatin)."""

    device: Literal["us2d"] = Field(description="the imaging device: us2d, 2D transverse ultrasound (the high-gain observer paper)")
    pixel: Positive = Field(0.2, description="pixel edge, mm")
    width: Positive = Field(40.0, description="lateral extent of the image (world x), mm")
    depth: Positive = Field(40.0, description="imaging depth below the probe face, mm")
    face: tuple[float, float] = Field((0.0, 20.0), description="world (x, y) of the probe face centre, mm; the beam runs along -y")
    plane_offset: NonNeg = Field(0.5, description="the image plane trails the tip by this along z, mm")
    needle_radius: Positive = Field(0.635, description="outer radius of the needle, mm (18 G)")
    psf: tuple[Positive, Positive] = Field((0.5, 0.25), description="lateral and axial std of the point-spread function, mm")
    needle_echo: Positive = Field(10.0, description="echo of the needle's near wall relative to the mean tissue echo")
    tail_level: NonNeg = Field(0.5, description="first reverberation ring relative to the wall echo")
    tail_length: Positive = Field(2.0, description="e-folding length of the reverberation tail, mm")
    attenuation: NonNeg = Field(0.1, description="two-way attenuation of echoes, dB/mm")
    noise_level: NonNeg = Field(0.05, description="electronic noise std relative to the mean tissue echo")
    dynamic_range: Positive = Field(50.0, description="display dynamic range, dB")
    threshold_db: Positive = Field(14.0, description="candidates: brighter than the row median by this, dB")
    candidates: int = Field(96, ge=8, le=1024, description="brightest candidate pixels given to RANSAC")
    ransac_iterations: int = Field(64, ge=4, le=4096, description="line hypotheses (pairs of candidates) RANSAC tries per frame")
    ransac_tolerance: Positive = Field(0.3, description="inlier distance to the line, mm")
    min_inliers: int = Field(8, ge=3, description="fewer inliers: no measurement")
    max_tilt: float = Field(25.0, gt=0, lt=90, description="the line must be within this of the beam, deg")


@DEVICES.register("us2d")
class TransverseUltrasound(Device):
    """The high-gain observer paper's 2D transverse ultrasound: tip ``(x, y)`` (see the module docstring)."""

    Settings = TransverseUltrasoundSettings
    axes = ("x", "y")

    def __init__(self, settings: TransverseUltrasoundSettings) -> None:
        super().__init__(settings)
        s = settings
        self.W = int(round(s.width / s.pixel))
        self.H = int(round(s.depth / s.pixel))
        self.depths = (np.arange(self.H) + 0.5) * s.pixel  # (H,) mm below the face
        self.lateral = s.face[0] + (np.arange(self.W) - (self.W - 1) / 2) * s.pixel  # (W,) world x
        self.gain = 10.0 ** (-s.attenuation * self.depths / 20.0)  # (H,)
        self._bank: np.ndarray | None = None

    @property
    def pixel(self) -> float:
        return self.settings.pixel

    def shaft_extent(self):
        return self.settings.plane_offset + 2.0, 0.1

    def poses(self) -> list[Pose]:
        """The needle below the probe's centre at depths from 1/8 to 7/8 of the image, tilted 0, 10 and
        20 deg from the insertion axis z toward the probe (the error includes the plane's offset)."""
        s = self.settings
        out = []
        for k in (1, 3, 5, 7):
            depth = s.depth * k / 8
            for tilt in (0, 10, 20):
                t = np.radians(tilt)
                out.append(Pose((s.face[0], s.face[1] - depth, 50.0), (0.0, np.sin(t), np.cos(t)), 20.0,
                                {"Depth [mm]": round(depth, 1), "Tilt [deg]": tilt}))
        return out

    # ------------------------------------------------------------------ geometry
    def cross_section(self, g: NeedleGeometry) -> tuple[np.ndarray, np.ndarray]:
        """Where the shaft crosses the image plane: ``(x, y) (B, 2)`` mm and whether it does ``(B,)``."""
        z_plane = g.tip[:, 2] - self.settings.plane_offset
        z = g.shaft[..., 2]  # (B, K), decreasing backwards along the shaft
        below = z <= z_plane[:, None]
        has = below.any(axis=1)
        k = np.argmax(below, axis=1)  # first shaft point at or behind the plane
        km = np.maximum(k - 1, 0)
        rows = np.arange(len(k))
        z1, z0 = z[rows, k], z[rows, km]
        f = np.where(np.abs(z0 - z1) > 1e-12, (z0 - z_plane) / (z0 - z1 + 1e-300), 0.0)
        f = np.clip(np.where(k == 0, 0.0, f), 0.0, 1.0)
        p = g.shaft[rows, km] * (1 - f)[:, None] + g.shaft[rows, k] * f[:, None]
        vis = g.visible[rows, k] & g.visible[rows, km] & has
        return p[:, :2], vis

    # ------------------------------------------------------------------ rendering
    def speckle(self, rng: np.random.Generator, n: int) -> np.ndarray:
        """``n`` speckle windows ``(n, H, W)`` from a periodic texture made once."""
        s = self.settings
        if self._bank is None:
            size = int(2 ** np.ceil(np.log2(max(self.H, self.W, 64))))
            self._bank = np.tile(periodic_speckle(rng, (size, size), (s.psf[1] / s.pixel, s.psf[0] / s.pixel)), (2, 2))
        P = self._bank.shape[0] // 2
        out = np.empty((n, self.H, self.W), dtype=np.float32)
        tiled = self._bank
        for i, (oy, ox) in enumerate(rng.integers(0, P, size=(n, 2))):
            out[i] = tiled[oy : oy + self.H, ox : ox + self.W]
        return out

    def render(self, g: NeedleGeometry, rng: np.random.Generator) -> np.ndarray:
        """B-mode frames ``(B, H, W)`` uint8 of the needles ``g``."""
        s = self.settings
        B = g.shaft.shape[0]
        xy, present = self.cross_section(g)
        tissue = np.ones((B, self.H, self.W), dtype=np.float32)
        if s.noise > 0:
            tissue += np.float32(s.noise) * (self.speckle(rng, B) - 1.0)
        # needle: separable lateral x axial profiles
        r = s.needle_radius
        sl = np.hypot(s.psf[0], 0.5 * r)
        lat = np.exp(-0.5 * ((self.lateral[None, :] - xy[:, :1]) / sl) ** 2)  # (B, W)
        d_wall = (s.face[1] - xy[:, 1]) - r  # depth of the near wall
        dz = self.depths[None, :] - d_wall[:, None]  # (B, H)
        ax = np.exp(-0.5 * (dz / s.psf[1]) ** 2)
        period = 2.0 * r
        n_rings = int(np.ceil(4 * s.tail_length / period))
        for j in range(1, n_rings + 1):
            amp = s.tail_level * np.exp(-(j - 1) * period / s.tail_length)
            ax += amp * np.exp(-0.5 * ((dz - j * period) / s.psf[1]) ** 2)
        ax *= present[:, None]
        echo = tissue + np.float32(s.needle_echo) * (ax[:, :, None] * lat[:, None, :]).astype(np.float32)
        echo *= self.gain[None, :, None].astype(np.float32)
        if s.noise > 0 and s.noise_level > 0:
            sd = np.float32(s.noise * s.noise_level / np.sqrt(2))
            n1 = rng.standard_normal(echo.shape, dtype=np.float32)
            n2 = rng.standard_normal(echo.shape, dtype=np.float32)
            echo = np.sqrt((echo + sd * n1) ** 2 + (sd * n2) ** 2)  # envelope of echo + complex noise
        return log_compress(echo, s.needle_echo, s.dynamic_range)

    # ------------------------------------------------------------------ measurement
    def detect(self, frames: np.ndarray, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """RANSAC tip finding on frames ``(B, H, W)`` uint8.

        Returns ``(xy (B, 2) mm world, valid (B,), px (B, 2) (column, row))``.
        """
        s = self.settings
        B, H, W = frames.shape
        img = frames.astype(np.float32)
        img = blur_axis(blur_axis(img, 1, 0.6), 2, 0.6)
        step = max(1, W // 64)  # the row's median from every step-th column
        comp = img - np.median(img[:, :, ::step], axis=2, keepdims=True)  # log domain: ratio to the row's median
        thr = s.threshold_db * 255.0 / s.dynamic_range
        K = min(s.candidates, H * W)
        flat = comp.reshape(B, -1)
        idx = np.argpartition(-flat, K - 1, axis=1)[:, :K]
        val = np.take_along_axis(flat, idx, 1)
        order = np.argsort(-val, axis=1)
        idx, val = np.take_along_axis(idx, order, 1), np.take_along_axis(val, order, 1)
        ok = val > thr  # (B, K), valid candidates first
        n_ok = ok.sum(1)
        pts = np.stack([idx % W, idx // W], -1).astype(float)  # (B, K, 2) column, row
        # hypotheses: pairs of valid candidates
        Hh = s.ransac_iterations
        u = rng.random((B, Hh, 2))
        pick = np.minimum((u * np.maximum(n_ok, 1)[:, None, None]).astype(np.int64), K - 1)
        p1 = np.take_along_axis(pts, pick[..., 0:1].repeat(2, -1), 1)  # (B, Hh, 2)
        p2 = np.take_along_axis(pts, pick[..., 1:2].repeat(2, -1), 1)
        d = p2 - p1
        nd = np.linalg.norm(d, axis=-1)
        good = (nd > 0.5) & (np.abs(d[..., 0]) <= np.sin(np.radians(s.max_tilt)) * nd)
        dn = d / np.maximum(nd, 1e-9)[..., None]
        rel = pts[:, None, :, :] - p1[:, :, None, :]  # (B, Hh, K, 2)
        dist = np.abs(rel[..., 0] * dn[..., None, 1] - rel[..., 1] * dn[..., None, 0])
        tol = s.ransac_tolerance / s.pixel
        inl = (dist < tol) & ok[:, None, :] & good[..., None]
        count = inl.sum(-1)
        best = np.argmax(count, axis=1)
        n_in = count[np.arange(B), best]
        inliers = inl[np.arange(B), best]  # (B, K)
        valid = n_in >= s.min_inliers
        # line column = a + b row, weighted least squares on the inliers
        w = np.where(inliers, np.maximum(val - thr, 0) + 1.0, 0.0)
        sw = np.maximum(w.sum(1), 1e-9)
        mv = (w * pts[..., 1]).sum(1) / sw
        mu = (w * pts[..., 0]).sum(1) / sw
        cvv = (w * (pts[..., 1] - mv[:, None]) ** 2).sum(1) / sw
        cuv = (w * (pts[..., 1] - mv[:, None]) * (pts[..., 0] - mu[:, None])).sum(1) / sw
        b = np.where(cvv > 1e-6, cuv / np.maximum(cvv, 1e-6), 0.0)
        a = mu - b * mv
        # profile along the line; the wall echo is its maximum within the inliers' rows
        rows = np.arange(H, dtype=float)
        cols = np.clip(a[:, None] + b[:, None] * rows[None, :], 0, W - 1)  # (B, H)
        c0 = np.floor(cols).astype(np.int64)
        c1 = np.minimum(c0 + 1, W - 1)
        fc = cols - c0
        bi = np.arange(B)[:, None]
        ri = np.arange(H)[None, :]
        prof = comp[bi, ri, c0] * (1 - fc) + comp[bi, ri, c1] * fc
        vmin = np.where(inliers, pts[..., 1], np.inf).min(1)
        vmax = np.where(inliers, pts[..., 1], -np.inf).max(1)
        span = (rows[None, :] >= vmin[:, None] - 3) & (rows[None, :] <= vmax[:, None] + 3)
        prof_m = np.where(span, prof, -np.inf)
        vpk = np.argmax(prof_m, axis=1)
        v_sub = vpk + _parabola(prof, vpk)
        # lateral peak on that row, near the line
        lat = comp[np.arange(B), vpk]  # (B, W)
        cl = np.clip(np.rint(a + b * vpk).astype(np.int64), 0, W - 1)
        near = np.abs(np.arange(W)[None, :] - cl[:, None]) <= 3
        upk = np.argmax(np.where(near, lat, -np.inf), axis=1)
        u_sub = upk + _parabola(lat, upk)
        x = s.face[0] + (u_sub - (W - 1) / 2) * s.pixel
        depth = (v_sub + 0.5) * s.pixel + s.needle_radius
        y = s.face[1] - depth
        valid &= np.isfinite(x) & np.isfinite(y)
        return np.stack([x, y], -1), valid, np.stack([u_sub, v_sub], -1)

    def to_px(self, xy: np.ndarray) -> np.ndarray:
        """World ``(x, y)`` of a cross-section centre -> pixel (column, row) of its near-wall echo."""
        s = self.settings
        u = (xy[..., 0] - s.face[0]) / s.pixel + (self.W - 1) / 2
        v = (s.face[1] - xy[..., 1] - s.needle_radius) / s.pixel - 0.5
        return np.stack([u, v], -1)

    def run(self, geometry, times, n_runs, rng, frames: FrameStore | None = None, on_frame=None) -> DeviceResult:
        M = len(times)
        tip = np.full((n_runs, M, 3), np.nan)
        valid = np.zeros((n_runs, M), dtype=bool)
        for j in range(M):
            g = geometry(j)
            img = self.render(g, rng)
            xy, ok, px = self.detect(img, rng)
            tip[:, j, :2] = np.where(ok[:, None], xy, np.nan)
            valid[:, j] = ok
            if frames is not None:
                true_xy, _ = self.cross_section(g)
                for r in frames.wanted(j):
                    if r < n_runs:
                        frames.add(int(r), j, img[r], px[r] if ok[r] else np.full(2, np.nan), self.to_px(true_xy[r]))
            if on_frame is not None:
                on_frame(j, {"tip": tip[:, j], "valid": valid[:, j]})
        return DeviceResult(tip=tip, valid=valid)


def _parabola(prof: np.ndarray, k: np.ndarray) -> np.ndarray:
    """Sub-sample offset of the peak at ``k (B,)`` of ``prof (B, L)`` from a parabola through 3 samples."""
    L = prof.shape[1]
    km, kp = np.clip(k - 1, 0, L - 1), np.clip(k + 1, 0, L - 1)
    r = np.arange(len(k))
    y0, y1, y2 = prof[r, km], prof[r, k], prof[r, kp]
    den = y0 - 2 * y1 + y2
    off = np.where((den < 0) & np.isfinite(den), 0.5 * (y0 - y2) / np.where(den < 0, den, -1.0), 0.0)
    return np.clip(off, -0.5, 0.5)
