"""Tests of the particle filters (``needlecli.observers.pf``: ``pf``; ``needlecli.observers.rbpf``: ``rbpf``).

References are independent of the code under test: on a linear-Gaussian model (``tests/linear_model.py``)
the Kalman filter of ``tests/test_ukf.py`` (written from scratch) is the exact posterior, which a particle
filter with many particles must match within its Monte-Carlo error; the random-number generator against
the normal and uniform distributions (Kolmogorov-Smirnov); systematic resampling against its definition.
"""

from __future__ import annotations

import dataclasses
import sys
from pathlib import Path

import linear_model
import numpy as np
import pytest
from linear_model import linear_system, rk4_transition

from needlecli.models import MODELS
from needlecli.observers.base import EstimationProblem
from needlecli.observers.pf import ParticleFilter, PFSettings, _count_below, normals, stream_base, uniforms
from needlecli.observers.rbpf import RaoBlackwellisedParticleFilter, RBPFSettings

sys.path.insert(0, str(Path(__file__).resolve().parent))
from test_ukf import _channel, kalman_reference  # noqa: E402

STATES = ("x", "y", "z", "vx", "vy", "vz")
DT = 0.01
Q = np.array([0.03, 0.03, 0.03, 0.05, 0.05, 0.05])  # the truth's noise std per grid step
Q_ROOT = Q / np.sqrt(DT)  # the filters' q: the same, per square-root second
P0 = np.array([0.09, 0.09, 0.09, 0.04, 0.04, 0.04])  # variances
SIGMA = {"pos": 0.3, "vel": 0.05}  # as kalman_reference of test_ukf has them (SIGMA_LIN)
RB_NAME = "linear_test_model_translation"


class _Translation(linear_model.LinearTestModel):
    """The linear test model with its positions declared translation states (its vector field does not
    depend on them): the Rao-Blackwellised filter's case."""

    translation_states = ("x", "y", "z")


if RB_NAME not in MODELS:
    MODELS.register(RB_NAME)(_Translation)


def linear_problem(model_name=linear_model.NAME, seed=0, n_runs=3, n_steps=60, dropout=0.2):
    """A linear-Gaussian truth whose initial state is drawn from the filters' prior ``N(x0, diag(P0))`` and
    whose noise is the filters' ``Q`` per step; ``pos`` (x, y, z) every 5 steps and ``vel`` (vx) every 2
    steps, 13 ms late; ``dropout`` of the samples lost."""
    rng = np.random.default_rng(seed)
    model = MODELS.get(model_name)()
    p = model.param_arrays()
    A, B = linear_system(float(p["damping"]), float(p["omega"]))
    phi, gam = rk4_transition(A, B, DT)
    T = n_steps + 1
    time = DT * np.arange(T)
    u = np.zeros((n_runs, T, 4))
    u[..., 0] = 1.0
    u[..., 1:] = np.sin(time[None, :, None] * np.array([1.0, 2.0, 3.0]) + rng.uniform(0, 6, (n_runs, 1, 3)))
    x0 = np.array([1.0, -2.0, 0.5, 0.3, -0.1, 0.2]) + np.zeros((n_runs, 6))
    x = x0 + np.sqrt(P0) * rng.standard_normal((n_runs, 6))
    truth = [x]
    for k in range(T - 1):
        x = x @ phi.T + u[:, k] @ gam.T + Q * rng.standard_normal((n_runs, 6))
        truth.append(x)
    truth = np.stack(truth, 1)

    def samples(cols, every, sigma):
        idx = np.arange(0, T, every)
        val = truth[:, idx][..., cols] + sigma * rng.standard_normal((n_runs, len(idx), len(cols)))
        valid = rng.random((n_runs, len(idx))) >= dropout
        return idx, np.where(valid[..., None], val, np.nan), valid

    pi, pv, pm = samples([0, 1, 2], 5, SIGMA["pos"])
    vi, vv, vm = samples([3], 2, SIGMA["vel"])
    channels = {"pos": _channel("pos", [0, 1, 2], pi, 0.0, pv, pm, time, SIGMA["pos"], selection=True),
                "vel": _channel("vel", [3], vi, 0.013, vv, vm, time, SIGMA["vel"], selection=True)}
    return EstimationProblem(time=time, inputs=u, input_names=model.input_names,
                             depth=np.cumsum(u[..., 0], axis=1) * DT, channels=channels, model=model, params=p,
                             interfaces=np.zeros(0), initial_truth=x0), truth


