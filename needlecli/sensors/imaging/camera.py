"""Overhead camera over the agar phantom (the magnetic needle EM paper, sec. 2.3.2), rendered and measured with OpenCV.

Rendering (grey levels, 0..255): a light agar background with vignetting, a low-frequency texture and a
few dark specks (bubbles, debris; fixed for a run), the silicone sheath and nitinol wire along the path
behind the tip, and the magnetic tip as a dark 7 x 1 mm rectangle from the state position ``p`` forward
along the heading (``p`` is the tip's trailing end, where the wire joins: the magnetic needle EM paper computes ``p`` by
offsetting half the tip length from the silhouette centre toward the wire). The needle's darkness fades
with its depth below the agar surface, ``c = exp(-(surface_z - z) / clarity)``: this is the opacity
signal. Per-frame sensor noise is added last.

Measurement (the magnetic needle EM paper): 8-bit grey; binary threshold at the needle's grey level + 5 (seeded at a clicked
pixel, then updated from the detected centre every frame: the "adaptive" threshold); open then close;
``cv2.findContours``; ``cv2.minAreaRect`` of the silhouette: its centre is the tip centre and its long
axis the heading, whose sign points away from the trailing wire (the darker end); ``p`` = centre - half
the tip length along the heading; pixels to world by the calibration. OpenCV has no batch API for
contours, so frames are drawn and measured one at a time (a Python loop over frames); the geometry,
calibration and the opacity rule are vectorised over runs.

Opacity: the grey level at the detected centre; the out-of-plane rule of the magnetic needle EM paper's eq. (7),
``B_z = 2.0 mT * (opacity - opacity_0)`` saturated at +-28 mT (:func:`bz_command`), ``opacity_0`` the
opacity at a run's first detection. Both are stored per sample (``opacity``, ``bz_command``). The loop is
closed by a controller (config section ``control:``, type ``opacity_bz``, :mod:`needlecli.control`): the
camera then measures frame by frame while the truth is simulated (``run``'s ``on_frame`` hands each
frame's opacity to the controller, which sets the field's out-of-plane component from its availability
time on); without one the command is only recorded.
"""

from __future__ import annotations

from typing import Literal

import cv2
import numpy as np
from pydantic import Field, model_validator

from needlecli.schema import NonNeg, Positive
from needlecli.sensors.imaging.base import DEVICES, Device, ImageSettings, Pose
from needlecli.sensors.imaging.render import DeviceResult, FrameStore

_SHIFT = 4  # sub-pixel bits of OpenCV's drawing functions
_ONE = 1 << _SHIFT
_NOISE_MEAN = 32  # noise images are stored as uint8 around this level (added with saturation)


def bz_command(opacity: np.ndarray, opacity_0: np.ndarray, *, gain: float = 2.0, limit: float = 28.0) -> np.ndarray:
    """Out-of-plane field command of the magnetic needle EM paper's eq. (7), mT: ``clip(gain (opacity - opacity_0), -limit, limit)``.

    Parameters
    ----------
    opacity, opacity_0 : grey levels (0..255) at the tip now and at the initial insertion point
        (broadcastable; NaN gives NaN)
    gain : mT per grey level (the magnetic needle EM paper: 2.0)
    limit : saturation, mT (the coils' 28 mT)
    """
    return np.clip(gain * (np.asarray(opacity, dtype=float) - opacity_0), -limit, limit)


