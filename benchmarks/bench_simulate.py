"""Benchmark: simulate 1,000 insertions of 80 mm at 100 Hz with three sensors (goal: under 3 s here).

Times are noisy on a shared machine, so each figure is also printed as a ratio against a reference
measured in the same run: a bare RK4 loop over the same number of steps on arrays of the same shape,
doing the trigonometry any needle model needs (the floor of what numpy can do for this work).

    python benchmarks/bench_simulate.py [--runs 1000] [--repeat 3]
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from needlecli.experiments.config.load import load_config
from needlecli.experiments.simulation.runner import build_sensors
from needlecli.experiments.simulation.truth import simulate_truth, stream

CONFIG = """
name: bench
model: {type: modified_unicycle, params: {kappa: 0.005, beta_cut: 0.035}}
inputs: {v: 1.5, u: {kind: flips, at_depths: [30.0]}}
process_noise: {std: {x: 0.002, y: 0.002, z: 0.002}}
sensors:
  - {name: us3d, type: position, rate: 1.0, sigma: 0.3, growth: {transducer: [0, 0, 90], a: 1.0, d_max: 80.0}}
  - {name: robot, type: encoder, rate: 100.0, channels: [roll], sigma: 0.0035}
  - {name: swe, type: elastography, rate: 1.0, sigma: 0.001}
runs: {count: 1000, seed: 1}
stop: {depth: 80.0}
simulation: {dt: 0.01}
"""


def reference(n_runs: int, n_steps: int, n: int = 7) -> float:
    """Bare RK4 of x' = (sin x, cos x)-style field on (n_runs, n): the numpy floor for this loop."""
    x = np.zeros((n_runs, n))

    def f(x):
        s, c = np.sin(x[:, 3:6]), np.cos(x[:, 3:6])
        out = np.empty_like(x)
        out[:, :3] = s * c
        out[:, 3:6] = c
        out[:, 6:] = 0.0
        return out

    t = time.perf_counter()
    states = np.empty((n_runs, n_steps, n))
    for k in range(n_steps):
        k1 = f(x)
        k2 = f(x + 0.005 * k1)
        k3 = f(x + 0.005 * k2)
        k4 = f(x + 0.01 * k3)
        x = x + (0.01 / 6) * (k1 + 2 * (k2 + k3) + k4)
        states[:, k] = x
    return time.perf_counter() - t


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=1000)
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args()
    cfg, _ = load_config(text=CONFIG, runs=args.runs)
    best_sim = best_ref = np.inf
    for _ in range(args.repeat):
        t0 = time.perf_counter()
        truth = simulate_truth(cfg)
        sensors = build_sensors(cfg, truth.model)
        streams = [s.measure(truth, stream(1, s.name)) for s in sensors]
        t_sim = time.perf_counter() - t0
        best_sim = min(best_sim, t_sim)
        best_ref = min(best_ref, reference(args.runs, len(truth.time) - 1))
    n_steps = len(truth.time) - 1
    samples = sum(int(s.valid.sum()) for s in streams)
    print(f"simulate: {args.runs} insertions x {n_steps} steps (80 mm at 1.5 mm/s, 100 Hz), 3 sensors, "
          f"{samples} samples")
    print(f"  time        {best_sim:7.2f} s   (goal < 3 s on 2 cores)   best of {args.repeat}")
    print(f"  reference   {best_ref:7.2f} s   bare numpy RK4 loop of the same size")
    print(f"  ratio       {best_sim / best_ref:7.2f} x reference")
    print(f"  per step    {1e6 * best_sim / n_steps:7.1f} us for all {args.runs} runs")


if __name__ == "__main__":
    main()