def particle_filter(problem, particles, *, rb=False, seed=1, **extra):
    cls, settings = (RaoBlackwellisedParticleFilter, RBPFSettings) if rb else (ParticleFilter, PFSettings)
    s = settings.model_validate({
        "type": "rbpf" if rb else "pf", "particles": particles,
        "q": dict(zip(STATES, map(float, Q_ROOT))), "p0": dict(zip(STATES, map(float, P0))),
        "measurements": {c: {"sigma": SIGMA[c]} for c in problem.channels}, "init": {"from": "truth"}, **extra})
    return cls(s).run(problem, np.random.default_rng(seed))


# ============================================================================ 1. the Kalman filter's limit
@pytest.mark.parametrize("rb", [False, True], ids=["pf", "rbpf"])
def test_many_particles_match_the_kalman_filter(rb):
    """On a linear-Gaussian model the posterior is the Kalman filter's. A weighted mean of particles
    carries Monte-Carlo error of about ``sigma / sqrt(ESS)`` at one step (``sigma`` the posterior std, ESS
    the effective sample size), a variance ``sigma^2 sqrt(2 / ESS)``; the errors of earlier steps carry
    over (through resampling, for about the time the model takes to forget them), which we allow for
    with a factor 2 on the std (4 on the variance of the error). With ``P = 20000`` particles and the
    filter's smallest ESS over the run (reported by the filter itself, per run) at 6 such errors: the mean
    within ``12 sigma / sqrt(ESS_min)`` of the Kalman filter's at every step, each variance within ``12
    sqrt(2 / ESS_min)`` relatively, each correlation within ``12 / sqrt(ESS_min)``. A wrong likelihood,
    noise or resampling is off by tenths of sigma or more (e.g. 1.4 sigma for a likelihood std of 0.1
    instead of 0.05); these bounds are 0.2 to 0.5 sigma. (The Rao-Blackwellised filter carries the
    positions exactly given the velocities: its error is smaller.)"""
    problem, _ = linear_problem(RB_NAME if rb else linear_model.NAME)
    ref_x, ref_p = kalman_reference(problem, q=Q_ROOT, p0=P0)
    post = particle_filter(problem, 20000, rb=rb)
    assert (post.status == "ok").all()
    ess_min = post.extras["ess"].min(axis=1)  # (N,)
    assert (ess_min > 500).all()  # the case is one a bootstrap filter handles (no collapse)
    tol = 12.0 / np.sqrt(ess_min)
    sd = np.sqrt(np.diagonal(ref_p, axis1=-2, axis2=-1))
    z = np.abs(post.state - ref_x) / sd
    assert (z.max(axis=(1, 2)) <= tol).all(), z.max(axis=(1, 2)) / tol
    var = np.diagonal(post.cov, axis1=-2, axis2=-1) / sd**2
    assert (np.abs(var - 1).max(axis=(1, 2)) <= tol * np.sqrt(2.0)).all(), np.abs(var - 1).max(axis=(1, 2)) / tol
    corr = (post.cov - ref_p) / (sd[..., :, None] * sd[..., None, :])
    assert (np.abs(corr).max(axis=(1, 2, 3)) <= tol).all(), np.abs(corr).max(axis=(1, 2, 3)) / tol
    # the counters: every valid sample arriving after t = 0 is used once (one channel sample per tick)
    for name in ("pos", "vel"):
        ch = problem.channels[name]
        arrives = np.ceil(ch.t_available / DT - 1e-9)
        in_time = (arrives > 0) & (arrives <= len(problem.time) - 1)
        np.testing.assert_array_equal(post.extras[f"used/{name}"], (ch.valid & in_time).sum(1))


