"""The pieces of the EM-tuned filter on the real recording (issue 17, item 3), against references derived
independently: needle-frame coordinates (closed forms), EM's R along and across the needle and a
sensor's offset along it recovered from synthetic data whose noise is known, robust (Student-t) weights
against outliers, held parameters, from_fit into a fit section and into a UKF in needle coordinates,
one common start for several observers, and the along/across error table and plot."""

from __future__ import annotations

import dataclasses

import h5py
import numpy as np
import pytest
import yaml
from typer.testing import CliRunner

from needlecli.cli.app import app
from needlecli.errors import ConfigError
from needlecli.experiments.config.load import load_config
from needlecli.fitting.em import EMOptions, fit_em, hold_rows
from needlecli.fitting.robust import fit_em_robust, sample_weights
from needlecli.fitting.statespace import DiscreteModel, MeasurementModel
from needlecli.models import MODELS
from needlecli.numerics.needle_frame import block_noise, needle_basis, reference_axis, to_needle, world_covariance

# ---------------------------------------------------------------------------------------------- frames


def test_needle_basis_is_orthonormal_with_the_tangent_first():
    rng = np.random.default_rng(1)
    t = rng.standard_normal((50, 3))
    F = needle_basis(t, 0)
    np.testing.assert_allclose(np.swapaxes(F, -1, -2) @ F, np.broadcast_to(np.eye(3), (50, 3, 3)), atol=1e-12)
    np.testing.assert_allclose(F[..., 0], t / np.linalg.norm(t, axis=-1, keepdims=True), atol=1e-12)
    np.testing.assert_allclose(F[..., 1, 0] * 0 + F[..., 0, 1], 0.0, atol=1e-12)  # e1 = x cross t: no x component
    np.testing.assert_allclose(np.linalg.det(F), 1.0, atol=1e-12)  # right-handed
    # along +z with reference x: e1 = -y, e2 = x (the module docstring)
    np.testing.assert_allclose(needle_basis(np.array([0.0, 0.0, 2.0]), 0), [[0, 0, 1], [0, -1, 0], [1, 0, 0]], atol=1e-12)
    assert reference_axis(np.array([[0.1, 0.9, 0.4], [0.05, 0.95, 0.3]])) == 0


def test_world_covariance_and_components_round_trip():
    rng = np.random.default_rng(2)
    F = needle_basis(rng.standard_normal((20, 3)), 1)
    var = np.array([9.0, 0.5, 0.2])
    R = world_covariance(F, var)
    np.testing.assert_allclose(np.swapaxes(F, -1, -2) @ R @ F, np.broadcast_to(np.diag(var), (20, 3, 3)), atol=1e-12)
    v = rng.standard_normal((20, 3))
    np.testing.assert_allclose(np.einsum("nij,nj->ni", F, to_needle(F, v)), v, atol=1e-12)
    np.testing.assert_allclose(world_covariance(F, np.full(3, 2.0)), np.broadcast_to(2.0 * np.eye(3), (20, 3, 3)), atol=1e-12)
    B = block_noise([np.full((2, 2), 4.0), np.ones((2, 3, 3))])
    np.testing.assert_allclose(B[0], [[4, 0, 0, 0, 0], [0, 4, 0, 0, 0], [0, 0, 1, 1, 1], [0, 0, 1, 1, 1], [0, 0, 1, 1, 1]])


def test_hold_rows_keeps_the_guess_and_zeroes_its_covariances():
    Q = np.arange(16.0).reshape(1, 4, 4) + np.arange(16.0).reshape(1, 4, 4).transpose(0, 2, 1)
    Q0 = np.diag([1.0, 2.0, 3.0, 4.0])[None]
    H = hold_rows(Q, Q0, (1, 3))
    assert H[0, 1, 1] == 2.0 and H[0, 3, 3] == 4.0 and H[0, 1, 3] == 0.0
    assert (H[0, 1, [0, 2]] == 0).all() and (H[0, [0, 2], 3] == 0).all()
    np.testing.assert_array_equal(H[0][np.ix_([0, 2], [0, 2])], Q[0][np.ix_([0, 2], [0, 2])])


