"""Identifiability of a fit (needlecli.fitting.identify) against a closed form: on a linear-Gaussian
random walk with a drift constant, the measurements are jointly Gaussian, y ~ N(a0 + g U, Q S + R I)
(S_ij = min(t_i, t_j)), so the log-likelihood and its Hessian in (g, log-scale of Q, log-scale of R) are
known exactly; the module's finite-difference Hessian of its filter's log-likelihood must match them.
A constant the data carry no information on is "not identified"; a process noise far below the
measurement noise is "weakly identified" (flat over a decade), and says why."""

from __future__ import annotations

import h5py
import numpy as np
import pytest
from pydantic import Field

from needlecli.fitting.identify import IDENTIFIED, NOT_IDENTIFIED, STOPPED_SHORT, WEAK, IdentifyOptions, identify
from needlecli.fitting.statespace import DiscreteModel, MeasurementModel
from needlecli.models.base import Model, ModelParams

DT = 0.1


class DriftParams(ModelParams):
    g: float = Field(0.5, description="drift per unit input")
    k: float = Field(0.0, description="drift per unit of the second input (always zero here)")


class Drift(Model):
    """``a' = g u1 + k u2``: a random walk with a drift the first input scales."""

    state_names = ("a",)
    state_units = ("mm",)
    input_names = ("u1", "u2")
    input_sizes = {"u1": 1, "u2": 1}
    input_units = {"u1": "1", "u2": "1"}
    Params = DriftParams

    def f(self, x, u, p):
        return (p["g"] * u[..., 0] + p["k"] * u[..., 1])[..., None] + 0.0 * x

    def initial_state(self, p):
        return np.zeros(1)


def _data(N=3, T=120, q=0.04, r=0.09, g=0.5, seed=1, augment=("g",)):
    rng = np.random.default_rng(seed)
    t = np.arange(T) * DT
    u1 = 1.0 + 0.5 * np.sin(0.3 * np.arange(T))  # held over each step
    u = np.zeros((N, T, 2))
    u[..., 0] = u1
    U = np.concatenate([[0.0], np.cumsum(u1[:-1] * DT)])  # integral of u1 up to each tick
    walk = np.concatenate([np.zeros((N, 1)), np.cumsum(np.sqrt(q * DT) * rng.standard_normal((N, T - 1)), 1)], 1)
    y = (g * U + walk + np.sqrt(r) * rng.standard_normal((N, T)))[..., None]
    dm = DiscreteModel(Drift(DriftParams(g=g, k=0.0)), {"g": np.full(N, g), "k": np.zeros(N)}, augment, DT,
                       np.arange(T), u, None)
    mm = MeasurementModel("pos", lambda z: z[..., :1], 1, np.arange(T), y, np.ones((N, T), bool), np.zeros(1, bool),
                          names=("a",), units=("mm",))
    return dm, mm, y[..., 0], U, t


def _closed_form(y, U, t, g, q, r):
    """Exact log-likelihood Hessian in (g, s, r) of y ~ N(g U, q S + r I) at the given values."""
    S = np.minimum(t[:, None], t[None, :])
    SQ, SR = q * S, r * np.eye(len(t))
    Sig = SQ + SR
    Si = np.linalg.inv(Sig)
    e = y - g * U
    a = Si @ e
    H = np.zeros((3, 3))
    H[0, 0] = -U @ Si @ U
    parts = [SQ, SR]
    for i, Pi in enumerate(parts, start=1):
        H[0, i] = H[i, 0] = -U @ Si @ Pi @ a
        for j, Pj in enumerate(parts, start=1):
            Pij = Pi if i == j else np.zeros_like(Pi)
            H[i, j] = (-0.5 * np.trace(Si @ Pij) + 0.5 * np.trace(Si @ Pj @ Si @ Pi)
                       + 0.5 * a @ Pij @ a - a @ Pj @ Si @ Pi @ a)
    ll = -0.5 * np.linalg.slogdet(2 * np.pi * Sig)[1] - 0.5 * e @ a
    return H, ll


