"""What the configured sensors can observe: the states whose error a table reports but no sensor sees.

A 2D probe gives x and y of the tip; nothing it measures depends on z, so the error of z stays the start's
whatever an observer does, and the E_xyz of every observer carries it (0.85 mm of start error beside
0.10 mm across the needle). This is found before any run, from the linearised model along the nominal
insertion (the config's model, parameters, initial state and inputs, the first input case, no noise):

* the path ``x_0 .. x_K`` at ``K + 1`` nodes of the insertion (at most :data:`NODES` intervals; each
  interval one RK4 step with the interval's mean input);
* the transition Jacobians ``F_j = d x_{j+1} / d x_j`` (complex step) and each sensor's measurement
  Jacobian ``H_j`` at every node (central differences; sensors whose samples are not a function of the
  state, such as an encoder's depth, give none), rows divided by the sensor's nominal sigma;
* the stacked sensitivity of the measurements to the initial state ``S = [H_0; H_1 F_0; H_2 F_1 F_0; ...]``,
  its columns scaled to each state's unit (so that the test does not depend on mm against rad), and its
  singular value decomposition: the directions with a singular value under :data:`RANK_TOL` times the
  largest are those the measurements do not see. The norm of a unit vector (the magnetic models' h and
  B) and the orthogonality of a rotation matrix are constraints, not unknowns: their gradients join ``S``.

A state a table reports on its own (a position axis, an angle, the curvature, any other scalar state;
not the entries of a rotation or a unit vector, which tables report as one angle) is **unobservable**
when its unit vector lies in the unseen directions (``z``, with a 2D probe), and observed only in
combination with others when a part of it above :data:`SHARE` does (the message names the states of
that part). ``needle validate`` and ``needle compare`` print one warning per such state;
replayed configs (recorded logs: no nominal path in the config) are not analysed.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from needlecli.models import MODELS, Model, NotMeasurable

if TYPE_CHECKING:
    from needlecli.experiments.config.types import ExperimentConfig

log = logging.getLogger("needlecli")

#: at most this many intervals of the nominal insertion are linearised
NODES = 200
#: a singular value under this fraction of the largest is a direction the sensors do not see
RANK_TOL = 1e-9
#: a state is (partly) unseen when the projection of its unit vector on the unseen directions is above this
SHARE = 0.1


@dataclass(frozen=True)
class Unobservable:
    """A state whose error no configured sensor observes along the nominal insertion.

    Attributes
    ----------
    state : str
        The model's state.
    sensors : tuple of str
        The sensors analysed (those whose samples are a function of the state), each ``name (channels)``.
    partners : tuple of str
        The states it is seen only in combination with (empty: not seen at all).
    position : bool
        Whether it is a position axis (part of E_xyz).
    """

    state: str
    sensors: tuple[str, ...]
    partners: tuple[str, ...] = ()
    position: bool = False

    def message(self) -> str:
        seen = ", ".join(self.sensors)
        if self.partners:
            return (f"state {self.state} is observed only in combination with {', '.join(self.partners)} by the "
                    f"configured sensors ({seen}) along the nominal insertion: an estimate of it keeps part of "
                    "the start's error, whatever the observer")
        return (f"state {self.state} is not observed by the configured sensors ({seen}) along the nominal "
                "insertion: an estimate of it keeps the start's error whatever the observer"
                + (" (and so does E_xyz; E_lat and the other axes do not)" if self.position else ""))


def _scales(model: Model, x: np.ndarray) -> np.ndarray:
    """A typical size of each state ``(n,)``, to compare sensitivities in different units: 1 length unit for
    lengths, 0.1 rad for angles, the state's own magnitude (at least 1e-3) for the others."""
    out = np.ones(model.n)
    for i, (name, unit) in enumerate(zip(model.state_names, model.state_units)):
        if name in model.angle_states or unit == "rad":
            out[i] = 0.1
        elif unit != model.length_unit:
            out[i] = max(abs(float(x[i])), 1e-3)
    return out


def _reported(model: Model) -> list[int]:
    """The states a table reports on their own (not a rotation's entries nor a unit vector's components)."""
    grouped = {s for block in getattr(model, "unit_vectors", {}).values() for s in block}
    grouped |= {s for s in model.state_names if len(s) == 3 and s[0] == "R" and s[1:].isdigit()}
    return [i for i, s in enumerate(model.state_names) if s not in grouped]


def _constraints(model: Model, x: np.ndarray) -> list[np.ndarray]:
    """Gradients ``(n,)`` of the state's constraints at ``x``: each unit vector's norm, and the entries of
    ``R^T R`` of a rotation held as its nine entries."""
    rows = []
    for block in getattr(model, "unit_vectors", {}).values():
        idx = [model.index(s) for s in block]
        g = np.zeros(model.n)
        g[idx] = x[idx]
        rows.append(g)
    names = [f"R{i}{j}" for i in range(1, 4) for j in range(1, 4)]
    if all(s in model.state_names for s in names):
        idx = np.array([model.index(s) for s in names]).reshape(3, 3)
        R = x[idx]
        for a in range(3):
            for b in range(a, 3):  # d (R^T R)_ab / d R_ij = delta_jb R_ia + delta_ja R_ib
                g = np.zeros(model.n)
                for i in range(3):
                    g[idx[i, b]] += R[i, a]
                    g[idx[i, a]] += R[i, b]
                rows.append(g)
    return rows


