"""Every compiled twin against its numpy reference: the one helper the kernel tests use
(:func:`compare_compiled_and_reference`) and the cases of each twin of ``needlecli.kernels.TWINS``.

A case is a function ``run(setting)`` that computes something with the kernels setting ``setting``
passed down as a run passes it (a config's ``simulation.kernels``, ``problem.kernels``, a system's
``kernels``, an argument); the helper runs it with ``numpy`` and with ``numba``, checks that the compiled
function of the twin ran in the second run only (the case reaches the twin, not a fallback), and that
the two results agree: 1e-10 (absolute, in the quantities' units, or relative to an array's largest
entry where the case says so), integers, booleans and strings equal, NaN in the same places.
"""

from __future__ import annotations

import contextlib
import copy
import dataclasses
import functools
import importlib
import os
import textwrap
import zlib
from collections.abc import Callable
from pathlib import Path

import numpy as np

from needlecli import kernels

ROOT = Path(__file__).resolve().parents[1]
ATOL = 1e-10


# ---------------------------------------------------------------------------------------------- the helper
@contextlib.contextmanager
def _no_override():
    """Without ``NEEDLECLI_KERNELS``: the setting the case passes decides."""
    before = os.environ.pop(kernels.ENV, None)
    try:
        yield
    finally:
        if before is not None:
            os.environ[kernels.ENV] = before


@contextlib.contextmanager
def calls_of(name: str):
    """The calls of twin ``name``'s compiled function (a list, one entry per call) while the block runs:
    the function callers are given by :func:`needlecli.kernels.twin`, wrapped."""
    module, _, attr = kernels.TWINS[name].compiled.partition(":")
    mod = importlib.import_module(module)
    real = getattr(mod, attr)
    calls: list[int] = []

    def spy(*a, **k):
        calls.append(1)
        return real(*a, **k)

    setattr(mod, attr, spy)
    try:
        yield calls
    finally:
        setattr(mod, attr, real)


def assert_agree(ref, got, atol: float = ATOL, rtol: float = 0.0, where: str = "") -> None:
    """``got`` equals ``ref`` entry by entry (dicts, sequences, dataclasses, arrays, numbers, strings):
    floats within ``atol + rtol * max|ref|`` (per array) with NaN alike, everything else equal."""
    if dataclasses.is_dataclass(ref) and not isinstance(ref, type):
        ref, got = dataclasses.asdict(ref), dataclasses.asdict(got)
    if isinstance(ref, dict):
        assert isinstance(got, dict) and list(got) == list(ref), f"{where}: keys {list(got)} != {list(ref)}"
        for k in ref:
            assert_agree(ref[k], got[k], atol, rtol, f"{where}/{k}")
        return
    if isinstance(ref, (tuple, list)):
        assert len(got) == len(ref), f"{where}: {len(got)} items != {len(ref)}"
        for i, (a, b) in enumerate(zip(ref, got)):
            assert_agree(a, b, atol, rtol, f"{where}[{i}]")
        return
    if ref is None or isinstance(ref, str):
        assert got == ref, f"{where}: {got!r} != {ref!r}"
        return
    a, b = np.asarray(ref), np.asarray(got)
    assert a.shape == b.shape, f"{where}: shape {b.shape} != {a.shape}"
    if a.dtype.kind in "fc":
        nan = np.isnan(a)
        assert np.array_equal(nan, np.isnan(b)), f"{where}: NaN in other places"
        scale = float(np.abs(a[~nan]).max(initial=0.0)) if np.isfinite(a[~nan]).all() else 0.0
        d = np.abs(np.where(nan, 0.0, b - a))
        inf = np.isinf(a)
        assert np.array_equal(a[inf], b[inf]), f"{where}: infinities differ"
        d = np.where(inf, 0.0, d)
        tol = atol + rtol * scale
        assert d.max(initial=0.0) <= tol, f"{where}: differs by {d.max():.3g} > {tol:.3g}"
    else:
        assert np.array_equal(a, b), f"{where}: differs ({a.dtype})"


