"""How much memory and disk an experiment needs, worked out from its config before any work, and a
refusal, with the figure, the key that drives it and what to change, of an experiment that will not fit.

The estimate counts the arrays of the results file as they are stored (docs/reference/results-file.md): the
truth ``(N, T, n)``, its parameters and inputs ``(N, T, .)``, each sensor's values, sigmas and validity
``(N, M, m)`` (and the clock's sample times, which a rate far above the grid's makes huge before they are
placed on it), each observer's estimates ``(N, T, n)`` and covariances ``(N, T', n, n)`` or ``(N, T', n)``
with ``T' = T / store_every``. ``T`` comes from the stop rule (the time at which the insertion schedule
reaches ``stop.depth``, found without simulating) or, for replayed logs, from the latest sample of the
trials. A run holds these arrays in memory, builds the file from them, then reads it back for the
tables: :data:`PEAK_FACTOR` times the stored size, and :data:`BASE_BYTES` for the process itself, is
what it needs (peak resident memory measured on the bundled configs: 300 MB plus 1.8 to 3.0 times the
stored size). The memory available is the system's ``MemAvailable`` (``NEEDLECLI_MEMORY``, in bytes or
with a unit such as ``8G``, sets another limit). The results file needs at most the stored size on
disk (compression makes it smaller).
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

from needlecli import platform
from needlecli.errors import ConfigError
from needlecli.io.atomic import human_bytes
from needlecli.models import MODELS

if TYPE_CHECKING:
    from needlecli.experiments.config.types import ExperimentConfig

PEAK_FACTOR = 3.5
BASE_BYTES = 300 * 2**20  # the Python process with numpy, scipy, h5py, pydantic loaded
_F8 = 8


@dataclass
class Part:
    """One block of the estimate: ``bytes`` held, the config ``key`` that sizes it, in words (``detail``)
    and what would make it smaller (``hint``)."""

    what: str
    bytes: float
    key: tuple
    detail: str
    hint: str


@dataclass
class Estimate:
    runs: int
    steps: int
    parts: list[Part] = field(default_factory=list)
    transient: list[Part] = field(default_factory=list)  # working arrays that are not stored

    @property
    def stored(self) -> float:
        return sum(p.bytes for p in self.parts)

    @property
    def needed(self) -> float:
        return PEAK_FACTOR * self.stored + sum(p.bytes for p in self.transient) + BASE_BYTES

    @property
    def file_bytes(self) -> int:
        """An upper bound of the results file's size (uncompressed arrays, metadata)."""
        return int(self.stored + 2**20 + 4096 * (len(self.parts) + 8))

    def largest(self) -> Part:
        return max(self.parts + self.transient, key=lambda p: p.bytes)


def available_memory() -> int | None:
    """Bytes of memory a new experiment may use: ``NEEDLECLI_MEMORY`` if set, else what the system says is
    available (:func:`needlecli.platform.available_memory`; None where it cannot say: no check)."""
    env = os.environ.get("NEEDLECLI_MEMORY", "").strip()
    if env:
        units = {"K": 2**10, "M": 2**20, "G": 2**30, "T": 2**40}
        try:
            if env[-1].upper() in units:
                return int(float(env[:-1]) * units[env[-1].upper()])
            return int(float(env))
        except ValueError:
            raise ConfigError("NEEDLECLI_MEMORY", (), f"{env!r} is not a number of bytes (e.g. 8G)") from None
    return platform.available_memory()


# ---------------------------------------------------------------------------------------------- the time grid
def _time_to_depth(sig, depth: float) -> float:
    """When an insertion schedule reaches ``depth`` (s), without simulating; inf if never."""
    kind = getattr(sig, "kind", "")
    if kind == "constant":
        v = float(sig.value[0] if isinstance(sig.value, (list, tuple)) else sig.value)
        return depth / v if v > 0 else math.inf
    if kind == "piecewise":
        tk = [float(t) for t in sig.times]
        vk = [float(v[0] if isinstance(v, (list, tuple)) else v) for v in sig.values]
        done, t = 0.0, 0.0
        segments = [(0.0, tk[0], vk[0], vk[0])] + [
            (tk[i], tk[i + 1], vk[i], vk[i + 1] if sig.interp == "linear" else vk[i]) for i in range(len(tk) - 1)]
        for a, b, va, vb in segments:
            gain = 0.5 * (va + vb) * (b - a)
            if done + gain >= depth and gain > 0:
                return a + (depth - done) / gain * (b - a)
            done, t = done + gain, b
        return t + (depth - done) / vk[-1] if vk[-1] > 0 else math.inf
    if kind == "flips":
        if sig.base > 0:
            return depth / sig.base
        return max(sig.at_times or [0.0]) + abs(sig.angle) / sig.rate
    return math.inf


