"""EM (the magnetic needle EM paper, Algorithm 1): on a linear-Gaussian model with known Q and R it recovers them within
sampling error and never lowers the log-likelihood; floors hold; the per-run parameter cases of the
config; ``needle fit-em`` end to end (a fit file, its tables, clear errors); the BiNM fit fails with the
singularity as the reason where the field crosses the heading."""

from __future__ import annotations

from pathlib import Path

import h5py
import numpy as np
import pytest
from report_checks import capture_figures, compile_tables, figure_problems, needs_pdflatex
from typer.testing import CliRunner

from needlecli.cli.app import app
from needlecli.errors import ConfigError
from needlecli.experiments.config.load import load_config
from needlecli.experiments.simulation.truth import simulate_truth
from needlecli.fitting.em import EMOptions, fit_em, relative_change
from needlecli.fitting.statespace import DiscreteModel, MeasurementModel
from needlecli.models.base import Model


class Oscillator(Model):
    state_names = ("a", "b")
    state_units = ("1", "1")
    input_names = ("v",)
    input_sizes = {"v": 1}
    input_units = {"v": "1"}
    F = np.array([[-0.5, 1.0], [-1.0, -0.3]])

    def f(self, x, u, p):
        return x @ self.F.T + u[..., :1] * np.array([1.0, 0.0])

    def initial_state(self, p):
        return np.zeros(2)


Q_TRUE = np.array([[0.20, 0.05], [0.05, 0.10]])
R1_TRUE, R2_TRUE = 0.05, 0.08
DT = 0.05


def _linear_data(N=6, T=400, seed=0):
    rng = np.random.default_rng(seed)
    u = np.sin(0.02 * np.arange(T))[None, :, None] * np.ones((N, 1, 1))
    ticks = np.arange(T)
    dm = DiscreteModel(Oscillator(), {}, (), DT, ticks, u, None)
    L = np.linalg.cholesky(Q_TRUE * DT)
    x = np.zeros((N, 2))
    xs = [x]
    for k in range(T - 1):
        x, _ = dm.transition(k, x, with_jacobian=False)
        x = x + rng.standard_normal((N, 2)) @ L.T
        xs.append(x)
    X = np.stack(xs, 1)
    i1, i2 = np.arange(0, T), np.arange(0, T, 2)
    y1 = X[:, i1, :1] + np.sqrt(R1_TRUE) * rng.standard_normal((N, len(i1), 1))
    y2 = X[:, i2, 1:] + np.sqrt(R2_TRUE) * rng.standard_normal((N, len(i2), 1))
    m1 = MeasurementModel("c1", lambda z: z[..., :1], 2, i1, y1, np.ones(y1.shape[:2], bool), np.zeros(1, bool))
    m2 = MeasurementModel("c2", lambda z: z[..., 1:], 2, i2, y2, np.ones(y2.shape[:2], bool), np.zeros(1, bool))
    return dm, [m1, m2]


@pytest.fixture(scope="module")
def linear():
    return _linear_data()


def test_em_recovers_q_and_r_on_a_linear_gaussian_model(linear):
    dm, meas = linear
    N = meas[0].y.shape[0]
    res = fit_em(dm, meas, np.zeros((N, 2)), np.eye(2), np.eye(2) * 0.5, [np.eye(1) * 0.3, np.eye(1) * 0.01],
                 EMOptions(max_iter=40, tol=2e-3))
    assert (res.status == "ok").all(), res.reason
    assert res.ll_decreases.sum() == 0  # never lower along plain EM steps
    # pooled over the runs, the estimates are within sampling error of the truth (about 5 % here)
    np.testing.assert_allclose(res.R[0].mean(0)[0, 0], R1_TRUE, rtol=0.12)
    np.testing.assert_allclose(res.R[1].mean(0)[0, 0], R2_TRUE, rtol=0.15)
    np.testing.assert_allclose(np.diagonal(res.Qc.mean(0)), np.diag(Q_TRUE), rtol=0.2)