def compare_compiled_and_reference(name: str, run: Callable[[str], object], *, atol: float = ATOL, rtol: float = 0.0,
                                   check: Callable[[object, object], None] | None = None):
    """Run ``run(setting)`` on the numpy path (``"numpy"``) and compiled (``"numba"``): twin ``name``'s
    compiled function must not run in the first and must run in the second, and the results must agree
    (``check(ref, got)``, default :func:`assert_agree` with ``atol``, ``rtol``). ``NEEDLECLI_KERNELS`` is
    unset meanwhile. Returns ``(reference, compiled)``."""
    with _no_override(), calls_of(name) as calls:
        ref = run("numpy")
        assert not calls, f"twin {name}: the compiled function ran with kernels: numpy"
        got = run("numba")
        assert calls, f"twin {name}: the case never reached the compiled function (a fallback to numpy?)"
    if check is not None:
        check(ref, got)
    else:
        assert_agree(ref, got, atol, rtol, name)
    return ref, got


# ---------------------------------------------------------------------------------------------- the cases
#: twin name -> case id -> (run, options of compare_compiled_and_reference)
CASES: dict[str, dict[str, tuple[Callable[[str], object], dict]]] = {}


def case(twin: str, id_: str, **opts):
    def deco(fn):
        CASES.setdefault(twin, {})[id_] = (fn, opts)
        return fn

    return deco


# ---- models: one RK4 step of each model that declares compiled equations
def random_states(model, rng, L: int) -> np.ndarray:
    """States ``(L, n)`` inside the model's domain: unicycles with angles past +-pi (and |beta| < pi/2), a
    rotation matrix, unit-ish vectors h and B of the magnetic models."""
    eq = model.compiled_equations
    x = rng.normal(size=(L, model.n)) * 0.5
    if eq == "so3":
        from needlecli.numerics import so3_exp

        return so3_exp(rng.normal(size=(L, 3)) * 2.0).reshape(L, 9)
    if eq in ("mnm", "binm"):
        for sl in (slice(3, 6), slice(6, 9)):
            x[:, sl] *= rng.uniform(0.8, 1.2, (L, 1)) / np.linalg.norm(x[:, sl], axis=-1, keepdims=True)
        return x
    x[:, 3:6] = rng.uniform(-4 * np.pi, 4 * np.pi, (L, 3))  # angles past +-pi: the reduction by pi/2
    x[:, 4] = rng.uniform(-1.4, 1.4, L)  # inside the unicycle's domain, |beta| < pi/2
    x[:, :3] *= 100.0
    if model.n == 7:
        x[:, 6] = rng.uniform(0.0, 0.05, L)
    return x


def _model_step(name: str):
    def run(setting):
        from needlecli.models import MODELS

        model = MODELS.get(name)()
        rng = np.random.default_rng(zlib.crc32(name.encode()))
        L = 37
        x = random_states(model, rng, L)
        u = rng.normal(size=(L, model.m))
        p = {k: rng.uniform(0.5, 1.5) * max(float(v), 1e-3) for k, v in model.param_arrays().items()}
        fn = kernels.twin("model_step", setting)
        if fn is None:
            return model.step(x, u, {k: np.full(L, v) for k, v in p.items()}, 0.01)
        from needlecli.kernels.models import MODEL_IDS

        X = np.ascontiguousarray(x.T)
        P = np.stack([np.full(L, p[k]) for k in p]) if p else np.zeros((1, L))
        fn(MODEL_IDS[model.compiled_equations], X, np.ascontiguousarray(u.T), P, 0.01, L,
           np.zeros((4, max(model.n, 6), L)))
        return X.T

    return run


def compiled_models() -> list[str]:
    from needlecli.models import MODELS

    return [n for n, cls in MODELS.loaded().items() if cls.compiled_equations]


for _name in compiled_models():
    case("model_step", _name)(_model_step(_name))


