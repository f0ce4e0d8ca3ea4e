"""Multi-rate unscented Kalman filter of the multi-rate UKF paper (sec. 2.3, appendix B), batched over runs.

Every Monte-Carlo run advances at once; sigma points are one more array axis. At each filter tick the
sigma points are propagated with the model (RK4 on the grid steps since the last tick, inputs held per
step), then updated with every measurement that became available in ``(t_{k-1}, t_k]``. Runs may differ
in what arrived: missing entries are masked out of the gain, which is the same as removing their rows
and columns (the matrices "sized to what arrived" of appendix B).

The multi-rate UKF paper's additions: measurement-noise reset by distance to the transducer
(``sigma = (1 + a d / d_max) sigma_c``, ``d`` from the measured tip), reset of ``P_kappa_kappa`` when the
tip crosses a tissue interface, the curvature constraint ``0 <= kappa <= kappa_max`` (else keep the
previous estimate), and final-position prediction from chosen observation depths. Optional chi-square
innovation gating rejects outliers per channel (counted per run).

One-sided channels (an ultrasound image plane, :mod:`needlecli.sensors.plane`: a seen needle has its tip
past the plane, a lost frame short of it) are inequalities, not measurements: named under
``measurements`` they update by the first two moments of the truncated (``sigma = 0``) or
probit-weighted Gaussian (:meth:`UnscentedKalmanFilter._update_bound`), one sample at a time after the
tick's ordinary update, on the numpy path (the compiled kernel does not take them); per run, the samples
used and those whose prediction broke the bound are counted (``used/<name>``, ``bound_violated/<name>``).

Exact shortcuts (each tested against the plain computation): a channel whose ``h`` is a state selection
(:class:`~needlecli.models.StateSelection`) is updated in closed form, which is what the unscented
transform of a linear ``h`` gives (one scalar state, the multi-rate UKF paper's 100 Hz roll, without a solve); the
square root of ``P`` is taken with the states the model's vector field depends on first, so that the
sigma points that move only the positions (``model.translation_states``) are displaced as the central
point instead of being propagated (9 of 15 points go through the model for the multi-rate UKF paper); and the translation
states of the sigma points are propagated relative to the central point's (increments of micrometres, not
positions of 80 mm), so that the rounding the alpha = 1e-3 weights (7e4) amplify into the mean stays at
1e-10 mm per tick instead of 1e-9 to 1e-8 (the model does not depend on them: the same points).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

import numpy as np
from pydantic import Field, model_validator

from needlecli.initial import InitialEstimate, check_initial, initial_covariance, initial_mean, make_start
from needlecli.models import MODELS, Model, StateSelection
from needlecli.numerics import wrap_angle
from needlecli.numerics.needle_frame import AXES, block_noise, needle_basis, reference_axis, world_covariance
from needlecli.numerics.unscented import (
    MerweWeights,
    angle_selection,
    mean_and_residuals,
    residual,
    robust_cholesky,
    sigma_points,
    symmetrize,
    weighted_cov,
    weighted_mean,
    wrap_where_needed,
)
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
from needlecli.schema import DistanceGrowth, NonNeg, Positive, Probability, Strict


class MeasurementSpec(Strict):
    """How the filter treats one measurement channel (a sensor, by name)."""

    sigma: NonNeg | list[NonNeg] = Field(description="noise std per component (R = diag(sigma^2)); a one-sided channel "
                                                     "(image_plane): the std of its bound (0: hard)")
    growth: DistanceGrowth | None = Field(None, description="R reset by distance to the transducer")
    gate: Probability | None = Field(None, description="chi-square gate probability, e.g. 0.999; off if unset")
    frame: Literal["world", "needle"] = Field(
        "world", description="coordinates of sigma: world axes, or (a position x, y, z) along the needle's tangent "
                             "then across it, R = F diag(sigma^2) F^T at the predicted tangent (needlecli.numerics.needle_frame)")
    across_axis: Literal["x", "y", "z"] | None = Field(
        None, description="frame: needle: the world axis of the across directions (default: the one least aligned "
                          "with the initial tangent)")

    sides: list[Literal["past", "short"]] = Field(
        default_factory=lambda: ["past", "short"], min_length=1,
        description="a channel that bounds the state from one side (image_plane): the samples used, past (the "
                    "bound g >= 0: the needle seen, its tip past the image plane) and/or short (g <= 0: the frame "
                    "lost, the tip short of the plane); the update is the truncated-Gaussian one, sigma the "
                    "bound's own std (0: a hard bound)")
    margin: NonNeg = Field(0.0, description="a one-sided channel (image_plane): the bound moved by this much in the "
                                           "sample's favour (side * g >= -margin: a tip seen up to margin short of "
                                           "the plane, a slice thickness), model length unit")

    @model_validator(mode="after")
    def _frame(self):
        if self.frame == "needle" and self.growth is not None:
            raise ValueError("growth is a distance law of world-axis noise: not with frame: needle")
        if self.across_axis is not None and self.frame != "needle":
            raise ValueError("across_axis is used only with frame: needle")
        return self


class KappaReset(Strict):
    """Reset of ``P_kappa_kappa`` to ``factor * P0_kappa_kappa`` when the tip crosses an interface."""

    factor: Positive = Field(1.0, description="P_kappa_kappa becomes factor times its initial variance at each "
                                              "interface (the multi-rate UKF paper's Fig. 8: 10)")
    interfaces: str = Field("experiment", description="'experiment' or the name of an elastography channel")


class UKFSettings(ObserverSettings):
    type: Literal["ukf"]
    model: str | None = Field(None, description="the filter's model (default: the experiment's)")
    params: dict[str, float] = Field(default_factory=dict, description="the filter's model parameters")
    rate: Positive | None = Field(None, description="filter rate, Hz (default: the simulation grid's)")
    alpha: Positive = Field(1e-3, description="spread of the Merwe scaled sigma points around the mean "
                                              "(the multi-rate UKF paper: 1e-3)")
    beta: NonNeg = Field(2.0, description="prior-distribution weight of the sigma points (2 is optimal for a "
                                          "Gaussian; the multi-rate UKF paper: 2)")
    kappa: float = Field(0.0, description="secondary scaling of the sigma points (the multi-rate UKF paper: 0); not the curvature")
    q: dict[str, NonNeg] = Field(default_factory=dict, description="process noise std per state, unit/sqrt(s)")
    p0: dict[str, NonNeg] = Field(default_factory=dict, description="initial variance per state (unit^2, not a std)")
    measurements: dict[str, MeasurementSpec] = Field(default_factory=dict, description="channels used, by sensor "
                                                     "name, with their noise, growth and gate (default: every channel "
                                                     "the model can predict, with the sensor's own sigma)")
    init: InitialEstimate = Field(default_factory=InitialEstimate, description="initial estimate (needlecli.initial)")
    kappa_max: Positive | None = Field(None, description="curvature constraint 0 <= kappa <= kappa_max")
    kappa_reset: KappaReset | None = Field(None, description="reset of the curvature variance at tissue interfaces "
                                                             "(default: none)")
    predict_at_depths: list[NonNeg] = Field(default_factory=list, description="observation depths for prediction")
    max_cov_trace: Positive = Field(1e8, description="a run whose tr(P) exceeds this has diverged")

    @model_validator(mode="after")
    def _check(self):
        if any(b <= a for a, b in zip(self.predict_at_depths, self.predict_at_depths[1:])):
            raise ValueError("predict_at_depths must increase strictly")
        return self


def tick_stride(rate: float | None, dt: float) -> int:
    """The filter's tick in grid steps of ``dt`` s: 1 without a ``rate`` (Hz), else the nearest whole
    number of steps to ``1 / rate`` (at least 1)."""
    return 1 if rate is None else max(1, int(round(1.0 / (rate * dt))))


def tick_length(rate: float | None, dt: float) -> float:
    """The filter's tick in s, ``tick_stride(rate, dt) * dt``: each tick's process noise is
    ``diag(q^2) * tick_length`` (``q`` per square-root second)."""
    return tick_stride(rate, dt) * dt


def _real(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and bool(np.isfinite(v))


def _chi2_quantile(p: float, m: int) -> float:
    from scipy.stats import chi2  # here: scipy.stats costs 0.5 s of start-up, and only gates need it

    return float(chi2.ppf(p, m))


_DIVERGED = "non-finite or exploding covariance at t = {t:.2f} s"


def _singular(model: Model) -> str:
    """Why a run stopped where its estimate left the model's domain, ``{t}`` the time of the tick."""
    return f"{model.singular_reason} (t = {{t:.2f}} s)"


