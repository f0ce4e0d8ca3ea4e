"""Every compiled kernel (``needlecli.kernels``) against the numpy reference, on random inputs.

Tolerance 1e-10 (absolute, in the models' units) wherever the two compute the same thing in one go: a
model step, the truth simulation, a few filter ticks. A filter run of hundreds of ticks carries the
rounding of its first ticks along (seed 003's alpha = 1e-3 weights residuals by 7e4, and the position
integrates the angles): there the kernel must agree with the numpy path as well as the numpy path agrees
with itself when only its sin and cos change by an ulp.
"""

from __future__ import annotations

import contextlib
import dataclasses
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("numba")

from needlecli import kernels  # noqa: E402
from needlecli.experiments.config.load import load_config  # noqa: E402
from needlecli.experiments.simulation.runner import run_experiment  # noqa: E402
from needlecli.experiments.simulation.truth import simulate_truth  # noqa: E402
from needlecli.models import MODELS  # noqa: E402
from needlecli.numerics import so3_exp  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
ATOL = 1e-10


@pytest.fixture
def numpy_path(monkeypatch):
    """Run the reference: ``NEEDLECLI_KERNELS=numpy`` while the fixture's block runs."""

    class Switch:
        def __enter__(self):
            monkeypatch.setenv(kernels.ENV, "numpy")

        def __exit__(self, *exc):
            monkeypatch.delenv(kernels.ENV)

    monkeypatch.delenv(kernels.ENV, raising=False)
    return Switch()


# ---------------------------------------------------------------------------------------------- sin, cos
def test_sincos_within_an_ulp_of_libm_and_libm_outside_its_range():
    from needlecli.kernels.models import sincos_rows

    rng = np.random.default_rng(0)
    x = np.concatenate([rng.uniform(-4, 4, 20000), rng.uniform(-1e5, 1e5, 20000),
                        np.arange(-64, 65) * (np.pi / 4), np.arange(-64, 65) * (np.pi / 4) + 1e-9,
                        [0.0, -0.0, 1e-300, 5e-324, 2e6, -3e8, 1e300, np.inf, -np.inf, np.nan]])
    SC = np.empty((2, x.size))
    sincos_rows(x[None, :], 0, 1, SC, x.size)
    with np.errstate(invalid="ignore"):  # sin(inf) is NaN
        s, c = np.array([np.sin(v) for v in x]), np.array([np.cos(v) for v in x])
    fin = np.isfinite(x)
    for got, ref in ((SC[0], s), (SC[1], c)):
        assert np.array_equal(np.isnan(got), np.isnan(ref))
        err = np.abs(got[fin] - ref[fin]) / np.spacing(np.maximum(np.abs(ref[fin]), 1e-300))
        small = np.abs(x[fin]) < 8.0  # angles as the models see them: 1 ulp; up to 1e6 rad: 2
        assert err[small].max() <= 1.0 and err.max() <= 2.0


# ---------------------------------------------------------------------------------------------- models
def _random_states(name: str, model, rng, L: int) -> np.ndarray:
    x = rng.normal(size=(L, model.n)) * 0.5
    if name == "so3":
        return so3_exp(rng.normal(size=(L, 3)) * 2.0).reshape(L, 9)
    if name in ("mnm", "binm"):
        for sl in (slice(3, 6), slice(6, 9)):
            x[:, sl] *= rng.uniform(0.8, 1.2, (L, 1)) / np.linalg.norm(x[:, sl], axis=-1, keepdims=True)
        return x
    x[:, 3:6] = rng.uniform(-4 * np.pi, 4 * np.pi, (L, 3))  # angles past +-pi: the reduction by pi/2
    x[:, 4] = rng.uniform(-1.4, 1.4, L)  # inside the unicycle's domain, |beta| < pi/2
    x[:, :3] *= 100.0
    if model.n == 7:
        x[:, 6] = rng.uniform(0.0, 0.05, L)
    return x


@pytest.mark.parametrize("name", ["unicycle", "modified_unicycle", "so3", "mnm", "binm"])
def test_model_steps_equal_numpy(name):
    from needlecli.kernels.models import MODEL_IDS, step, step_fast

    rng = np.random.default_rng(hash(name) % 2**32)
    model = MODELS.get(name)()
    L = 37
    x = _random_states(name, model, rng, L)
    u = rng.normal(size=(L, model.m))
    p = {k: rng.uniform(0.5, 1.5) * max(float(v), 1e-3) for k, v in model.param_arrays().items()}
    P = np.stack([np.full(L, p[k]) for k in p]) if p else np.zeros((1, L))
    ref = model.step(x, u, {k: np.full(L, v) for k, v in p.items()}, 0.01)
    for fn in (step, step_fast):
        X = np.ascontiguousarray(x.T)
        fn(MODEL_IDS[name], X, np.ascontiguousarray(u.T), P, 0.01, L, np.zeros((4, max(model.n, 6), L)))
        np.testing.assert_allclose(X.T, ref, rtol=0, atol=ATOL)