# ---------------------------------------------------------------------------------------------- synthetic data
def _synthetic(sig_needle, *, N=4, T=120.0, rate=4.0, kappa=0.012, outliers=0.0, ou=None, seed=3):
    """Unicycle insertions at 1 mm/s (no process noise) measured at ``rate`` as ``p + o t + F diag(sig) e``
    (F the needle basis at the true tangent, reference axis x; ``o`` an Ornstein-Uhlenbeck offset
    ``(tau, sigma)`` or none); ``outliers``: that fraction of samples 12 mm off across the needle."""
    rng = np.random.default_rng(seed)
    model = MODELS.get("unicycle")(MODELS.get("unicycle").Params(kappa=kappa))
    dt = 1.0 / rate
    K = int(T * rate)
    x = np.zeros((N, 6))
    x[:, 5] = rng.uniform(-np.pi, np.pi, N)  # bending in any direction
    states = [x]
    u = np.zeros((N, 2))
    u[:, 0] = 1.0
    for _ in range(K):
        for _ in range(5):
            x = model.step(x, u, model.param_arrays(), dt / 5)
        states.append(x)
    truth = np.stack(states, 1)  # (N, K+1, 6)
    F = needle_basis(model.tangent(truth), 0)
    e = rng.standard_normal(truth.shape[:2] + (3,)) * np.asarray(sig_needle)
    y = truth[..., :3] + np.einsum("nkij,nkj->nki", F, e)
    if ou is not None:
        tau, so = ou
        phi = np.exp(-dt / tau)
        o = np.zeros(truth.shape[:2])
        o[:, 0] = so * rng.standard_normal(N)
        for k in range(1, K + 1):
            o[:, k] = phi * o[:, k - 1] + so * np.sqrt(1 - phi**2) * rng.standard_normal(N)
        y = y + o[..., None] * F[..., 0]
    bad = rng.random(truth.shape[:2]) < outliers
    y = y + bad[..., None] * 12.0 * F[..., 1]
    inputs = np.zeros((N, K + 1, 2))
    inputs[..., 0] = 1.0
    ticks = np.arange(K + 1)
    return model, truth, y, bad, inputs, ticks, dt


def _system(model, y, inputs, ticks, dt, *, offset=None, kappa=0.012, frame="needle"):
    sensor_states = [("us_offset", "mm", 1.0 / offset)] if offset is not None else []
    dm = DiscreteModel(model, {"kappa": np.asarray(kappa)}, (), dt, ticks, inputs, substeps=2,
                       sensor_states=sensor_states)
    N, M = y.shape[:2]
    mm = MeasurementModel("us", lambda x: x[..., :3], model.n, np.arange(M), y, np.ones((N, M), dtype=bool),
                          np.zeros(3, dtype=bool), ("x", "y", "z"), ("mm",) * 3, False, frame=frame, tangent_fn=model.tangent, frame_axis=0,
                          offset_index=dm.names.index("us_offset") if offset is not None else None)
    return dm, mm


def _start(model, y, truth, dm):
    m0 = np.zeros((y.shape[0], dm.n))
    m0[:, :3] = y[:, 0]
    m0[:, 3:6] = truth[:, 0, 3:6]
    P0 = np.diag([9.0, 9.0, 9.0, 1e-3, 1e-3, 1e-2] + [9.0] * (dm.n - 6))
    return m0, P0


def _held_q(dm, extra=()):
    q = np.diag([0.0, 0.0, 0.0, 1e-6, 1e-6, 1e-6] + list(extra))
    idx = tuple(range(3, 6)) + tuple(range(6, 6 + len(extra)))
    return q, EMOptions(max_iter=80, tol=1e-3, estep_max=1, q_index=idx, q_hold=(3, 4, 5))


