"""Recorded insertions: the log file format (a public contract, see docs/reference/log-file.md).

One HDF5 file holds one or more trials::

    /                               attrs: format = "needlecli-log", version, created, description,
                                           synthetic (bool), source (what made it: config and seed, or
                                           the importer), config (the YAML that made it, if synthetic)
    /trials/<id>/                   attrs: metadata (needle, medium, field_strength, operator_notes, ...)
    /trials/<id>/inputs/<name>/t        (K,)   s, strictly increasing
    /trials/<id>/inputs/<name>/value    (K,) or (K, k)   attrs unit, kind (commanded | measured)
    /trials/<id>/sensors/<name>/t       (M,)   acquisition times, s, strictly increasing
    /trials/<id>/sensors/<name>/value   (M, m) attrs names, units
    /trials/<id>/sensors/<name>/valid   (M,) bool (optional: all valid)
    /trials/<id>/sensors/<name>/sigma   (M, m) optional: each sample's noise std (NaN where not valid)
    /trials/<id>/sensors/<name>         attrs sensor: JSON of the sensor's settings (type, axes, ...)
    /trials/<id>/truth/t                (L,)   optional ground truth (or manual segmentation)
    /trials/<id>/truth/state            (L, n) attrs names, units, kind (ground truth | manual segmentation)

A log is read completely and checked before any work: a missing group, timestamps going backwards or
repeated, values that are not finite in valid samples, shapes that do not match the names: each is a
:class:`~needlecli.errors.DataError` naming the file, trial, channel and sample.
"""

from __future__ import annotations

import datetime as _dt
import json
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from needlecli import __version__
from needlecli.errors import DataError
from needlecli.io.csv_layout import factors_from_label
from needlecli.io.layout import LOG, check_layout
from needlecli.io.results import Group, _decode, _one_line, write_atomic
from needlecli.schema import NAME_PATTERN

LOG_FORMAT = "needlecli-log"
LOG_VERSION = 1


@dataclass
class SensorStream:
    """One sensor's samples in one trial. ``settings`` describe the sensor (its ``type`` at least)."""

    t: np.ndarray
    value: np.ndarray
    valid: np.ndarray
    names: tuple[str, ...]
    units: tuple[str, ...]
    settings: dict[str, Any]
    sigma: np.ndarray | None = None  # (M, m) per-sample noise std where the export gives one (else nominal)


@dataclass
class InputStream:
    t: np.ndarray
    value: np.ndarray  # (K, k)
    unit: str
    kind: str = "commanded"


@dataclass
class TruthStream:
    t: np.ndarray
    state: np.ndarray  # (L, n)
    names: tuple[str, ...]
    units: tuple[str, ...]
    kind: str = "ground truth"


@dataclass
class Trial:
    id: str
    inputs: dict[str, InputStream] = field(default_factory=dict)
    sensors: dict[str, SensorStream] = field(default_factory=dict)
    truth: TruthStream | None = None
    meta: dict[str, Any] = field(default_factory=dict)

    @property
    def end_time(self) -> float:
        ends = [float(s.t[-1]) for s in self.sensors.values() if s.t.size]
        ends += [float(s.t[-1]) for s in self.inputs.values() if s.t.size]
        if self.truth is not None and self.truth.t.size:
            ends.append(float(self.truth.t[-1]))
        return max(ends) if ends else 0.0


def design_factors(trial: Trial) -> list[str]:
    """The metadata keys a trial lists as its design factors (``design_factors``: a list, or its JSON as
    a log stores it), in order; empty without."""
    f = trial.meta.get("design_factors")
    if isinstance(f, str):
        try:
            f = json.loads(f)
        except json.JSONDecodeError:
            f = [f]
    return [str(x) for x in f] if isinstance(f, (list, tuple, np.ndarray)) else []


@dataclass
class Log:
    trials: list[Trial]
    attrs: dict[str, Any] = field(default_factory=dict)
    path: str = "<memory>"


