"""Simulation of the true insertions: all Monte-Carlo runs advance together, one loop over time."""

from __future__ import annotations

import zlib
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from needlecli.experiments.schedule import evaluate_signal
from needlecli.models import MODELS, Model

STATUS_OK = "ok"
STATUS_SINGULAR = "singular"
STATUS_DIVERGED = "diverged"


def stream(seed: int, name: str) -> np.random.Generator:
    """Independent random stream for a named component; stable when other components change."""
    return np.random.default_rng(np.random.SeedSequence([seed, zlib.crc32(name.encode())]))


@dataclass
class Truth:
    """The simulated insertions.

    time (T,) s; states (N, T, n); inputs (N, T, m) flat (a broadcast view when every run has the same
    schedule); case (N,) index of the input case of each run (``case_labels``); depth (T,) inserted
    length; base_angle (N, T) integral of the rotation input; params name -> (N, T) (curvature follows
    the tissue layers); param_case (N,) index of the parameter case of each run (``param_case_labels``);
    status / reason (N,) str; event_time (N,) time a run stopped (NaN if it did not); valid_until (N,)
    last time with a valid state.
    """

    model: Model
    time: np.ndarray
    states: np.ndarray
    inputs: np.ndarray
    depth: np.ndarray
    base_angle: np.ndarray
    params: dict[str, np.ndarray]
    interfaces: np.ndarray
    status: np.ndarray
    reason: np.ndarray
    event_time: np.ndarray
    case: np.ndarray | None = None
    case_labels: list[str] | None = None
    param_case: np.ndarray | None = None
    param_case_labels: list[str] | None = None
    end_time: np.ndarray | None = None  # (N,) end of each run (replayed trials differ)
    trial_ids: list[str] | None = None  # replayed trials' ids
    truth_kind: str = "simulation"  # or what the logs recorded: ground truth, manual segmentation, none

    @property
    def valid_until(self) -> np.ndarray:
        end = self.time[-1] if self.end_time is None else self.end_time
        return np.where(np.isnan(self.event_time), end, self.event_time)

    def states_at(self, idx: np.ndarray) -> np.ndarray:
        """``states[:, idx]``: a view (no copy) when the indices are evenly spaced, as clocks are."""
        idx = np.asarray(idx)
        if idx.size > 1:
            step = idx[1] - idx[0]
            if step > 0 and np.all(np.diff(idx) == step):
                return self.states[:, idx[0] : idx[-1] + 1 : step]
        return self.states[:, idx]

    def input_dict(self) -> dict[str, np.ndarray]:
        """Inputs by name, ``(N, T, size)``."""
        return {k: self.inputs[..., self.model.input_slice(k)] for k in self.model.input_names}


def time_grid(cfg, model: Model) -> tuple[np.ndarray, np.ndarray, dict[str, np.ndarray]]:
    """Time grid, depth and input samples ``(T, size)`` from the config's stop rule and schedules."""
    dt = cfg.simulation.dt
    name_v = model.insertion_input
    sig_v = cfg.inputs[name_v]
    if cfg.stop.time is not None:
        n_steps = int(np.ceil(cfg.stop.time / dt - 1e-9))
        time = dt * np.arange(n_steps + 1)
        v = evaluate_signal(sig_v, time, None)[:, 0]
        depth = np.concatenate([[0.0], np.cumsum(v[:-1] * dt)])
    else:
        # grow the horizon until the final depth is reached (schedules may pause)
        horizon = 1024
        while True:
            time = dt * np.arange(horizon + 1)
            v = evaluate_signal(sig_v, time, None)[:, 0]
            depth = np.concatenate([[0.0], np.cumsum(v[:-1] * dt)])
            reached = np.nonzero(depth >= cfg.stop.depth - 1e-9)[0]
            if reached.size:
                n = int(reached[0]) + 1
                time, depth = time[:n], depth[:n]
                break
            if horizon > 50_000_000:
                raise ValueError("the final depth is not reached within 5e7 steps")
            horizon *= 4
    inputs = {}
    for k in model.input_names:
        if k in cfg.inputs:
            inputs[k] = evaluate_signal(cfg.inputs[k], time, depth)
        else:
            inputs[k] = np.zeros((len(time), model.input_sizes[k]))
    return time, depth, inputs


def curvature_schedule(cfg, depth: np.ndarray) -> np.ndarray | None:
    """Curvature ``(T,)`` from the tissue layers at each step's depth, or None without layers."""
    if cfg.tissue is None:
        return None
    starts = np.array([layer.depth for layer in cfg.tissue.layers])
    values = np.array([layer.curvature for layer in cfg.tissue.layers])
    return values[np.searchsorted(starts, depth, side="right") - 1]