def test_em_fits_r_along_and_across_the_needle():
    """The noise drawn in the needle's frame is what EM's R in needle coordinates recovers (6 % of its
    variance: about 2 standard errors of 1900 samples), and it is not isotropic."""
    sig = np.array([3.0, 0.6, 0.3])
    model, truth, y, _, inputs, ticks, dt = _synthetic(sig)
    dm, mm = _system(model, y, inputs, ticks, dt)
    m0, P0 = _start(model, y, truth, dm)
    Q0, opts = _held_q(dm)
    res = fit_em(dm, [mm], m0, P0, Q0, [np.eye(3)], opts)
    assert (res.status == "ok").all()
    R = np.mean(res.R[0], axis=0)
    np.testing.assert_allclose(np.diag(R), sig**2, rtol=0.08)
    assert abs(R[0, 1]) < 0.1 * sig[0] * sig[1]
    # the held process noise stayed at its guess
    np.testing.assert_allclose(res.Qc[:, 3:6, 3:6], np.broadcast_to(Q0[3:6, 3:6], (4, 3, 3)), rtol=1e-12, atol=1e-20)


def test_em_fits_the_offset_of_the_image_plane_along_the_needle():
    """An Ornstein-Uhlenbeck offset along the tangent (tau 5 s, 2.5 mm) under white noise: the sensor
    state's fitted process noise gives its stationary std within 35 % (25 correlation times of data)."""
    sig = np.array([0.3, 0.5, 0.5])
    model, truth, y, _, inputs, ticks, dt = _synthetic(sig, ou=(5.0, 2.5), T=150.0, N=4)
    dm, mm = _system(model, y, inputs, ticks, dt, offset=5.0)
    assert dm.names[-1] == "us_offset" and dm.decay[0] == pytest.approx(0.2)
    m0, P0 = _start(model, y, truth, dm)
    Q0, opts = _held_q(dm, extra=(2 * 1.0**2 / 5.0,))
    opts = dataclasses.replace(opts, q_index=(3, 4, 5, 6), max_iter=150)
    res = fit_em(dm, [mm], m0, P0, Q0, [np.eye(3)], opts)
    sigma_o = np.sqrt(np.median(res.Qc[:, 6, 6]) * 5.0 / 2.0)
    assert 2.5 / 1.35 < sigma_o < 2.5 * 1.35
    # across the needle the offset does not reach: R there is the white noise's
    np.testing.assert_allclose(np.sqrt(np.median(res.R[0][:, [1, 2], [1, 2]], axis=0)), sig[1:], rtol=0.15)


def test_student_t_weights_resist_outliers():
    """8 % of the samples 12 mm off across the needle: Gaussian EM's R across grows fiftyfold; with
    Student-t weights (4 degrees of freedom) the outliers get weights near 0.03 and R across stays within
    a few times the clean noise (each far outlier still adds about (nu + m) w / M of R: 0.08 x 7 here), the
    clean direction along the needle below its Gaussian variance (a t scale on Gaussian data)."""
    sig = np.array([2.0, 0.5, 0.5])
    model, truth, y, bad, inputs, ticks, dt = _synthetic(sig, outliers=0.08, N=2, T=60.0)
    dm, mm = _system(model, y, inputs, ticks, dt)
    m0, P0 = _start(model, y, truth, dm)
    Q0, opts = _held_q(dm)
    gauss = fit_em(dm, [mm], m0, P0, Q0, [np.eye(3)], opts)
    assert np.median(gauss.R[0][:, 1, 1]) > 10 * sig[1] ** 2
    res, info, meas = fit_em_robust(dm, [mm], m0, P0, Q0, [np.eye(3)], dataclasses.replace(opts, tol=1e-2), [4.0],
                                    max_passes=60, tol=0.05)
    r_across = np.median(res.R[0][:, 1, 1])
    assert 0.5 * sig[1] ** 2 < r_across < 4.0 * sig[1] ** 2 and r_across < 0.1 * np.median(gauss.R[0][:, 1, 1])
    assert 0.6 * sig[0] ** 2 < np.median(res.R[0][:, 0, 0]) < sig[0] ** 2
    w = info.weights[0]
    assert np.median(w[bad]) < 0.1 < 0.8 < np.median(w[~bad])
    assert (info.passes > 1).all() and meas[0].weight is info.weights[0]
    # the weights are the closed-form E-step at the final fit
    again = sample_weights(mm, res.m, res.P, res.R[0], 4.0)
    assert np.abs(again - w).max() < 0.05


