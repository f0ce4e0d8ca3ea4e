"""The one tested place for angle wrapping."""

from __future__ import annotations

import numpy as np


def wrap_angle(a: np.ndarray | float) -> np.ndarray:
    """Wrap angles to [-pi, pi). Works on any shape."""
    w = (np.asarray(a) + np.pi) % (2.0 * np.pi) - np.pi
    return w - 2.0 * np.pi * (w >= np.pi)  # ``%`` rounds to 2 pi for a just below -pi (mod 2 pi)


def angle_diff(a: np.ndarray | float, b: np.ndarray | float) -> np.ndarray:
    """Wrapped difference ``a - b`` in [-pi, pi)."""
    return wrap_angle(np.asarray(a) - np.asarray(b))