# ============================================================================ 2. the pieces
def test_counter_based_draws_are_standard_and_independent():
    """Normals and uniforms of the counter-based generator against their distributions (Kolmogorov-Smirnov
    at 1e-3 on 2e5 draws of each of four runs); draws of another tick, purpose or key are uncorrelated
    (|r| < 5 / sqrt(M)); the same key gives the same draws."""
    from scipy import stats

    runs = np.arange(4, dtype=np.uint64)
    z = normals(stream_base(99, 1, runs, 7), 200_000)
    u = uniforms(stream_base(99, 1, runs, 7), 200_000)
    for i in range(4):
        assert stats.kstest(z[i], "norm").pvalue > 1e-3
        assert stats.kstest(u[i], "uniform").pvalue > 1e-3
    M = 200_000
    for other in (stream_base(99, 1, runs, 8), stream_base(99, 2, runs, 7), stream_base(98, 1, runs, 7)):
        assert abs(np.corrcoef(z[0], normals(other, M)[0])[0, 1]) < 5 / np.sqrt(M)
    assert abs(np.corrcoef(z[0], z[1])[0, 1]) < 5 / np.sqrt(M)
    np.testing.assert_array_equal(normals(stream_base(99, 1, runs, 7), 10), z[:, :10])


def test_systematic_resampling_counts():
    """``_count_below`` is the merge of the cumulative weights and the systematic points: per row the
    number of cumulative weights ``<= (u + i) / P``, as ``np.searchsorted(c, pos, side='right')`` gives it,
    ties included."""
    rng = np.random.default_rng(4)
    w = rng.random((5, 50)) ** 4
    w[2, 10:] = 0.0  # a run with few particles of weight
    c = np.cumsum(w / w.sum(1, keepdims=True), axis=1)
    c[:, -1] = 1.0
    pos = (rng.random((5, 1)) + np.arange(50)) / 50
    pos[3] = c[3]  # ties: a point on a cumulative weight counts it
    got = _count_below(c, pos)
    for r in range(5):
        np.testing.assert_array_equal(got[r], np.searchsorted(c[r], pos[r], side="right"))


# ============================================================================ 3. in experiments
def _unicycle(observer: str, runs: int = 3, extra_sensor: str = "") -> str:
    return f"""\
name: pf_case
model: {{type: unicycle, params: {{kappa: 0.005}}, initial_state: {{beta: 1.45}}}}
inputs: {{v: 1.5, u: 0.0}}
sensors:
  - {{name: us, type: position, rate: 10.0, sigma: 0.3}}
  - {{name: robot, type: encoder, rate: 100.0, channels: [roll], sigma: 0.0035}}{extra_sensor}
observers:
  - {observer}
runs: {{count: {runs}, seed: 1}}
stop: {{time: 0.5}}
"""


def _run(text: str, setting: str = "numpy", seed: int | None = None):
    from needlecli.experiments.config.load import load_config
    from needlecli.experiments.simulation.runner import build_problem, simulate_and_measure
    from needlecli.experiments.simulation.truth import stream
    from needlecli.observers import OBSERVERS
    from needlecli.observers.contract import check_posterior

    cfg, _ = load_config(text=text, overrides=["simulation.kernels=numpy"])
    truth, sensors, streams, _ = simulate_and_measure(cfg)
    problem = dataclasses.replace(build_problem(cfg, truth, sensors, streams), kernels=setting)
    o = cfg.observers[0]
    post = OBSERVERS.get(o.type)(o).run(problem, stream(cfg.runs.seed if seed is None else seed, "observer/pf"))
    assert check_posterior(post, problem) is None  # the results contract, as every observer's
    return post


SETTINGS = ["numpy", pytest.param("numba", marks=pytest.mark.skipif(
    __import__("importlib").util.find_spec("numba") is None, reason="numba not installed"))]


@pytest.mark.parametrize("setting", SETTINGS)
def test_particles_that_leave_the_domain_die_and_the_run_goes_on(setting):
    """The unicycle is undefined at beta = pi/2. Particles drawn about beta = 1.45 with std 0.2 (27 % beyond
    pi/2) die at the first tick: the ESS falls to about 0.73 P and the run goes on; particles all beyond
    pi/2 stop the run 'singular' at the first tick, with the reason."""
    obs = ("{name: pf, type: pf, particles: 400, q: {x: 1.0e-3, y: 1.0e-3, z: 1.0e-3, alpha: 1.0e-4, beta: 1.0e-4, "
           "gamma: 1.0e-3}, p0: {beta: BETA_VAR}, init: {from: truth, values: {beta: BETA}}}")
    post = _run(_unicycle(obs.replace("BETA_VAR", "0.04").replace("BETA", "1.45")), setting)
    assert (post.status == "ok").all()
    share = post.extras["ess"][:, 1] / 400  # after the first tick (no sample yet: the survivors' weights equal)
    np.testing.assert_allclose(share, 0.73, atol=4 * np.sqrt(0.27 * 0.73 / 400))
    post = _run(_unicycle(obs.replace("BETA_VAR", "1.0e-6").replace("BETA", "1.6")), setting)
    assert (post.status == "singular").all()
    assert all(r.startswith("every particle left the model's domain: cos(beta)") and "t = 0.01 s" in r
               for r in post.reason)


