"""Benchmark: ``needle sweep`` executors.

1. Scaling on local processes: the same small UKF cells (each about a second of work) on 2 worker
   processes against 1, as cells per second and their ratio (ideal: 2.0 on 2 free cores): on warm
   workers (the executor's own pool, started and importing needlecli before the clock), and for the whole
   ``run_sweep`` call (worker start included).
2. Overhead per cell: trivial cells (one run of a few steps, no observer) run inline in this process, on a
   local process pool of 1 worker and on a Dask cluster of 1 worker (started before the clock; the
   client connects within it), printed as the extra time per cell and as ratios to inline.
3. Table 1 on Dask (issue 27): 8 cells of the multi-rate UKF paper's Table 1 study (``runs.seed`` 0 to 7, 100 insertions
   each, no covariances stored) on a local Dask cluster of 1 and of 2 workers, one core each
   (``NEEDLECLI_THREADS=1``), the kernel cache warm, inline in this process beside them (one core too):
   target 2 workers at least 1.6x as fast as 1. Then the same sweep on 2 workers with an empty kernel
   cache: the compilations each worker made, summed per kernel (target: each kernel compiled once, by
   one worker, the other loading what it saved).

    python benchmarks/bench_sweep.py [--cells 8] [--trivial 40] [--table1 8]
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path
from unittest import mock

from needlecli.experiments.studies.sweep import Grid, plan_sweep, run_cell, run_sweep
from needlecli.experiments.studies.sweep.execution import _pin_worker_threads, _thread_env

ROOT = Path(__file__).resolve().parent.parent
TABLE1 = ROOT / "configs" / "multirate-ukf-us3d" / "table1.yaml"
DASK_RATIO = 1.6

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


def compile_counts() -> dict[str, int]:
    """Run on a worker: how many times this process compiled each kernel of needlecli for each of its
    signatures (numba's cache misses of every dispatcher of the kernel modules; a kernel loaded from the
    cache is not counted)."""
    from numba.core.registry import CPUDispatcher

    out: dict[str, int] = {}
    for name, mod in list(sys.modules.items()):
        if not name.startswith("needlecli.kernels.") or mod is None:
            continue
        for attr, obj in vars(mod).items():
            if isinstance(obj, CPUDispatcher) and obj.__module__ == name:
                for sig, n in obj.stats.cache_misses.items():
                    out[f"{name.rsplit('.', 1)[1]}.{attr}{sig}"] = n
    return out


def _warm_kernels(cell) -> None:
    """Run on a worker: one cell into a scratch folder, so that the worker has loaded every kernel before
    the clock (as it has after its first cell of a sweep)."""
    import dataclasses

    with tempfile.TemporaryDirectory() as d:
        run_cell(dataclasses.replace(cell, path=str(Path(d) / "warm.h5")))


def table1_on_dask(tmp: Path, n: int) -> dict | None:
    """Item 3: ``n`` cells of Table 1 inline and on 1 and 2 Dask workers (one core each), warm; then 2
    workers on an empty kernel cache, with their compilations per kernel."""
    try:
        from distributed import Client, LocalCluster
    except ImportError:
        print("table 1 on dask: skipped (pip install 'needlecli[dask]')")
        return None
    import logging

    logging.getLogger("distributed").setLevel(logging.WARNING)
    grid = Grid.model_validate({"fixed": {"output.covariance": "none"}, "grid": {"runs.seed": list(range(n))}})
    cells = plan_sweep(TABLE1, grid, out_dir=tmp / "t1")
    one_core = {"NEEDLECLI_THREADS": "1", "NEEDLECLI_COLD": "wait"}
    with mock.patch.dict(os.environ, one_core):
        timed(cells[:1], tmp / "t1_warm", executor="inline")  # the kernels in the cache before any clock
        t_inline = timed(cells, tmp / "t1_inline", executor="inline")
    t = {}
    for k in (1, 2):
        with LocalCluster(n_workers=k, threads_per_worker=1, processes=True, dashboard_address=":0",
                          env=one_core) as cluster, Client(cluster) as client:
            client.run(_warm_kernels, cells[0])  # workers started, their kernels loaded, before the clock
            t[k] = timed(cells, tmp / f"t1_dask{k}", executor="dask", scheduler=cluster.scheduler_address)
    cache = tmp / "t1_cold_cache"
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=":0",
                      env={**one_core, "NEEDLECLI_KERNEL_CACHE": str(cache)}) as cluster, Client(cluster) as client:
        t_cold = timed(cells, tmp / "t1_cold", executor="dask", scheduler=cluster.scheduler_address)
        per_worker = client.run(compile_counts)
    total: dict[str, int] = {}
    for counts in per_worker.values():
        for kname, c in counts.items():
            total[kname] = total.get(kname, 0) + c
    twice = {kname: c for kname, c in total.items() if c > 1}
    print(f"table 1 on dask: {n} cells of {TABLE1.relative_to(ROOT)} (runs.seed 0..{n - 1}, 100 insertions each, "
          "covariances not stored), one core per worker (NEEDLECLI_THREADS=1), warm kernel cache")
    print(f"  inline        {t_inline:6.1f} s   ({n / t_inline:.2f} cells/s, in this process)")
    print(f"  dask, 1 wkr   {t[1]:6.1f} s   ({n / t[1]:.2f} cells/s)")
    print(f"  dask, 2 wkr   {t[2]:6.1f} s   ({n / t[2]:.2f} cells/s)   2 workers / 1: {t[1] / t[2]:.2f}x "
          f"(target >= {DASK_RATIO:g}x)")
    print(f"  cold cache, 2 workers: {t_cold:.1f} s; {len(total)} kernel signature(s) compiled, "
          + ("each (signature) once" if not twice else f"some more than once: {json.dumps(twice)}")
          + "; per worker: " + ", ".join(f"{sum(c.values())}" for c in per_worker.values()))
    return {"ratio": t[1] / t[2], "once": not twice, "compiled": len(total)}


def write_targets(path: Path | None, r: dict | None) -> None:
    """Item 3's rows of the benchmark page's targets table."""
    if path is None or r is None:
        return
    rows = [{"target": f"an 8-cell sweep of Table 1 on 2 local Dask workers (one core each): at least {DASK_RATIO:g}x "
                       "as fast as on 1 (warm kernel cache)",
             "measured": f"{r['ratio']:.2f}x", "verdict": "MET" if r["ratio"] >= DASK_RATIO else "NOT MET"},
            {"target": "the same sweep on 2 Dask workers and an empty kernel cache: each kernel compiled once",
             "measured": f"{r['compiled']} kernel signatures, " + ("each compiled once" if r["once"] else
                                                                   "some more than once"),
             "verdict": "MET" if r["once"] else "NOT MET"}]
    path.write_text(json.dumps(rows, indent=1))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cells", type=int, default=8, help="UKF cells for the scaling measurement")
    ap.add_argument("--trivial", type=int, default=40, help="trivial cells for the overhead measurement")
    ap.add_argument("--table1", type=int, default=8, help="cells of the Table 1 sweep on Dask (0: skip it)")
    ap.add_argument("--only-table1", action="store_true", help="item 3 alone")
    ap.add_argument("--json", type=Path, help="also write item 3's targets to this file (tools/bench_page.py)")
    args = ap.parse_args()
    os.environ.setdefault("NEEDLECLI_COLD", "wait")
    load = os.getloadavg()[0]
    if load > 0.5:
        print(f"note: load average {load:.1f} before the run: other processes compete for the "
              f"{os.cpu_count()} CPUs, and the scaling below understates what free cores give")
    with tempfile.TemporaryDirectory() as d:
        tmp = Path(d)
        if args.only_table1:
            write_targets(args.json, table1_on_dask(tmp, args.table1))
            return
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
        if args.table1:
            write_targets(args.json, table1_on_dask(tmp, args.table1))


if __name__ == "__main__":
    main()
