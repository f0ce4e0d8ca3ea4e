"""Benchmark: ``needle sweep`` executors.

1. Scaling on local processes: the same small UKF cells (each about a second of work) on 2 worker
   processes against 1, as cells per second and their ratio (ideal: 2.0 on 2 free cores): on warm
   workers (the executor's own pool, started and importing needlecli before the clock), and for the whole
   ``run_sweep`` call (worker start included).
2. Overhead per cell: trivial cells (one run of a few steps, no observer) run inline in this process, on a
   local process pool of 1 worker and on a Dask cluster of 1 worker (started before the clock; the
   client connects within it), printed as the extra time per cell and as ratios to inline.

    python benchmarks/bench_sweep.py [--cells 8] [--trivial 40]
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from pathlib import Path

from needlecli.experiments.studies.sweep import Grid, plan_sweep, run_cell, run_sweep
from needlecli.experiments.studies.sweep.execution import _pin_worker_threads, _thread_env

SMALL = """
name: bench_sweep_cell
model: {type: modified_unicycle, params: {kappa: 0.005, beta_cut: 0.035}, param_std: {kappa: 0.001}}
inputs: {v: 1.5, u: 0.0}
sensors:
  - {name: us3d, type: position, rate: 1.0, sigma: 0.3}
  - {name: robot, type: encoder, rate: 100.0, channels: [roll], sigma: 0.0035}
  - {name: swe, type: elastography, rate: 1.0, sigma: 0.001}
observers:
  - name: ukf
    type: ukf
    q: {x: 2.0e-3, y: 2.0e-3, z: 2.0e-3, alpha: 2.0e-5, beta: 2.0e-5, gamma: 5.0e-4, kappa: 2.0e-6}
    p0: {x: 1.0, y: 1.0, z: 1.0, alpha: 5.0e-3, beta: 5.0e-3, gamma: 0.1, kappa: 2.0e-6}
    init: {from: truth, std: {alpha: 0.0873, beta: 0.0873}, first_measurement: {x: us3d.x, y: us3d.y, z: us3d.z}}
runs: {count: 20, seed: 1}
stop: {depth: 12.0}
output: {store_every: 50, covariance: diag}
"""
TRIVIAL = """
name: bench_sweep_trivial
model: {type: modified_unicycle, params: {kappa: 0.005}}
inputs: {v: 1.5, u: 0.0}
sensors: [{name: us3d, type: position, rate: 10.0, sigma: 0.3}]
runs: {count: 1, seed: 1}
stop: {depth: 0.15}
"""


def _sweep(tmp: Path, text: str, n: int, tag: str):
    cfg = tmp / f"{tag}.yaml"
    cfg.write_text(text)
    grid = Grid.model_validate({"grid": {"runs.seed": list(range(n))}})
    return plan_sweep(cfg, grid, out_dir=tmp / tag)


def timed(cells, out: Path, **kw) -> float:
    t = time.perf_counter()
    res = run_sweep(cells, out_dir=out, **kw)
    dt = time.perf_counter() - t
    assert res.failed == 0, [o.error for o in res.outcomes.values() if o.status == "failed"]
    return dt


def _warm() -> None:
    import needlecli.experiments.simulation.runner  # noqa: F401  (what a cell imports first)


def warm_pool_time(cells, workers: int) -> float:
    """Seconds for the cells on a pool of ``workers`` processes started (and warmed) before the clock."""
    import multiprocessing as mp
    from concurrent.futures import ProcessPoolExecutor, wait

    pool = ProcessPoolExecutor(max_workers=workers, mp_context=mp.get_context("spawn"), initializer=_pin_worker_threads)
    try:
        with _thread_env():
            wait([pool.submit(_warm) for _ in range(workers)])
        t = time.perf_counter()
        outs = [f.result() for f in [pool.submit(run_cell, c) for c in cells]]
        dt = time.perf_counter() - t
    finally:
        pool.shutdown()
    assert all(o.status == "ok" for o in outs), [o.error for o in outs]
    return dt


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cells", type=int, default=8, help="UKF cells for the scaling measurement")
    ap.add_argument("--trivial", type=int, default=40, help="trivial cells for the overhead measurement")
    args = ap.parse_args()
    load = os.getloadavg()[0]
    if load > 0.5:
        print(f"note: load average {load:.1f} before the run: other processes compete for the "
              f"{os.cpu_count()} CPUs, and the scaling below understates what free cores give")
    with tempfile.TemporaryDirectory() as d:
        tmp = Path(d)
        cells = _sweep(tmp, SMALL, args.cells, "small")
        t_inline = timed(cells[:1], tmp / "warm", executor="inline")  # one cell in this process, for scale
        w1, w2 = warm_pool_time(cells, 1), warm_pool_time(cells, 2)
        t1 = timed(cells, tmp / "w1", executor="local", workers=1)
        t2 = timed(cells, tmp / "w2", executor="local", workers=2)
        print(f"sweep scaling: {args.cells} cells (UKF, 20 runs x 800 steps; {t_inline:.2f} s for one cell inline), "
              f"{os.cpu_count()} CPUs")
        print("              warm workers             whole run_sweep (worker start included)")
        print(f"  1 worker    {args.cells / w1:6.2f} cells/s ({w1:5.1f} s)   {args.cells / t1:6.2f} cells/s ({t1:5.1f} s)")
        print(f"  2 workers   {args.cells / w2:6.2f} cells/s ({w2:5.1f} s)   {args.cells / t2:6.2f} cells/s ({t2:5.1f} s)")
        print(f"  ratio 2/1   {w1 / w2:6.2f}                    {t1 / t2:6.2f}            (ideal 2.00)")

        triv = _sweep(tmp, TRIVIAL, args.trivial, "trivial")
        ti = timed(triv, tmp / "ti", executor="inline")
        tl = timed(triv, tmp / "tl", executor="local", workers=1)
        print(f"overhead per trivial cell ({args.trivial} cells of 1 run x 7 steps, results file written):")
        print(f"  inline      {1e3 * ti / args.trivial:7.1f} ms per cell")
        tw = warm_pool_time(triv, 1)
        print(f"  local, 1 process   +{1e3 * (tw - ti) / args.trivial:6.1f} ms per cell on a warm worker "
              f"(ratio {tw / ti:.2f}); +{1e3 * (tl - ti) / args.trivial:.1f} ms with the worker's start (ratio {tl / ti:.2f})")
        try:
            from distributed import LocalCluster
        except ImportError:
            print("  dask: skipped (pip install 'needlecli[dask]')")
            return
        import logging

        logging.getLogger("distributed").setLevel(logging.WARNING)
        with LocalCluster(n_workers=1, threads_per_worker=1, processes=True, dashboard_address=":0") as cluster:
            timed(triv[:2], tmp / "tdw", executor="dask", scheduler=cluster.scheduler_address)  # warm the worker
            td = timed(triv, tmp / "td", executor="dask", scheduler=cluster.scheduler_address)
        print(f"  dask, 1 worker     +{1e3 * (td - ti) / args.trivial:6.1f} ms per cell "
              f"(ratio {td / ti:.2f}, scheduler, transfer and client connection)")


if __name__ == "__main__":
    main()
