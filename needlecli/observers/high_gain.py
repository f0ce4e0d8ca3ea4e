r"""Nonlinear high-gain observer of the high-gain observer paper (sec. III) for pitch and roll from the lateral deflection x.

On the transformed state :math:`s = (x, \sin\beta, -\cos\beta\sin\gamma)` the unicycle reads

.. math::
    s' = A s + \phi(u, s),\quad
    A = \begin{pmatrix}0 & v & 0\\ 0 & 0 & -v\kappa\\ 0 & 0 & 0\end{pmatrix},\quad
    \phi = (0,\ 0,\ \kappa v s_2 - \zeta u \sqrt{1 - s_2^2 - s_3^2}),\quad y = C s = s_1,

with :math:`\zeta = \mathrm{sign}(\cos\gamma)`. The observer is

.. math::
    \hat s' = A \hat s + \phi(u, \hat s) + \Lambda_\theta L (C \hat s - y),\quad
    \Lambda_\theta = \mathrm{diag}(\theta, \theta^2, \theta^3),

whose error :math:`\varepsilon = \Lambda_\theta^{-1}(\hat s - s)` obeys
:math:`\varepsilon' = \theta (A + L C) \varepsilon + \Lambda_\theta^{-1}\,\delta\phi` (``L = (-100, -1.05,
1.37)`` makes :math:`A + LC` Hurwitz). It estimates x, beta and gamma; alpha, y and z do not enter x and
are not observable from it.

Numerics. A large theta makes the correction stiff (eigenvalues ``theta * (-100, ~-0.01, ~-0.01)`` for
the high-gain observer paper's v and kappa), so the linear part is integrated exactly: an integrating-factor (Lawson) RK4 step
whose linear flow is the matrix exponential over the grid step (computed in theta-scaled coordinates,
cached per insertion speed), with only the bounded square-root term left to RK4. The square root's
argument is clamped at 0. ``zeta`` starts as the sign of ``cos`` of the initial roll estimate and flips
when ``sqrt(1 - s2^2 - s3^2)`` falls below ``zeta_eps`` (re-armed once it is back above ``2 zeta_eps``),
i.e. when the estimate passes ``gamma = pi/2 + n pi``, which the high-gain observer paper assumes are transient via points.

Sampled measurements. The output y arrives at the sensor's rate (e.g. 25 Hz) while the observer runs
on the simulation grid. ``hold: predictor`` (default) replaces y between samples by the output predicted
from the last sample, :math:`w' = C(A\hat s + \phi) = v \hat s_2`, :math:`w(t_j) = y_j` (Karafyllis and
Kravaris' inter-sample predictor; a latency is bridged the same way), so the innovation ``x_hat - w`` is
continuous and nothing is learnt from the staircase. ``hold: zoh`` holds the last sample (the literal
reading); it biases the derivative estimates between samples and is kept for comparison. Either way
the sampled-data design needs ``theta * T_s`` small: the ``theta = 67e4`` of the high-gain observer paper's simulation (as
legible) assumes a continuous measurement; at 25-100 Hz, theta of order 10-1000 is usable (docs/papers/highgain-us2d.md).
"""

from __future__ import annotations

from typing import Literal

import numpy as np
from pydantic import Field, model_validator
from scipy.linalg import expm

from needlecli.initial import start_state
from needlecli.numerics import wrap_angle
from needlecli.observers.base import (
    OBSERVERS,
    STATUS_DIVERGED,
    EstimationProblem,
    Observer,
    ObserverSettings,
    Posterior,
)
from needlecli.observers.record import RunRecorder
from needlecli.schema import NonNeg, Positive, Strict

ESTIMATED = ("x", "beta", "gamma")


# ---------------------------------------------------------------------------------------------- maths
def to_transformed(x: np.ndarray, beta: np.ndarray, gamma: np.ndarray) -> np.ndarray:
    """``s = (x, sin b, -cos b sin g)``, shape ``(..., 3)``."""
    return np.stack([x, np.sin(beta), -np.cos(beta) * np.sin(gamma)], -1)