@case("model_step", "huge angles", atol=ATOL, rtol=1e-15)
def _model_step_huge_angles(setting):
    """Angles beyond the polynomial sine's range (3e6 rad): the fused step falls back to libm's."""
    from needlecli.models import MODELS

    model = MODELS.get("modified_unicycle")()
    x = np.array([[0.0, 0.0, 0.0, 3e6, 0.2, -5e6, 0.005], [1.0, 2.0, 3.0, 0.1, 0.2, 0.3, 0.004]])
    u = np.array([[1.5, 0.3], [1.5, 0.3]])
    fn = kernels.twin("model_step", setting)
    if fn is None:
        return model.step(x, u, {"kappa": 0.005, "beta_cut": 0.035}, 0.01)
    from needlecli.kernels.models import MODEL_IDS

    X = np.ascontiguousarray(x.T)
    fn(MODEL_IDS["modified_unicycle"], X, np.ascontiguousarray(u.T), np.array([[0.005, 0.005], [0.035, 0.035]]), 0.01,
       2, np.zeros((4, 7, 2)))
    return X.T


# ---- truth
def _truth(path: str, overrides: list[str], runs: int = 5):
    def run(setting):
        from needlecli.experiments.config.load import load_config
        from needlecli.experiments.simulation.truth import simulate_truth

        cfg, _ = load_config(ROOT / path, runs=runs, overrides=[*overrides, f"simulation.kernels={setting}"])
        t = simulate_truth(cfg)
        return {"states": t.states, "status": t.status.astype(str), "reason": t.reason.astype(str),
                "event_time": t.event_time}

    return run


def _truth_check(ref, got):
    assert_agree(ref, got, ATOL * max(1.0, np.nanmax(np.abs(ref["states"])) / 100))


for _path, _over in [
    ("configs/multirate-ukf-us3d/table1.yaml", ["stop.depth=20"]),  # process noise, per-run curvature
    ("configs/default.yaml", ["stop.depth=30"]),  # flips: the roll angle runs past pi
    ("configs/examples/two_layer_flips.yaml", []),  # tissue layers: the curvature along time
    ("configs/em-magnetic-pratt2022/study.yaml", ["stop.time=5"]),  # input and parameter cases, MNM
    ("configs/examples/binm_singular.yaml", []),  # runs that stop at the singularity
    ("configs/so3-invariant/helix_batch.yaml", []),  # SO(3)
    ("configs/highgain-us2d/simulation.yaml", []),  # unicycle
    ("configs/multirate-ukf-us3d/table1.yaml", ["stop.depth=3", "process_noise.std.beta=80.0"]),  # diverged runs
]:
    case("truth", " ".join([_path, *_over]), check=_truth_check)(_truth(_path, _over))


# ---- the UKF
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


def posterior(p) -> dict:
    """What an observer's posterior holds, as a dict of arrays."""
    return {"state": p.state, "cov": p.cov, "status": np.asarray(p.status).astype(str),
            "reason": np.asarray(p.reason).astype(str), "extras": dict(p.extras)}


def assert_posteriors_agree(ref: dict, got: dict, atol: float = ATOL) -> None:
    """Two observers' results (:func:`posterior`) agree to ``atol``; the normalised innovations squared
    (``nis/``) to 1e-6 relative (a state difference of atol moves nu^T S^-1 nu by 2 |nu| atol / S, about 1e-7
    relative for the roll encoder, sigma 3.5e-3 rad), the same samples used (NaN alike)."""
    assert_agree({k: v for k, v in ref.items() if k != "extras"}, {k: v for k, v in got.items() if k != "extras"}, atol)
    assert ref["extras"].keys() == got["extras"].keys()
    for k, v in ref["extras"].items():
        if k.startswith("nis/"):
            nan = np.isnan(v)
            assert np.array_equal(nan, np.isnan(got["extras"][k])), k
            np.testing.assert_allclose(got["extras"][k][~nan], v[~nan], rtol=1e-6, atol=atol, err_msg=k)
        else:
            assert_agree(v, got["extras"][k], atol, 0.0, k)


@functools.cache
def numpy_problem(text: str):
    """The config of ``text`` and its estimation problem, the truth and measurements simulated on the numpy
    path (the same input for both paths of an observer)."""
    from needlecli.experiments.config.load import load_config
    from needlecli.experiments.simulation.runner import build_problem, simulate_and_measure

    cfg, _ = load_config(text=text, overrides=["simulation.kernels=numpy"])
    with _no_override():
        truth, sensors, streams, _ = simulate_and_measure(cfg)
    return cfg, build_problem(cfg, truth, sensors, streams)