def test_plain_em_log_likelihood_never_decreases(linear):
    dm, meas = linear
    i = np.arange(2)
    dm3, meas3 = dm.take(i), [m.take(i) for m in meas]
    res = fit_em(dm3, meas3, np.zeros((2, 2)), np.eye(2), np.eye(2) * 2.0, [np.eye(1) * 1.0, np.eye(1) * 0.01],
                 EMOptions(max_iter=10, tol=1e-9, accelerate=False))
    ll = res.history["loglik"]
    assert np.isfinite(ll).all()
    steps = np.diff(ll, axis=1)
    assert (steps >= -1e-9 * np.abs(ll[:, 1:])).all(), steps.min()
    assert (ll[:, -1] - ll[:, 0] > 10).all()  # and it did climb from the poor guess


def test_floors_and_relative_change(linear):
    dm, meas = linear
    i = np.arange(2)
    res = fit_em(dm.take(i), [m.take(i) for m in meas], np.zeros((2, 2)), np.eye(2), np.eye(2) * 0.2,
                 [np.eye(1) * 0.05, np.eye(1) * 0.08], EMOptions(max_iter=3, r_floor=(0.5, None)))
    assert (res.R[0][:, 0, 0] >= 0.5 - 1e-12).all()
    assert res.floor_hits[0] > 0
    a = np.array([np.diag([1.0, 4.0])])
    assert relative_change(a * 1.01, a)[0] == pytest.approx(np.log(1.01))
    assert relative_change(np.array([np.diag([1.0, 8.0])]), a)[0] == pytest.approx(np.log(2.0))
    assert relative_change(np.full((1, 2, 2), np.nan), a)[0] == np.inf


class TwoWalks(Model):
    """Two independent random walks ``a' = 0``, ``b' = 0``: only ``a`` is measured, ``b`` never is (as the
    noise of a unit vector along itself, which a measured direction does not see)."""

    state_names = ("a", "b")
    state_units = ("1", "1")
    input_names = ("v",)
    input_sizes = {"v": 1}
    input_units = {"v": "1"}

    def f(self, x, u, p):
        return 0.0 * x + 0.0 * u[..., :1]

    def initial_state(self, p):
        return np.zeros(2)


def _two_walks(N=4, T=300, q=0.04, r=0.05, seed=3):
    rng = np.random.default_rng(seed)
    ticks = np.arange(T)
    dm = DiscreteModel(TwoWalks(), {}, (), DT, ticks, np.zeros((N, T, 1)), None)
    x = np.concatenate([np.zeros((N, 1, 2)), np.cumsum(np.sqrt(q * DT) * rng.standard_normal((N, T - 1, 2)), 1)], 1)
    y = x[..., :1] + np.sqrt(r) * rng.standard_normal((N, T, 1))
    mm = MeasurementModel("a", lambda z: z[..., :1], 2, ticks, y, np.ones((N, T), bool), np.zeros(1, bool))
    return dm, [mm]


def test_a_tied_block_takes_the_noise_the_data_see():
    """Fitted free, the variance of the walk no sample sees stays at EM's guess (its M-step returns what it
    was given: the trace with it); tied (``q_isotropic``), it is the seen walk's, which the free fit
    estimates on its own (the independent reference), within EM's tolerance."""
    dm, meas = _two_walks()
    N = meas[0].y.shape[0]
    guess = np.diag([0.3, 0.3])
    args = (dm, meas, np.zeros((N, 2)), np.eye(2) * 1e-6, guess, [np.eye(1) * 0.1])
    free = fit_em(*args, EMOptions(max_iter=200, tol=1e-4))
    tied = fit_em(*args, EMOptions(max_iter=200, tol=1e-4, q_isotropic=((0, 1),)))
    assert (free.status == "ok").all() and (tied.status == "ok").all(), (free.reason, tied.reason)
    np.testing.assert_allclose(free.Qc[:, 1, 1], 0.3, rtol=1e-6)  # never seen: where it started
    np.testing.assert_allclose(tied.Qc[:, 0, 0], tied.Qc[:, 1, 1], rtol=1e-12)
    assert (tied.Qc[:, 0, 1] == 0).all()
    np.testing.assert_allclose(tied.Qc[:, 0, 0], free.Qc[:, 0, 0], rtol=0.02)
    np.testing.assert_allclose(tied.Qc[:, 0, 0].mean(), 0.04, rtol=0.25)  # and near the truth


