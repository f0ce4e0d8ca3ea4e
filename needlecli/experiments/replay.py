"""Replay: recorded trials from log files instead of a simulation, in the shapes the observers expect.

Trials become runs on one time grid (``simulation.dt``), long enough for the longest trial. Inputs are
held between their samples and are zero after a trial ends. Each sensor sample is placed at the nearest
grid time (at most ``dt / 2`` away; the original time is kept in ``t_original``); a stream's times are the
union over trials, and a trial without a sample at one of them has it marked invalid. The truth (ground
truth or manual segmentation, where a log has it) is placed the same way; grid times without a truth
sample hold NaN, so errors are computed only where the truth was recorded.
"""

from __future__ import annotations

import functools
from pathlib import Path

import numpy as np
from pydantic import ValidationError

from needlecli.errors import DataError
from needlecli.experiments.truth import STATUS_OK, Truth
from needlecli.io.logs import Trial, design_factors, read_log
from needlecli.models import MODELS
from needlecli.sensors import SENSORS, MeasurementStream


@functools.lru_cache(maxsize=8)
def _read_log_once(path: str, mtime_ns: int, size: int):
    """A log read and checked once per version of the file (a config's checks and its run share it)."""
    return read_log(path)


def _read_log(path: Path):
    try:
        st = path.stat()
    except OSError:
        return read_log(path)  # says what is wrong with it
    return _read_log_once(str(path), st.st_mtime_ns, st.st_size)


def load_trials(cfg, base_dir: Path) -> list[Trial]:
    trials: list[Trial] = []
    for p in cfg.source.logs:
        path = Path(p) if Path(p).is_absolute() else base_dir / p
        log = _read_log(path)
        for tr in log.trials:
            tr.meta.setdefault("log", str(path))
        trials.extend(log.trials)
    if cfg.source.trials is not None:
        by_id = {t.id: t for t in trials}
        missing = [t for t in cfg.source.trials if t not in by_id]
        if missing:
            raise DataError(f"{', '.join(cfg.source.logs)}: no trial {missing[0]!r}; trials: {', '.join(by_id)}")
        trials = [by_id[t] for t in cfg.source.trials]
    return trials


def _where(tr: Trial, what: str) -> str:
    return f"{tr.meta.get('log', '<log>')}: [trial {tr.id} -> {what}]"


def replay_truth(cfg, base_dir: Path):
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
                    raise DataError(f"{_where(tr, 'inputs')} missing input {name!r} (the insertion speed)")
                continue
            s = tr.inputs[name]
            want = model.input_units[name]
            if s.unit and s.unit != want:
                raise DataError(f"{_where(tr, f'input {name}')} unit {s.unit!r} does not match the model's {want!r}")
            if s.value.shape[1] != sl.stop - sl.start:
                raise DataError(f"{_where(tr, f'input {name}')} has {s.value.shape[1]} columns, model needs {sl.stop - sl.start}")
            k = np.clip(np.searchsorted(s.t, time + 1e-9, side="right") - 1, 0, None)
            inputs[i, :, sl] = np.where(alive[:, None], s.value[k], 0.0)
    v = inputs[..., model.input_slice(model.insertion_input).start]
    depth = np.concatenate([np.zeros((N, 1)), np.cumsum(v[:, :-1] * dt, axis=1)], axis=1)

    # ---- sensors: the same set in every trial, settings from the log
    sensors, streams = [], {}
    for sensor in _sensors(trials, model):
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
            raise DataError(f"{_where(tr, 'truth')} none of its names {list(tr.truth.names)} is a state of model {model.registered_name!r}")
        for j, c in cols:
            unit = tr.truth.units[j] if j < len(tr.truth.units) else ""
            if unit and unit != model.state_units[c]:
                raise DataError(f"{_where(tr, 'truth')} unit {unit!r} of {tr.truth.names[j]!r} does not match the model's {model.state_units[c]!r}")
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