def test_weights_scale_the_noise_of_a_sample():
    """A sample of weight w is a measurement with noise R / w: scaling y, h and H by sqrt(w) (the filter's
    update with the scaled sample equals the update with R / w)."""
    model, truth, y, _, inputs, ticks, dt = _synthetic(np.array([1.0, 1.0, 1.0]), N=1, T=5.0)
    dm, mm = _system(model, y, inputs, ticks, dt, frame="world")
    z = truth[:, :, :]
    w = np.full(mm.valid.shape, 0.25)
    _, H1, d1, y1 = dataclasses.replace(mm, weight=w).linearise(z)
    _, H0, d0, y0 = mm.linearise(z)
    np.testing.assert_allclose(H1, 0.5 * H0)
    np.testing.assert_allclose(y1 - (H1 @ z[..., None])[..., 0] - d1, 0.5 * (y0 - (H0 @ z[..., None])[..., 0] - d0))


# ---------------------------------------------------------------------------------------------- configs end to end
def _sim_config(observers, fit=None, runs=3, extra_runs=None):
    data = {
        "name": "realem_test",
        "model": {"type": "unicycle", "params": {"kappa": 0.012}},
        "inputs": {"v": 1.0, "u": 0.0},
        "process_noise": {"std": {"alpha": 1e-3, "beta": 1e-3}},
        "stop": {"time": 40.0},
        "sensors": [{"name": "us", "type": "position", "rate": 4.0, "sigma": 0.8}],
        "observers": observers,
        "runs": {"count": runs, "seed": 5, **(extra_runs or {})},
        "simulation": {"dt": 0.05},
        "output": {"store_every": 1, "covariance": "none"},
    }
    if fit is not None:
        data["fit"] = fit
    return data


_FIT = {"models": ["unicycle"], "q": {"alpha": 2e-3, "beta": 2e-3, "gamma": 2e-3},
        "p0": {"x": 1.0, "y": 1.0, "z": 1.0, "alpha": 1e-3, "beta": 1e-3, "gamma": 0.1, "kappa": 1e-4},
        "measurements": {"us": {"sigma": [1.0, 1.0, 1.0], "frame": "needle", "student_t": 5.0,
                                "along_offset": {"tau": 4.0, "sigma": 1.0}}},
        "init": {"from": "nominal", "first_measurement": {"x": "us.x", "y": "us.y", "z": "us.z"}},
        "em": {"max_iter": 200, "tol": 1.0e-2, "reweight_max": 3}, "identify": {"enabled": True}}


@pytest.fixture(scope="module")
def needle_fit(tmp_path_factory):
    d = tmp_path_factory.mktemp("realem")
    cfg = d / "fit.yaml"
    cfg.write_text(yaml.safe_dump(_sim_config([{"name": "open_loop", "type": "open_loop"}], fit=_FIT)))
    r = CliRunner().invoke(app, ["fit-em", str(cfg), "--out", str(d / "fit.h5"), "--quiet"])
    assert r.exit_code == 0, r.output
    return d, d / "fit.h5"


def _s(v):
    return [x.decode() if isinstance(x, bytes) else str(x) for x in np.atleast_1d(v)]


def test_fit_file_records_needle_coordinates_weights_and_the_sensor_state(needle_fit):
    _, fit = needle_fit
    with h5py.File(fit) as f:
        g = f["fit/unicycle"]
        assert _s(g.attrs["names"])[-1] == "us_offset" and _s(g.attrs["sensor_states"]) == ["us_offset"]
        assert list(g.attrs["sensor_state_tau"]) == [4.0]
        assert _s(g["R"].attrs["needle_frame"]) == ["us"] and _s(g["R"].attrs["needle_axis"]) == ["x"]
        assert g["weights/us"].shape == f["measurements/us/valid"].shape
        assert (g["reweight_passes"][()] >= 1).all()
        q = _s(g["identifiability"].attrs["quantities"])
        assert "tr(R_us_along)" in q and "tr(R_us_across)" in q and "tr(Q_us_offset)" in q