def _steps(cfg: ExperimentConfig, base_dir: Path, trials) -> tuple[int, tuple, str]:
    """Grid steps ``T``, the key that sets them and why."""
    dt = float(cfg.simulation.dt)
    if cfg.source is not None:
        ends = [(tr.end_time, tr) for tr in trials]
        end, tr = max(ends, key=lambda e: e[0]) if ends else (0.0, None)
        where = ""
        if tr is not None:
            last = max(((float(s.t[-1]), f"sensor {n}") for n, s in tr.sensors.items() if s.t.size),
                       default=(0.0, ""))
            log = tr.meta.get("log", "the log")
            where = f"trial {tr.id} of {log} ends at t = {end:.6g} s" + (f" ({last[1]})" if last[1] else "")
        return int(math.ceil(end / dt - 1e-9)) + 1, ("source", "logs"), where
    model_cls = MODELS.get(cfg.model.type)
    if cfg.stop.time is not None:
        t, key, why = float(cfg.stop.time), ("stop", "time"), f"stop.time = {cfg.stop.time:g} s"
    else:
        t = _time_to_depth(cfg.inputs[model_cls.insertion_input], float(cfg.stop.depth))
        key, why = ("stop", "depth"), f"stop.depth = {cfg.stop.depth:g} reached after {t:.6g} s"
    if t <= 3600.0:  # an insertion of at most an hour: the step is what makes the grid long
        key, why = ("simulation", "dt"), f"{why} in steps of simulation.dt = {dt:g} s"
    steps = int(math.ceil(t / dt - 1e-9)) + 2 if math.isfinite(t) else 2**62
    return steps, key, why


