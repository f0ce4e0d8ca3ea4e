"""3D ultrasound volumes from a motorised end-fire probe at a fixed pose (the multi-rate UKF paper), tip by segmentation.

Probe: the transducer at ``transducer`` looks along ``axis``; the volume is the cone of half-angle
``half_angle`` around it up to the acquisition depth ``max_depth`` (the multi-rate UKF paper: 80 mm), scan-converted to
cubic voxels of ``voxel`` mm (0.4 mm) on a world-aligned lattice. Beams fan out from the transducer: the
beam at a point runs along the line from the transducer to it.

Rendering (B-mode, 8 bit after log compression), vectorised over runs:

* tissue speckle fixed to the phantom (static tissue, fixed probe): a periodic speckle texture indexed by
  world voxel, at a random offset per run;
* the needle shaft as a bright line, the convolution of the shaft (a polyline of short straight pieces
  following the tip's path) with an anisotropic point-spread function: ``psf_axial`` along the beam,
  ``psf_lateral (1 + lateral_growth d / max_depth)`` across it (the beam widens with the distance ``d``
  from the transducer). Its echo falls with the angle ``theta`` between needle and beam (specular
  reflection, the multi-rate UKF paper's sec. 2.1): ``needle_echo (floor + (1 - floor) sin(theta)^power)``, spread over
  the wider beam far away;
* artefacts: a reverberation tail behind the needle along the beam, and bright clutter blobs;
* electronic noise, amplified with depth by the time-gain compensation (``attenuation`` dB/mm).

Only part of a volume is rendered (a volume of 0.4 mm voxels over the whole cone is ~10^7 voxels):
``roi_size`` mm around a predicted tip at full resolution. The prediction is the sensor's own: the
previous detection extrapolated with the velocity of the last two detections; before the first
detection a configured ``roi_prior``; without either, or after ``lost_after`` samples without a
detection, the whole volume is searched coarse-to-fine: rendered with voxels ``coarse`` times larger as
the block maximum of the full-resolution volume (max-pooling keeps a thin bright needle that block means
would average into the speckle: the speckle texture max-pooled, the shaft's peak echo in every block it
crosses), segmented, then the full-resolution region around the coarse tip. An observer's prediction is
not available to sensors in this architecture (sensors measure before observers run).

Segmentation (per region, all runs at once): voxels brighter than the volume's median by
``threshold_db``; a weighted principal axis refined twice on the voxels within ``inlier_radius`` of it
(robust to clutter); the intensity profile along that axis; the tip is where the profile falls to half
the shaft's level at the end farther along the ``insertion`` direction. No measurement when the bright segment is
shorter than ``min_length``, not elongated, or when the tip is not inside the region.
"""

from __future__ import annotations

import warnings
from typing import Literal

import numpy as np
from pydantic import Field, field_validator

from needlecli.schema import NonNeg, Positive
from needlecli.sensors.imaging.base import DEVICES, Device, ImageSettings, Pose
from needlecli.sensors.imaging.render import (
    DeviceResult,
    FrameStore,
    NeedleGeometry,
    block_max,
    log_compress,
    log_expand,
    periodic_speckle,
    tile_take,
)

Vec3 = tuple[float, float, float]
_BANK = 64  # period of the speckle texture, voxels
_REFINE = 4  # refinements of the axis
_SPECKLE_DB = 5.57  # std of fully developed speckle in dB (robust: 1.4826 MAD)


class EndFireUltrasoundSettings(ImageSettings):
    """3D end-fire ultrasound at 1 Hz (the multi-rate UKF paper: 4DEC-9/10 on a Sonix RP, 0.4 mm voxels)."""

    device: Literal["us3d"] = Field(description="the imaging device: us3d, 3D end-fire ultrasound volumes (the multi-rate UKF paper)")
    voxel: Positive = Field(0.4, description="voxel edge, mm")
    transducer: Vec3 = Field((0.0, -50.0, 40.0), description="world position of the transducer, mm")
    axis: Vec3 = Field((0.0, 1.0, 0.0), description="direction the probe looks along")
    half_angle: float = Field(60.0, gt=0, lt=90, description="half-angle of the imaged cone, deg")
    max_depth: Positive = Field(80.0, description="acquisition depth d_max, mm (the multi-rate UKF paper: 80)")
    psf_lateral: Positive = Field(1.0, description="lateral std of the point-spread function at the transducer, mm")
    lateral_growth: NonNeg = Field(1.0, description="lateral std grows as (1 + lateral_growth d / max_depth)")
    psf_axial: Positive = Field(0.4, description="axial std of the point-spread function, mm")
    needle_echo: Positive = Field(10.0, description="needle echo relative to the mean tissue echo, needle across the beam")
    visibility_floor: float = Field(0.4, ge=0, le=1, description="relative echo of a needle along the beam")
    visibility_power: Positive = Field(2.0, description="echo ~ floor + (1 - floor) sin(theta)^power")
    attenuation: NonNeg = Field(0.15, description="two-way attenuation compensated by the gain, dB/mm (noise grows)")
    noise_level: NonNeg = Field(0.2, description="electronic noise std relative to the mean tissue echo at the transducer")
    reverb_level: NonNeg = Field(0.3, description="reverberation tail behind the needle, relative to its echo")
    reverb_length: Positive = Field(1.0, description="e-folding length of the reverberation tail, mm")
    clutter: NonNeg = Field(0.1, description="bright clutter blobs fixed in the phantom, mean number per cm^3")
    clutter_level: NonNeg = Field(4.0, description="echo of a clutter blob relative to the mean tissue echo")
    clutter_size: Positive = Field(0.8, description="std of a clutter blob, mm")
    dynamic_range: Positive = Field(50.0, description="display dynamic range, dB")
    visible_from: float = Field(-10.0, le=0, description="arc length from which the shaft shows, mm (negative: "
                                "pre-inserted, as the initialisation volume of the multi-rate UKF paper)")
    roi_size: Positive = Field(12.0, description="edge of the region rendered and segmented at full resolution, mm")
    roi_prior: Vec3 | None = Field(None, description="where to look before the first detection (default: search)")
    coarse: int = Field(4, ge=2, le=8, description="voxel factor of the coarse search level")
    lost_after: int = Field(2, ge=1, description="samples without a detection before the whole volume is searched")
    threshold_db: Positive = Field(12.0, description="segmented voxels: brighter than the volume's median by this, dB")
    inlier_radius: Positive = Field(2.0, description="voxels within this of the axis refine it, mm")
    min_length: Positive = Field(3.0, description="shortest bright segment accepted as the needle, mm (at least 4 voxels)")
    min_elongation: Positive = Field(1.8, description="ratio of the axis' spread to the largest cross spread")
    insertion: Vec3 = Field((0.0, 0.0, 1.0), description="direction of insertion: the tip is the end of the "
                            "segmented shaft farther along it")

    @field_validator("axis", "insertion")
    @classmethod
    def _unit(cls, v):
        if np.linalg.norm(v) == 0:
            raise ValueError("must not be the zero vector")
        return v