def test_tied_plain_em_never_lowers_the_likelihood(linear):
    """The tie is the M-step's maximiser under the constraint: plain EM with it still climbs (on a model
    whose states are coupled and whose true Q is not isotropic)."""
    dm, meas = linear
    i = np.arange(2)
    res = fit_em(dm.take(i), [m.take(i) for m in meas], np.zeros((2, 2)), np.eye(2), np.diag([2.0, 0.5]),
                 [np.eye(1) * 1.0, np.eye(1) * 0.01], EMOptions(max_iter=10, tol=1e-9, accelerate=False,
                                                                q_isotropic=((0, 1),)))
    ll = res.history["loglik"]
    assert np.isfinite(ll).all()
    assert (np.diff(ll, axis=1) >= -1e-9 * np.abs(ll[:, 1:])).all()
    np.testing.assert_allclose(res.Qc[:, 0, 0], res.Qc[:, 1, 1], rtol=1e-12)


def test_tie_is_the_constrained_maximiser():
    """``tie_isotropic(S)`` maximises ``-log|Q| - tr(Q^-1 S)`` over ``Q = blockdiag(Q_rest, s I)``: no
    nearby point of that set does better."""
    from needlecli.fitting.em import tie_isotropic

    rng = np.random.default_rng(0)
    A = rng.standard_normal((4, 4))
    S = A @ A.T + 0.5 * np.eye(4)

    def objective(Q):
        return -np.linalg.slogdet(Q)[1] - np.trace(np.linalg.solve(Q, S))

    best = tie_isotropic(S[None], ((1, 3),))[0]
    assert best[1, 1] == pytest.approx((S[1, 1] + S[3, 3]) / 2) and best[1, 0] == 0 and best[1, 3] == 0
    for _ in range(200):
        E = 1e-2 * rng.standard_normal((4, 4))
        Q = tie_isotropic((best + 0.5 * (E + E.T))[None], ((1, 3),))[0]  # a nearby point of the set
        if np.linalg.eigvalsh(Q).min() > 0:
            assert objective(Q) <= objective(best) + 1e-12


# ---------------------------------------------------------------------------------------------- configs
CASES = """\
name: cases
model:
  type: mnm
  params: {c: 9.5}
  initial_state: {hy: -1.0, By: -1.0}
  param_cases: {labels: [low, mid, high], cases: [{c: 5.0}, {c: 9.0}, {c: 12.0}]}
inputs:
  v: 0.002
  omega_B: {kind: cases, labels: [A, B], cases: [[0, 0, 0.01], [0, 0, -0.01]]}
runs: {count: 12, seed: 1}
stop: {time: 1.0}
"""


def test_param_cases_cycle_after_the_input_cases():
    cfg, _ = load_config(text=CASES)
    tr = simulate_truth(cfg)
    assert tr.case.tolist() == [0, 1] * 6
    assert tr.param_case.tolist() == [0, 0, 1, 1, 2, 2] * 2  # every (input, parameter) pair per 6 runs
    np.testing.assert_array_equal(tr.params["c"][:, 0], np.array([5.0, 5.0, 9.0, 9.0, 12.0, 12.0] * 2))
    assert tr.param_case_labels == ["low", "mid", "high"]