# ---------------------------------------------------------------------------------------------- the estimate
def estimate(cfg: ExperimentConfig, base_dir: str | Path = ".", trials=None) -> Estimate:
    """The memory an experiment needs (see the module docstring). ``trials`` (replay): the log trials."""
    base_dir = Path(base_dir)
    if cfg.source is not None and trials is None:
        from needlecli.experiments.config.logs import load_trials

        trials = load_trials(cfg, base_dir)
    model_cls = MODELS.get(cfg.model.type)
    n, m = len(model_cls.state_names), sum(model_cls.input_sizes.values())
    p = len(model_cls.Params.model_fields)
    N = len(trials) if cfg.source is not None else int(cfg.runs.count)
    T, t_key, t_why = _steps(cfg, base_dir, trials)
    dt = float(cfg.simulation.dt)
    duration = (T - 1) * dt
    est = Estimate(runs=N, steps=T)
    runs_key = ("runs", "count") if cfg.source is None else ("source", "trials")
    fewer = ("fewer runs (runs.count), or run the experiment in chunks of fewer runs (needle sweep with a "
             "grid runs.seed: range(K))") if cfg.source is None else "fewer trials (source.trials)"
    # what sizes N x T: blame the factor that is far from usual (runs in the hundreds, steps ~1e4-1e5)
    nt_key, nt_why = (runs_key, f"{N:,} runs") if N / 1e3 >= T / 1e5 else (t_key, f"{T:,} steps of dt = {dt:g} s ({t_why})")
    absurd = N > 1e5 or T > 1e7  # then N x T drives every block, whatever else sizes it
    nt_hint = fewer if nt_key == runs_key else (
        "a shorter insertion (stop), a faster insertion speed, or a larger simulation.dt" if cfg.source is None
        else "check the log's timestamps (s), or a larger simulation.dt")
    est.parts.append(Part("truth", N * T * (2 * n + p + m + 1) * _F8, nt_key,
                          f"the truth of {N:,} runs x {T:,} steps ({nt_why})", nt_hint))
    for i, s in enumerate(cfg.sensors):
        rate = float(s.rate)
        clock = max(0, math.floor((duration - float(s.start)) * rate + 1e-9) + 1)
        M = min(clock, T)
        width = _channels(s, model_cls)
        key = ("sensors", i, "rate")
        name = s.name or s.type
        est.parts.append(Part(f"sensor {name}", N * M * (2 * width * _F8 + 1) + 3 * M * _F8, nt_key if absurd else key,
                              f"sensor {name}: {M:,} samples per run at {rate:g} Hz over {duration:.6g} s"
                              + (f" ({nt_why})" if absurd else ""),
                              nt_hint if absurd else f"a lower rate of sensor {name}, " + fewer))
        if clock > T:  # the clock's sample times before they are placed on the grid
            est.transient.append(Part(f"clock of {name}", 4 * clock * _F8, key,
                                      f"sensor {name} samples at {rate:g} Hz, {clock:,} sample times over "
                                      f"{duration:.6g} s on a grid of {T:,} steps",
                                      f"a rate at most the grid's 1/dt = {1 / dt:g} Hz (faster samples fall "
                                      "on the same grid times)"))
    if cfg.source is not None and trials:
        for name, st in trials[0].sensors.items():
            M = min(T, sum(len(tr.sensors[name].t) for tr in trials if name in tr.sensors))
            width = st.value.shape[1] if st.value.ndim == 2 else 1
            est.parts.append(Part(f"sensor {name}", N * M * (3 * width * _F8 + 1) + 3 * M * _F8, ("source", "logs"),
                                  f"sensor {name} of the logs: {M:,} grid times x {N:,} trials", "fewer trials "
                                  "(source.trials)"))
    stride = int(cfg.output.store_every)
    Tc = -(-T // stride)
    for o in cfg.observers:
        if isinstance(o, dict):
            continue
        oname = o.name or o.type
        omodel = getattr(o, "model", None) or cfg.model.type
        no = len(MODELS.get(omodel).state_names) if omodel in MODELS else n
        no += len(getattr(o, "augment", []) or [])
        est.parts.append(Part(f"observer {oname}", N * T * no * _F8, nt_key,
                              f"the estimates of observer {oname} ({N:,} runs x {T:,} steps x {no} states, {nt_why})",
                              nt_hint))
        layout = cfg.output.covariance
        cov = {"full": no * no, "diag": no, "none": 0}[layout]
        if cov:
            est.parts.append(Part(f"covariances of {oname}", N * Tc * cov * _F8, nt_key if absurd else ("output", "covariance"),
                                  f"the {layout} covariances of observer {oname} ({N:,} runs x {Tc:,} stored steps x "
                                  f"{cov} entries; store_every = {stride}" + (f"; {nt_why})" if absurd else ")"),
                                  nt_hint if absurd else "keep fewer: output.store_every: K (every K-th step), "
                                  "output.covariance: diag or none; or " + fewer))
    return est


def _channels(s, model_cls) -> int:
    for attr in ("axes", "channels"):
        v = getattr(s, attr, None)
        if isinstance(v, (list, tuple)) and v:
            return len(v)
    return 3


def check_memory(cfg: ExperimentConfig, source: str, base_dir: str | Path = ".", trials=None) -> Estimate:
    """Refuse (:class:`ConfigError` naming the key that drives it) an experiment that needs more memory
    than is available; return the estimate."""
    est = estimate(cfg, base_dir, trials)
    avail = available_memory()
    if avail is not None and BASE_BYTES > avail:
        raise ConfigError(source, (), f"{human_bytes(avail)} of memory are available, less than the "
                          f"{human_bytes(BASE_BYTES)} the program itself needs (NEEDLECLI_MEMORY sets the limit)")
    if avail is not None and est.needed > avail:
        big = est.largest()
        raise ConfigError(source, big.key, (
            f"the experiment needs about {human_bytes(est.needed)} of memory and {human_bytes(avail)} are available: "
            f"{big.detail} hold {human_bytes(big.bytes)}; {big.hint}"))
    return est