class CameraSettings(ImageSettings):
    """Overhead camera of the magnetic needle EM paper: 800 x 668 px over 90 x 75 mm (about 0.11 mm per pixel), 6 Hz."""

    device: Literal["camera"] = Field(description="the imaging device: camera, the magnetic needle EM paper's overhead camera")
    size: tuple[int, int] = Field((800, 668), description="frame width, height, px")
    fov: tuple[Positive, Positive] = Field((90.0, 75.0), description="field of view in x, y, mm")
    center: tuple[float, float] = Field((0.0, -30.0), description="world x, y (mm) at the frame centre (the magnetic needle EM paper: "
                                        "the needle enters at the top centre, x = 0, and goes down, -y)")
    background: float = Field(200.0, ge=0, le=255, description="grey level of the agar")
    vignetting: NonNeg = Field(0.08, le=0.9, description="relative darkening at the frame corners")
    texture: NonNeg = Field(3.0, description="std of the agar's low-frequency texture, grey levels")
    specks: NonNeg = Field(6.0, description="mean number of dark specks (bubbles, debris) per run")
    pixel_noise: NonNeg = Field(1.0, description="sensor noise std per frame, grey levels")
    tip_length: Positive = Field(7.0, description="length of the magnetic tip, mm")
    tip_diameter: Positive = Field(1.0, description="diameter of the magnetic tip, mm")
    sheath_diameter: Positive = Field(1.65, description="silicone sheath around the wire, mm")
    wire_diameter: Positive = Field(0.25, description="nitinol wire, mm")
    tip_grey: float = Field(20.0, ge=0, le=255, description="grey level of the tip right under the agar surface")
    sheath_shade: NonNeg = Field(0.25, le=1, description="darkening of the translucent sheath relative to the tip")
    wire_shade: NonNeg = Field(0.6, le=1, description="darkening of the wire relative to the tip")
    surface_z: float = Field(7.0, description="world z of the agar's top surface, mm (the slab is 14 mm thick)")
    clarity: Positive = Field(10.0, description="depth below the surface at which the contrast falls by 1/e, mm")
    click: tuple[int, int] | None = Field(
        None, description="pixel (column, row) clicked on the needle; default: the tip's centre in the first frame "
        "that shows it")
    threshold_offset: float = Field(5.0, ge=0, description="threshold = needle grey level + this (the magnetic needle EM paper: 5)")
    center_window: int = Field(3, ge=1, le=9, description="odd window (px) over which the centre grey level is read")
    kernel: int = Field(5, ge=1, le=31, description="size of the open / close structuring element, px")
    area_range: tuple[Positive, Positive] = Field(
        (0.6, 2.0), description="accepted silhouette area as a fraction of the tip's expected area")
    wire_contrast: NonNeg = Field(2.0, description="grey levels by which the wire end must be darker to set the heading")
    opacity_gain: float = Field(2.0, description="mT per grey level (the magnetic needle EM paper's eq. 7)")
    bz_limit: Positive = Field(28.0, description="saturation of the out-of-plane command, mT")
    calibration_scale: float = Field(0.0, ge=-0.1, le=0.1, description="relative scale error of the calibration")
    calibration_offset: tuple[float, float] = Field((0.0, 0.0), description="offset error of the calibration, mm")

    @model_validator(mode="after")
    def _odd(self):
        if self.center_window % 2 == 0:
            raise ValueError("center_window must be odd")
        return self


