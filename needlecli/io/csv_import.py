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
from needlecli.io.csv_layout import (
    DiscoverSpec,
    Formula,
    FrameSpec,
    MissingSpec,
    QuaternionSpec,
    TimeSpec,
    discover_trials,
    dumps,
    fill_file,
    first_valid_late,
    frame_trial,
    merge_meta,
    missing_masks,
    order_rows,
    quaternion_masks,
    read_meta_file,
    sample_rate,
    start_trial,
    stream_times,
    time_columns,
)
from needlecli.io.logs import InputStream, Log, SensorStream, Trial, TruthStream
from needlecli.io.yamlfile import read_yaml
from needlecli.numerics import matrix_to_euler_xyz, quaternion_to_matrix
from needlecli.schema import Name, Strict, error_message, validation_error
from needlecli.sensors import SENSORS

R_NAMES = tuple(f"R{i}{j}" for i in range(1, 4) for j in range(1, 4))

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
    id: Name = Field(description="the trial's name in the log (letters, digits, _ and -)")
    dir: str = Field(".", description="folder of the trial's CSV files, relative to the mapping")
    meta: dict[str, str | int | float | bool] = Field(default_factory=dict, description="the trial's metadata "
                                                      "(needle, medium, design factors, ...): names to values")
    meta_file: str | None = Field(None, description="a command file of this trial (key,value lines, a header "
                                  "and a row, or YAML/JSON), relative to the mapping")


class InputSpec(Strict):
    file: str | None = Field(None, description="CSV file of the input in the trial's folder; may hold {id} and "
                             "metadata fields (or give value)")
    column: str | list[str] | None = Field(None, description="the input's column, or one column per component "
                                           "(e.g. omega_B)")
    value: float | str | None = Field(None, description="a constant: a number or a formula of the trial's "
                                      "metadata (e.g. speed_mm_s), instead of file and column")
    unit: str = Field("", description="unit of the values (mm/s, cm/s, m/s, deg/s, rad/s), converted to "
                      "length_unit/s (v) or rad/s (u, omega_B); empty: already in those")
    kind: Literal["commanded", "measured"] = Field("commanded", description="what the values are: the command sent "
                                                   "to the robot or a measurement of what it did (kept in the log)")
    time: TimeSpec | None = Field(None, description="this input's time (default: the mapping's)")

    @model_validator(mode="after")
    def _source(self):
        if (self.value is None) == (self.file is None):
            raise ValueError("give either file and column, or value")
        if self.file is not None and self.column is None:
            raise ValueError("column: required key is missing (the input's column in the file)")
        return self


class StreamSpec(Strict):
    file: str = Field(description="CSV file in the trial's folder; may hold {id} and metadata fields")
    columns: dict[str, str] = Field(default_factory=dict, description="channel name -> CSV column (none for a tangent from a quaternion)")
    units: list[str] | None = Field(None, description="one unit per column of `columns`, in their order")
    valid_column: str | None = Field(None, description="a column that marks each sample valid (1/0 or true/false); "
                                     "an invalid sample is kept as lost")
    time: TimeSpec | None = Field(None, description="this stream's time (default: the mapping's)")
    missing: MissingSpec | None = Field(None, description="this stream's lost-sample rules (default: the mapping's)")
    quaternion: QuaternionSpec | None = Field(None, description="orientation columns (w, x, y, z)")
    sigma_column: str | list[str] | None = Field(None, description="per-sample noise std: one column for every "
                                                 "component or one per component")
    sigma_unit: str | None = Field(None, description="unit of the sigma column(s) (default: the values' unit)")

    @model_validator(mode="after")
    def _units_per_column(self):
        if self.units is not None and len(self.units) != len(self.columns):
            raise ValueError(f"units gives {len(self.units)} unit(s) for {len(self.columns)} columns; give one per column")
        return self


class SensorSpec(StreamSpec):
    sensor: dict = Field(description="the sensor's settings (type, rate, axes/channels, sigma, ...); without "
                         "rate, each trial's rate follows from its sample times")


class TruthSpec(StreamSpec):
    kind: Literal["ground truth", "manual segmentation"] = Field(
        "ground truth", description="where the truth comes from: a reference instrument (ground truth) or the "
        "tip marked by hand in the images (manual segmentation); kept in the log")


