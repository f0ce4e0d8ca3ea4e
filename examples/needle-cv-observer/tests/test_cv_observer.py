"""The constant-velocity Kalman filter against an independent reference: with no process noise and a
(nearly) diffuse prior, the Kalman filter's estimate after the last sample is the weighted least-squares
line through the samples (np.polyfit), position and velocity; and a sample is never used before it is
available."""

from __future__ import annotations

import numpy as np

from needle_cv_observer import ConstantVelocityKF, CVSettings
from needlecli.models import MODELS
from needlecli.problem import Channel, EstimationProblem


def _problem(values, t, latency=0.0, dt=0.01, T=None):
    model = MODELS.get("unicycle")(MODELS.get("unicycle").Params(kappa=0.0))
    T = T or int(round(t[-1] / dt)) + 50
    time = np.arange(T) * dt
    N, M, A = values.shape
    ch = Channel(name="cam", sensor_type="position", t=t, t_available=t + latency,
                 index=np.searchsorted(time, t - 1e-12), value=values, valid=np.ones((N, M), bool),
                 names=("x", "y", "z")[:A], units=("mm",) * A, sigma=np.full(A, 0.5), angle=np.zeros(A, bool), h=None)
    return EstimationProblem(time=time, inputs=np.zeros((N, T, 2)), input_names=("v", "u"), depth=np.zeros((N, T)),
                             channels={"cam": ch}, model=model, params=model.param_arrays(), interfaces=np.zeros(0))


def test_equals_least_squares_line():
    rng = np.random.default_rng(3)
    t = np.arange(0.0, 5.0, 0.2)
    N = 4
    p0, v = rng.normal(size=(N, 1, 3)), rng.normal(size=(N, 1, 3))
    y = p0 + v * t[None, :, None] + 0.5 * rng.standard_normal((N, len(t), 3))
    prob = _problem(y, t)
    obs = ConstantVelocityKF(CVSettings(type="cv_kf", measurement="cam", q=0.0, p0_position=1e10, p0_velocity=1e10))
    post = obs.run(prob, np.random.default_rng(0))
    k = int(np.searchsorted(prob.time, t[-1] - 1e-12))  # the tick of the last sample
    for run in range(N):
        for a in range(3):
            slope, intercept = np.polyfit(t, y[run, :, a], 1)
            assert abs(post.state[run, k, a] - (intercept + slope * prob.time[k])) < 1e-5
            assert abs(post.state[run, k, 3 + a] - slope) < 1e-5
    assert post.names == ("x", "y", "z", "v_x", "v_y", "v_z")


def test_no_sample_before_it_is_available():
    t = np.array([0.0, 1.0, 2.0])
    y = np.array([[[0.0], [10.0], [10.0]]])
    obs = ConstantVelocityKF(CVSettings(type="cv_kf", measurement="cam", q=0.0))
    post = obs.run(_problem(y, t, latency=0.5), np.random.default_rng(0))
    k_avail = int(np.searchsorted(post.state[0, :, 0] != 0.0, True))  # first tick whose estimate moved
    assert abs(k_avail * 0.01 - 1.5) < 0.011  # the sample taken at 1 s acts from 1.5 s, not before