@pytest.mark.parametrize("setting", SETTINGS)
def test_same_seed_same_particles(setting):
    """The particles come from the run's stream: the same seed gives the same estimates, another seed others;
    the ESS and resampling flags are per run and tick ``(N, K)``."""
    obs = ("{name: pf, type: pf, particles: 200, q: {x: 1.0e-3, y: 1.0e-3, z: 1.0e-3, alpha: 1.0e-3, beta: 1.0e-3, "
           "gamma: 1.0e-3}, p0: {alpha: 0.01, beta: 0.01, gamma: 0.01}, init: {from: truth}}")
    a, b, c = (_run(_unicycle(obs), setting), _run(_unicycle(obs), setting), _run(_unicycle(obs), setting, seed=2))
    np.testing.assert_array_equal(a.state, b.state)
    assert np.abs(a.state - c.state).max() > 1e-6
    K = len(a.extras["ticks"])
    assert a.extras["ess"].shape == a.extras["resampled"].shape == (3, K) and a.extras["resampled"].any()


def test_rbpf_refuses_what_is_not_conditionally_linear():
    """The Rao-Blackwellised filter says why where it does not apply: a model without translation states,
    a Student-t likelihood on a position channel, a one-sided channel."""
    from needlecli.errors import ConfigError
    from needlecli.experiments.config.load import load_config

    so3 = """\
name: so3_case
model: {type: so3}
inputs: {v: 1.5, u: 0.5}
sensors: [{name: tan, type: tangent, rate: 10.0, sigma: 0.01}]
observers: [{name: rb, type: rbpf}]
stop: {time: 1.0}
"""
    with pytest.raises(ConfigError, match="no positions that its motion does not depend on"):
        load_config(text=so3)
    with pytest.raises(ConfigError, match=r"measurements -> us -> likelihood.*Gaussian likelihood only"):
        load_config(text=_unicycle("{name: rb, type: rbpf, measurements: {us: {sigma: 0.3, likelihood: student_t}}}"))
    load_config(text=_unicycle("{name: rb, type: pf, measurements: {us: {sigma: 0.3, likelihood: student_t}}}"))
    load_config(text=_unicycle("{name: rb, type: rbpf, measurements: {robot: {sigma: 0.01, likelihood: student_t}}}"))
    with pytest.raises(ConfigError, match="dof is for likelihood: student_t"):
        load_config(text=_unicycle("{name: p, type: pf, measurements: {us: {sigma: 0.3, dof: 3.0}}}"))


def test_outliers_of_a_sensor():
    """``outliers``: a share of the samples with ``scale`` times the noise; the other samples keep the noise
    they have without the setting (drawn first from the same stream). Per axis, a gross error (std 6 mm)
    is beyond 1.8 mm (6 sigma of the ordinary noise) with probability 2 (1 - Phi(0.3)) = 0.764."""
    from scipy.stats import norm

    from needlecli.experiments.config.load import load_config
    from needlecli.experiments.simulation.runner import simulate_and_measure

    def us(extra):
        text = _unicycle("{name: o, type: open_loop}", runs=40).replace(
            "{name: us, type: position, rate: 10.0, sigma: 0.3}", "{name: us, type: position, rate: 10.0, sigma: 0.3"
            + extra + "}").replace("time: 0.5", "time: 20.0")
        cfg, _ = load_config(text=text)
        truth, _, streams, _ = simulate_and_measure(cfg)
        s = streams["us"] if isinstance(streams, dict) else next(x for x in streams if x is not None and x.value.shape[-1] == 3)
        return s.value - truth.states[:, s.index, :3]

    plain, wild = us(""), us(", outliers: {probability: 0.2, scale: 20.0}")
    same = np.all(wild == plain, axis=-1)
    share = 1 - same.mean()
    n = same.size
    assert abs(share - 0.2) < 4 * np.sqrt(0.2 * 0.8 / n)  # the gross ones differ (all: continuous draws)
    beyond = np.abs(wild[~same]) > 1.8
    p = 2 * (1 - norm.cdf(0.3))
    assert abs(beyond.mean() - p) < 4 * np.sqrt(p * (1 - p) / beyond.size)
    assert np.abs(plain).max() < 1.8