def _jacobian(h, x: np.ndarray, scale: np.ndarray) -> np.ndarray:
    """``dh/dx (m, n)`` at ``x`` by central differences (steps of 1e-6 of each state's scale)."""
    steps = 1e-6 * scale
    xp = x[None, :] + np.diag(steps)
    xm = x[None, :] - np.diag(steps)
    with np.errstate(all="ignore"):
        return ((np.asarray(h(xp), dtype=float) - np.asarray(h(xm), dtype=float)) / (2 * steps[:, None])).T


def unobservable_states(cfg: ExperimentConfig) -> list[Unobservable]:
    """The states of ``cfg``'s model that a table reports and that its sensors do not observe along the
    nominal insertion (module docstring); empty for a replay, a config without sensors, or a model whose
    path cannot be linearised (an advice: a model or sensor that fails here, a plug-in's too, is left to
    the run, where its failure is reported; the log says so at debug level)."""
    try:
        return _unobservable(cfg)
    except Exception as e:  # noqa: BLE001 (component code: the run reports it, not this advice)
        log.debug("observability of %s not analysed: %s: %s", cfg.name, type(e).__name__, e)
        return []


def _unobservable(cfg: ExperimentConfig) -> list[Unobservable]:
    from needlecli.experiments.simulation.truth import time_grid
    from needlecli.numerics import complex_step_jacobian
    from needlecli.sensors import SENSORS
    from needlecli.sensors.base import measurement_function

    if cfg.source is not None or cfg.stop is None or not cfg.sensors:
        return []
    model = MODELS.get(cfg.model.type)(cfg.model.params)
    params = {k: float(np.mean(v)) for k, v in model.param_arrays().items()}
    time, _, inputs = time_grid(cfg, model)
    u = np.concatenate([(a[0] if a.ndim == 3 else a) for a in (inputs[k] for k in model.input_names)], -1)
    T = len(time)
    if T < 2:
        return []
    nodes = np.unique(np.linspace(0, T - 1, min(NODES, T - 1) + 1).round().astype(int))
    x = np.asarray(model.initial_state(params), dtype=float).reshape(-1).copy()
    for k, v in cfg.model.initial_state.items():
        x[model.index(k)] = v
    sensors = []
    for s in cfg.sensors:
        sensor = SENSORS.get(s.type)(s, model)
        h = measurement_function(sensor, model)
        if h is None or getattr(sensor, "inequality", False):
            continue
        sigma = np.broadcast_to(np.asarray(getattr(s, "sigma", 1.0) or 1.0, dtype=float), (len(sensor.channel_names),))
        sensors.append((sensor.name, tuple(sensor.channel_names), h, np.where(sigma > 0, sigma, 1.0)))
    if not sensors:
        return []
    scale = _scales(model, x)
    rows = []
    phi = np.eye(model.n)
    try:
        for j, k in enumerate(nodes):
            for _, _, h, sigma in sensors:
                try:
                    H = _jacobian(h, x, scale) / sigma[:, None]
                except NotMeasurable:
                    continue
                if np.isfinite(H).all():
                    rows.append(H @ phi)
            if j + 1 < len(nodes):
                k1 = nodes[j + 1]
                dt = float(time[k1] - time[k])
                um = u[k:k1].mean(0)

                def step(xx, um=um, dt=dt):
                    return model.step(xx, np.broadcast_to(um, xx.shape[:-1] + um.shape), params, dt)

                F = complex_step_jacobian(step, x)
                x = np.asarray(model.step(x[None], um[None], params, dt), dtype=float)[0]
                phi = F @ phi
                if not (np.isfinite(x).all() and np.isfinite(phi).all()):
                    return []
    except (NotMeasurable, FloatingPointError):
        return []
    if not rows:
        return []
    S = np.concatenate(rows, 0) * scale[None, :]
    big = float(np.abs(S).max()) or 1.0
    for g in _constraints(model, x):  # the constraints are known: not unseen directions
        S = np.vstack([S, big * g * scale / (np.linalg.norm(g * scale) or 1.0)])
    _, sv, vt = np.linalg.svd(S, full_matrices=S.shape[0] < model.n)  # vt: (n, n) either way
    sv = np.concatenate([sv, np.zeros(model.n - len(sv))]) if len(sv) < model.n else sv
    null = vt[sv <= RANK_TOL * sv[0]] if sv[0] > 0 else vt
    out = []
    for i in _reported(model):  # e_i projected on the unseen directions: in them (1), partly, or not (0)
        proj = null.T @ null[:, i] if null.size else np.zeros(model.n)
        norm = float(np.linalg.norm(proj))
        if norm <= SHARE:
            continue
        partners = () if norm >= 1.0 - 1e-6 else tuple(
            model.state_names[m] for m in np.nonzero(np.abs(proj) > SHARE * norm)[0] if m != i)
        seen_by = tuple(f"{name} ({', '.join(ch)})" for name, ch, *_ in sensors)
        name = model.state_names[i]
        out.append(Unobservable(name, seen_by, partners, position=name in model.translation_states))
    return out
