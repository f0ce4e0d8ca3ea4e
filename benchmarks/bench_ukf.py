"""Benchmark: the multi-rate UKF paper's Table 1 study (100 insertions x 5,334 steps at 100 Hz, 3 sensors, batched UKF),
against FilterPy's UnscentedKalmanFilter on one insertion of the same model and data.

Targets: the whole study (truth + sensors + UKF) under 5 s on 2 cores, and needlecli's UKF at least 50x
faster than FilterPy per insertion-step (one run advanced by one 10 ms filter tick).

The FilterPy filter is set up to compute what needlecli's does, written as FilterPy users write it: Merwe
sigma points (alpha 1e-3, beta 2, kappa 0), fx = the modified unicycle's RK4 step on one state with
scalar ``math`` sin/cos (the run's inputs), per tick the measurements that became available (roll only: 1-d h; position + roll + curvature:
5-d h, with R reset by distance to the transducer from the measured position), Q, R and P0 of the config,
angle-aware mean, residual and state addition, the curvature constraint, and the needlecli run's estimate
at step 0 as its initial state. Its estimate must agree with needlecli's for that run (max position
difference printed; the script exits 1 if it exceeds 1e-6 mm, since the speed ratio is then meaningless).
FilterPy draws the update's sigma points from the predicted (x, P), Q included; a UKF that reuses the
propagated points instead stays within about 1e-5 mm of it here, so the check cannot tell the two apart.

Times are noisy on a shared machine, so the study and the UKF are also printed as ratios against the bare
numpy RK4 reference of ``bench_simulate.py`` (100 runs, same number of steps) measured in the same run.

FilterPy is optional (``pip install 'needlecli[bench]'``); without it the comparison is skipped.

    python benchmarks/bench_ukf.py [--repeat 2] [--filterpy-steps N] [--run 0]
"""

from __future__ import annotations

import argparse
import contextlib
import math
import os
import sys
import time
from pathlib import Path

import numpy as np
from bench_simulate import reference  # same folder: the script's directory is on sys.path

from needlecli.experiments.config.load import load_config
from needlecli.experiments.simulation.runner import build_problem, build_sensors, run_experiment
from needlecli.experiments.simulation.truth import stream
from needlecli.observers import OBSERVERS

ROOT = Path(__file__).resolve().parent.parent
CONFIG = "configs/multirate-ukf-us3d/table1.yaml"
RATIO_TARGET = 50.0
AGREE_MM = 1e-6

# what each channel of the study measures, as states of the modified unicycle (checked against needlecli's h)
H_STATES = {"us3d": ("x", "y", "z"), "robot": ("gamma",), "swe": ("kappa",)}


def _wrap(a):
    """Angles to [-pi, pi)."""
    return (a + np.pi) % (2.0 * np.pi) - np.pi


@contextlib.contextmanager
def kernels_mode(mode: str):
    """Run the block on the compiled kernels (``auto``) or on the numpy reference (``numpy``)."""
    before = os.environ.get("NEEDLECLI_KERNELS")
    os.environ["NEEDLECLI_KERNELS"] = mode
    try:
        yield
    finally:
        if before is None:
            del os.environ["NEEDLECLI_KERNELS"]
        else:
            os.environ["NEEDLECLI_KERNELS"] = before


def time_study(cfg, text, repeat):
    """Best-of-``repeat`` wall time of the whole study (in process, no file), and the last result."""
    best = np.inf
    for _ in range(repeat):
        t0 = time.perf_counter()
        res = run_experiment(cfg, text, write=False)
        best = min(best, time.perf_counter() - t0)
    return best, res


def time_ukf(cfg, res, repeat):
    """Best-of-``repeat`` time of the UKF alone on the study's truth and measurements, and its estimate."""
    sensors = build_sensors(cfg, res.truth.model)
    problem = build_problem(cfg, res.truth, sensors, res.measurements)
    (settings,) = [o for o in cfg.observers if o.type == "ukf"]
    best = np.inf
    for _ in range(repeat):
        obs = OBSERVERS.get(settings.type)(settings)
        t0 = time.perf_counter()
        post = obs.run(problem, stream(cfg.runs.seed, f"observer/{obs.name}"))  # the runner's stream
        best = min(best, time.perf_counter() - t0)
    return best, obs.name, post


def filterpy_reference(cfg, res, obs_name, run, steps, repeat):
    """FilterPy on insertion ``run``: ``(us per step, estimates, update counts, FilterPy's version)``, or
    None when FilterPy is not installed."""
    try:
        import filterpy
    except ImportError:
        return None
    t_fp = np.inf
    for _ in range(repeat):
        t, est, counts = filterpy_run(cfg, res, obs_name, run, steps)
        t_fp = min(t_fp, t)
    return 1e6 * t_fp / steps, est, counts, filterpy.__version__