# ---------------------------------------------------------------------------------------------- writing
def log_tree(log: Log) -> Group:
    root = Group(attrs={
        "format": LOG_FORMAT,
        "version": LOG_VERSION,
        "needlecli_version": __version__,
        "created": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
        **{k: v for k, v in log.attrs.items() if k not in ("format", "version")},
    })
    trials = Group()
    for tr in log.trials:
        g = Group(attrs=_meta_attrs(tr.meta))
        ins = Group()
        for name, s in tr.inputs.items():
            ins.data[name] = Group(data={"t": s.t, "value": s.value}, attrs={"unit": s.unit, "kind": s.kind})
        g.data["inputs"] = ins
        sens = Group()
        for name, s in tr.sensors.items():
            data = {"t": s.t, "value": s.value, "valid": s.valid.astype(bool)}
            if s.sigma is not None:  # an addition older readers ignore (no version bump)
                data["sigma"] = np.where(s.valid[:, None], s.sigma, np.nan)
            sens.data[name] = Group(
                data=data,
                attrs={"names": list(s.names), "units": list(s.units), "sensor": json.dumps(s.settings)},
                dataset_attrs={"value": {"names": list(s.names), "units": list(s.units)}},
            )
        g.data["sensors"] = sens
        if tr.truth is not None:
            g.data["truth"] = Group(
                data={"t": tr.truth.t, "state": tr.truth.state},
                attrs={"names": list(tr.truth.names), "units": list(tr.truth.units), "kind": tr.truth.kind},
            )
        trials.data[tr.id] = g
    root.data["trials"] = trials
    return root


def _meta_attrs(meta: dict) -> dict:
    out = {}
    for k, v in meta.items():
        if isinstance(v, np.generic):
            v = v.item()
        out[k] = v if isinstance(v, (str, int, float, bool)) else json.dumps(v, default=str)
    return out


def write_log(path: str | Path, log: Log, source: str | Path | None = None) -> Path:
    """Write a log atomically (temporary file, then rename), after checking it with the reader's own
    checks (:func:`check_log`): nothing is written that :func:`read_log` would refuse. ``source`` is
    what the log was made from (a mapping, a data folder), named in the error."""
    check_log(log, source if source is not None else path, writing=True)
    return write_atomic(path, log_tree(log))


# ---------------------------------------------------------------------------------------------- checks
_PLAIN = re.compile(NAME_PATTERN)


def _fail(path, where: str, msg: str) -> DataError:
    return DataError(f"{path}: [{where}] {msg}")


def _check_times(path, where: str, t: np.ndarray) -> None:
    if t.ndim != 1:
        raise _fail(path, where, f"t must be one-dimensional, has shape {t.shape}")
    bad = np.nonzero(~np.isfinite(t))[0]
    if bad.size:
        raise _fail(path, where, f"timestamp of sample {bad[0]} is not finite ({t[bad[0]]})")
    neg = np.nonzero(t < 0)[0]
    if neg.size:
        raise _fail(path, where, f"timestamp of sample {neg[0]} is negative ({t[neg[0]]:.6g} s); times count from "
                    "the start of the trial")
    d = np.diff(t)
    back = np.nonzero(d < 0)[0]
    if back.size:
        i = back[0] + 1
        raise _fail(path, where, f"timestamps go backwards at sample {i} ({t[i - 1]:.6g} -> {t[i]:.6g} s)")
    rep = np.nonzero(d == 0)[0]
    if rep.size:
        i = rep[0] + 1
        raise _fail(path, where, f"timestamp repeated at sample {i} ({t[i]:.6g} s)")


def _check_name(path, where: str, what: str, name) -> None:
    if not isinstance(name, str) or not _PLAIN.match(name) or len(name) > 100:
        raise _fail(path, where, f"{what} {name!r} is not a plain name (letters, digits, _ . -)")


def _check_stream(path, tr: Trial, what: str, name: str, s) -> str:
    """A stream's name, times and value shape; returns where it is, for messages."""
    where = f"trial {tr.id} -> {what} {name}"
    _check_name(path, where, f"{what} name", name)
    _check_times(path, where, s.t)
    if s.value.ndim != 2 or s.value.shape[0] != len(s.t):
        raise _fail(path, where, f"value has shape {s.value.shape} for {len(s.t)} timestamps")
    return where


