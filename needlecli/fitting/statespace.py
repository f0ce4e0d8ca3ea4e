"""A model as a discrete state-space system on a grid of ticks, with unknown constants as states.

:class:`DiscreteModel` turns a continuous :class:`~needlecli.models.Model` into the transition between
consecutive *ticks* (a subset of the experiment's time grid: every grid step, the measurement times, or a
rate), integrated with RK4 and differentiated exactly (:func:`~needlecli.numerics.kalman.rk4_with_jacobian`
on the model's Jacobian). Model parameters named in ``augment`` (the magnetic needle EM paper: ``c`` of the MNM, ``l_inv`` of
the BiNM) become extra states with no dynamics, ``z = (x, theta)``, so that the smoother estimates them.

:class:`MeasurementModel` is one measurement channel on the same ticks: its ``h`` for the model's state,
the samples, and the linearisation ``y ~ H z + d`` (central differences: sensor functions such as a
normalised field direction are not complex-analytic).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from needlecli.kernels import twin
from needlecli.models import Model, StateSelection
from needlecli.numerics.kalman import Channel, finite_difference_h, rk4_with_jacobian
from needlecli.numerics.needle_frame import needle_basis


def make_ticks(n_grid: int, sample_indices: Sequence[np.ndarray], mode: str | float, grid_dt: float) -> np.ndarray:
    """Indices of the time grid where the filter has a state (always the first and last grid point).

    ``mode``: ``"grid"`` every grid step; ``"measurements"`` the measurement times only; a number: that
    rate in Hz, plus every measurement time (so that every sample describes a tick exactly).
    """
    if mode == "grid":
        return np.arange(n_grid)
    parts = [np.array([0, n_grid - 1])] + [np.asarray(s, dtype=np.int64) for s in sample_indices]
    if mode != "measurements":
        stride = max(1, int(round(1.0 / (float(mode) * grid_dt))))
        parts.append(np.arange(0, n_grid, stride))
    ticks = np.unique(np.concatenate(parts))
    return ticks[(ticks >= 0) & (ticks < n_grid)]


class DiscreteModel:
    """Transitions of ``model`` between ticks, for all runs at once.

    Parameters
    ----------
    model : the continuous model
    params : name -> value, scalar or (N,): the model's parameters (those in ``augment`` are only the
        default initial values of the augmented states)
    augment : parameter names carried as constant states after the model's states
    grid_dt : the time grid's step, s
    ticks : (K+1,) indices of the grid
    inputs : (N, T, m) the model's inputs on the grid, held over each grid step
    substeps : None: one RK4 step per grid step, with that step's input (the truth's own integration);
        an int s: s equal RK4 steps per tick interval with the interval's mean input (faster)
    sensor_states : ``(name, unit, decay)`` of states that belong to a sensor, not to the needle (an image
        plane's offset along the needle, :class:`MeasurementModel`'s ``offset_index``), after the augmented
        constants: ``s' = -decay s`` (an Ornstein-Uhlenbeck process with its process noise; decay 1/tau in
        1/s; 0: a constant)
    kernels : the kernels setting (``auto``, ``numba``, ``numpy``; :func:`needlecli.kernels.resolve`) of the
        transitions and of the Kalman passes over this system (``simulation.kernels``, through
        :class:`~needlecli.problem.EstimationProblem`)
    """

    def __init__(
        self,
        model: Model,
        params: dict[str, np.ndarray],
        augment: Sequence[str],
        grid_dt: float,
        ticks: np.ndarray,
        inputs: np.ndarray,
        substeps: int | None = None,
        sensor_states: Sequence[tuple[str, str, float]] = (),
        kernels: str = "auto",
    ) -> None:
        self.model = model
        self.kernels = kernels
        self._inputs = inputs
        self.augment = tuple(augment)
        self.sensor_states = tuple(s[0] for s in sensor_states)
        self.decay = np.array([float(s[2]) for s in sensor_states])
        for a in self.augment:
            if a not in model.Params.model_fields:
                raise ValueError(f"model {model.registered_name!r} has no parameter {a!r}")
            if a in model.state_names:
                raise ValueError(f"{a!r} is already a state of model {model.registered_name!r}")
        self.nx = model.n
        self.n = model.n + len(self.augment) + len(self.sensor_states)
        self.names = tuple(model.state_names) + self.augment + self.sensor_states
        self.units = (tuple(model.state_units) + tuple(param_unit(model, a) for a in self.augment)
                      + tuple(s[1] for s in sensor_states))
        self.angles = np.array([s in model.angle_states for s in self.names])
        self.N = inputs.shape[0]
        self.params = {k: np.asarray(v, dtype=float) for k, v in params.items()}
        self.ticks = np.asarray(ticks, dtype=np.int64)
        self.grid_dt = float(grid_dt)
        self.dt = np.diff(self.ticks) * self.grid_dt  # (K,)
        K = len(self.dt)
        lengths = np.diff(self.ticks)
        if substeps is None:
            L = int(lengths.max()) if K else 1
            j = np.arange(L)
            self.sub_dt = np.where(j[None, :] < lengths[:, None], self.grid_dt, 0.0)  # (K, L)
            idx = np.minimum(self.ticks[:-1, None] + j[None, :], inputs.shape[1] - 1)
            self.sub_u = inputs[:, idx]  # (N, K, L, m)
        else:
            s = int(substeps)
            self.sub_dt = np.repeat((self.dt / s)[:, None], s, axis=1)
            cs = np.concatenate([np.zeros((self.N, 1, inputs.shape[-1])), np.cumsum(inputs, axis=1)], axis=1)
            mean_u = (cs[:, self.ticks[1:]] - cs[:, self.ticks[:-1]]) / np.maximum(lengths, 1)[None, :, None]
            self.sub_u = np.repeat(mean_u[:, :, None, :], s, axis=2)  # (N, K, s, m)

    def take(self, idx: np.ndarray) -> DiscreteModel:
        """The same system for the runs ``idx`` only."""
        out = object.__new__(DiscreteModel)
        out.__dict__.update(self.__dict__)
        out.params = {k: (v[idx] if v.ndim else v) for k, v in self.params.items()}
        out.sub_u = self.sub_u[idx]
        out._inputs = self._inputs[idx]
        out.N = len(np.arange(self.N)[idx])
        return out

    # ------------------------------------------------------------------ the augmented vector field
    def _p(self, z: np.ndarray, lead: int) -> dict[str, np.ndarray]:
        """Parameters for states ``z (N, [K,] ..., n)``: per-run arrays get axes for the extra dims."""
        p = {}
        for k, v in self.params.items():
            p[k] = v.reshape(v.shape + (1,) * (lead - v.ndim)) if v.ndim else v
        for i, a in enumerate(self.augment):
            p[a] = z[..., self.nx + i]
        return p

    def f(self, z: np.ndarray, u: np.ndarray) -> np.ndarray:
        p = self._p(z, z.ndim - 1)
        dx = self.model.f(z[..., : self.nx], u, p)
        if self.n == self.nx:
            return dx
        parts = [dx, np.zeros(dx.shape[:-1] + (len(self.augment),))]
        if self.sensor_states:
            parts.append(-self.decay * z[..., self.n - len(self.sensor_states) :])
        return np.concatenate(parts, -1)

    def jac(self, z: np.ndarray, u: np.ndarray) -> np.ndarray:
        p = self._p(z, z.ndim - 1)
        x = z[..., : self.nx]
        jx = self.model.jacobian(x, u, p)
        if self.n == self.nx:
            return jx
        J = np.zeros(jx.shape[:-2] + (self.n, self.n))
        J[..., : self.nx, : self.nx] = jx
        for i, a in enumerate(self.augment):
            J[..., : self.nx, self.nx + i] = self.model.param_jacobian(x, u, p, a)
        for i, d in enumerate(self.decay):
            k = self.n - len(self.sensor_states) + i
            J[..., k, k] = -d
        return J

    # ------------------------------------------------------------------ transitions
    def transition(self, k: int, z: np.ndarray, with_jacobian: bool = True):
        """Interval ``k`` for states ``z (N, n)``: ``(z_next, A (N, n, n))``."""
        if with_jacobian and (fast := self._compiled("transition_one")) is not None:
            z, A = fast(self, k, z)
            return self._normalize(z), A
        A = np.broadcast_to(np.eye(self.n), (self.N, self.n, self.n)) if with_jacobian else None
        for j in range(self.sub_dt.shape[1]):
            h = self.sub_dt[k, j]
            if h == 0.0:
                continue
            u = self.sub_u[:, k, j]
            if with_jacobian:
                z, F = rk4_with_jacobian(lambda zz, u=u: self.f(zz, u), lambda zz, u=u: self.jac(zz, u), z, h)
                A = F @ A
            else:
                z = _rk4(lambda zz, u=u: self.f(zz, u), z, h)
        return self._normalize(z), A

    def _compiled(self, name: str):
        """The compiled twin ``name`` (``transition_one``, ``transition_all``: RK4 with its Jacobian) where
        the setting asks for it and it covers this system (sensor states: numpy), else None."""
        if self.sensor_states or not self.model.compiled_equations:
            return None
        fast = twin(name, self.kernels)
        if fast is None:
            return None
        from needlecli.kernels import kalman as compiled

        return fast if compiled.transitions_supported(self) else None

    def transition_all(self, zbar: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Every interval at once from ``zbar (N, K, n)`` (the states at ticks ``0..K-1``):
        ``(f_k(zbar_k) (N, K, n), A (N, K, n, n))``."""
        if (fast := self._compiled("transition_all")) is not None:
            return fast(self, zbar)
        z = zbar
        A = None
        for j in range(self.sub_dt.shape[1]):
            h = self.sub_dt[None, :, j]  # (1, K)
            if not np.any(h):
                continue
            u = self.sub_u[:, :, j]
            z, F = rk4_with_jacobian(lambda zz, u=u: self.f(zz, u), lambda zz, u=u: self.jac(zz, u), z, h)
            A = F if A is None else F @ A
        if A is None:
            A = np.broadcast_to(np.eye(self.n), zbar.shape + (self.n,)).copy()
        return z, A

    def propagate_mean(self, z: np.ndarray) -> np.ndarray:
        """States on every grid step ``(N, T, n)`` from states at the ticks ``z (N, K+1, n)``: each tick's
        state carried over the grid steps to the next tick with the model (the mean between ticks)."""
        N, K1, n = z.shape
        T = int(self.ticks[-1]) + 1
        out = np.empty((N, T, n))
        out[:, self.ticks] = z
        lengths = np.diff(self.ticks)
        if K1 < 2 or lengths.max() == 1:
            return out
        cur = z[:, :-1].copy()
        prev = np.arange(K1 - 1)
        with np.errstate(all="ignore"):
            for j in range(1, int(lengths.max())):
                sel = np.nonzero(lengths > j)[0]  # intervals with a grid point ticks[k] + j inside
                u = self._inputs[:, self.ticks[sel] + j - 1]
                cur = cur[:, np.searchsorted(prev, sel)]
                cur = self._normalize(_rk4(lambda zz, u=u: self.f(zz, u), cur, self.grid_dt))
                out[:, self.ticks[sel] + j] = cur
                prev = sel
        return out

    def _normalize(self, z: np.ndarray) -> np.ndarray:
        xs = z[..., : self.nx]
        x = self.model.normalize(xs)
        if x is xs:
            return z
        return np.concatenate([x, z[..., self.nx :]], -1)

    # ------------------------------------------------------------------ domain
    def left_domain(self, z: np.ndarray) -> np.ndarray:
        """Per run ``(N,)``: whether the trajectory ``z (N, K+1, n)`` enters or jumps over the model's
        singularity anywhere (NaN counts)."""
        p = self._p(z[:, 1:], z.ndim - 1)
        x = z[..., : self.nx]
        bad = self.model.left_domain(x[:, :-1], x[:, 1:], p).any(-1)
        return bad | self.model.singular(x[:, 0], self._p(z[:, 0], 1))

    def near_singular(self, z: np.ndarray) -> np.ndarray:
        p = self._p(z, z.ndim - 1)
        return self.model.near_singular(z[..., : self.nx], p).any(-1)


