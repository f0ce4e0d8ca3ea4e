"""Import a lab's CSV exports into a log file, described by a small mapping YAML (no code).

One CSV per stream: a time column plus named value columns. The mapping says which file and columns
make each input, sensor and the ground truth, in which units; values are converted to the project's
units here, at the edge (mm, rad, s; m for the magnetic models)::

    description: phantom study, lab X
    time_column: t                 # default t
    time_unit: s                   # s or ms
    trials:
      - {id: trial1, dir: exports/trial1, meta: {needle: nitinol 0.5 mm, medium: agar 2 %}}
    inputs:
      v: {file: robot.csv, column: speed, unit: mm/s}
      u: {file: robot.csv, column: rot, unit: deg/s, kind: measured}
    sensors:
      us3d:
        file: us.csv
        columns: {x: tip_x, y: tip_y, z: tip_z}
        units: [mm, mm, mm]
        valid_column: ok           # optional: 1/0 or true/false
        sensor: {type: position, rate: 1.0, axes: [x, y, z], sigma: 0.3}
    truth:                         # optional
      file: tracker.csv
      columns: {x: px, y: py, z: pz}
      units: [mm, mm, mm]
      kind: ground truth           # or manual segmentation
"""

from __future__ import annotations

import csv
import math
from pathlib import Path
from typing import Literal

import numpy as np
from pydantic import Field, ValidationError, field_validator, model_validator

from needlecli.errors import ConfigError, DataError
from needlecli.io.logs import InputStream, Log, SensorStream, Trial, TruthStream
from needlecli.io.yamlfile import read_yaml
from needlecli.schema import Name, Strict, error_message, validation_error
from needlecli.sensors import SENSORS

# factor from the first unit to the second
_UNITS = {
    ("m", "mm"): 1000.0, ("cm", "mm"): 10.0, ("um", "mm"): 1e-3, ("mm", "m"): 1e-3, ("cm", "m"): 1e-2,
    ("deg", "rad"): math.pi / 180.0, ("m/s", "mm/s"): 1000.0, ("mm/s", "m/s"): 1e-3, ("cm/s", "mm/s"): 10.0,
    ("deg/s", "rad/s"): math.pi / 180.0, ("1/m", "1/mm"): 1e-3, ("1/mm", "1/m"): 1e3,
}


def unit_factor(have: str, want: str) -> float | None:
    """Factor converting ``have`` to ``want``, or None if they do not convert."""
    if have == want or not have:
        return 1.0
    return _UNITS.get((have, want))


class TrialSpec(Strict):
    id: Name
    dir: str = "."
    meta: dict[str, str | int | float | bool] = Field(default_factory=dict)


class InputSpec(Strict):
    file: str
    column: str | list[str]
    unit: str = ""
    kind: Literal["commanded", "measured"] = "commanded"


class StreamSpec(Strict):
    file: str
    columns: dict[str, str] = Field(min_length=1, description="channel name -> CSV column")
    units: list[str] | None = Field(None, description="one unit per column of `columns`, in their order")
    valid_column: str | None = None

    @model_validator(mode="after")
    def _units_per_column(self):
        if self.units is not None and len(self.units) != len(self.columns):
            raise ValueError(f"units gives {len(self.units)} unit(s) for {len(self.columns)} columns; give one per column")
        return self


class SensorSpec(StreamSpec):
    sensor: dict = Field(description="the sensor's settings (type, rate, axes/channels, sigma, ...)")


class TruthSpec(StreamSpec):
    kind: Literal["ground truth", "manual segmentation"] = "ground truth"


class Mapping(Strict):
    description: str = ""
    time_column: str = "t"
    time_unit: Literal["s", "ms"] = "s"
    length_unit: Literal["mm", "m"] = Field("mm", description="the project's length unit for this data")
    trials: list[TrialSpec] = Field(min_length=1)
    inputs: dict[Name, InputSpec] = Field(default_factory=dict)
    sensors: dict[Name, SensorSpec] = Field(min_length=1)
    truth: TruthSpec | None = None

    @field_validator("trials")
    @classmethod
    def _unique_ids(cls, v):
        seen: dict[str, int] = {}
        for i, t in enumerate(v):
            if t.id in seen:
                raise ValueError(f"trial {i} has the id {t.id!r} of trial {seen[t.id]}; each trial needs its own id")
            seen[t.id] = i
        return v


