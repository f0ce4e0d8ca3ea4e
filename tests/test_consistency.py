"""Consistency statistics (issue 15, item 4): NEES against a hand computation on a linear model, NIS
against an independent Kalman filter, the chi-square intervals, the verdicts, wrapped angles, and
the multi-rate UKF paper's UKF whose alpha and beta are optimistic over the first seconds (P0 below the 5 deg initial error)."""

from __future__ import annotations

from pathlib import Path

import h5py
import linear_model  # noqa: F401  (registers the linear test model)
import numpy as np
import pytest
from linear_model import linear_system, rk4_transition
from scipy.stats import chi2
from typer.testing import CliRunner

from needlecli.cli.app import app
from needlecli.experiments.config.load import load_config
from needlecli.experiments.simulation.runner import run_experiment
from needlecli.io.results import Group, read_results
from needlecli.reports.consistency import chi2_bounds, consistency_table, lasting_spans, nees, verdict
from needlecli.reports.evaluate import evaluate_results

ROOT = Path(__file__).resolve().parents[1]
LINEAR = """\
name: lin
model: {type: linear_test_model}
inputs: {v: 1.0, a: [0.3, -0.2, 0.1]}
process_noise: {std: {x: 0.1, y: 0.1, z: 0.1, vx: 0.5, vy: 0.5, vz: 0.5}}
sensors: [{name: pos, type: position, rate: 10, sigma: 0.3}]
observers:
  - name: kf
    type: ukf
    alpha: 1.0
    q: {x: 0.01, y: 0.01, z: 0.01, vx: 0.05, vy: 0.05, vz: 0.05}   # the truth's noise per 10 ms tick
    p0: {x: 0.04, y: 0.04, z: 0.04, vx: 0.25, vy: 0.25, vz: 0.25}
    measurements: {pos: {sigma: 0.3}}
    init: {from: truth, std: {x: 0.2, y: 0.2, z: 0.2, vx: 0.5, vy: 0.5, vz: 0.5}}
  - name: model_only
    type: open_loop
    init: {from: truth, std: {x: 0.2, y: 0.2, z: 0.2, vx: 0.5, vy: 0.5, vz: 0.5}}
    q: {x: 0.1, y: 0.1, z: 0.1, vx: 0.5, vy: 0.5, vz: 0.5}
runs: {count: 200, seed: 1}
stop: {time: 3.0}
simulation: {dt: 0.01}
output: {store_every: 5}
"""
STATES = ("x", "y", "z", "vx", "vy", "vz")


def _run(tmp: Path, name: str, overrides=()) -> Path:
    cfg, text = load_config(text=LINEAR, overrides=list(overrides))
    return run_experiment(cfg, text, out=tmp / f"{name}.h5").path


@pytest.fixture(scope="module")
def linear(tmp_path_factory) -> Path:
    """A UKF that is the Kalman filter of the model (alpha = 1, the truth's Q and R, P0 the spread of
    its start): consistent by construction; and the model alone with the EKF prediction's covariance."""
    return _run(tmp_path_factory.mktemp("lin"), "lin")


def _row(df, obs, test, of):
    sel = df[(df["Observer"] == obs) & (df["Test"] == test) & (df["Of"].str.startswith(of))]
    assert len(sel) == 1, (obs, test, of, df[["Observer", "Test", "Of"]])
    return sel.iloc[0]


