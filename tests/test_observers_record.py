"""The run recorder (needlecli.observers.record), the bookkeeping every observer's run shares: on its own
against plainly computed expectations (held steps, kept covariances in each layout, status and reason with
the event's time, the last good estimate of a stopped run, counters, progress), then that every built-in
observer's Posterior is built by it and that a plug-in observer written on it runs in ``needle simulate``
and its results file passes ``needle evaluate``."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest
from numpy.testing import assert_array_equal

from needlecli.observers.record import RunRecorder, event_reason
from needlecli.problem import EstimationProblem

ROOT = Path(__file__).resolve().parent.parent


def _problem(N: int = 3, T: int = 11, stride: int = 1, layout: str = "full", dt: float = 0.125) -> EstimationProblem:
    """A problem with ``N`` runs on ``T`` grid steps of ``dt`` (all the recorder reads)."""
    return EstimationProblem(time=dt * np.arange(T), inputs=np.zeros((N, T, 0)), input_names=(),
                             depth=np.zeros((N, T)), channels={}, model=None, params={}, interfaces=np.zeros(0),
                             cov_stride=stride, cov_layout=layout)


def _last_tick(ticks, j: int) -> int:
    """The index of the last tick at or before grid step j."""
    return max(i for i, k in enumerate(ticks) if k <= j)


# ---------------------------------------------------------------------------------------------- estimates
@pytest.mark.parametrize("layout", ["full", "diag", "none"])
@pytest.mark.parametrize("stride", [1, 3])
def test_steps_between_ticks_hold_and_covariances_are_kept_every_stride(layout, stride):
    rng = np.random.default_rng(0)
    N, T, n = 3, 11, 2
    ticks = [0, 4, 5, 9]  # steps 1-3, 6-8 and (after the last record) 10 hold the last tick
    xs, Ps = rng.normal(size=(len(ticks), N, n)), rng.normal(size=(len(ticks), N, n, n))
    rec = RunRecorder(_problem(N, T, stride, layout), n, series={"mode": np.int8})
    for i, k in enumerate(ticks):
        x, P = xs[i].copy(), Ps[i].copy()
        rec.record(k, x, P, mode=np.full(N, i))
        x[:], P[:] = np.nan, np.nan  # the caller's arrays change afterwards: nothing recorded moves
    post = rec.posterior(("a", "b"), ("mm", "rad"), angle_states=("b",))
    assert post.state.shape == (N, T, n)
    for j in range(T):
        assert_array_equal(post.state[:, j], xs[_last_tick(ticks, j)])
        assert_array_equal(rec.series["mode"][:, j], _last_tick(ticks, j))
    kept = list(range(0, T, stride))
    assert_array_equal(rec.cov_index, kept)
    if layout == "none":
        assert post.cov is None
        return
    assert post.cov.shape == ((N, len(kept), n, n) if layout == "full" else (N, len(kept), n))
    for slot, j in enumerate(kept):
        P = Ps[_last_tick(ticks, j)]
        assert_array_equal(post.cov[:, slot], P if layout == "full" else np.diagonal(P, axis1=1, axis2=2))


def test_without_covariance_none_is_kept_whatever_the_layout():
    rec = RunRecorder(_problem(layout="full"), 2, covariance=False)
    rec.record(0, np.ones((3, 2)))
    assert rec.posterior(("a", "b"), ("1", "1")).cov is None


def test_records_start_at_step_zero_and_increase():
    x, P = np.zeros((3, 1)), np.zeros((3, 1, 1))
    rec = RunRecorder(_problem(), 1)
    with pytest.raises(ValueError, match="the first at 0"):
        rec.record(2, x, P)
    rec.record(0, x, P)
    for k in (0, 11):  # again, past the grid
        with pytest.raises(ValueError, match="increasing steps below 11"):
            rec.record(k, x, P)
    with pytest.raises(ValueError, match="record P with x"):
        rec.record(1, x)
    with pytest.raises(ValueError, match="series recorded: mode; declared: none"):
        rec.record(1, x, P, mode=np.zeros(3))
    with pytest.raises(ValueError, match="no estimate recorded"):
        RunRecorder(_problem(), 1).posterior(("a",), ("1",))
    with pytest.raises(ValueError, match="2 names and 1 units for 1 states"):
        rec.posterior(("a", "b"), ("1",))


def test_record_all_is_record_at_every_tick():
    rng = np.random.default_rng(1)
    N, T, n, ticks = 2, 12, 3, np.array([0, 2, 3, 7, 11])
    x, P = rng.normal(size=(N, len(ticks), n)), rng.normal(size=(N, len(ticks), n, n))
    rec = RunRecorder(_problem(N, T, stride=2, layout="diag"), n)
    rec.record_all(ticks, x, P)
    for j in range(T):
        assert_array_equal(rec.states[:, j], x[:, _last_tick(ticks, j)])
    for slot, j in enumerate(range(0, T, 2)):
        assert_array_equal(rec.cov[:, slot], np.diagonal(P[:, _last_tick(ticks, j)], axis1=1, axis2=2))
    # the estimate on the whole grid (carried between ticks by a model), covariances still from the ticks
    grid = rng.normal(size=(N, T, n))
    rec = RunRecorder(_problem(N, T, stride=2, layout="full"), n)
    rec.record_all(ticks, P=P, state=grid)
    assert rec.states is grid
    assert_array_equal(rec.cov[:, 3], P[:, _last_tick(ticks, 6)])
    with pytest.raises(ValueError, match="not both|at the ticks"):
        rec.record_all(ticks, x, P, state=grid)


def test_adopt_takes_arrays_of_the_recorders_shapes_only():
    rec = RunRecorder(_problem(3, 5, stride=2, layout="diag"), 2)
    states, cov = np.zeros((3, 5, 2)), np.zeros((3, 3, 2))
    with pytest.raises(ValueError, match=r"cov of shape \(3, 5, 2\), expected \(3, 3, 2\)"):
        rec.adopt(states, np.zeros((3, 5, 2)))
    with pytest.raises(ValueError, match="covariances expected"):
        rec.adopt(states)
    rec.adopt(states, cov)
    post = rec.posterior(("a", "b"), ("1", "1"))
    assert post.state is states and post.cov is cov


# ---------------------------------------------------------------------------------------------- stopped runs
def test_stop_gives_status_and_reason_with_the_time_of_the_event_to_alive_runs_only():
    rec = RunRecorder(_problem(N=4), 1)
    new = rec.stop(2, np.array([True, False, True, False]), "diverged", "blew up at t = {t:.3f} s {not a time}")
    assert_array_equal(new, [True, False, True, False])
    new = rec.stop(5, np.array([True, True, False, False]), "singular", "{t}: B . h -> 0")  # run 0 stopped already
    assert_array_equal(new, [False, True, False, False])
    assert list(rec.status) == ["diverged", "singular", "diverged", "ok"]
    assert list(rec.reason) == ["blew up at t = 0.250 s {not a time}", "0.625: B . h -> 0",
                                "blew up at t = 0.250 s {not a time}", ""]
    assert_array_equal(rec.alive, [False, False, False, True])
    assert_array_equal(rec.event, [2, 5, 2, -1])
    # a step per run, a reason per run, an event without a time
    rec = RunRecorder(_problem(N=3), 1)
    rec.stop(np.array([1, 8, 4]), np.array([True, False, True]), "diverged", ["a {t:.2f}", "b {t:.2f}", "c {t:.2f}"])
    rec.stop(None, np.ones(3, dtype=bool), "unobservable", ["x", "no samples", "z"])
    assert list(rec.reason) == ["a 0.12", "no samples", "c 0.50"]
    assert list(rec.status) == ["diverged", "unobservable", "diverged"]
    assert_array_equal(rec.event, [1, -1, 4])
    rec.record(0, np.zeros((3, 1)), np.zeros((3, 1, 1)))
    post = rec.posterior(("a",), ("1",))
    assert post.status.dtype.kind == "U" and list(post.status) == ["diverged", "unobservable", "diverged"]


def test_event_reason_replaces_only_the_time():
    assert event_reason("cos(beta) -> 0 {x} (t = {t:.2f} s, {t})", 1.5) == "cos(beta) -> 0 {x} (t = 1.50 s, 1.5)"


def test_check_singular_where_finite_diverged_where_not_finite_or_exploding():
    """Runs: 0 fine; 1 finite and out of the domain; 2 non-finite and out of the domain (NaN is outside);
    3 exploding; 4 exploding and out of the domain; 5 a NaN covariance; 6 out of the domain, stopped before."""
    N = 7
    x = np.ones((N, 2))
    x[2, 1] = np.nan
    P = np.broadcast_to(np.eye(2), (N, 2, 2)).copy()
    P[3] *= 100.0
    P[4] *= 100.0
    P[5, 0, 0] = np.nan
    sing = np.array([False, True, True, False, True, False, True])
    rec = RunRecorder(_problem(N=N), 2)
    rec.stop(1, np.arange(N) == 6, "diverged", "before")
    new = rec.check(3, x, P, singular=sing, max_trace=50.0, singular_reason="domain at {t:.2f}",
                    diverged_reason="blown at {t:.2f}")
    assert_array_equal(new, [False, True, True, True, True, True, False])
    assert list(rec.status) == ["ok", "singular", "diverged", "diverged", "singular", "diverged", "diverged"]
    assert list(rec.reason) == ["", "domain at 0.38", "blown at 0.38", "blown at 0.38", "domain at 0.38",
                                "blown at 0.38", "before"]
    # without a covariance: the estimate alone
    rec = RunRecorder(_problem(N=N), 2, covariance=False)
    assert_array_equal(rec.check(1, x), np.arange(N) == 2)


def test_hold_keeps_the_last_good_value_of_stopped_runs_along_the_runs_axis():
    rng = np.random.default_rng(2)
    rec = RunRecorder(_problem(N=4), 2)
    new, old = rng.normal(size=(4, 2, 2)), rng.normal(size=(4, 2, 2))
    assert rec.hold(new, old) is new  # every run alive
    rec.stop(1, np.array([False, True, False, True]), "diverged", "x")
    held = rec.hold(new, old)
    assert_array_equal(held[[0, 2]], new[[0, 2]])
    assert_array_equal(held[[1, 3]], old[[1, 3]])
    soa = rec.hold(np.moveaxis(new, 0, -1), np.moveaxis(old, 0, -1), axis=-1)  # runs last: (..., N)
    assert_array_equal(np.moveaxis(soa, -1, 0), held)


def test_stop_first_and_hold_from_on_whole_trajectories_as_a_loop_over_the_stopped_runs():
    """The reference: for each run its first bad tick, the first listed event there, and from that tick on
    the estimate before it (the first one where it is bad at once)."""
    rng = np.random.default_rng(3)
    N, K, n = 40, 9, 2
    sing, blown = rng.random((N, K)) < 0.06, rng.random((N, K)) < 0.06
    blown[0, 0] = True  # bad at the first tick
    sing[1, 4] = blown[1, 4] = True  # both at once: the first listed wins
    steps = np.arange(K) * 3
    z, P = rng.normal(size=(N, K, n)), rng.normal(size=(N, K, n, n))
    z_ref, P_ref = z.copy(), P.copy()
    status, reason = ["ok"] * N, [""] * N
    for i in range(N):
        bad = sing[i] | blown[i]
        if bad.any():
            k = int(np.argmax(bad))
            status[i] = "singular" if sing[i, k] else "diverged"
            reason[i] = f"{status[i]} at {0.125 * steps[k]:.2f}"
            z_ref[i, k:] = z_ref[i, max(k - 1, 0)]
            P_ref[i, k:] = P_ref[i, max(k - 1, 0)]
    rec = RunRecorder(_problem(N=N, T=3 * K), n)
    first = rec.stop_first(steps, [(sing, "singular", "singular at {t:.2f}"), (blown, "diverged", "diverged at {t:.2f}")])
    assert (first >= 0).sum() > 5 and first[0] == 0 and rec.status[1] == "singular"
    assert list(rec.status) == status and list(rec.reason) == reason
    assert_array_equal(rec.hold_from(z, first), z_ref)
    assert_array_equal(rec.hold_from(P, first), P_ref)


# ---------------------------------------------------------------------------------------------- counters, progress
def test_counters_are_extras_changed_in_place():
    rec = RunRecorder(_problem(N=3), 1)
    c = rec.counter("repairs")
    c += np.array([True, False, True])
    rec.counter("repairs")[1] += 2
    rec.record(0, np.zeros((3, 1)), np.zeros((3, 1, 1)))
    post = rec.posterior(("a",), ("1",), extras={"other": np.arange(3)}, attrs={"model": "m"})
    assert_array_equal(post.extras["repairs"], [1, 2, 1])
    assert post.extras["repairs"].dtype == np.int64
    assert set(post.extras) == {"repairs", "other"} and post.attrs == {"model": "m"}


@pytest.mark.parametrize("every", [1, 7])
def test_progress_about_every_percent_of_the_grid(every):
    seen = []
    T = 1001
    rec = RunRecorder(_problem(N=1, T=T), 1, covariance=False, progress=lambda k, n: seen.append((k, n)))
    for k in range(0, T, every):
        rec.record(k, np.zeros((1, 1)))
    rec.posterior(("a",), ("1",))  # the last record (994 for every 7) held to the end
    done = [k for k, _ in seen]
    assert {n for _, n in seen} == {T - 1}
    assert done == sorted(set(done)) and 90 <= len(done) <= 101
    assert max(np.diff([0, *done])) <= 10 + every
    assert done[-1] == T - 1


# ---------------------------------------------------------------------------------------------- every observer
ALL_OBSERVERS = """\
name: every
model: {type: unicycle, params: {kappa: 0.004}, initial_std: {beta: 0.01, gamma: 0.05}}
inputs: {v: 2.0, u: 0.3}
process_noise: {std: {x: 0.01, y: 0.01, z: 0.01, alpha: 1.0e-4, beta: 1.0e-4, gamma: 1.0e-3}}
sensors:
  - {name: us, type: position, rate: 10.0, sigma: 0.2}
  - {name: tan, type: tangent, rate: 10.0, sigma: 0.01}
