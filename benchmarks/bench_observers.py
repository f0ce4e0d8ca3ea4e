"""Benchmark: the high-gain observer (the high-gain observer paper) and the invariant SO(3) observer (the SO(3) observer paper) on a batch of
1,000 insertions, time per insertion step (all runs at once).

Each figure is also printed as a ratio against a bare numpy RK4 loop of the same size measured in the
same run (``reference`` of ``bench_simulate.py``), since absolute times are noisy on a shared machine.
Only the observers are timed; the truth and the measurements are simulated once beforehand.

    python benchmarks/bench_observers.py [--runs 1000] [--repeat 3]
"""

from __future__ import annotations

import argparse
import time

import numpy as np
from bench_simulate import reference

from needlecli.experiments.config.load import load_config
from needlecli.experiments.simulation.runner import build_problem, build_sensors
from needlecli.experiments.simulation.truth import simulate_truth, stream
from needlecli.observers import OBSERVERS

HIGH_GAIN = """
name: bench_high_gain
model: {type: unicycle, params: {kappa: 0.0019}, initial_state: {gamma: 0.05236, beta: 0.05}}
inputs:
  v: 2.0
  u: {kind: flips, at_depths: [22.36, 67.08], rate: 3.14159}
sensors: [{name: us2d, type: position, rate: 25.0, axes: [x, y], sigma: 0.1, latency: 0.04}]
observers:
  - {name: hg, type: high_gain, measurement: us2d, theta: 3.0, kappa: 0.002, init: {values: {x: 0, beta: 0}}}
runs: {count: 1000, seed: 1}
stop: {depth: 100.0}
"""

SO3 = """
name: bench_so3
model: {type: so3, params: {kappa: 0.028571}}
inputs:
  v: 10.0
  u: {kind: cases, cases: [0.785398, 0.0981748]}
sensors: [{name: tracker, type: tangent, rate: 50.0, sigma: 0.005}]
observers:
  - {name: inv, type: so3_invariant, gain: 0.65, init: {error_deg: [10.0, 179.0], axis: random}}
runs: {count: 1000, seed: 1}
stop: {depth: 100.0}
"""


def problem(text: str, runs: int):
    cfg, _ = load_config(text=text, runs=runs)
    truth = simulate_truth(cfg)
    sensors = build_sensors(cfg, truth.model)
    streams = {s.name: s.measure(truth, stream(1, s.name)) for s in sensors}
    return cfg, build_problem(cfg, truth, sensors, streams)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=1000)
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args()
    for label, text in (("high_gain (the high-gain observer paper)", HIGH_GAIN), ("so3_invariant (the SO(3) observer paper)", SO3)):
        cfg, prob = problem(text, args.runs)
        obs = OBSERVERS.get(cfg.observers[0].type)(cfg.observers[0])
        n_steps = len(prob.time) - 1
        best = best_ref = np.inf
        for _ in range(args.repeat):
            t0 = time.perf_counter()
            obs.run(prob, np.random.default_rng(0))
            best = min(best, time.perf_counter() - t0)
            best_ref = min(best_ref, reference(args.runs, n_steps))
        print(f"{label}: {args.runs} runs x {n_steps} steps, best of {args.repeat}")
        print(f"  time        {best:7.2f} s")
        print(f"  reference   {best_ref:7.2f} s   bare numpy RK4 loop of the same size")
        print(f"  ratio       {best / best_ref:7.2f} x reference")
        print(f"  per step    {1e6 * best / n_steps:7.1f} us for all {args.runs} runs")


if __name__ == "__main__":
    main()