#: metadata that describes how a trial was stored or imported rather than the experiment
_NOT_DESIGN = {"import_report", "config", "log", "source", "folder", "alignment", "design_factors"}


def trial_metadata(trials: list[Trial]) -> dict:
    """The trials' scalar metadata as columns ``name -> (N,)`` (numbers as floats, NaN where a trial lacks
    the key; otherwise strings, empty where missing), for grouping fits by them. Keys that say how the
    data were stored (the import report, JSON, long text) are left out. ``"design_factors"``: the keys
    any trial lists as its design factors."""
    keys: dict[str, None] = {}
    factors: dict[str, None] = {}
    for tr in trials:
        for k, v in tr.meta.items():
            if k in _NOT_DESIGN or isinstance(v, (list, dict, tuple)):
                continue
            if isinstance(v, str) and (len(v) > 120 or v[:1] in "[{"):
                continue
            keys[k] = None
        for k in design_factors(tr):
            factors[k] = None
    cols = {}
    for k in keys:
        vals = [tr.meta.get(k) for tr in trials]
        present = [v for v in vals if v is not None]
        if all(isinstance(v, (int, float, np.integer, np.floating)) and not isinstance(v, (bool, np.bool_))
               for v in present):
            cols[k] = np.array([np.nan if v is None else float(v) for v in vals])
        else:
            cols[k] = np.array(["" if v is None else str(v) for v in vals])
    return {"columns": cols, "design_factors": [k for k in factors if k in cols]}


def _sensors(trials: list[Trial], model) -> list:
    """The sensors of the logs, from the first trial's settings; every trial must have the same ones."""
    names = list(trials[0].sensors)
    for tr in trials[1:]:
        for n in names:
            if n not in tr.sensors:
                raise DataError(f"{_where(tr, 'sensors')} missing channel {n!r} (trial {trials[0].id} has it)")
        for n in tr.sensors:
            if n not in names:
                raise DataError(f"{_where(tr, 'sensors')} channel {n!r} is in no other trial ({trials[0].id} lacks it)")
    out = []
    for name in names:
        settings = dict(trials[0].sensors[name].settings)
        settings["name"] = name
        stype = settings.get("type")
        if stype not in SENSORS:
            raise DataError(f"{_where(trials[0], f'sensor {name}')} unknown sensor type {stype!r}; known: {', '.join(SENSORS.names())}")
        cls = SENSORS.get(stype)
        try:
            sensor = cls(cls.Settings.model_validate(settings), model)
        except ValidationError as e:
            err = e.errors()[0]
            raise DataError(f"{_where(trials[0], f'sensor {name}')} settings: {'.'.join(map(str, err['loc']))}: {err['msg']}") from None
        except ValueError as e:
            raise DataError(f"{_where(trials[0], f'sensor {name}')} settings: {e}") from None
        problem = sensor.check_model()
        if problem:
            raise DataError(f"{_where(trials[0], f'sensor {name}')} {problem}")
        for tr in trials:
            st = tr.sensors[name]
            if tuple(st.names) != tuple(sensor.channel_names):
                raise DataError(f"{_where(tr, f'sensor {name}')} columns {list(st.names)}, expected {list(sensor.channel_names)}")
            if tuple(st.units) != tuple(sensor.channel_units):
                raise DataError(f"{_where(tr, f'sensor {name}')} units {list(st.units)} do not match {list(sensor.channel_units)}")
        out.append(sensor)
    return out


def replay_sensors(cfg, base_dir: Path) -> list:
    """The sensors a replay config will have (reads and checks the logs)."""
    model = MODELS.get(cfg.model.type)(cfg.model.params)
    return _sensors(load_trials(cfg, base_dir), model)


def polynomial_reference(ref, model, streams, depth: np.ndarray, time: np.ndarray) -> np.ndarray:
    """Reference states ``(N, T, n)`` from polynomial fits ``x(s)``, ``y(s)`` of a position sensor's valid
    samples against the depth ``s`` (seed 000); NaN for what the fit does not give, outside the depths
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