class Mapping(Strict):
    description: str = Field("", description="what the data are (kept in the log's attributes)")
    time_column: str = Field("t", description="the time column of every CSV, unless time or a stream's time says "
                             "otherwise")
    time_unit: Literal["s", "ms"] = Field("s", description="unit of time_column")
    time: TimeSpec | None = Field(None, description="where sample times come from (default: time_column)")
    length_unit: Literal["mm", "m"] = Field("mm", description="the project's length unit for this data")
    discover: DiscoverSpec | None = Field(None, description="trials from file names instead of a list")
    trials: list[TrialSpec] = Field(default_factory=list, validate_default=True,
                                    description="the trials, each with its id and folder (or use discover)")
    factors: list[str] = Field(default_factory=list, description="metadata keys that are design factors")
    missing: MissingSpec | None = Field(None, description="rows that are lost samples although every cell holds a "
                                        "number (default: none), for every stream")
    leading_invalid: Literal["start", "trim", "keep"] = Field(
        "start", description="start: the trial starts at the first valid sample of start_stream; trim: that "
        "stream's leading invalid rows are dropped; keep: as recorded")
    start_stream: str | None = Field(None, description="the stream whose first valid sample starts the trial "
                                     "(default: the frame's reference, else the first sensor)")
    frame: FrameSpec | None = Field(None, description="express each trial in its own frame")
    inputs: dict[Name, InputSpec] = Field(default_factory=dict, description="the model's inputs by name (v, u, "
                                          "omega_B): a column of a CSV or a constant")
    sensors: dict[Name, SensorSpec] = Field(min_length=1, description="the measurement streams by sensor name (at "
                                            "least one): file, columns, units and the sensor's settings")
    truth: TruthSpec | None = Field(None, description="the reference the estimates are compared with (optional): "
                                    "positions and/or orientations")

    @field_validator("trials")
    @classmethod
    def _unique_ids(cls, v, info):
        discover = info.data.get("discover")
        if not v and discover is None:
            raise ValueError("give the trials (a list) or discover (a file-name template)")
        if v and discover is not None:
            raise ValueError("give either trials or discover, not both")
        seen: dict[str, int] = {}
        for i, t in enumerate(v):
            if t.id in seen:
                raise ValueError(f"trial {i} has the id {t.id!r} of trial {seen[t.id]}; each trial needs its own id")
            seen[t.id] = i
        return v


def read_csv(path: Path, columns: list[str]) -> dict[str, np.ndarray]:
    """Numeric columns of a CSV with a header row; a bad row is an error naming file and line. Empty
    cells (and nan, NA) are missing values (NaN): a lost sensor sample, an error in an input or truth.

    Blank lines (nothing but spaces) at the end of the file are ignored; a blank line between rows is an
    error (a row of empty cells, ``,,,``, is how a lost sample is written: a blank line could be one, or
    a pasted gap, and a time from the row index would shift by it). A column the mapping reads must be
    named once in the header (two ``px``: which one is x would be a guess)."""
    from needlecli.io.inputs import check_kind

    check_kind(path, "a CSV file")  # a regular file (never a FIFO that would wait for ever)
    try:
        with path.open(newline="", encoding="utf-8") as f:
            rows = list(csv.reader(f))
    except (OSError, UnicodeDecodeError, csv.Error) as e:
        raise DataError(f"{path}: cannot read the CSV ({e})") from None

    def blank(row: list[str]) -> bool:
        return not row or (len(row) == 1 and not row[0].strip())

    while rows and blank(rows[-1]):
        rows.pop()
    if not rows:
        raise DataError(f"{path}: the CSV is empty")
    header = [h.strip() for h in rows[0]]
    for c in columns:
        if c not in header:
            raise DataError(f"{path}: [column {c}] not in the header ({', '.join(header)})")
        twice = [j for j, h in enumerate(header) if h == c]
        if len(twice) > 1:
            raise DataError(f"{path}: [line 1, column {twice[1] + 1}] the header names {c!r} twice (columns "
                            f"{twice[0] + 1} and {twice[1] + 1}): which one the mapping reads is ambiguous")
    if len(header) > 1:
        gap = next((r for r, row in enumerate(rows[1:]) if blank(row)), None)
        if gap is not None:
            raise DataError(f"{path}: [line {gap + 2}] is blank, between rows: blank lines are accepted at the end "
                            "only (a lost sample is a row of empty cells, e.g. ',,,')")
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