def test_nees_equals_a_hand_computation(linear):
    """e^T P^-1 e of every run at every stored covariance after the first, by a plain loop."""
    with h5py.File(linear) as f:
        x = f["estimates/kf/state"][()]
        P = f["estimates/kf/cov"][()]
        idx = f["estimates/kf/cov_index"][()]
        truth = f["truth/state"][()]
    hand = np.empty((x.shape[0], len(idx) - 1))
    for r in range(x.shape[0]):
        for j, k in enumerate(idx[1:]):
            e = x[r, k] - truth[r, k]
            hand[r, j] = e @ np.linalg.inv(P[r, j + 1]) @ e
    df = consistency_table(read_results(linear))
    row = _row(df, "kf", "ANEES", "all states")
    assert row["Dof"] == 6 and row["Runs"] == "200/200"
    np.testing.assert_allclose(row["Mean"], hand.mean(), rtol=1e-10)
    np.testing.assert_allclose(nees(read_results(linear), "kf")[0].values, hand, rtol=1e-8)
    for i, s in enumerate(STATES):  # per state: e_i^2 / P_ii
        e = x[:, idx[1:], i] - truth[:, idx[1:], i]
        np.testing.assert_allclose(_row(df, "kf", "ANEES", s)["Mean"], np.mean(e**2 / P[:, 1:, i, i]), rtol=1e-10)
    lo, hi = chi2.ppf([0.025, 0.975], 200 * 6) / 200
    np.testing.assert_allclose([row["95% low"], row["95% high"]], [lo, hi])
    assert lo < row["Mean"] < hi and row["Verdict"] == "consistent"


def test_nis_equals_an_independent_kalman_filter(linear):
    """The NIS the UKF recorded for each sample equals nu^T S^-1 nu of a Kalman filter written here from
    the model's matrices (same start, same schedule: a sample at t is used at the tick of t)."""
    res = read_results(linear)
    g = res.data["estimates"].data["kf"]
    m = res.data["measurements"].data["pos"]
    time = res.data["time"]
    A, B = linear_system(0.4, 0.7)
    phi, gam = rk4_transition(A, B, time[1] - time[0])
    u = np.concatenate([res.data["inputs"].data["v"][..., None], res.data["inputs"].data["a"]], -1)
    Q = np.diag(np.array([0.01] * 3 + [0.05] * 3) ** 2)
    R = 0.3**2 * np.eye(3)
    H = np.eye(6)[:3]
    x = g.data["state"][:, 0].copy()
    P = np.broadcast_to(g.data["cov"][:, 0], (x.shape[0], 6, 6)).copy()
    at = {int(k): j for j, k in enumerate(m.data["index"])}
    nis = np.full(m.data["valid"].shape, np.nan)
    for k in range(len(time) - 1):
        x = x @ phi.T + u[:, k] @ gam.T
        P = phi @ P @ phi.T + Q
        j = at.get(k + 1)
        if j is None:
            continue
        nu = m.data["value"][:, j] - x @ H.T
        S = H @ P @ H.T + R
        nis[:, j] = np.einsum("ni,ni->n", nu, np.linalg.solve(S, nu[..., None])[..., 0])
        K = P @ H.T @ np.linalg.inv(S)
        x = x + np.einsum("nij,nj->ni", K, nu)
        P = P - K @ S @ np.swapaxes(K, -1, -2)
    np.testing.assert_allclose(g.data["nis"].data["pos"], nis, rtol=1e-8, atol=1e-12)
    assert np.isnan(nis[:, 0]).all()  # the sample at t = 0 serves the initialisation
    df = consistency_table(res)
    np.testing.assert_allclose(_row(df, "kf", "ANIS", "pos")["Mean"], np.nanmean(nis), rtol=1e-12)


def test_verdicts_follow_the_covariance(linear, tmp_path):
    df = consistency_table(read_results(linear))
    assert _row(df, "kf", "ANIS", "pos")["Verdict"] == "consistent"
    assert not (df["Observer"] == "model_only").any() or (df[(df["Observer"] == "model_only")]["Test"] == "ANEES").all()
    # R four times too small: the filter believes its measurements and itself too much
    opt = consistency_table(read_results(_run(tmp_path, "opt", ["runs.count=100", "observers.0.measurements.pos.sigma=0.15"])))
    assert _row(opt, "kf", "ANIS", "pos")["Verdict"] == "optimistic"
    assert _row(opt, "kf", "ANEES", "all states")["Verdict"] == "optimistic"
    # P0 and Q ten times too large in std: it believes itself far too little
    big = {f"observers.0.q.{s}": v for s, v in zip(STATES, [0.1] * 3 + [0.5] * 3)}
    big.update({f"observers.0.p0.{s}": v for s, v in zip(STATES, [4.0] * 3 + [25.0] * 3)})
    pes = consistency_table(read_results(_run(tmp_path, "pes", ["runs.count=100"] + [f"{k}={v}" for k, v in big.items()])))
    assert _row(pes, "kf", "ANEES", "all states")["Verdict"] == "pessimistic"
    assert _row(pes, "kf", "ANIS", "pos")["Verdict"] == "pessimistic"


