"""Open-loop prediction: the model driven by the known inputs from an initial estimate, no measurement.

The reference every observer must beat, and the simplest complete user of the observer contract. The
covariance is propagated as in an EKF prediction, ``P <- F P F^T + Q dt``, with ``F`` the Jacobian of
the RK4 step (complex step through the step, so it is exact to rounding).
"""

from __future__ import annotations

from typing import Literal

import numpy as np
from pydantic import Field

from needlecli.initial import InitialEstimate, check_initial, initial_mean, make_start, with_start_covariance
from needlecli.numerics import complex_step_jacobian
from needlecli.observers.base import (
    OBSERVERS,
    STATUS_DIVERGED,
    STATUS_OK,
    STATUS_SINGULAR,
    EstimationProblem,
    FitTakes,
    Observer,
    ObserverSettings,
    Posterior,
    cov_steps,
    shrink_cov,
)
from needlecli.observers.defaults import INIT_ANGLE_STD
from needlecli.schema import NonNeg


class OpenLoopInit(InitialEstimate):
    """Initial estimate (:class:`~needlecli.initial.InitialEstimate`); ``P0`` is ``diag(std^2)`` plus
    ``p0_floor``."""

    p0_floor: NonNeg = Field(1e-12, description="added to every initial variance")


class OpenLoopSettings(ObserverSettings):
    type: Literal["open_loop"]
    init: OpenLoopInit = Field(default_factory=OpenLoopInit, description="initial estimate (needlecli.initial)")
    params: dict[str, float] = Field(default_factory=dict, description="the observer's own model parameters")
    q: dict[str, NonNeg] = Field(default_factory=dict, description="process noise std per state, unit/sqrt(s)")


@OBSERVERS.register("open_loop")
class OpenLoop(Observer):
    Settings = OpenLoopSettings
    takes_common_start = True
    fit_takes = FitTakes(q="per_root_second", measurements=False, sensor_states=False)

    @classmethod
    def derived_settings(cls, ctx):
        """The prediction from what is known before the insertion: the model's nominal initial state
        (nominal curvature, not the run's true one) with 5 deg std on the angle states."""
        return {"init": {"from": "nominal", "std": {a: INIT_ANGLE_STD for a in ctx.model.angle_states}}}

    @staticmethod
    def _params(problem, settings) -> dict:
        params = {k: np.asarray(v, dtype=float) for k, v in problem.params.items()}
        params.update({k: np.asarray(v, dtype=float) for k, v in settings.params.items()})
        return params

    @staticmethod
    def _p0(settings, model, start=None) -> np.ndarray:
        std = np.array([settings.init.std.get(k, 0.0) for k in model.state_names])
        return with_start_covariance(np.diag(std**2 + settings.init.p0_floor), model.state_names, start)

    @classmethod
    def initial_estimate(cls, settings, problem, rng):
        model = problem.model
        return make_start(settings.init, problem, model, cls._params(problem, settings), rng,
                          cls._p0(settings, model), settings.name or settings.type)

    @classmethod
    def check(cls, settings, model, sensors):
        out = [(("init", *loc), msg) for loc, msg in check_initial(settings.init, model.state_names, model.registered_name, sensors)]
        for k in settings.q:
            if k not in model.state_names:
                out.append((("q", k), f"model {model.registered_name!r} has no state {k!r}"))
        for k in settings.params:
            if k not in model.Params.model_fields:
                out.append((("params", k), f"model {model.registered_name!r} has no parameter {k!r}"))
        return out

    def run(self, problem: EstimationProblem, rng: np.random.Generator, progress=None) -> Posterior:
        model = problem.model
        s = self.settings
        n_runs, T, n = problem.n_runs, len(problem.time), model.n
        params = self._params(problem, s)
        x = initial_mean(s.init, problem, model, params, rng)
        P = np.broadcast_to(self._p0(s, model, problem.start), (n_runs, n, n)).copy()
        dt_all = np.diff(problem.time)
        qd = np.array([s.q.get(k, 0.0) for k in model.state_names]) ** 2

        keep = cov_steps(T, problem.cov_stride)
        states = np.empty((n_runs, T, n))
        covs = [] if problem.cov_layout != "none" else None
        states[:, 0] = x
        status = np.full(n_runs, STATUS_OK, dtype=object)
        reason = np.full(n_runs, "", dtype=object)
        alive = np.ones(n_runs, dtype=bool)
        if covs is not None and 0 in keep:
            covs.append(shrink_cov(P, problem.cov_layout))
        every = max(1, (T - 1) // 100)
        with np.errstate(all="ignore"):
            for k in range(T - 1):
                u = problem.inputs[:, k]
                dt = float(dt_all[k])
                step = lambda xx, u=u, dt=dt: model.step(xx, u[:, None, :], params, dt)
                F = complex_step_jacobian(step, x)
                xn = model.step(x, u, params, dt)
                P = F @ P @ np.swapaxes(F, -1, -2) + np.diag(qd * dt)
                P = 0.5 * (P + np.swapaxes(P, -1, -2))
                sing = model.left_domain(x, xn, params)
                bad = alive & (sing | ~np.isfinite(xn).all(-1))
                if bad.any():
                    status[bad & sing] = STATUS_SINGULAR
                    reason[bad & sing] = model.singular_reason
                    status[bad & ~sing] = STATUS_DIVERGED
                    reason[bad & ~sing] = f"non-finite estimate at t = {problem.time[k + 1]:.3f} s"
                    alive &= ~bad
                    xn = np.where(alive[:, None], xn, x)
                x = xn
                states[:, k + 1] = x
                if covs is not None and (k + 1) in keep:
                    covs.append(shrink_cov(P, problem.cov_layout))
                if progress is not None and (k % every == 0 or k == T - 2):
                    progress(k + 1, T - 1)
        cov = np.stack(covs, 1) if covs is not None else None
        return Posterior(
            state=states,
            cov=cov,
            status=status.astype(str),
            reason=reason.astype(str),
            names=model.state_names,
            units=model.state_units,
            angle_states=model.angle_states,
        )