def _times(path: Path, t: np.ndarray, scale: float, lines: np.ndarray | None = None) -> np.ndarray:
    """Times in s, checked: finite, strictly increasing (``lines``: each sample's line in the file)."""
    t = t * scale
    lines = np.arange(len(t)) + 2 if lines is None else lines
    bad = np.nonzero(~np.isfinite(t))[0]
    if bad.size:
        raise DataError(f"{path}: [line {lines[bad[0]]}] the time is not finite")
    d = np.diff(t)
    if (d < 0).any():
        i = int(np.nonzero(d < 0)[0][0]) + 1
        raise DataError(f"{path}: [line {lines[i]}] time goes backwards ({t[i - 1]:.6g} -> {t[i]:.6g} s)")
    if (d == 0).any():
        i = int(np.nonzero(d == 0)[0][0]) + 1
        raise DataError(f"{path}: [line {lines[i]}] time repeated ({t[i]:.6g} s)")
    return t


def _convert(path: Path, what: str, have: list[str], want: tuple[str, ...], values: np.ndarray) -> np.ndarray:
    out = values.copy()
    for j, (h, w) in enumerate(zip(have, want)):
        f = unit_factor(h, w)
        if f is None:
            raise DataError(f"{path}: [{what}] unit {h!r} does not convert to {w!r}")
        out[:, j] *= f
    return out


def load_mapping(mapping_path: str | Path) -> Mapping:
    """Read and validate a mapping YAML (a :class:`~needlecli.errors.ConfigError` naming the key)."""
    mapping_path = Path(mapping_path)
    data, _ = read_yaml(mapping_path, "a CSV mapping")
    try:
        return Mapping.model_validate(data)
    except ValidationError as e:
        raise validation_error(e, data, str(mapping_path), schema=Mapping) from None


def import_csv(mapping_path: str | Path) -> Log:
    """Build a log from CSV exports as a mapping YAML describes them (module docstring, and
    :mod:`needlecli.io.csv_layout` for step-indexed exports, file-name templates, command files, lost
    samples, quaternions, per-sample sigmas, trial starts and frames)."""
    mapping_path = Path(mapping_path)
    mp = load_mapping(mapping_path)
    src = str(mapping_path)
    # sensors from their settings (validated once, before reading any CSV)
    sensors = {}
    for name, spec in mp.sensors.items():
        stype = spec.sensor.get("type")
        if stype not in SENSORS:
            raise ConfigError(src, ("sensors", name, "sensor", "type"),
                              f"unknown sensor type {stype!r}; known: {', '.join(SENSORS.names())}")
        cls = SENSORS.get(stype)
        given = dict(spec.sensor)
        rate_from_data = "rate" not in given
        if rate_from_data:
            given["rate"] = 1.0  # a placeholder: each trial's rate follows from its sample times
        try:
            settings = cls.Settings.model_validate({**given, "name": name})
        except ValidationError as e:
            err = e.errors()[0]
            raise ConfigError(src, ("sensors", name, "sensor", *err["loc"]), error_message(err)) from None
        sensors[name] = (cls, settings, rate_from_data)
    _check_layout(mp, src)
    base = mapping_path.parent
    default_time = mp.time or TimeSpec(column=mp.time_column, unit=mp.time_unit)
    trials = []
    for tid, tdir, meta in _trial_list(mp, base, src):
        tr = Trial(id=tid, meta=dict(meta))
        report: dict = {"mapping": mapping_path.name, "streams": {}}
        rotations: dict[str, np.ndarray] = {}
        for name, spec in mp.inputs.items():
            tr.inputs[name] = _read_input(mp, spec, name, tid, tdir, meta, default_time, src, report)
        for name, spec in mp.sensors.items():
            cls, settings, rate_from_data = sensors[name]
            tr.sensors[name], rot = _read_sensor(mp, spec, name, cls, settings, rate_from_data, tid, tdir, meta,
                                                 default_time, src, report)
            if rot is not None:
                rotations[name] = rot
            missing = report["streams"][name]["invalid"].get("empty cell", 0)
            if missing:
                tr.meta[f"{name}_missing_values"] = int(missing)
        if mp.truth is not None:
            tr.truth, rot = _read_truth(mp, mp.truth, tid, tdir, meta, default_time, src, report)
            if rot is not None:
                rotations["truth"] = rot
        start_trial(tr, mp.leading_invalid, _start_stream(mp), rotations, report)
        if mp.frame is not None:
            frame_trial(tr, mp.frame, rotations, report, path=f"{tdir}", unit=mp.length_unit)
        for sname, s in tr.sensors.items():
            if sensors[sname][2]:
                rate = sample_rate(s.t)
                if rate is not None:
                    s.settings["rate"] = rate
            report["streams"][sname]["rate_hz"] = s.settings.get("rate")
            report["streams"][sname]["rate_from"] = "sample times" if sensors[sname][2] else "mapping"
        for f in mp.factors:
            if f not in tr.meta:
                raise DataError(f"{tdir}: [trial {tid}] design factor {f!r} is not in its metadata "
                                f"(metadata: {', '.join(sorted(tr.meta)) or 'none'})")
        if mp.factors:
            tr.meta["design_factors"] = list(mp.factors)
        late = first_valid_late(tr)
        if late:
            report["warnings"] = late
        tr.meta["import_report"] = dumps(report)
        trials.append(tr)
    return Log(trials=trials, attrs={"description": mp.description, "synthetic": False,
                                     "source": f"needle log import-csv {mapping_path.name}"})


