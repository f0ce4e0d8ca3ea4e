"""Benchmark: the seed 003 Table 1 study (100 insertions x 5,334 steps at 100 Hz, 3 sensors, batched UKF),
against FilterPy's UnscentedKalmanFilter on one insertion of the same model and data.

Targets: the whole study (truth + sensors + UKF) under 5 s on 2 cores, and needlecli's UKF at least 50x
faster than FilterPy per insertion-step (one run advanced by one 10 ms filter tick).

The FilterPy filter is set up to compute what needlecli's does: Merwe sigma points (alpha 1e-3, beta 2,
kappa 0), fx = the modified unicycle's RK4 step of needlecli (``model.step`` on one state, the run's
inputs), per tick the measurements that became available (roll only: 1-d h; position + roll + curvature:
5-d h, with R reset by distance to the transducer from the measured position), Q, R and P0 of the config,
angle-aware mean, residual and state addition, the curvature constraint, and the needlecli run's estimate
at step 0 as its initial state. Its estimate must agree with needlecli's for that run (max position
difference printed; the script exits 1 if it exceeds 1e-3 mm, since the speed ratio is then meaningless).
FilterPy draws the update's sigma points from the predicted (x, P), Q included; a UKF that reuses the
propagated points instead stays within about 1e-5 mm of it here, so the check cannot tell the two apart.

Times are noisy on a shared machine, so the study and the UKF are also printed as ratios against the bare
numpy RK4 reference of ``bench_simulate.py`` (100 runs, same number of steps) measured in the same run.

FilterPy is optional (``pip install 'needlecli[bench]'``); without it the comparison is skipped.

    python benchmarks/bench_ukf.py [--repeat 2] [--filterpy-steps N] [--run 0]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
from bench_simulate import reference  # same folder: the script's directory is on sys.path

from needlecli.experiments.config import load_config
from needlecli.experiments.runner import build_problem, build_sensors, run_experiment
from needlecli.experiments.truth import stream
from needlecli.observers import OBSERVERS

ROOT = Path(__file__).resolve().parent.parent
CONFIG = "configs/seed003/table1.yaml"
STUDY_TARGET_S = 5.0
RATIO_TARGET = 50.0
AGREE_MM = 1e-3

# what each channel of the study measures, as states of the modified unicycle (checked against needlecli's h)
H_STATES = {"us3d": ("x", "y", "z"), "robot": ("gamma",), "swe": ("kappa",)}


def _wrap(a):
    """Angles to [-pi, pi)."""
    return (a + np.pi) % (2.0 * np.pi) - np.pi


def time_study(cfg, text, repeat):
    """Best-of-``repeat`` wall time of the whole study, and the last result."""
    best = np.inf
    for _ in range(repeat):
        t0 = time.perf_counter()
        res = run_experiment(cfg, text, write=False)
        best = min(best, time.perf_counter() - t0)
    return best, res


def time_ukf(cfg, res, repeat):
    """Best-of-``repeat`` time of the UKF alone on the study's truth and measurements."""
    sensors = build_sensors(cfg, res.truth.model)
    problem = build_problem(cfg, res.truth, sensors, res.measurements)
    (settings,) = [o for o in cfg.observers if o.type == "ukf"]
    best = np.inf
    for _ in range(repeat):
        obs = OBSERVERS.get(settings.type)(settings)
        t0 = time.perf_counter()
        post = obs.run(problem, stream(cfg.runs.seed, f"observer/{obs.name}"))  # the runner's stream
        best = min(best, time.perf_counter() - t0)
    if not np.array_equal(post.state, res.estimates[obs.name].state, equal_nan=True):
        sys.exit("the UKF run alone does not reproduce the study's estimate: the timing would not be of the same work")
    return best, obs.name


