r"""Bootstrap particle filter (``pf``), batched over runs and particles, with the Rao-Blackwellised variant's
numerics (``rbpf``, :mod:`needlecli.observers.rbpf`).

Every run carries ``P`` weighted particles, ``X (N, P, n)``: particles are one more batch axis, as sigma
points are for the UKF. At each filter tick (the ticks and the multi-rate schedule of the UKF: the grid,
or every ``rate``-th step and the last one; the samples that became available since the last tick, the
latest valid one of each channel):

1. **predict**: every particle through the model (RK4 on the grid steps of the tick, the inputs held per
   step), then process noise ``w ~ N(0, diag(q^2) dt_tick)`` per tick (``q`` per square-root second, as
   every observer's); angles wrapped, the state brought back onto its manifold (``model.normalize``). A
   particle that left the model's domain (``model.left_domain``, e.g. the BiNM's ``h . B = 0``) or stopped
   being finite is dead: weight zero, its state held;
2. **update**: each sample multiplies the weights by its likelihood ``p(y | x_i)``: Gaussian
   (``R = diag(sigma^2)``, sigma grown with the measured distance where configured) or, per channel,
   Student-t with ``dof`` degrees of freedom (``likelihood: student_t``, heavy tails for ultrasound
   outliers); a one-sided channel (the image plane) by the probit ``Phi((s g(x) + margin) / sigma)`` (a
   hard bound at ``sigma = 0``). A chi-square gate (``gate``) tests the sample's normalised innovation
   ``nu^T S^-1 nu`` against the particle cloud's ``S = Cov_w(h(x_i)) + R``; a gated sample is not used.
   The same ``nu^T S^-1 nu`` of every used sample is kept (``nis/<channel>``) for the consistency tables;
3. **estimate**: the weighted mean (angles by their circular mean ``atan2(sum w sin, sum w cos)``; the
   model's ``normalize`` on it: a rotation's mean is brought back onto SO(3)) and the covariance about it,
   angle residuals wrapped;
4. **resample** (systematic) where the effective sample size ``ESS = 1 / sum w_i^2`` fell below
   ``resample_below * P``; optionally **jittered** (``roughening: h``): the resampled particle states
   ``x_i`` become ``x_bar + a (x_i - x_bar) + h L z_i``, ``a = sqrt(1 - h^2)``, ``L L^T`` the weighted
   covariance of the cloud before resampling, ``z_i`` standard normals -- the kernel smoothing of Liu
   and West (2001), which refreshes a cloud of copies where the process noise is too small to (the multi-rate UKF paper's
   orientation noise is 2e-5 rad per tick) while keeping its mean and covariance. Gordon, Salmond and
   Smith's roughening (a jitter proportional to the spread, added at every resampling) inflates the
   cloud instead: resampling at the roll encoder's 100 Hz, it made the multi-rate UKF paper's curvature and yaw diverge
   within seconds. Off by default: the filter is then the plain bootstrap filter, whose limit is the Bayes
   posterior of the model as configured.

Per tick the ESS (before resampling) and whether the run resampled are kept (``ess``, ``resampled``
``(N, K)`` at the grid steps ``ticks (K,)``), and the log-likelihood of each run's samples (``loglik``).

**Random numbers.** Every draw (the initial particles, the process noise, the resampling offset, the
roughening) comes from a counter-based generator keyed by one number drawn from the run's stream
(``rng``): a normal or uniform is a hash (SplitMix64's finaliser) of the key, the draw's purpose, the run,
the tick and the particle's component, so that the compiled kernel (:mod:`needlecli.kernels.pf`), which
computes the same hashes, receives the same random numbers as this numpy path without any array of them
being passed: same config and seed, same particles, on either path. Normals are Box-Muller pairs of two
53-bit uniforms.

**Rao-Blackwellised (marginalised) filter** (``marginal``): where the model's vector field does not depend
on its positions (``model.translation_states``: the unicycles, the magnetic models) and the position is
measured linearly (position channels that select those states), the position given a particle's
orientation trajectory and the inputs is linear-Gaussian: ``p_{k+1} = p_k + d_k(theta) + w_p``,
``y = H p + v``. The particles then carry the other states (orientation, curvature) and a Kalman filter
per particle carries the position: its mean ``p_i`` rides in the particle (the model moves it by the
particle's own displacement) and its covariance ``P_p`` is the same for every particle of a run (the same
``A = I``, ``Q_p``, ``H``, ``R``), so it is one ``(N, 3, 3)`` array. A position sample weighs a particle by
its marginal likelihood ``N(y; H p_i, H P_p H^T + R)`` and updates ``p_i`` and ``P_p`` by the Kalman gain;
the estimate's covariance is the mixture's, ``P_p`` plus the spread of the ``p_i``. The ultrasteer
project's marginalised filter on SO(3) works so.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
from pydantic import Field, model_validator

from needlecli.initial import InitialEstimate, initial_covariance, initial_mean, make_start
from needlecli.models import Model, StateSelection
from needlecli.numerics import sincos, wrap_angle
from needlecli.numerics.unscented import robust_cholesky, symmetrize
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
from needlecli.observers.ukf import UnscentedKalmanFilter, check_filter
from needlecli.schema import DistanceGrowth, NonNeg, Positive, Probability, Strict

# ---------------------------------------------------------------------------------------------- random numbers
#: what a draw is for (part of its hash): the initial particles, process noise, resampling, roughening
INIT, PROCESS, RESAMPLE, ROUGHEN = 0, 1, 2, 3
_GOLDEN = np.uint64(0x9E3779B97F4A7C15)
_M1 = np.uint64(0xBF58476D1CE4E5B9)
_M2 = np.uint64(0x94D049BB133111EB)
_TWO_53 = 2.0**-53


def _mix(z: np.ndarray) -> np.ndarray:
    """SplitMix64's finaliser on ``uint64`` arrays (wrapping arithmetic)."""
    z = (z ^ (z >> np.uint64(30))) * _M1
    z = (z ^ (z >> np.uint64(27))) * _M2
    return z ^ (z >> np.uint64(31))


