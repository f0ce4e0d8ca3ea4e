r"""Extended Kalman filter (``ekf``) and extended Kalman smoother (``eks``, iterated on request), batched
over runs, with several measurement channels at their own rates (the magnetic needle EM paper, eq. 6).

The filter has a state at every *tick* (``ticks``: every grid step, the measurement times, or a rate
plus the measurement times); between ticks the model's RK4 steps carry the mean (and the exact Jacobian
of those steps carries the covariance), ``P <- A P A^T + Q_c dt``. Every sample describes the tick of
its acquisition time (these are batch estimators: latency does not delay them). A measured direction
(field, tangent) is used in the plane across it (2 components). Model constants named in ``augment``
become constant states, estimated with the rest (e.g. ``c`` of the MNM).

The ``eks`` runs the EKF and the Rauch-Tung-Striebel smoother on its linearisation; ``iterations > 1``
re-linearises around the smoothed trajectory (the iterated EKS), with ``update_x0`` also moving the prior
mean to the smoothed initial state (the magnetic needle EM paper, Algorithm 1). Estimates are reported on the results
file's time grid: at ticks as estimated, between ticks carried by the model from the previous tick.
"""

from __future__ import annotations

from typing import Literal

import numpy as np
from pydantic import Field

from needlecli.fitting.problem import build_system, check_setup, own_model
from needlecli.fitting.settings import KalmanSetup
from needlecli.fitting.smoother import ekf, eks, ieks
from needlecli.initial import InitialEstimate, describe
from needlecli.models import MODELS
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
from needlecli.observers.defaults import filter_settings
from needlecli.observers.record import RunRecorder
from needlecli.problem import CommonStart
from needlecli.schema import Positive


class EKFSettings(ObserverSettings, KalmanSetup):
    type: Literal["ekf"]
    augment: list[str] = Field(default_factory=list, description="model parameters estimated as constant states")
    init: InitialEstimate = Field(default_factory=InitialEstimate, description="initial estimate (needlecli.initial)")
    joseph: bool = Field(True, description="Joseph-form covariance update")
    max_cov_trace: Positive = Field(1e8, description="a run whose tr(P) exceeds this has diverged")


class EKSSettings(EKFSettings):
    type: Literal["eks"]  # type: ignore[assignment]
    iterations: int = Field(1, ge=1, le=1000, description="smoother passes: 1 the EKS, more the iterated EKS")
    update_x0: bool = Field(False, description="x0 <- x_0|N between passes (the magnetic needle EM paper)")
    tol: Positive = Field(1e-3, description="the iterated EKS stops when nothing moves by more than this many std")