def test_fused_step_falls_back_to_libm_for_huge_angles():
    from needlecli.kernels.models import MODIFIED_UNICYCLE, step_fast

    model = MODELS.get("modified_unicycle")()
    x = np.array([[0.0, 0.0, 0.0, 3e6, 0.2, -5e6, 0.005], [1.0, 2.0, 3.0, 0.1, 0.2, 0.3, 0.004]])
    u = np.array([[1.5, 0.3], [1.5, 0.3]])
    X = np.ascontiguousarray(x.T)
    P = np.array([[0.005, 0.005], [0.035, 0.035]])
    step_fast(MODIFIED_UNICYCLE, X, np.ascontiguousarray(u.T), P, 0.01, 2, np.zeros((4, 7, 2)))
    ref = model.step(x, u, {"kappa": 0.005, "beta_cut": 0.035}, 0.01)
    np.testing.assert_allclose(X.T, ref, rtol=1e-15, atol=ATOL)


# ---------------------------------------------------------------------------------------------- truth
TRUTH_CONFIGS = [
    ("configs/seed003/table1.yaml", ["stop.depth=20"]),  # process noise, per-run curvature
    ("configs/default.yaml", ["stop.depth=30"]),  # flips: the roll angle runs past pi
    ("configs/examples/two_layer_flips.yaml", []),  # tissue layers: the curvature along time
    ("configs/seed004/study.yaml", ["stop.time=5"]),  # input and parameter cases, MNM
    ("configs/examples/binm_singular.yaml", []),  # runs that stop at the singularity
    ("configs/seed001/helix_batch.yaml", []),  # SO(3)
    ("configs/seed000/simulation.yaml", []),  # unicycle
]


@pytest.mark.parametrize("path,overrides", TRUTH_CONFIGS, ids=[p for p, _ in TRUTH_CONFIGS])
def test_truth_equals_numpy(path, overrides, numpy_path):
    cfg, _ = load_config(ROOT / path, runs=5, overrides=overrides)
    with numpy_path:
        ref = simulate_truth(cfg)
    got = simulate_truth(cfg)
    np.testing.assert_allclose(got.states, ref.states, rtol=0, atol=ATOL * max(1.0, np.abs(ref.states).max() / 100))
    np.testing.assert_array_equal(got.status, ref.status)
    np.testing.assert_array_equal(got.reason, ref.reason)
    np.testing.assert_array_equal(got.event_time, ref.event_time)


def test_truth_reports_divergence_as_numpy(numpy_path):
    cfg, _ = load_config(ROOT / "configs/seed003/table1.yaml", runs=3,
                         overrides=["stop.depth=3", "process_noise.std.beta=80.0"])  # beta through pi/2 at once
    with numpy_path:
        ref = simulate_truth(cfg)
    got = simulate_truth(cfg)
    assert (ref.status != "ok").any()
    np.testing.assert_array_equal(got.status, ref.status)
    np.testing.assert_array_equal(got.event_time, ref.event_time)
    np.testing.assert_allclose(got.states, ref.states, rtol=0, atol=ATOL)