def agreement(est, state) -> tuple[float, int]:
    """Largest tip-position difference (mm) between FilterPy's estimates and one run of needlecli's."""
    dpos = np.linalg.norm(est[:, :3] - state[: len(est), :3], axis=-1)
    return float(np.max(dpos)), int(np.argmax(dpos))


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
    Q = np.diag([s.q.get(k, 0.0) ** 2 * dt for k in names])  # q per sqrt(s): the variance of one tick
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

    beta_cut = float(params["beta_cut"])

    def f(x, v, w):  # the modified unicycle (the multi-rate UKF paper, eq. 1) on one state, with scalar math
        sa, ca = math.sin(x[3]), math.cos(x[3])
        sb, cb = math.sin(x[4]), math.cos(x[4])
        sg, cg = math.sin(x[5]), math.cos(x[5])
        kv = x[6] * v
        g_r = w - kv * cg * sb / cb  # the roll rate
        cut = 0.5 * beta_cut * g_r
        return np.array([v * sb, -v * cb * sa, v * cb * ca, (kv * cg - cut * sg) / cb, kv * sg + cut * cg, g_r, 0.0])

    def fx(x, dt, u):  # RK4 over the filter tick, inputs held (as FilterPy's examples write fx)
        v, w = u
        k1 = f(x, v, w)
        k2 = f(x + 0.5 * dt * k1, v, w)
        k3 = f(x + 0.5 * dt * k2, v, w)
        k4 = f(x + dt * k3, v, w)
        return x + dt / 6.0 * (k1 + 2.0 * k2 + 2.0 * k3 + k4)

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
    with kernels_mode("numpy"):
        t_study_np, res = time_study(cfg, text, 1)
        t_ukf_np, obs_name, post_np = time_ukf(cfg, res, args.repeat)
    with kernels_mode("auto"):
        t_study, _ = time_study(cfg, text, args.repeat)
        t_ukf, _, post = time_ukf(cfg, res, args.repeat)
    runs, steps = res.truth.states.shape[0], len(res.truth.time) - 1
    t_ref = min(reference(runs, steps) for _ in range(args.repeat))
    us_ukf, us_np = 1e6 * t_ukf / (runs * steps), 1e6 * t_ukf_np / (runs * steps)
    dk = float(np.max(np.abs(post.state - post_np.state)))

    print(f"the multi-rate UKF paper's Table 1 ({CONFIG}): "
          f"{runs} insertions x {steps} steps (80 mm at 1.5 mm/s, 100 Hz), 3 sensors, batched UKF   best of {args.repeat}")
    print(f"  study       {t_study:7.2f} s compiled, {t_study_np:7.2f} s numpy   truth + sensors + UKF (run_experiment, no file)")
    print(f"  UKF alone   {t_ukf:7.2f} s compiled ({us_ukf:5.2f} us per insertion-step), {t_ukf_np:7.2f} s numpy "
          f"({us_np:5.2f} us): {t_ukf_np / t_ukf:.1f}x; largest difference {dk:.1e}")
    print(f"  reference   {t_ref:7.2f} s   bare numpy RK4 loop, {runs} runs x {steps} steps (bench_simulate.reference)")

    fp_steps = steps if args.filterpy_steps is None else max(1, min(args.filterpy_steps, steps))
    ref = filterpy_reference(cfg, res, obs_name, args.run, fp_steps, args.repeat)
    if ref is None:
        print("\nFilterPy comparison SKIPPED: filterpy is not installed (pip install 'needlecli[bench]')")
        return
    us_fp, est, counts, version = ref
    d_np, at_np = agreement(est, post_np.state[args.run])
    d_k, _ = agreement(est, post.state[args.run])
    scope = "all steps" if fp_steps == steps else f"first {fp_steps} of {steps} steps, scaled per step"
    print(f"\nFilterPy {version} UnscentedKalmanFilter, fx with scalar math, insertion {args.run}, {scope}   "
          f"best of {args.repeat}")
    print(f"  time        {us_fp:7.1f} us per insertion-step   ({us_fp * steps * 1e-6:.1f} s for the whole insertion)")
    print("  updates     " + ", ".join(f"{v} x {k}" for k, v in counts.items()))
    print(f"  agreement   max |position - needlecli's| {d_np:.2e} mm (numpy path, at step {at_np}), {d_k:.2e} mm "
          f"(compiled)   " + ("agree" if max(d_np, d_k) <= AGREE_MM else f"DISAGREE (> {AGREE_MM} mm)"))
    print(f"  ratios      needlecli's UKF {us_fp / us_ukf:7.1f}x faster per insertion-step compiled, "
          f"{us_fp / us_np:6.1f}x on the numpy path")
    print("\ntargets")
    ratio = us_fp / us_ukf
    print(f"  UKF at least {RATIO_TARGET:g}x faster than FilterPy per insertion-step: {ratio:.1f}x -> "
          f"{verdict(ratio >= RATIO_TARGET)}")
    if max(d_np, d_k) > AGREE_MM:
        sys.exit(f"FilterPy and needlecli disagree by {max(d_np, d_k):.2e} mm: the speed ratio compares different work")


if __name__ == "__main__":
    main()
