"""Fitted constants in their canonical form: a symmetry of the model leaves the path unchanged, and the
fit reports the representative a reader expects.

The unicycle's ``(kappa, gamma)`` and ``(-kappa, gamma + pi)`` give the same path (its body rotated by pi
about the tangent; the model declares it with ``curvature_roll_state``). EM, which estimates kappa as an
unconstrained augmented state, may settle on the negative branch when the initial roll is off by about
pi; such a trial is reported with ``|kappa|`` and the roll + pi, and flagged, never as a curvature below
zero without a word.
"""

from __future__ import annotations

import numpy as np

from needlecli.numerics import wrap_angle


def flip_negative_curvature(names: tuple[str, ...], model_cls, result) -> np.ndarray:
    """In place on an :class:`~needlecli.fitting.em.EMResult` whose states are ``names``: trials whose
    fitted curvature is negative get ``-kappa`` and ``roll + pi`` in ``x0`` and the smoothed and filtered
    trajectories, and the signs of the curvature's covariances with the other states flipped (``T P T``,
    ``T = diag(..., -1, ...)``). Returns the mask ``(N,)`` of flipped trials (all False where the model
    has no such symmetry or the curvature is not fitted)."""
    c, roll = model_cls.curvature_param, getattr(model_cls, "curvature_roll_state", None)
    N = result.x0.shape[0]
    if roll is None or c not in names or roll not in names:
        return np.zeros(N, dtype=bool)
    ic, ir = names.index(c), names.index(roll)
    neg = np.asarray(result.x0[:, ic] < 0)
    if not neg.any():
        return neg
    for arr in (result.x0, result.m, result.filtered):
        a = arr[neg]
        a[..., ic] = -a[..., ic]
        a[..., ir] = wrap_angle(a[..., ir] + np.pi)
        arr[neg] = a
    for arr in (result.P, result.Qc):
        a = arr[neg]
        a[..., ic, :] = -a[..., ic, :]
        a[..., :, ic] = -a[..., :, ic]
        arr[neg] = a
    note = f"{c} < 0 fitted: reported as -{c} with {roll} + pi (the same path)"
    result.reason = np.array([(f"{r}; {note}" if r else note) if flip else r
                              for r, flip in zip(result.reason.tolist(), neg)])  # a new array: the old one's
    # fixed string width would cut the note
    return neg