def _check_layout(mp: Mapping, src: str) -> None:
    names = set(mp.sensors) | ({"truth"} if mp.truth is not None else set())
    for key, val in (("start_stream", mp.start_stream), ("frame", mp.frame.reference if mp.frame else None)):
        if val is not None and val not in names:
            loc = (key,) if key == "start_stream" else ("frame", "reference")
            raise ConfigError(src, loc, f"no stream {val!r}; streams: {', '.join(sorted(names))}")
    if mp.frame is not None:
        ref = mp.truth if mp.frame.reference == "truth" else mp.sensors[mp.frame.reference]
        cols = set(ref.columns)
        if not {"x", "y", "z"} <= cols:
            raise ConfigError(src, ("frame", "reference"), f"stream {mp.frame.reference!r} has no x, y, z columns "
                              "(the frame needs the tip position)")
        if mp.frame.z == "orientation" and ref.quaternion is None:
            raise ConfigError(src, ("frame", "z"), f"stream {mp.frame.reference!r} has no quaternion")
        if mp.frame.bend == "orientation" and ref.quaternion is None:
            raise ConfigError(src, ("frame", "bend"), f"stream {mp.frame.reference!r} has no quaternion")
    _check_unused(mp, src)


def _check_unused(mp: Mapping, src: str) -> None:
    """A key given where nothing reads it is an error, as everywhere in the mapping: a quaternion that
    neither gives a tangent sensor's direction nor the frame's orientation, ``sigma_unit`` without
    ``sigma_column``, a truth's ``sigma_column`` (a truth has no noise), a time ``unit`` beside a
    ``period`` (in s), a constant input's ``time``, ``columns`` or ``units`` of a tangent that comes from
    its quaternion."""
    truth_rot = mp.truth is not None and (mp.truth.quaternion is not None
                                          or {"alpha", "beta", "gamma"} <= set(mp.truth.columns))
    for name, spec in mp.sensors.items():
        loc = ("sensors", name)
        tangent = spec.sensor.get("type") == "tangent"
        if spec.quaternion is not None and not tangent:
            if mp.frame is None or mp.frame.reference != name:
                raise ConfigError(src, (*loc, "quaternion"), "a sensor's quaternion gives a tangent sensor's "
                                  "direction or the frame's orientation (frame.reference); this one would be unused")
            if mp.frame.z == "path" and not (mp.frame.bend in ("auto", "orientation") and truth_rot):
                raise ConfigError(src, (*loc, "quaternion"), "with frame z: path the frame's axes come from the path"
                                  + (" and its bending direction too (bend: path)" if mp.frame.bend == "path" else
                                     ", and the truth has no orientation its bending direction would roll")
                                  + "; this quaternion would be unused")
        if tangent and spec.quaternion is not None:
            for key in ("columns", "units"):
                if getattr(spec, key):
                    raise ConfigError(src, (*loc, key), "the tangent comes from the quaternion (R e3); these "
                                      f"{key} would be unused")
    streams = [(("sensors", n), s) for n, s in mp.sensors.items()] + ([(("truth",), mp.truth)] if mp.truth else [])
    for loc, spec in streams:
        if spec.sigma_unit is not None and spec.sigma_column is None:
            raise ConfigError(src, (*loc, "sigma_unit"), "without sigma_column it would be unused")
        if loc == ("truth",) and spec.sigma_column is not None:
            raise ConfigError(src, (*loc, "sigma_column"), "a truth has no noise: this column would be unused")
    times = [(("time",), mp.time)] + [((*loc, "time"), s.time) for loc, s in streams] + [
        (("inputs", n, "time"), s.time) for n, s in mp.inputs.items()]
    for loc, t in times:
        if t is not None and t.period is not None and "unit" in t.model_fields_set:
            raise ConfigError(src, (*loc, "unit"), "a period is in s: this unit would be unused (it is the unit "
                              "of a time column or formula)")
    for name, spec in mp.inputs.items():
        if spec.value is not None and spec.time is not None:
            raise ConfigError(src, ("inputs", name, "time"), "a constant input (value) has no sample times: this "
                              "time would be unused")