def stream_base(key: int, purpose: int, runs: np.ndarray, tick: int) -> np.ndarray:
    """The hash ``(N,)`` (``uint64``) from which the draws of ``purpose`` at filter tick ``tick`` of each
    run in ``runs (N,)`` (their indices in the problem) are counted."""
    with np.errstate(over="ignore"):
        b = _mix(np.full(1, key, dtype=np.uint64) + _GOLDEN * np.uint64(purpose + 1))
        b = _mix(b + _GOLDEN * (np.asarray(runs, dtype=np.uint64) + np.uint64(1)))
        return _mix(b + _GOLDEN * np.uint64(tick + 1))


def uniforms(base: np.ndarray, count: int) -> np.ndarray:
    """``(N, count)`` uniforms in ``[0, 1)`` (53 bits): draw ``e`` of run ``r`` hashes ``base[r] + (e + 1) G``."""
    with np.errstate(over="ignore"):
        e = np.arange(1, count + 1, dtype=np.uint64)
        z = _mix(base[:, None] + _GOLDEN * e[None, :])
    return (z >> np.uint64(11)).astype(np.float64) * _TWO_53


def normals(base: np.ndarray, count: int) -> np.ndarray:
    """``(N, count)`` standard normals: Box-Muller on uniforms ``2j, 2j + 1`` gives draws ``2j`` (cos) and
    ``2j + 1`` (sin)."""
    pairs = (count + 1) // 2
    u = uniforms(base, 2 * pairs)
    rho = np.log1p(-u[:, 0::2])
    rho *= -2.0
    np.sqrt(rho, out=rho)
    s, c = sincos((2.0 * np.pi) * u[:, 1::2])
    out = np.empty((len(base), 2 * pairs))
    np.multiply(rho, c, out=out[:, 0::2])
    np.multiply(rho, s, out=out[:, 1::2])
    return out[:, :count]


# ---------------------------------------------------------------------------------------------- settings
class ParticleMeasurementSpec(Strict):
    """How the particle filter weighs one measurement channel (a sensor, by name)."""

    sigma: NonNeg | list[NonNeg] = Field(description="noise std (Student-t: scale) per component; a one-sided "
                                                     "channel (image_plane): the std of its bound (0: hard)")
    likelihood: Literal["gaussian", "student_t"] = Field(
        "gaussian", description="the sample's likelihood: gaussian, or student_t (multivariate t with scale "
                                "diag(sigma^2) and dof degrees of freedom: heavy tails for outliers)")
    dof: Positive = Field(4.0, description="likelihood: student_t: its degrees of freedom (small: heavy tails)")
    growth: DistanceGrowth | None = Field(None, description="sigma reset by distance to the transducer")
    gate: Probability | None = Field(None, description="chi-square gate probability on the cloud's innovation, "
                                                       "e.g. 0.999; off if unset")
    sides: list[Literal["past", "short"]] = Field(
        default_factory=lambda: ["past", "short"], min_length=1,
        description="a one-sided channel (image_plane): the samples used, past (needle seen) and/or short (lost)")
    margin: NonNeg = Field(0.0, description="a one-sided channel (image_plane): the bound moved by this much in "
                                           "the sample's favour, model length unit")

    @model_validator(mode="after")
    def _dof(self):
        if "dof" in self.model_fields_set and self.likelihood != "student_t":
            raise ValueError("dof is for likelihood: student_t")
        return self


