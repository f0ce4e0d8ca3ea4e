"""Simulation of the true insertions: all Monte-Carlo runs advance together, one loop over time."""

from __future__ import annotations

import zlib
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from needlecli.experiments.config.schedule import evaluate_signal
from needlecli.models import MODELS, Model

if TYPE_CHECKING:
    from needlecli.experiments.config.types import ExperimentConfig

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
    trial_meta: dict | None = None  # replayed trials' metadata: {"columns": name -> (N,), "design_factors": [...]}
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


def time_grid(cfg: ExperimentConfig, model: Model) -> tuple[np.ndarray, np.ndarray, dict[str, np.ndarray]]:
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


def curvature_schedule(cfg: ExperimentConfig, depth: np.ndarray) -> np.ndarray | None:
    """Curvature ``(T,)`` from the tissue layers at each step's depth, or None without layers."""
    if cfg.tissue is None:
        return None
    starts = np.array([layer.depth for layer in cfg.tissue.layers])
    values = np.array([layer.curvature for layer in cfg.tissue.layers])
    return values[np.searchsorted(starts, depth, side="right") - 1]


def simulate_truth(cfg: ExperimentConfig, *, runs: int | None = None, progress: Callable[[int, int], None] | None = None) -> Truth:
    """Simulate every run of the experiment at once. Deterministic for a given config and seed."""
    return TruthSimulator(cfg, runs=runs, progress=progress).finish()


#: ``before_step(k, x) -> x``: called before the grid step ``k -> k + 1`` with the state at ``t_k`` of every
#: run ``(N, n)``; returns the state to step from (the same array when nothing changes)
BeforeStep = Callable[[int, np.ndarray], np.ndarray]


