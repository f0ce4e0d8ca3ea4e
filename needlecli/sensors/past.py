r"""Measurements of the past: where the needle was, computed from the state now.

A bevel-tip needle follows its tip (follow-the-leader): the shaft lies on the path the tip has
travelled. Two kinds of samples describe that past rather than the tip now:

* a **transverse image plane** sees where the *shaft* crosses it, which is the tip only when the plane
  happens to be at the tip (:mod:`needlecli.sensors.transverse`);
* a **delayed sample**, taken at ``t`` and available at ``t + latency``, describes the state at ``t``.

What the filter keeps of the past, and why
------------------------------------------
**The arc back from the tip** (:func:`arc_back`, :func:`plane_crossing`): the tip's pose at an inserted
length ``s`` behind the tip, from the state's own orientation and curvature. The body twist per unit of
insertion ``xi = (omega, nu)`` (angular, linear) is read off the model's equations at unit insertion
speed and every other input zero (:func:`body_twist`: a complex-step derivative of the tip's pose along
the vector field, exact to rounding); held constant, the pose ``s`` back is the exponential of the twist,

.. math::  R(s) = R\,\exp(s[\omega]_\times), \qquad p(s) = p + R\,s\,V(s\omega)\,\nu,
           \qquad V(\phi) = I + \frac{1 - \cos\theta}{\theta^2}[\phi]_\times + \frac{\theta - \sin\theta}{\theta^3}[\phi]_\times^2

(``theta = |phi|``; ``s < 0`` behind the tip, ``s > 0`` the arc continued ahead). For the unicycle
models without shaft rotation this is the circle of radius ``1 / kappa`` the tip has travelled: exact
while the curvature is constant, which is the models' own assumption between two filter ticks. It
costs nothing to carry (no extra states) and is the same function of the state in every observer and in
EM. The alternative, past states carried as stochastic clones, is exact for any motion but grows the
state by a clone per plane position still in view (a scanning probe revisits the shaft over metres of
probe travel) and needs bookkeeping of when each clone leaves the image; it is not used.

A plane ``{X : n . (X - o) = 0}`` crosses the arc where ``g(s) = n . (p(s) - o) = 0``; Newton's method
from the straight line's crossing ``s_0 = -g(0) / g'(0)`` (``g'(s) = n . R(s) nu``) with a fixed number of
steps (:data:`NEWTON_STEPS`, so that the result is the same smooth function at every sigma point) gives
it to rounding for any crossing within a quarter turn of the arc.

**The model run back over a latency** (:func:`retrodict`): a delayed sample updates the state it was
taken from, the current state (each sigma point, or the EKF's linearisation point) carried back over
the latency by the model's own RK4 step with the recorded inputs and a negative time step. For a
follow-the-leader model this is the arc back by the inserted length of the latency (the same pose);
for any model it is the deterministic part of the past state, the process noise of the latency
neglected (Bar-Shalom's one-step retrodiction; Stone Soup's out-of-sequence examples keep the state at
the sample's time instead). A stream whose clock is off by an unknown ``delta`` is the same with ``delta``
a constant state that EM estimates (temporal calibration: ``measurements.<c>.time_offset`` of a fit, the
first-order ``x - delta f(x, u)`` in :class:`needlecli.fitting.statespace.MeasurementModel`).

All functions are pure and batched over leading axes; :class:`PathSensor` is the base of the sensors whose
``h`` is computed on the arc back from the tip.
"""

from __future__ import annotations

import numpy as np

from needlecli.numerics import hat, vee
from needlecli.sensors.base import Sensor

#: Newton steps of :func:`plane_crossing` (from the straight line's crossing: the error after k steps is
#: about ``(kappa s)^(2^k)`` of ``s``; 6 reach rounding for any crossing within a quarter turn)
NEWTON_STEPS = 6
_SMALL = 1e-4  # below this angle (rad) the series of V and exp