def test_hessian_and_standard_errors_match_the_closed_form():
    q, r, g = 0.04, 0.09, 0.5
    dm, mm, y, U, t = _data(q=q, r=r, g=g)
    N = y.shape[0]
    x0 = np.zeros((N, 2))
    x0[:, 1] = g
    Q = np.zeros((N, 2, 2))
    Q[:, 0, 0] = q
    R = [np.full((N, 1, 1), r)]
    res = identify(dm, [mm], x0, np.zeros((2, 2)), Q, R, np.ones(N, bool), const_sd=np.full((N, 1), 0.05),
                   options=IdentifyOptions(step_log=0.05))
    assert res.names == ["g", "tr(Q_a)", "tr(R_pos)"]
    for i in range(N):
        H, ll = _closed_form(y[i], U, t, g, q, r)
        assert res.loglik[i] == pytest.approx(ll, rel=1e-9, abs=1e-9)  # the filter's likelihood is the exact one
        np.testing.assert_allclose(res.hessian[i], H, rtol=0.03, atol=0.03 * np.abs(H).max())
        se = np.sqrt(np.diag(np.linalg.inv(-H)))
        np.testing.assert_allclose(res.se[i], [se[0], q * se[1], r * se[2]], rtol=0.03)
    pooled = sum(_closed_form(y[i], U, t, g, q, r)[0] for i in range(N))
    se_p = np.sqrt(np.diag(np.linalg.inv(-pooled)))
    np.testing.assert_allclose(res.pooled_se, [se_p[0], q * se_p[1], r * se_p[2]], rtol=0.03)
    assert list(res.pooled_verdict) == [IDENTIFIED] * 3


def test_a_constant_without_information_is_not_identified_and_leaves_the_others():
    dm, mm, y, U, t = _data(augment=("g", "k"))  # k multiplies an input that is always zero
    N = y.shape[0]
    x0 = np.zeros((N, 3))
    x0[:, 1] = 0.5
    Q = np.zeros((N, 3, 3))
    Q[:, 0, 0] = 0.04
    res = identify(dm, [mm], x0, np.zeros((3, 3)), Q, [np.full((N, 1, 1), 0.09)], np.ones(N, bool),
                   const_sd=np.full((N, 2), 0.05))
    k = res.names.index("k")
    assert (res.verdict[:, k] == NOT_IDENTIFIED).all() and np.isnan(res.se[:, k]).all()
    assert "no positive information" in res.reason[0, k]
    assert (res.verdict[:, res.names.index("g")] == IDENTIFIED).all()
    assert np.isfinite(res.se[:, res.names.index("g")]).all()


def test_process_noise_far_below_the_measurement_noise_is_not_called_identified():
    """Q at 1/1000 of R over 12 s: the likelihood hardly changes with it (at the true value it is not even
    concave in some trials); never "identified", always with the reason."""
    q, r = 1e-3, 1.0
    dm, mm, y, U, t = _data(q=q, r=r)
    N = y.shape[0]
    x0 = np.zeros((N, 2))
    x0[:, 1] = 0.5
    Q = np.zeros((N, 2, 2))
    Q[:, 0, 0] = q
    res = identify(dm, [mm], x0, np.zeros((2, 2)), Q, [np.full((N, 1, 1), r)], np.ones(N, bool),
                   const_sd=np.full((N, 1), 0.05))
    kq = res.names.index("tr(Q_a)")
    assert set(res.verdict[:, kq]) <= {WEAK, NOT_IDENTIFIED} and WEAK in set(res.verdict[:, kq])
    for v, why in zip(res.verdict[:, kq], res.reason[:, kq]):
        assert ("flat over a decade" in why or "relative SE" in why) if v == WEAK else "no positive information" in why
    assert res.pooled_verdict[kq] in (WEAK, NOT_IDENTIFIED)
    assert (res.verdict[:, res.names.index("tr(R_pos)")] == IDENTIFIED).all()
    assert (res.verdict[:, res.names.index("g")] == IDENTIFIED).all()