observers:
  - {name: ol, type: open_loop}
  - name: ukf
    type: ukf
    rate: 10.0
    q: {x: 0.01, y: 0.01, z: 0.01, alpha: 1.0e-3, beta: 1.0e-3, gamma: 1.0e-2}
    p0: {x: 1.0, y: 1.0, z: 1.0, alpha: 1.0e-3, beta: 1.0e-3, gamma: 1.0e-2}
    measurements: {us: {sigma: 0.2}}
  - {name: ekf, type: ekf, measurements: {us: {sigma: 0.2}}, q: {x: 0.01, y: 0.01, z: 0.01}, p0: {x: 1.0, y: 1.0, z: 1.0}}
  - {name: eks, type: eks, measurements: {us: {sigma: 0.2}}, q: {x: 0.01, y: 0.01, z: 0.01}, p0: {x: 1.0, y: 1.0, z: 1.0}}
  - {name: hg, type: high_gain, measurement: us, theta: 5.0}
  - {name: so3, type: so3_invariant, measurements: {tan: {}}, min_excitation: 0.001}
runs: {count: 2, seed: 4}
stop: {time: 1.0}
output: {store_every: 2, covariance: diag}
"""


@pytest.mark.parametrize("path", ["numpy", "compiled"])
def test_every_builtin_observer_builds_its_posterior_through_the_recorder(path, monkeypatch):
    from needlecli import kernels
    from needlecli.experiments.config.load import load_config
    from needlecli.experiments.simulation.runner import run_experiment

    if path == "numpy":
        monkeypatch.setenv(kernels.ENV, "numpy")
    else:
        monkeypatch.delenv(kernels.ENV, raising=False)
    built = []
    real = RunRecorder.posterior

    def spy(self, *a, **k):
        post = real(self, *a, **k)
        built.append(post)
        return post

    monkeypatch.setattr(RunRecorder, "posterior", spy)
    cfg, text = load_config(text=ALL_OBSERVERS)
    res = run_experiment(cfg, text, write=False)
    assert set(res.estimates) == {"ol", "ukf", "ekf", "eks", "hg", "so3"}
    for name, post in res.estimates.items():
        assert any(post is b for b in built), name
        assert (post.status == "ok").all(), (name, post.reason)
    assert res.estimates["ukf"].cov.shape == (2, len(range(0, res.estimates["ukf"].state.shape[1], 2)), 6)


PLUGIN = '''\
from typing import Literal

import numpy as np

from needlecli.observers import OBSERVERS, Observer, ObserverSettings, RunRecorder


class Settings(ObserverSettings):
    type: Literal["drift"]
    q: float = 0.5
    max_trace: float = 1.0e9


class Drift(Observer):
    """The model driven by the inputs from its default start, P growing by q dt, estimates every other
    grid step: only the maths; the recorder keeps the rest."""

    Settings = Settings

    def run(self, problem, rng, progress=None):
        m, s = problem.model, self.settings
        params = {k: np.asarray(v, dtype=float) for k, v in problem.params.items()}
        N, T = problem.n_runs, len(problem.time)
        x = np.broadcast_to(np.asarray(m.initial_state(params), dtype=float), (N, m.n)).copy()
        P = np.broadcast_to(np.eye(m.n), (N, m.n, m.n)).copy()
        rec = RunRecorder(problem, m.n, progress=progress)
        rec.record(0, x, P)
        for k in range(1, T):
            dt = float(problem.time[k] - problem.time[k - 1])
            xn, Pn = m.step(x, problem.inputs[:, k - 1], params, dt), P + s.q * dt * np.eye(m.n)
            rec.check(k, xn, Pn, singular=m.left_domain(x, xn, params), max_trace=s.max_trace)
            x, P = rec.hold(xn, x), rec.hold(Pn, P)
            if k % 2 == 0:
                rec.record(k, x, P)
        return rec.posterior(m.state_names, m.state_units, angle_states=m.angle_states,
                             extras={"steps": np.full(N, T)})
'''

PLUGIN_CONFIG = """\
name: drift
model: {type: unicycle, params: {kappa: 0.004}}
inputs: {v: 2.0, u: 0.0}
sensors: [{name: us, type: position, rate: 5.0, sigma: 0.2}]
observers: [{name: mine, type: drift, max_trace: %s}, {name: ol, type: open_loop}]
runs: {count: 3, seed: 1}
stop: {time: 2.0}
output: {store_every: 3, covariance: full}
"""


def _needle(args, env, cwd):
    return subprocess.run([sys.executable, "-m", "needlecli", *args], env=env, cwd=cwd, capture_output=True, text=True)


@pytest.mark.parametrize("max_trace", ["1.0e9", "7.0"])
def test_a_plugin_observer_written_on_the_recorder_simulates_and_evaluates(tmp_path, max_trace):
    """In a subprocess (registries read entry points once per process); with a trace limit the runs reach
    (P = (1 + 0.5 t) I, tr 7 at t = 1/3 s), every run diverges there and holds its estimate."""
    import h5py

    site = tmp_path / "site"
    (site / "driftplug-0.1.dist-info").mkdir(parents=True)
    (site / "driftplug.py").write_text(PLUGIN)
    (site / "driftplug-0.1.dist-info" / "METADATA").write_text("Metadata-Version: 2.1\nName: driftplug\nVersion: 0.1\n")
    (site / "driftplug-0.1.dist-info" / "entry_points.txt").write_text(
        textwrap.dedent("[needlecli.observers]\ndrift = driftplug:Drift\n"))
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(site), str(ROOT)])}
    cfg, out = tmp_path / "drift.yaml", tmp_path / "drift.h5"
    cfg.write_text(PLUGIN_CONFIG % max_trace)
    p = _needle(["simulate", str(cfg), "--out", str(out), "--quiet"], env, tmp_path)
    assert p.returncode == 0, p.stderr
    with h5py.File(out) as f:
        g = f["estimates/mine"]
        state, ol = g["state"][()], f["estimates/ol/state"][()]
        T = state.shape[1]
        assert g["cov"].shape == (3, len(range(0, T, 3)), 6, 6)
        assert_array_equal(g["cov_index"][()], np.arange(0, T, 3))
        assert_array_equal(g["steps"][()], [T] * 3)
        status = g["status"].asstr()[()]
        reason = g["reason"].asstr()[()]
        odd = np.arange(1, T - 1, 2)
        assert_array_equal(state[:, odd], state[:, odd - 1])  # not recorded: held
        if max_trace == "1.0e9":
            assert list(status) == ["ok"] * 3
            assert_array_equal(state[:, ::2], ol[:, ::2])  # the same model from the same start, no noise
        else:  # tr P = 6 (1 + 0.5 t) > 7 first at grid step k: every run holds the estimate of step k - 1
            t = f["time"][()]
            k = int(np.argmax(6 * (1 + 0.5 * t) > 7.0))
            assert list(status) == ["diverged"] * 3
            assert all(r == f"non-finite or exploding estimate at t = {t[k]:.2f} s" for r in reason)
            k2 = k + k % 2  # the first record from then on
            assert_array_equal(state[:, k2:], np.repeat(ol[:, k - 1 : k], T - k2, axis=1))
            assert not np.array_equal(ol[:, -1], ol[:, k - 1])
    p = _needle(["evaluate", str(out), "--out", str(tmp_path / "eval"), "--format", "csv", "--no-plots", "-q"],
                env, tmp_path)
    assert p.returncode == 0, p.stderr
    table = (tmp_path / "eval" / "drift_status.csv").read_text()
    assert ("mine,ok,3/3" if max_trace == "1.0e9" else "mine,diverged,3/3,,non-finite or exploding estimate at "
            "t = 0.34 s") in table, table