# ---------------------------------------------------------------------------------------------- UKF
def ukf_config(seed: int, stop: str) -> str:
    """A random small UKF experiment: one of the four models the compiled UKF covers; missing samples
    (dropout), latency, a filter rate below the grid's (several samples per tick), gates, noise growing
    with distance, the roll starting next to pi and turning past it, tissue interfaces with the curvature
    reset, the curvature constraint, predictions; covariances stored full, diagonal or not at all."""
    rng = np.random.default_rng(seed)
    model = ("modified_unicycle", "unicycle", "mnm", "binm")[seed % 4]
    drop = float(rng.choice([0.0, 0.3]))
    lat = float(rng.choice([0.0, 0.02]))
    rate = rng.choice(["", "rate: 50.0", "rate: 25.0"])
    gate = rng.choice([0.99, 0.5])  # 0.5: many samples rejected
    out = f"output: {{store_every: {rng.choice([1, 3])}, covariance: {rng.choice(['full', 'diag', 'none'])}}}"
    if model in ("mnm", "binm"):
        param = "c" if model == "mnm" else "l_inv"
        return textwrap.dedent(f"""\
            name: k{seed}
            model: {{type: {model}, params: {{{param}: 9.5}}, initial_state: {{hy: -1.0, By: -0.9, Bx: 0.3}}}}
            inputs: {{v: 0.002, omega_B: [0, 0, 0.3]}}
            process_noise: {{std: {{px: 3.0e-5, py: 3.0e-5, hx: 2.0e-3, hy: 2.0e-3, Bx: 1.0e-4, By: 1.0e-4}}}}
            sensors:
              - {{name: camera, type: position, rate: 100.0, axes: [x, y], sigma: 5.2e-5, dropout: {drop}, latency: {lat}}}
            observers:
              - name: ukf
                type: ukf
                {rate}
                q: {{px: 1.0e-6, py: 1.0e-6, pz: 1.0e-7, hx: 1.0e-3, hy: 1.0e-3, hz: 1.0e-4, Bx: 1.0e-4, By: 1.0e-4, Bz: 1.0e-5}}
                p0: {{px: 1.0e-8, py: 1.0e-8, pz: 1.0e-10, hx: 1.0e-4, hy: 1.0e-4, hz: 1.0e-4, Bx: 1.0e-4, By: 1.0e-4, Bz: 1.0e-4}}
                measurements: {{camera: {{sigma: 5.2e-5, gate: {gate}}}}}
                init: {{from: truth, std: {{hx: 0.01}}, first_measurement: {{px: camera.x, py: camera.y}}}}
                predict_at_depths: [0.00004, 0.0001]
            runs: {{count: 4, seed: {seed}}}
            stop: {{{stop}}}
            {out}
            """)
    modified = model == "modified_unicycle"
    kappa = "0.005, beta_cut: 0.035" if modified else "0.005"
    swe = "\n  - {name: swe, type: elastography, rate: 100.0, sigma: 0.001}" if modified else ""
    q = "{x: 2.0e-3, y: 2.0e-3, z: 2.0e-3, alpha: 2.0e-5, beta: 2.0e-5, gamma: 5.0e-4" + (", kappa: 2.0e-6}" if modified else "}")
    p0 = "{x: 1.0, y: 1.0, z: 1.0, alpha: 5.0e-3, beta: 5.0e-3, gamma: 0.1" + (", kappa: 2.0e-6}" if modified else "}")
    fm = "{x: us.x, y: us.y, z: us.z, gamma: robot.roll" + (", kappa: swe.kappa}" if modified else "}")
    extra = "kappa_max: 0.0052\n    kappa_reset: {factor: 10.0}\n    " if modified else ""
    text = f"""\
name: k{seed}
model: {{type: {model}, params: {{kappa: {kappa}}}, param_std: {{kappa: 0.0005}}, initial_state: {{gamma: 3.1}},
        initial_std: {{alpha: 0.05, beta: 0.05, gamma: 0.05}}}}
inputs: {{v: 1.5, u: {{kind: flips, at_depths: [0.001, 0.5], rate: 6.0}}}}
tissue: {{layers: [{{depth: 0, curvature: 0.004}}, {{depth: 0.03, curvature: 0.008}}]}}
process_noise: {{std: {{x: 0.02, y: 0.02, z: 0.02, alpha: 2.0e-4, beta: 2.0e-4, gamma: 5.0e-3}}}}
sensors:
  - {{name: us, type: position, rate: 100.0, sigma: 0.3, latency: {lat}, dropout: {drop}, growth: {{transducer: [0, 0, 90], a: 1.0, d_max: 80.0}}}}
  - {{name: robot, type: encoder, rate: 100.0, channels: [roll], sigma: 0.0035, dropout: {drop}}}{swe}
observers:
  - name: ukf
    type: ukf
    {rate}
    q: {q}
    p0: {p0}
    measurements: {{us: {{sigma: 0.3, growth: {{transducer: [0, 0, 90], a: 1.0, d_max: 80.0}}, gate: {gate}}}, robot: {{sigma: 0.0035}}{', swe: {sigma: 0.001}' if modified else ''}}}
    init: {{from: truth, std: {{alpha: 0.05, beta: 0.05}}, first_measurement: {fm}}}
    {extra}predict_at_depths: [0.02, 0.05]
runs: {{count: 4, seed: {seed}}}
stop: {{{stop}}}
{out}
"""
    return text


def _both(text: str, numpy_path):
    cfg, text = load_config(text=text)
    with numpy_path:
        ref = run_experiment(cfg, text, write=False)
    got = run_experiment(cfg, text, write=False)
    return ref, got


def _assert_posteriors_agree(ref, got, atol):
    for name, a in ref.estimates.items():
        b = got.estimates[name]
        np.testing.assert_array_equal(a.status, b.status)
        np.testing.assert_array_equal(a.reason, b.reason)
        np.testing.assert_allclose(b.state, a.state, rtol=0, atol=atol)
        if a.cov is not None:
            np.testing.assert_allclose(b.cov, a.cov, rtol=0, atol=atol)
        assert a.extras.keys() == b.extras.keys()
        for k, v in a.extras.items():
            if v.dtype.kind in "iub":
                np.testing.assert_array_equal(b.extras[k], v, err_msg=k)
            elif k.startswith("nis/"):  # nu^T S^-1 nu: a state difference of atol moves it by 2 |nu| atol / S,
                # about 1e-7 relative for the roll encoder (sigma 3.5e-3 rad); the same samples used (NaN alike)
                np.testing.assert_array_equal(np.isnan(b.extras[k]), np.isnan(v), err_msg=k)
                np.testing.assert_allclose(b.extras[k], v, rtol=1e-6, atol=atol, err_msg=k)
            else:
                np.testing.assert_allclose(b.extras[k], v, rtol=0, atol=atol, err_msg=k)


@pytest.mark.parametrize("seed", range(8))
def test_ukf_ticks_equal_numpy(seed, numpy_path):
    """6 grid steps: initialisation, updates of every kind (one scalar, several channels at once, several
    samples of a channel in one tick), wrap-around, masks, gates, noise growing with distance, a reset,
    the constraint, predictions. (The UKF's mean carries about 1e-11 of rounding per tick at alpha = 1e-3
    on states of order 1, in both implementations: 1e-10 holds for about this many ticks; longer runs
    are compared below against the reference's own reproducibility.)"""
    stop = "time: 0.04" if seed % 4 >= 2 else "depth: 0.09"  # magnetic models: 4 steps, unicycles 6
    ref, got = _both(ukf_config(seed, stop), numpy_path)
    _assert_posteriors_agree(ref, got, ATOL)


def test_ukf_covers_what_it_claims(numpy_path):
    """The configurations above went through the kernel (not the numpy path by a silent fallback)."""
    import needlecli.kernels.ukf as ku

    calls = []
    real = ku.filter_runs

    def spy(*a, **k):
        calls.append(1)
        return real(*a, **k)

    ku.filter_runs = spy
    try:
        for seed in range(4):
            _both(ukf_config(seed, "time: 0.1"), numpy_path)
    finally:
        ku.filter_runs = real
    assert len(calls) == 4


