r"""Invariant observer on SO(3) of the SO(3) observer paper (sec. IV): the full tip orientation from the measured tangent.

.. math::
    \hat R' = \hat R\,(\hat w + g),\quad g = k\,\hat R^T \widehat{(y \times \hat y)}\,\hat R,\quad
    \hat y = \hat R e_3,

with the known body angular velocity :math:`w = (\kappa v, 0, u)` (inputs ``v``, ``u`` and the observer's
curvature) and ``y`` the measured tangent :math:`R e_3` (our frame; the SO(3) observer paper puts it on its x axis). On
SO(3) :math:`\hat R g = k \widehat{(y \times \hat y)} \hat R`, so the correction turns :math:`\hat y` by
:math:`k (y \times \hat y) \times \hat y`: toward ``y`` only for **k < 0** (the paper's proof, eq. 23).
The config gives the magnitude (``gain: 0.65``, the SO(3) observer paper's number, 1/s, independent of the length
unit); the observer uses ``k = -gain``. Several tangent channels add their cross products (``weight``
each).

Integration: RK4 on the 9 entries over each grid step (inputs and measurements held), then one Newton
step toward the polar factor, ``R <- 1.5 R - 0.5 R R^T R``, which squares the RK4 step's departure from
SO(3) (about 1e-13), so ``|R^T R - I|`` stays at rounding level. Measurements are held from the step at
which they become available until the next one (zero-order hold; a latency is not compensated).

Observability (the SO(3) observer paper, Lemma III.1): the rotation about the measured axis is recovered only through
angular velocity perpendicular to it, ``|w x e3| = kappa |v|`` here. A run whose accumulated
perpendicular rotation ``int |w x e3| dt`` stays below ``min_excitation`` (rad) cannot converge: its
status is ``unobservable`` (not ``ok``), with the reason, and ``needle evaluate`` leaves it out.
"""

from __future__ import annotations

from typing import Literal

import numpy as np
from pydantic import Field, field_validator

from needlecli.initial import start_state
from needlecli.models import NotMeasurable
from needlecli.numerics import matrix_to_euler_xyz, so3_exp
from needlecli.observers.base import (
    OBSERVERS,
    STATUS_DIVERGED,
    STATUS_UNOBSERVABLE,
    EstimationProblem,
    Observer,
    ObserverSettings,
    Posterior,
)
from needlecli.observers.record import RunRecorder
from needlecli.schema import NonNeg, Positive, Strict

R_NAMES = tuple(f"R{i}{j}" for i in range(1, 4) for j in range(1, 4))
E_MEAS = np.array([0.0, 0.0, 1.0])  # body axis a tangent sensor measures: y = R e3


# ---------------------------------------------------------------------------------------------- maths
# The step works on components first and runs last (``R (3, 3, N)``, ``w (3, N)``, ``y (c, 3, N)``):
# every operation is then on contiguous (N,) rows, about 3x faster than (N, 3, 3) stacks for this size.
def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``a x b`` over the first component axis of ``(..., 3, N)`` arrays (written out)."""
    return np.stack([a[..., 1, :] * b[..., 2, :] - a[..., 2, :] * b[..., 1, :],
                     a[..., 2, :] * b[..., 0, :] - a[..., 0, :] * b[..., 2, :],
                     a[..., 0, :] * b[..., 1, :] - a[..., 1, :] * b[..., 0, :]], -2)


def _matmul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``a @ b`` for ``(3, 3, N)`` stacks."""
    return np.einsum("ikn,kjn->ijn", a, b)


def invariant_field(r: np.ndarray, w: np.ndarray, y: np.ndarray, b: np.ndarray, k: float) -> np.ndarray:
    """``R_hat' = R hat(w) + k sum_c hat(y_c x R b_c) R``, layout components first: ``R_hat (3, 3, N)``,
    body angular velocity ``w (3, N)``, measured unit vectors ``y (c, 3, N)`` and the body vectors
    ``b (c, 3, N)`` they are images of (``y = R b``; zeros for channels without a sample). On SO(3)
    ``hat(y x y_hat) R = R (R^T hat(y x y_hat) R)``: the SO(3) observer paper's ``R_hat g``."""
    y_hat = np.einsum("ijn,cjn->cin", r, b)
    c = _cross(y, y_hat).sum(0)
    out = np.empty_like(r)
    out[:, 0] = r[:, 1] * w[2] - r[:, 2] * w[1]  # R hat(w), by columns
    out[:, 1] = r[:, 2] * w[0] - r[:, 0] * w[2]
    out[:, 2] = r[:, 0] * w[1] - r[:, 1] * w[0]
    out[0] += k * (c[1] * r[2] - c[2] * r[1])  # k hat(c) R, by rows
    out[1] += k * (c[2] * r[0] - c[0] * r[2])
    out[2] += k * (c[0] * r[1] - c[1] * r[0])
    return out