class PFSettings(ObserverSettings):
    type: Literal["pf"]
    model: str | None = Field(None, description="the filter's model (default: the experiment's)")
    params: dict[str, float] = Field(default_factory=dict, description="the filter's model parameters")
    rate: Positive | None = Field(None, description="filter rate, Hz (default: the simulation grid's)")
    particles: int = Field(1000, ge=2, le=10_000_000, description="particles per run")
    resample_below: Probability = Field(0.5, description="systematic resampling when the effective sample "
                                                         "size falls below this fraction of the particles")
    roughening: Probability = Field(0.0, description="jitter after resampling, h of Liu and West's kernel "
                                                     "smoothing: x_bar + sqrt(1 - h^2) (x_i - x_bar) + h L z with L L^T "
                                                     "the cloud's covariance (mean and covariance kept), e.g. 0.1; 0: none")
    q: dict[str, NonNeg] = Field(default_factory=dict, description="process noise std per state, unit/sqrt(s)")
    p0: dict[str, NonNeg] = Field(default_factory=dict, description="initial variance per state (unit^2, not a std)")
    measurements: dict[str, ParticleMeasurementSpec] = Field(
        default_factory=dict, description="channels used, by sensor name, with their likelihood, noise, growth and "
                                          "gate (default: every channel the model can predict, Gaussian with the "
                                          "sensor's own sigma)")
    init: InitialEstimate = Field(default_factory=InitialEstimate, description="initial estimate (needlecli.initial): "
                                  "the particles are drawn from N(mean, P0)")
    max_cov_trace: Positive = Field(1e8, description="a run whose tr(P) exceeds this has diverged")


_DIVERGED = "non-finite or exploding covariance at t = {t:.2f} s"
_DEAD = "every particle left the model's domain or stopped being finite at t = {t:.2f} s"
_LOG_2PI = math.log(2.0 * math.pi)


def _singular(model: Model) -> str:
    return f"every particle left the model's domain: {model.singular_reason} (t = {{t:.2f}} s)"


def student_constant(dof: float, m: int) -> float:
    """``log Gamma((dof + m) / 2) - log Gamma(dof / 2) - m / 2 log(dof pi)``: the Student-t log-density's
    constant without its scale."""
    return math.lgamma(0.5 * (dof + m)) - math.lgamma(0.5 * dof) - 0.5 * m * math.log(dof * math.pi)


def unit_vector_states(h, model: Model) -> np.ndarray | None:
    """The states ``(3,)`` whose normalised vector ``h`` measures, where ``h`` is a sensor's measurement of a
    quantity the model declares a unit vector of states (:attr:`~needlecli.models.Model.unit_vectors`:
    the magnetic models' tangent and field direction); None otherwise."""
    sensor = getattr(h, "__self__", None)
    if sensor is None or getattr(h, "__name__", "") != "h" or not getattr(sensor, "unit_vector", False):
        return None
    req = tuple(getattr(sensor, "requires", ()))
    names = model.unit_vectors.get(req[0]) if len(req) == 1 else None
    if names is None or len(names) != 3 or getattr(sensor, "model", None) is None:
        return None
    return np.array([model.index(k) for k in names], dtype=np.int64)


@dataclass
class _Setup:
    """What the tick loop works with, set up once: the filter's model and parameters, its inputs ``(N, T,
    m)``, ticks ``(K,)``, grid step, channels and one-sided channels, the initial mean ``(N, n)`` and the
    factor ``B (n, k)`` that draws the ``k`` particle states (``x0 + B z``), the process noise std per tick
    ``q (n,)`` (the setting's ``q sqrt(dt_tick)``), the translation states kept by Kalman filters (``marg``, RBPF) with their initial
    covariance ``Pp0`` and noise ``Qp``, the key of the random numbers, the particles per run, the
    resampling threshold and roughening."""

    model: Model
    params: dict
    inputs: np.ndarray
    ticks: np.ndarray
    dt: float
    chans: list[dict]
    bounds: list[dict]
    x0: np.ndarray
    B0: np.ndarray
    drawn: np.ndarray
    q: np.ndarray
    marg: np.ndarray | None
    Pp0: np.ndarray | None
    Qp: np.ndarray | None
    key: int
    P: int
    below: float
    rough: float
    angles: np.ndarray = field(init=False)
    noisy: np.ndarray = field(init=False)

    def __post_init__(self):
        self.angles = self.model.angle_mask
        part = np.ones(self.model.n, dtype=bool)
        if self.marg is not None:
            part[self.marg] = False
        self.noisy = np.nonzero(part & (self.q > 0))[0]


