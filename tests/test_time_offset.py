"""Temporal calibration: EM estimates a stream's clock offset (``measurements.<c>.time_offset``, a constant
sensor state; needlecli.fitting.statespace.MeasurementModel: h of the state delta earlier). Insertions
whose speed varies (a constant speed makes the offset a constant shift along the needle, the start's),
measured 0.5 s late by a clock that says otherwise."""

from __future__ import annotations

import numpy as np

from needlecli.fitting.em import EMOptions, fit_em
from needlecli.fitting.statespace import DiscreteModel, MeasurementModel
from needlecli.models import MODELS


def test_em_finds_the_clock_offset_of_a_stream():
    rng = np.random.default_rng(11)
    model = MODELS.get("unicycle")(MODELS.get("unicycle").Params(kappa=0.01))
    p = model.param_arrays()
    N, fine, per, K, lag = 3, 0.05, 5, 240, 10  # 0.25 s ticks, 60 s; the samples 10 fine steps = 0.5 s old
    t_fine = np.arange(K * per + 1) * fine
    v = 1.5 + 1.2 * np.sin(2 * np.pi * t_fine / 15.0)  # mm/s, 0.3-2.7
    v_tick = v[:: per][:K + 1]
    x = np.zeros((N, 6))
    x[:, 5] = rng.uniform(-np.pi, np.pi, N)
    pos = [x[:, :3]]
    for j in range(K * per):  # the speed held over each tick as the filter's inputs hold it
        u = np.stack([np.full(N, v_tick[j // per]), np.zeros(N)], -1)
        x = model.step(x, u, p, fine)
        pos.append(x[:, :3])
    pos = np.stack(pos, 1)  # (N, K per + 1, 3)
    idx = np.maximum(np.arange(K + 1) * per - lag, 0)
    y = pos[:, idx] + 0.1 * rng.standard_normal((N, K + 1, 3))
    inputs = np.zeros((N, K + 1, 2))
    inputs[..., 0] = v_tick
    ticks = np.arange(K + 1)
    dm = DiscreteModel(model, {"kappa": np.asarray(0.01)}, (), fine * per, ticks, inputs, substeps=per,
                       sensor_states=[("us_delay", "s", 0.0)])
    d = dm.names.index("us_delay")
    valid = np.ones((N, K + 1), dtype=bool)
    valid[:, :3] = False  # before the needle has moved the 0.5 s: the clamp above
    mm = MeasurementModel("us", lambda x_: x_[..., :3], model.n, np.arange(K + 1), y, valid, np.zeros(3, bool),
                          ("x", "y", "z"), ("mm",) * 3, delay_index=d, inputs=inputs, drift=dm.drift)
    m0 = np.zeros((N, dm.n))  # the start: the entry known to 0.5 mm, the insertion direction, the roll
    m0[:, :3] = pos[:, 0]
    m0[:, 5] = x[:, 5]  # (constant without rotation, as a robot's encoder gives it); the offset's guess 0
    P0 = np.diag([0.25, 0.25, 0.25, 1e-4, 1e-4, 1e-6, 1.0])
    Q0 = np.diag([0.0, 0.0, 0.0, 1e-8, 1e-8, 1e-8, 0.0])
    opts = EMOptions(max_iter=60, tol=1e-4, estep_max=3, q_index=(3, 4, 5), q_hold=(3, 4, 5))
    res = fit_em(dm, [mm], m0, P0, Q0, [np.eye(3) * 0.04], opts)
    delta = res.x0[:, d]
    np.testing.assert_allclose(delta, 0.5, atol=0.05)