class _Kalman(Observer):
    smoother = False
    takes_common_start = True
    fit_takes = FitTakes(measurements=True, sensor_states=True)

    @classmethod
    def derived_settings(cls, ctx):
        """Tuned as the UKF is (:func:`~needlecli.observers.defaults.filter_settings`): the same
        measurement sigmas with the same distance growth, the same process noise ``q`` (per square-root
        second), the same init and initial variances (which a common start replaces anyway)."""
        u = filter_settings(ctx)
        return {"q": u["q"], "p0": u["p0"], "init": u["init"],
                "measurements": {n: {k: m[k] for k in ("sigma", "growth") if k in m}
                                 for n, m in u["measurements"].items()}}

    @classmethod
    def check(cls, settings, model, sensors):
        if settings.model and settings.model not in MODELS:
            return [(("model",), f"unknown model {settings.model!r}; known: {', '.join(MODELS.names())}")]
        mcls = MODELS.get(settings.model) if settings.model else type(model)
        out = check_setup(settings, mcls, sensors, settings.augment)
        for k in mcls.input_names:
            if k not in model.input_names:
                out.append((("model",), f"the filter's model needs input {k!r}, which the experiment does not give"))
        return out

    @classmethod
    def initial_estimate(cls, settings, problem, rng):
        S = build_system(problem, settings, own_model(settings, problem.model), settings.augment, rng=rng)
        return CommonStart(names=S.names, mean=S.m0, cov=S.P0,
                           source=f"{settings.name or settings.type}'s initial estimate: {describe(settings.init, S.names)}")

    def run(self, problem: EstimationProblem, rng: np.random.Generator, progress=None) -> Posterior:
        s = self.settings
        model = own_model(s, problem.model)
        S = build_system(problem, s, model, s.augment, rng=rng)
        dm = S.dm
        N, n = problem.n_runs, dm.n
        Q = np.broadcast_to(S.Qc, (N, n, n))
        R = [np.broadcast_to(r, (N,) + r.shape) for r in S.R]
        extras: dict[str, np.ndarray] = {}
        with np.errstate(all="ignore"):  # compiled passes where they exist and problem.kernels asks (S.dm.kernels)
            if not self.smoother:
                fwd = ekf(dm, S.meas, S.m0, S.P0, Q, R, progress=progress)
                z, P, ll, rep = fwd.m_filt, fwd.P_filt, fwd.loglik, fwd.repairs
            elif s.iterations == 1:
                res = eks(dm, S.meas, S.m0, S.P0, Q, R, progress=progress)
                z, P, ll, rep = res.sm.m, res.sm.P, res.fwd.loglik, res.fwd.repairs + res.sm.repairs
            else:
                e = ieks(dm, S.meas, S.m0, S.P0, Q, R, max_iter=s.iterations, tol=s.tol, update_x0=s.update_x0,
                         joseph=s.joseph)
                res = e.result
                z, P, ll, rep = res.sm.m, res.sm.P, res.fwd.loglik, res.fwd.repairs + res.sm.repairs
                extras["iterations"] = e.iterations
                extras["settled"] = e.settled
                extras["x0"] = e.m0
        rec = RunRecorder(problem, n)
        first = rec.stop_first(dm.ticks, _events(dm, z, P, s.max_cov_trace))
        z, P = rec.hold_from(z, first), rec.hold_from(P, first)  # a stopped run holds its last good estimate
        rec.record_all(dm.ticks, P=P, state=dm.propagate_mean(z))  # the model carries the mean between ticks
        extras.update({"loglik": ll, "cholesky_repairs": rep, "ticks": dm.ticks})
        return rec.posterior(
            dm.names, dm.units, angle_states=tuple(a for a in model.angle_states), extras=extras,
            attrs={"model": model.registered_name, "ticks": str(s.ticks), "augment": list(s.augment),
                   "smoother": self.smoother},
        )


def _events(dm, z, P, max_trace) -> list[tuple[np.ndarray, str, str]]:
    """What stops a run at a tick, ``(N, K)`` masks in order of precedence: the estimate left the model's
    domain (singular), or it stopped being finite or its covariance exploded (diverged)."""
    N, K1, n = z.shape
    with np.errstate(all="ignore"):
        p = dm._p(z[:, 1:], 2)
        x = z[..., : dm.nx]
        sing = np.zeros((N, K1), dtype=bool)
        sing[:, 1:] = dm.model.left_domain(x[:, :-1], x[:, 1:], p)
        sing[:, 0] = dm.model.singular(x[:, 0], dm._p(z[:, 0], 1))
        tr = np.trace(P, axis1=-2, axis2=-1)
        bad_num = ~np.isfinite(z).all(-1) | ~np.isfinite(tr) | (tr > max_trace)
    return [(sing, STATUS_SINGULAR, f"{dm.model.singular_reason} (t = {{t:.2f}} s)"),
            (bad_num, STATUS_DIVERGED, "non-finite or exploding estimate at t = {t:.2f} s")]


@OBSERVERS.register("ekf")
class ExtendedKalmanFilter(_Kalman):
    """Batched multi-rate EKF: exact RK4 transition Jacobians, joint update with every sample of a tick."""

    Settings = EKFSettings


@OBSERVERS.register("eks")
class ExtendedKalmanSmoother(_Kalman):
    """EKF + RTS smoother (``iterations: 1``) or the iterated EKS (more), smoothed estimates per run."""

    Settings = EKSSettings
    smoother = True
    compiled_entry = ("kalman", "filter_smoother")  # the kernel that compiles longest (the warm-up's)
    causal = False