# ============================================================================ 4. the commands, end to end
def _study(tmp_path: Path, runs: int = 4) -> Path:
    """The EM tutorial's experiment (configs/tutorials/fit_em.yaml: a unicycle, a 5 Hz tracker, a fit:
    section), shortened, with a bootstrap and a Rao-Blackwellised filter of 200 particles beside its
    open loop."""
    import yaml

    data = yaml.safe_load((Path(__file__).resolve().parents[1] / "configs/tutorials/fit_em.yaml").read_text())
    data["format"] = 2  # q per square-root second
    data["runs"]["count"] = runs
    data["stop"] = {"depth": 8.0}
    data["output"] = {"covariance": "full", "tables": ["summary"]}
    data["fit"]["em"] = {"max_iter": 100, "tol": 0.05}
    filt = {"particles": 200, "roughening": 0.1,
            "q": {"x": 0.01, "y": 0.01, "z": 0.01, "alpha": 1.0e-3, "beta": 1.0e-3, "gamma": 1.0e-3},
            "p0": {"alpha": 1.0e-3, "beta": 1.0e-3, "gamma": 1.0e-2},
            "measurements": {"tracker": {"sigma": 0.2}},
            "init": {"from": "truth", "first_measurement": {"x": "tracker.x", "y": "tracker.y", "z": "tracker.z"}}}
    data["observers"] += [{"name": "pf", "type": "pf", **filt}, {"name": "rbpf", "type": "rbpf", **filt}]
    path = tmp_path / "study.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


def _cli(*args):
    from typer.testing import CliRunner

    from needlecli.cli.app import app

    r = CliRunner().invoke(app, [str(a) for a in args])
    assert r.exit_code == 0, r.output
    return r


def _estimates_contract(path: Path, names=("pf", "rbpf"), runs: int = 4) -> None:
    """Each filter's group: covariances ``(N, T, n, n)`` symmetric PSD, ESS and the resampled flags ``(N, K)``
    at its ticks, the NIS of the tracker's samples; every run ok."""
    from needlecli.io.results import read_results

    res = read_results(path)
    T = np.asarray(res.data["time"]).shape[0]
    for name in names:
        g = res.data["estimates"].data[name].data
        assert (np.asarray(g["status"]).astype(str) == "ok").all()
        C = np.asarray(g["cov"])
        assert C.shape == (runs, T, 6, 6)
        np.testing.assert_allclose(C, np.swapaxes(C, -1, -2), atol=1e-12)
        assert np.linalg.eigvalsh(C).min() > -1e-12
        K = np.asarray(g["ticks"]).shape[0]
        assert np.asarray(g["ess"]).shape == np.asarray(g["resampled"]).shape == (runs, K)
        assert ((np.asarray(g["ess"]) > 0) & (np.asarray(g["ess"]) <= 200 + 1e-9)).all()
        assert np.isfinite(np.asarray(g["nis"].data["tracker"])).any()


