"""The imaging device contract: a device renders frames of the needle and measures the tip in them.

A device is chosen in a position sensor's ``image:`` section by ``device:`` (``us2d``, ``us3d``,
``camera``) and run by the ``image`` pipeline (:mod:`needlecli.sensors.imaging.pipeline`). It works on
the needle's shape in mm (:class:`~needlecli.sensors.imaging.render.NeedleGeometry`), so the same code
measures simulated insertions and chosen poses (``needle characterize-sensor``).

New devices: subclass :class:`Device` with a ``Settings`` schema (subclass of :class:`ImageSettings`
with ``device: Literal[...]``), decorate with ``@DEVICES.register("name")`` and add the settings class to
the union in :mod:`needlecli.sensors.imaging`.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import ClassVar

import numpy as np
from pydantic import Field

from needlecli.registry import Registry
from needlecli.schema import NonNeg, Strict
from needlecli.sensors.imaging.render import DeviceResult, FrameStore, NeedleGeometry


@dataclass(frozen=True)
class Pose:
    """A straight needle to measure: its tip (mm, world), unit direction of insertion, visible length
    (mm), and the labels of the table row it belongs to (e.g. distance and angle)."""

    tip: tuple[float, float, float]
    direction: tuple[float, float, float]
    length: float
    labels: dict


#: ``on_frame(j, outputs)``: what a device reports after measuring sample ``j`` of every run
OnFrame = Callable[[int, dict[str, np.ndarray]], None]


class ImageSettings(Strict):
    """Settings every imaging device has (lengths in mm, whatever the model's unit)."""

    device: str
    noise: NonNeg = Field(1.0, description="scale of every random part of the frames (0: noise-free rendering)")
    save_frames: int = Field(0, ge=0, le=100, description="frames kept per saved run (evenly spaced samples)")
    save_runs: int = Field(1, ge=1, le=1000, description="the first this many runs have frames kept")


class Device:
    """Base class of imaging devices.

    Class attributes
    ----------------
    Settings : the pydantic schema of the ``image:`` section for this device.
    axes : the tip coordinates the device measures (a position sensor may use any subset).
    """

    Settings: ClassVar[type[ImageSettings]] = ImageSettings
    axes: ClassVar[tuple[str, ...]] = ("x", "y", "z")
    registered_name: ClassVar[str] = ""

    def __init__(self, settings: ImageSettings) -> None:
        self.settings = settings

    @property
    def pixel(self) -> float:
        """Edge of one pixel (voxel), mm."""
        raise NotImplementedError

    @property
    def visible_from(self) -> float:
        """Arc length (mm) from which the shaft is visible (negative: pre-inserted)."""
        return 0.0

    def shaft_extent(self) -> tuple[float, float]:
        """How much of the needle behind the tip the device needs, and the spacing of its points (mm)."""
        raise NotImplementedError

    def poses(self) -> list[Pose]:
        """The poses ``needle characterize-sensor`` measures by default (what the device's error depends on)."""
        raise NotImplementedError

    def measure_once(self, g: NeedleGeometry, rng: np.random.Generator, mode: str = "tracking") -> DeviceResult:
        """One independent frame of each needle of ``g`` (a batch of poses and repeats), as the first frame
        of a run would be measured. ``mode``: ``tracking`` (devices that look in a region place it as
        tracking would) or ``search`` (no prior)."""
        return self.run(lambda j: g, np.zeros(1), g.shaft.shape[0], rng)

    def run(
        self,
        geometry: Callable[[int], NeedleGeometry],
        times: np.ndarray,
        n_runs: int,
        rng: np.random.Generator,
        frames: FrameStore | None = None,
        on_frame: OnFrame | None = None,
    ) -> DeviceResult:
        """Render and measure every sample ``j`` of ``times (M,)`` for all runs; ``geometry(j)`` gives the
        needle of every run at sample ``j``. Samples are taken in time order (devices may track).

        ``on_frame(j, outputs)``, when given, is called once sample ``j`` is measured for every run, before
        ``geometry(j + 1)`` is asked for: ``outputs`` holds the sample's ``tip`` (N, 3) mm, ``valid`` (N,)
        and the device's per-sample extras (the camera's ``opacity`` (N,)). A controller closes its loop
        through it (the simulation behind ``geometry`` has not passed sample ``j``'s time yet)."""
        raise NotImplementedError


DEVICES: Registry[type[Device]] = Registry("imaging device", builtins={
    "us2d": "needlecli.sensors.imaging.ultrasound2d",
    "us3d": "needlecli.sensors.imaging.ultrasound3d",
    "camera": "needlecli.sensors.imaging.camera",
})