@pytest.mark.parametrize("edit, where, text", [
    ("cases: [{c: 5.0}, {kappa: 1.0}, {c: 12.0}]", "model -> param_cases", "case 1: unknown parameter 'kappa'"),
    ("cases: [{c: 5.0}, {c: -1.0}, {c: 12.0}]", "model -> param_cases", "case 1: c:"),
    ("labels: [low], cases", "model -> param_cases", "labels has 1 entries for 3 cases"),
])
def test_param_cases_are_validated(edit, where, text):
    bad = CASES.replace("cases: [{c: 5.0}, {c: 9.0}, {c: 12.0}]", edit) if "labels" not in edit else \
        CASES.replace("labels: [low, mid, high], cases", edit)
    with pytest.raises(ConfigError) as e:
        load_config(text=bad)
    assert where in str(e.value) and text in str(e.value)


# ---------------------------------------------------------------------------------------------- CLI
FIT = """\
name: tiny_fit
model:
  type: mnm
  params: {c: 9.5}
  initial_state: {hy: -1.0, By: -1.0}
  param_cases: {labels: [a, b], cases: [{c: 6.0}, {c: 11.0}]}
inputs:
  v: 0.002
  omega_B: {kind: cases, labels: [T2 +x, T2 -x], cases: [[0, 0, 0.05], [0, 0, -0.05]]}
process_noise: {std: {px: 1.0e-5, py: 1.0e-5, hx: 2.0e-3, hy: 2.0e-3, Bx: 1.0e-4, By: 1.0e-4}}
sensors:
  - {name: camera, type: position, rate: 6.0, axes: [x, y], sigma: 5.2e-5}
  - {name: coils, type: bfield, rate: 6.0, sigma: 1.0e-4}
runs: {count: 4, seed: 9}
stop: {time: 4.0}
fit:
  q: {px: 3.0e-5, py: 3.0e-5, hx: 5.0e-3, hy: 5.0e-3, Bx: 3.0e-4, By: 3.0e-4}
  p0: {px: 1.0e-6, py: 1.0e-6, pz: 1.0e-8, hx: 1.0e-2, hy: 1.0e-6, hz: 1.0e-4, Bx: 1.0e-6, By: 1.0e-6, Bz: 1.0e-6, c: 100.0, l_inv: 100.0}
  measurements: {camera: {sigma: 1.0e-4, floor: 2.5e-9}, coils: {sigma: 3.0e-4}}
  init:
    values: {hx: 0.0, hy: -1.0, c: 8.0, l_inv: 8.0}
    first_measurement: {px: camera.x, py: camera.y, Bx: coils.bx, By: coils.by, Bz: coils.bz}
  em: {max_iter: 4}
  repeats: 3
"""


def invoke(*args):
    return CliRunner().invoke(app, [str(a) for a in args])


@pytest.fixture(scope="module")
def fitted(tmp_path_factory):
    d = tmp_path_factory.mktemp("fit")
    (d / "tiny.yaml").write_text(FIT)
    out = d / "tiny_fit.h5"
    r = invoke("fit-em", d / "tiny.yaml", "--model", "both", "--out", out, "--quiet")
    assert r.exit_code == 0, r.output + repr(r.exception)
    return d, out


def test_fit_em_writes_the_fit_file(fitted):
    d, out = fitted
    with h5py.File(out) as f:
        assert f.attrs["format"] == "needlecli-fit" and int(f.attrs["version"]) == 1
        assert set(f["fit"]) == {"mnm", "binm"} and list(f.attrs["models"]) == ["mnm", "binm"]
        for m, c in (("mnm", "c"), ("binm", "l_inv")):
            g = f[f"fit/{m}"]
            assert g[f"constant/{c}"].shape == (4,)
            assert g["Q"].shape == (4, 10, 10) and g["R/camera"].shape == (4, 2, 2)
            assert g["R/coils"].shape == (4, 2, 2)  # a measured direction: across it
            assert g["state"].shape[0] == 4 and g["state"].shape[2] == 10
            assert g["history/loglik"].shape == (4, 4)
            assert set(g["status"][()].astype(str)) <= {"ok", "max_iter"}
            assert (np.linalg.eigvalsh(g["R/camera"][()]) >= 2.5e-9 - 1e-18).all()
        assert f["truth/param_case"][()].tolist() == [0, 0, 1, 1]