def _start_stream(mp: Mapping) -> str:
    return mp.start_stream or (mp.frame.reference if mp.frame is not None else next(iter(mp.sensors)))


def _trial_list(mp: Mapping, base: Path, src: str) -> list[tuple[str, Path, dict]]:
    if mp.discover is not None:
        return discover_trials(base, mp.discover, src)
    out = []
    for i, ts in enumerate(mp.trials):
        meta = dict(ts.meta)
        if ts.meta_file:
            mf = base / fill_file(ts.meta_file, ts.id, meta, src, ("trials", i, "meta_file"))
            merge_meta(meta, read_meta_file(mf), f"{mf}:", f"the mapping's trials -> {i} -> meta")
        out.append((ts.id, base / ts.dir, meta))
    return out


def _read_rows(path: Path, cols: list[str]) -> dict[str, np.ndarray]:
    return read_csv(path, list(dict.fromkeys(cols)))


def _stream_time(mp, spec, default_time, meta, src, loc):
    tspec = spec.time or default_time
    tcols, formula = time_columns(tspec, set(meta), src, (*loc, "time") if spec.time else ("time",))
    return tspec, tcols, formula


def _check_formula_names(path: Path, formula, tcols: list[str], meta: dict) -> None:
    """A name of a time formula that is neither the row, the trial's metadata nor a column of the file:
    one error saying all three (before the CSV is read)."""
    if formula is None or not tcols or not path.is_file():
        return
    try:
        with path.open(newline="", encoding="utf-8") as f:
            header = [h.strip() for h in next(csv.reader(f), [])]
    except (OSError, UnicodeDecodeError, csv.Error):
        return  # read_csv says what is wrong with the file
    for c in tcols:
        if c not in header:
            raise DataError(f"{path}: [time formula {formula.text}] unknown name {c!r}: not row, not a column "
                            f"({', '.join(header)}), not the trial's metadata ({', '.join(sorted(meta)) or 'none'})")