class TruthSimulator:
    """The truth simulation as a stepper: all runs advance together, one grid step at a time, so that
    something can act on the state between steps (a controller closing a loop through a sensor).

    ``advance_to(k)`` fills ``states[:, :k + 1]``; ``finish()`` runs to the end and returns the
    :class:`Truth`. Without ``before_step`` the result does not depend on how the steps are chunked and
    equals :func:`simulate_truth` bit for bit (the same random draws in the same order).

    ``before_step(k, x)`` is called before the RK4 step from ``t_k`` (and once at the last grid time),
    with the state at ``t_k``. What it returns replaces the state at ``t_k`` of the runs still going (the
    recorded ``states[:, k]`` is the state after the change, so every recorded step is an exact model
    step); a change that leaves the model's domain stops the run there (status ``singular``).
    """

    def __init__(self, cfg: ExperimentConfig, *, runs: int | None = None, progress: Callable[[int, int], None] | None = None,
                 before_step: BeforeStep | None = None) -> None:
        model_cls = MODELS.get(cfg.model.type)
        model = model_cls(cfg.model.params)
        self.model = model
        self.cfg = cfg
        self.progress = progress
        self.before_step = before_step
        n_runs = runs or cfg.runs.count
        self.n_runs = n_runs
        seed = cfg.runs.seed
        time, depth, input_dict = time_grid(cfg, model)
        T = len(time)
        self.time, self.depth, self.T = time, depth, T
        self.dt = dt = cfg.simulation.dt
        # per-run inputs: run i follows case i mod K of every input given as cases (all with the same K)
        n_cases = max((a.shape[0] for a in input_dict.values() if a.ndim == 3), default=0)
        case = np.arange(n_runs) % n_cases if n_cases else None
        per_run = [a[case] if a.ndim == 3 else np.broadcast_to(a, (n_runs,) + a.shape) for a in
                   (input_dict[k] for k in model.input_names)]
        u = np.concatenate(per_run, -1) if n_cases else np.broadcast_to(
            np.concatenate([input_dict[k] for k in model.input_names], -1), (n_runs, T, model.m))
        self.u, self.case = u, case
        self.case_labels = next((cfg.inputs[k].case_labels() for k in model.input_names
                                 if k in cfg.inputs and getattr(cfg.inputs[k], "kind", "") == "cases"), None)

        # parameters: per run (parameter cases, param_std), per step (tissue layers)
        rng_p = stream(seed, "truth/params")
        base = model.param_arrays()
        pc = cfg.model.param_cases
        self.param_case = (np.arange(n_runs) // max(n_cases, 1)) % len(pc.cases) if pc is not None else None
        params_run: dict[str, np.ndarray] = {}
        for k, v in base.items():
            std = cfg.model.param_std.get(k, 0.0)
            value = np.full(n_runs, float(v))
            if pc is not None:
                per_case = np.array([c.get(k, float(v)) for c in pc.cases])
                value = per_case[self.param_case]
            params_run[k] = value + (std * rng_p.standard_normal(n_runs) if std > 0 else 0.0)
        kappa_t = curvature_schedule(cfg, depth)
        cname = model.curvature_param
        params_t = dict(params_run)
        if kappa_t is not None and cname is not None:
            params_t[cname] = np.broadcast_to(kappa_t, (n_runs, T))
        self.params_t = params_t

        # initial state
        x0 = np.asarray(model.initial_state(self.p_at(0)), dtype=float)
        for k, v in cfg.model.initial_state.items():
            x0[model.index(k)] = v
        x = np.broadcast_to(x0, (n_runs, model.n)).copy()
        rng_x = stream(seed, "truth/initial")
        sx = np.array([cfg.model.initial_std.get(s, 0.0) for s in model.state_names])
        if np.any(sx > 0):
            x = x + sx * rng_x.standard_normal(x.shape)
        x = model.normalize(model.sync_params(x, self.p_at(0)))

        self.q = np.array([cfg.process_noise.std.get(s, 0.0) for s in model.state_names]) * np.sqrt(dt)
        self.use_q = bool(np.any(self.q > 0))
        self.rng_q = stream(seed, "truth/process")

        self.states = np.empty((n_runs, T, model.n))
        self.states[:, 0] = x
        self.x = x
        self.alive = np.ones(n_runs, dtype=bool)
        self.status = np.full(n_runs, STATUS_OK, dtype=object)
        self.reason = np.full(n_runs, "", dtype=object)
        self.event = np.full(n_runs, np.nan)
        bad0 = model.singular(x, self.p_at(0))
        if bad0.any():
            self.alive &= ~bad0
            self.status[bad0] = STATUS_SINGULAR
            self.reason[bad0] = model.singular_reason
            self.event[bad0] = 0.0
        self.k = 0  # states[:, : k + 1] are filled
        self.acted = -1  # the last grid index before_step was applied at (states before it are final)
        self._every = max(1, (T - 1) // 200)
        from needlecli import kernels

        # the compiled stepper (needlecli.kernels.truth) serves runs without a before_step
        self._twin = kernels.twin("truth", cfg.simulation.kernels) if model.compiled_equations else None
        self._kernel = None

    def p_at(self, k: int) -> dict[str, np.ndarray]:
        """Parameters at grid index ``k`` (per run ``(N,)`` or scalars)."""
        return {name: (a[:, k] if a.ndim == 2 else a) for name, a in self.params_t.items()}

    def _act(self, k: int) -> None:
        """Apply ``before_step`` at grid index ``k`` (once) to the runs still going."""
        if self.acted >= k:
            return
        self.acted = k
        if self.before_step is None:
            return
        x = self.x
        xa = self.before_step(k, x)
        if xa is x:
            return
        xa = np.where(self.alive[:, None], xa, x)
        pk = self.p_at(k)
        bad = (self.model.left_domain(x, xa, pk) | ~np.isfinite(xa).all(-1)) & self.alive
        if bad.any():  # the change itself left the domain: the run stops at t_k with its state before it
            self.status[bad] = STATUS_SINGULAR
            self.reason[bad] = self.model.singular_reason or "the state left the model's domain"
            self.event[bad] = self.time[k]
            self.alive &= ~bad
            xa = np.where(bad[:, None], x, xa)
        self.states[:, k] = xa
        self.x = xa

    def advance_to(self, k: int) -> None:
        """Simulate until ``states[:, : k + 1]`` are filled (nothing when they already are)."""
        k = min(int(k), self.T - 1)
        if self._twin is not None and self.before_step is None:
            if self._kernel is None:
                self._kernel = self._twin(self)
            self._kernel.advance_to(self, k)
            return
        model, time, dt, u = self.model, self.time, self.dt, self.u
        status, reason, event = self.status, self.reason, self.event
        with np.errstate(all="ignore"):
            while self.k < k:
                i = self.k
                self._act(i)
                x = self.x
                alive = self.alive
                pk = self.p_at(i)
                xn = model.step(x, u[:, i], pk, dt)
                if self.use_q:
                    xn = xn + self.q * self.rng_q.standard_normal(xn.shape)
                pk1 = self.p_at(i + 1)
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
                    event[bad] = time[i + 1]
                    alive &= ~bad
                if not alive.all():
                    xn = np.where(alive[:, None], xn, x)  # a stopped run holds its last valid state
                self.states[:, i + 1] = xn
                self.x = xn
                self.k = i + 1
                if self.progress is not None and (i % self._every == 0 or i == self.T - 2):
                    self.progress(i + 1, self.T - 1)

    def finish(self) -> Truth:
        """Run to the last grid time and return the truth."""
        self.advance_to(self.T - 1)
        with np.errstate(all="ignore"):
            self._act(self.T - 1)
        cfg, model, n_runs, T, dt, u = self.cfg, self.model, self.n_runs, self.T, self.dt, self.u
        params_out = {name: np.broadcast_to(a[:, None] if a.ndim == 1 else a, (n_runs, T))
                      for name, a in self.params_t.items()}
        interfaces = (
            np.array([layer.depth for layer in cfg.tissue.layers[1:]]) if cfg.tissue is not None else np.zeros(0)
        )
        if "u" in model.input_names and model.input_sizes["u"] == 1:
            w = u[:, :-1, model.input_slice("u").start]
            base_angle = np.concatenate([np.zeros((n_runs, 1)), np.cumsum(w * dt, axis=1)], axis=1)
        else:
            base_angle = np.zeros((n_runs, T))
        pc = cfg.model.param_cases
        return Truth(
            model=model,
            time=self.time,
            states=self.states,
            inputs=u,
            depth=self.depth,
            base_angle=base_angle,
            params=params_out,
            interfaces=interfaces,
            status=self.status.astype(str),
            reason=self.reason.astype(str),
            event_time=self.event,
            case=self.case,
            case_labels=self.case_labels,
            param_case=self.param_case,
            param_case_labels=pc.case_labels() if pc is not None else None,
        )