def test_evaluate_reads_the_fit_file(fitted):
    d, out = fitted
    r = invoke("evaluate", out, "--out", d / "tables")
    assert r.exit_code == 0, r.output + repr(r.exception)
    for t in ("fit_parameters", "mnm_parameters", "binm_parameters", "binm_vs_mnm", "fit_recovery", "fit_status"):
        assert (d / "tables" / f"tiny_fit_{t}.csv").exists()
        assert f"## {t}" in r.output
    assert "c @ a" in r.output and "SD as Traj. Err. (mm)" in r.output
    assert (d / "tables" / "tiny_fit_fit_paths.png").exists()
    r = invoke("evaluate", out, "--tables", "summary", "--no-plots")
    assert r.exit_code == 2 and "needs a results file" in r.output


def test_fit_em_user_errors(tmp_path, fitted):
    d, out = fitted
    junk = tmp_path / "notes.txt"
    junk.write_text("x")
    r = invoke("fit-em", junk)
    assert r.exit_code == 2 and "not an experiment config" in r.output and "Traceback" not in r.output
    r = invoke("fit-em", out)
    assert r.exit_code == 2 and "is a fit file already" in r.output
    logfile = Path(__file__).resolve().parents[1] / "datasets" / "em-magnetic-pratt2022_like.h5"
    if logfile.exists():
        r = invoke("fit-em", logfile)
        assert r.exit_code == 2 and "is a log file" in r.output and "source" in r.output
    r = invoke("fit-em", d / "tiny.yaml", "--model", "bicycle")
    assert r.exit_code == 2 and "--model" in r.output
    r = invoke("fit-em", d / "tiny.yaml", d / "tiny.yaml", "--out", tmp_path / "x.h5")
    assert r.exit_code == 2 and "--out" in r.output
    bad = FIT.replace("hx: 0.0, hy: -1.0, c: 8.0", "hx: 0.0, hy: -1.0, kappa: 8.0")
    (tmp_path / "bad.yaml").write_text(bad)
    r = invoke("fit-em", tmp_path / "bad.yaml")
    assert r.exit_code == 2 and "[fit -> init -> values -> kappa]" in r.output
    for tie, what in (("[h, q]", "[fit -> isotropic -> 1] no fitted model (mnm, binm) has a block 'q'"),
                      ("[h]\n  hold: [hx]", "[fit -> isotropic -> 0] block 'h' has held states (hx)")):
        (tmp_path / "bad.yaml").write_text(FIT.replace("  em: {max_iter: 4}", f"  isotropic: {tie}\n  em: {{max_iter: 4}}"))
        r = invoke("fit-em", tmp_path / "bad.yaml")
        assert r.exit_code == 2 and what in r.output, r.output


SINGULAR = """\
name: tiny_t2prelim
model: {type: mnm, params: {c: 9.5}, initial_state: {hy: -1.0, By: -1.0}}
inputs:
  v: 0.002
  omega_B: {kind: piecewise, times: [0.0, 1.0], values: [[0, 0, 1.4], [0, 0, 0.15]]}
process_noise: {std: {px: 1.0e-5, py: 1.0e-5, hx: 2.0e-3, hy: 2.0e-3, Bx: 1.0e-4, By: 1.0e-4}}
sensors:
  - {name: camera, type: position, rate: 6.0, axes: [x, y], sigma: 5.2e-5}
  - {name: coils, type: bfield, rate: 6.0, sigma: 1.0e-4}
runs: {count: 2, seed: 5}
stop: {time: 4.0}
fit:
  models: [binm]
  q: {px: 3.0e-5, py: 3.0e-5, hx: 5.0e-3, hy: 5.0e-3, Bx: 3.0e-4, By: 3.0e-4}
  p0: {px: 1.0e-6, py: 1.0e-6, pz: 1.0e-8, hx: 1.0e-2, hy: 1.0e-6, hz: 1.0e-4, Bx: 1.0e-6, By: 1.0e-6, Bz: 1.0e-6, l_inv: 100.0}
  measurements: {camera: {sigma: 1.0e-4}, coils: {sigma: 3.0e-4}}
  init: {values: {hx: 0.0, hy: -1.0, l_inv: 8.0}, first_measurement: {px: camera.x, py: camera.y, Bx: coils.bx, By: coils.by, Bz: coils.bz}}
  em: {max_iter: 3}
"""