def test_from_fit_gives_the_ukf_sigma_in_needle_coordinates(needle_fit):
    d, fit = needle_fit
    ukf = {"name": "ukf_em", "type": "ukf", "from_fit": {"file": str(fit), "model": "unicycle"},
           "p0": {"x": 1.0, "y": 1.0, "z": 1.0, "alpha": 1e-3, "beta": 1e-3, "gamma": 0.1},
           "init": {"first_measurement": {"x": "us.x", "y": "us.y", "z": "us.z"}}}
    cfg, text = load_config(text=yaml.safe_dump(_sim_config([ukf])))
    with h5py.File(fit) as f:
        g = f["fit/unicycle"]
        ok = g["status"][()].astype(str) == "ok"
        R = np.median(g["R/us"][()][ok], axis=0)
        Q = np.median(g["Q"][()][ok], axis=0)
    nu = 5.0
    var = np.diag(R) * nu / (nu - 2.0)  # the Student-t's variance
    var[0] += Q[-1, -1] * 4.0 / 2.0  # and the offset's stationary variance, along the needle
    spec = cfg.observers[0].measurements["us"]
    assert spec.frame == "needle" and spec.across_axis == "x"
    np.testing.assert_allclose(spec.sigma, np.sqrt(var), rtol=1e-12)
    assert "us_offset" not in cfg.observers[0].q
    # a world-axes frame given by hand contradicts the fit's coordinates
    ukf["measurements"] = {"us": {"frame": "world"}}
    with pytest.raises(ConfigError, match="needle coordinates"):
        load_config(text=yaml.safe_dump(_sim_config([ukf])))


def test_a_fit_section_takes_and_holds_another_fit(needle_fit, tmp_path):
    d, fit = needle_fit
    f2 = {k: v for k, v in _FIT.items() if k not in ("q",)}
    f2 = {**f2, "from_fit": {"file": str(fit), "model": "unicycle", "pick": "median"},
          "hold": ["alpha", "beta", "gamma", "kappa"], "hold_reason": "the needle's motion, from the first fit",
          "measurements": {"us": {"sigma": [1.0, 1.0, 1.0], "frame": "needle"}}}
    cfg_path = tmp_path / "fit2.yaml"
    cfg_path.write_text(yaml.safe_dump(_sim_config([{"name": "open_loop", "type": "open_loop"}], fit=f2)))
    r = CliRunner().invoke(app, ["fit-em", str(cfg_path), "--out", str(tmp_path / "fit2.h5"), "--quiet"])
    assert r.exit_code == 0, r.output
    with h5py.File(fit) as a, h5py.File(tmp_path / "fit2.h5") as b:
        ga, gb = a["fit/unicycle"], b["fit/unicycle"]
        ok = ga["status"][()].astype(str) == "ok"
        names = _s(ga.attrs["names"])
        Qa = np.median(ga["Q"][()][ok], axis=0)
        kappa = float(np.median(ga["constant/kappa"][()][ok]))
        assert "kappa" not in _s(gb.attrs["names"])  # held: a parameter, not a state
        np.testing.assert_allclose(gb["constant/kappa"][()], kappa, rtol=1e-12)
        for s in ("alpha", "beta", "gamma"):
            i = names.index(s)
            np.testing.assert_allclose(gb["Q"][()][:, i, i], Qa[i, i], rtol=1e-12)
        assert _s(gb.attrs["held"]) == ["alpha", "beta", "gamma", "kappa"]
        assert _s(gb.attrs["hold_reason"]) == ["the needle's motion, from the first fit"]  # why, in the file
        q = _s(gb["identifiability"].attrs["quantities"])
        assert "kappa" not in q and "tr(Q_alpha)" not in q


@pytest.mark.parametrize("edit, loc, message", [
    (lambda f: f.update(hold=["pz"]), "fit -> hold -> 0", "has a state or fitted constant"),
    (lambda f: f.update(hold=["x"]), "fit -> hold -> 0", "nothing to hold"),
    (lambda f: f["measurements"]["us"].update(frame="needle", across_axis=None, along_offset={"tau": 1.0, "sigma": -1.0}),
     "fit -> measurements -> us -> along_offset -> sigma", "greater than or equal"),
])
def test_fit_section_mistakes(edit, loc, message):
    fit = yaml.safe_load(yaml.safe_dump(_FIT))
    edit(fit)
    with pytest.raises(ConfigError) as e:
        load_config(text=yaml.safe_dump(_sim_config([{"name": "open_loop", "type": "open_loop"}], fit=fit)))
    assert loc in str(e.value) and message in str(e.value)


