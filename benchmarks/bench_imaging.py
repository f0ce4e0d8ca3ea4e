"""Benchmark: frames per second of each imaging pipeline (render + measure), with two targets:

* the magnetic needle EM paper's design through the overhead camera: 48 trials x 27 s x 6 Hz = 7,776 frames of 800 x 668 px
  in under 60 s;
* 3D ultrasound volumes at 1 Hz over an 80 mm insertion at 1.5 mm/s, tracked: under 50 ms per volume
  (the whole-volume coarse-to-fine search, needed before the first detection, is timed on its own);

plus the 2D transverse ultrasound of the high-gain observer paper (25 Hz). Times are noisy on a shared machine, so each is
also printed as a ratio against ``reference`` of ``benchmarks/bench_simulate.py`` (a bare numpy RK4 loop)
measured in the same run.

    python benchmarks/bench_imaging.py [--trials 48] [--runs 10] [--repeat 1]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_simulate import reference  # noqa: E402

from needlecli.experiments.config.load import load_config  # noqa: E402
from needlecli.experiments.simulation.runner import build_sensors  # noqa: E402
from needlecli.experiments.simulation.truth import simulate_truth, stream  # noqa: E402
from needlecli.sensors.imaging import EndFireUltrasound, EndFireUltrasoundSettings  # noqa: E402
from needlecli.sensors.imaging.render import NeedleGeometry  # noqa: E402

CAMERA = """
name: bench_camera
model: {type: mnm, params: {c: 9.5}, initial_state: {hy: -1.0, By: -1.0}}
inputs:
  v: 0.002
  omega_B: {kind: piecewise, interp: linear, times: [0.0, 27.0], values: [[0, 0, -0.12], [0, 0, 0.2]]}
sensors:
  - {name: camera, type: position, rate: 6.0, axes: [x, y], sigma: 5.0e-5, pipeline: image, image: {device: camera}}
runs: {count: 48, seed: 4}
stop: {time: 27.0}
"""

US3D = """
name: bench_us3d
model: {type: modified_unicycle, params: {kappa: 0.005, beta_cut: 0.035}}
inputs: {v: 1.5, u: 0.0}
sensors:
  - {name: us3d, type: position, rate: 1.0, sigma: 0.3, pipeline: image, image: {device: us3d}}
runs: {count: 10, seed: 3}
stop: {depth: 80.0}
"""

US2D = """
name: bench_us2d
model: {type: unicycle, params: {kappa: 0.0019}, initial_state: {gamma: 0.0524}}
inputs: {v: 2.0, u: {kind: flips, at_depths: [20.0, 45.0], rate: 3.14159}}
sensors:
  - {name: us2d, type: position, rate: 25.0, axes: [x, y], sigma: 0.1, pipeline: image, image: {device: us2d}}
runs: {count: 6, seed: 0}
stop: {depth: 50.0}
"""


def _measure(text: str, runs: int | None, repeat: int):
    """Best time of measuring the truth with the config's image sensor; also the stream."""
    cfg, _ = load_config(text=text, runs=runs)
    truth = simulate_truth(cfg)
    sensor = build_sensors(cfg, truth.model)[0]
    best = np.inf
    for _ in range(repeat):
        t0 = time.perf_counter()
        st = sensor.measure(truth, stream(cfg.runs.seed, sensor.name))
        best = min(best, time.perf_counter() - t0)
    return best, st


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--trials", type=int, default=48, help="camera trials (the magnetic needle EM paper: 48)")
    ap.add_argument("--runs", type=int, default=10, help="3D ultrasound insertions")
    ap.add_argument("--repeat", type=int, default=1)
    args = ap.parse_args()
    ref = min(reference(100, 2000) for _ in range(3))
    print(f"reference   {ref:7.3f} s   bare numpy RK4 loop, 100 runs x 2000 steps (bench_simulate.reference)")

    t, st = _measure(CAMERA, args.trials, args.repeat)
    n = st.valid.size
    print(f"camera      {n} frames of 800 x 668 px ({args.trials} trials x 27 s x 6 Hz): {t:6.2f} s, "
          f"{n / t:6.1f} frames/s, {t / ref:6.1f} x reference   (goal: 7,776 frames < 60 s)   "
          f"valid {st.valid.mean():.1%}")

    t, st = _measure(US3D, args.runs, args.repeat)
    n = st.valid.size
    searched = int(st.attrs["searched"].sum())
    print(f"us3d        {n} volumes ({args.runs} insertions of 80 mm at 1.5 mm/s, 1 Hz, 0.4 mm voxels), "
          f"{searched} whole-volume searches: {t:6.2f} s, {1e3 * t / n:6.1f} ms/volume, {n / t:6.1f} volumes/s, "
          f"{t / ref:6.1f} x reference   (goal: < 50 ms/volume)   valid {st.valid.mean():.1%}")

    dev = EndFireUltrasound(EndFireUltrasoundSettings(device="us3d"))
    rng = np.random.default_rng(0)
    B = 10
    g = NeedleGeometry.straight(np.c_[np.zeros(B), np.zeros(B), np.linspace(20, 70, B)],
                                np.array([[0.0, 0.0, 1.0]]), 80.0, 1.0)
    best = np.inf
    for _ in range(max(args.repeat, 2)):
        t0 = time.perf_counter()
        dev.measure_once(g, rng, "search")
        best = min(best, time.perf_counter() - t0)
    print(f"us3d search {B} whole volumes coarse-to-fine (cone of 60 deg, 80 mm): {1e3 * best / B:6.1f} ms/volume, "
          f"{best / ref:6.2f} x reference")

    t, st = _measure(US2D, None, args.repeat)
    n = st.valid.size
    print(f"us2d        {n} frames of 200 x 200 px (6 insertions of 50 mm at 2 mm/s, 25 Hz): {t:6.2f} s, "
          f"{n / t:6.1f} frames/s, {t / ref:6.1f} x reference   valid {st.valid.mean():.1%}")


if __name__ == "__main__":
    main()
