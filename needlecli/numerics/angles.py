"""The one tested place for angle wrapping."""

from __future__ import annotations

import numpy as np


def wrap_angle(a: np.ndarray | float) -> np.ndarray:
    """Wrap angles to [-pi, pi). Works on any shape."""
    a = np.asarray(a)
    w = a - (2.0 * np.pi) * np.floor((a + np.pi) * (0.5 / np.pi))  # floor: 3x faster than ``%`` here
    # rounding at the cut can leave w one ulp outside [-pi, pi) (either side, depending on the formula)
    return np.maximum(w - 2.0 * np.pi * (w >= np.pi), -np.pi)


def angle_diff(a: np.ndarray | float, b: np.ndarray | float) -> np.ndarray:
    """Wrapped difference ``a - b`` in [-pi, pi)."""
    return wrap_angle(np.asarray(a) - np.asarray(b))