def test_needle_settings_are_for_fits_and_positions():
    ekf = {"name": "e", "type": "ekf", "q": {"alpha": 1e-3}, "measurements": {"us": {"student_t": 4.0}}}
    with pytest.raises(ConfigError, match="setting of needle fit-em"):
        load_config(text=yaml.safe_dump(_sim_config([ekf])))
    ukf = {"name": "u", "type": "ukf", "measurements": {"us": {"sigma": 1.0, "across_axis": "x"}}}
    with pytest.raises(ConfigError, match="only with frame: needle"):
        load_config(text=yaml.safe_dump(_sim_config([ukf])))


def test_ukf_in_needle_coordinates_with_equal_sigmas_is_the_world_filter(tmp_path):
    """R = F diag(s^2) F^T = s^2 I: the needle-frame UKF with one sigma is the world-axes one, to
    rounding, when both start from the same draw (runs.common_start)."""
    base = {"type": "ukf", "q": {"alpha": 1e-4, "beta": 1e-4, "gamma": 1e-4},
            "p0": {"x": 1.0, "y": 1.0, "z": 1.0, "alpha": 1e-3, "beta": 1e-3, "gamma": 0.1},
            "init": {"std": {"alpha": 0.03, "beta": 0.03}, "first_measurement": {"x": "us.x", "y": "us.y", "z": "us.z"}}}
    obs = [{**base, "name": "world", "measurements": {"us": {"sigma": 0.8}}},
           {**base, "name": "needle", "measurements": {"us": {"sigma": [0.8, 0.8, 0.8], "frame": "needle"}}},
           {**base, "name": "needle_aniso", "measurements": {"us": {"sigma": [3.0, 0.8, 0.8], "frame": "needle"}}}]
    cfg = tmp_path / "u.yaml"
    cfg.write_text(yaml.safe_dump(_sim_config(obs, extra_runs={"common_start": {"observer": "world",
                                                                                "observers": ["needle", "needle_aniso"]}})))
    r = CliRunner().invoke(app, ["simulate", str(cfg), "--out", str(tmp_path / "u.h5"), "--quiet"])
    assert r.exit_code == 0, r.output
    with h5py.File(tmp_path / "u.h5") as f:
        w, n, a = (f[f"estimates/{k}/state"][()] for k in ("world", "needle", "needle_aniso"))
    np.testing.assert_allclose(n, w, atol=1e-9)
    np.testing.assert_array_equal(a[:, 0], w[:, 0])  # the common start
    assert np.abs(a - w).max() > 1e-3  # a larger along sigma does change the estimate


@pytest.mark.parametrize("cs, loc, message", [
    ({"observer": "nobody", "observers": ["u"]}, "runs -> common_start -> observer", "no observer named"),
    ({"observer": "hg", "observers": ["u"]}, "runs -> common_start -> observer", "gives no initial estimate"),
    ({"observer": "u", "observers": ["u", "ghost"]}, "runs -> common_start -> observers -> 1", "no observer named"),
])
def test_common_start_mistakes(cs, loc, message):
    obs = [{"name": "u", "type": "ukf"}, {"name": "hg", "type": "high_gain"}]
    with pytest.raises(ConfigError) as e:
        load_config(text=yaml.safe_dump(_sim_config(obs, extra_runs={"common_start": cs})))
    assert loc in str(e.value) and message in str(e.value)


