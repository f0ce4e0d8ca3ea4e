"""Time integration and Jacobians of vector fields ``f(x, u) -> x'`` batched over leading axes."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

VectorField = Callable[[np.ndarray], np.ndarray]


def rk4_step(f: VectorField, x: np.ndarray, dt: float | np.ndarray) -> np.ndarray:
    """One classical Runge-Kutta step of ``x' = f(x)`` (inputs held over the step).

    Parameters
    ----------
    f : callable
        ``f(x) -> dx`` with ``x`` of shape ``(..., n)``.
    x : ndarray, shape (..., n)
    dt : float or ndarray broadcastable to ``(..., 1)``
    """
    # one stage buffer and one accumulator, updated in place: few temporaries on the hot path
    half = 0.5 * dt
    k = f(x)
    z = k * half
    z += x
    k2 = f(z)
    acc = k + k2  # k1 + 2 k2 + 2 k3 + k4, accumulated
    acc += k2
    np.multiply(k2, half, out=z)
    z += x
    k = f(z)
    acc += k
    acc += k
    np.multiply(k, dt, out=z)
    z += x
    acc += f(z)
    acc *= dt / 6.0
    acc += x
    return acc


def complex_step_jacobian(f: VectorField, x: np.ndarray, h: float = 1e-30) -> np.ndarray:
    """Jacobian ``df/dx`` of shape ``(..., m, n)`` by the complex step, exact to rounding.

    ``f`` must be analytic in ``x`` (no ``abs``, no conjugation, no wrapping) and broadcast over a
    leading batch axis. All ``n`` perturbations are evaluated in one call (an extra axis, no loop).
    """
    x = np.asarray(x, dtype=float)
    n = x.shape[-1]
    xc = x[..., None, :] + 1j * h * np.eye(n)  # (..., n_pert, n)
    fx = f(xc)  # (..., n_pert, m)
    return np.swapaxes(fx.imag / h, -1, -2)


def finite_difference_jacobian(f: VectorField, x: np.ndarray, eps: float = 1e-6) -> np.ndarray:
    """Central finite-difference Jacobian ``(..., m, n)``; a second method to check analytic ones."""
    x = np.asarray(x, dtype=float)
    n = x.shape[-1]
    step = eps * np.maximum(1.0, np.abs(x))[..., None, :] * np.eye(n)
    fp = f(x[..., None, :] + step)
    fm = f(x[..., None, :] - step)
    d = np.diagonal(step, axis1=-2, axis2=-1)[..., :, None]
    return np.swapaxes((fp - fm) / (2.0 * d), -1, -2)