def test_a_likelihood_that_rises_over_the_decade_says_em_stopped_short():
    """A decade that raises the log-likelihood by more than the nats: the estimate is where EM stopped, not
    the maximum ("EM stopped short of the maximum", never "not identified" nor "flat"); a floor that held
    an R there is the floor's doing (weakly identified, held by its floor); a decade within the nats is
    flat."""
    from needlecli.fitting.identify import IdentifyOptions, Quantity, _verdicts

    qs = [Quantity("tr(R_a)", "R", 0, "mm^2"), Quantity("tr(R_b)", "R", 1, "mm^2"), Quantity("tr(R_c)", "R", 2, "mm^2")]
    rse = np.array([[0.1, 0.1, 0.1]])
    decade = np.array([[[5.0, -1.2e3], [5.0, 0.7], [5.0, 3.0]]])  # (x10, x1/10) costs in nats
    verdict, reason = _verdicts(qs, rse, decade, np.zeros((1, 3), bool), IdentifyOptions())
    assert list(verdict[0]) == [STOPPED_SHORT, WEAK, IDENTIFIED]
    assert reason[0, 0] == "not the log-likelihood's maximum (x1/10 raises it by 1.2e+03 nats)"
    assert "flat" not in reason[0, 0]
    assert "flat over a decade (x1/10 costs 0.7 nats; < 2)" == reason[0, 1]
    floored = np.array([[True, False, False]])
    verdict, reason = _verdicts(qs, rse, decade, np.zeros((1, 3), bool), IdentifyOptions(), floored=floored)
    assert verdict[0, 0] == WEAK and "held by its floor (x1/10 raises it by 1.2e+03 nats)" == reason[0, 0]


def test_em_stopped_short_of_the_maximum_on_the_closed_form_model():
    """Process noise 30 times its maximum-likelihood value (where an EM that crawls could stop): a decade
    down raises the exact log-likelihood by far more than the nats, and the verdict says so."""
    q, r = 0.04, 0.09
    dm, mm, y, U, t = _data(q=q, r=r)
    N = y.shape[0]
    x0 = np.zeros((N, 2))
    x0[:, 1] = 0.5
    Q = np.zeros((N, 2, 2))
    Q[:, 0, 0] = 30 * q
    res = identify(dm, [mm], x0, np.zeros((2, 2)), Q, [np.full((N, 1, 1), r)], np.ones(N, bool),
                   const_sd=np.full((N, 1), 0.05))
    kq = res.names.index("tr(Q_a)")
    for i in range(N):  # the exact likelihood: a tenth of the noise is far more likely
        assert _closed_form(y[i], U, t, 0.5, 3 * q, r)[1] - _closed_form(y[i], U, t, 0.5, 30 * q, r)[1] > 2.0
    assert (res.verdict[:, kq] == STOPPED_SHORT).all() and res.group_verdict[0, kq] == STOPPED_SHORT
    assert "x1/10 raises it by" in res.group_reason[0, kq]


def test_failed_trials_are_left_out():
    dm, mm, y, U, t = _data()
    N = y.shape[0]
    x0 = np.zeros((N, 2))
    x0[:, 1] = 0.5
    Q = np.zeros((N, 2, 2))
    Q[:, 0, 0] = 0.04
    ok = np.array([True, False, True])
    res = identify(dm, [mm], x0, np.zeros((2, 2)), Q, [np.full((N, 1, 1), 0.09)], ok, const_sd=np.full((N, 1), 0.05))
    assert np.isnan(res.hessian[1]).all() and not res.used[1] and res.used[[0, 2]].all()
    assert (res.verdict[1] == "").all()