@DEVICES.register("us3d")
class EndFireUltrasound(Device):
    """The multi-rate UKF paper's 3D end-fire ultrasound: tip ``(x, y, z)`` (see the module docstring)."""

    Settings = EndFireUltrasoundSettings
    axes = ("x", "y", "z")

    def __init__(self, settings: EndFireUltrasoundSettings) -> None:
        super().__init__(settings)
        s = settings
        self.h = s.voxel
        self.tr = np.asarray(s.transducer, dtype=float)
        self.ax = np.asarray(s.axis, dtype=float) / np.linalg.norm(s.axis)
        self.cos_half = np.cos(np.radians(s.half_angle))
        self.n_roi = max(8, int(round(s.roi_size / self.h)))
        # the cone's bounding box on the coarse lattice
        hc = self.h * s.coarse
        lo, hi = self._cone_box()
        self.c_start = np.floor(lo / hc).astype(np.int64)
        self.c_shape = tuple(int(v) for v in np.ceil(hi / hc).astype(np.int64) - self.c_start + 1)
        self._bank: np.ndarray | None = None
        self._bank_c: np.ndarray | None = None
        self._coarse_maps: tuple[np.ndarray, np.ndarray] | None = None

    @property
    def pixel(self) -> float:
        return self.h

    @property
    def visible_from(self) -> float:
        return self.settings.visible_from

    def shaft_extent(self):
        return self.settings.max_depth * 2.0 - self.settings.visible_from, 1.0

    # ------------------------------------------------------------------ geometry of the probe
    def _cone_box(self) -> tuple[np.ndarray, np.ndarray]:
        s = self.settings
        a = self.ax
        e1 = np.cross(a, [1.0, 0, 0] if abs(a[0]) < 0.9 else [0, 1.0, 0])
        e1 /= np.linalg.norm(e1)
        e2 = np.cross(a, e1)
        th = np.radians(s.half_angle)
        phi = np.linspace(0, 2 * np.pi, 73)
        pts = [self.tr]
        for t in np.linspace(0, th, 7):
            rim = np.cos(t) * a[None] + np.sin(t) * (np.cos(phi)[:, None] * e1 + np.sin(phi)[:, None] * e2)
            pts.append(self.tr + s.max_depth * rim)
        P = np.vstack(pts)
        return P.min(0), P.max(0)

    def distance(self, p: np.ndarray) -> np.ndarray:
        return np.linalg.norm(np.asarray(p) - self.tr, axis=-1)

    def in_view(self, p: np.ndarray) -> np.ndarray:
        """Whether points ``(..., 3)`` mm are inside the imaged cone."""
        rel = np.asarray(p) - self.tr
        d = np.linalg.norm(rel, axis=-1)
        return (d <= self.settings.max_depth) & (rel @ self.ax >= self.cos_half * d)

    def sigma_lateral(self, d: np.ndarray) -> np.ndarray:
        s = self.settings
        return s.psf_lateral * (1.0 + s.lateral_growth * np.asarray(d) / s.max_depth)

    def echo(self, tangent: np.ndarray, beam: np.ndarray) -> np.ndarray:
        """Needle echo for unit ``tangent`` and ``beam`` directions ``(..., 3)``."""
        s = self.settings
        c = np.abs(np.sum(tangent * beam, -1))
        sin = np.sqrt(np.clip(1.0 - c * c, 0.0, 1.0))
        return s.needle_echo * (s.visibility_floor + (1.0 - s.visibility_floor) * sin**s.visibility_power)

    def noise_sd(self, d: np.ndarray) -> np.ndarray:
        s = self.settings
        return s.noise * s.noise_level * 10.0 ** (s.attenuation * np.asarray(d) / 20.0)

    # ------------------------------------------------------------------ rendering helpers
    def _banks(self, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        if self._bank is None:
            self._bank = periodic_speckle(rng, (_BANK,) * 3, (self.settings.psf_lateral / self.h,) * 3)
            self._bank_c = block_max(self._bank, self.settings.coarse)
        return self._bank, self._bank_c  # type: ignore[return-value]

    @staticmethod
    def _axes(start: np.ndarray, shape: tuple[int, int, int], h: float) -> list[np.ndarray]:
        """World coordinates of voxel centres along each axis, ``(B, n_axis)`` per axis."""
        return [(start[:, a, None] + np.arange(shape[a])[None, :]) * h for a in range(3)]

    @staticmethod
    def _bsum(parts: list[np.ndarray]) -> np.ndarray:
        """Sum of per-axis arrays ``(B, nx)``, ``(B, ny)``, ``(B, nz)`` broadcast to ``(B, nx, ny, nz)``."""
        return parts[0][:, :, None, None] + parts[1][:, None, :, None] + parts[2][:, None, None, :]

    def _pieces(self, g: NeedleGeometry, lo: np.ndarray, hi: np.ndarray, piece: float):
        """The visible shaft near the boxes ``[lo, hi] (B, 3)`` mm as a chain of straight pieces about
        ``piece`` mm long (chords of the curved shaft): ``a, b (B, P, 3)`` end points (``b`` toward the
        tip), ``ok (B, P)``."""
        s = self.settings
        margin = 3.0 * self.sigma_lateral(s.max_depth) + 3.0 * s.reverb_length
        inside = np.all((g.shaft >= lo[:, None] - margin) & (g.shaft <= hi[:, None] + margin), -1) & g.visible
        K = g.shaft.shape[1]
        has = inside.any(1)
        i0 = np.argmax(inside, axis=1)  # nearest to the tip
        i1 = K - 1 - np.argmax(inside[:, ::-1], axis=1)  # farthest
        # one point beyond each end (still visible), so the pieces cross the margin
        i0 = np.maximum(i0 - 1, 0)
        i1 = np.minimum(i1 + 1, K - 1)
        vis_end = K - 1 - np.argmax(g.visible[:, ::-1], axis=1)
        i1 = np.minimum(i1, vis_end)
        arc = (i1 - i0) * g.ds
        P = max(1, int(np.ceil(arc[has].max() / piece))) if has.any() else 1
        fr = i0[:, None] + (i1 - i0)[:, None] * (np.arange(P + 1) / P)[None, :]  # fractional indices
        k = np.clip(np.floor(fr).astype(np.int64), 0, K - 2)
        f = (fr - k)[..., None]
        take = lambda idx: np.take_along_axis(g.shaft, idx[..., None], 1)  # noqa: E731
        pts = take(k) * (1 - f) + take(k + 1) * f  # (B, P+1, 3) from the tip end backwards
        ok = np.broadcast_to((has & (i1 > i0))[:, None], (len(has), P)).copy()
        return pts[:, 1:], pts[:, :-1], ok

    def _needle_analytic(self, g: NeedleGeometry, start: np.ndarray, shape, h: float) -> np.ndarray:
        """The shaft convolved with the anisotropic PSF (and its reverberation ghost along the beam),
        ``(B, nx, ny, nz)`` float32, full resolution. Each straight piece costs a fixed number of passes
        over the batch; the smooth box along a piece (a linear ramp of the PSF's slope at each end, so
        that the boxes of a chain add up to one and half the echo remains at the tip) ends it."""
        s = self.settings
        f32 = np.float32
        B = start.shape[0]
        lo, hi = start * h, (start + np.array(shape) - 1) * h
        a, b, ok = self._pieces(g, lo, hi, piece=10.0)
        out = np.zeros((B,) + tuple(shape), dtype=f32)
        if not ok.any():
            return out
        X = [x.astype(f32) for x in self._axes(start, shape, h)]
        seg = b - a
        length = np.linalg.norm(seg, axis=-1)
        u = seg / np.maximum(length, 1e-9)[..., None]
        mid = 0.5 * (a + b)
        beam = mid - self.tr
        dmid = np.linalg.norm(beam, axis=-1)
        beam = beam / np.maximum(dmid, 1e-9)[..., None]
        sl = self.sigma_lateral(dmid)
        sa = s.psf_axial
        amp = self.echo(u, beam) * (s.psf_lateral / sl) * self.in_view(mid) * ok * (length > 1e-6)
        ub = np.sum(u * beam, -1)
        su = np.sqrt(ub**2 * sa**2 + (1 - ub**2) * sl**2)
        ramp = np.sqrt(2 * np.pi) / 2  # half-width of a ramp with the normal CDF's slope at 0, in stds
        ghost_sa2 = sa**2 + s.reverb_length**2
        ghost_amp = s.reverb_level * sa / np.sqrt(ghost_sa2) * np.sqrt(2 * np.pi) * s.reverb_length / (2 * sa)
        col = lambda v: np.asarray(v, dtype=f32)[:, None, None, None]  # noqa: E731
        for k in range(a.shape[1]):
            if not (amp[:, k] > 0).any():
                continue
            rel = [X[i] - a[:, k, i : i + 1].astype(f32) for i in range(3)]
            t = self._bsum([rel[i] * u[:, k, i : i + 1].astype(f32) for i in range(3)])
            e = self._bsum([rel[i] * beam[:, k, i : i + 1].astype(f32) for i in range(3)])
            q = self._bsum([rel[i] * rel[i] for i in range(3)])
            e -= col(ub[:, k]) * t  # beam part of the offset from the line
            q -= t * t  # squared distance to the line
            q -= e * e  # lateral part
            np.maximum(q, 0, out=q)
            q *= col(-0.5 / sl[:, k] ** 2)
            core = np.exp(q + e * e * f32(-0.5 / sa**2))
            if s.reverb_level > 0:  # a ghost of the needle deeper along the beam
                e -= f32(s.reverb_length)
                core += col(np.full(B, ghost_amp)) * np.exp(q + e * e * f32(-0.5 / ghost_sa2))
            c = col(1.0 / (2 * ramp * su[:, k]))
            r1 = t * c
            r1 += f32(0.5)
            r2 = col(0.5 + length[:, k] / (2 * ramp * su[:, k])) - t * c
            np.minimum(r1, r2, out=r1)
            np.clip(r1, 0, 1, out=r1)
            core *= r1
            core *= col(amp[:, k])
            out += core
        return out

    def _needle_maxpool(self, g: NeedleGeometry, start: np.ndarray, shape, h: float) -> np.ndarray:
        """The shaft on the coarse lattice as the block maximum of its full-resolution echo: each block the
        shaft crosses holds the line's peak; the face neighbours hold the PSF's value at the shared face.
        ``(B, nx, ny, nz)`` float32."""
        B = start.shape[0]
        n_sub = max(1, int(np.ceil(g.ds / (0.4 * h))))
        f = (np.arange(n_sub) / n_sub)[None, None, :, None]
        P = (g.shaft[:, :-1, None] * (1 - f) + g.shaft[:, 1:, None] * f).reshape(B, -1, 3)
        V = np.repeat(g.visible[:, :-1] & g.visible[:, 1:], n_sub, axis=1)
        tang = -np.repeat(np.diff(g.shaft, axis=1), n_sub, axis=1)
        tang /= np.maximum(np.linalg.norm(tang, axis=-1, keepdims=True), 1e-9)
        beam = P - self.tr
        d = np.linalg.norm(beam, axis=-1)
        beam /= np.maximum(d, 1e-9)[..., None]
        sl = self.sigma_lateral(d)
        amp = self.echo(tang, beam) * (self.settings.psf_lateral / sl) * V * self.in_view(P)
        q = P / h - start[:, None, :] + 0.5  # block coordinates (voxel centres at integers)
        i0 = np.floor(q).astype(np.int64)
        fq = q - i0
        n = np.array(shape)
        out = np.zeros((B,) + tuple(shape), dtype=np.float32)
        flat = out.reshape(-1)
        bidx = np.broadcast_to(np.arange(B)[:, None], amp.shape)
        moves = [(np.zeros(3, int), np.ones_like(amp))]
        for ax in range(3):
            for step, dist in ((-1, fq[..., ax]), (1, 1.0 - fq[..., ax])):
                o = np.zeros(3, int)
                o[ax] = step
                moves.append((o, np.exp(-0.5 * (dist * h / sl) ** 2)))
        for o, factor in moves:
            ii = i0 + o
            val = amp * factor
            ok = np.all((ii >= 0) & (ii < n), -1) & (val > 0)
            lin = ((bidx * n[0] + ii[..., 0]) * n[1] + ii[..., 1]) * n[2] + ii[..., 2]
            np.maximum.at(flat, lin[ok], val[ok].astype(np.float32))
        return out

    def clutter_blobs(self, rng: np.random.Generator, n_runs: int) -> list[np.ndarray]:
        """The static clutter of each run (bright spots fixed in the phantom: bubbles, calcifications):
        ``(n, 4)`` arrays of world x, y, z (mm) and echo, uniform in the imaged cone."""
        s = self.settings
        if s.clutter <= 0 or s.noise <= 0:
            return [np.zeros((0, 4)) for _ in range(n_runs)]
        cone_cm3 = 2.0 / 3.0 * np.pi * s.max_depth**3 * (1.0 - self.cos_half) / 1000.0
        a = self.ax
        e1 = np.cross(a, [1.0, 0, 0] if abs(a[0]) < 0.9 else [0, 1.0, 0])
        e1 /= np.linalg.norm(e1)
        e2 = np.cross(a, e1)
        out = []
        for _ in range(n_runs):
            n = int(rng.poisson(s.clutter * cone_cm3))
            d = s.max_depth * rng.random(n) ** (1 / 3)
            ct = rng.uniform(self.cos_half, 1.0, n)
            st = np.sqrt(1 - ct * ct)
            ph = rng.uniform(0, 2 * np.pi, n)
            dirs = ct[:, None] * a + st[:, None] * (np.cos(ph)[:, None] * e1 + np.sin(ph)[:, None] * e2)
            amp = s.noise * s.clutter_level * rng.uniform(0.5, 1.5, n)
            out.append(np.column_stack([self.tr + d[:, None] * dirs, amp]))
        return out

    def _clutter(self, vol: np.ndarray, start: np.ndarray, h: float, blobs: list[np.ndarray], pooled: bool) -> None:
        """Add each run's clutter blobs that fall in its region, in place (a small patch per blob; on a
        max-pooled lattice (``pooled``) a blob keeps its peak and widens by half a block)."""
        s = self.settings
        shape = np.array(vol.shape[1:])
        sd2 = s.clutter_size**2 + (h**2 / 4 if pooled else h**2 / 12)
        shrink = 1.0 if pooled else (s.clutter_size**2 / sd2) ** 1.5
        reach = int(np.ceil(3 * np.sqrt(sd2) / h))
        for r, bl in enumerate(blobs):
            if len(bl) == 0:
                continue
            q = bl[:, :3] / h - start[r]  # lattice coordinates in the region
            near = np.all((q >= -reach) & (q <= shape - 1 + reach), -1)
            for (qx, qy, qz), amp in zip(q[near], bl[near, 3]):
                lo = np.maximum(np.floor([qx, qy, qz]).astype(int) - reach, 0)
                hi = np.minimum(np.floor([qx, qy, qz]).astype(int) + reach + 1, shape)
                if np.any(hi <= lo):
                    continue
                g = [np.exp(-0.5 * ((np.arange(lo[i], hi[i]) - c) * h) ** 2 / sd2).astype(np.float32)
                     for i, c in enumerate((qx, qy, qz))]
                vol[r, lo[0] : hi[0], lo[1] : hi[1], lo[2] : hi[2]] += np.float32(amp * shrink) * (
                    g[0][:, None, None] * g[1][None, :, None] * g[2][None, None, :])

    def _coarse_view(self) -> tuple[np.ndarray, np.ndarray]:
        """In-view mask and noise std of every voxel of the coarse lattice (the same for all runs)."""
        if self._coarse_maps is None:
            h = self.h * self.settings.coarse
            X = self._axes(self.c_start[None], self.c_shape, h)
            rel = [X[i] - self.tr[i] for i in range(3)]
            d = np.sqrt(self._bsum([r * r for r in rel]))[0]
            along = self._bsum([rel[i] * self.ax[i] for i in range(3)])[0]
            mask = (d <= self.settings.max_depth) & (along >= self.cos_half * d)
            sd = self.noise_sd(d).astype(np.float32)
            self._coarse_maps = (mask, sd)
        return self._coarse_maps

    def render(self, g: NeedleGeometry, start: np.ndarray, shape, rng: np.random.Generator, *,
               level: int = 1, offsets: np.ndarray, blobs: list[np.ndarray] | None = None) -> np.ndarray:
        """B-mode volumes ``(B, nx, ny, nz)`` uint8 on the lattice of voxel ``voxel * level`` starting at
        lattice index ``start (B, 3)`` (0 outside the imaged cone). ``offsets (B, 3)``: each run's place in
        the speckle texture; ``blobs``: each run's clutter (:meth:`clutter_blobs`).

        ``level`` 1 renders analytically at full resolution (noise level taken at the region's centre);
        ``level`` = ``coarse`` renders the whole cone as block maxima of it."""
        s = self.settings
        h = self.h * level
        fine, coarse = self._banks(rng)
        tissue = tile_take(fine if level == 1 else coarse, start + offsets // level, shape)
        if s.noise != 1.0:
            tissue = np.float32(1.0) + np.float32(s.noise) * (tissue - np.float32(1.0))
        if level == 1:
            tissue += self._needle_analytic(g, start, shape, h)
        else:
            np.maximum(tissue, self._needle_maxpool(g, start, shape, h) + 1.0, out=tissue)
        echo = tissue
        if blobs is not None:
            self._clutter(echo, start, h, blobs, pooled=level > 1)
        if level == 1:
            corners = np.stack(np.meshgrid(*[[0, 1]] * 3, indexing="ij"), -1).reshape(-1, 3)
            ext = (start[:, None, :] + corners[None] * (np.array(shape) - 1)) * h  # (B, 8, 3)
            mask = None
            if not self.in_view(ext).all():
                X = self._axes(start, shape, h)
                rel = [X[i] - self.tr[i] for i in range(3)]
                d = np.sqrt(self._bsum([r * r for r in rel]))
                along = self._bsum([rel[i] * self.ax[i] for i in range(3)])
                mask = (d <= s.max_depth) & (along >= self.cos_half * d)
            centre = (start + (np.array(shape) - 1) / 2) * h
            sd = self.noise_sd(self.distance(centre)).astype(np.float32)[:, None, None, None]
        else:
            mask, sd = self._coarse_view()
        if s.noise > 0 and s.noise_level > 0:
            noise = rng.standard_normal(echo.shape, dtype=np.float32)
            noise *= sd
            echo += noise
            np.abs(echo, out=echo)
        vol = log_compress(echo, s.needle_echo, s.dynamic_range)
        if mask is not None:
            vol[~np.broadcast_to(mask, vol.shape)] = 0
        return vol

    # ------------------------------------------------------------------ segmentation
    def segment(self, vol: np.ndarray, start: np.ndarray, level: int = 1):
        """Find the needle's tip in volumes ``(B, nx, ny, nz)`` uint8 whose voxel (0, 0, 0) is lattice
        index ``start (B, 3)`` of voxel ``voxel * level``.

        Returns ``tip (B, 3)`` mm world, ``valid (B,)``, ``at_edge (B,)`` (the tip was found on the region's
        border: the needle may go on beyond it) and ``tip_vox (B, 3)`` in voxel coordinates of the volume.
        """
        s = self.settings
        h = self.h * level
        B = vol.shape[0]
        shape = np.array(vol.shape[1:])
        V = int(np.prod(shape))
        f = vol.reshape(B, V).astype(np.float32)
        sub_rng = np.random.default_rng(12345)  # a fixed subsample for the background level
        sub = sub_rng.integers(0, V, size=min(V, 4096))
        fs = f[:, sub]
        fs = np.where(fs > 0, fs, np.nan)  # 0: outside the imaged cone
        bg = _nanmedian(fs, axis=1)
        spread = 1.4826 * _nanmedian(np.abs(fs - bg[:, None]), axis=1) * s.dynamic_range / 255.0  # dB
        bg = np.where(np.isfinite(bg), bg, 255.0)
        spread = np.where(np.isfinite(spread), spread, _SPECKLE_DB)
        # threshold_db is meant for fully developed speckle; block maxima (coarse level) spread less
        T = np.maximum(s.threshold_db * np.minimum(spread / _SPECKLE_DB, 1.0), 3.0) * 255.0 / s.dynamic_range
        w = np.maximum(f - (bg + T)[:, None], 0)  # (B, V) excess over the threshold, grey levels
        # refinement weights: the squared excess of linear intensity, which keeps the line's ridge and
        # little of its (wide, anisotropic) cross-section, so that the region's faces do not tilt the axis
        lut = log_expand(np.arange(256), s.needle_echo, s.dynamic_range).astype(np.float32)
        thr_lin = log_expand(bg + T, s.needle_echo, s.dynamic_range).astype(np.float32)
        wl = lut[vol.reshape(B, V)]
        wl -= thr_lin[:, None]
        np.maximum(wl, 0, out=wl)
        wl *= wl
        grid = [np.arange(n, dtype=np.float32) for n in shape]
        G = np.stack(np.meshgrid(*grid, indexing="ij"), -1).reshape(V, 3)
        r_in = s.inlier_radius / h + 0.5
        # a line through the brightest voxels by RANSAC (robust to clutter), then refined twice by the
        # weighted principal axis of the voxels near it
        K = min(256, V)
        top = np.argpartition(-w, K - 1, axis=1)[:, :K]
        c, axis = _ransac_line(G[top], np.take_along_axis(w, top, 1) > 0, r_in, s.min_length / h)
        for _ in range(_REFINE):
            c32, a32 = c.astype(np.float32), axis.astype(np.float32)
            rel = [grid[i][None, :] - c32[:, i : i + 1] for i in range(3)]
            t = self._bsum([rel[i] * a32[:, i : i + 1] for i in range(3)])
            d2 = self._bsum([rel[i] ** 2 for i in range(3)]) - t * t
            wi = wl * (d2.reshape(B, V) <= r_in**2)
            c, axis, lam = _principal_axis(wi.reshape((B,) + tuple(shape)))
        elong = np.sqrt(lam[:, 2] / np.maximum(lam[:, 1], 1e-9))
        # the tip is the end farther along the insertion
        sign = np.where(axis @ np.asarray(s.insertion, dtype=float) >= 0, 1.0, -1.0)
        axis = axis * sign[:, None]
        # profile along the axis, linear intensity
        half = float(np.linalg.norm(shape)) / 2 + 1
        st = np.arange(-half, half + 1e-9, 0.5)
        pts = c[:, None, :] + st[None, :, None] * axis[:, None, :]  # (B, S, 3) voxel coordinates
        prof, inside = _trilinear(vol, pts)
        lin = log_expand(prof, s.needle_echo, s.dynamic_range)
        lin = np.where(inside, lin, np.nan)
        lin_s = lin.copy()
        lin_s[:, 1:-1] = 0.25 * lin[:, :-2] + 0.5 * lin[:, 1:-1] + 0.25 * lin[:, 2:]
        bg_lin = log_expand(bg, s.needle_echo, s.dynamic_range)
        above = np.nan_to_num(lin_s, nan=0.0) > thr_lin[:, None]
        S = len(st)
        k_start, k_end = _longest_run(above, bridge=int(round(1.0 / (0.5 * h))))
        has = k_end >= k_start
        idx = np.arange(S)[None, :]
        run_len = (k_end - k_start) * 0.5 * h
        # plateau: the shaft's level away from its ends (the tip's end is blurred over ~ the beam width at
        # the region's distance, which the probe's specification gives)
        step = 0.5 * h
        centre = (start + (shape - 1) / 2) * h
        margin = 3.0 * self.sigma_lateral(self.distance(centre)) + 0.5  # (B,) mm
        win = (idx >= k_start[:, None] + int(round(1.0 / step))) & (idx <= k_end[:, None] - np.rint(margin / step)[:, None])
        win = np.where(win.any(1, keepdims=True), win, (idx >= k_start[:, None]) & (idx <= k_end[:, None]))
        plateau = _nanmedian(np.where(win, lin_s, np.nan), axis=1)
        level_half = bg_lin + 0.5 * (plateau - bg_lin)
        # the last sample at or above the half level, from the bright run to just past its end
        ge = np.nan_to_num(lin_s, nan=0.0) >= level_half[:, None]
        reach = (idx >= k_start[:, None]) & (idx <= k_end[:, None] + int(round(2.0 / (0.5 * h))))
        cand = ge & reach
        k_star = S - 1 - np.argmax(cand[:, ::-1], axis=1)
        k_drop = k_star + 1
        k1 = np.minimum(k_drop, S - 1)
        rows = np.arange(B)
        y0, y1 = lin_s[rows, k_star], lin_s[rows, k1]
        frac = np.where((k1 > k_star) & np.isfinite(y1) & (y0 > y1), (y0 - level_half) / np.where(y0 > y1, y0 - y1, 1.0), 0.0)
        s_tip = st[k_star] + np.clip(frac, 0, 1) * 0.5
        tip_vox = c + s_tip[:, None] * axis
        tip = (start + tip_vox) * h
        at_edge = ~np.isfinite(y1) | (k_drop >= S) | np.any((tip_vox < 1.0) | (tip_vox > shape - 2.0), -1)
        valid = (
            has
            & (run_len >= max(s.min_length, 4 * h))
            & (elong >= s.min_elongation)
            & np.isfinite(plateau)
            & (plateau > thr_lin)
            & np.all(np.isfinite(tip), -1)
        )
        return tip, valid, at_edge, tip_vox

    # ------------------------------------------------------------------ characterisation
    def poses(self) -> list[Pose]:
        """Tips on the probe's axis at distances from 3/16 to 15/16 of ``max_depth``, the needle at 90,
        70, 50 and 30 deg to the beam, in the plane of the beam and the insertion direction."""
        s = self.settings
        b = self.ax
        ins = np.asarray(s.insertion, dtype=float) / np.linalg.norm(s.insertion)
        e = ins - (ins @ b) * b
        if np.linalg.norm(e) < 1e-6:
            e = np.cross(b, [1.0, 0, 0] if abs(b[0]) < 0.9 else [0, 1.0, 0])
        e /= np.linalg.norm(e)
        out = []
        for k in range(3, 16, 2):
            d = s.max_depth * k / 16
            for theta in (90, 70, 50, 30):
                th = np.radians(theta)
                t = np.sin(th) * e + np.cos(th) * b
                out.append(Pose(tuple(self.tr + d * b), tuple(t), 30.0,
                                {"Distance [mm]": round(d, 1), "Angle [deg]": theta}))
        return out

    def measure_once(self, g, rng, mode="tracking"):
        """``tracking``: the region placed as tracking would, around the true tip moved by N(0, 1 mm^2)
        per axis (a prediction from the previous detections); ``search``: the whole volume searched
        coarse-to-fine (no prior)."""
        B = g.shaft.shape[0]
        offsets = self.settings.coarse * rng.integers(0, _BANK // self.settings.coarse, size=(B, 3))
        blobs = self.clutter_blobs(rng, B)
        if mode == "search":
            centre, found = self.search(g, rng, offsets, blobs)
        else:
            centre, found = g.tip + rng.normal(0.0, 1.0, (B, 3)), np.ones(B, dtype=bool)
        tip = np.full((B, 3), np.nan)
        ok = np.zeros(B, dtype=bool)
        rows = np.nonzero(found)[0]
        if rows.size:
            t, o, *_ = self.fine_pass(g.take(rows), centre[rows], rng, offsets[rows], [blobs[i] for i in rows])
            tip[rows], ok[rows] = t, o
        return DeviceResult(tip=np.where(ok[:, None], tip, np.nan)[:, None], valid=ok[:, None])

    # ------------------------------------------------------------------ the sequence
    def roi_start(self, tip: np.ndarray) -> np.ndarray:
        """Lattice index of the first voxel of the full-resolution region for a predicted ``tip (B, 3)``:
        centred ``0.2 roi_size`` behind it (against the insertion) to hold more of the shaft."""
        ins = np.asarray(self.settings.insertion, dtype=float)
        centre = tip - 0.2 * self.settings.roi_size * ins / np.linalg.norm(ins)
        return np.rint(centre / self.h).astype(np.int64) - self.n_roi // 2

    def fine_pass(self, g, centre, rng, offsets, blobs=None):
        """Render and segment the regions around ``centre (B, 3)``; one re-centred second pass where the
        tip was found on the region's border. Returns tip, valid, start, volume, tip_vox."""
        shape = (self.n_roi,) * 3
        start = self.roi_start(centre)
        vol = self.render(g, start, shape, rng, offsets=offsets, blobs=blobs)
        tip, ok, edge, tv = self.segment(vol, start)
        redo = np.nonzero(edge & np.all(np.isfinite(tip), -1) & (np.linalg.norm(tip - centre, axis=-1) < 2 * self.settings.roi_size))[0]
        if redo.size:
            st2 = self.roi_start(tip[redo])
            v2 = self.render(g.take(redo), st2, shape, rng, offsets=offsets[redo],
                             blobs=None if blobs is None else [blobs[i] for i in redo])
            t2, ok2, e2, tv2 = self.segment(v2, st2)
            tip[redo], ok[redo], edge[redo], tv[redo] = t2, ok2, e2, tv2
            start[redo], vol[redo] = st2, v2
        ok &= ~edge
        return tip, ok, start, vol, tv

    def search(self, g, rng, offsets, blobs=None):
        """Coarse-to-fine search of the whole volume: ``(coarse tip (B, 3), found (B,))``."""
        level = self.settings.coarse
        B = g.shaft.shape[0]
        start = np.broadcast_to(self.c_start, (B, 3)).copy()
        vol = self.render(g, start, self.c_shape, rng, level=level, offsets=offsets, blobs=blobs)
        tip, ok, edge, _ = self.segment(vol, start, level=level)
        return tip, ok

    def run(self, geometry, times, n_runs, rng, frames: FrameStore | None = None, on_frame=None) -> DeviceResult:
        s = self.settings
        M = len(times)
        tip = np.full((n_runs, M, 3), np.nan)
        valid = np.zeros((n_runs, M), dtype=bool)
        searched = np.zeros((n_runs, M), dtype=bool)
        offsets = s.coarse * rng.integers(0, _BANK // s.coarse, size=(n_runs, 3))
        blobs = self.clutter_blobs(rng, n_runs)
        last = np.full((n_runs, 3), np.nan)
        t_last = np.full(n_runs, np.nan)
        prev = np.full((n_runs, 3), np.nan)
        t_prev = np.full(n_runs, np.nan)
        misses = np.zeros(n_runs, dtype=np.int64)
        ever = np.zeros(n_runs, dtype=bool)
        for j, t in enumerate(times):
            g = geometry(j)
            centre = last.copy()
            vel_ok = np.isfinite(t_prev) & np.isfinite(t_last) & (t_last > t_prev)
            vel = np.where(vel_ok[:, None], (last - prev) / np.where(vel_ok, t_last - t_prev, 1.0)[:, None], 0.0)
            centre = centre + vel * np.where(np.isfinite(t_last), t - t_last, 0.0)[:, None]
            centre[misses >= s.lost_after] = np.nan
            if s.roi_prior is not None:
                centre[~ever] = np.asarray(s.roi_prior)
            need = ~np.all(np.isfinite(centre), -1)
            if need.any():
                rows = np.nonzero(need)[0]
                ct, found = self.search(g.take(rows), rng, offsets[rows], [blobs[i] for i in rows])
                centre[rows[found]] = ct[found]
                searched[rows, j] = True
            rows = np.nonzero(np.all(np.isfinite(centre), -1))[0]
            keep = frames.wanted(j) if frames is not None else np.zeros(0, dtype=np.int64)
            if rows.size:
                tp, ok, start, vol, tv = self.fine_pass(g.take(rows), centre[rows], rng, offsets[rows],
                                                        [blobs[i] for i in rows])
                tip[rows[ok], j] = tp[ok]
                valid[rows[ok], j] = True
                for i, r in enumerate(rows):
                    if r in keep and frames is not None:
                        origin = start[i] * self.h
                        frames.add(int(r), j, vol[i], tv[i] if ok[i] else np.full(3, np.nan),
                                   (g.tip[r] - origin) / self.h, origin=origin)
            hit = valid[:, j]
            prev = np.where(hit[:, None], last, prev)
            t_prev = np.where(hit, t_last, t_prev)
            last = np.where(hit[:, None], tip[:, j], last)
            t_last = np.where(hit, t, t_last)
            misses = np.where(hit, 0, misses + 1)
            ever |= hit
            if on_frame is not None:
                on_frame(j, {"tip": tip[:, j], "valid": valid[:, j], "searched": searched[:, j]})
        return DeviceResult(tip=tip, valid=valid, extras={"searched": searched})


def _nanmedian(a: np.ndarray, axis: int) -> np.ndarray:
    """``np.nanmedian`` that gives NaN for all-NaN rows without a warning."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        return np.nanmedian(a, axis=axis)


def _ransac_line(pts: np.ndarray, ok: np.ndarray, r_in: float, min_sep: float, n_hyp: int = 64):
    """Best line through candidate points ``pts (B, K, 3)`` (``ok (B, K)`` valid, brightest first): among
    ``n_hyp`` lines through pairs of valid candidates at least ``min_sep`` apart, the one with most
    candidates within ``r_in``. Returns a point on it and its direction, ``(B, 3)`` each; all hypotheses of
    all volumes in one array operation. Deterministic (fixed sampling stream)."""
    B, K, _ = pts.shape
    n_ok = np.maximum(ok.sum(1), 1)
    rng = np.random.default_rng(0)
    pick = np.minimum((rng.random((B, n_hyp, 2)) * n_ok[:, None, None]).astype(np.int64), K - 1)
    p1 = pts[np.arange(B)[:, None], pick[..., 0]]
    p2 = pts[np.arange(B)[:, None], pick[..., 1]]
    d = p2 - p1
    nd = np.linalg.norm(d, axis=-1)
    good = nd >= min_sep
    u = d / np.maximum(nd, 1e-9)[..., None]
    rel = pts[:, None, :, :] - p1[:, :, None, :]  # (B, H, K, 3)
    t = np.einsum("bhkc,bhc->bhk", rel, u)
    d2 = np.einsum("bhkc,bhkc->bhk", rel, rel) - t * t
    score = ((d2 <= r_in**2) & ok[:, None, :]).sum(-1) * good
    best = np.argmax(score, axis=1)
    r = np.arange(B)
    axis = np.where((score[r, best] > 0)[:, None], u[r, best], np.array([0.0, 0.0, 1.0]))
    centre = np.where((score[r, best] > 0)[:, None], p1[r, best], pts[:, 0])
    return centre.astype(float), axis.astype(float)


def _principal_axis(w: np.ndarray):
    """Weighted centroid ``(B, 3)``, principal axis ``(B, 3)`` and eigenvalues ``(B, 3)`` (ascending) of the
    voxel centres of volumes with weights ``w (B, nx, ny, nz)``, in voxel coordinates. The moments come
    from the volume's sums over one axis (the voxels form a grid), three passes over the batch."""
    B = w.shape[0]
    x, y, z = (np.arange(n, dtype=np.float64) for n in w.shape[1:])
    m_xy = w.sum(3, dtype=np.float64)  # (B, nx, ny)
    m_xz = w.sum(2, dtype=np.float64)  # (B, nx, nz)
    m_yz = w.sum(1, dtype=np.float64)  # (B, ny, nz)
    mx, my, mz = m_xy.sum(2), m_xy.sum(1), m_xz.sum(1)  # marginals (B, n)
    W = np.maximum(mx.sum(1), 1e-12)
    c = np.stack([mx @ x, my @ y, mz @ z], -1) / W[:, None]
    S = np.empty((B, 3, 3))
    S[:, 0, 0], S[:, 1, 1], S[:, 2, 2] = mx @ x**2, my @ y**2, mz @ z**2
    S[:, 0, 1] = S[:, 1, 0] = np.einsum("bij,i,j->b", m_xy, x, y)
    S[:, 0, 2] = S[:, 2, 0] = np.einsum("bik,i,k->b", m_xz, x, z)
    S[:, 1, 2] = S[:, 2, 1] = np.einsum("bjk,j,k->b", m_yz, y, z)
    S = S / W[:, None, None] - c[:, :, None] * c[:, None, :]
    lam, vec = np.linalg.eigh(S)
    return c, vec[:, :, 2], lam


def _trilinear(vol: np.ndarray, pts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Values of volumes ``(B, nx, ny, nz)`` at voxel coordinates ``pts (B, S, 3)`` (trilinear) and whether
    each point is inside."""
    B = vol.shape[0]
    n = np.array(vol.shape[1:])
    inside = np.all((pts >= 0) & (pts <= n - 1), -1)
    q = np.clip(pts, 0, n - 1 - 1e-6)
    i0 = np.floor(q).astype(np.int64)
    f = q - i0
    out = np.zeros(pts.shape[:2])
    b = np.arange(B)[:, None]
    for corner in range(8):
        o = np.array([(corner >> k) & 1 for k in range(3)])
        ii = np.minimum(i0 + o, n - 1)
        wt = np.prod(np.where(o, f, 1 - f), axis=-1)
        out += wt * vol[b, ii[..., 0], ii[..., 1], ii[..., 2]]
    return out, inside


def _longest_run(above: np.ndarray, bridge: int) -> tuple[np.ndarray, np.ndarray]:
    """First and last index ``(B,)`` of the longest run of True in each row of ``above (B, S)``, gaps of
    up to ``bridge`` samples bridged (speckle drop-outs along the shaft); ``(0, -1)`` for rows without
    any. A loop over rows of a short 1D profile."""
    B, S = above.shape
    k0 = np.zeros(B, dtype=np.int64)
    k1 = np.full(B, -1, dtype=np.int64)
    for r in range(B):
        on = np.flatnonzero(above[r])
        if on.size == 0:
            continue
        breaks = np.flatnonzero(np.diff(on) > bridge + 1)
        starts = np.concatenate([[0], breaks + 1])
        ends = np.concatenate([breaks, [on.size - 1]])
        i = int(np.argmax(on[ends] - on[starts]))
        k0[r], k1[r] = on[starts[i]], on[ends[i]]
    return k0, k1