def _coefficients(theta: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``sin(t) / t``, ``(1 - cos t) / t^2`` and ``(t - sin t) / t^3`` of angles ``theta (...)``, by their
    series below :data:`_SMALL` (exact to rounding there)."""
    t = np.asarray(theta)
    small = np.abs(t) < _SMALL
    ts = np.where(small, 1.0, t)
    t2 = t * t
    a = np.where(small, 1.0 - t2 / 6.0, np.sin(ts) / ts)
    b = np.where(small, 0.5 - t2 / 24.0, (1.0 - np.cos(ts)) / (ts * ts))
    c = np.where(small, 1.0 / 6.0 - t2 / 120.0, (ts - np.sin(ts)) / (ts * ts * ts))
    return a, b, c


def body_twist(model, x: np.ndarray, params) -> tuple[np.ndarray, np.ndarray]:
    """The tip's body twist per unit of insertion at states ``x (..., n)``: ``(omega (..., 3), nu (..., 3))``
    with ``R^T dR/ds = [omega]_x`` and ``R^T dp/ds = nu``, from the model's vector field at unit insertion
    speed (``model.insertion_input`` = 1) and every other input zero, by a complex step along it (the models'
    equations are analytic: their default Jacobian is a complex step too). ``params``: the model's parameters
    (name -> array broadcastable to ``x.shape[:-1]``)."""
    x = np.asarray(x, dtype=float)
    if x.ndim == 1:  # the models' in-place kernels want a batch axis
        omega, nu = body_twist(model, x[None], params)
        return omega[0], nu[0]
    u = np.zeros(model.m)
    u[model.input_slice(model.insertion_input)] = 1.0
    h = 1e-20
    with np.errstate(all="ignore"):
        f = np.real(model.f(x, u, params))
        xc = x + 1j * h * f
        R = model.tip_rotation(x)
        dR = np.imag(model.tip_rotation(xc)) / h
        dp = np.imag(model.tip_position(xc)) / h
    Rt = np.swapaxes(R, -1, -2)
    W = Rt @ dR
    omega = vee(0.5 * (W - np.swapaxes(W, -1, -2)))
    nu = (Rt @ dp[..., None])[..., 0]
    return omega, nu


def arc_back(p: np.ndarray, R: np.ndarray, omega: np.ndarray, nu: np.ndarray, s: np.ndarray):
    """The pose on the arc of constant body twist ``(omega, nu) (..., 3)`` through ``(p (..., 3), R (..., 3, 3))``
    at inserted length ``s (...)`` from it (negative: behind the tip): ``(p(s) (..., 3), R(s) (..., 3, 3))``
    (module docstring)."""
    s = np.asarray(s, dtype=float)
    phi = s[..., None] * omega
    theta = np.linalg.norm(phi, axis=-1)
    a, b, c = _coefficients(theta)
    K = hat(phi)
    K2 = K @ K
    eye = np.eye(3)
    E = eye + a[..., None, None] * K + b[..., None, None] * K2
    V = eye + b[..., None, None] * K + c[..., None, None] * K2
    d = s[..., None] * (V @ nu[..., None])[..., 0]
    return p + (R @ d[..., None])[..., 0], R @ E


def plane_crossing(p: np.ndarray, R: np.ndarray, omega: np.ndarray, nu: np.ndarray, origin: np.ndarray,
                   normal: np.ndarray, steps: int = NEWTON_STEPS) -> tuple[np.ndarray, np.ndarray]:
    """Where the arc through the tip ``(p (..., 3), R (..., 3, 3))`` with body twist ``(omega, nu) (..., 3)``
    crosses the plane through ``origin (..., 3)`` with normal ``normal (..., 3)``: ``(X (..., 3), s (...))``,
    ``s`` the inserted length from the tip (negative: behind it; positive: the plane is ahead of the tip and
    the arc is continued to it). NaN where the arc runs parallel to the plane."""
    n = normal / np.linalg.norm(normal, axis=-1, keepdims=True)
    g0 = np.einsum("...i,...i->...", n, p - origin)
    t0 = (R @ nu[..., None])[..., 0]
    d0 = np.einsum("...i,...i->...", n, t0)
    with np.errstate(all="ignore"):
        s = -g0 / d0
        for _ in range(steps):
            X, Rs = arc_back(p, R, omega, nu, s)
            g = np.einsum("...i,...i->...", n, X - origin)
            dg = np.einsum("...i,...i->...", n, (Rs @ nu[..., None])[..., 0])
            s = s - g / dg
    X, _ = arc_back(p, R, omega, nu, s)
    return X, s


def retrodict(model, x: np.ndarray, inputs: np.ndarray, params, dt: float) -> np.ndarray:
    """States ``x (..., n)`` carried back over the grid steps whose inputs are ``inputs (..., L, m)`` (oldest
    first, each held over one step of ``dt``): the model's RK4 step with ``-dt``, newest step first. The
    deterministic part of the state ``L dt`` earlier (module docstring)."""
    for j in range(inputs.shape[-2] - 1, -1, -1):
        x = model.step(x, inputs[..., j, :], params, -dt)
    return x


class PathSensor(Sensor):
    """A sensor that measures the needle's past path through the arc back from the tip (a transverse plane's
    crossing, the inserted length): it needs the tip's pose and the model's insertion input, whose unit
    speed gives the body twist (:func:`body_twist`)."""

    requires = ("tip_position", "tip_rotation")

    def check_model(self):
        why = super().check_model()
        if why is None and self.model.insertion_input not in self.model.input_names:
            return (f"sensor {self.registered_name!r} needs the insertion input of model "
                    f"{self.model.registered_name!r}")
        return why

    def path_twist(self, x: np.ndarray):
        """The tip's position ``(..., 3)``, rotation ``(..., 3, 3)`` and body twist per unit of insertion
        ``(omega, nu)`` ``(..., 3)`` each at states ``x (..., n)``, with the model's parameters."""
        model = self.model
        omega, nu = body_twist(model, x, model.param_arrays())
        return model.tip_position(x), model.tip_rotation(x), omega, nu
