"""The one tested place for angle wrapping."""

from __future__ import annotations

import numpy as np


def wrap_angle(a: np.ndarray | float, out: np.ndarray | None = None) -> np.ndarray:
    """Wrap angles to [-pi, pi). Works on any shape. ``out`` (float64, ``a``'s shape; may be ``a``
    itself): written in place, the same numbers, without temporaries the size of ``a``."""
    if out is not None:
        return _wrap_into(np.asarray(a), out)
    a = np.asarray(a)
    w = a - (2.0 * np.pi) * np.floor((a + np.pi) * (0.5 / np.pi))  # floor: 3x faster than ``%`` here
    # rounding at the cut can leave w one ulp outside [-pi, pi) (either side, depending on the formula)
    return np.maximum(w - 2.0 * np.pi * (w >= np.pi), -np.pi)


def _wrap_into(a: np.ndarray, out: np.ndarray) -> np.ndarray:
    """:func:`wrap_angle` into ``out``, operation for operation (bit for bit the same)."""
    t = np.add(a, np.pi)
    np.multiply(t, 0.5 / np.pi, out=t)
    np.floor(t, out=t)
    np.multiply(t, 2.0 * np.pi, out=t)
    np.subtract(a, t, out=out)
    cut = np.greater_equal(out, np.pi)  # there w - 2 pi (and w - 0 = w elsewhere)
    np.subtract(out, 2.0 * np.pi, out=out, where=cut)
    return np.maximum(out, -np.pi, out=out)


def angle_diff(a: np.ndarray | float, b: np.ndarray | float) -> np.ndarray:
    """Wrapped difference ``a - b`` in [-pi, pi)."""
    return wrap_angle(np.asarray(a) - np.asarray(b))


def sincos(a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(sin a, cos a)`` from one tangent of the half angle: ``t = tan(a/2)``,
    ``sin a = 2t / (1 + t^2)``, ``cos a = (1 - t^2) / (1 + t^2)``.

    numpy's float64 ``tan`` is vectorised (SIMD) where ``sin`` and ``cos`` are not, so this is about twice as
    fast as ``np.sin(a), np.cos(a)`` on the models' hot path; within 2.3e-16 of them in absolute value (2 ulp
    relative for sin), exact at 0 and +-pi, finite for any finite angle (``tan(a/2)`` never overflows in
    float64), and analytic, so complex-step derivatives stay exact.
    """
    a = np.asarray(a)
    if a.ndim == 0:  # numpy turns 0-d results into scalars, which cannot be written in place
        s, c = sincos(a.reshape(1))
        return s[0], c[0]
    t = a * 0.5
    np.tan(t, out=t)
    t2 = t * t
    r = t2 + 1.0
    np.divide(1.0, r, out=r)
    t += t
    t *= r  # sin
    np.subtract(1.0, t2, out=t2)
    t2 *= r  # cos
    return t, t2