# ---------------------------------------------------------------------------------------------- reports
def test_along_across_table_and_plot(tmp_path):
    """The along and across components rebuild the error's magnitude, frame by frame (hypot), and the
    plot draws every observer and the raw sensor (a replayed file: here a simulation written as a log and
    replayed)."""
    from needlecli.io.results import read_results
    from needlecli.reports.along_across import real_error_along_across, sources

    obs = [{"name": "ukf", "type": "ukf", "measurements": {"us": {"sigma": 0.8}},
            "p0": {"x": 1.0, "y": 1.0, "z": 1.0, "alpha": 1e-3, "beta": 1e-3, "gamma": 0.1},
            "init": {"first_measurement": {"x": "us.x", "y": "us.y", "z": "us.z"}}}]
    sim = tmp_path / "s.yaml"
    sim.write_text(yaml.safe_dump(_sim_config(obs)))
    runner = CliRunner()
    assert runner.invoke(app, ["simulate", str(sim), "--out", str(tmp_path / "s.h5"), "--quiet"]).exit_code == 0
    r = runner.invoke(app, ["log", "from-results", str(tmp_path / "s.h5"), "--out", str(tmp_path / "s.log.h5")])
    assert r.exit_code == 0, r.output
    rep = {"name": "rep", "source": {"logs": [str(tmp_path / "s.log.h5")]}, "model": {"type": "unicycle", "params": {"kappa": 0.012}},
           "observers": obs, "simulation": {"dt": 0.05}, "output": {"store_every": 1, "covariance": "none"}}
    (tmp_path / "r.yaml").write_text(yaml.safe_dump(rep))
    r = runner.invoke(app, ["simulate", str(tmp_path / "r.yaml"), "--out", str(tmp_path / "r.h5"), "--quiet"])
    assert r.exit_code == 0, r.output
    res = read_results(tmp_path / "r.h5")
    src = {label: (al, ac) for label, _, _, al, ac in sources(res)}
    assert set(src) == {"us (raw measurements)", "ukf"}
    with h5py.File(tmp_path / "r.h5") as f:
        tr = f["truth/state"][()]
        est = f["estimates/ukf/state"][()]
    have = np.isfinite(tr[..., 0]).any(0)
    al, ac = src["ukf"]
    np.testing.assert_allclose(np.hypot(al, ac), np.linalg.norm(est[:, have, :3] - tr[:, have, :3], axis=-1), atol=1e-9)
    df = real_error_along_across(res)
    assert list(df["Source"]) == ["us (raw measurements)", "ukf"]
    raw = df.iloc[0]
    assert raw["Across mean"] > 0.5 and abs(raw["Along mean (signed)"]) < 0.3  # isotropic 0.8 mm noise
    out = tmp_path / "ev"
    r = runner.invoke(app, ["evaluate", str(tmp_path / "r.h5"), "--out", str(out), "--quiet"])
    assert r.exit_code == 0, r.output
    png = out / "rep_error_along_across.png"
    assert png.exists() and png.stat().st_size > 10_000


def test_from_fit_gives_the_ekf_the_offset_state_and_the_ukf_its_white_equivalent(needle_fit, tmp_path):
    """An EKF (which has sensor states) takes the fitted offset itself: along_offset with the fit's tau and
    sigma = sqrt(q^2 tau / 2), the white R along the needle alone; a UKF with ``offset: white`` takes
    2 sigma^2 tau / dt along the needle, dt the mean interval between the channel's valid samples."""
    d, fit = needle_fit
    base = {"p0": {"x": 1.0, "y": 1.0, "z": 1.0, "alpha": 1e-3, "beta": 1e-3, "gamma": 0.1},
            "init": {"first_measurement": {"x": "us.x", "y": "us.y", "z": "us.z"}}}
    ekf = {"name": "ekf_em", "type": "ekf", "from_fit": {"file": str(fit), "model": "unicycle"}, **base}
    ukf = {"name": "ukf_w", "type": "ukf", "from_fit": {"file": str(fit), "model": "unicycle", "offset": "white"}, **base}
    cfg, _ = load_config(text=yaml.safe_dump(_sim_config([ekf, ukf])))
    with h5py.File(fit) as f:
        g = f["fit/unicycle"]
        ok = g["status"][()].astype(str) == "ok"
        R = np.median(g["R/us"][()][ok], axis=0)
        q2 = np.median(g["Q"][()][ok], axis=0)[-1, -1]
        t, valid = f["measurements/us/t"][()], f["measurements/us/valid"][()]
    white = np.diag(R) * 5.0 / 3.0  # the Student-t's variance (nu = 5)
    e = cfg.observers[0].measurements["us"]
    assert e.along_offset.tau == 4.0
    np.testing.assert_allclose(e.along_offset.sigma, np.sqrt(q2 * 4.0 / 2.0), rtol=1e-12)
    np.testing.assert_allclose(e.sigma, np.sqrt(white), rtol=1e-12)
    dt = np.median([(t[v][-1] - t[v][0]) / (v.sum() - 1) for v in valid[ok]])
    u = cfg.observers[1].measurements["us"]
    np.testing.assert_allclose(u.sigma[0] ** 2, white[0] + 2.0 * (q2 * 4.0 / 2.0) * 4.0 / dt, rtol=1e-12)
    np.testing.assert_allclose(u.sigma[1:], np.sqrt(white[1:]), rtol=1e-12)
    # the EKF runs with the offset as a state of its own
    path = tmp_path / "e.yaml"
    path.write_text(yaml.safe_dump(_sim_config([ekf])))
    r = CliRunner().invoke(app, ["simulate", str(path), "--out", str(tmp_path / "e.h5"), "--quiet"])
    assert r.exit_code == 0, r.output
    with h5py.File(tmp_path / "e.h5") as f:
        assert _s(f["estimates/ekf_em"].attrs["names"])[-1] == "us_offset"
        assert np.isfinite(f["estimates/ekf_em/state"][()]).all()