def filterpy_run(cfg, res, obs_name, run, steps):
    """FilterPy's UKF over the first ``steps`` ticks of insertion ``run``: (seconds, estimates, h use counts)."""
    from filterpy.kalman import MerweScaledSigmaPoints, UnscentedKalmanFilter

    (s,) = [o for o in cfg.observers if o.type == "ukf"]
    assert s.model is None and not s.params and s.rate is None and s.kappa_reset is None, "set up for Table 1"
    model = res.truth.model
    params = model.param_arrays()
    names, n = model.state_names, model.n
    ang_x = model.angle_mask
    dt = float(res.truth.time[1] - res.truth.time[0])
    inputs = np.ascontiguousarray(res.truth.inputs[run])
    Q = np.diag([s.q.get(k, 0.0) ** 2 for k in names])
    P0 = np.diag(np.maximum([s.p0.get(k, s.init.std.get(k, 0.0) ** 2) for k in names], 1e-12))
    x0 = res.estimates[obs_name].state[run, 0]
    i_kappa = model.index("kappa")

    # measurement channels in the filter's order, the state each component is, the tick each sample arrives
    sensors = {sn.name: sn for sn in build_sensors(cfg, model)}
    chans = []
    for name, spec in s.measurements.items():
        st = res.measurements[name]
        idx = np.array([model.index(k) for k in H_STATES[name]])
        xr = np.random.default_rng(0).normal(size=(4, n)) * 0.1
        assert np.allclose(sensors[name].h(xr), xr[:, idx]), f"H_STATES[{name!r}] is not needlecli's h"
        sigma = np.broadcast_to(np.asarray(spec.sigma, dtype=float), (len(idx),)).copy()
        avail = np.ceil(st.t_available / dt - 1e-9).astype(np.int64)
        chans.append((name, st, idx, sigma, spec.growth, sensors[name].angle_channels, avail))
    arrivals: dict[int, list[tuple[int, int]]] = {}
    for ci, (*_, avail) in enumerate(chans):
        for j, k in enumerate(avail):
            if 0 < k <= steps and chans[ci][1].valid[run, j]:
                arrivals.setdefault(int(k), []).append((ci, j))  # samples at t = 0 only initialise

    # one h per combination of channels that arrive together (here: roll alone 1-d, all three 5-d)
    hs, ang_z = {}, {}
    for key in {tuple(sorted({ci for ci, _ in a})) for a in arrivals.values()}:
        idx = np.concatenate([chans[ci][2] for ci in key])
        hs[key] = lambda x, _idx=idx: x[_idx]
        mask = np.concatenate([chans[ci][5] for ci in key])
        assert ang_z.get(len(idx), mask).tolist() == mask.tolist(), "two measurement layouts of one size"
        ang_z[len(idx)] = mask
    labels = {key: "+".join(chans[ci][0] for ci in key) + f" ({len(hs[key](x0))}-d h)" for key in hs}
    counts = dict.fromkeys(sorted(labels.values(), key=len), 0)

    def residual_x(a, b):
        d = a - b
        d[ang_x] = _wrap(d[ang_x])
        return d

    def x_mean(sigmas, wm):  # as needlecli: residuals about the central point, wrapped
        ref = sigmas[0]
        d = sigmas - ref
        d[:, ang_x] = _wrap(d[:, ang_x])
        m = ref + wm @ d
        m[ang_x] = _wrap(m[ang_x])
        return m

    def residual_z(a, b):
        d = np.subtract(a, b)
        m = ang_z[d.shape[-1]]
        d[..., m] = _wrap(d[..., m])
        return d

    def z_mean(sigmas, wm):
        ref = sigmas[0]
        d = sigmas - ref
        mask = ang_z[d.shape[-1]]
        d[:, mask] = _wrap(d[:, mask])
        m = ref + wm @ d
        m[mask] = _wrap(m[mask])
        return m

    def state_add(x, dx):
        y = x + dx
        y[ang_x] = _wrap(y[ang_x])
        return y

    def fx(x, dt, u):
        return model.step(x, u, params, dt)

    points = MerweScaledSigmaPoints(n=n, alpha=s.alpha, beta=s.beta, kappa=s.kappa)
    kf = UnscentedKalmanFilter(dim_x=n, dim_z=5, dt=dt, hx=None, fx=fx, points=points, x_mean_fn=x_mean,
                               z_mean_fn=z_mean, residual_x=residual_x, residual_z=residual_z, state_add=state_add)
    kf.x = x0.copy()
    kf.P = P0.copy()
    kf.Q = Q
    est = np.empty((steps + 1, n))
    est[0] = kf.x

    t0 = time.perf_counter()
    for k in range(1, steps + 1):
        kappa_prev = kf.x[i_kappa]
        kf.predict(u=inputs[k - 1])
        arrived = arrivals.get(k)
        if arrived:
            key = tuple(sorted({ci for ci, _ in arrived}))
            zs, rs = [], []
            for ci in key:
                name, st, idx, sigma, growth, _, _ = chans[ci]
                j = max(j for c, j in arrived if c == ci)  # the latest sample of the tick
                y = st.value[run, j]
                sig = sigma if growth is None else sigma * growth.factor(y)
                zs.append(y)
                rs.append(sig**2)
            kf.update(np.concatenate(zs), R=np.diag(np.concatenate(rs)), hx=hs[key])
            counts[labels[key]] += 1
        if not 0.0 <= kf.x[i_kappa] <= s.kappa_max:  # curvature constraint: keep the previous estimate
            kf.x[i_kappa] = kappa_prev
        est[k] = kf.x
    return time.perf_counter() - t0, est, counts


