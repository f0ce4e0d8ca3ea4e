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
from needlecli.sensors.imaging.render import FrameStore, TruthPath

_AXES = ("x", "y", "z")


@PIPELINES.register("image")
class ImagePipeline(Pipeline):
    """Render, then measure with the device's image-processing pipeline (see the module docstring)."""

    supports = ("position",)

    def measure(self, sensor, truth, idx, rng):
        cfg = sensor.settings.image
        device = DEVICES.get(cfg.device)(cfg)
        path = TruthPath(truth, visible_from=device.visible_from)
        length, ds = device.shaft_extent()
        n_runs = truth.states.shape[0]
        frames = FrameStore(len(idx), min(cfg.save_runs, n_runs), cfg.save_frames)
        res = device.run(lambda j: path.geometry(int(idx[j]), length, ds), truth.time[idx], n_runs, rng, frames)
        cols = [_AXES.index(a) for a in sensor.settings.axes]
        value = res.tip[..., cols] / path.scale
        valid = res.valid & np.all(np.isfinite(value), -1)
        sigma = np.ascontiguousarray(np.broadcast_to(sensor.sigma(truth, idx), value.shape))
        self.extras = {"image_valid": valid.copy(), **res.extras, **frames.extras()}
        return value, valid, sigma