def test_ukf_divergence_and_status_as_numpy(numpy_path):
    """Runs that miss the first position samples (dropout) keep a covariance above the limit: they stop
    as diverged at the same tick, hold their last estimate; the others go on."""
    text = ukf_config(1, "depth: 0.09").replace("type: ukf\n", "type: ukf\n    max_cov_trace: 3.0\n")
    ref, got = _both(text, numpy_path)
    st = ref.estimates["ukf"].status
    assert (st == "diverged").any() and (st == "ok").any()
    _assert_posteriors_agree(ref, got, ATOL)


def test_ukf_cholesky_repairs_as_numpy(numpy_path):
    """A roll measured to 1e-9 rad leaves P at the edge of positive definiteness: each run repairs its
    factor once, in both paths. (Where a matrix sits exactly on the edge, whether its Cholesky fails is
    itself a matter of rounding: the repair counts may then differ by one.)"""
    text = ukf_config(1, "depth: 0.09").replace("robot: {sigma: 0.0035}", "robot: {sigma: 1.0e-9}")
    ref, got = _both(text, numpy_path)
    assert (ref.estimates["ukf"].extras["cholesky_repairs"] == 1).all()
    _assert_posteriors_agree(ref, got, ATOL)


def test_ukf_whole_insertion_within_the_references_own_rounding(numpy_path, monkeypatch):
    """Seed 003's Table 1 set-up over 30 mm (2,000 ticks): the kernel differs from the numpy path by no
    more than the numpy path differs from itself with numpy's sin and cos (within 2 ulp of its own)."""
    import needlecli.models.unicycle as unicycle

    cfg, text = load_config(ROOT / "configs/seed003/table1.yaml", runs=4, overrides=["stop.depth=30"])
    with numpy_path:
        ref = run_experiment(cfg, text, write=False).estimates["ukf"].state
        with monkeypatch.context() as m:
            m.setattr(unicycle, "sincos", lambda a: (np.sin(a), np.cos(a)))
            other = run_experiment(cfg, text, write=False).estimates["ukf"].state
    got = run_experiment(cfg, text, write=False).estimates["ukf"].state
    noise = np.abs(other - ref).max()
    assert 0 < noise < 1e-8
    assert np.abs(got - ref).max() <= 10 * noise


# ---------------------------------------------------------------------------------------------- selection
def test_selection_by_environment_and_config(monkeypatch):
    monkeypatch.delenv(kernels.ENV, raising=False)
    assert kernels.compiled(None) and kernels.compiled("auto") and not kernels.compiled("numpy")
    monkeypatch.setenv(kernels.ENV, "numpy")
    assert not kernels.compiled("numba")
    monkeypatch.setenv(kernels.ENV, "fast")
    with pytest.raises(kernels.KernelError, match="NEEDLECLI_KERNELS"):
        kernels.compiled(None)


def test_config_key_selects_the_numpy_path(monkeypatch):
    import needlecli.kernels.ukf as ku

    monkeypatch.delenv(kernels.ENV, raising=False)
    monkeypatch.setattr(ku, "filter_runs", lambda *a, **k: pytest.fail("the kernel ran"))
    cfg, text = load_config(text=ukf_config(1, "time: 0.1") + "simulation: {dt: 0.01, kernels: numpy}\n")
    assert run_experiment(cfg, text, write=False).estimates["ukf"].status.size == 4


def test_needle_list_says_what_is_compiled():
    out = subprocess.run([sys.executable, "-m", "needlecli", "list"], capture_output=True, text=True, cwd=ROOT,
                         env={**os.environ, "PYTHONPATH": str(ROOT)}, check=True).stdout
    assert "kernels: auto" in out and "compiled observer ukf" in out and "compiled models: unicycle" in out


def test_help_and_list_do_not_import_numba():
    code = ("import sys; sys.argv = ['needle', '--help']\nfrom needlecli.cli.app import run\n"
            "try:\n    run()\nexcept SystemExit:\n    pass\nprint('numba' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT,
                         env={**os.environ, "PYTHONPATH": str(ROOT)}, check=True).stdout
    assert out.strip().splitlines()[-1] == "False"


@pytest.mark.parametrize("where", ["checkout", "copy"])
def test_compiled_code_is_cached_on_disk(where, tmp_path):
    """A second process loads the kernels from the cache instead of compiling them: from this checkout
    and from a copy of the package elsewhere (as pip installs it)."""
    if where == "copy":
        import shutil

        shutil.copytree(ROOT / "needlecli", tmp_path / "site" / "needlecli",
                        ignore=shutil.ignore_patterns("__pycache__"))
        path = tmp_path / "site"
    else:
        path = ROOT
    code = ("from needlecli.kernels import core\ncore.wrap(7.0)\ns = core.wrap.stats\n"
            "print(sum(s.cache_hits.values()), sum(s.cache_misses.values()))")
    env = {**os.environ, "PYTHONPATH": str(path), "NEEDLECLI_KERNEL_CACHE": str(tmp_path / "cache")}
    runs = [subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=tmp_path, env=env,
                           check=True).stdout.split() for _ in range(2)]
    assert runs[0] == ["0", "1"] and runs[1] == ["1", "0"]


