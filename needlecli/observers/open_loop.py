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
    STATUS_SINGULAR,
    EstimationProblem,
    FitTakes,
    Observer,
    ObserverSettings,
    Posterior,
)
from needlecli.observers.defaults import INIT_ANGLE_STD
from needlecli.observers.record import RunRecorder
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
    model_only = True  # the reference every filter must beat (needle compare warns when one does not)
    fit_takes = FitTakes(measurements=False, sensor_states=False)

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
        rec = RunRecorder(problem, n, progress=progress)
        rec.record(0, x, P)
        with np.errstate(all="ignore"):
            for k in range(T - 1):
                u = problem.inputs[:, k]
                dt = float(dt_all[k])
                step = lambda xx, u=u, dt=dt: model.step(xx, u[:, None, :], params, dt)
                F = complex_step_jacobian(step, x)
                xn = model.step(x, u, params, dt)
                P = F @ P @ np.swapaxes(F, -1, -2) + np.diag(qd * dt)
                P = 0.5 * (P + np.swapaxes(P, -1, -2))
                # the model's domain first (a non-finite state counts as outside it)
                new = rec.stop(k + 1, model.left_domain(x, xn, params), STATUS_SINGULAR, model.singular_reason)
                new |= rec.stop(k + 1, ~np.isfinite(xn).all(-1), STATUS_DIVERGED, "non-finite estimate at t = {t:.3f} s")
                if new.any():  # the stopped runs keep this step's start (P goes on)
                    xn = rec.hold(xn, x)
                x = xn
                rec.record(k + 1, x, P)
        return rec.posterior(model.state_names, model.state_units, angle_states=model.angle_states)