@OBSERVERS.register("pf")
class ParticleFilter(Observer):
    r"""Batched bootstrap particle filter (module docstring): particles propagated through the model with
    process noise, weighted by each sample's likelihood, systematic resampling below an effective sample
    size; the estimate the weighted mean (circular for angles) and covariance.

    .. math:: w_i \propto w_i\, p(y_k \mid x_i),\qquad \hat x = \sum_i w_i x_i,\qquad
        P = \sum_i w_i (x_i - \hat x)(x_i - \hat x)^T
    """

    Settings = PFSettings
    takes_common_start = True
    compiled_entry = ("pf", "run")  # the kernel that compiles longest (the warm-up's)
    fit_takes = FitTakes(measurements=True, sensor_states=False)
    #: particles for the positions (False) or Kalman filters per particle (True: the RBPF)
    marginal = False
    #: particles per run, and the jitter after resampling, of a comparison's derived settings
    COMPARE_PARTICLES = 500
    COMPARE_JITTER = 0.1

    @classmethod
    def derived_settings(cls, ctx):
        """The UKF's (:func:`~needlecli.observers.defaults.filter_settings`: the sensors' nominal sigmas
        with their growth, the start, ``q`` from the truth's process noise), Gaussian likelihoods,
        :attr:`COMPARE_PARTICLES` particles, Liu and West's jitter :attr:`COMPARE_JITTER` after resampling
        (the needle models' orientation noise per tick is too small to refresh a resampled cloud), no
        prediction (the filter has none)."""
        s = filter_settings(ctx)
        s.pop("predict_at_depths", None)
        return {"particles": cls.COMPARE_PARTICLES, "roughening": cls.COMPARE_JITTER, **s}

    @classmethod
    def upgrade_settings(cls, settings, *, config_format, dt):
        """As the UKF's (:meth:`UnscentedKalmanFilter.upgrade_settings`): config format 1 gave ``q`` per filter
        tick; it is now per square-root second."""
        return UnscentedKalmanFilter.upgrade_settings(settings, config_format=config_format, dt=dt)

    # ------------------------------------------------------------------ configuration checks
    #: the filter's own model (``model`` and ``params`` of the settings), chosen as the UKF's
    _model_cls = UnscentedKalmanFilter._model_cls
    _model = UnscentedKalmanFilter._model

    @classmethod
    def check(cls, settings, model, sensors):
        return check_filter(settings, model, sensors, channel=cls._check_likelihood)[0]

    @staticmethod
    def _check_likelihood(name, spec, sensor, own) -> list[tuple[tuple, str]]:
        """A one-sided channel's likelihood is the probit of its bound, not a setting."""
        if getattr(sensor, "inequality", False) and spec.likelihood != "gaussian":
            return [(("likelihood",), "a one-sided channel's likelihood is the probit of its bound")]
        return []

    @classmethod
    def initial_estimate(cls, settings, problem, rng):
        model = cls(settings)._model(problem)
        P0 = initial_covariance(settings.init, model.state_names, settings.p0, 1e-12)
        return make_start(settings.init, problem, model, model.param_arrays(), rng, P0, settings.name or settings.type)

    # ------------------------------------------------------------------ set-up
    def _channels(self, problem: EstimationProblem, model: Model) -> list[dict]:
        """The measurement channels used (as :meth:`UnscentedKalmanFilter._channels` chooses them), each with
        its likelihood and, for the compiled kernel, how ``h`` reads the state (``kind`` 0: a selection
        ``idx``; 1: the unit vector of states ``idx``; -1: neither). Marginal (RBPF) channels select
        translation states."""
        trans = {model.index(k) for k in model.translation_states}
        out = UnscentedKalmanFilter._channels(self, problem, model)
        for c in out:
            spec = self.settings.measurements.get(c["name"])
            h, m = c["h"], c["m"]
            if isinstance(h, StateSelection):
                kind, idx = 0, np.asarray(h.index, dtype=np.int64)
            else:
                uv = unit_vector_states(h, model)
                kind, idx = (1, uv) if uv is not None else (-1, np.zeros(m, dtype=np.int64))
            student = spec is not None and spec.likelihood == "student_t"
            c.update(kind=kind, idx=idx, marginal=self.marginal and kind == 0 and set(idx.tolist()) <= trans,
                     student=student, dof=float(spec.dof) if student else 0.0,
                     const=student_constant(float(spec.dof), m) if student else -0.5 * m * _LOG_2PI)
        return out

    def _bounds(self, problem: EstimationProblem, model: Model) -> list[dict]:
        return UnscentedKalmanFilter._bounds(self, problem, model)

    def _setup(self, problem: EstimationProblem, rng: np.random.Generator) -> _Setup:
        s = self.settings
        model = self._model(problem)
        params = model.param_arrays()
        n = model.n
        dt, stride, ticks = UnscentedKalmanFilter._ticks(self, problem.time)
        x0 = initial_mean(s.init, problem, model, params, rng)
        P0 = initial_covariance(s.init, model.state_names, s.p0, 1e-12, start=problem.start)
        q = np.array([s.q.get(k, 0.0) for k in model.state_names], dtype=float) * math.sqrt(stride * dt)  # per tick
        key = int(rng.integers(0, 2**63 - 1))
        marg = Pp0 = Qp = None
        if self.marginal:
            marg = np.array([model.index(k) for k in model.translation_states], dtype=np.int64)
            drawn = np.array([i for i in range(n) if i not in set(marg.tolist())], dtype=np.int64)
            # the positions given the drawn states: mean mu_p + G (theta - mu_theta), covariance P_pp - G P_theta_p
            Ptt = P0[np.ix_(drawn, drawn)]
            G = np.linalg.solve(Ptt, P0[np.ix_(drawn, marg)]).T
            Pp0 = symmetrize(P0[np.ix_(marg, marg)] - G @ P0[np.ix_(drawn, marg)])
            Qp = np.diag(q[marg] ** 2)
            root = robust_cholesky(Ptt[None])[0][0]
            B0 = np.zeros((n, len(drawn)))
            B0[drawn] = root
            B0[marg] = G @ root
        else:
            drawn = np.arange(n, dtype=np.int64)
            B0 = robust_cholesky(P0[None])[0][0]
        return _Setup(model=model, params=params, inputs=UnscentedKalmanFilter._inputs(problem, model), ticks=ticks,
                      dt=dt, chans=self._channels(problem, model), bounds=self._bounds(problem, model), x0=x0, B0=B0,
                      drawn=drawn, q=q, marg=marg, Pp0=Pp0, Qp=Qp, key=key, P=int(s.particles),
                      below=float(s.resample_below), rough=float(s.roughening))

    # ------------------------------------------------------------------ run
    def run(self, problem: EstimationProblem, rng: np.random.Generator, progress=None) -> Posterior:
        f = self._setup(problem, rng)
        from needlecli import kernels  # the compiled tick loop, where it covers this filter

        fast = kernels.twin("pf", problem.kernels) if f.model.compiled_equations else None
        if fast is not None:
            from needlecli.kernels import pf as compiled

            if compiled.supports(f.model, f.chans, f.bounds):
                return self._from_kernel(fast(f, problem, self.settings.max_cov_trace, progress), problem, f)
        return self._filter(problem, f, progress)

    def _filter(self, problem: EstimationProblem, f: _Setup, progress=None) -> Posterior:
        """The tick loop on numpy, every run and particle at once (the reference of the compiled kernel)."""
        s = self.settings
        model, params = f.model, f.params
        N, n, P, K = problem.n_runs, model.n, f.P, len(f.ticks)
        runs = np.arange(N, dtype=np.uint64)
        rec = RunRecorder(problem, n, progress=progress)
        counts = self._counts(rec, f.chans, f.bounds)
        schedule, bound_schedule = (UnscentedKalmanFilter._schedule(f.chans, f.ticks),
                                    UnscentedKalmanFilter._schedule(f.bounds, f.ticks))
        ess = np.full((N, K), float(P))
        resampled = np.zeros((N, K), dtype=bool)
        loglik = np.zeros(N)
        collapsed = rec.counter("weight_collapses")
        with np.errstate(all="ignore"):
            X = self._initial_particles(f, runs)
            logw = np.full((N, P), -math.log(P))
            Pp = None if f.marg is None else np.broadcast_to(f.Pp0, (N,) + f.Pp0.shape).copy()
            x, C = self._estimate(f, X, np.full((N, P), 1.0 / P), Pp)
            rec.record(0, x, C)
            for i in range(1, K):
                k0, k1 = f.ticks[i - 1], f.ticks[i]
                x_prev, C_prev, X_prev = x, C, X
                X = self._predict(f, X, k0, k1, runs, i)
                if Pp is not None:
                    Pp = Pp + f.Qp
                left = model.left_domain(X_prev, X, params)
                dead = left | ~np.isfinite(X).all(-1)
                if dead.any():
                    X = np.where(dead[..., None], X_prev, X)
                    logw = np.where(dead, -np.inf, logw)
                prior = _logsumexp(logw)  # (N,): the mass that survived
                gone = ~np.isfinite(prior)  # every particle dead
                rec.stop(k1, gone & (left & np.isfinite(X_prev).all(-1)).any(-1), STATUS_SINGULAR, _singular(model))
                rec.stop(k1, gone, STATUS_DIVERGED, _DEAD)
                logw = np.where(gone[:, None], -math.log(P), logw)
                prior = np.where(gone, 0.0, prior)
                w = np.exp(logw - prior[:, None])
                post, X, Pp = self._update(f, X, Pp, logw, w, schedule[i], bound_schedule[i], rec.alive, counts)
                total = _logsumexp(post)
                lost = ~np.isfinite(total)  # no particle agrees with a hard bound: the update is left out
                collapsed += lost & rec.alive
                logw = np.where(lost[:, None], logw, post)
                total = np.where(lost, prior, total)
                loglik += np.where(rec.alive, total - prior, 0.0)
                logw = logw - total[:, None]
                w = np.exp(logw)
                ess[:, i] = 1.0 / np.sum(w * w, axis=-1)
                x, C = self._estimate(f, X, w, Pp)
                rec.check(k1, x, C, max_trace=s.max_cov_trace, diverged_reason=_DIVERGED)
                x, C = rec.hold(x, x_prev), rec.hold(C, C_prev)
                rec.record(k1, x, C)
                due = (ess[:, i] < f.below * P) & rec.alive
                resampled[:, i] = due
                if due.any():
                    X, logw = self._resample(f, X, logw, w, x, C, due, runs, i)
        return self._posterior(rec, f, ess, resampled, loglik)

    def _initial_particles(self, f: _Setup, runs: np.ndarray) -> np.ndarray:
        """``x0 + B z`` per particle, ``z`` the ``k`` standard normals of each (``(N, P, n)``); angles wrapped,
        on the model's manifold."""
        N, k = len(runs), f.B0.shape[1]
        z = normals(stream_base(f.key, INIT, runs, 0), f.P * k).reshape(N, f.P, k)
        X = f.x0[:, None, :] + np.einsum("ij,npj->npi", f.B0, z)
        return f.model.normalize(_wrap_needed(X, f.angles))

    def _predict(self, f: _Setup, X: np.ndarray, k0: int, k1: int, runs: np.ndarray, tick: int) -> np.ndarray:
        """Particles ``(N, P, n)`` through the model over grid steps ``k0..k1``, then process noise of tick
        ``tick``, angles wrapped, the manifold restored."""
        for j in range(k0, k1):
            X = f.model.step(X, f.inputs[:, j, None, :], f.params, f.dt)
        if f.noisy.size:
            N, P = X.shape[:2]
            z = normals(stream_base(f.key, PROCESS, runs, tick), P * f.noisy.size).reshape(N, P, f.noisy.size)
            if f.noisy.size == X.shape[-1]:
                X = X + f.q * z
            else:
                X = X.copy()
                X[..., f.noisy] += f.q[f.noisy] * z
        return f.model.normalize(_wrap_needed(X, f.angles))

    def _update(self, f: _Setup, X, Pp, logw, w, arrived, bounds, alive, counts):
        """The log-weights ``(N, P)`` after the samples that arrived at this tick, and the particles and
        position covariances after the Kalman updates of marginal channels; channel by channel, in order
        (a marginal channel's likelihood and update use the positions as the channels before it left
        them); gates and NIS against the cloud of the predicted weights ``w (N, P)``."""
        N = X.shape[0]
        post = logw
        for c, samples in arrived:
            y = np.zeros((N, c["m"]))
            v = np.zeros(N, dtype=bool)
            jsel = np.zeros(N, dtype=np.int64)
            for j in samples:  # several samples of a channel in one tick: the latest valid one (as the UKF)
                vj = c["valid"][:, j] & alive
                y = np.where(vj[:, None], c["value"][:, j], y)
                jsel = np.where(vj, j, jsel)
                v |= vj
            if not v.any():
                continue
            r = np.broadcast_to(c["sigma"] ** 2, (N, c["m"])).copy()
            if c["growth"] is not None and c["pos_cols"]:
                fac = c["growth"].factor(y[:, c["pos_cols"]], axes=c["pos_axes"])
                r[:, c["pos_cols"]] *= (fac**2)[:, None]
            Hx = X[..., c["idx"]] if c["kind"] == 0 else c["h"](X)
            nu = y[:, None, :] - Hx
            if c["angle"].any():
                nu[..., c["angle"]] = _wrap_needed_values(nu[..., c["angle"]])
            nub = np.matmul(w[:, None, :], nu)[:, 0]
            du = nu - nub[:, None, :]
            S = np.matmul(np.swapaxes(du * w[..., None], 1, 2), du)
            if c["marginal"]:  # the Kalman filter's innovation covariance, shared by the particles of a run
                pi = _positions_in(f.marg, c["idx"])
                Sk = Pp[:, pi][:, :, pi] + _diag(r)
                S = S + Sk
                Sk_inv = np.linalg.inv(Sk)
                d2 = np.einsum("npi,npi->np", np.matmul(nu, Sk_inv), nu)
                ll = -0.5 * d2 - 0.5 * (c["m"] * _LOG_2PI + np.linalg.slogdet(Sk)[1])[:, None]
            else:
                S = S + _diag(r)
                d2 = np.matmul(nu * nu, (1.0 / r)[..., None])[..., 0]
                logdet = np.sum(np.log(r), axis=-1)
                if c["student"]:
                    ll = (c["const"] - 0.5 * logdet)[:, None] - 0.5 * (c["dof"] + c["m"]) * np.log1p(d2 / c["dof"])
                else:
                    ll = (c["const"] - 0.5 * logdet)[:, None] - 0.5 * d2
            nis = np.einsum("ni,ni->n", nub, np.linalg.solve(S, nub[..., None])[..., 0])
            on = v.copy()
            if c["gate"] is not None:
                out = on & ~(nis <= c["gate"])
                counts["gated"][c["name"]] += out
                on &= ~out
            counts["used"][c["name"]] += on
            counts["nis"][c["name"]][on, jsel[on]] = nis[on]
            post = post + np.where(on[:, None], ll, 0.0)
            if c["marginal"] and on.any():  # the Kalman update of the positions (from the predicted p_i)
                G = np.matmul(Pp[:, :, pi], Sk_inv) * on[:, None, None]  # (N, 3, m) gain
                X = X.copy()
                X[..., f.marg] += np.matmul(nu, np.swapaxes(G, 1, 2))
                Pp = symmetrize(Pp - np.matmul(G, np.swapaxes(Pp[:, :, pi], 1, 2)))
        for b, samples in bounds:  # one-sided channels: the probit of each sample's bound
            for j in samples:
                post = self._update_bound(X, post, w, b, j, alive, counts)
        return post, X, Pp

    @staticmethod
    def _update_bound(X, post, w, b, j, alive, counts):
        """``log Phi((side g(x) + margin) / sigma)`` of sample ``j`` of one-sided channel ``b`` on every
        particle (a hard bound at ``sigma = 0``: 0 or -inf), per run where valid and the side is used."""
        from scipy.special import log_ndtr

        v = b["valid"][:, j] & alive
        if not v.any():
            return post
        value = np.where(v[:, None], b["value"][:, j], 0.0)
        g, side = b["bound"](X, value[:, None, :])
        side = np.broadcast_to(side, g.shape)[:, 0]
        v = v & np.where(side > 0, b["past"], b["short"])
        z = side[:, None] * g + b["margin"]
        ll = log_ndtr(z / b["sigma"]) if b["sigma"] > 0 else np.where(z >= 0, 0.0, -np.inf)
        counts["used"][b["name"]] += v
        counts["violated"][b["name"]] += v & (np.einsum("np,np->n", w, z) < 0)
        return post + np.where(v[:, None], ll, 0.0)

    def _estimate(self, f: _Setup, X, w, Pp):
        """The weighted mean ``(N, n)`` (circular for angles, on the model's manifold) and the covariance
        about it ``(N, n, n)`` (angle residuals wrapped; RBPF: plus the positions' Kalman covariance)."""
        x = np.matmul(w[:, None, :], X)[:, 0]
        a = f.angles
        if a.any():
            sa, ca = sincos(X[..., a])
            x[:, a] = np.arctan2(np.matmul(w[:, None, :], sa)[:, 0], np.matmul(w[:, None, :], ca)[:, 0])
        x = f.model.normalize(x)
        d = X - x[:, None, :]
        if a.any():
            d[..., a] = _wrap_needed_values(d[..., a])
        C = np.matmul(np.swapaxes(d * w[..., None], 1, 2), d)
        if Pp is not None:
            C[:, f.marg[:, None], f.marg[None, :]] += Pp
        return x, symmetrize(C)

    def _resample(self, f: _Setup, X, logw, w, x, C, due, runs, tick):
        """Systematic resampling of the runs ``due (N,)``: particle ``i`` becomes the one whose cumulative
        weight interval holds ``(u + i) / P``, ``u`` one uniform per run; then roughening."""
        N, P, n = X.shape
        u = uniforms(stream_base(f.key, RESAMPLE, runs, tick), 1)  # (N, 1)
        c = np.cumsum(w, axis=-1)
        c[:, -1] = 1.0
        pos = (u + np.arange(P)) / P
        idx = _count_below(c, pos)
        idx = np.where(due[:, None], np.minimum(idx, P - 1), np.arange(P))
        X = np.take_along_axis(X, idx[..., None], axis=1)
        logw = np.where(due[:, None], -math.log(P), logw)
        if f.rough > 0:
            X = self._jitter(f, X, x, C, due, runs, tick)
        return X, logw

    def _jitter(self, f: _Setup, X, x, C, due, runs, tick):
        """Liu and West's kernel smoothing of the drawn states of the runs ``due``: ``x + a (X - x) + h L z``
        with ``a = sqrt(1 - h^2)``, ``L`` the lower Cholesky factor of their block of ``C (N, n, n)`` (the
        cloud's covariance before resampling), angle residuals wrapped."""
        N, P, n = X.shape
        h, dr = f.rough, f.drawn
        a = math.sqrt(1.0 - h * h)
        L = robust_cholesky(C[due][:, dr[:, None], dr[None, :]])[0]  # (D, k, k)
        z = normals(stream_base(f.key, ROUGHEN, runs[due], tick), P * dr.size).reshape(-1, P, dr.size)
        Xd = X[due]
        d = Xd[..., dr] - x[due][:, None, dr]
        ang = f.angles[dr]
        if ang.any():
            d[..., ang] = _wrap_needed_values(d[..., ang])
        Xd[..., dr] = x[due][:, None, dr] + a * d + h * np.matmul(z, np.swapaxes(L, 1, 2))
        X = X.copy()
        X[due] = f.model.normalize(_wrap_needed(Xd, f.angles))
        return X

    # ------------------------------------------------------------------ results
    @staticmethod
    def _counts(rec: RunRecorder, chans, bounds) -> dict:
        return {
            "used": {c["name"]: rec.counter(f"used/{c['name']}") for c in [*chans, *bounds]},
            "gated": {c["name"]: rec.counter(f"gated/{c['name']}") for c in chans},
            "nis": {c["name"]: rec.extras.setdefault(f"nis/{c['name']}", np.full(np.shape(c["valid"]), np.nan))
                    for c in chans},
            "violated": {b["name"]: rec.counter(f"bound_violated/{b['name']}") for b in bounds},
        }

    def _posterior(self, rec: RunRecorder, f: _Setup, ess, resampled, loglik) -> Posterior:
        s = self.settings
        model = f.model
        rec.extras.update({"ess": ess, "resampled": resampled, "ticks": np.asarray(f.ticks, dtype=np.int64),
                           "loglik": loglik})
        return rec.posterior(
            model.state_names, model.state_units, angle_states=model.angle_states,
            attrs={"model": model.registered_name, "particles": int(s.particles),
                   "resample_below": float(s.resample_below), "roughening": float(s.roughening),
                   "marginalised": [model.state_names[i] for i in (f.marg if f.marg is not None else [])],
                   "filter_rate": 1.0 / ((f.ticks[1] - f.ticks[0] if len(f.ticks) > 1 else 1) * f.dt)},
        )

    def _from_kernel(self, k: dict, problem: EstimationProblem, f: _Setup) -> Posterior:
        """The posterior from the compiled filter's arrays (status codes: 0 ok, 1 diverged, 2 singular, 3
        every particle dead)."""
        rec = RunRecorder(problem, f.model.n)
        rec.adopt(k["states"], k["cov"])
        at = np.maximum(k["event"], 0)
        rec.stop(at, k["status"] == 2, STATUS_SINGULAR, _singular(f.model))
        rec.stop(at, k["status"] == 3, STATUS_DIVERGED, _DEAD)
        rec.stop(at, k["status"] != 0, STATUS_DIVERGED, _DIVERGED)
        counts = self._counts(rec, f.chans, ())
        rec.counter("weight_collapses")[:] = 0
        for i, c in enumerate(f.chans):
            counts["used"][c["name"]][:] = k["used"][:, i]
            counts["gated"][c["name"]][:] = k["gated"][:, i]
            counts["nis"][c["name"]][:] = k["nis"][i]
        return self._posterior(rec, f, k["ess"], k["resampled"], k["loglik"])