def test_first_run_compiles_the_observers_in_a_second_process(tmp_path):
    """On an empty kernel cache, a run compiles the UKF in a second process while it compiles the truth
    (kernels.warm_up): the run itself then loads the UKF from the cache (a cache hit, no compilation), and
    its estimates are those of a run on a warm cache, bit for bit. Concurrent saves to the cache are locked:
    a third run compiles nothing."""
    code = textwrap.dedent("""
        import sys, numpy as np
        from needlecli.experiments.config.load import load_config
        from needlecli.experiments.simulation.runner import run_experiment
        cfg, text = load_config(sys.argv[1], overrides=["runs.count=3", "stop.depth=5"])
        res = run_experiment(cfg, text, write=False)
        np.save(sys.argv[2], res.estimates["ukf"].state)
        from needlecli.kernels import ukf, truth
        s = ukf.run.stats
        print(sum(s.cache_hits.values()), sum(s.cache_misses.values()), sum(truth.advance.stats.cache_misses.values()))
    """)
    env = {**os.environ, "PYTHONPATH": str(ROOT), "NEEDLECLI_KERNEL_CACHE": str(tmp_path / "cache")}
    env.pop("NEEDLECLI_KERNELS", None)
    out = [subprocess.run([sys.executable, "-c", code, str(ROOT / "configs/seed003/table1.yaml"),
                           str(tmp_path / f"x{i}.npy")], capture_output=True, text=True, cwd=tmp_path, env=env,
                          check=True).stdout.split() for i in range(3)]
    assert out[0] == ["1", "0", "1"]  # the UKF from the cache the second process wrote; the truth compiled here
    assert out[1] == out[2] == ["1", "0", "0"]
    np.testing.assert_array_equal(np.load(tmp_path / "x0.npy"), np.load(tmp_path / "x1.npy"))
    assert not list((tmp_path / "cache").rglob("*.tmp.*"))  # every save complete


# ---------------------------------------------------------------------------------------------- EM passes
@pytest.fixture(scope="module")
def seed004_system():
    """Seed 004's study, 6 trials over 4 s, both models: the systems fit-em builds."""
    from needlecli.experiments.simulation.runner import build_problem
    from needlecli.experiments.studies.fit import load_trials
    from needlecli.fitting.problem import build_system, fit_augment, own_model

    trials = load_trials(ROOT / "configs/seed004/study.yaml", overrides=["runs.count=6", "stop.time=4"])
    problem = build_problem(trials.cfg, trials.truth, trials.sensors, trials.streams)
    out = {}
    for name in ("mnm", "binm"):
        model = own_model(trials.cfg.fit, trials.truth.model, name)
        out[name] = build_system(problem, trials.cfg.fit, model, fit_augment(type(model)))
    return out


def _rel(a, b):
    a, b = np.asarray(a), np.asarray(b)
    return float(np.nanmax(np.abs(a - b)) / max(np.nanmax(np.abs(a)), 1e-300))