def check_trial(path, tr: Trial) -> None:
    """The reader's checks of one trial's values: times finite, non-negative and increasing; values
    shaped like their times and names; valid samples, inputs and the truth finite; sensor settings with
    their type; plain names."""
    _check_name(path, f"trial {tr.id}", "trial id", tr.id)
    for name, s in tr.inputs.items():
        where = _check_stream(path, tr, "input", name, s)
        bad = np.nonzero(~np.isfinite(s.value).all(-1))[0]
        if bad.size:
            raise _fail(path, where, f"sample {bad[0]} is not finite ({s.value[bad[0]].tolist()})")
    for name, s in tr.sensors.items():
        where = _check_stream(path, tr, "sensor", name, s)
        v = s.value
        if s.valid.shape != (len(s.t),):
            raise _fail(path, where, f"valid has shape {s.valid.shape} for {len(s.t)} timestamps")
        if len(s.names) != v.shape[1] or len(s.units) != v.shape[1]:
            raise _fail(path, where, f"{v.shape[1]} value columns but names {list(s.names)} and units {list(s.units)}")
        bad = np.nonzero(s.valid & ~np.isfinite(v).all(-1))[0]
        if bad.size:
            raise _fail(path, where, f"sample {bad[0]} is marked valid but is not finite ({v[bad[0]].tolist()})")
        if not isinstance(s.settings, dict) or "type" not in s.settings:
            raise _fail(path, where, "attribute 'sensor' must give the sensor's settings with its 'type'")
        sigma = getattr(s, "sigma", None)
        if sigma is not None:  # a sigma per sample (a tracker's RMS error), positive where the sample is valid
            if sigma.shape != v.shape:
                raise _fail(path, where, f"sigma has shape {sigma.shape}, value {v.shape}")
            bad = np.nonzero(s.valid & ~(np.isfinite(sigma) & (sigma > 0)).all(-1))[0]
            if bad.size:
                raise _fail(path, where, f"sample {bad[0]} is valid but its sigma is not positive ({sigma[bad[0]].tolist()})")
    if tr.truth is not None:
        where = f"trial {tr.id} -> truth"
        t, st, names = tr.truth.t, tr.truth.state, tr.truth.names
        _check_times(path, where, t)
        if st.ndim != 2 or st.shape != (len(t), len(names)):
            raise _fail(path, where, f"state has shape {st.shape}, expected ({len(t)}, {len(names)}) for names {list(names)}")
        if len(set(names)) != len(names):
            raise _fail(path, where, f"names {list(names)} repeat a name")
        bad = np.nonzero(~np.isfinite(st).all(-1))[0]
        if bad.size:
            raise _fail(path, where, f"sample {bad[0]} is not finite")


def check_log(log: Log, source, *, writing: bool = False) -> None:
    """Every check :func:`read_log` makes, on a log in memory (importers check what they would write)."""
    if not log.trials:
        raise DataError(f"{source}: the log holds no trials" + ("; nothing was written" if writing else ""))
    seen: set[str] = set()
    try:
        for tr in log.trials:
            if tr.id in seen:
                raise _fail(source, f"trial {tr.id}", "a trial with this id is given twice")
            seen.add(tr.id)
            check_trial(source, tr)
    except DataError as e:
        if writing:
            raise DataError(f"{e}; nothing was written") from None
        raise


# ---------------------------------------------------------------------------------------------- reading
def _dataset(path, g: h5py.Group, name: str, where: str) -> np.ndarray:
    try:
        return g[name][()]
    except (OSError, ValueError, TypeError, KeyError) as e:
        raise _fail(path, where, f"cannot read {name!r} ({_one_line(e)})") from None


def _strings(v) -> tuple[str, ...]:
    v = _decode(v)
    if isinstance(v, str):
        return (v,)
    return tuple(str(x) for x in np.atleast_1d(v))


