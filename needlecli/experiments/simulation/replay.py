"""Replay: recorded trials from log files instead of a simulation, in the shapes the observers expect.

Trials become runs on one time grid (``simulation.dt``), long enough for the longest trial. Inputs are
held between their samples and are zero after a trial ends. Each sensor sample is placed at the nearest
grid time (at most ``dt / 2`` away; the original time is kept in ``t_original``); a stream's times are the
union over trials, and a trial without a sample at one of them has it marked invalid. The truth (ground
truth or manual segmentation, where a log has it) is placed the same way; grid times without a truth
sample hold NaN, so errors are computed only where the truth was recorded.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from needlecli.errors import DataError
from needlecli.experiments.config.logs import load_trials, log_sensors, trial_metadata, trial_where
from needlecli.experiments.simulation.truth import STATUS_OK, Truth
from needlecli.io.logs import Trial
from needlecli.models import MODELS
from needlecli.sensors import MeasurementStream

if TYPE_CHECKING:
    from needlecli.experiments.config.types import ExperimentConfig


def replay_truth(cfg: ExperimentConfig, base_dir: Path):
    """Build the truth (what the logs know of it), the sensors and their streams from the logs."""
    model_cls = MODELS.get(cfg.model.type)
    model = model_cls(cfg.model.params)
    trials = load_trials(cfg, base_dir)
    N = len(trials)
    dt = cfg.simulation.dt
    end = np.array([tr.end_time for tr in trials])
    T = int(np.ceil(end.max() / dt - 1e-9)) + 1
    time = dt * np.arange(T)

    # ---- inputs, held between samples, zero after the trial's end
    inputs = np.zeros((N, T, model.m))
    for i, tr in enumerate(trials):
        alive = time <= end[i] + 1e-12
        for name in model.input_names:
            sl = model.input_slice(name)
            if name not in tr.inputs:
                if name == model.insertion_input:
                    raise DataError(f"{trial_where(tr, 'inputs')} missing input {name!r} (the insertion speed)")
                continue
            s = tr.inputs[name]
            want = model.input_units[name]
            if s.unit and s.unit != want:
                raise DataError(f"{trial_where(tr, f'input {name}')} unit {s.unit!r} does not match the model's {want!r}")
            if s.value.shape[1] != sl.stop - sl.start:
                raise DataError(f"{trial_where(tr, f'input {name}')} has {s.value.shape[1]} columns, model needs {sl.stop - sl.start}")
            k = np.clip(np.searchsorted(s.t, time + 1e-9, side="right") - 1, 0, None)
            inputs[i, :, sl] = np.where(alive[:, None], s.value[k], 0.0)
    v = inputs[..., model.input_slice(model.insertion_input).start]
    depth = np.concatenate([np.zeros((N, 1)), np.cumsum(v[:, :-1] * dt, axis=1)], axis=1)

    # ---- sensors: the same set in every trial, settings from the log
    sensors, streams = [], {}
    for sensor in log_sensors(trials, model):
        name = sensor.name
        stype = sensor.registered_name
        m = len(sensor.channel_names)
        grid = [np.rint(tr.sensors[name].t / dt).astype(np.int64) for tr in trials]
        idx = np.unique(np.concatenate([g[(g >= 0) & (g < T)] for g in grid]))
        value = np.full((N, len(idx), m), np.nan)
        valid = np.zeros((N, len(idx)), dtype=bool)
        t_orig = np.full((N, len(idx)), np.nan)
        per_sample = any(tr.sensors[name].sigma is not None for tr in trials)
        sample_sig = np.full((N, len(idx), m), np.nan) if per_sample else None
        n_invalid = 0
        for i, tr in enumerate(trials):  # placing each trial's samples: one vectorised assignment per trial
            s, g = tr.sensors[name], grid[i]
            keep = (g >= 0) & (g < T)
            pos = np.searchsorted(idx, g[keep])
            value[i, pos] = s.value[keep]
            valid[i, pos] = s.valid[keep]
            t_orig[i, pos] = s.t[keep]
            if per_sample and s.sigma is not None:
                sample_sig[i, pos] = s.sigma[keep]
            n_invalid += int((~s.valid).sum())
        value[~valid] = np.nan
        sig = np.zeros(m)
        try:
            sig = np.broadcast_to(np.asarray(getattr(sensor.settings, "sigma", 0.0), dtype=float), (m,))
        except ValueError:
            pass
        attrs = {"type": stype, "rate": sensor.settings.rate, "latency": sensor.settings.latency,
                 "dropout": sensor.settings.dropout, "pipeline": "replay", "invalid_samples_skipped": n_invalid,
                 "t_original": t_orig}
        sigma = np.broadcast_to(sig, value.shape).copy()
        if per_sample:  # the logs' per-sample sigmas (the nominal one where a trial has none)
            sigma = np.where(np.isfinite(sample_sig), sample_sig, sigma)
            attrs.update({"sigma_per_sample": True, "nominal_sigma": np.asarray(sig, dtype=float).copy()})
        streams[name] = MeasurementStream(
            t=time[idx], t_available=time[idx] + sensor.settings.latency, index=idx, value=value, valid=valid,
            sigma=sigma, names=sensor.channel_names, units=sensor.channel_units, attrs=attrs,
        )
        sensors.append(sensor)

    # ---- truth where recorded
    states = np.full((N, T, model.n), np.nan)
    for i, tr in enumerate(trials):
        if tr.truth is None:
            continue
        cols = [(j, model.state_names.index(nm)) for j, nm in enumerate(tr.truth.names) if nm in model.state_names]
        if not cols:
            raise DataError(f"{trial_where(tr, 'truth')} none of its names {list(tr.truth.names)} is a state of model {model.registered_name!r}")
        for j, c in cols:
            unit = tr.truth.units[j] if j < len(tr.truth.units) else ""
            if unit and unit != model.state_units[c]:
                raise DataError(f"{trial_where(tr, 'truth')} unit {unit!r} of {tr.truth.names[j]!r} does not match the model's {model.state_units[c]!r}")
        g = np.rint(tr.truth.t / dt).astype(np.int64)
        keep = (g >= 0) & (g < T)
        for j, c in cols:
            states[i, g[keep], c] = tr.truth.state[keep, j]
    truth_kind = _truth_kind(trials)
    if cfg.source.reference is not None:
        states = polynomial_reference(cfg.source.reference, model, streams, depth, time)
        truth_kind = f"polynomial fit of {cfg.source.reference.sensor} (degree {cfg.source.reference.degree})"
    params = {k: np.broadcast_to(np.asarray(v, dtype=float), (N, T)) for k, v in model.param_arrays().items()}
    truth = Truth(
        model=model, time=time, states=states, inputs=inputs, depth=depth,
        base_angle=np.zeros((N, T)), params=params,
        interfaces=np.zeros(0), status=np.full(N, STATUS_OK), reason=np.full(N, ""),
        event_time=np.full(N, np.nan), end_time=end,
        trial_ids=[tr.id for tr in trials], truth_kind=truth_kind, trial_meta=trial_metadata(trials),
    )
    return truth, sensors, streams


def polynomial_reference(ref, model, streams, depth: np.ndarray, time: np.ndarray) -> np.ndarray:
    """Reference states ``(N, T, n)`` from polynomial fits ``x(s)``, ``y(s)`` of a position sensor's valid
    samples against the depth ``s`` (the high-gain observer paper); NaN for what the fit does not give, outside the depths
    the samples cover, and for trials with too few samples. All trials are fitted at once: weighted least
    squares in a Chebyshev basis on each trial's sampled depth range mapped to [-1, 1] (the valid samples
    weigh 1, the others 0), solved by batched normal equations."""
    from numpy.polynomial import chebyshev as C

    st = streams[ref.sensor]
    N, T = depth.shape
    out = np.full((N, T, model.n), np.nan)
    cols = {c: st.names.index(c) for c in ("x", "y") if c in st.names}
    ok = st.valid  # (N, M)
    s_meas = depth[:, st.index]  # (N, M) depth at each sample
    enough = ok.sum(1) > ref.degree
    lo = np.where(ok, s_meas, np.inf).min(1)
    hi = np.where(ok, s_meas, -np.inf).max(1)
    span = np.where(enough & (hi > lo), hi - lo, 1.0)
    lo = np.where(enough, lo, 0.0)

    def scaled(s):  # depth -> [-1, 1] per trial
        return 2.0 * (s - lo[:, None]) / span[:, None] - 1.0

    V = C.chebvander(scaled(s_meas), ref.degree) * ok[..., None]  # (N, M, k), invalid rows zero
    A = np.swapaxes(V, 1, 2) @ V + np.eye(ref.degree + 1) * (~enough)[:, None, None]  # solvable everywhere
    Vt = C.chebvander(scaled(depth), ref.degree)  # (N, T, k)
    # d/ds of each basis function: Chebyshev derivative coefficients, times ds -> dt
    dVt = (C.chebvander(scaled(depth), ref.degree - 1) @ C.chebder(np.eye(ref.degree + 1))) * (2.0 / span)[:, None, None]
    inside = enough[:, None] & (depth >= lo[:, None]) & (depth <= (lo + span)[:, None])
    slopes = {}
    for c, j in cols.items():  # x and y
        y = np.where(ok, st.value[..., j], 0.0)
        coef = np.linalg.solve(A, (np.swapaxes(V, 1, 2) @ y[..., None]))  # (N, k, 1)
        if c in model.state_names:
            out[..., model.index(c)] = np.where(inside, (Vt @ coef)[..., 0], np.nan)
        slopes[c] = np.where(inside, (dVt @ coef)[..., 0], np.nan)
    beta = np.arcsin(np.clip(slopes["x"], -1.0, 1.0))
    if "beta" in model.state_names:
        out[..., model.index("beta")] = beta
    if "y" in slopes and "alpha" in model.state_names:
        out[..., model.index("alpha")] = np.arcsin(np.clip(-slopes["y"] / np.cos(beta), -1.0, 1.0))
    return out


def _truth_kind(trials: list[Trial]) -> str:
    kinds = {tr.truth.kind for tr in trials if tr.truth is not None}
    if not kinds:
        return "none"
    return ", ".join(sorted(kinds))
