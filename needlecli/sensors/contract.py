"""What a sensor's measurement must be, checked against the truth it measured (every sensor, built-in or a
plug-in, after every ``measure``: :mod:`needlecli.experiments.simulation.components`).

A :class:`~needlecli.sensors.base.MeasurementStream` of ``M`` samples of ``m`` channels, for ``N`` runs
on a grid of ``T`` times:

- ``names`` and ``units``: ``m`` texts each;
- ``t``, ``t_available`` real numbers ``(M,)``, finite; ``index`` integers ``(M,)`` in ``[0, T)``;
- ``value`` and ``sigma`` real numbers ``(N, M, m)``; ``valid`` true/false values ``(N, M)``;
- where a sample is valid, its value and its sigma finite and the sigma not negative (an invalid sample's
  value is NaN);
- ``attrs`` a mapping.

The first problem is returned in words; the caller names the sensor.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from needlecli.guard import texts, what
from needlecli.sensors.base import MeasurementStream


def check_stream(st: object, n_runs: int, n_steps: int) -> str | None:
    """The first way ``st`` breaks the sensor contract for ``n_runs`` runs on a grid of ``n_steps`` times
    (module docstring), in words; None when it keeps it."""
    if not isinstance(st, MeasurementStream):
        return f"{what(st)}, not a MeasurementStream"
    names, units = texts(st.names), texts(st.units)
    if names is None:
        return f"names {what(st.names)}, not a list of texts"
    if units is None or len(units) != len(names):
        return f"units {what(st.units)}, not a list of texts" if units is None else \
            f"{len(units)} units for {len(names)} channel names"
    t = st.t
    if not isinstance(t, np.ndarray) or t.ndim != 1 or t.dtype.kind not in "fiu":
        return f"t {what(t)}, expected real numbers of shape (M,)"
    M, m = len(t), len(names)
    env = {"N": n_runs, "M": M, "m": m}
    for name, v, shape, kinds in (("t_available", st.t_available, ("M",), "fiu"), ("index", st.index, ("M",), "iu"),
                                  ("value", st.value, ("N", "M", "m"), "fiu"), ("valid", st.valid, ("N", "M"), "b"),
                                  ("sigma", st.sigma, ("N", "M", "m"), "fiu")):
        want = tuple(env[s] for s in shape)
        if not isinstance(v, np.ndarray) or v.dtype.kind not in kinds:
            words = {"fiu": "real numbers", "iu": "integers", "b": "true/false values"}[kinds]
            return f"{name} {what(v)}, expected {words}"
        if v.shape != want:
            syms = "(" + ", ".join(shape) + ("," if len(shape) == 1 else "") + ")"
            vals = "(" + ", ".join(map(str, want)) + ("," if len(want) == 1 else "") + ")"
            return f"{name} of shape {v.shape}, expected {syms} = {vals}"
    for name, v in (("t", t), ("t_available", st.t_available)):
        bad = np.flatnonzero(~np.isfinite(v))
        if bad.size:
            return f"{name}[{bad[0]}] = {v[bad[0]]}, not a finite time"
    bad = np.flatnonzero((st.index < 0) | (st.index >= n_steps))
    if bad.size:
        return f"index[{bad[0]}] = {st.index[bad[0]]}, outside the {n_steps} times of the grid"
    for name, v in (("value", st.value), ("sigma", st.sigma)):
        bad = st.valid & ~np.isfinite(v).all(axis=-1)
        if bad.any():
            r, j = (int(x) for x in np.argwhere(bad)[0])
            c = int(np.flatnonzero(~np.isfinite(v[r, j]))[0])
            return f"{name}[{r}, {j}, {c}] = {v[r, j, c]} for a sample marked valid (run {r}, sample {j})"
    bad = st.valid & (st.sigma < 0).any(axis=-1)
    if bad.any():
        r, j = (int(x) for x in np.argwhere(bad)[0])
        c = int(np.flatnonzero(st.sigma[r, j] < 0)[0])
        return f"a negative sigma: sigma[{r}, {j}, {c}] = {st.sigma[r, j, c]} (run {r}, sample {j})"
    if not isinstance(st.attrs, Mapping):
        return f"attrs {what(st.attrs)}, not a mapping"
    return None