def _read_input(mp, spec: InputSpec, name, tid, tdir, meta, default_time, src, report) -> InputStream:
    want = {"v": f"{mp.length_unit}/s", "u": "rad/s", "omega_B": "rad/s"}.get(name, spec.unit)
    f = unit_factor(spec.unit, want)
    where = f"{tdir}: [trial {tid} -> input {name}]"
    if f is None:
        raise DataError(f"{where} unit {spec.unit!r} does not convert to {want!r}")
    if spec.value is not None:  # a constant from the command file (or a number)
        if isinstance(spec.value, str):
            v = Formula(spec.value, src, ("inputs", name, "value"))({k: x for k, x in meta.items()}, where)
        else:
            v = np.asarray(float(spec.value))
        v = np.atleast_1d(v).astype(float).reshape(1, -1)
        if not np.isfinite(v).all():
            raise DataError(f"{where} value {spec.value!r} is not finite ({v.ravel().tolist()})")
        report["streams"][f"input {name}"] = {"value": str(spec.value), "constant": v.ravel().tolist()}
        return InputStream(t=np.zeros(1), value=v * f, unit=want, kind=spec.kind)
    cols = [spec.column] if isinstance(spec.column, str) else list(spec.column)
    path = tdir / fill_file(spec.file, tid, meta, src, ("inputs", name, "file"))
    tspec, tcols, formula = _stream_time(mp, spec, default_time, meta, src, ("inputs", name))
    _check_formula_names(path, formula, tcols, meta)
    d = _read_rows(path, [*tcols, *cols])
    n = len(d[cols[0]])
    t = _times(path, stream_times(tspec, formula, n, d, meta, str(path)), 1.0)
    v = np.stack([d[c] for c in cols], -1)
    bad = np.nonzero(~np.isfinite(v).all(-1))[0]
    if bad.size:
        raise DataError(f"{path}: [line {bad[0] + 2}, input {name}] value is not finite")
    report["streams"][f"input {name}"] = {"file": path.name, "rows": n, "time": tspec.describe()}
    return InputStream(t=t, value=v * f, unit=want, kind=spec.kind)


def _read_samples(mp, spec: StreamSpec, name: str, value_cols: list[str], tid, tdir, meta, default_time, src, loc,
                  report):
    """One stream's rows: ``(path, t, values (M, k), valid (M,), quaternions (M, 4) or None, sigma (M, s) or
    None)``, the lost samples marked invalid with their reason (counted in ``report``), rows whose time
    cannot be placed (lost samples only) dropped."""
    path = tdir / fill_file(spec.file, tid, meta, src, (*loc, "file"))
    tspec, tcols, formula = _stream_time(mp, spec, default_time, meta, src, loc)
    qcols = spec.quaternion.columns if spec.quaternion is not None else []
    scols = [spec.sigma_column] if isinstance(spec.sigma_column, str) else list(spec.sigma_column or [])
    extra = [spec.valid_column] if spec.valid_column else []
    _check_formula_names(path, formula, tcols, meta)
    d = _read_rows(path, [*tcols, *value_cols, *qcols, *scols, *extra])
    n = len(next(iter(d.values()))) if d else 0
    t = stream_times(tspec, formula, n, d, meta, str(path))
    v = np.stack([d[c] for c in value_cols], -1) if value_cols else np.zeros((n, 0))
    q = np.stack([d[c] for c in qcols], -1) if qcols else None
    sig = np.stack([d[c] for c in scols], -1) if scols else None
    reasons: dict[str, np.ndarray] = {}
    valid = np.ones(n, dtype=bool)

    def mark(reason: str, mask: np.ndarray) -> None:
        new = mask & valid
        if new.any():
            reasons[reason] = reasons.get(reason, np.zeros(n, dtype=bool)) | new
            valid[new] = False

    if spec.valid_column:
        mark(f"{spec.valid_column} = 0", d[spec.valid_column] == 0)
    cells = np.concatenate([x for x in (v, q) if x is not None and x.size], -1) if (v.size or q is not None) else v
    mark("empty cell", ~np.isfinite(cells).all(-1) if cells.size else np.zeros(n, dtype=bool))
    lost = spec.missing or mp.missing
    with np.errstate(invalid="ignore"):
        for reason, mask in missing_masks(np.where(np.isfinite(cells), cells, np.nan), lost).items():
            mark(reason, mask)
        if q is not None:
            _, not_unit = quaternion_masks(q, spec.quaternion.tol)
            mark(f"quaternion not of unit length (tol {spec.quaternion.tol:g})", not_unit)
        if sig is not None:
            mark("sigma not positive or empty", ~(np.isfinite(sig) & (sig > 0)).all(-1))
            if lost is not None:
                for s in lost.sentinel:
                    mark(f"sentinel {s:g}", (sig == s).any(-1))
    keep = order_rows(t, valid)
    dropped = int((~keep).sum())
    lines = np.nonzero(keep)[0] + 2
    t = _times(path, t[keep], 1.0, lines)
    if name == "truth" and "empty cell" in reasons and (reasons["empty cell"] & keep).any():
        raise DataError(f"{path}: [line {int(np.nonzero(reasons['empty cell'])[0][0]) + 2}, truth] value is not finite")
    rep = {"file": path.name, "rows": n, "time": tspec.describe(), "valid": int(valid[keep].sum()),
           "invalid": {r: int((m & keep).sum()) for r, m in reasons.items() if (m & keep).any()}}
    if dropped:
        rep["dropped rows (lost samples whose time cannot be placed)"] = dropped
    report["streams"][name] = rep
    return path, t, v[keep], valid[keep], (q[keep] if q is not None else None), (sig[keep] if sig is not None else None)