def _at_maximum(seed=3, q=0.2, r=0.09, g=0.5):
    """The closed-form data and each trial's exact maximum ``(g, log q, log r)`` (an optimiser on the
    closed form), every maximum inside (q > 0) for this seed."""
    from scipy.optimize import minimize

    dm, mm, y, U, t = _data(q=q, r=r, g=g, seed=seed)
    best = []
    for i in range(y.shape[0]):
        f = minimize(lambda th, i=i: -_closed_form(y[i], U, t, th[0], np.exp(th[1]), np.exp(th[2]))[1],
                     [g, np.log(q), np.log(r)], method="Nelder-Mead", options={"xatol": 1e-7, "fatol": 1e-10})
        best.append(f.x)
    return dm, mm, y, np.array(best)


def _fit_at(dm, mm, best, q_factor=1.0):
    N = len(best)
    x0 = np.zeros((N, 2))
    x0[:, 1] = best[:, 0]
    Q = np.zeros((N, 2, 2))
    Q[:, 0, 0] = q_factor * np.exp(best[:, 1])
    return (dm, [mm], x0, np.zeros((2, 2)), Q, [np.exp(best[:, 2])[:, None, None]], np.ones(N, bool))


def test_newton_steps_point_to_the_exact_maximum():
    """At each trial's exact maximum identify gives no step; with q 1.3 times its maximum, the Newton step
    in q's log scale lands on it (the log-likelihood is nearly quadratic in log q over that range); at 4
    times, the group's verdict says EM stopped short, with where the maximum is."""
    dm, mm, y, best = _at_maximum()
    N = len(best)
    for factor, expected in ((1.0, 0.0), (1.3, -np.log(1.3))):
        res = identify(*_fit_at(dm, mm, best, factor), const_sd=np.full((N, 1), 0.05),
                       options=IdentifyOptions(step_log=0.05))
        np.testing.assert_allclose(res.newton[:, 1], expected, atol=0.02)
        np.testing.assert_allclose(res.newton[:, [0, 2]], 0.0, atol=0.01)
    assert res.group_verdict[0, 1] == IDENTIFIED  # 1.3 times: within 2 SE of the mean step (3 trials)
    res = identify(*_fit_at(dm, mm, best, 4.0), const_sd=np.full((N, 1), 0.05))
    assert res.group_verdict[0, 1] == STOPPED_SHORT, res.group_reason
    assert res.group_reason[0, 1].startswith("the log-likelihood peaks at x0.")


def test_recovery_against_a_hand_computation():
    """The miss of the mean in the larger of its two standard errors (spread, information)."""
    from needlecli.numerics.recovery import recovery

    est = np.array([[1.0, 5.0], [2.0, 5.0], [3.0, np.nan]])
    truth = np.array([[0.0, 4.0], [0.0, 4.0], [0.0, 4.0]])
    se = np.array([[0.1, 0.3], [0.1, 0.4], [0.1, 0.5]])
    mean_truth, miss, sem, z = recovery(est, se, truth)
    np.testing.assert_allclose(mean_truth, [0.0, 4.0])
    np.testing.assert_allclose(miss, [2.0, 1.0])
    np.testing.assert_allclose(sem, [1.0 / np.sqrt(3.0), 0.5 / 2.0])  # spread wins; then the SEs (no spread)
    np.testing.assert_allclose(z, [2.0 * np.sqrt(3.0), 4.0])