def read_csv(path: Path, columns: list[str]) -> dict[str, np.ndarray]:
    """Numeric columns of a CSV with a header row; a bad row is an error naming file and line. Empty
    cells (and nan, NA) are missing values (NaN): a lost sensor sample, an error in an input or truth."""
    if not path.exists():
        raise DataError(f"{path}: no such CSV file")
    try:
        with path.open(newline="", encoding="utf-8") as f:
            rows = list(csv.reader(f))
    except (OSError, UnicodeDecodeError, csv.Error) as e:
        raise DataError(f"{path}: cannot read the CSV ({e})") from None
    if not rows:
        raise DataError(f"{path}: the CSV is empty")
    header = [h.strip() for h in rows[0]]
    for c in columns:
        if c not in header:
            raise DataError(f"{path}: [column {c}] not in the header ({', '.join(header)})")
    idx = [header.index(c) for c in columns]
    out = np.empty((len(rows) - 1, len(columns)))
    for r, row in enumerate(rows[1:]):
        line = r + 2
        if len(row) != len(header):
            raise DataError(f"{path}: [line {line}] has {len(row)} fields, the header has {len(header)}")
        for j, i in enumerate(idx):
            cell = row[i].strip()
            low = cell.lower()
            if low in ("true", "false"):
                out[r, j] = 1.0 if low == "true" else 0.0
                continue
            if low in ("", "nan", "na", "n/a", "null"):  # a missing value: the caller decides what it means
                out[r, j] = np.nan
                continue
            try:
                out[r, j] = float(cell)
            except ValueError:
                raise DataError(f"{path}: [line {line}, column {columns[j]}] {cell!r} is not a number") from None
    return {c: out[:, j] for j, c in enumerate(columns)}


def _times(path: Path, t: np.ndarray, scale: float) -> np.ndarray:
    t = t * scale
    bad = np.nonzero(~np.isfinite(t))[0]
    if bad.size:
        raise DataError(f"{path}: [line {bad[0] + 2}] the time is not finite")
    d = np.diff(t)
    if (d < 0).any():
        i = int(np.nonzero(d < 0)[0][0]) + 1
        raise DataError(f"{path}: [line {i + 2}] time goes backwards ({t[i - 1]:.6g} -> {t[i]:.6g} s)")
    if (d == 0).any():
        i = int(np.nonzero(d == 0)[0][0]) + 1
        raise DataError(f"{path}: [line {i + 2}] time repeated ({t[i]:.6g} s)")
    return t


def _convert(path: Path, what: str, have: list[str], want: tuple[str, ...], values: np.ndarray) -> np.ndarray:
    out = values.copy()
    for j, (h, w) in enumerate(zip(have, want)):
        f = unit_factor(h, w)
        if f is None:
            raise DataError(f"{path}: [{what}] unit {h!r} does not convert to {w!r}")
        out[:, j] *= f
    return out