def _rk4(f, x, h):
    h = np.asarray(h, dtype=float)[..., None]
    k1 = f(x)
    k2 = f(x + 0.5 * h * k1)
    k3 = f(x + 0.5 * h * k2)
    k4 = f(x + h * k3)
    return x + (h / 6.0) * (k1 + 2.0 * (k2 + k3) + k4)


def param_unit(model: Model, name: str) -> str:
    field = model.Params.model_fields.get(name)
    desc = (field.description or "") if field is not None else ""
    return desc.rsplit(",", 1)[-1].strip() if "," in desc else "1"


def tangent_basis(u: np.ndarray, axis: int) -> np.ndarray:
    """Orthonormal bases ``(..., 3, 2)`` of the planes perpendicular to unit vectors ``u (..., 3)``:
    ``e1 = a x u / |a x u|``, ``e2 = u x e1`` with ``a`` the coordinate axis ``axis`` (one choice for a
    whole channel, so that the components mean the same thing at every sample)."""
    a = np.zeros(3)
    a[axis] = 1.0
    e1 = np.cross(a, u)
    e1 = e1 / np.linalg.norm(e1, axis=-1, keepdims=True)
    e2 = np.cross(u, e1)
    return np.stack([e1, e2], -1)


@dataclass
class MeasurementModel:
    """One channel on the ticks: ``h`` of the model's state, samples, noise, and its linearisation.

    h : ``h(x (..., nx)) -> (..., m)``; tick (M,) tick index of each sample; y (N, M, m); valid (N, M);
    angle (m,) bool.

    A measured direction (``unit_vector``, 3 components) is used in the plane perpendicular to the
    predicted direction: 2 components, ``y_t = E^T y``, ``h_t(z) = E^T h(z)`` with the basis ``E`` of
    :func:`tangent_basis` at the linearisation point. Along the direction itself a unit vector has no
    noise and no information (its Jacobian has no row there); kept, that component's variance would
    shrink without end in EM. ``R`` of such a channel is 2 x 2.

    ``scale`` (N, M, m) (optional): each sample's noise std relative to the channel's reference (an export's
    per-sample sigma over the nominal one). Sample ``i`` then has noise ``diag(scale_i) R diag(scale_i)``:
    the channel is whitened, ``y``, ``h`` and the linearisation divided by ``scale_i``, so that the filters
    and EM see one ``R`` (the noise of a sample at the reference sigma; EM fits it). The log-likelihood is
    that of the whitened samples (it differs by the constant ``sum log scale``).
    """

    name: str
    h: Callable[[np.ndarray], np.ndarray]
    nx: int
    tick: np.ndarray
    y: np.ndarray
    valid: np.ndarray
    angle: np.ndarray
    names: tuple[str, ...] = ()
    units: tuple[str, ...] = ()
    unit_vector: bool = False  # the components form a measured direction (renormalised)
    scale: np.ndarray | None = None  # (N, M, m) per-sample noise std over the reference (None: all 1)
    #: ``"needle"``: a position used in coordinates along and across the needle (components ``t, e1, e2``
    #: of :func:`~needlecli.numerics.needle_frame.needle_basis` at the linearisation point, reference axis
    #: ``frame_axis``), so that its R is a covariance in the needle's frame; ``tangent_fn`` is the model's
    #: tangent ``x (..., nx) -> (..., 3)``
    frame: str = "world"
    tangent_fn: Callable[[np.ndarray], np.ndarray] | None = None
    frame_axis: int = 0
    #: index of a sensor state (:class:`DiscreteModel`'s ``sensor_states``) that offsets the measured
    #: position along the needle: ``h(z) = h(x) + z[offset_index] t(x)`` (``tangent_fn`` normalised)
    offset_index: int | None = None
    #: (N, M) robust weights of the samples (Student-t EM, :mod:`needlecli.fitting.robust`): a sample of
    #: weight ``w`` is used with noise ``R / w`` (``y``, ``h`` and ``H`` scaled by ``sqrt(w)``); None: all 1
    weight: np.ndarray | None = None
    #: the kernels setting of :meth:`linearise` (:class:`DiscreteModel`'s ``kernels``)
    kernels: str = "auto"

    @property
    def m(self) -> int:
        """Components used by the filter (2 for a measured direction)."""
        return 2 if self.tangent else self.y.shape[-1]

    @property
    def tangent(self) -> bool:
        return self.unit_vector and self.y.shape[-1] == 3

    @property
    def axis(self) -> int:
        """The reference axis of the tangent bases: the one least aligned with the measured directions."""
        v = np.where(self.valid[..., None], np.abs(self.y), np.nan)
        with np.errstate(all="ignore"):
            mean = np.nanmean(v.reshape(-1, 3), axis=0)
        return int(np.argmin(np.nan_to_num(mean, nan=1.0)))

    def take(self, idx: np.ndarray) -> MeasurementModel:
        out = MeasurementModel(self.name, self.h, self.nx, self.tick, self.y[idx], self.valid[idx], self.angle,
                               self.names, self.units, self.unit_vector,
                               None if self.scale is None else self.scale[idx], self.frame, self.tangent_fn,
                               self.frame_axis, self.offset_index, None if self.weight is None else self.weight[idx],
                               self.kernels)
        if self.tangent:
            out._axis_cache = self._axis()
        return out

    def h_aug(self, z: np.ndarray) -> np.ndarray:
        x = z[..., : self.nx]
        if self.offset_index is None:
            return self.h(x)
        t = self.tangent_fn(x)
        return self.h(x) + z[..., self.offset_index, None] * t / np.linalg.norm(t, axis=-1, keepdims=True)

    def linearise(self, z: np.ndarray, y: np.ndarray | None = None, sample: int | None = None):
        """At states ``z (..., n)``: ``(h(z), H (..., m, n), d = h(z) - H z, y)`` with the measurements
        ``y (..., m_raw)`` (default: every sample, ``z`` then ``(N, M, n)``) in the same coordinates
        (whitened by ``scale``: of every sample, or of sample ``sample`` when ``z`` is ``(N, n)``; weighted
        by ``weight`` likewise)."""
        if (self.scale is None and self.weight is None and self.frame == "world" and self.offset_index is None
                and z.ndim in (2, 3) and z.shape[0] == self.valid.shape[0]):  # (whitening, weights, the needle's
            kind = measurement_kind(self)                                     # frame and offsets: numpy below)
            fast = twin("linearise", self.kernels) if kind is not None else None
            if fast is not None:
                return fast(self, kind, z, y)
        yh, H = finite_difference_h(self.h_aug, z)
        if y is None:
            y = np.where(self.valid[..., None], self.y, 0.0)
        if self.tangent or self.frame == "needle":
            if self.tangent:
                E = tangent_basis(yh / np.linalg.norm(yh, axis=-1, keepdims=True), self._axis())
            else:
                E = needle_basis(self.tangent_fn(z[..., : self.nx]), self.frame_axis)
            Et = np.swapaxes(E, -1, -2)
            yh = (Et @ yh[..., None])[..., 0]
            H = Et @ H
            y = np.where(self.valid[..., None] if y.ndim == 3 else True, (Et @ y[..., None])[..., 0], 0.0)
        if self.scale is not None:
            w = self.scale if sample is None else self.scale[:, sample]
            yh, H, y = yh / w, H / w[..., None], y / w
        if self.weight is not None:
            w = self.weight if sample is None else self.weight[:, sample]
            s = np.sqrt(np.broadcast_to(w, yh.shape[:-1]))[..., None]
            yh, H, y = s * yh, s[..., None] * H, s * y
        d = yh - (H @ z[..., None])[..., 0]
        return yh, H, d, y

    def _axis(self) -> int:
        if not hasattr(self, "_axis_cache"):
            self._axis_cache = self.axis
        return self._axis_cache

    def channel(self, R: np.ndarray, y: np.ndarray | None = None) -> Channel:
        """The channel for the filter with noise ``R``; ``y`` the measurements in the filter's coordinates
        (from :meth:`linearise`; needed for a measured direction)."""
        if y is None:
            if self.tangent or self.frame == "needle" or self.weight is not None:
                raise ValueError("a measured direction, a needle-frame or weighted channel needs its measurements "
                                 "in the filter's coordinates (from linearise)")
            y = np.where(self.valid[..., None], self.y, 0.0)
        return Channel(tick=self.tick, y=y, valid=self.valid, R=R,
                       angle=None if self.tangent else self.angle)


#: sensors whose ``h`` is the model's quantity of that name as it is (a unit vector where the model
#: declares it one: :attr:`~needlecli.models.Model.unit_vectors`)
_QUANTITY_OF = {"tangent": "tangent", "bfield": "field_direction"}


def measurement_kind(mm):
    """``(kind, idx)`` of a channel's ``h`` that the compiled linearisation
    (:func:`needlecli.kernels.kalman.fd_linearise`) covers, or None: kind 0 a selection of the states
    ``idx``; kind 1 the states ``idx`` normalised, a unit vector the model declares
    (:attr:`~needlecli.models.Model.unit_vectors`), measured as a direction (``mm.tangent``)."""
    h = mm.h
    if isinstance(h, StateSelection):
        return 0, np.asarray(h.index, dtype=np.int64)
    sensor = getattr(h, "__self__", None)
    model = getattr(sensor, "model", None)
    if sensor is None or model is None or not mm.tangent or getattr(h, "__name__", "") != "h":
        return None
    names = model.unit_vectors.get(_QUANTITY_OF.get(sensor.registered_name, ""))
    if names is None or len(names) != 3:
        return None
    return 1, np.array([model.index(k) for k in names], dtype=np.int64)