# ---------------------------------------------------------------------------------------------- helpers
def _wrap_needed_values(a: np.ndarray) -> np.ndarray:
    """``a`` wrapped to ``[-pi, pi)`` where ``|a| >= pi`` (the identity inside, as the kernels do)."""
    return np.where(np.abs(a) < np.pi, a, wrap_angle(a))


def _wrap_needed(X: np.ndarray, angles: np.ndarray) -> np.ndarray:
    if not angles.any():
        return X
    X = X.copy()
    X[..., angles] = _wrap_needed_values(X[..., angles])
    return X


def _logsumexp(a: np.ndarray) -> np.ndarray:
    """``log sum exp`` over the last axis ``(N, P) -> (N,)``; -inf where every entry is -inf."""
    m = np.max(a, axis=-1)
    safe = np.where(np.isfinite(m), m, 0.0)
    return safe + np.log(np.sum(np.exp(a - safe[:, None]), axis=-1))


def _diag(r: np.ndarray) -> np.ndarray:
    """``(N, m)`` variances as diagonal matrices ``(N, m, m)``."""
    out = np.zeros(r.shape + r.shape[-1:])
    i = np.arange(r.shape[-1])
    out[:, i, i] = r
    return out


def _positions_in(marg: np.ndarray, idx: np.ndarray) -> np.ndarray:
    """Where the states ``idx`` are among the translation states ``marg``."""
    return np.array([int(np.nonzero(marg == i)[0][0]) for i in idx], dtype=np.int64)


def _count_below(c: np.ndarray, pos: np.ndarray) -> np.ndarray:
    """For each row, how many entries of the increasing ``c (N, P)`` are ``<= pos`` (increasing ``(N, P)``):
    a merge of the two, by a stable sort of their concatenation (``c`` first, so that a tie counts)."""
    N, P = c.shape
    order = np.argsort(np.concatenate([c, pos], axis=1), axis=1, kind="stable")
    from_c = order < P
    below = np.cumsum(from_c, axis=1)  # c entries up to each place
    return below[~from_c].reshape(N, P)