def _read_trial(path, tid: str, g: h5py.Group) -> Trial:
    """One trial's arrays (the structure was checked against :data:`~needlecli.io.layout.LOG`)."""
    meta = {k: _decode(v) for k, v in g.attrs.items()}
    tr = Trial(id=tid, meta=meta)
    for name, s in (g["inputs"].items() if "inputs" in g else []):
        where = f"trial {tid} -> input {name}"
        t = np.asarray(_dataset(path, s, "t", where), dtype=float)
        v = np.asarray(_dataset(path, s, "value", where), dtype=float)
        v = v.reshape(len(t), -1) if v.ndim == 1 and v.size == len(t) else v
        tr.inputs[name] = InputStream(t=t, value=v, unit=str(_decode(s.attrs.get("unit", ""))),
                                      kind=str(_decode(s.attrs.get("kind", "commanded"))))
    for name, s in g["sensors"].items():
        where = f"trial {tid} -> sensor {name}"
        t = np.asarray(_dataset(path, s, "t", where), dtype=float)
        v = np.asarray(_dataset(path, s, "value", where), dtype=float)
        if v.ndim == 1:
            v = v[:, None]
        valid = np.asarray(_dataset(path, s, "valid", where), dtype=bool) if "valid" in s else np.ones(len(t), bool)
        sigma = np.asarray(_dataset(path, s, "sigma", where), dtype=float) if "sigma" in s else None
        try:
            settings = json.loads(_decode(s.attrs.get("sensor", "{}")))
        except (json.JSONDecodeError, TypeError, RecursionError):
            raise _fail(path, where, "attribute 'sensor' is not valid JSON") from None
        tr.sensors[name] = SensorStream(t=t, value=v, valid=valid, names=_strings(s.attrs.get("names", ())),
                                        units=_strings(s.attrs.get("units", ())), settings=settings, sigma=sigma)
    if "truth" in g:
        where = f"trial {tid} -> truth"
        s = g["truth"]
        t = np.asarray(_dataset(path, s, "t", where), dtype=float)
        st = np.asarray(_dataset(path, s, "state", where), dtype=float)
        tr.truth = TruthStream(t=t, state=st, names=_strings(s.attrs.get("names", ())),
                               units=_strings(s.attrs.get("units", ())),
                               kind=str(_decode(s.attrs.get("kind", "ground truth"))))
    check_trial(path, tr)
    return tr


def read_log(path: str | Path) -> Log:
    """Read and check a log file completely, its kind and format checked first (:mod:`needlecli.io.inputs`)."""
    from needlecli.errors import shown
    from needlecli.io.inputs import describe, open_hdf5
    from needlecli.io.layout import root_attribute

    path = Path(path)
    try:
        with open_hdf5(path, "a log file") as f:
            fmt = root_attribute(f, "format", "any", path)
            if isinstance(fmt, np.ndarray):  # an array where the documented text is: named with its path
                root_attribute(f, "format", "str", path)
            if not isinstance(fmt, str) or fmt != LOG_FORMAT:
                shown_fmt = fmt if isinstance(fmt, (str, int, float)) or fmt is None else f"an array of shape {np.shape(fmt)}"
                raise DataError(f"{shown(path)}: not a needlecli log: it is {describe(path)} (format attribute "
                                f"{shown_fmt!r:.40}, expected {LOG_FORMAT!r})")
            version = root_attribute(f, "version", "int", path) or 0
            if version > LOG_VERSION:
                raise DataError(f"{shown(path)}: log version {version} is newer than this needlecli reads ({LOG_VERSION})")
            check_layout(f, LOG, path)
            if not len(f["trials"]):
                raise DataError(f"{path}: the log holds no trials")
            trials = [_read_trial(path, tid, g) for tid, g in f["trials"].items()]
            attrs = {k: _decode(v) for k, v in f.attrs.items()}
    except DataError:
        raise
    except (OSError, KeyError, ValueError, TypeError, RuntimeError) as e:
        raise DataError(f"{path}: cannot read the log ({e.__class__.__name__}: {_one_line(e)})") from None
    return Log(trials=trials, attrs=attrs, path=str(path))