@DEVICES.register("camera")
class OverheadCamera(Device):
    """The magnetic needle EM paper's overhead camera: tip position ``(x, y)``, heading, opacity (see the module docstring)."""

    Settings = CameraSettings
    axes = ("x", "y")

    def __init__(self, settings: CameraSettings) -> None:
        super().__init__(settings)
        s = settings
        self.W, self.H = s.size
        self.sx, self.sy = s.fov[0] / self.W, s.fov[1] / self.H  # mm per px
        self.kernel = cv2.getStructuringElement(cv2.MORPH_RECT, (s.kernel, s.kernel))
        self.tip_area_px = (s.tip_length / self.sx) * (s.tip_diameter / self.sy)
        self._banks: list[np.ndarray] | None = None
        self._shading: np.ndarray | None = None

    @property
    def pixel(self) -> float:
        return float(max(self.sx, self.sy))

    def shaft_extent(self):
        # the wire across the whole field of view
        return float(np.hypot(*self.settings.fov)), 1.0

    # ------------------------------------------------------------------ calibration
    def world_to_px(self, xy: np.ndarray) -> np.ndarray:
        """True projection (what the rendering uses): world ``(..., 2+)`` mm -> pixel (column, row)."""
        xy = np.asarray(xy, dtype=float)
        u = (xy[..., 0] - self.settings.center[0]) / self.sx + (self.W - 1) / 2
        v = (self.settings.center[1] - xy[..., 1]) / self.sy + (self.H - 1) / 2
        return np.stack([u, v], -1)

    def px_to_world(self, uv: np.ndarray) -> np.ndarray:
        """The pipeline's calibration (with its configured errors): pixel ``(..., 2)`` -> world mm."""
        s = self.settings
        k = 1.0 + s.calibration_scale
        uv = np.asarray(uv, dtype=float)
        x = (uv[..., 0] - (self.W - 1) / 2) * self.sx * k + s.center[0] + s.calibration_offset[0]
        y = s.center[1] - (uv[..., 1] - (self.H - 1) / 2) * self.sy * k + s.calibration_offset[1]
        return np.stack([x, y], -1)

    def contrast(self, z: np.ndarray) -> np.ndarray:
        """How dark the needle looks at depth ``z`` (mm, world): 1 at the agar surface."""
        s = self.settings
        return np.exp(-np.clip(s.surface_z - np.asarray(z, dtype=float), 0.0, None) / s.clarity)

    # ------------------------------------------------------------------ rendering
    def background(self, rng: np.random.Generator) -> np.ndarray:
        """The agar of one run (fixed over the run), uint8 ``(H, W)``, minus the noise images' mean."""
        s = self.settings
        H, W = self.H, self.W
        if self._shading is None:  # vignetting, the same for every run
            yy, xx = np.mgrid[0:H, 0:W].astype(np.float32)
            r2 = ((xx - (W - 1) / 2) / (W / 2)) ** 2 + ((yy - (H - 1) / 2) / (H / 2)) ** 2
            self._shading = (s.background * (1.0 - s.vignetting * r2 / 2.0)).astype(np.float32)
        img = self._shading
        if s.texture > 0 and s.noise > 0:
            low = rng.standard_normal((12, 14)).astype(np.float32)
            img = img + s.noise * s.texture * cv2.resize(low, (W, H), interpolation=cv2.INTER_CUBIC)
        img = np.clip(img - _NOISE_MEAN, 0, 255).astype(np.uint8)
        if s.specks > 0 and s.noise > 0:
            for _ in range(rng.poisson(s.specks)):
                c = (int(rng.integers(0, W)), int(rng.integers(0, H)))
                rad = int(rng.integers(1, 6))
                grey = int(np.clip(s.background * rng.uniform(0.3, 0.8) - _NOISE_MEAN, 0, 255))
                cv2.circle(img, c, rad, grey, -1, cv2.LINE_AA)
        return img

    def _noise_crop(self, rng: np.random.Generator) -> np.ndarray:
        """Per-frame sensor noise: a random window of two noise images made once (uint8 around 32)."""
        s = self.settings
        pad = 64
        if self._banks is None:
            sd = s.noise * s.pixel_noise
            self._banks = [
                np.clip(np.rint(_NOISE_MEAN + sd * rng.standard_normal((self.H + pad, self.W + pad))), 0, 255).astype(np.uint8)
                for _ in range(2)
            ]
        b = self._banks[int(rng.integers(0, 2))]
        oy, ox = (int(v) for v in rng.integers(0, pad, size=2))
        return b[oy : oy + self.H, ox : ox + self.W]

    def draw(self, bg: np.ndarray, shaft: np.ndarray, visible: np.ndarray, tangent: np.ndarray,
             noise: np.ndarray | None) -> np.ndarray:
        """One frame (uint8 ``(H, W)``): the needle of one run (``shaft (K, 3)`` mm from the tip back,
        ``visible (K,)``, ``tangent (3,)``) drawn on its background, then the noise added."""
        s = self.settings
        img = bg.copy()
        p = shaft[0]
        c = float(self.contrast(p[2]))
        dark = (s.background - s.tip_grey) * c
        base = s.background - _NOISE_MEAN
        pts = shaft[visible]
        if len(pts) >= 2:
            uv = np.rint(self.world_to_px(pts) * _ONE).astype(np.int32)
            sheath = max(1, int(round(s.sheath_diameter / self.sx)))
            wire = max(1, int(round(s.wire_diameter / self.sx)))
            cv2.polylines(img, [uv], False, float(np.clip(base - dark * s.sheath_shade, 0, 255)), sheath,
                          cv2.LINE_AA, _SHIFT)
            cv2.polylines(img, [uv], False, float(np.clip(base - dark * s.wire_shade, 0, 255)), wire,
                          cv2.LINE_AA, _SHIFT)
        if visible[0]:
            q = p + s.tip_length * tangent
            a, b = self.world_to_px(p), self.world_to_px(q)
            d = b - a
            n = np.array([-d[1], d[0]]) / max(np.hypot(*d), 1e-9) * (s.tip_diameter / 2 / self.sy)
            corners = np.array([a + n, b + n, b - n, a - n])
            cv2.fillConvexPoly(img, np.rint(corners * _ONE).astype(np.int32),
                               float(np.clip(base - dark, 0, 255)), cv2.LINE_AA, _SHIFT)
        if noise is not None:
            return cv2.add(img, noise)
        return cv2.add(img, np.full_like(img, _NOISE_MEAN))

    def poses(self) -> list[Pose]:
        """The tip's centre at the frame centre and at two quarter points, headings 0, 30, 60 and 90 deg,
        3.5, 7 and 10.5 mm below the agar surface (rows aggregate the three positions)."""
        s = self.settings
        cx, cy = s.center
        spots = [(cx, cy), (cx - 0.25 * s.fov[0], cy + 0.25 * s.fov[1]), (cx + 0.25 * s.fov[0], cy - 0.25 * s.fov[1])]
        out = []
        for depth in (3.5, 7.0, 10.5):
            for heading in (0, 30, 60, 90):
                h = np.array([np.cos(np.radians(heading)), np.sin(np.radians(heading)), 0.0])
                for x, y in spots:
                    p = np.array([x, y, s.surface_z - depth]) - 0.5 * s.tip_length * h
                    out.append(Pose(tuple(p), tuple(h), 30.0,
                                    {"Depth below surface [mm]": depth, "Heading [deg]": heading}))
        return out

    # ------------------------------------------------------------------ measurement
    def grey_at(self, img: np.ndarray, uv: np.ndarray) -> float:
        """Mean grey level of the ``center_window`` around pixel ``uv`` (column, row)."""
        h = self.settings.center_window // 2
        u, v = int(round(uv[0])), int(round(uv[1]))
        win = img[max(v - h, 0) : v + h + 1, max(u - h, 0) : u + h + 1]
        return float(win.mean()) if win.size else float("nan")

    def detect(self, img: np.ndarray, threshold: float, near: np.ndarray, heading: np.ndarray | None):
        """The magnetic needle EM paper's pipeline on one grey frame.

        Parameters
        ----------
        img : (H, W) uint8
        threshold : grey level; pixels at or below it are the needle
        near : (2,) pixel the silhouette should be closest to (previous centre or the click)
        heading : (2,) previous heading in pixel axes (column, row), or None

        Returns
        -------
        None when there is no measurement, else ``(centre_px (2,), heading_px (2,))``: the silhouette's
        rectangle centre and its long axis pointing from the wire to the tip.
        """
        s = self.settings
        _, mask = cv2.threshold(img, threshold, 255, cv2.THRESH_BINARY_INV)
        mask = cv2.morphologyEx(mask, cv2.MORPH_OPEN, self.kernel)
        mask = cv2.morphologyEx(mask, cv2.MORPH_CLOSE, self.kernel)
        contours, _ = cv2.findContours(mask, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
        lo, hi = s.area_range[0] * self.tip_area_px, s.area_range[1] * self.tip_area_px
        best, best_d = None, np.inf
        for cnt in contours:
            area = cv2.contourArea(cnt)
            if not lo <= area <= hi:
                continue
            x, y, w, h = cv2.boundingRect(cnt)
            if x <= 0 or y <= 0 or x + w >= self.W or y + h >= self.H:  # cut by the frame's edge
                continue
            rect = cv2.minAreaRect(cnt)
            d = np.hypot(rect[0][0] - near[0], rect[0][1] - near[1])
            if d < best_d:
                best, best_d = rect, d
        if best is None:
            return None
        box = cv2.boxPoints(best)
        e1, e2 = box[1] - box[0], box[2] - box[1]
        axis = e1 if np.hypot(*e1) >= np.hypot(*e2) else e2
        length = float(np.hypot(*axis))
        if length <= 0:
            return None
        axis = axis / length
        centre = np.array(best[0], dtype=float)
        # the wire's end is the darker one just beyond the silhouette
        off = length / 2 + 0.5 * s.sheath_diameter / self.sx + 1.0
        g_plus = self.grey_at(img, centre + off * axis)
        g_minus = self.grey_at(img, centre - off * axis)
        if np.isfinite(g_plus) and np.isfinite(g_minus) and abs(g_plus - g_minus) >= s.wire_contrast:
            sign = 1.0 if g_minus < g_plus else -1.0  # heading points away from the wire
        elif heading is not None:
            sign = 1.0 if float(axis @ heading) >= 0 else -1.0
        else:
            return None
        return centre, sign * axis

    def run(self, geometry, times, n_runs, rng, frames: FrameStore | None = None, on_frame=None) -> DeviceResult:
        s = self.settings
        M = len(times)
        tip = np.full((n_runs, M, 3), np.nan)
        valid = np.zeros((n_runs, M), dtype=bool)
        opacity = np.full((n_runs, M), np.nan)
        heading_out = np.full((n_runs, M, 2), np.nan)
        centre_out = np.full((n_runs, M, 2), np.nan)
        threshold = np.full(n_runs, np.nan)
        near = np.full((n_runs, 2), np.nan)
        prev_heading: list[np.ndarray | None] = [None] * n_runs
        op0 = np.full(n_runs, np.nan)
        backgrounds: dict[int, np.ndarray] = {}
        rng_scene = np.random.default_rng(rng.integers(2**63))
        for j in range(M):
            g = geometry(j)
            keep = set(frames.wanted(j).tolist()) if frames is not None else set()
            centre_true = g.tip[:, :2] + 0.5 * s.tip_length * g.tangent[:, :2]
            true_px = self.world_to_px(centre_true)
            for r in range(n_runs):
                if r not in backgrounds:
                    backgrounds[r] = self.background(rng_scene)
                noise = self._noise_crop(rng) if s.noise > 0 and s.pixel_noise > 0 else None
                img = self.draw(backgrounds[r], g.shaft[r], g.visible[r], g.tangent[r], noise)
                if np.isnan(threshold[r]):  # the operator clicks the needle
                    if s.click is not None:
                        click = np.array(s.click, dtype=float)
                    elif g.visible[r, 0] and np.all((true_px[r] > 0) & (true_px[r] < (self.W - 1, self.H - 1))):
                        click = true_px[r]
                    else:
                        click = None
                    if click is not None:
                        threshold[r] = self.grey_at(img, click) + s.threshold_offset
                        near[r] = click
                found = None
                if np.isfinite(threshold[r]):
                    found = self.detect(img, threshold[r], near[r], prev_heading[r])
                if found is not None:
                    c_px, h_px = found
                    c_w = self.px_to_world(c_px)
                    h_w = np.array([h_px[0] * self.sx, -h_px[1] * self.sy])
                    h_w /= np.linalg.norm(h_w)
                    tip[r, j, :2] = c_w - 0.5 * s.tip_length * h_w
                    valid[r, j] = True
                    heading_out[r, j] = h_w
                    centre_out[r, j] = c_px
                    op = self.grey_at(img, c_px)
                    opacity[r, j] = op
                    if np.isnan(op0[r]):
                        op0[r] = op
                    threshold[r] = op + s.threshold_offset  # adaptive: from the current centre
                    near[r] = c_px
                    prev_heading[r] = h_px
                if r in keep and frames is not None:
                    tip_px = self.world_to_px(tip[r, j, :2]) if valid[r, j] else np.full(2, np.nan)
                    frames.add(r, j, img, tip_px, self.world_to_px(g.tip[r, :2]))
            if on_frame is not None:  # every run's frame j is measured: a controller may act on it
                on_frame(j, {"tip": tip[:, j], "valid": valid[:, j], "opacity": opacity[:, j]})
        extras = {
            "opacity": opacity,
            "bz_command": bz_command(opacity, op0[:, None], gain=s.opacity_gain, limit=s.bz_limit),
            "heading": heading_out,
            "centre_px": centre_out,
        }
        return DeviceResult(tip=tip, valid=valid, extras=extras)