def test_an_estimate_off_its_truth_by_five_standard_errors_is_biased_never_identified():
    """Each trial fitted at its exact maximum: every quantity identified; with the truth put 5 standard
    errors of the group's mean below it (the larger of the spread's and the information's, computed here),
    the group's verdict is biased, with the miss; 1 SE off, identified."""
    from needlecli.fitting.identify import BIASED, verdict_text

    dm, mm, y, best = _at_maximum()
    N = len(best)
    args = _fit_at(dm, mm, best)
    base = identify(*args, const_sd=np.full((N, 1), 0.05))
    assert (base.group_verdict == IDENTIFIED).all(), base.group_reason
    sem = np.maximum(base.estimate.std(0, ddof=1) / np.sqrt(N), np.sqrt((base.se**2).sum(0)) / N)
    for off, expect in ((5.0, BIASED), (1.0, IDENTIFIED)):
        res = identify(*args, const_sd=np.full((N, 1), 0.05),
                       truth=np.broadcast_to(base.estimate.mean(0) - off * sem, (N, 3)))
        assert list(res.group_verdict[0]) == [expect] * 3, res.group_reason
        np.testing.assert_allclose(res.group_z[0], off, rtol=1e-9)
        assert (res.verdict == base.verdict).all()  # a trial's own verdict is its information's
        if expect == BIASED:
            assert all(r.startswith("estimate - truth = +5.0 SE (") for r in res.group_reason[0])
            assert verdict_text(res.group_verdict[0, 0], res.group_z[0, 0]) == "biased (estimate - truth = +5.0 SE)"
            assert "the likelihood's maximum itself misses the truth" in res.group_reason[0, 0]  # EM did not stop short


def test_groups_pool_their_own_trials_only():
    """Each design group's SE is the closed form's from the summed Hessians of its own trials; the
    trials of the other group do not enter."""
    q, r, g = 0.04, 0.09, 0.5
    dm, mm, y, U, t = _data(N=4, q=q, r=r, g=g)
    x0 = np.zeros((4, 2))
    x0[:, 1] = g
    Q = np.zeros((4, 2, 2))
    Q[:, 0, 0] = q
    group = np.array([0, 1, 1, 0])
    res = identify(dm, [mm], x0, np.zeros((2, 2)), Q, [np.full((4, 1, 1), r)], np.ones(4, bool),
                   const_sd=np.full((4, 1), 0.05), options=IdentifyOptions(step_log=0.05), group=group,
                   group_labels=["speed=1", "speed=2"])
    assert res.group_labels == ["speed=1", "speed=2"] and list(res.group_trials) == [2, 2]
    for k in range(2):
        H = sum(_closed_form(y[i], U, t, g, q, r)[0] for i in np.nonzero(group == k)[0])
        se = np.sqrt(np.diag(np.linalg.inv(-H)))
        np.testing.assert_allclose(res.group_se[k], [se[0], q * se[1], r * se[2]], rtol=0.03)
    assert not np.allclose(res.group_se[0], res.pooled_se, rtol=0.1)  # pooled over all: another figure


def test_trial_counts_name_the_trials():
    from needlecli.reports.identify import trial_counts

    v = np.array([IDENTIFIED, IDENTIFIED, WEAK, IDENTIFIED, STOPPED_SHORT], dtype=object)
    ids = np.array(["run 0", "run 1", "run 2", "run 3", "trial 12"])
    assert trial_counts(v, ids) == ("identified 3/5; weakly identified 1/5: run 2; "
                                    "EM stopped short of the maximum 1/5: trial 12")
    assert trial_counts(v[:2], ids[:2]) == "identified 2/2"


def test_a_free_unit_vector_block_says_how_much_of_its_trace_is_unseen():
    """The MNM's field along -y, its process noise diag(a, b) on (Bx, By): the part along the field is b
    (a / (a + b) across); free, that fraction is reported and above ``along_max`` the verdict is weak;
    tied (fit.isotropic), it is not counted."""
    from needlecli.fitting.identify import IdentifyOptions, Quantity, _verdicts, along_fraction
    from needlecli.models.magnetic import MagneticNeedleModel

    m = MagneticNeedleModel()
    dm = DiscreteModel(m, m.param_arrays(), ("c",), 0.1, np.arange(3), np.zeros((2, 3, 4)), None)
    iB = [dm.names.index(s) for s in ("Bx", "By", "Bz")]
    qs = [Quantity("tr(Q_B)", "Q", iB, "1/s")]
    Q = np.zeros((2, 10, 10))
    Q[:, iB[0], iB[0]], Q[:, iB[1], iB[1]] = 1e-8, 4e-8
    zbar = np.zeros((2, 3, 10))
    zbar[..., iB[1]] = -1.0
    frac = along_fraction(dm, qs, Q, zbar)
    np.testing.assert_allclose(frac, 0.8)
    assert np.isnan(along_fraction(dm, qs, Q, zbar, tied=("B",))).all()
    verdict, reason = _verdicts(qs, np.array([[0.05]] * 2), np.full((2, 1, 2), 50.0), np.zeros((2, 1), bool),
                                IdentifyOptions(), along=frac)
    assert (verdict == WEAK).all() and "80 % of its trace lies along the unit vector" in reason[0, 0]