# ---------------------------------------------------------------------------------------------- from results
def log_from_results(res: Group, *, description: str = "", truth_every: int = 1, prefix: str = "run") -> Log:
    """A simulated experiment's streams as a log, one trial per run: inputs on the simulation grid,
    every sensor's samples with their validity, and the truth (every ``truth_every``-th step, as a
    tracker at a lower rate would record it). Marked synthetic, with its config and seed."""
    from needlecli.errors import ConfigError
    from needlecli.io.yamlfile import parse_yaml

    time = res.data["time"]
    truth = res.data["truth"]
    names = tuple(truth.attrs["names"])
    units = tuple(truth.attrs["units"])
    try:
        cfg = parse_yaml(str(res.attrs.get("config", "")), "the results file's config")
    except ConfigError:  # what the results file holds is what the log gets: its streams, their settings
        cfg = {}
    sensors = cfg.get("sensors") if isinstance(cfg.get("sensors"), list) else []
    sensor_cfg = {(s.get("name") or s.get("type")): s for s in sensors if isinstance(s, dict)}
    n_runs = truth.data["state"].shape[0]
    case_meta = _param_case_meta(truth, n_runs, ((cfg.get("model") or {}).get("param_cases") or {}).get("labels"))
    trials = []
    for r in range(n_runs):  # writing a file: one group per trial is the format, not a computation
        tr = Trial(id=f"{prefix}{r:04d}", meta={"run": r, "seed": int(res.attrs.get("seed", 0)),
                                                "experiment": str(res.attrs.get("name", "")), "synthetic": True,
                                                **case_meta[r]})
        for name, v in res.data["inputs"].data.items():
            if name == "case":
                continue
            arr = np.asarray(v[r])
            tr.inputs[name] = InputStream(t=time, value=arr.reshape(len(time), -1),
                                          unit=str(res.data["inputs"].attrs.get(f"{name}_unit", "")))
        for name, g in res.data["measurements"].data.items():
            settings = dict(sensor_cfg.get(name, {"type": g.attrs.get("type", "unknown")}))
            settings["name"] = name
            val = g.data["value"][r]
            sig = g.data.get("sigma")
            sig = np.asarray(sig[r], dtype=float) if sig is not None else None
            valid = g.data["valid"][r]
            varies = sig is not None and valid.any() and not np.allclose(sig[valid], sig[valid][:1], rtol=0, atol=0)
            tr.sensors[name] = SensorStream(
                t=g.data["t"], value=np.where(valid[:, None], val, 0.0), valid=valid,
                names=tuple(g.attrs["names"]), units=tuple(g.attrs["units"]), settings=settings,
                sigma=sig if varies else None,  # only a sigma that changes from sample to sample (growth)
            )
        ok = np.isfinite(truth.data["state"][r]).all(-1)
        ok &= (np.arange(len(time)) % truth_every) == 0
        end = truth.data["event_time"][r]
        if np.isfinite(end):
            ok &= time <= end
        tr.truth = TruthStream(t=time[ok], state=truth.data["state"][r][ok], names=names, units=units)
        trials.append(tr)
    return Log(trials=trials, attrs={
        "description": description or f"synthetic: needle simulate of {res.attrs.get('name', '')}",
        "synthetic": True,
        "source": f"needlecli {res.attrs.get('needlecli_version', '')} simulate, seed {res.attrs.get('seed', '')}",
        "config": res.attrs.get("config", ""),
    })


def _param_case_meta(truth: Group, n_runs: int, labels: list | None) -> list[dict]:
    """Each run's parameter case as trial metadata: ``param_case`` (its label), and design factors from
    labels written ``name=value[, name=value ...]`` (``duty_cycle=0.25`` -> ``duty_cycle: 0.25``, listed in
    ``design_factors``)."""
    out: list[dict] = [{} for _ in range(n_runs)]
    idx = truth.data.get("param_case")
    if idx is None:
        return out
    labels = [str(x) for x in (labels or [])]
    for r, k in enumerate(np.asarray(idx)):
        label = labels[int(k)] if int(k) < len(labels) else f"case {int(k)}"
        meta: dict = {"param_case": label}
        factors = factors_from_label(label)
        if factors:
            meta.update(factors)
            meta["design_factors"] = list(factors)
        out[r] = meta
    return out


def merge_logs(logs: list[Log], description: str = "") -> Log:
    """One log with the trials of several (ids must differ); each trial keeps where it came from."""
    trials, seen = [], set()
    for log in logs:
        for tr in log.trials:
            if tr.id in seen:
                raise DataError(f"{log.path}: [trial {tr.id}] a trial with this id is already in the merged log")
            seen.add(tr.id)
            tr.meta.setdefault("source", str(log.attrs.get("source", "")))
            if log.attrs.get("config"):
                tr.meta.setdefault("config", str(log.attrs["config"]))
            trials.append(tr)
    synthetic = all(bool(log.attrs.get("synthetic", False)) for log in logs)
    return Log(trials=trials, attrs={
        "description": description or "; ".join(str(lg.attrs.get("description", "")) for lg in logs),
        "synthetic": synthetic,
        "source": "needle log merge: " + ", ".join(lg.path for lg in logs),
    })