@pytest.mark.parametrize("name", ["mnm", "binm"])
def test_em_passes_equal_numpy(name, seed004_system, numpy_path):
    """Linearisation (RK4 Jacobians, measurement Jacobians in tangent planes), the affine filter, the RTS
    smoother and the M-step sums, compiled against numpy on the same random trajectory, to 1e-10
    relative (an entry's difference to the largest entry of its array). Missing samples included."""
    from needlecli.fitting.smoother import affine_loglik, affine_pass, linearise
    from needlecli.numerics.kalman import em_measurement_noise, em_process_noise

    S = seed004_system[name]
    dm, meas = S.dm, S.meas
    rng = np.random.default_rng(5)
    for mm in meas:  # drop a third of the samples
        mm.valid = mm.valid & (rng.random(mm.valid.shape) > 0.3)
    N, K1 = dm.N, len(dm.ticks)
    zbar = S.m0[:, None, :] + 1e-3 * rng.standard_normal((N, K1, dm.n)) * np.sqrt(np.diag(S.P0))
    Q = np.broadcast_to(S.Qc, (N,) + S.Qc.shape).copy()
    R = [np.broadcast_to(r, (N,) + r.shape).copy() for r in S.R]
    P0 = np.broadcast_to(S.P0, (N,) + S.P0.shape)
    out = {}
    for mode in ("numpy", "compiled"):
        if mode == "numpy":
            with numpy_path:
                lin = linearise(dm, meas, zbar)
                res = affine_pass(lin, dm, meas, S.m0, P0, Q, R, joseph=False)
                q = em_process_noise(res.sm, lin.A, lin.b, dm.dt, index=S.q_index, state_angles=dm.angles)
                r = [em_measurement_noise(res.sm, mm.channel(R[j], lin.y[j]), lin.H[j], lin.d[j])[0]
                     for j, mm in enumerate(meas)]
        else:
            lin = linearise(dm, meas, zbar)
            res = affine_pass(lin, dm, meas, S.m0, P0, Q, R, joseph=False)
            q = em_process_noise(res.sm, lin.A, lin.b, dm.dt, index=S.q_index, state_angles=dm.angles)
            r = [em_measurement_noise(res.sm, mm.channel(R[j], lin.y[j]), lin.H[j], lin.d[j])[0]
                 for j, mm in enumerate(meas)]
        out[mode] = (lin, res, q, r)
    (la, ra, qa, Ra), (lb, rb, qb, Rb) = out["numpy"], out["compiled"]
    for x, y in [(la.A, lb.A), (la.b, lb.b), *zip(la.H, lb.H), *zip(la.y, lb.y)]:
        assert _rel(x, y) < 1e-10
    for k in (0, K1 // 2, K1 - 2):  # one interval as the first EKF pass steps it (normalised)
        with numpy_path:
            za, Aa = dm.transition(k, zbar[:, k])
        zb, Ab = dm.transition(k, zbar[:, k])
        assert _rel(za, zb) < 1e-10 and _rel(Aa, Ab) < 1e-10
    for k in ("m_pred", "m_filt", "loglik"):
        assert _rel(getattr(ra.fwd, k), getattr(rb.fwd, k)) < 1e-10, k
    for k in ("m", "P"):
        assert _rel(getattr(ra.sm, k), getattr(rb.sm, k)) < 1e-10, k
    # EM's pass keeps the filter's covariances and the smoother's gains in the kernel: not written; nor the
    # cross-covariances, whose M-step sums it makes in the same pass (q above: from those sums)
    assert rb.fwd.P_pred.shape[1] == rb.fwd.P_filt.shape[1] == rb.sm.G.shape[1] == rb.sm.C.shape[1] == 0
    assert rb.sm.q_sums is not None and rb.sm.r_sums is not None  # (R above: from the pass's sums)
    # the standard deviations and the finiteness EM reads at every pass, made as the pass writes P: numpy's
    np.testing.assert_array_equal(rb.sm.sd, np.sqrt(np.maximum(np.diagonal(rb.sm.P, axis1=-2, axis2=-1), 1e-300)))
    np.testing.assert_array_equal(rb.sm.finite, np.isfinite(rb.sm.P).all((-1, -2, -3)))
    from needlecli.numerics.kalman import kalman_filter_smoother

    Qbad = Q.copy()
    Qbad[1] = np.inf  # trial 1's covariances become infinite, then NaN
    chans = [mm.channel(R[j], lb.y[j]) for j, mm in enumerate(meas)]
    with np.errstate(all="ignore"):
        _, smb = kalman_filter_smoother(S.m0, P0, Qbad, dm.dt, lb.A, lb.b, chans, lb.H, lb.d, state_angles=dm.angles)
    assert smb.finite.tolist() == np.isfinite(smb.P).all((-1, -2, -3)).tolist() == [True, False] + [True] * (N - 2)
    with np.errstate(invalid="ignore"):
        np.testing.assert_array_equal(smb.sd, np.sqrt(np.maximum(np.diagonal(smb.P, axis1=-2, axis2=-1), 1e-300)))
    assert dataclasses.replace(smb, sd=None, finite=None).all_finite().tolist() == smb.finite.tolist()
    # the filter and the smoother on their own write them, and give the fused pass's numbers bit for bit
    from needlecli.numerics.kalman import kalman_forward_affine, rts_smoother

    fwd = kalman_forward_affine(S.m0, P0, Q, dm.dt, lb.A, lb.b, [mm.channel(R[j], lb.y[j]) for j, mm in enumerate(meas)],
                                lb.H, lb.d, state_angles=dm.angles)
    sm = rts_smoother(fwd, state_angles=dm.angles)
    for k in ("P_pred", "P_filt"):
        assert _rel(getattr(ra.fwd, k), getattr(fwd, k)) < 1e-10, k
    # the gains solve G_k P_{k+1|k} = P_{k|k} A_k^T (against numpy's LU the ill-conditioned directions of
    # P_{k+1|k} differ at 1e-6; the products the smoother makes of them agree above)
    lhs = sm.G @ (0.5 * (fwd.P_pred[:, 1:] + np.swapaxes(fwd.P_pred[:, 1:], -1, -2)))
    assert _rel(fwd.P_filt[:, :-1] @ np.swapaxes(lb.A, -1, -2), lhs) < 1e-10
    for k in ("m_pred", "m_filt", "loglik", "repairs"):
        np.testing.assert_array_equal(getattr(fwd, k), getattr(rb.fwd, k))
    for k in ("m", "P", "repairs"):
        np.testing.assert_array_equal(getattr(sm, k), getattr(rb.sm, k))
    assert _rel(ra.sm.C, sm.C) < 1e-10
    # the M-step's sums from the stored cross-covariances: those of the pass (summed in the other order)
    assert _rel(em_process_noise(sm, lb.A, lb.b, dm.dt, index=S.q_index, state_angles=dm.angles), qb) < 1e-12
    for j, mm in enumerate(meas):  # the measurement-noise sums of the stored smoother: the pass's
        ch = mm.channel(R[j], lb.y[j])
        got, cnt = em_measurement_noise(sm, ch, lb.H[j], lb.d[j])
        want, cnt_b = em_measurement_noise(rb.sm, ch, lb.H[j], lb.d[j])
        assert _rel(got, want) < 1e-12
        np.testing.assert_array_equal(cnt, cnt_b)
        other = em_measurement_noise(rb.sm, ch, lb.H[j] * (1.0 + 1e-9), lb.d[j])[0]  # another linearisation
        assert _rel(other, want) > 0 and _rel(other, want) < 1e-6
    with pytest.raises(ValueError, match="no cross-covariances"):  # sums of another linearisation: refused
        em_process_noise(rb.sm, lb.A * (1.0 + 1e-9), lb.b, dm.dt, index=S.q_index, state_angles=dm.angles)
    assert _rel(qa, qb) < 1e-10 and all(_rel(x, y) < 1e-10 for x, y in zip(Ra, Rb))
    np.testing.assert_array_equal(ra.fwd.repairs + ra.sm.repairs, rb.fwd.repairs + rb.sm.repairs)
    # the log-likelihood alone (identifiability's evaluation points): the full pass's, bit for bit
    ll = affine_loglik(lb, dm, meas, S.m0, P0, Q, R)
    np.testing.assert_array_equal(ll, rb.fwd.loglik)
    with numpy_path:
        assert _rel(affine_loglik(la, dm, meas, S.m0, P0, Q, R), ll) < 1e-10
    # many points on the trials' rows in place (identifiability): the rows copied out first, bit for bit
    from needlecli.fitting.smoother import take_linearisation

    rows = np.array([2, 0, 0, 5, 2, 3, 1, 5, 4])
    Qs = Q[rows] * rng.uniform(0.5, 2.0, (len(rows), 1, 1))
    Rs = [r[rows] * rng.uniform(0.5, 2.0, (len(rows), 1, 1)) for r in R]
    m0s = S.m0[rows] + 1e-4 * rng.standard_normal((len(rows), dm.n))
    for ctx in (numpy_path, contextlib.nullcontext()):
        with ctx:
            copied = affine_loglik(take_linearisation(lb, rows), dm.take(rows), [mm.take(rows) for mm in meas],
                                   m0s, P0[rows], Qs, Rs)
            in_place = affine_loglik(lb, dm, meas, m0s, P0[rows], Qs, Rs, rows=rows)
        np.testing.assert_array_equal(in_place, copied)


def test_fit_em_iterations_equal_numpy(numpy_path):
    """Three EM iterations (E-step, M-step, SQUAREM) of both models on 6 trials: the same fit."""
    from needlecli.experiments.studies.fit import fit_trials, load_trials

    trials = load_trials(ROOT / "configs/seed004/study.yaml",
                         overrides=["runs.count=6", "stop.time=4", "fit.em.max_iter=3"])
    with numpy_path:
        ref = fit_trials(trials, workers=1)
    got = fit_trials(trials, workers=1)
    for name, mf in ref.fits.items():
        a, b = mf.result, got.fits[name].result
        np.testing.assert_array_equal(a.iterations, b.iterations)
        np.testing.assert_array_equal(a.status, b.status)
        for k in ("Qc", "x0", "m", "P", "filtered", "ekf"):
            assert _rel(getattr(a, k), getattr(b, k)) < 1e-9, (name, k)
        assert all(_rel(x, y) < 1e-9 for x, y in zip(a.R, b.R))


# ---------------------------------------------------------------------------------------------- metrics
def test_rotation_error_equals_numpy():
    """E_R from Euler angles without the rotation matrices, against numpy's matrices and rotation angle:
    random orientations, angles past pi, errors near 0 and near pi."""
    from needlecli.kernels.metrics import rotation_error
    from needlecli.numerics import euler_xyz_to_matrix, rotation_angle

    rng = np.random.default_rng(2)
    t = rng.uniform(-2 * np.pi, 2 * np.pi, (7, 300, 3))
    e = t + rng.normal(size=t.shape) * np.logspace(-9, 0.5, 300)[None, :, None]
    e[:, -5:] = t[:, -5:] * np.array([1.0, -1.0, 1.0]) + np.array([np.pi, 0.0, np.pi])  # the same orientation
    rt, re = euler_xyz_to_matrix(*np.moveaxis(t, -1, 0)), euler_xyz_to_matrix(*np.moveaxis(e, -1, 0))
    ref = rotation_angle(np.swapaxes(rt, -1, -2) @ re)
    np.testing.assert_allclose(rotation_error(t, e), ref, rtol=0, atol=ATOL)


# ---------------------------------------------------------------------------------------------- results file
@pytest.mark.parametrize("mode", ["auto", "gzip", "none"])
def test_results_compression_where_it_pays(mode, tmp_path):
    """output.compression: ``auto`` gzips the arrays that repeat along an axis (inputs held the same for
    every run, per-run parameters, constant noise levels) and writes the others as they are; ``gzip``
    all large arrays; ``none`` nothing. The arrays read back are the same either way."""
    import h5py

    cfg, text = load_config(ROOT / "configs/seed003/table1.yaml", runs=6,
                            overrides=["stop.depth=20", f"output.compression={mode}"])
    res = run_experiment(cfg, text, out=tmp_path / "r.h5")
    with h5py.File(res.path) as f:
        filters = {k: f[k].compression for k in ("inputs/v", "truth/params/beta_cut", "measurements/robot/sigma",
                                                  "truth/state", "estimates/ukf/state")}
        np.testing.assert_array_equal(f["truth/state"][()], res.truth.states)
    want = {"auto": ["gzip"] * 3 + [None] * 2, "gzip": ["gzip"] * 5, "none": [None] * 5}[mode]
    assert list(filters.values()) == want


def test_results_file_the_same_however_written(tmp_path, monkeypatch):
    """The results file is written straight from the arrays into room reserved ahead (O_DIRECT for the
    arrays where the file system has it, else the page cache) or, where room cannot be reserved, built in
    memory first: every array reads back as it was, whichever way (and the first two give the same bytes);
    arrays repeating along an axis are gzipped with each distinct chunk compressed once."""
    import errno

    from needlecli.io import results
    from needlecli.io.tree import Group

    cfg, text = load_config(ROOT / "configs/seed003/table1.yaml", runs=5, overrides=["stop.depth=10"])
    res = run_experiment(cfg, text, write=False)
    from needlecli.experiments.simulation.runner import build_sensors, results_tree

    tree = results_tree(cfg, text, res.truth, res.measurements, res.estimates, build_sensors(cfg, res.truth.model))
    tree.data["extra"] = Group(data={"rows_alike": np.broadcast_to(np.arange(7000.0), (30, 7000)),
                                     "held": np.repeat(np.arange(30.0)[:, None], 9000, axis=1)})
    results.write_atomic(tmp_path / "direct.h5", tree)
    monkeypatch.setenv("NEEDLECLI_NO_DIRECT_IO", "1")
    results.write_atomic(tmp_path / "cached.h5", tree)

    def no_room(fd, offset, length):
        raise OSError(errno.EOPNOTSUPP, "not supported")

    monkeypatch.setattr(results.os, "posix_fallocate", no_room)
    results.write_atomic(tmp_path / "image.h5", tree)
    assert (tmp_path / "direct.h5").read_bytes() == (tmp_path / "cached.h5").read_bytes()

    def arrays(g, prefix=""):
        for k, v in g.data.items():
            if isinstance(v, Group):
                yield from arrays(v, f"{prefix}{k}/")
            else:
                yield prefix + k, np.asarray(v)

    want = dict(arrays(tree))
    for name in ("direct", "cached", "image"):
        got = dict(arrays(results.read_results(tmp_path / f"{name}.h5")))
        assert got.keys() == want.keys()
        for k, a in want.items():
            if a.dtype.kind in "UO":
                np.testing.assert_array_equal(got[k].astype(str), a.astype(str), err_msg=k)
            else:
                np.testing.assert_array_equal(got[k], a, err_msg=k)
    import h5py

    with h5py.File(tmp_path / "direct.h5") as f:
        assert f["extra/rows_alike"].compression == "gzip" and f["extra/held"].compression == "gzip"
        assert f["extra/rows_alike"].id.get_storage_size() < 1e5 and f["truth/state"].compression is None


@pytest.mark.parametrize("path,overrides", [("configs/seed003/table1.yaml", ["stop.depth=10"]),
                                            ("configs/default.yaml", ["stop.depth=30"]),
                                            ("configs/seed004/study.yaml", ["stop.time=3"])],
                         ids=["seed003", "flips", "mnm"])
def test_errors_equal_numpy(path, overrides, numpy_path):
    """The errors of the summary tables straight from the state arrays: the position norm, the wrapped
    angle errors and the other states' errors equal the numpy path's bit for bit, E_R to 1e-10; runs
    excluded alike (a run made to diverge, one with a NaN estimate)."""
    from needlecli.experiments.simulation.runner import build_sensors, results_tree
    from needlecli.metrics import compute_errors

    cfg, text = load_config(ROOT / path, runs=5, overrides=overrides)
    res = run_experiment(cfg, text, write=False)
    tree = results_tree(cfg, text, res.truth, res.measurements, res.estimates, build_sensors(cfg, res.truth.model))
    for grp in tree.data["estimates"].data.values():
        grp.data["status"] = np.asarray(grp.data["status"]).astype(object)
        grp.data["status"][1] = "diverged"
        grp.data["state"] = np.array(grp.data["state"])
        grp.data["state"][2, 5:9] = np.nan
    got = compute_errors(tree)
    with numpy_path:
        ref = compute_errors(tree)
    assert got.keys() == ref.keys()
    for obs, es in ref.items():
        assert list(got[obs].quantities) == list(es.quantities) and got[obs].excluded == es.excluded
        for q, qe in es.quantities.items():
            g = got[obs].quantities[q]
            assert g.unit == qe.unit and np.array_equal(g.runs, qe.runs), q
            if q == "E_R":
                np.testing.assert_allclose(g.values, qe.values, rtol=0, atol=1e-10 * 180 / np.pi, err_msg=q)
            else:
                np.testing.assert_array_equal(g.values, qe.values, err_msg=q)


def test_the_commands_memory_policy():
    """``needle`` maps numpy's large arrays on ordinary pages unless the user asks for huge ones, with or
    without a glibc MALLOC_ variable set (then glibc's heap is left as it is; needlecli.cli.app.memory_policy)."""
    code = ("from needlecli.cli.app import memory_policy\nmemory_policy()\nimport numpy\n"
            "print(numpy._core.multiarray._get_madvise_hugepage())")
    env = {k: v for k, v in os.environ.items() if k != "NUMPY_MADVISE_HUGEPAGE" and not k.startswith("MALLOC_")}
    env["PYTHONPATH"] = str(ROOT)
    for extra, want in (({}, "False"), ({"NUMPY_MADVISE_HUGEPAGE": "1"}, "True"),
                        ({"MALLOC_ARENA_MAX_": "2"}, "False")):
        out = subprocess.run([sys.executable, "-c", code], env={**env, **extra}, capture_output=True, text=True,
                             check=True).stdout.strip()
        assert out == want, (extra, out)