def _read_sensor(mp, spec: SensorSpec, name, cls, settings, rate_from_data, tid, tdir, meta, default_time, src, report):
    try:
        chan = _channels(cls, settings, mp.length_unit)
    except ConfigError as e:  # settings that contradict each other: the mapping's sensor entry
        raise ConfigError(src, ("sensors", name, "sensor"), e.message) from None
    derived = settings.type == "tangent" and spec.quaternion is not None  # R e3 of the quaternion
    for c in spec.columns:
        if c not in chan[0]:
            raise ConfigError(src, ("sensors", name, "columns", c), f"sensor {settings.type!r} has channels {', '.join(chan[0])}")
    if not derived:
        missing = [c for c in chan[0] if c not in spec.columns]
        if missing:
            raise ConfigError(src, ("sensors", name, "columns"), f"no column for channel {missing[0]!r}")
    cols = [] if derived else [spec.columns[c] for c in chan[0]]
    path, t, v, valid, q, sig = _read_samples(mp, spec, name, cols, tid, tdir, meta, default_time, src,
                                              ("sensors", name), report)
    rot = None
    if q is not None:
        rot = np.full((len(t), 3, 3), np.nan)
        rot[valid] = quaternion_to_matrix(q[valid])
    if derived:
        v = np.where(valid[:, None], np.nan_to_num(rot[:, :, 2]), 0.0)
    else:
        have = [dict(zip(spec.columns, spec.units))[c] for c in chan[0]] if spec.units else list(chan[1])  # column order
        v = _convert(path, f"sensor {name}", have, chan[1], np.where(valid[:, None], v, 0.0))
        v = np.where(valid[:, None], v, 0.0)
    sigma = None
    if sig is not None:
        m = len(chan[0])
        if sig.shape[1] not in (1, m):
            raise ConfigError(src, ("sensors", name, "sigma_column"), f"{sig.shape[1]} columns for {m} channels")
        have = spec.sigma_unit or (spec.units[0] if spec.units else chan[1][0])
        sig = np.broadcast_to(sig, (len(t), m)).copy()
        sigma = _convert(path, f"sensor {name} sigma", [have] * m, chan[1], np.where(valid[:, None], sig, np.nan))
    stored = settings.model_dump(mode="json")
    return SensorStream(t=t, value=v, valid=valid, names=chan[0], units=chan[1], settings=stored, sigma=sigma), rot


def _read_truth(mp, spec: TruthSpec, tid, tdir, meta, default_time, src, report):
    names = list(spec.columns)
    rot_names = ("alpha", "beta", "gamma", *R_NAMES)
    if spec.quaternion is not None:
        clash = [n for n in names if n in rot_names]
        if clash:
            raise ConfigError(src, ("truth", "columns", clash[0]), "given by the quaternion too")
    path, t, v, valid, q, _ = _read_samples(mp, spec, "truth", [spec.columns[c] for c in names], tid, tdir, meta,
                                            default_time, src, ("truth",), report)
    if not valid.all():  # a truth has no lost samples: they are left out
        report["streams"]["truth"]["left out (truth keeps valid samples only)"] = int((~valid).sum())
    t, v = t[valid], v[valid]
    want = tuple(_truth_unit(n, mp.length_unit) for n in names)
    v = _convert(path, "truth", spec.units or list(want), want, v)
    rot = None
    if q is not None:
        rot = quaternion_to_matrix(q[valid])
        v = np.concatenate([v, matrix_to_euler_xyz(rot), rot.reshape(-1, 9)], -1)
        names += list(rot_names)
        want += ("rad",) * 3 + ("1",) * 9
    return TruthStream(t=t, state=v, names=tuple(names), units=want, kind=spec.kind), rot


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