def run_observer(text: str, setting: str) -> dict:
    """The first observer of config ``text`` on its numpy-simulated problem with ``problem.kernels``
    ``setting``: its posterior (:func:`posterior`)."""
    from needlecli.experiments.simulation.truth import stream
    from needlecli.observers import OBSERVERS

    cfg, problem = numpy_problem(text)
    o = cfg.observers[0]
    obs = OBSERVERS.get(o.type)(o)
    return posterior(obs.run(dataclasses.replace(problem, kernels=setting), stream(cfg.runs.seed, f"observer/{obs.name}")))


for _seed in range(8):  # each of the four models twice, every kind of update (6 grid steps: a filter's mean carries
    # about 1e-11 of rounding per tick at alpha = 1e-3 on states of order 1, in both implementations: 1e-10
    # holds for about this many ticks; whole insertions: tests/test_kernels.py)
    _text = ukf_config(_seed, "time: 0.04" if _seed % 4 >= 2 else "depth: 0.09")
    case("ukf", f"seed{_seed}", check=assert_posteriors_agree)(functools.partial(run_observer, _text))


# ---- the Kalman passes of EM (the magnetic needle EM paper's study, 6 trials over 4 s, both models)
@functools.cache
def seed004_systems():
    """The systems fit-em builds for the magnetic needle EM paper's study (6 trials, 4 s), by model."""
    from needlecli.experiments.simulation.runner import build_problem
    from needlecli.experiments.studies.fit import load_trials
    from needlecli.fitting.problem import build_system, fit_augment, own_model

    with _no_override():
        trials = load_trials(ROOT / "configs/em-magnetic-pratt2022/study.yaml",
                             overrides=["runs.count=6", "stop.time=4", "simulation.kernels=numpy"])
    problem = build_problem(trials.cfg, trials.truth, trials.sensors, trials.streams)
    return {name: build_system(problem, trials.cfg.fit, own_model(trials.cfg.fit, trials.truth.model, name),
                               fit_augment(type(own_model(trials.cfg.fit, trials.truth.model, name))))
            for name in ("mnm", "binm")}


@functools.cache
def em_inputs(name: str):
    """The magnetic needle EM paper's system of model ``name`` with a third of the samples missing, a random trajectory about
    the initial state, the noise per trial, and the affine model (a linearisation on the numpy path) and
    its filter and smoother on the numpy path: fixed inputs of the passes."""
    from needlecli.fitting.smoother import linearise
    from needlecli.numerics.kalman import kalman_forward_affine, rts_smoother

    S = seed004_systems()[name]
    rng = np.random.default_rng(5)
    dm = copy.copy(S.dm)
    dm.kernels = "numpy"
    meas = [dataclasses.replace(mm, valid=mm.valid & (rng.random(mm.valid.shape) > 0.3), kernels="numpy")
            for mm in S.meas]
    N, K1 = dm.N, len(dm.ticks)
    zbar = S.m0[:, None, :] + 1e-3 * rng.standard_normal((N, K1, dm.n)) * np.sqrt(np.diag(S.P0))
    Q = np.broadcast_to(S.Qc, (N,) + S.Qc.shape).copy()
    R = [np.broadcast_to(r, (N,) + r.shape).copy() for r in S.R]
    P0 = np.broadcast_to(S.P0, (N,) + S.P0.shape)
    with _no_override():
        lin = linearise(dm, meas, zbar)
        chans = [mm.channel(R[j], lin.y[j]) for j, mm in enumerate(meas)]
        fwd = kalman_forward_affine(S.m0, P0, Q, dm.dt, lin.A, lin.b, chans, lin.H, lin.d, state_angles=dm.angles,
                                    kernels="numpy")
        sm = rts_smoother(fwd, state_angles=dm.angles, kernels="numpy")
    return {"S": S, "dm": dm, "meas": meas, "zbar": zbar, "Q": Q, "R": R, "P0": P0, "lin": lin, "chans": chans,
            "fwd": fwd, "sm": sm}


def _with(dm, meas, setting):
    """The system with the kernels setting ``setting``."""
    d = copy.copy(dm)
    d.kernels = setting
    return d, [dataclasses.replace(mm, kernels=setting) for mm in meas]