def test_seed004_study_flags_q_h_and_not_c(seed004_fit):
    """On the magnetic needle EM paper's design the data identify c and not Q_h (issue: refits from three starting guesses of
    Q_h end 0.06x to 5.6x the truth within 0.7 nats), in every field strength the trials have."""
    from needlecli.io.fit import read_fit
    from needlecli.reports.identify import identifiability_table
    from needlecli.reports.seed004 import table1, table3

    res = read_fit(seed004_fit)
    df = identifiability_table(res)
    assert set(df["Group"]) == {"10 mT", "19 mT"}  # 6 trials: no 28 mT trial
    df = df.set_index(["Model", "Quantity", "Group"])
    for model, const in (("mnm", "c"), ("binm", "l_inv")):
        for grp in ("10 mT", "19 mT"):
            assert df.loc[(model, const, grp), "Verdict"] == IDENTIFIED
            assert df.loc[(model, "tr(Q_h)", grp), "Verdict"] != IDENTIFIED
            why = df.loc[(model, "tr(Q_h)", grp), "Reason"]
            assert "flat over a decade" in why or "maximum" in why
            assert df.loc[(model, "tr(R_camera)", grp), "Verdict"] == IDENTIFIED
    t1 = table1(res)
    assert "tr(Q_h) †" in t1.columns and "tr(Q_B)" in t1.columns and "not determined" in t1.attrs["note"]
    t3 = table3(res)
    assert "Q_h †" in t3.columns and "do not determine" in t3.attrs["note"]


def _truths_and_estimates(f, model):
    """Each identifiability quantity's estimate and truth per trial, from the fit file's arrays (not its
    identifiability group): the constants, traces of Q blocks and R, the truth's parameters, q_std, sigma."""
    g = f[f"fit/{model}"]
    ig = g["identifiability"]
    names = [x.decode() if isinstance(x, bytes) else x for x in g.attrs["names"]]
    qs = [x.decode() if isinstance(x, bytes) else x for x in ig.attrs["quantities"]]
    same = model == (f.attrs["model"].decode() if isinstance(f.attrs["model"], bytes) else f.attrs["model"])
    q_std = f["truth/q_std"][()]
    N = g["Q"].shape[0]
    est, tru = np.full((N, len(qs)), np.nan), np.full((N, len(qs)), np.nan)
    for k, q in enumerate(qs):
        if not q.startswith("tr("):
            est[:, k] = g[f"constant/{q}"][()]
            tru[:, k] = f[f"truth/params/{q}"][()] if same else np.nan
        elif q.startswith("tr(Q_"):
            idx = [i for i, s in enumerate(names) if s[:-1] == q[5:-1] and s[-1] in "xyz"]
            est[:, k] = np.trace(g["Q"][()][:, idx][:, :, idx], axis1=-2, axis2=-1)
            tru[:, k] = (q_std[idx] ** 2).sum() if same else np.nan
        else:
            ch = q[5:-1]
            est[:, k] = np.trace(g[f"R/{ch}"][()], axis1=-2, axis2=-1)
            tru[:, k] = g[f"R/{ch}"].shape[-1] * np.mean(f[f"truth/sigma/{ch}"][()] ** 2)
    return qs, est, tru