def simulate_truth(cfg, *, runs: int | None = None, progress: Callable[[int, int], None] | None = None) -> Truth:
    """Simulate every run of the experiment at once. Deterministic for a given config and seed."""
    model_cls = MODELS.get(cfg.model.type)
    model = model_cls(cfg.model.params)
    n_runs = runs or cfg.runs.count
    seed = cfg.runs.seed
    time, depth, input_dict = time_grid(cfg, model)
    T = len(time)
    dt = cfg.simulation.dt
    # per-run inputs: run i follows case i mod K of every input given as cases (all with the same K)
    n_cases = max((a.shape[0] for a in input_dict.values() if a.ndim == 3), default=0)
    case = np.arange(n_runs) % n_cases if n_cases else None
    per_run = [a[case] if a.ndim == 3 else np.broadcast_to(a, (n_runs,) + a.shape) for a in
               (input_dict[k] for k in model.input_names)]
    u = np.concatenate(per_run, -1) if n_cases else np.broadcast_to(
        np.concatenate([input_dict[k] for k in model.input_names], -1), (n_runs, T, model.m))
    case_labels = next((cfg.inputs[k].case_labels() for k in model.input_names
                        if k in cfg.inputs and getattr(cfg.inputs[k], "kind", "") == "cases"), None)

    # parameters: per run (parameter cases, param_std), per step (tissue layers)
    rng_p = stream(seed, "truth/params")
    base = model.param_arrays()
    pc = cfg.model.param_cases
    param_case = (np.arange(n_runs) // max(n_cases, 1)) % len(pc.cases) if pc is not None else None
    params_run: dict[str, np.ndarray] = {}
    for k, v in base.items():
        std = cfg.model.param_std.get(k, 0.0)
        value = np.full(n_runs, float(v))
        if pc is not None:
            per_case = np.array([c.get(k, float(v)) for c in pc.cases])
            value = per_case[param_case]
        params_run[k] = value + (std * rng_p.standard_normal(n_runs) if std > 0 else 0.0)
    kappa_t = curvature_schedule(cfg, depth)
    cname = model.curvature_param
    params_t = dict(params_run)
    if kappa_t is not None and cname is not None:
        params_t[cname] = np.broadcast_to(kappa_t, (n_runs, T))

    def p_at(k: int) -> dict[str, np.ndarray]:
        return {name: (a[:, k] if a.ndim == 2 else a) for name, a in params_t.items()}

    # initial state
    x0 = np.asarray(model.initial_state(p_at(0)), dtype=float)
    for k, v in cfg.model.initial_state.items():
        x0[model.index(k)] = v
    x = np.broadcast_to(x0, (n_runs, model.n)).copy()
    rng_x = stream(seed, "truth/initial")
    sx = np.array([cfg.model.initial_std.get(s, 0.0) for s in model.state_names])
    if np.any(sx > 0):
        x = x + sx * rng_x.standard_normal(x.shape)
    x = model.normalize(model.sync_params(x, p_at(0)))

    q = np.array([cfg.process_noise.std.get(s, 0.0) for s in model.state_names]) * np.sqrt(dt)
    use_q = bool(np.any(q > 0))
    rng_q = stream(seed, "truth/process")

    states = np.empty((n_runs, T, model.n))
    states[:, 0] = x
    alive = np.ones(n_runs, dtype=bool)
    status = np.full(n_runs, STATUS_OK, dtype=object)
    reason = np.full(n_runs, "", dtype=object)
    event = np.full(n_runs, np.nan)
    bad0 = model.singular(x, p_at(0))
    if bad0.any():
        alive &= ~bad0
        status[bad0] = STATUS_SINGULAR
        reason[bad0] = model.singular_reason
        event[bad0] = 0.0

    every = max(1, (T - 1) // 200)
    with np.errstate(all="ignore"):
        for k in range(T - 1):
            pk = p_at(k)
            xn = model.step(x, u[:, k], pk, dt)
            if use_q:
                xn = xn + q * rng_q.standard_normal(xn.shape)
            pk1 = p_at(k + 1)
            xn = model.sync_params(xn, pk1)
            sing = model.left_domain(x, xn, pk1)
            finite = np.isfinite(xn).all(-1)
            bad = (sing | ~finite) & alive
            if bad.any():
                near = ~finite & model.near_singular(x, pk)
                is_sing = bad & (sing | near)
                is_div = bad & ~is_sing
                status[is_sing] = STATUS_SINGULAR
                reason[is_sing] = model.singular_reason
                status[is_div] = STATUS_DIVERGED
                reason[is_div] = "non-finite truth state"
                event[bad] = time[k + 1]
                alive &= ~bad
            if not alive.all():
                xn = np.where(alive[:, None], xn, x)  # a stopped run holds its last valid state
            states[:, k + 1] = xn
            x = xn
            if progress is not None and (k % every == 0 or k == T - 2):
                progress(k + 1, T - 1)

    params_out = {name: np.broadcast_to(a[:, None] if a.ndim == 1 else a, (n_runs, T)) for name, a in params_t.items()}
    interfaces = (
        np.array([layer.depth for layer in cfg.tissue.layers[1:]]) if cfg.tissue is not None else np.zeros(0)
    )
    if "u" in model.input_names and model.input_sizes["u"] == 1:
        w = u[:, :-1, model.input_slice("u").start]
        base_angle = np.concatenate([np.zeros((n_runs, 1)), np.cumsum(w * dt, axis=1)], axis=1)
    else:
        base_angle = np.zeros((n_runs, T))
    return Truth(
        model=model,
        time=time,
        states=states,
        inputs=u,
        depth=depth,
        base_angle=base_angle,
        params=params_out,
        interfaces=interfaces,
        status=status.astype(str),
        reason=reason.astype(str),
        event_time=event,
        case=case,
        case_labels=case_labels,
        param_case=param_case,
        param_case_labels=pc.case_labels() if pc is not None else None,
    )