@dataclass
class _Filter:
    """What the tick loop works with, set up once per run of the filter: the filter's model and its
    parameters, its inputs ``(N, T, m)``, the sigma-point weights and the order of the square root
    (:meth:`UnscentedKalmanFilter._translation_order`), the ticks ``(K,)`` and grid step ``dt``, the
    channels and one-sided channels, ``Q``, ``P0`` ``(n, n)``, the curvature's index, the tissue
    interfaces and the prediction depths."""

    model: Model
    params: dict
    inputs: np.ndarray
    weights: MerweWeights
    order: np.ndarray | slice | None
    back: np.ndarray | slice | None
    n_act: int
    ticks: np.ndarray
    dt: float
    chans: list[dict]
    bounds: list[dict]
    Q: np.ndarray
    P0: np.ndarray
    kappa_i: int | None
    interfaces: np.ndarray
    depths: np.ndarray
    angles: np.ndarray = field(init=False)
    angle_sel: object = field(init=False)
    tsel: np.ndarray | None = field(init=False)  # the translation states, moved relative to the central point

    def __post_init__(self):
        self.angles = self.model.angle_mask
        self.angle_sel = angle_selection(self.angles)
        self.tsel = None if self.order is None else np.array(
            [self.model.index(k) for k in self.model.translation_states], dtype=np.int64)


@dataclass
class _Counts:
    """The filter's counters per run ``(N,)`` (``nis``: per sample ``(N, M)``), by channel where named."""

    repairs: np.ndarray
    hits: np.ndarray
    resets: np.ndarray
    used: dict[str, np.ndarray]
    gated: dict[str, np.ndarray]
    nis: dict[str, np.ndarray]
    violated: dict[str, np.ndarray]


