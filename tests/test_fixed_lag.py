"""The fixed-lag smoother (needlecli.fitting.smoother.fixed_lag, observer ``fixed_lag``): each estimate from
every sample up to ``lag`` s after its time. Checked against a textbook Kalman filter and RTS smoother
written here, run on the data cut at the end of each estimate's window."""

from __future__ import annotations

import numpy as np

from needlecli.fitting.smoother import fixed_lag
from needlecli.numerics.kalman import ForwardResult


def _kalman(y, A, Q, H, R, m0, P0):
    """Textbook Kalman filter, one run: predicted and filtered means and covariances ``(K+1, n)``, ``(K+1, n, n)``."""
    K1, n = len(y), len(m0)
    mp, Pp, mf, Pf = np.zeros((K1, n)), np.zeros((K1, n, n)), np.zeros((K1, n)), np.zeros((K1, n, n))
    m, P = m0, P0
    for k in range(K1):
        if k > 0:
            m, P = A @ m, A @ P @ A.T + Q
        mp[k], Pp[k] = m, P
        S = H @ P @ H.T + R
        Kg = P @ H.T @ np.linalg.inv(S)
        m, P = m + Kg @ (y[k] - H @ m), P - Kg @ S @ Kg.T
        mf[k], Pf[k] = m, P
    return mp, Pp, mf, Pf


def _rts(mp, Pp, mf, Pf, A):
    """Textbook RTS smoother over every tick given: smoothed means ``(K+1, n)``."""
    ms, Ps = mf.copy(), Pf.copy()
    for k in range(len(mf) - 2, -1, -1):
        G = Pf[k] @ A.T @ np.linalg.inv(Pp[k + 1])
        ms[k] = mf[k] + G @ (ms[k + 1] - mp[k + 1])
        Ps[k] = Pf[k] + G @ (Ps[k + 1] - Pp[k + 1]) @ G.T
    return ms, Ps


def test_fixed_lag_is_the_rts_smoother_of_the_data_up_to_the_lag():
    rng = np.random.default_rng(7)
    dt, K1, N = 0.2, 40, 3
    A = np.array([[1.0, dt], [0.0, 1.0]])
    Q = np.diag([1e-3, 1e-2])
    H = np.array([[1.0, 0.0]])
    R = np.array([[0.04]])
    times = np.arange(K1) * dt
    runs = []
    for _ in range(N):
        x, ys = np.zeros(2), []
        for _k in range(K1):
            x = A @ x + rng.multivariate_normal(np.zeros(2), Q)
            ys.append(H @ x + rng.normal(0.0, 0.2, 1))
        runs.append(_kalman(np.array(ys), A, Q, H, R, np.zeros(2), np.eye(2)))
    mp, Pp, mf, Pf = (np.stack([r[i] for r in runs]) for i in range(4))
    fwd = ForwardResult(m_pred=mp, P_pred=Pp, m_filt=mf, P_filt=Pf, A=np.broadcast_to(A, (N, K1 - 1, 2, 2)).copy(),
                        loglik=np.zeros(N), repairs=np.zeros(N, dtype=np.int64))
    lag = 1.0  # 5 ticks
    got = fixed_lag(fwd, times, lag, kernels="numpy")
    for i in range(N):
        for k in range(K1):
            e = min(k + 5, K1 - 1)
            ms, Ps = _rts(mp[i, : e + 1], Pp[i, : e + 1], mf[i, : e + 1], Pf[i, : e + 1], A)
            np.testing.assert_allclose(got.m[i, k], ms[k], atol=1e-10)
            np.testing.assert_allclose(got.P[i, k], Ps[k], atol=1e-10)
    np.testing.assert_allclose(fixed_lag(fwd, times, 0.0, kernels="numpy").m, mf, atol=1e-12)
    whole = [_rts(mp[i], Pp[i], mf[i], Pf[i], A)[0] for i in range(N)]
    np.testing.assert_allclose(fixed_lag(fwd, times, 100.0, kernels="numpy").m, np.stack(whole), atol=1e-10)


def test_the_fixed_lag_observer_is_offline():
    from needlecli.observers import OBSERVERS

    cls = OBSERVERS.get("rts_fixed_lag")
    assert cls.causal is False
    assert cls.Settings.model_validate({"type": "rts_fixed_lag", "lag": 0.5}).lag == 0.5


def test_tables_mark_the_estimates_that_saw_the_future():
    """The recorded-data tables name a smoother's estimates (offline), with the fixed-lag smoother's lag, from
    the attributes the Kalman observers write (``smoother``; the fixed-lag smoother's ``causal``, ``lag``)."""
    from needlecli.io.results import Group
    from needlecli.observers import OBSERVERS
    from needlecli.reports.tables import offline_label

    cls = OBSERVERS.get("rts_fixed_lag")
    obs = cls(cls.Settings.model_validate({"type": "rts_fixed_lag", "name": "lag", "lag": 2.0}))
    assert offline_label("lag", Group(attrs={"smoother": False, **obs._offline_attrs()})) == "lag (offline, 2 s ahead)"
    assert offline_label("eks", Group(attrs={"smoother": True})) == "eks (offline)"
    assert offline_label("ekf", Group(attrs={"smoother": False})) == "ekf"
    assert offline_label("ukf", Group(attrs={})) == "ukf"