def verdict(ok: bool) -> str:
    return "MET" if ok else "NOT MET"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=2, help="best of this many runs of each timed part")
    ap.add_argument("--filterpy-steps", type=int, default=None,
                    help="FilterPy on this prefix of the insertion and scaled (default: all steps)")
    ap.add_argument("--run", type=int, default=0, help="the insertion FilterPy filters")
    args = ap.parse_args()

    cfg, text = load_config(ROOT / CONFIG)
    t_study, res = time_study(cfg, text, args.repeat)
    t_ukf, obs_name = time_ukf(cfg, res, args.repeat)
    runs, steps = res.truth.states.shape[0], len(res.truth.time) - 1
    t_ref = min(reference(runs, steps) for _ in range(args.repeat))
    us_ukf = 1e6 * t_ukf / (runs * steps)

    print(f"seed 003 Table 1 ({CONFIG}): "
          f"{runs} insertions x {steps} steps (80 mm at 1.5 mm/s, 100 Hz), 3 sensors, batched UKF   best of {args.repeat}")
    print(f"  study       {t_study:7.2f} s   truth + sensors + UKF (run_experiment, write=False)")
    print(f"  UKF alone   {t_ukf:7.2f} s   {us_ukf:7.2f} us per insertion-step")
    print(f"  reference   {t_ref:7.2f} s   bare numpy RK4 loop, {runs} runs x {steps} steps (bench_simulate.reference)")
    print(f"  ratios      study {t_study / t_ref:.1f} x reference, UKF {t_ukf / t_ref:.1f} x reference")

    ratio = None
    try:
        import filterpy
    except ImportError:
        filterpy = None
        print("\nFilterPy comparison SKIPPED: filterpy is not installed (pip install 'needlecli[bench]' or "
              "pip install filterpy)")
    if filterpy is not None:
        fp_steps = steps if args.filterpy_steps is None else max(1, min(args.filterpy_steps, steps))
        t_fp = np.inf
        for _ in range(args.repeat):
            t, est, counts = filterpy_run(cfg, res, obs_name, args.run, fp_steps)
            t_fp = min(t_fp, t)
        us_fp = 1e6 * t_fp / fp_steps
        ratio = us_fp / us_ukf
        ours = res.estimates[obs_name].state[args.run, : fp_steps + 1]
        dpos = np.linalg.norm(est[:, :3] - ours[:, :3], axis=-1)
        dmax = float(np.max(dpos))
        scope = "all steps" if fp_steps == steps else f"first {fp_steps} of {steps} steps, scaled per step"
        print(f"\nFilterPy {filterpy.__version__} UnscentedKalmanFilter, insertion {args.run}, {scope}   "
              f"best of {args.repeat}")
        print(f"  time        {t_fp:7.2f} s   {us_fp:7.1f} us per insertion-step"
              + ("" if fp_steps == steps else f"   ({t_fp * steps / fp_steps:.1f} s for the whole insertion)"))
        print("  updates     " + ", ".join(f"{v} x {k}" for k, v in counts.items()))
        print(f"  agreement   max |position - needlecli's| over the steps {dmax:.2e} mm "
              f"(at step {int(np.argmax(dpos))})   " + ("agree" if dmax <= AGREE_MM else f"DISAGREE (> {AGREE_MM} mm)"))
        print(f"  ratio       {ratio:7.1f} x   FilterPy / needlecli per insertion-step")

    print("\ntargets")
    print(f"  Table 1 study under {STUDY_TARGET_S:g} s on this 2-core machine: {t_study:.2f} s -> "
          f"{verdict(t_study < STUDY_TARGET_S)}")
    if ratio is None:
        print(f"  UKF at least {RATIO_TARGET:g}x faster than FilterPy per insertion-step: not measured (no filterpy)")
    else:
        print(f"  UKF at least {RATIO_TARGET:g}x faster than FilterPy per insertion-step: {ratio:.1f}x -> "
              f"{verdict(ratio >= RATIO_TARGET)}")
        if dmax > AGREE_MM:
            sys.exit(f"FilterPy and needlecli disagree by {dmax:.2e} mm: the speed ratio compares different work")


if __name__ == "__main__":
    main()