@OBSERVERS.register("ukf")
class UnscentedKalmanFilter(Observer):
    r"""Batched multi-rate UKF with Merwe scaled sigma points (the multi-rate UKF paper uses alpha 1e-3, beta 2, kappa 0).

    Prediction :math:`\mathcal X_{k|k-1} = f(\mathcal X_{k-1|k-1}, u)`,
    :math:`P_{k|k-1} = \sum_i W^c_i \delta\mathcal X_i \delta\mathcal X_i^T + Q`,
    :math:`Q = \mathrm{diag}(q^2)\,\Delta t_{tick}` (``q`` per square-root second); update with the
    measurements available at tick ``k`` only. Angles are averaged and differenced wrapped.
    """

    Settings = UKFSettings
    takes_common_start = True
    compiled_entry = ("ukf", "run")  # the kernel that compiles longest (the warm-up's)
    default_reference = True  # a comparison whose config gives no start starts from this, derived settings
    fit_takes = FitTakes(measurements=True, sensor_states=False)

    @classmethod
    def derived_settings(cls, ctx):
        """:func:`~needlecli.observers.defaults.filter_settings`: every sensor with a nominal sigma, the
        start from the first samples, ``q`` from the truth's process noise, a prediction from 25 % of the
        insertion."""
        return filter_settings(ctx)

    @classmethod
    def upgrade_settings(cls, settings, *, config_format, dt):
        """Config format 1 gave ``q`` per filter tick, ``sqrt(Q_ii dt_tick)``; it is now per square-root
        second: each value divided by ``sqrt(dt_tick)`` (the tick of :func:`tick_length`, from ``rate`` and
        ``dt``)."""
        q, rate = settings.get("q"), settings.get("rate")
        if config_format >= 2 or not isinstance(q, dict) or not q:
            return []
        if not _real(dt) or dt <= 0 or not (rate is None or (_real(rate) and rate > 0)):
            return []  # the schema says what is wrong
        tick = tick_length(rate, float(dt))
        root = float(np.sqrt(tick))
        new = {k: (v / root if _real(v) else v) for k, v in q.items()}
        settings["q"] = new
        pairs = ", ".join(f"{k} {q[k]:g} -> {new[k]:g}" for k in q if _real(q[k]))
        if not pairs:
            return []
        return [f"q was per filter tick of {tick:g} s (config format {config_format}); now per square-root second "
                f"(q_tick / sqrt({tick:g} s)): {pairs}"]

    # ------------------------------------------------------------------ configuration checks
    @classmethod
    def _model_cls(cls, settings, model):
        return MODELS.get(settings.model) if settings.model else type(model)

    @classmethod
    def check(cls, settings, model, sensors):
        out = []
        if settings.model and settings.model not in MODELS:
            return [(("model",), f"unknown model {settings.model!r}; known: {', '.join(MODELS.names())}")]
        mcls = cls._model_cls(settings, model)
        for where, keys in (("q", settings.q), ("p0", settings.p0)):
            for k in keys:
                if k not in mcls.state_names:
                    out.append(((where, k), f"model {mcls.registered_name!r} has no state {k!r}"))
        for k in settings.params:
            if k not in mcls.Params.model_fields:
                out.append((("params", k), f"model {mcls.registered_name!r} has no parameter {k!r}"))
        try:
            own = mcls(mcls.Params(**{**(model.params.model_dump() if mcls is type(model) else {}), **settings.params}))
        except Exception as e:  # parameters out of the model's range
            return out + [(("params",), str(e).splitlines()[-1].strip())]
        from needlecli.sensors.base import measurement_function

        for name in settings.measurements:
            spec = settings.measurements[name]
            if name not in sensors:
                known = ", ".join(sensors) or "none"
                out.append((("measurements", name), f"no sensor named {name!r}; sensors: {known}"))
            elif getattr(sensors[name], "inequality", False):  # a one-sided bound (image_plane)
                out += [(("measurements", name, *loc), msg) for loc, msg in cls._check_bound(sensors[name], own, spec)]
            elif {"sides", "margin"} & spec.model_fields_set:
                out.append((("measurements", name, "sides" if "sides" in spec.model_fields_set else "margin"),
                            f"only for a channel that bounds the state from one side; sensor {name!r} is a "
                            f"{sensors[name].registered_name}"))
            elif measurement_function(sensors[name], own) is None:
                out.append((("measurements", name),
                            f"model {mcls.registered_name!r} cannot predict what sensor {name!r} measures"))
            elif settings.measurements[name].frame == "needle" and (
                    tuple(sensors[name].channel_names) != ("x", "y", "z") or not mcls.provides("tangent")):
                out.append((("measurements", name, "frame"), "needle coordinates need a position with axes x, y, z "
                            f"and a model with a tangent (sensor {name!r}: {', '.join(sensors[name].channel_names)})"))
        out += [(("init", *loc), msg) for loc, msg in
                check_initial(settings.init, mcls.state_names, mcls.registered_name, sensors)]
        for k in mcls.input_names:
            if k not in model.input_names:
                out.append((("model",), f"the filter's model needs input {k!r}, which the experiment does not give"))
        if settings.kappa_max is not None or settings.kappa_reset is not None:
            if mcls.curvature_param not in mcls.state_names:
                out.append((("kappa_max" if settings.kappa_max is not None else "kappa_reset",),
                            f"model {mcls.registered_name!r} has no curvature state"))
        if settings.kappa_reset is not None and settings.kappa_reset.interfaces != "experiment":
            sensor = sensors.get(settings.kappa_reset.interfaces)
            if sensor is None or sensor.registered_name != "elastography":
                out.append((("kappa_reset", "interfaces"), "must be 'experiment' or the name of an elastography sensor"))
        return out

    @staticmethod
    def _check_bound(sensor, model, spec) -> list[tuple[tuple, str]]:
        """What is wrong with the settings of a one-sided channel (an image plane), as (key path, message)."""
        from needlecli.sensors.base import inequality_function

        if inequality_function(sensor, model) is None:
            return [((), f"model {model.registered_name!r} cannot be bounded by sensor {sensor.name!r}: "
                          f"{sensor.registered_name} needs {', '.join(sensor.requires)}")]
        out = []
        if isinstance(spec.sigma, list) and len(spec.sigma) != 1:
            out.append((("sigma",), "a one-sided channel has one bound: give one std"))
        for key in ("growth", "gate", "across_axis"):
            if getattr(spec, key) is not None:
                out.append(((key,), "not for a one-sided channel (the truncated update has no innovation to gate)"))
        if spec.frame != "world":
            out.append((("frame",), "not for a one-sided channel (its bound is a plane in world coordinates)"))
        return out

    # ------------------------------------------------------------------ run
    def _model(self, problem: EstimationProblem) -> Model:
        """The filter's own model: the experiment's, or ``model`` with ``params`` of the settings."""
        s = self.settings
        mcls = self._model_cls(s, problem.model)
        if mcls is type(problem.model) and not s.params:
            return problem.model
        base = problem.model.params.model_dump() if mcls is type(problem.model) else {}
        base.update(s.params)
        return mcls(mcls.Params(**base))

    def run(self, problem: EstimationProblem, rng: np.random.Generator, progress=None) -> Posterior:
        s = self.settings
        model: Model = self._model(problem)
        params = model.param_arrays()
        n, N = model.n, problem.n_runs
        order, back, n_act = self._translation_order(model)
        w = MerweWeights(n, s.alpha, s.beta, s.kappa)
        dt_grid, stride, ticks = self._ticks(problem.time)
        inputs = self._inputs(problem, model)

        # --- channels used, and the tick at which each sample becomes available
        chans = self._channels(problem, model)
        bounds = self._bounds(problem, model)  # one-sided channels: truncated updates (numpy path only)

        # --- initial estimate
        x, P0 = self._initial(problem, model, params, rng, chans)
        for c in chans:  # needle coordinates: the reference axis, given or far from the initial tangent
            if c["frame"] == "needle":
                c["axis"] = c["axis"] if c["axis"] is not None else reference_axis(model.tangent(x))
        Q = np.diag((np.array([s.q.get(k, 0.0) for k in model.state_names]) * np.sqrt(stride * dt_grid)) ** 2)
        kappa_i = model.index(model.curvature_param) if model.curvature_param in model.state_names else None
        interfaces = self._interfaces(problem, N)
        depths = np.asarray(s.predict_at_depths, dtype=float)

        from needlecli import kernels  # the compiled tick loop, where it covers this filter

        fast = kernels.twin("ukf", problem.kernels) if model.compiled_equations else None
        if fast is not None:
            from needlecli.kernels import ukf as compiled

            # a channel in the needle's frame (a full R at the predicted tangent) or a one-sided channel
            # (a truncated update): the numpy path below
            if compiled.supports(model, chans) and all(c["frame"] == "world" for c in chans) and not bounds:
                return self._from_kernel(fast(
                    model, params, problem, s, chans, ticks, inputs, x, P0, Q, kappa_i, interfaces, depths, w, order,
                    n_act, progress), problem, model, chans, stride, dt_grid, depths)

        f = _Filter(model=model, params=params, inputs=inputs, weights=w, order=order, back=back, n_act=n_act,
                    ticks=ticks, dt=dt_grid, chans=chans, bounds=bounds, Q=Q, P0=P0, kappa_i=kappa_i,
                    interfaces=interfaces, depths=depths)
        return self._posterior(*self._filter(problem, f, x, progress), model, stride, dt_grid, depths)

    def _filter(self, problem: EstimationProblem, f: _Filter, x: np.ndarray, progress=None):
        """The tick loop on numpy, every run at once (the reference of the compiled kernel): at each tick,
        predict, reset the curvature variance at an interface, update with what arrived, constrain the
        curvature, then stop the runs that diverged or left the model's domain and record. ``x (N, n)``:
        the initial estimate. Returns the recorder, the tick at which each prediction depth started
        ``(D,)`` and the predicted final states ``(N, D, n)``."""
        s = self.settings
        N, n = x.shape
        rec = RunRecorder(problem, n, progress=progress)
        counts = self._counts(rec, f.chans, f.bounds)
        schedule, bound_schedule = self._schedule(f.chans, f.ticks), self._schedule(f.bounds, f.ticks)
        P = np.broadcast_to(f.P0, (N, n, n)).copy()
        pred_tick = np.full(len(f.depths), -1, dtype=np.int64)
        roll = np.zeros((N, 0, n))  # rollouts to the final depth, advanced with the sigma points
        roll_ids: list[int] = []
        rec.record(0, x, P)  # samples available at t = 0 serve the initialisation only
        with np.errstate(all="ignore"):
            for i in range(1, len(f.ticks)):
                k0, k1 = f.ticks[i - 1], f.ticks[i]
                x_prev, P_prev = x, P
                x, P, roll = self._predict(f, x, P, roll, k0, k1, rec.alive, counts.repairs)
                if s.kappa_reset is not None and f.kappa_i is not None and f.interfaces.size:
                    self._reset_kappa(f, P, problem.depth[:, k0], problem.depth[:, k1], rec.alive, counts.resets)
                # ---- update with what arrived in (t_k0, t_k1]
                x, P = self._update_tick(f, x, P, schedule[i], bound_schedule[i], rec.alive, counts)
                # ---- curvature constraint: keep the previous estimate outside [0, kappa_max]
                if f.kappa_i is not None and s.kappa_max is not None:
                    kk = x[:, f.kappa_i]
                    out = ((kk < 0) | (kk > s.kappa_max)) & rec.alive
                    if out.any():
                        x[out, f.kappa_i] = x_prev[out, f.kappa_i]
                        counts.hits += out
                rec.check(k1, x, P, singular=f.model.left_domain(x_prev, x, f.params), max_trace=s.max_cov_trace,
                          singular_reason=_singular(f.model), diverged_reason=_DIVERGED)
                x, P = rec.hold(x, x_prev), rec.hold(P, P_prev)  # a stopped run holds its last good estimate
                rec.record(k1, x, P)
                # ---- final-position prediction from the observation depths reached now
                if f.depths.size:
                    due = np.nonzero((pred_tick < 0) & (f.depths <= problem.depth[0, k1] + 1e-9))[0]
                    if due.size:  # start one open-loop rollout per depth from the current estimate
                        roll = np.concatenate([roll, np.repeat(x[:, None, :], due.size, axis=1)], axis=1)
                        roll_ids.extend(due.tolist())
                        pred_tick[due] = k1
        pred_final = np.full((N, len(f.depths), n), np.nan)
        if roll_ids:
            pred_final[:, roll_ids] = roll
        return rec, pred_tick, pred_final

    @staticmethod
    def _predict(f: _Filter, x, P, roll, k0, k1, alive, repairs):
        """Sigma points of ``(x (N, n), P (N, n, n))`` through the model over grid steps ``k0..k1``, with
        the predictions in flight ``roll (N, R, n)`` riding along; the predicted ``(x, P)`` and ``roll``.
        The square root factors the states f depends on first (:meth:`_translation_order`): its last
        columns move positions only, and those sigma points move as the central one."""
        N, n = x.shape
        n_act, tsel = f.n_act, f.tsel
        root, bad = robust_cholesky(P[:, f.order][:, :, f.order] if f.order is not None else P)
        repairs += bad & alive
        if f.order is not None:
            root = root[:, f.back]
        cols = np.swapaxes(root, -1, -2) * np.sqrt(f.weights.scale)  # row i: column i of sqrt(scale P)
        S = 1 + 2 * n_act
        X = np.empty((N, S + roll.shape[1], n))
        X[:, 0] = x
        np.add(x[:, None, :], cols[:, :n_act], out=X[:, 1 : 1 + n_act])
        np.subtract(x[:, None, :], cols[:, :n_act], out=X[:, 1 + n_act : S])
        if tsel is not None:  # translation states relative to the central point's (see the module)
            X[:, 0, tsel] = 0.0
            X[:, 1 : 1 + n_act, tsel] = cols[:, :n_act, tsel]
            X[:, 1 + n_act : S, tsel] = -cols[:, :n_act, tsel]
        X[:, S:] = roll
        for j in range(k0, k1):
            X = f.model.step(X, f.inputs[:, j, None, :], f.params, f.dt)
        X, roll = X[:, :S], X[:, S:]
        if n_act < n:  # the position-only points: displaced as the central point
            full = np.empty((N, 2 * n + 1, n))
            full[:, :S] = X
            moved = X[:, 0][:, None, :]
            np.add(moved, cols[:, n_act:], out=full[:, S : S + n - n_act])
            np.subtract(moved, cols[:, n_act:], out=full[:, S + n - n_act :])
            X = full
        xp, dX = mean_and_residuals(X, f.weights.wm, f.angles)
        if tsel is not None:
            xp[:, tsel] += x[:, tsel]
        return xp, symmetrize(weighted_cov(dX, dX, f.weights.wc) + f.Q), roll

    def _reset_kappa(self, f: _Filter, P, d0, d1, alive, resets) -> None:
        """Where the tip crossed a tissue interface between depths ``d0`` and ``d1`` ``(N,)``, raise the
        curvature variance of ``P`` (in place) to ``factor * P0_kappa_kappa``."""
        crossed = np.any((d0[:, None] < f.interfaces) & (f.interfaces <= d1[:, None]), axis=-1) & alive
        if crossed.any():
            i = f.kappa_i
            target = self.settings.kappa_reset.factor * f.P0[i, i]
            P[:, i, i] += np.maximum(target - P[:, i, i], 0.0) * crossed
            resets += crossed

    def _update_tick(self, f: _Filter, x, P, arrived, bounds, alive, counts: _Counts):
        """The update of one tick with the samples that ``arrived`` and the one-sided ``bounds`` samples."""
        angles, ang_sel = f.angles, f.angle_sel
        if len(arrived) == 1 and arrived[0][0]["scalar"] and len(arrived[0][1]) == 1:
            (c, (j,)), = arrived  # one scalar sample that is a state (the multi-rate UKF paper's roll at 100 Hz)
            x, P = self._update_scalar(x, P, c, j, alive, counts.used, counts.nis)
            if ang_sel is not None:
                wrap_where_needed(x, ang_sel)
        elif arrived:
            if all(c["select"] is not None for c, _ in arrived):
                # every h picks states: the unscented transform of a linear h is its closed form
                X = dX = None
            else:
                # from sigma points of the predicted (x, P): the propagated ones carry neither Q nor
                # the kappa reset, and Pyy, Pxy without them give a gain that is not the Kalman gain
                root, bad = robust_cholesky(P)
                counts.repairs += bad & alive
                X = sigma_points(x, root, f.weights, angles)
                dX = residual(X, x[..., None, :], angles)
            x, P = self._update(x, P, X, dX, arrived, f.weights, alive, counts.gated, counts.used, counts.nis)
            if ang_sel is not None:  # the update may carry an angle across the cut
                wrap_where_needed(x, ang_sel)
        for b, samples in bounds:  # one-sided channels: one truncated update per sample
            for j in samples:
                x, P = self._update_bound(x, P, b, j, f.weights, angles, alive, counts.used, counts.violated,
                                          counts.repairs)
            if ang_sel is not None:
                wrap_where_needed(x, ang_sel)
        return x, P

    def _from_kernel(self, k, problem, model, chans, stride, dt_grid, depths) -> Posterior:
        """The posterior from the compiled filter's arrays (status codes: 0 ok, 1 diverged, 2 singular)."""
        rec = RunRecorder(problem, model.n)
        rec.adopt(k["states"], k["cov"])
        at = np.maximum(k["event"], 0)
        rec.stop(at, k["status"] == 2, STATUS_SINGULAR, _singular(model))
        rec.stop(at, k["status"] != 0, STATUS_DIVERGED, _DIVERGED)
        counts = self._counts(rec, chans, ())
        counts.repairs[:], counts.hits[:], counts.resets[:] = k["repairs"], k["hits"], k["resets"]
        for i, c in enumerate(chans):
            counts.used[c["name"]][:] = k["used"][:, i]
            counts.gated[c["name"]][:] = k["gated"][:, i]
            counts.nis[c["name"]][:] = k["nis"][i]
        return self._posterior(rec, k["pred_tick"], k["roll"], model, stride, dt_grid, depths)

    @staticmethod
    def _counts(rec: RunRecorder, chans: list[dict], bounds: list[dict]) -> _Counts:
        """The filter's counters, kept by ``rec`` under their names in the results file."""
        return _Counts(
            repairs=rec.counter("cholesky_repairs"), hits=rec.counter("constraint_hits"),
            resets=rec.counter("kappa_resets"),
            used={c["name"]: rec.counter(f"used/{c['name']}") for c in [*chans, *bounds]},
            gated={c["name"]: rec.counter(f"gated/{c['name']}") for c in chans},
            # per sample used: nu^T S^-1 nu
            nis={c["name"]: rec.extras.setdefault(f"nis/{c['name']}", np.full(np.shape(c["valid"]), np.nan))
                 for c in chans},
            violated={b["name"]: rec.counter(f"bound_violated/{b['name']}") for b in bounds},  # prediction broke it
        )

    def _posterior(self, rec: RunRecorder, pred_tick, pred_final, model, stride, dt_grid, depths) -> Posterior:
        s = self.settings
        extras = {}
        if depths.size:
            extras["prediction/depth"] = depths
            extras["prediction/time"] = np.where(pred_tick >= 0, rec.time[np.maximum(pred_tick, 0)], np.nan)
            extras["prediction/final_state"] = pred_final
        return rec.posterior(
            model.state_names, model.state_units, angle_states=model.angle_states, extras=extras,
            attrs={"filter_rate": 1.0 / (stride * dt_grid), "model": model.registered_name,
                   "sigma_alpha": s.alpha, "sigma_beta": s.beta, "sigma_kappa": s.kappa},
        )

    # ------------------------------------------------------------------ pieces
    def _ticks(self, time: np.ndarray) -> tuple[float, int, np.ndarray]:
        """The grid step (s), the filter's stride in grid steps and its ticks ``(K,)``: grid steps every
        stride from 0, and the last grid step."""
        T = len(time)
        dt_grid = float(time[1] - time[0]) if T > 1 else 1.0
        stride = tick_stride(self.settings.rate, dt_grid)
        ticks = np.arange(0, T, stride)
        if ticks[-1] != T - 1:
            ticks = np.append(ticks, T - 1)
        return dt_grid, stride, ticks

    @staticmethod
    def _inputs(problem: EstimationProblem, model: Model) -> np.ndarray:
        """The inputs of the filter's model ``(N, T, m)``, by name from the experiment's."""
        in_cols = []
        for k in model.input_names:
            sl = problem.model.input_slice(k)
            in_cols.extend(range(sl.start, sl.stop))
        return problem.inputs[..., in_cols]

    @staticmethod
    def _translation_order(model: Model) -> tuple[np.ndarray | None, np.ndarray | None, int]:
        """State order for the square root of P: the states f depends on first, the positions it does not
        depend on (``model.translation_states``) last. With a lower Cholesky factor of P in that order,
        the last columns move only positions: their sigma points see the same vector field as the central
        point at every RK4 stage, so they are displaced exactly as it is and need no model evaluation
        (9 of the multi-rate UKF paper's 15 points are propagated). Any square root of P gives sigma points with the same
        mean and covariance. Returns ``(order, inverse, number of propagated columns)``; the order is a
        reversing slice when the positions are the first states (no copies)."""
        fixed = [model.index(k) for k in model.translation_states]
        if not fixed:
            return None, None, model.n
        n_act = model.n - len(fixed)
        if sorted(fixed) == list(range(len(fixed))):  # positions first: the reversed order serves, as views
            return slice(None, None, -1), slice(None, None, -1), n_act
        active = [i for i in range(model.n) if i not in fixed]
        order = np.array(active + fixed)
        return order, np.argsort(order), n_act

    def _channels(self, problem: EstimationProblem, model: Model) -> list[dict]:
        s = self.settings
        names = [c for c in s.measurements if problem.channels[c].bound_for(model) is None] or (
            [] if s.measurements else [c for c, ch in problem.channels.items() if ch.h_for(model) is not None])
        dt = float(problem.time[1] - problem.time[0]) if len(problem.time) > 1 else 1.0
        out = []
        for name in names:
            ch = problem.channels[name]
            h = ch.h_for(model)
            if h is None:
                raise ValueError(f"channel {name!r} cannot be predicted from model {model.registered_name!r}")
            m = len(ch.names)
            spec = s.measurements.get(name)
            sigma = np.broadcast_to(np.asarray(spec.sigma if spec else ch.sigma, dtype=float), (m,)).copy()
            growth = spec.growth if spec else None
            pos_cols = [i for i, c in enumerate(ch.names) if c in ("x", "y", "z")]
            avail = np.ceil(ch.t_available / dt - 1e-9).astype(np.int64)
            order = np.argsort(avail, kind="stable")
            out.append({
                "name": name, "h": h, "m": m, "sigma": sigma, "growth": growth,
                "select": h.index if isinstance(h, StateSelection) else None,
                "pos_cols": pos_cols, "pos_axes": [("x", "y", "z").index(ch.names[i]) for i in pos_cols],
                "gate": _chi2_quantile(spec.gate, m) if spec and spec.gate else None,
                "angle": np.asarray(ch.angle, dtype=bool), "value": ch.value, "valid": ch.valid,
                "avail": avail[order], "order": order, "channel": ch,
                "frame": spec.frame if spec else "world", "tangent": model.tangent if spec and spec.frame == "needle" else None,
                "axis": AXES.index(spec.across_axis) if spec and spec.across_axis else None,
            })
            c = out[-1]
            c["scalar"] = m == 1 and c["select"] is not None and c["gate"] is None and not pos_cols
        return out

    def _bounds(self, problem: EstimationProblem, model: Model) -> list[dict]:
        """The one-sided channels the settings name (``measurements``; never by default), with their
        bound ``side * g(x) >= -margin``, softness ``sigma`` and the sides used."""
        dt = float(problem.time[1] - problem.time[0]) if len(problem.time) > 1 else 1.0
        out = []
        for name, spec in self.settings.measurements.items():
            ch = problem.channels[name]
            bound = ch.bound_for(model)
            if bound is None:
                continue
            avail = np.ceil(ch.t_available / dt - 1e-9).astype(np.int64)
            order = np.argsort(avail, kind="stable")
            out.append({"name": name, "bound": bound, "value": ch.value, "valid": ch.valid,
                        "sigma": float(np.ravel(spec.sigma)[0]), "margin": float(spec.margin),
                        "past": "past" in spec.sides, "short": "short" in spec.sides,
                        "avail": avail[order], "order": order})
        return out

    @staticmethod
    def _update_bound(x, P, b, j, w, angles, alive, used, violated, repairs):
        r"""Truncated-Gaussian update with sample ``j`` of one-sided channel ``b``, per run where valid.

        With ``z = side * g(x) + margin`` (the sample says ``z >= 0``, softened by ``z + e >= 0``,
        ``e ~ N(0, sigma^2)``: a probit likelihood ``Phi(z / sigma)``, the hard bound at ``sigma = 0``),
        the unscented transform of the prediction gives ``z``'s mean ``m``, variance ``s^2`` and cross
        covariance ``P_xz``; the posterior's first two moments in ``z`` are those of the truncated (or
        probit-weighted) Gaussian, ``E[z] = m + s^2 lambda / s_t`` and ``Var z = s^2 - s^4 lambda
        (lambda + a) / s_t^2`` with ``s_t^2 = s^2 + sigma^2``, ``a = m / s_t``, ``lambda = phi(a) / Phi(a)``,
        and the state follows by the linear regression on ``z`` (exact moments where ``g`` is linear and
        the prediction Gaussian): ``x += P_xz lambda / s_t``, ``P -= P_xz P_xz^T lambda (lambda + a) / s_t^2``
        (a rank-one downdate that keeps ``P`` positive: ``lambda (lambda + a) < 1``)."""
        from scipy.special import log_ndtr

        v = b["valid"][:, j] & alive
        if not v.any():
            return x, P
        value = np.where(v[:, None], b["value"][:, j], 0.0)
        root, bad = robust_cholesky(P)
        repairs += bad & v
        X = sigma_points(x, root, w, angles)
        dX = residual(X, x[..., None, :], angles)
        g, side = b["bound"](X, value[:, None, :])
        side = np.broadcast_to(side, g.shape)[:, 0]
        v = v & np.where(side > 0, b["past"], b["short"])
        if not v.any():
            return x, P
        z = side[:, None] * g + b["margin"]  # (N, S)
        m = z[:, 0] + (z - z[:, :1]) @ w.wm  # about the central point: the 1e-3 spread's weights are 7e4
        dz = z - m[:, None]
        s2 = (dz**2) @ w.wc
        pxz = np.einsum("nsi,ns,s->ni", dX, dz, w.wc)
        st2 = s2 + b["sigma"] ** 2
        v = v & (st2 > 0) & np.isfinite(m) & np.isfinite(st2)
        st = np.sqrt(np.where(v, st2, 1.0))
        a = np.where(v, m, 0.0) / st
        lam = np.exp(-0.5 * a**2 - 0.5 * np.log(2.0 * np.pi) - log_ndtr(a))  # phi(a) / Phi(a), stable for a << 0
        shrink = np.where(v, lam * (lam + a), 0.0) / st**2
        used[b["name"]] += v
        violated[b["name"]] += v & (m < 0)
        x = x + pxz * np.where(v, lam / st, 0.0)[:, None]
        u = pxz * np.sqrt(shrink)[:, None]
        return x, symmetrize(P - u[:, :, None] * u[:, None, :])

    def _initial(self, problem, model, params, rng, chans):
        s = self.settings
        x = initial_mean(s.init, problem, model, params, rng)
        return x, initial_covariance(s.init, model.state_names, s.p0, 1e-12, start=problem.start)

    @classmethod
    def initial_estimate(cls, settings, problem, rng):
        model = cls(settings)._model(problem)
        P0 = initial_covariance(settings.init, model.state_names, settings.p0, 1e-12)
        return make_start(settings.init, problem, model, model.param_arrays(), rng, P0, settings.name or settings.type)

    def _interfaces(self, problem, N) -> np.ndarray:
        r = self.settings.kappa_reset
        if r is None:
            return np.zeros(0)
        if r.interfaces == "experiment":
            return np.asarray(problem.interfaces, dtype=float)
        return np.asarray(problem.channels[r.interfaces].attrs.get("interfaces", np.zeros((N, 0))), dtype=float)

    @staticmethod
    def _schedule(chans: list[dict], ticks: np.ndarray) -> list[list[tuple[dict, np.ndarray]]]:
        """For each filter tick, the channels with samples that became available since the last tick,
        and those samples (in time order). Samples available at the first tick serve initialisation."""
        schedule: list[list[tuple[dict, np.ndarray]]] = [[] for _ in ticks]
        for c in chans:
            tick_of = np.searchsorted(ticks, c["avail"], side="left")
            for i in np.unique(tick_of):
                if 0 < i < len(ticks):
                    schedule[i].append((c, c["order"][tick_of == i]))
        return schedule

    @staticmethod
    def _update_scalar(x, P, c, j, alive, used, nis):
        """:meth:`_update` for one scalar sample ``j`` of channel ``c`` that measures one state ``i``:
        ``Pyy = P_ii + r``, ``Pxy = P[:, i]``, no solve; ``P - u u^T`` with ``u = Pxy / sqrt(Pyy)`` stays
        exactly symmetric. Runs without a valid sample are left unchanged."""
        i = int(c["select"][0])
        v = c["valid"][:, j] & alive
        used[c["name"]] += v
        if not v.any():
            return x, P
        nu = c["value"][:, j, 0] - x[:, i]
        if c["angle"][0]:
            nu = wrap_angle(nu)
        nu = np.where(v, nu, 0.0)
        s = np.where(v, P[:, i, i] + float(c["sigma"][0]) ** 2, 1.0)
        nis[c["name"]][v, j] = (nu**2 / s)[v]
        pxy = P[:, :, i] * v[:, None]
        x = x + pxy * (nu / s)[:, None]
        u = pxy / np.sqrt(s)[:, None]
        return x, P - u[:, :, None] * u[:, None, :]

    def _update(self, x, P, X, dX, arrived, w, alive, gated, used, nis):
        """Update with the samples that arrived at this tick, per run where valid; the normalised
        innovation squared of each channel's sample used goes to ``nis`` (its own block of ``S``)."""
        N = x.shape[0]
        ys, masks, rs, hs, angs, blocks = [], [], [], [], [], []
        start = 0
        for c, samples in arrived:
            if len(samples) == 1:
                j = samples[0]
                v = c["valid"][:, j] & alive
                y = np.where(v[:, None], c["value"][:, j], 0.0)
                jsel = np.full(N, j)
            else:  # several samples of a channel in one tick: the latest valid one wins
                y = np.zeros((N, c["m"]))
                v = np.zeros(N, dtype=bool)
                jsel = np.zeros(N, dtype=np.int64)
                for j in samples:
                    vj = c["valid"][:, j] & alive
                    y = np.where(vj[:, None], c["value"][:, j], y)
                    jsel = np.where(vj, j, jsel)
                    v |= vj
            if not v.any():
                continue
            r = np.broadcast_to(c["sigma"] ** 2, (N, c["m"]))
            if c["frame"] == "needle":  # a covariance in the needle's frame at the predicted tangent
                r = world_covariance(needle_basis(c["tangent"](x), c["axis"]), c["sigma"] ** 2)
            elif c["growth"] is not None and c["pos_cols"]:
                f = c["growth"].factor(y[:, c["pos_cols"]], axes=c["pos_axes"])
                r = r.copy()
                r[:, c["pos_cols"]] *= (f**2)[:, None]
            blocks.append((c, start, c["m"], jsel))
            start += c["m"]
            ys.append(y)
            masks.append(np.broadcast_to(v[:, None], (N, c["m"])))
            rs.append(r)
            hs.append(c["select"] if X is None else c["h"](X))
            angs.append(c["angle"])
        if not ys:
            return x, P
        if len(ys) == 1:
            y, mask, R, Y, ang_y = ys[0], masks[0].astype(float), rs[0], hs[0], angs[0]
        else:
            y = np.concatenate(ys, -1)
            mask = np.concatenate(masks, -1).astype(float)
            R = block_noise(rs) if any(r.ndim == 3 for r in rs) else np.concatenate(rs, -1)
            Y = np.concatenate(hs, -1)  # (N, S, M)
            ang_y = np.concatenate(angs)
        M = y.shape[-1]
        if X is None:  # h(x) = x[..., idx]: y_hat = x[idx], Pyy = P[idx, idx] + R, Pxy = P[:, idx]
            idx = Y
            y_hat = x[:, idx]
            Pxy = P[:, :, idx]
            Pyy = Pxy[:, idx, :]
        else:
            y_hat = weighted_mean(Y, w.wm, ang_y)
            dY = residual(Y, y_hat[:, None, :], ang_y)
            Pyy = weighted_cov(dY, dY, w.wc)
            Pxy = weighted_cov(dX, dY, w.wc)
        if R.ndim == 3:  # a full block (needle coordinates)
            Pyy = Pyy + R
        else:
            Pyy[:, np.arange(M), np.arange(M)] += R
        nu = residual(y, y_hat, ang_y) * mask
        # chi-square gating per channel block
        for c, b0, m, jsel in blocks:
            sl = slice(b0, b0 + m)
            on = mask[:, b0] > 0
            if m == 1:
                q = nu[:, b0] ** 2 / Pyy[:, b0, b0]
            else:
                q = np.einsum("ni,ni->n", nu[:, sl], np.linalg.solve(Pyy[:, sl, sl], nu[:, sl][..., None])[..., 0])
            if c["gate"] is not None:
                out = on & ~(q <= c["gate"])
                if out.any():
                    mask[out, sl] = 0.0
                    nu[out, sl] = 0.0
                    gated[c["name"]] += out
                    on = on & ~out
            used[c["name"]] += on
            nis[c["name"]][on, jsel[on]] = q[on]
        if mask.all():
            Pyy_m, Pxy_m = Pyy, Pxy
        else:  # missing entries: zero their rows and columns, unit diagonal, so their gain is zero
            Pyy_m = Pyy * (mask[:, :, None] * mask[:, None, :])
            Pyy_m[:, np.arange(M), np.arange(M)] += 1.0 - mask
            Pxy_m = Pxy * mask[:, None, :]
        if M == 1:  # one scalar measurement (the multi-rate UKF paper's roll at 100 Hz): no solve; P - u u^T stays symmetric
            s = Pyy_m[:, 0, 0]
            pxy = Pxy_m[:, :, 0]
            x = x + pxy * (nu / s[:, None])
            u = pxy / np.sqrt(s)[:, None]
            return x, P - u[:, :, None] * u[:, None, :]
        K = np.swapaxes(np.linalg.solve(Pyy_m, np.swapaxes(Pxy_m, -1, -2)), -1, -2)  # (N, n, M)
        x = x + np.matmul(K, nu[..., None])[..., 0]
        P = symmetrize(P - K @ Pyy_m @ np.swapaxes(K, -1, -2))
        return x, P