def test_simulate_evaluate_replay_compare_crossval_with_the_particle_filters(tmp_path, monkeypatch):
    """Both filters through every command that runs observers: ``simulate`` (the results contract's
    covariances, the ESS and resampling flags per tick, NEES and NIS in ``evaluate``'s consistency table),
    a replay of the simulation's log, ``compare`` (with the settings they derive themselves) and
    ``crossval`` (their EM-tuned copies, from ``from_fit``)."""
    import pandas as pd

    from needlecli.io.logs import log_from_results, write_log
    from needlecli.io.results import read_results

    monkeypatch.chdir(tmp_path)
    cfg = _study(tmp_path)
    _cli("simulate", cfg, "--out", tmp_path / "sim.h5", "--quiet")
    _estimates_contract(tmp_path / "sim.h5")
    _cli("evaluate", tmp_path / "sim.h5", "--tables", "consistency", "--out", tmp_path / "ev", "--no-plots", "--quiet")
    table = (tmp_path / "ev" / "fit_em_consistency.md").read_text()
    for name in ("pf", "rbpf"):
        assert f"| {name} " in table and "ANEES" in table and "ANIS" in table

    # a replay: the simulation's log, the same observers
    import yaml

    write_log(tmp_path / "log.h5", log_from_results(read_results(tmp_path / "sim.h5")))
    data = yaml.safe_load(cfg.read_text())
    for k in ("inputs", "sensors", "stop", "process_noise"):
        data.pop(k, None)
    data["source"] = {"logs": [str(tmp_path / "log.h5")]}
    (tmp_path / "replay.yaml").write_text(yaml.safe_dump(data, sort_keys=False))
    _cli("simulate", tmp_path / "replay.yaml", "--out", tmp_path / "replay.h5", "--quiet")
    assert read_results(tmp_path / "replay.h5").attrs["source"] == "replay"
    _estimates_contract(tmp_path / "replay.h5")

    _cli("compare", cfg, "--observers", "hand_tuned,pf,rbpf", "--out", tmp_path / "cmp", "--quiet")
    df = pd.read_csv(tmp_path / "cmp" / "compare.csv").set_index("observer")
    assert {"pf", "rbpf"} <= set(df.index), df.index
    assert (df.loc[["pf", "rbpf"], "E_xyz_mean"] < 0.2).all()  # under the tracker's noise: they filter

    _cli("crossval", cfg, "--observer", "pf", "--observer", "rbpf", "--folds", "2", "--from-depths", "",
         "--out", "cv", "--quiet")
    s = pd.read_csv(tmp_path / "cv" / "crossval_summary.csv").set_index("Observer")
    assert {"pf", "pf_em", "rbpf", "rbpf_em"} <= set(s.index) and (s["Held-out trials"] == 4).all()


def test_the_image_plane_weighs_particles_by_its_probit(tmp_path):
    """The one-sided image plane (tests/test_plane_bound.py's experiment: the filters started 5 mm off along
    the needle, the plane their only measurement) brings the bootstrap filter to the tip, by the probit
    likelihood of the seen/lost verdict, as it brings the UKF; without it the 5 mm stay. The
    Rao-Blackwellised filter refuses the plane (position and tangent bounded together: not conditionally
    linear), and the plane's likelihood is not a setting."""
    import yaml
    from test_plane_bound import SIM

    from needlecli.errors import ConfigError
    from needlecli.experiments.config.load import load_config
    from needlecli.experiments.simulation.runner import run_experiment
    from needlecli.io.results import read_results

    data = yaml.safe_load(SIM)
    for o in data["observers"]:
        o.update(type="pf", particles=300, roughening=0.1)
    cfg, text = load_config(text=yaml.safe_dump(data, sort_keys=False))
    run_experiment(cfg, text, out=tmp_path / "plane.h5", base_dir=tmp_path)
    res = read_results(tmp_path / "plane.h5")
    truth = np.asarray(res.data["truth"].data["state"])
    est = {o: np.asarray(res.data["estimates"].data[o].data["state"]) for o in ("with_plane", "without")}
    used = np.asarray(res.data["estimates"].data["with_plane"].data["used"].data["plane"])
    assert (used > 0.9 * np.asarray(res.data["measurements"].data["plane"].data["index"]).size).all()
    err = {o: np.abs(e[:, -1, 2] - truth[:, -1, 2]).mean() for o, e in est.items()}
    assert err["without"] > 4.0 and err["with_plane"] < 1.5, err
    for change, match in (({"type": "rbpf"}, "not conditionally linear"),
                          ({"measurements": {"plane": {"sigma": 0.2, "likelihood": "student_t"}}}, "probit")):
        bad = yaml.safe_load(SIM)
        bad["observers"][0].update({"type": "pf", **change})
        with pytest.raises(ConfigError, match=match):
            load_config(text=yaml.safe_dump(bad, sort_keys=False))
