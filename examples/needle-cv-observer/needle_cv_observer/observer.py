r"""A constant-velocity Kalman filter on the tip position, registered as needlecli observer ``cv_kf``.

Each measured axis ``a`` of a position channel is a 2-state linear system, position and velocity:

.. math::

    x_{k+1} = F x_k + w_k, \quad F = \begin{pmatrix} 1 & \Delta t \\ 0 & 1 \end{pmatrix}, \quad
    Q = q^2 \begin{pmatrix} \Delta t^3/3 & \Delta t^2/2 \\ \Delta t^2/2 & \Delta t \end{pmatrix},
    \qquad y_j = p_a(t_j) + v_j, \; v_j \sim N(0, \sigma_a^2),

(white acceleration of spectral density ``q^2``). The axes are independent (a diagonal ``R``), so the
filter runs on arrays ``(runs, axes, 2)``: one loop over time, none over runs. A sample is used at the
first tick of the problem's time grid at or after it is available (acquisition time plus latency), never
earlier.
"""

from __future__ import annotations

from typing import Literal

import numpy as np
from pydantic import Field

from needlecli.observers import OBSERVERS, EstimationProblem, Observer, ObserverSettings, Posterior
from needlecli.observers.base import STATUS_OK, cov_steps, shrink_cov
from needlecli.schema import NonNeg, Positive

_AXES = ("x", "y", "z")


class CVSettings(ObserverSettings):
    """Settings of the constant-velocity Kalman filter (``type: cv_kf``)."""

    type: Literal["cv_kf"]
    measurement: str = Field(description="position sensor (channel) whose samples are filtered")
    q: NonNeg = Field(0.1, description="std of the white acceleration, length unit / s^(3/2)")
    sigma: Positive | None = Field(None, description="measurement noise std (default: the sensor's nominal sigma)")
    p0_position: Positive = Field(1.0, description="initial position variance, length unit^2 (the prior's mean: the "
                                  "first valid sample, which is then filtered like every other)")
    p0_velocity: Positive = Field(4.0, description="initial velocity variance, (length unit / s)^2 (start: 0)")


@OBSERVERS.register("cv_kf")
class ConstantVelocityKF(Observer):
    """Constant-velocity Kalman filter on each measured axis of one position channel."""

    Settings = CVSettings

    @classmethod
    def check(cls, settings, model, sensors):
        s = sensors.get(settings.measurement)
        if s is None:
            return [(("measurement",), f"no sensor named {settings.measurement!r}; sensors: {', '.join(sensors) or 'none'}")]
        if s.registered_name != "position":
            return [(("measurement",), f"sensor {settings.measurement!r} is a {s.registered_name} sensor, not a position sensor")]
        if len(model.translation_states) != 3:
            return [(("measurement",), f"model {model.registered_name!r} has no tip position states")]
        return []

    def run(self, problem: EstimationProblem, rng: np.random.Generator, progress=None) -> Posterior:
        s = self.settings
        ch = problem.channels[s.measurement]
        axes = [_AXES.index(a) for a in ch.names]
        pos_names = [problem.model.translation_states[a] for a in axes]
        unit = problem.model.length_unit
        N, T, A = problem.n_runs, len(problem.time), len(axes)
        time = problem.time
        sigma = np.broadcast_to(np.asarray(s.sigma if s.sigma is not None else ch.sigma, dtype=float), (A,))
        r = sigma**2
        # the tick at which each sample becomes usable (its availability, on the grid)
        tick = np.searchsorted(time, np.asarray(ch.t_available) - 1e-12, side="left")
        first = np.argmax(ch.valid, axis=1)
        has = ch.valid.any(axis=1)
        x = np.zeros((N, A, 2))
        x[:, :, 0] = np.where(has[:, None], ch.value[np.arange(N), first], 0.0)
        P = np.zeros((N, A, 2, 2))
        P[..., 0, 0] = s.p0_position
        P[..., 1, 1] = s.p0_velocity
        keep = cov_steps(T, problem.cov_stride)
        states = np.empty((N, T, 2 * A))
        covs = [] if problem.cov_layout != "none" else None
        order = np.argsort(tick, kind="stable")
        j = 0
        for k in range(T):
            if k > 0:
                dt = float(time[k] - time[k - 1])
                F = np.array([[1.0, dt], [0.0, 1.0]])
                Q = s.q**2 * np.array([[dt**3 / 3, dt**2 / 2], [dt**2 / 2, dt]])
                x = x @ F.T
                P = F @ P @ F.T + Q
            while j < len(order) and tick[order[j]] <= k:
                m = order[j]
                j += 1
                ok = ch.valid[:, m]
                if not ok.any():
                    continue
                y = ch.value[:, m]  # (N, A)
                S = P[..., 0, 0] + r  # (N, A)
                K = P[..., :, 0] / S[..., None]  # (N, A, 2)
                nu = np.where(ok[:, None], y - x[..., 0], 0.0)
                x = x + K * nu[..., None]
                KH = K[..., :, None] * np.array([1.0, 0.0])  # K H, H = [1, 0]
                I_KH = np.eye(2) - KH
                Pn = I_KH @ P @ np.swapaxes(I_KH, -1, -2) + r[..., None, None] * K[..., :, None] * K[..., None, :]
                P = np.where(ok[:, None, None, None], Pn, P)  # Joseph form: symmetric, positive definite
            states[:, k] = np.concatenate([x[..., 0], x[..., 1]], axis=-1)
            if covs is not None and k in keep:
                full = np.zeros((N, 2 * A, 2 * A))
                for a in range(A):  # the axes' 2 x 2 blocks (a loop over at most 3 axes)
                    idx = np.array([a, A + a])
                    full[:, idx[:, None], idx[None, :]] = P[:, a]
                covs.append(shrink_cov(full, problem.cov_layout))
            if progress is not None and (k % max(1, T // 100) == 0 or k == T - 1):
                progress(k + 1, T)
        return Posterior(
            state=states,
            cov=np.stack(covs, 1) if covs is not None else None,
            status=np.full(N, STATUS_OK),
            reason=np.full(N, ""),
            names=tuple(pos_names) + tuple(f"v_{n}" for n in pos_names),
            units=(unit,) * A + (f"{unit}/s",) * A,
        )