def test_white_equivalent_of_an_offset_is_the_variance_of_its_long_averages():
    """Independent reference: the exact variance of the mean of n samples of the offset sampled every dt
    (AR(1), phi = exp(-dt / tau): sigma^2 / n^2 sum_ij phi^|i - j|) approaches r / n with r the white
    equivalent 2 sigma^2 tau / dt of from_fit's ``offset: white``, for n dt >> tau and dt << tau."""
    from needlecli.experiments.config.from_fit import offset_variance

    class _Meas:  # a channel of 4000 samples every 0.05 s, all valid
        data = {"t": np.arange(4000) * 0.05, "valid": np.ones((1, 4000), dtype=bool)}

    tau, sigma2, dt = 2.0, 1.7, 0.05
    q2 = 2.0 * sigma2 / tau
    assert offset_variance(q2, tau, "stationary", _Meas, np.ones(1, bool), "c", ()) == pytest.approx(sigma2)
    r = offset_variance(q2, tau, "white", _Meas, np.ones(1, bool), "c", ())
    n = 4000
    phi = np.exp(-dt / tau)
    k = np.arange(1, n)
    exact = sigma2 / n**2 * (n + 2.0 * np.sum((n - k) * phi**k))
    assert r / n == pytest.approx(exact, rel=0.02)
    with pytest.raises(ConfigError, match="random walk"):
        offset_variance(q2, np.inf, "white", _Meas, np.ones(1, bool), "c", ())


def test_needle_frame_offset_and_weights_take_the_numpy_path(monkeypatch):
    """The compiled linearisation covers channels that select states in world axes: a channel in the
    needle's frame, with an offset state or with robust weights (all with a state-selecting h, which the
    kernel would otherwise take) linearises as the numpy reference does, and so do the transitions of a
    system with a sensor state."""
    from needlecli import kernels
    from needlecli.fitting.smoother import linearise
    from needlecli.models.base import StateSelection

    model, truth, y, _, inputs, ticks, dt = _synthetic([2.0, 0.5, 0.5], N=2, T=20.0, ou=(2.0, 1.0))
    dm, mm = _system(model, y, inputs, ticks, dt, offset=2.0)
    N, M = y.shape[:2]
    chans = [dataclasses.replace(mm, h=StateSelection([0, 1, 2])),  # needle frame and offset
             dataclasses.replace(mm, h=StateSelection([0, 1, 2]), frame="world", tangent_fn=None, offset_index=None,
                                 weight=np.random.default_rng(1).uniform(0.2, 1.0, (N, M)))]
    rng = np.random.default_rng(4)
    m0, _ = _start(model, y, truth, dm)
    zbar = m0[:, None, :] + 0.1 * rng.standard_normal((N, len(dm.ticks), dm.n))
    got = linearise(dm, chans, zbar)
    monkeypatch.setenv(kernels.ENV, "numpy")
    ref = linearise(dm, chans, zbar)
    for a, b in [(got.A, ref.A), (got.b, ref.b), *zip(got.H, ref.H), *zip(got.y, ref.y), *zip(got.d, ref.d)]:
        np.testing.assert_array_equal(a, b)