def test_interval_and_verdict():
    lo, hi = chi2_bounds(1, 1)
    np.testing.assert_allclose([lo, hi], [chi2.ppf(0.025, 1), chi2.ppf(0.975, 1)])
    lo, hi = chi2_bounds(np.array([0, 50]), 3)
    assert np.isnan(lo[0]) and np.isclose(hi[1], chi2.ppf(0.975, 150) / 50)
    assert [verdict(v, 0.8, 1.2) for v in (1.0, 1.3, 0.7, np.nan)] == ["consistent", "optimistic", "pessimistic", "n/a"]
    t = np.arange(0, 20, 0.1)
    flag = (t < 5.0) | (np.arange(len(t)) % 37 == 0)  # a lasting span and scattered single times
    assert lasting_spans(t, flag) == "0.0-4.9"


def test_angles_are_wrapped():
    """An estimate at pi - 0.01 of a truth at -pi + 0.01 is 0.02 rad off, not 2 pi - 0.02."""
    T = 3
    truth = Group(data={"state": np.full((1, T, 1), -np.pi + 0.01), "status": np.array(["ok"])},
                  attrs={"names": ["alpha"], "units": ["rad"], "angles": ["alpha"]})
    est = Group(data={"state": np.full((1, T, 1), np.pi - 0.01), "cov": np.full((1, T, 1, 1), 0.02**2),
                      "cov_index": np.arange(T), "status": np.array(["ok"])},
                attrs={"names": ["alpha"], "units": ["rad"], "angles": ["alpha"]})
    res = Group(data={"time": np.arange(T) * 0.1, "depth": np.arange(T) * 1.0, "truth": truth,
                      "estimates": Group(data={"f": est})}, attrs={"source": "simulation"})
    np.testing.assert_allclose(nees(res, "f")[0].values, 1.0)


def test_cli_table_and_observers_without_a_covariance(linear, tmp_path):
    r = CliRunner().invoke(app, ["evaluate", str(linear), "--tables", "consistency", "--out", str(tmp_path), "--no-plots"])
    assert r.exit_code == 0, r.output
    assert "## consistency" in r.output and "two-sided 95 % chi-square" in r.output
    text = (tmp_path / "lin_consistency.md").read_text()
    assert "Innovations not recorded (no ANIS): model_only." in text
    cfg, raw = load_config(ROOT / "configs/highgain-us2d/simulation.yaml", overrides=["runs.count=2", "stop.depth=5"])
    out = run_experiment(cfg, raw, out=tmp_path / "hg.h5").path
    df = evaluate_results(out, tables=["consistency"])["consistency"]
    assert df.empty and "Without a covariance (not tabulated): high_gain" in df.attrs["note"]


def test_seed003_alpha_and_beta_are_optimistic_over_the_first_seconds(tmp_path):
    """configs/multirate-ukf-us3d/table1.yaml: P0 of alpha and beta (5e-3 rad^2, 4.1 deg std) is below the 5 deg
    initial error, so their NEES stays above the interval for the first seconds, then settles."""
    cfg, raw = load_config(ROOT / "configs/multirate-ukf-us3d/table1.yaml", overrides=["stop.depth=12", "observers.0.predict_at_depths=[]"])
    out = run_experiment(cfg, raw, out=tmp_path / "t1.h5").path
    df = evaluate_results(out, tables=["consistency"])["consistency"]
    for s in ("alpha", "beta"):
        row = _row(df, "ukf", "ANEES", s)
        start, end = (float(v) for v in row["Optimistic over [s]"].split(",")[0].split("-"))
        assert start <= 0.2 and end >= 3.0, row["Optimistic over [s]"]
    assert _row(df, "ukf", "ANEES", "z")["Optimistic over [s]"] == ""