def test_seed004_recovery_check_agrees_with_the_verdicts(seed004_fit):
    """The study's own recovery check, recomputed here from the fit file's estimates and the truth it
    simulated: a group and quantity whose mean misses the truth by more than 2 standard errors of that
    mean reads "biased", and no other; the fit file's z is this one."""
    with h5py.File(seed004_fit) as f:
        for model in ("mnm", "binm"):
            ig = f[f"fit/{model}/identifiability"]
            qs, est, tru = _truths_and_estimates(f, model)
            np.testing.assert_allclose(ig["estimate"][()], est, rtol=1e-9)
            se, used, group = ig["se"][()], ig["used"][()], ig["group"][()]
            np.testing.assert_array_equal(group, f["truth/param_case"][()])
            verdict = ig["group_verdict"][()].astype(str)
            checked = 0
            for gi in np.unique(group):
                sel = used & (group == gi)
                n = sel.sum()
                for k, q in enumerate(qs):
                    e = est[sel, k] - tru[sel, k]
                    if not np.isfinite(e).all():
                        assert verdict[gi, k] != "biased"
                        continue
                    sem = max(e.std(ddof=1) / np.sqrt(n), np.sqrt((se[sel, k] ** 2).sum()) / n)
                    z = e.mean() / sem
                    np.testing.assert_allclose(ig["group_z"][()][gi, k], z, rtol=1e-9)
                    assert (verdict[gi, k] == "biased") == (abs(z) > 2.0), (model, q, gi, z, verdict[gi, k])
                    checked += 1
            assert checked >= (10 if model == "mnm" else 4)


def test_fit_file_records_groups_and_per_trial_verdicts(seed004_fit):
    from needlecli.io.fit import read_fit
    from needlecli.reports.identify import identifiability_table

    with h5py.File(seed004_fit) as f:
        ig = f["fit/mnm/identifiability"]
        d = len(ig.attrs["quantities"])
        assert [x.decode() if isinstance(x, bytes) else x for x in ig.attrs["group_labels"]] == ["10 mT", "19 mT", "28 mT"]
        assert ig["verdict"].shape == (6, d) and ig["group_verdict"].shape == (3, d) and ig["z"].shape == (6, d)
        assert list(ig["group_trials"][()]) == [4, 2, 0]
        assert np.isfinite(ig["truth"][()]).all()  # every quantity of the truth's own model has a truth
    df = identifiability_table(read_fit(seed004_fit)).set_index(["Model", "Quantity", "Group"])
    assert df.loc[("mnm", "c", "10 mT"), "Per trial"] == "identified 4/4"
    assert df.loc[("mnm", "c", "19 mT"), "Trials"] == 2


def test_identifiability_table_from_the_command_line(seed004_fit, tmp_path):
    from typer.testing import CliRunner

    from needlecli.cli.app import app

    r = CliRunner().invoke(app, ["evaluate", str(seed004_fit), "--tables", "identifiability", "--no-plots",
                                 "--out", str(tmp_path)])
    assert r.exit_code == 0, r.output
    assert "tr(Q_h)" in r.output and "10 mT" in r.output
    assert (tmp_path / "em-magnetic-pratt2022_study_identifiability.tex").exists()


def test_a_fit_file_with_malformed_group_verdicts_is_refused(seed004_fit, tmp_path):
    """The identifiability group's additions are checked by the fit file's layout when it is opened."""
    import shutil

    from needlecli.errors import DataError
    from needlecli.io.fit import read_fit

    bad = tmp_path / "bad.h5"
    shutil.copy(seed004_fit, bad)
    with h5py.File(bad, "a") as f:
        ig = f["fit/mnm/identifiability"]
        del ig["group_verdict"]
        ig["group_verdict"] = np.array([["identified"]] * 2).astype("S")  # 2 groups of 1 for 3 labels, 6 quantities
    with pytest.raises(DataError, match=r"\[/fit/mnm/identifiability/group_verdict\] has shape \(2, 1\)"):
        read_fit(bad)