def _em_case(twin: str, fn, atol: float = 0.0):
    """Both models; to 1e-10 relative to each array's largest entry (as the passes' tests always were)."""
    for name in ("mnm", "binm"):
        case(twin, name, rtol=1e-10, atol=atol)(functools.partial(fn, name))


def _transition_all(name, setting):
    e = em_inputs(name)
    dm, _ = _with(e["dm"], e["meas"], setting)
    return dm.transition_all(e["zbar"][:, :-1])


def _transition_one(name, setting):
    e = em_inputs(name)
    dm, _ = _with(e["dm"], e["meas"], setting)
    K1 = len(dm.ticks)
    return [dm.transition(k, e["zbar"][:, k]) for k in (0, K1 // 2, K1 - 2)]


def _linearise(name, setting):
    """Positions (a selection) and directions (in the plane across the predicted one: h there is 0 to
    rounding, 1e-20, hence the absolute floor of this case)."""
    e = em_inputs(name)
    _, meas = _with(e["dm"], e["meas"], setting)
    return [mm.linearise(e["zbar"][:, mm.tick]) for mm in meas]


def _forward(name, setting):
    from needlecli.numerics.kalman import kalman_forward_affine

    e = em_inputs(name)
    lin, dm = e["lin"], e["dm"]
    return kalman_forward_affine(e["S"].m0, e["P0"], e["Q"], dm.dt, lin.A, lin.b, e["chans"], lin.H, lin.d,
                                 state_angles=dm.angles, kernels=setting)


def _loglik(name, setting):
    """Many points on their trials' rows (identifiability's evaluation points)."""
    from needlecli.numerics.kalman import kalman_loglik_affine

    e = em_inputs(name)
    lin, dm, S = e["lin"], e["dm"], e["S"]
    rng = np.random.default_rng(7)
    rows = np.array([2, 0, 0, 5, 2, 3, 1, 5, 4])
    chans = [dataclasses.replace(ch, R=r[rows] * rng.uniform(0.5, 2.0, (len(rows), 1, 1)))
             for ch, r in zip(e["chans"], e["R"])]
    m0 = S.m0[rows] + 1e-4 * rng.standard_normal((len(rows), dm.n))
    return kalman_loglik_affine(m0, e["P0"][rows], e["Q"][rows] * rng.uniform(0.5, 2.0, (len(rows), 1, 1)), dm.dt,
                                lin.A, lin.b, chans, lin.H, lin.d, state_angles=dm.angles, rows=rows, kernels=setting)


def _filter_smoother(name, setting):
    """EM's fused pass: what it writes (the compiled pass writes neither the filter's covariances nor the
    smoother's gains and cross-covariances; repairs are counted per matrix, not per batch: their sum)."""
    from needlecli.numerics.kalman import kalman_filter_smoother

    e = em_inputs(name)
    lin, dm = e["lin"], e["dm"]
    fwd, sm = kalman_filter_smoother(e["S"].m0, e["P0"], e["Q"], dm.dt, lin.A, lin.b, e["chans"], lin.H, lin.d,
                                     state_angles=dm.angles, kernels=setting)
    return {"m_pred": fwd.m_pred, "m_filt": fwd.m_filt, "loglik": fwd.loglik, "m": sm.m, "P": sm.P,
            "repairs": fwd.repairs + sm.repairs}


def _rts(name, setting):
    """The smoother of a stored filter (its gains against numpy's LU differ at 1e-6 in the ill-conditioned
    directions of P_{k+1|k}: compared through what the smoother makes of them)."""
    from needlecli.numerics.kalman import rts_smoother

    e = em_inputs(name)
    sm = rts_smoother(e["fwd"], state_angles=e["dm"].angles, kernels=setting)
    return {"m": sm.m, "P": sm.P, "C": sm.C, "repairs": sm.repairs}


def _process_noise(name, setting):
    from needlecli.numerics.kalman import em_process_noise

    e = em_inputs(name)
    lin, dm = e["lin"], e["dm"]
    return em_process_noise(e["sm"], lin.A, lin.b, dm.dt, index=e["S"].q_index, state_angles=dm.angles,
                            kernels=setting)


def _measurement_noise(name, setting):
    from needlecli.numerics.kalman import em_measurement_noise

    e = em_inputs(name)
    lin = e["lin"]
    return [em_measurement_noise(e["sm"], ch, lin.H[j], lin.d[j], kernels=setting) for j, ch in enumerate(e["chans"])]


for _twin, _fn in (("transition_all", _transition_all), ("transition_one", _transition_one),
                   ("kalman_forward_affine", _forward), ("kalman_loglik_affine", _loglik),
                   ("kalman_filter_smoother", _filter_smoother), ("rts_smoother", _rts),
                   ("em_process_noise", _process_noise), ("em_measurement_noise", _measurement_noise)):
    _em_case(_twin, _fn)
_em_case("linearise", _linearise, atol=1e-15)


# ---- metrics
@functools.cache
def errors_tree(path: str, overrides: tuple[str, ...]):
    """A results file's content (numpy path) with a run made to diverge and a NaN estimate."""
    from needlecli.experiments.config.load import load_config
    from needlecli.experiments.simulation.runner import build_sensors, results_tree, run_experiment

    cfg, text = load_config(ROOT / path, runs=5, overrides=[*overrides, "simulation.kernels=numpy"])
    with _no_override():
        res = run_experiment(cfg, text, write=False)
    tree = results_tree(cfg, text, res.truth, res.measurements, res.estimates, build_sensors(cfg, res.truth.model))
    for grp in tree.data["estimates"].data.values():
        grp.data["status"] = np.asarray(grp.data["status"]).astype(object)
        grp.data["status"][1] = "diverged"
        grp.data["state"] = np.array(grp.data["state"])
        grp.data["state"][2, 5:9] = np.nan
    return tree


def _errors(path, overrides, setting):
    from needlecli.metrics import compute_errors

    out = {}
    for obs, es in compute_errors(errors_tree(path, overrides), kernels=setting).items():
        out[obs] = {"excluded": dict(es.excluded), "quantities": {q: {"unit": e.unit, "runs": e.runs, "values": e.values}
                                                                   for q, e in es.quantities.items()}}
    return out


def _errors_check(ref, got):
    """The position norm, wrapped angles and other states bit for bit; E_R (sines and cosines to 1 ulp) to
    1e-10 rad."""
    assert_agree({o: {**r, "quantities": {q: v for q, v in r["quantities"].items() if q != "E_R"}} for o, r in ref.items()},
                 {o: {**r, "quantities": {q: v for q, v in r["quantities"].items() if q != "E_R"}} for o, r in got.items()},
                 0.0)
    for o, r in ref.items():
        assert ("E_R" in r["quantities"]) == ("E_R" in got[o]["quantities"])
        if "E_R" in r["quantities"]:
            assert_agree(r["quantities"]["E_R"], got[o]["quantities"]["E_R"], ATOL * 180 / np.pi)


for _path, _over in [("configs/multirate-ukf-us3d/table1.yaml", ("stop.depth=10",)), ("configs/default.yaml", ("stop.depth=30",)),
                     ("configs/examples/mnm_s_turn.yaml", ("stop.time=3",))]:  # metres, h and B
    case("state_errors", _path, check=_errors_check)(functools.partial(_errors, _path, _over))


@case("rotation_error", "random orientations")
def _rotation(setting):
    """Random orientations as Euler angles, angles past pi, errors from 1e-9 to 3 rad, the same
    orientation given two ways (an error of 0 from angles far apart)."""
    from needlecli.numerics import euler_xyz_to_matrix, rotation_angle

    rng = np.random.default_rng(2)
    t = rng.uniform(-2 * np.pi, 2 * np.pi, (7, 300, 3))
    e = t + rng.normal(size=t.shape) * np.logspace(-9, 0.5, 300)[None, :, None]
    e[:, -5:] = t[:, -5:] * np.array([1.0, -1.0, 1.0]) + np.array([np.pi, 0.0, np.pi])
    fn = kernels.twin("rotation_error", setting)
    if fn is not None:
        return fn(t, e)
    rt, re = euler_xyz_to_matrix(*np.moveaxis(t, -1, 0)), euler_xyz_to_matrix(*np.moveaxis(e, -1, 0))
    return rotation_angle(np.swapaxes(rt, -1, -2) @ re)