def import_csv(mapping_path: str | Path) -> Log:
    """Build a log from CSV exports as a mapping YAML describes them."""
    mapping_path = Path(mapping_path)
    data, _ = read_yaml(mapping_path, "a CSV mapping")
    try:
        mp = Mapping.model_validate(data)
    except ValidationError as e:
        raise validation_error(e, data, str(mapping_path)) from None
    # sensors from their settings (validated once, before reading any CSV)
    sensors = {}
    for name, spec in mp.sensors.items():
        stype = spec.sensor.get("type")
        if stype not in SENSORS:
            raise ConfigError(str(mapping_path), ("sensors", name, "sensor", "type"),
                              f"unknown sensor type {stype!r}; known: {', '.join(SENSORS.names())}")
        cls = SENSORS.get(stype)
        try:
            settings = cls.Settings.model_validate({**spec.sensor, "name": name})
        except ValidationError as e:
            err = e.errors()[0]
            raise ConfigError(str(mapping_path), ("sensors", name, "sensor", *err["loc"]), error_message(err)) from None
        sensors[name] = (cls, settings)
    base = mapping_path.parent
    tscale = 1e-3 if mp.time_unit == "ms" else 1.0
    trials = []
    for ts in mp.trials:
        tdir = base / ts.dir
        tr = Trial(id=ts.id, meta=dict(ts.meta))
        for name, spec in mp.inputs.items():
            cols = [spec.column] if isinstance(spec.column, str) else list(spec.column)
            path = tdir / spec.file
            d = read_csv(path, [mp.time_column, *cols])
            t = _times(path, d[mp.time_column], tscale)
            v = np.stack([d[c] for c in cols], -1)
            bad = np.nonzero(~np.isfinite(v).all(-1))[0]
            if bad.size:
                raise DataError(f"{path}: [line {bad[0] + 2}, input {name}] value is not finite")
            want = {"v": f"{mp.length_unit}/s", "u": "rad/s", "omega_B": "rad/s"}.get(name, spec.unit)
            f = unit_factor(spec.unit, want)
            if f is None:
                raise DataError(f"{path}: [input {name}] unit {spec.unit!r} does not convert to {want!r}")
            tr.inputs[name] = InputStream(t=t, value=v * f, unit=want, kind=spec.kind)
        for name, spec in mp.sensors.items():
            cls, settings = sensors[name]
            path = tdir / spec.file
            try:
                chan = _channels(cls, settings, mp.length_unit)
            except ConfigError as e:
                raise ConfigError(str(mapping_path), ("sensors", name, "sensor"), e.message) from None
            for c in spec.columns:
                if c not in chan[0]:
                    raise ConfigError(str(mapping_path), ("sensors", name, "columns", c),
                                      f"sensor {settings.type!r} has channels {', '.join(chan[0])}")
            missing = [c for c in chan[0] if c not in spec.columns]
            if missing:
                raise ConfigError(str(mapping_path), ("sensors", name, "columns"), f"no column for channel {missing[0]!r}")
            cols = [spec.columns[c] for c in chan[0]]
            extra = [spec.valid_column] if spec.valid_column else []
            d = read_csv(path, [mp.time_column, *cols, *extra])
            t = _times(path, d[mp.time_column], tscale)
            v = np.stack([d[c] for c in cols], -1)
            valid = d[spec.valid_column] != 0 if spec.valid_column else np.ones(len(t), bool)
            nonfinite = ~np.isfinite(v).all(-1)
            valid = valid & ~nonfinite  # a missing value is a lost sample: invalid, and counted
            have = [dict(zip(spec.columns, spec.units))[c] for c in chan[0]] if spec.units else list(chan[1])
            v = _convert(path, f"sensor {name}", have, chan[1], np.where(nonfinite[:, None], 0.0, v))
            tr.sensors[name] = SensorStream(t=t, value=v, valid=valid, names=chan[0], units=chan[1],
                                            settings=settings.model_dump(mode="json"))
            if nonfinite.any():
                tr.meta[f"{name}_missing_values"] = int(nonfinite.sum())
        if mp.truth is not None:
            spec = mp.truth
            path = tdir / spec.file
            names = list(spec.columns)
            d = read_csv(path, [mp.time_column, *spec.columns.values()])
            t = _times(path, d[mp.time_column], tscale)
            v = np.stack([d[spec.columns[c]] for c in names], -1)
            bad = np.nonzero(~np.isfinite(v).all(-1))[0]
            if bad.size:
                raise DataError(f"{path}: [line {bad[0] + 2}, truth] value is not finite")
            want = tuple(_truth_unit(n, mp.length_unit) for n in names)
            v = _convert(path, "truth", spec.units or list(want), want, v)
            tr.truth = TruthStream(t=t, state=v, names=tuple(names), units=want, kind=spec.kind)
        trials.append(tr)
    return Log(trials=trials, attrs={"description": mp.description, "synthetic": False,
                                     "source": f"needle log import-csv {mapping_path.name}"})


def _channels(cls, settings, length_unit: str) -> tuple[tuple[str, ...], tuple[str, ...]]:
    """Channel names and units of a sensor without a model (units in the project's length unit)."""

    class _Units:
        registered_name = "import"

    _Units.length_unit = length_unit
    try:
        sensor = cls(settings, _Units())
        return tuple(sensor.channel_names), tuple(sensor.channel_units)
    except ValueError as e:  # settings that contradict each other (2 sigmas for 3 axes)
        raise ConfigError("", (), " ".join(str(e).split())) from None


def _truth_unit(name: str, length_unit: str) -> str:
    if name in ("x", "y", "z", "px", "py", "pz"):
        return length_unit
    if name in ("alpha", "beta", "gamma"):
        return "rad"
    if name == "kappa":
        return f"1/{length_unit}"
    return "1"
