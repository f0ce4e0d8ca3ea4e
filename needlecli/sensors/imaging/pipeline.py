"""The ``image`` pipeline: render frames of the true needle with an imaging device and measure them.

Chosen per position sensor with ``pipeline: image`` and an ``image:`` section naming the device; the
sensor keeps its clock (rate, start, latency, dropout) and channels, so observers run unchanged on either
pipeline. What the pipeline adds to the measurement stream (stored beside ``value`` in the results
file, ``/measurements/<sensor>/<name>``):

``image_valid`` (N, M) bool
    the device made a detection (before dropouts and the end of a run are applied)
``frames``, ``frame_run``, ``frame_sample``, ``frame_tip``, ``frame_truth`` [, ``frame_origin``]
    frames kept for a person to look at (``image: {save_frames: k, save_runs: r}``), see
    :class:`~needlecli.sensors.imaging.render.FrameStore`
device extras
    the camera's ``opacity``, ``bz_command`` (mT), ``heading`` (N, M, 2) and ``centre_px``; the 3D
    ultrasound's ``searched`` (N, M) bool (the whole volume had to be searched)

``sigma`` of the stream is the sensor's configured ``sigma`` (and ``growth``): the noise the sensor
states, for observers that take R from the sensor; set it from ``needle characterize-sensor``.
"""

from __future__ import annotations

import numpy as np

from needlecli.sensors.base import PIPELINES, Pipeline
from needlecli.sensors.imaging.base import DEVICES
from needlecli.sensors.imaging.render import FrameStore, LiveTruthPath, TruthPath

_AXES = ("x", "y", "z")


@PIPELINES.register("image")
class ImagePipeline(Pipeline):
    """Render, then measure with the device's image-processing pipeline (see the module docstring)."""

    supports = ("position",)
    live = True

    def measure(self, sensor, truth, idx, rng):
        cfg = sensor.settings.image
        device = DEVICES.get(cfg.device)(cfg)
        path = TruthPath(truth, visible_from=device.visible_from)
        value, valid = self._run(sensor, device, path, truth.time[idx], idx, rng, None)
        return value, valid, self.sigma_of(sensor, truth, idx, value)

    def measure_live(self, sensor, sim, idx, rng, on_frame):
        """Measure while ``sim`` (a :class:`~needlecli.experiments.simulation.truth.TruthSimulator`) runs: each
        frame's geometry advances the simulation to the frame's grid index, and ``on_frame(j, outputs)``
        gets the frame's outputs before the simulation goes past it. Returns ``value``, ``valid``."""
        cfg = sensor.settings.image
        device = DEVICES.get(cfg.device)(cfg)
        path = LiveTruthPath(sim.model, sim.states, sim.depth, sim.advance_to, visible_from=device.visible_from)
        return self._run(sensor, device, path, sim.time[idx], idx, rng, on_frame)

    def _run(self, sensor, device, path, times, idx, rng, on_frame):
        cfg = sensor.settings.image
        n_runs = path.n_runs
        frames = FrameStore(len(idx), min(cfg.save_runs, n_runs), cfg.save_frames)
        length, ds = device.shaft_extent()
        if self.progress is not None:  # frames one at a time: say how far the rendering is
            report, inner, total = self.progress, on_frame, len(idx)

            def on_frame(j, outputs):
                if inner is not None:
                    inner(j, outputs)
                report(j + 1, total)

        res = device.run(lambda j: path.geometry(int(idx[j]), length, ds), times, n_runs, rng, frames, on_frame=on_frame)
        cols = [_AXES.index(a) for a in sensor.settings.axes]
        value = res.tip[..., cols] / path.scale
        valid = res.valid & np.all(np.isfinite(value), -1)
        self.extras = {"image_valid": valid.copy(), **res.extras, **frames.extras()}
        return value, valid