def test_binm_fit_fails_at_its_singularity(tmp_path):
    from needlecli.experiments.studies.fit import fit_trials, load_trials

    (tmp_path / "s.yaml").write_text(SINGULAR)
    trials = load_trials(tmp_path / "s.yaml")
    h, b = trials.truth.states[..., 3:6], trials.truth.states[..., 6:9]
    assert ((h * b).sum(-1) < 0).any(1).all()  # the MNM truth crosses h . B = 0
    res = fit_trials(trials, workers=1).fits["binm"].result
    assert (res.status == "singular").all(), res.reason
    assert all("B . h -> 0" in r for r in res.reason)


def test_fit_em_needs_a_fit_section(tmp_path):
    (tmp_path / "nofit.yaml").write_text(FIT.split("fit:\n")[0])
    r = invoke("fit-em", tmp_path / "nofit.yaml", "--quiet")
    assert r.exit_code == 2 and "[fit] required key is missing" in r.output
    (tmp_path / "noq.yaml").write_text(FIT.replace("  q: {px: 3.0e-5, py: 3.0e-5, hx: 5.0e-3, hy: 5.0e-3, Bx: 3.0e-4, By: 3.0e-4}\n", ""))
    r = invoke("fit-em", tmp_path / "noq.yaml", "--quiet")
    assert r.exit_code == 2 and "[fit -> q] required key is missing" in r.output


def test_evaluate_writes_the_em_tables_of_a_fit_file(fitted):
    """Issue 15: the tables documented for fit files are reachable from the command line."""
    d, out = fitted
    r = invoke("evaluate", out, "--out", d / "em", "--tables", "em_per_trial,em_per_speed,em_loglik", "--no-plots")
    assert r.exit_code == 0, r.output + repr(r.exception)
    for t in ("em_per_trial", "em_per_speed", "em_loglik"):
        assert (d / "em" / f"tiny_fit_{t}.tex").exists() and f"## {t}" in r.output
    per_trial = (d / "em" / "tiny_fit_em_per_trial.csv").read_text().splitlines()
    assert len(per_trial) == 1 + 2 * 4  # two models x four trials


@needs_pdflatex
def test_fit_tables_compile(fitted, tmp_path):
    from needlecli.reports.evaluate import evaluate_results
    from needlecli.reports.seed004 import ALL_FIT_TABLES

    d, out = fitted
    evaluate_results(out, tables=list(ALL_FIT_TABLES), out_dir=tmp_path / "t", formats=["tex"])
    compile_tables(sorted((tmp_path / "t").glob("*.tex")), tmp_path)


def test_fit_figures_hold_data_in_one_colour_per_model(fitted, tmp_path, monkeypatch):
    from needlecli.io.fit import read_fit
    from needlecli.reports.plots import draw_plots, observer_colour, observer_colours
    from needlecli.reports.seed004 import FIT_PLOTS

    d, out = fitted
    figs = capture_figures(monkeypatch, render=False)
    res = read_fit(out)
    written = draw_plots(res, None, tmp_path / "p", FIT_PLOTS)
    assert len(written) == 2 and len(figs) == 2
    colours = observer_colours(res)
    assert colours == {"binm": observer_colour("binm"), "mnm": observer_colour("mnm")}  # by name, not file order
    assert colours["binm"] != colours["mnm"]
    problems = [p for fig in figs for p in figure_problems(fig, colours)]
    assert not problems, "\n".join(problems)
    title = figs[1].axes[0].get_title()
    assert "through" not in title and ("closest" in title or "reached the singularity" in title)