def orthonormalize_soa(r: np.ndarray) -> np.ndarray:
    """One Newton step toward the polar factor, ``1.5 R - 0.5 R R^T R``, for ``(3, 3, N)``."""
    return 1.5 * r - 0.5 * _matmul(np.einsum("ikn,jkn->ijn", r, r), r)


def rk4_so3_step(r: np.ndarray, w: np.ndarray, y: np.ndarray, b: tuple, k: float, dt: float) -> np.ndarray:
    """RK4 on the 9 entries, then one Newton step back onto SO(3) (layout of :func:`invariant_field`).
    ``w`` and ``y`` are held over the step; ``b = (b0, b_half, b1)`` are the body vectors at the start,
    middle and end of the step (a held world direction turns in the body frame as the body rotates)."""
    k1 = invariant_field(r, w, y, b[0], k)
    k2 = invariant_field(r + 0.5 * dt * k1, w, y, b[1], k)
    k3 = invariant_field(r + 0.5 * dt * k2, w, y, b[1], k)
    k4 = invariant_field(r + dt * k3, w, y, b[2], k)
    return orthonormalize_soa(r + (dt / 6.0) * (k1 + 2.0 * (k2 + k3) + k4))


def rotate_vectors(vec: np.ndarray, rotvec: np.ndarray) -> np.ndarray:
    """``exp(hat(rotvec)) vec`` by Rodrigues' formula, ``vec (c, 3, N)``, ``rotvec (3, N)``."""
    th = np.sqrt(np.sum(rotvec * rotvec, 0))
    a = rotvec / np.where(th > 0, th, 1.0)
    cos, sin = np.cos(th), np.sin(th)
    return vec * cos + _cross(a, vec) * sin + a * (np.sum(a * vec, -2, keepdims=True) * (1.0 - cos))


def orthonormality_error(r: np.ndarray) -> np.ndarray:
    """``max |R^T R - I|`` per matrix, ``r (..., 3, 3)`` (the usual layout)."""
    d = np.swapaxes(r, -1, -2) @ r - np.eye(3)
    return np.abs(d).max(axis=(-2, -1))


def perturb_rotation(r0: np.ndarray, angle: np.ndarray, axis: np.ndarray) -> np.ndarray:
    """``R0 exp(angle hat(axis))``: an error of ``angle`` about the body ``axis (..., 3)`` (unit)."""
    return r0 @ so3_exp(angle[..., None] * axis)


# ---------------------------------------------------------------------------------------------- settings
class SO3Init(Strict):
    """Initial estimate: the true initial rotation (``from: truth``) or the model's default pose
    (``from: nominal``), times an error rotation of ``error_deg`` (a number, or ``[lo, hi]`` drawn
    uniformly per run) about the measured body axis (``axis: measured``: the estimated and the measured
    tangent then agree, as in the SO(3) observer paper's Fig. 3) or about a uniformly random body axis per run."""

    from_: Literal["truth", "nominal"] = Field("truth", alias="from", description="start from the true initial "
                                              "rotation (truth) or the model's default pose (nominal)")
    error_deg: NonNeg | tuple[NonNeg, NonNeg] = Field(0.0, description="angle of the initial error rotation, deg (at "
                                                      "most 180): a number, or [lo, hi] drawn uniformly per run")
    axis: Literal["measured", "random"] = Field("measured", description="axis of the error rotation: the measured body "
                                                "axis (the tangent, as the SO(3) observer paper's Fig. 3) or a random axis per run")

    @field_validator("error_deg")
    @classmethod
    def _range(cls, v):
        vals = v if isinstance(v, tuple) else (v,)
        if any(x > 180.0 for x in vals):
            raise ValueError("a rotation error is at most 180 deg")
        if isinstance(v, tuple) and v[1] < v[0]:
            raise ValueError("error_deg range must be [lo, hi] with lo <= hi")
        return v


