"""Benchmark: EM (the magnetic needle EM paper, Algorithm 1) on the full 48-trial synthetic study, both models (MNM, BiNM),
100 iterations at most (goal: under 60 s on 2 cores; the two models run in parallel processes).

Times are noisy on a shared machine, so the fit is also printed as a ratio against a reference measured
in the same run: the bare numpy RK4 loop of ``bench_simulate.py`` (1,000 runs x 5,333 steps).

    python benchmarks/bench_em.py [--config configs/em-magnetic-pratt2022/study.yaml] [--workers 2]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_simulate import reference  # noqa: E402

from needlecli.experiments.studies.fit import fit_trials, load_trials  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--config", default=str(ROOT / "configs" / "em-magnetic-pratt2022" / "study.yaml"))
    ap.add_argument("--workers", type=int, default=2)
    args = ap.parse_args()
    t0 = time.perf_counter()
    trials = load_trials(args.config)
    t_sim = time.perf_counter() - t0
    t0 = time.perf_counter()
    out = fit_trials(trials, models=["mnm", "binm"], workers=args.workers)
    t_fit = time.perf_counter() - t0
    t_ref = reference(1000, 5333)
    n = trials.truth.states.shape[0]
    print(f"EM: {n} trials x 2 models (the magnetic needle EM paper's study), at most {trials.cfg.fit.em.max_iter} iterations, "
          f"{args.workers} worker(s)")
    for name, mf in out.fits.items():
        r = mf.result
        st, cnt = np.unique(r.status, return_counts=True)
        print(f"  {name:5s} {mf.seconds:7.2f} s   iterations median {int(np.median(r.iterations))}, "
              f"max {int(r.iterations.max())}; E-step passes {int(r.estep_passes.sum())}; "
              + ", ".join(f"{c} {s}" for s, c in zip(st, cnt)))
    print(f"  simulate    {t_sim:7.2f} s   (truth and measurements)")
    print(f"  fit (wall)  {t_fit:7.2f} s   (goal < 60 s on 2 cores)")
    print(f"  reference   {t_ref:7.2f} s   bare numpy RK4 loop, 1000 runs x 5333 steps (bench_simulate)")
    print(f"  ratio       {t_fit / t_ref:7.2f} x reference")


if __name__ == "__main__":
    main()