def from_transformed(s: np.ndarray, zeta: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(x, beta, gamma)`` of ``s (..., 3)`` with ``zeta = sign(cos gamma)`` (the high-gain observer paper's eq. 4):
    ``beta = asin(s2)``, ``gamma = atan2(-s3 / cos b, zeta sqrt(1 - s2^2 - s3^2) / cos b)``."""
    s2 = np.clip(s[..., 1], -1.0, 1.0)
    root = np.sqrt(np.maximum(1.0 - s2**2 - s[..., 2] ** 2, 0.0))
    return s[..., 0], np.arcsin(s2), np.arctan2(-s[..., 2], zeta * root)  # cos b > 0 cancels


def transformed_field(s: np.ndarray, v, u, kappa, zeta) -> np.ndarray:
    """``s' = A s + phi(u, s)`` of the transformed unicycle (square-root argument clamped at 0)."""
    root = np.sqrt(np.maximum(1.0 - s[..., 1] ** 2 - s[..., 2] ** 2, 0.0))
    return np.stack([v * s[..., 1], -v * kappa * s[..., 2], kappa * v * s[..., 1] - zeta * u * root], -1)


def error_matrix(v: float, kappa: float, gain) -> np.ndarray:
    """``A + L C`` (3, 3): ``theta`` times it is the linear error dynamics in ``Lambda^-1 (s_hat - s)``."""
    l1, l2, l3 = gain
    return np.array([[l1, v, 0.0], [l2, 0.0, -v * kappa], [l3, 0.0, 0.0]])


def is_hurwitz(v: float, kappa: float, gain) -> bool:
    """Routh-Hurwitz for ``det(sI - (A + LC)) = s^3 - L1 s^2 - v L2 s + L3 v^2 kappa``."""
    l1, l2, l3 = gain
    a2, a1, a0 = -l1, -v * l2, l3 * v * v * kappa
    return a2 > 0 and a1 > 0 and a0 > 0 and a2 * a1 > a0


def _linear_part(v: float, kappa: float, theta: float, gain, hold: str) -> np.ndarray:
    """Linear part (5, 5) of the augmented observer on ``q = (r, s2, s3, w, p)``:
    ``r = x_hat - w`` the innovation, ``w`` the output the observer compares with (held or predicted
    sample), ``p`` the integral of ``v s2_hat`` (never reset: bridges latencies)."""
    l1, l2, l3 = gain
    m = np.zeros((5, 5))
    m[0, 0] = theta * l1
    if hold == "zoh":
        m[0, 1] = v  # r' = v s2 + theta L1 r  (w held)
    else:
        m[3, 1] = v  # w' = v s2, r' = theta L1 r
    m[1, 0] = theta**2 * l2
    m[1, 2] = -v * kappa
    m[2, 0] = theta**3 * l3
    m[2, 1] = kappa * v
    m[4, 1] = v
    return m


def linear_flows(v: float, kappa: float, theta: float, gain, hold: str, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """``exp(M dt / 2)`` and ``exp(M dt)`` of :func:`_linear_part`, computed on the theta-scaled matrix
    ``D^-1 M D``, ``D = diag(theta, theta^2, theta^3, theta, theta)``, whose entries are all O(theta)."""
    m = _linear_part(v, kappa, theta, gain, hold)
    d = np.array([theta, theta**2, theta**3, theta, theta])
    ms = m * d[None, :] / d[:, None]
    out = []
    for h in (0.5 * dt, dt):
        e = expm(ms * h) * d[:, None] / d[None, :]
        out.append(e)
    return out[0], out[1]


def lawson_rk4(q: np.ndarray, eh: np.ndarray, e: np.ndarray, nonlin, dt: float) -> np.ndarray:
    """One integrating-factor (Lawson) RK4 step of ``q' = M q + N(q)``, ``q (..., n)``, given
    ``eh = exp(M dt/2)`` and ``e = exp(M dt)`` (``(..., n, n)`` or ``(n, n)``). Exact for ``N = 0``,
    so it stays stable however stiff ``M`` is."""

    def mul(a, x):
        return x @ a.T if a.ndim == 2 else np.einsum("...ij,...j->...i", a, x)

    k1 = nonlin(q)
    k2 = nonlin(mul(eh, q + 0.5 * dt * k1))
    k3 = nonlin(mul(eh, q) + 0.5 * dt * k2)
    k4 = nonlin(mul(e, q) + dt * mul(eh, k3))
    return mul(e, q) + (dt / 6.0) * (mul(e, k1) + 2.0 * mul(eh, k2 + k3) + k4)


def observer_step(q: np.ndarray, eht: np.ndarray, et: np.ndarray, zu: np.ndarray, dt: float) -> np.ndarray:
    """One step of the augmented observer ``q' = M q + N(q)`` on ``q (N, 5) = (r, s2, s3, w, p)``:
    :func:`lawson_rk4` written out for ``N(q) = -zeta u sqrt(1 - s2^2 - s3^2) e3`` (only the flows'
    third column is needed). ``eht``, ``et``: ``exp(M dt/2)^T``, ``exp(M dt)^T`` as ``(5, 5)`` or
    ``(N, 5, 5)``; ``zu (N,)``: ``zeta * u``."""

    def nl(s2, s3):
        return -zu * np.sqrt(np.maximum(1.0 - s2 * s2 - s3 * s3, 0.0))

    def mul(x, mt):
        return x @ mt if mt.ndim == 2 else np.einsum("nj,nji->ni", x, mt)

    qh, qe = mul(q, eht), mul(q, et)
    ch, ce = (eht[2], et[2]) if eht.ndim == 2 else (eht[:, 2], et[:, 2])
    n1 = nl(q[:, 1], q[:, 2])
    a = qh + (0.5 * dt * n1)[:, None] * ch
    n2 = nl(a[:, 1], a[:, 2])
    n3 = nl(qh[:, 1], qh[:, 2] + 0.5 * dt * n2)
    b = qe + (dt * n3)[:, None] * ch
    n4 = nl(b[:, 1], b[:, 2])
    qn = qe + (dt / 6.0) * (n1[:, None] * ce + (2.0 * (n2 + n3))[:, None] * ch)
    qn[:, 2] += (dt / 6.0) * n4
    return qn


def sampled_radius(v: float, kappa: float, theta: float, gain, period: float) -> float:
    """Spectral radius of the linear error map from one sample to the next with ``hold: predictor``
    (u = 0, exact model): between samples ``e' = A_l e + Lambda L r``, ``r' = theta L1 r``, and each
    sample resets ``r = e1``. Below 1 the sampled loop converges; the continuous design needs
    ``theta * period`` small enough for that."""
    l1, l2, l3 = gain
    m = np.zeros((4, 4))
    m[0, 1] = v
    m[1, 2] = -v * kappa
    m[2, 1] = kappa * v
    m[:3, 3] = [theta * l1, theta**2 * l2, theta**3 * l3]
    m[3, 3] = theta * l1
    d = np.array([theta, theta**2, theta**3, theta])
    phi = expm(m * d[None, :] / d[:, None] * period) * d[:, None] / d[None, :]
    step = phi[:3, :3].copy()
    step[:, 0] += phi[:3, 3]
    return float(np.max(np.abs(np.linalg.eigvals(step))))


def largest_stable_theta(v: float, kappa: float, gain, period: float) -> float:
    """The largest theta (to 1 %) whose sampled loop (:func:`sampled_radius`) is stable."""
    lo, hi = 1e-6, 1e12
    if sampled_radius(v, kappa, lo, gain, period) >= 1.0:
        return 0.0
    while hi / lo > 1.01:
        mid = np.sqrt(lo * hi)
        lo, hi = (mid, hi) if sampled_radius(v, kappa, mid, gain, period) < 1.0 else (lo, mid)
    return lo


# ---------------------------------------------------------------------------------------------- settings
class HighGainInit(Strict):
    """Initial estimate of ``(x, beta, gamma)``: the truth's initial values (``from: truth``; the high-gain observer paper
    starts the roll from the known 3 deg) or zeros (``from: nominal``), then fixed ``values`` (the high-gain observer paper:
    ``{x: 0, beta: 0}``), then Gaussian noise of ``std``. zeta starts as ``sign(cos gamma_hat0)``."""

    from_: Literal["truth", "nominal"] = Field("truth", alias="from", description="start from the truth's initial "
                                              "x, beta, gamma (truth) or from zeros (nominal)")
    values: dict[Literal["x", "beta", "gamma"], float] = Field(default_factory=dict, description="fixed starting "
                                                                 "values, x in mm, beta and gamma in rad (the high-gain observer paper: "
                                                                 "{x: 0, beta: 0})")
    std: dict[Literal["x", "beta", "gamma"], NonNeg] = Field(default_factory=dict, description="std of Gaussian noise "
                                                             "added to the start per run, x in mm, beta and gamma in rad")


class HighGainSettings(ObserverSettings):
    type: Literal["high_gain"]
    measurement: str | None = Field(
        None, description="position channel whose 'x' component is the output (default: the only one)"
    )
    theta: Positive = Field(100.0, description="high-gain parameter (> 1 in the high-gain observer paper)")
    gain: tuple[float, float, float] = Field((-100.0, -1.05, 1.37), description="L, with A + L C Hurwitz")
    kappa: NonNeg | None = Field(None, description="the observer's curvature, 1/mm (default: the model's)")
    hold: Literal["predictor", "zoh"] = Field("predictor", description="the output between samples")
    zeta_eps: float = Field(0.5, gt=0.0, le=1.0, description="band sqrt(1 - s2^2 - s3^2) < eps where zeta may flip")
    zeta_u_min: NonNeg = Field(1e-3, description="|u| (rad/s) above which the shaft counts as rotating")
    init: HighGainInit = Field(default_factory=HighGainInit, description="the initial estimate of x, beta, gamma "
                                                                         "(zeta starts as sign(cos gamma_hat0))")

    @model_validator(mode="after")
    def _signs(self):
        l1, l2, l3 = self.gain
        if not (l1 < 0 and l2 < 0 and l3 > 0):
            raise ValueError("gain needs L1 < 0, L2 < 0, L3 > 0 for A + L C to be Hurwitz (v, kappa > 0)")
        return self


# ---------------------------------------------------------------------------------------------- observer
@OBSERVERS.register("high_gain")
class HighGainObserver(Observer):
    """The high-gain observer paper's observer, batched over runs (module docstring for the equations and numerics)."""

    Settings = HighGainSettings
    takes_common_start = True  # with a common start, the high-gain observer paper's prescribed init.values apply on top of it

    @classmethod
    def derived_settings(cls, ctx):
        """The high-gain observer paper's start, x_hat0 = beta_hat0 = 0 (the roll from the common start)."""
        return {"init": {"from": "nominal", "values": {"x": 0.0, "beta": 0.0}}}

    @classmethod
    def prescribed_start(cls, settings):
        """``init.values`` (the high-gain observer paper: x_hat0 = beta_hat0 = 0) apply on top of a common start."""
        vals = settings.init.values
        if not vals:
            return None
        if len(set(vals.values())) == 1:
            return f"{', '.join(vals)} = {next(iter(vals.values())):g}"
        return ", ".join(f"{k} = {v:g}" for k, v in vals.items())

    @classmethod
    def _position_channels(cls, sensors) -> list[str]:
        return [n for n, s in sensors.items() if s.registered_name == "position" and "x" in s.channel_names]

    @classmethod
    def check(cls, settings, model, sensors):
        out = []
        for k in ("v", "u"):
            if k not in model.input_names or model.input_sizes.get(k) != 1:
                out.append((("type",), f"the high-gain observer needs the scalar inputs v and u; model "
                                       f"{model.registered_name!r} has {', '.join(model.input_names)}"))
                return out
        if settings.kappa is None and "kappa" not in model.Params.model_fields:
            out.append((("kappa",), f"model {model.registered_name!r} has no kappa: give the observer's"))
        usable = cls._position_channels(sensors)
        if settings.measurement is not None:
            if settings.measurement not in sensors:
                known = ", ".join(sensors) or "none"
                out.append((("measurement",), f"no sensor named {settings.measurement!r}; sensors: {known}"))
            elif settings.measurement not in usable:
                out.append((("measurement",), f"sensor {settings.measurement!r} is not a position sensor with an x axis"))
        elif len(usable) != 1:
            what = "no position sensor with an x axis" if not usable else f"several ({', '.join(usable)}): name one"
            out.append((("measurement",), f"the output x needs one position channel; there is {what}"))
        if settings.init.from_ == "truth":
            for k in ESTIMATED:
                if k not in model.state_names and k not in settings.init.values:
                    out.append((("init", "values", k), f"model {model.registered_name!r} has no state {k!r} "
                                                       "to start from: give a value"))
        return out

    # ------------------------------------------------------------------ run
    def run(self, problem: EstimationProblem, rng: np.random.Generator, progress=None) -> Posterior:
        s = self.settings
        N, T = problem.n_runs, len(problem.time)
        model = problem.model
        times = problem.time
        v_all = problem.inputs[..., model.input_slice("v").start]
        u_all = problem.inputs[..., model.input_slice("u").start]
        kappa = float(s.kappa if s.kappa is not None else np.mean(problem.params["kappa"]))
        theta, gain, hold = float(s.theta), tuple(float(g) for g in s.gain), s.hold
        vmax = float(np.max(np.abs(v_all))) if v_all.size else 0.0

        # --- measurement: which samples become available at which grid step
        ch_name = s.measurement or next(n for n, c in problem.channels.items()
                                        if c.sensor_type == "position" and "x" in c.names)
        ch = problem.channels[ch_name]
        col = ch.names.index("x")
        dt_grid = float(times[1] - times[0]) if T > 1 else 1.0
        avail = np.ceil(ch.t_available / dt_grid - 1e-9).astype(np.int64)
        due: dict[int, np.ndarray] = {}
        for k in np.unique(avail[avail < T]):
            due[int(k)] = np.nonzero(avail == k)[0]  # in time order
        period = float(np.median(np.diff(ch.t))) if len(ch.t) > 1 else dt_grid
        radius = sampled_radius(vmax, kappa, theta, gain, period) if hold == "predictor" else 0.0

        # --- initial estimate
        x0 = np.zeros((N, 3))
        if problem.start is not None:  # a comparison's common start; the high-gain observer paper's prescribed values on top
            xs = start_state(problem, model, problem.params)
            for i, k in enumerate(ESTIMATED):
                if k in model.state_names:
                    x0[:, i] = xs[:, model.index(k)]
        elif s.init.from_ == "truth" and problem.initial_truth is not None:
            for i, k in enumerate(ESTIMATED):
                if k in model.state_names:
                    x0[:, i] = problem.initial_truth[:, model.index(k)]
        for k, val in s.init.values.items():
            x0[:, ESTIMATED.index(k)] = val
        if problem.start is None:
            std = np.array([s.init.std.get(k, 0.0) for k in ESTIMATED])
            x0 = x0 + std * rng.standard_normal(x0.shape)
        s0 = to_transformed(x0[:, 0], x0[:, 1], x0[:, 2])
        zeta = np.where(np.cos(x0[:, 2]) < 0, -1.0, 1.0)
        root0 = np.sqrt(np.maximum(1.0 - s0[:, 1] ** 2 - s0[:, 2] ** 2, 0.0))
        armed = root0 >= s.zeta_eps  # a start inside the band must leave it before a flip counts
        low = np.full(N, np.inf)  # lowest root since entering the band
        rise = 0.05 * s.zeta_eps  # how far the root must climb back from its minimum to count as passed
        flips = np.zeros(N, dtype=np.int64)

        q = np.zeros((N, 5))  # (r, s2, s3, w, p): x_hat = r + w
        q[:, 1:3] = s0[:, 1:3]
        q[:, 3] = s0[:, 0]
        p_hist = np.zeros((N, T))  # p at each grid step (latency bridging)
        rec = RunRecorder(problem, 3, covariance=False, series={"zeta": np.int8}, progress=progress)

        def reset(k: int) -> None:
            """Samples that became available at grid step k: the compared output w jumps to them."""
            for j in due.get(k, ()):
                y = ch.value[:, j, col]
                ok = ch.valid[:, j] & np.isfinite(y)
                if not ok.any():
                    continue
                # predictor: carry the sample from its acquisition to now with the observer's prediction
                w_new = y + (q[:, 4] - p_hist[:, ch.index[j]]) if hold == "predictor" else y
                x_hat = q[:, 0] + q[:, 3]
                q[:, 3] = np.where(ok, w_new, q[:, 3])
                q[:, 0] = np.where(ok, x_hat - q[:, 3], q[:, 0])

        cache: dict[tuple[float, float], tuple[np.ndarray, np.ndarray]] = {}

        def flows(vk: np.ndarray, dt: float):
            """``(eh^T, e^T)``, ``(5, 5)`` or ``(N, 5, 5)`` when runs differ in speed."""
            def one(v):
                key = (v, dt)
                if key not in cache:
                    eh, e = linear_flows(v, kappa, theta, gain, hold, dt)
                    cache[key] = (np.ascontiguousarray(eh.T), np.ascontiguousarray(e.T))
                return cache[key]
            if vk.min() == vk.max():
                return one(float(vk[0]))
            vals, inv = np.unique(vk, return_inverse=True)
            fl = [one(float(x)) for x in vals]
            return np.stack([f[0] for f in fl])[inv], np.stack([f[1] for f in fl])[inv]

        def record(k: int) -> None:  # the transformed state (x_hat, s2, s3) and zeta
            rec.record(k, np.stack([q[:, 0] + q[:, 3], q[:, 1], q[:, 2]], -1), zeta=zeta)

        reset(0)
        record(0)
        with np.errstate(all="ignore"):
            for k in range(T - 1):
                dt = float(times[k + 1] - times[k])
                eht, et = flows(v_all[:, k], dt)
                qn = observer_step(q, eht, et, zeta * u_all[:, k], dt)
                finite = np.isfinite(qn).all(-1)
                if not finite.all():  # a run stops; the stopped runs keep this step's start
                    rec.stop(k + 1, ~finite, STATUS_DIVERGED, "non-finite estimate at t = {t:.3f} s")
                    qn = rec.hold(qn, q)
                q = qn
                # zeta: flip where the estimate passes gamma = pi/2 + n pi while the shaft rotates
                root = np.sqrt(np.maximum(1.0 - q[:, 1] ** 2 - q[:, 2] ** 2, 0.0))
                inband = root < s.zeta_eps
                low = np.where(inband & armed, np.minimum(low, root), np.inf)
                flip = armed & inband & (root > low + rise) & (np.abs(u_all[:, k]) > s.zeta_u_min) & rec.alive
                if flip.any():
                    zeta = np.where(flip, -zeta, zeta)
                    flips += flip
                armed = (armed & ~flip) | ~inband
                p_hist[:, k + 1] = q[:, 4]
                reset(k + 1)
                record(k + 1)
        out_q, zetas = rec.states, rec.series["zeta"]
        clipped = (np.abs(out_q[..., 1]) > 1.0).sum(-1)
        with np.errstate(all="ignore"):
            xh, bh, gh = from_transformed(out_q, zetas)
            states = np.stack([xh, bh, wrap_angle(gh)], -1)
        if radius >= 1.0:  # the estimate cannot converge, whether or not it overflowed yet
            why = (f"sampled loop unstable: theta = {theta:g} with samples every {period:g} s "
                   f"(spectral radius {radius:.3g} >= 1); stable up to theta ~ "
                   f"{largest_stable_theta(vmax, kappa, gain, period):.3g}, or use hold: zoh")
            rec.reason[:] = [why + (f"; {r}" if r else "") for r in rec.reason]
            rec.status[:] = STATUS_DIVERGED
        return rec.posterior(
            ESTIMATED, (model.length_unit, "rad", "rad"), angle_states=("beta", "gamma"), state=states,
            extras={"s": out_q, "zeta": zetas, "zeta_flips": flips, "s2_clipped_steps": clipped},
            attrs={
                "not_estimated": "alpha, y, z: not observable from x",
                "theta": theta, "gain": list(gain), "kappa": kappa, "hold": hold, "measurement": ch_name,
                "zeta_eps": s.zeta_eps, "hurwitz": bool(is_hurwitz(max(vmax, 1e-12), max(kappa, 1e-300), gain)),
                "sample_period": period, "sampled_loop_radius": radius,
                # continuous-time error poles theta * eig(A + L C) at the largest insertion speed, 1/s
                "error_poles": np.sort(theta * np.linalg.eigvals(error_matrix(vmax, kappa, gain)).real).tolist(),
            },
        )