class TangentSpec(Strict):
    """How the observer uses one tangent channel."""

    weight: Positive = Field(1.0, description="multiplies the gain for this channel's cross product")


class SO3InvariantSettings(ObserverSettings):
    type: Literal["so3_invariant"]
    gain: Positive = Field(0.65, description="|k|, 1/s (the correction uses k = -gain)")
    kappa: NonNeg | None = Field(None, description="the observer's curvature (default: the model's)")
    measurements: dict[str, TangentSpec] = Field(
        default_factory=dict, description="tangent channels by sensor name (default: every tangent sensor)"
    )
    init: SO3Init = Field(default_factory=SO3Init, description="the initial estimate: a start rotation times an "
                                                               "error rotation")
    min_excitation: NonNeg = Field(
        0.01, description="rad of rotation perpendicular to the measured axis a run needs to be observable"
    )


# ---------------------------------------------------------------------------------------------- observer
@OBSERVERS.register("so3_invariant")
class SO3InvariantObserver(Observer):
    """The invariant observer on SO(3) (`so3-invariant`), batched over runs (module docstring for the equations)."""

    Settings = SO3InvariantSettings
    takes_common_start = True  # with a common start, init.error_deg does not apply

    @classmethod
    def check(cls, settings, model, sensors):
        out = []
        for k in ("v", "u"):
            if k not in model.input_names or model.input_sizes.get(k) != 1:
                return [(("type",), f"the SO(3) observer needs the scalar inputs v and u; model "
                                    f"{model.registered_name!r} has {', '.join(model.input_names)}")]
        if not model.provides("tip_rotation"):
            return [(("type",), f"model {model.registered_name!r} has no tip orientation to estimate")]
        if settings.kappa is None and "kappa" not in model.Params.model_fields:
            out.append((("kappa",), f"model {model.registered_name!r} has no kappa: give the observer's"))
        tangents = [n for n, s in sensors.items() if s.registered_name == "tangent"]
        for name in settings.measurements:
            if name not in sensors:
                known = ", ".join(sensors) or "none"
                out.append((("measurements", name), f"no sensor named {name!r}; sensors: {known}"))
            elif name not in tangents:
                out.append((("measurements", name), f"sensor {name!r} is not a tangent sensor"))
        if not settings.measurements and not tangents:
            out.append((("measurements",), "the SO(3) observer needs a tangent sensor; there is none"))
        return out

    # ------------------------------------------------------------------ run
    def run(self, problem: EstimationProblem, rng: np.random.Generator, progress=None) -> Posterior:
        s = self.settings
        model = problem.model
        N, T = problem.n_runs, len(problem.time)
        time = problem.time
        v_all = problem.inputs[..., model.input_slice("v").start]
        u_all = problem.inputs[..., model.input_slice("u").start]
        kappa = float(s.kappa if s.kappa is not None else np.mean(problem.params["kappa"]))
        k_gain = -float(s.gain)

        # --- channels and when their samples become available
        names = list(s.measurements) or [n for n, c in problem.channels.items() if c.sensor_type == "tangent"]
        weights = np.array([s.measurements[n].weight if n in s.measurements else 1.0 for n in names])
        chans = [problem.channels[n] for n in names]
        dt_grid = float(time[1] - time[0]) if T > 1 else 1.0
        due: list[dict[int, np.ndarray]] = []
        for ch in chans:
            avail = np.ceil(ch.t_available / dt_grid - 1e-9).astype(np.int64)
            d: dict[int, np.ndarray] = {}
            for k in np.unique(avail[avail < T]):
                d[int(k)] = np.nonzero(avail == k)[0]
            due.append(d)
        y = np.zeros((len(chans), 3, N))  # held samples (zeros: none yet), weights folded in
        b = np.zeros((len(chans), 3, N))  # body vector of each held sample, transported to now
        seen = np.zeros(N, dtype=bool)
        zero = np.zeros(N)

        def body_rate(k: int) -> np.ndarray:
            return np.stack([kappa * v_all[:, k], zero, u_all[:, k]])  # (3, N)

        def refresh(k: int) -> None:
            """Samples available at grid step k; a latency is bridged by transporting e3 from the
            acquisition step with the known body rotation."""
            for c, ch in enumerate(chans):
                for j in due[c].get(k, ()):
                    val = ch.value[:, j]
                    ok = ch.valid[:, j] & np.isfinite(val).all(-1)
                    if ok.any():
                        nrm = np.linalg.norm(val[ok], axis=-1, keepdims=True)
                        y[c][:, ok] = (weights[c] * val[ok] / nrm).T
                        e = np.broadcast_to(E_MEAS[:, None], (3, N))
                        for i in range(int(ch.index[j]), k):
                            e = rotate_vectors(e, -body_rate(i) * (time[i + 1] - time[i]))
                        b[c][:, ok] = e[:, ok]
                        seen[ok] = True

        # --- initial estimate
        try:
            if problem.start is not None:  # a comparison's common start, without the SO(3) observer paper's error rotation
                r0 = np.asarray(model.tip_rotation(start_state(problem, model, problem.params)), dtype=float)
            elif s.init.from_ == "truth" and problem.initial_truth is not None:
                r0 = np.asarray(model.tip_rotation(problem.initial_truth), dtype=float)
            else:
                x0 = np.asarray(model.initial_state(problem.params), dtype=float)
                r0 = np.broadcast_to(model.tip_rotation(x0), (N, 3, 3)).copy()
        except NotMeasurable as e:
            raise ValueError(str(e)) from None
        err = s.init.error_deg if problem.start is None else 0.0
        if isinstance(err, tuple):
            angle = np.deg2rad(rng.uniform(err[0], err[1], N))
        else:
            angle = np.full(N, np.deg2rad(err))
        if s.init.axis == "measured":
            axis = np.broadcast_to(E_MEAS, (N, 3))
        else:
            a = rng.standard_normal((N, 3))
            axis = a / np.linalg.norm(a, axis=-1, keepdims=True)
        r = np.ascontiguousarray(np.moveaxis(perturb_rotation(r0, angle, axis), 0, -1))  # (3, 3, N)

        # --- observability: rotation perpendicular to the measured axis over the run
        w_perp = kappa * np.abs(v_all[:, :-1])  # |w x e3| for w = (kappa v, 0, u)
        excitation = (w_perp * np.diff(time)[None, :]).sum(-1) if T > 1 else np.zeros(N)

        rec = RunRecorder(problem, 9, covariance=False, progress=progress)  # the entries of R_hat, by rows
        refresh(0)
        rec.record(0, r.reshape(9, N).T)
        with np.errstate(all="ignore"):
            for k in range(T - 1):
                dt = float(time[k + 1] - time[k])
                w = body_rate(k)
                # a held sample is a fixed world direction: its body vector turns by -w
                b_half = rotate_vectors(b, -0.5 * dt * w)
                b_end = rotate_vectors(b, -dt * w)
                rn = rk4_so3_step(r, w, y, (b, b_half, b_end), k_gain, dt)
                b = b_end
                new = rec.stop(k + 1, ~np.isfinite(rn).all(axis=(0, 1)), STATUS_DIVERGED,
                               "non-finite estimate at t = {t:.3f} s")
                if new.any():  # the stopped runs keep this step's start
                    rn = rec.hold(rn, r, axis=-1)
                r = rn
                refresh(k + 1)
                rec.record(k + 1, r.reshape(9, N).T)
        mats = rec.states.reshape(N, T, 3, 3)
        states = np.concatenate([rec.states, matrix_to_euler_xyz(mats)], -1)
        ortho = np.zeros(N)
        for k0 in range(0, T, 512):  # max over the run of |R^T R - I|, in chunks
            np.maximum(ortho, orthonormality_error(mats[:, k0 : k0 + 512]).max(-1), out=ortho)

        rec.stop(None, excitation < s.min_excitation, STATUS_UNOBSERVABLE, [
            f"not observable: angular velocity parallel to the measured vector (rotation about other axes "
            f"over the run {np.rad2deg(e):.3g} deg < {np.rad2deg(s.min_excitation):.3g} deg)" for e in excitation])
        rec.stop(None, ~seen, STATUS_UNOBSERVABLE, "not observable: no valid tangent measurement")
        return rec.posterior(
            R_NAMES + ("alpha", "beta", "gamma"), ("1",) * 9 + ("rad", "rad", "rad"),
            angle_states=("alpha", "beta", "gamma"), state=states,
            extras={"orthonormality_error": ortho, "excitation": excitation, "initial_error": angle},
            attrs={"gain": k_gain, "kappa": kappa, "measurements": names, "measured_axis": "e3",
                   "min_excitation": s.min_excitation},
        )
