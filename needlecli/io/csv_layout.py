"""How a lab's exports are laid out, beyond one time-stamped CSV per stream: the parts of the CSV mapping
(:mod:`needlecli.io.csv_import`) that carry real exports without code.

* **Time** (``time:``, globally or per stream): a column (``s``, ``ms``, ``us``, ``min``), a fixed sample
  period, or a formula of the row index, the file's columns and the trial's metadata
  (``row * step_mm / speed_mm_s``; :class:`Formula`: arithmetic, ``sqrt``, ``abs``, ``cumsum``, ...).
* **Trials from file names** (``discover:``): a template such as ``exports/{id}_dc{duty_cycle}_pose.csv``;
  every file that matches is a trial, the fields in braces are its id and metadata (numbers where they
  parse), and an optional per-trial command file (``meta_file: exports/{id}_cmd.csv``: ``key,value``
  lines, one header row and one row of values, or YAML/JSON) adds the rest (step length, speed, rotation
  speed, duty cycle, ...).
* **Missing samples** (``missing:``): all-zero rows (a tracker that lost the tip) and sentinel values are
  lost samples, kept as invalid and counted with their reason.
* **Orientation as quaternions** (``quaternion: {w, x, y, z}``, column names): the truth gets
  ``alpha, beta, gamma`` and ``R11 .. R33``; a ``tangent`` sensor its ``R e3``; a quaternion far from unit
  length is a lost sample.
* **Per-sample sigma** (``sigma_column``): a column as each sample's noise std (the log keeps it; fits
  weigh each sample by it).
* **Trial start** (``leading_invalid``): ``start`` (default) starts the trial at the first valid sample
  of the reference stream, ``trim`` drops that stream's leading invalid rows and keeps the clock,
  ``keep`` leaves the trial as recorded; which one, and how much was cut, goes into the trial's report.
* **Trial frames** (``frame:``): origin at the first valid pose, ``z`` along the initial insertion
  direction, the bending direction on ``-y`` (:mod:`needlecli.io.frames`).

Everything the importer read, dropped and why goes into each trial's ``import_report`` (metadata, JSON),
which ``needle log info`` prints.
"""

from __future__ import annotations

import ast
import csv
import json
import math
import re
from pathlib import Path
from typing import Literal

import numpy as np
from pydantic import Field, model_validator

from needlecli.errors import ConfigError, DataError
from needlecli.schema import Positive, Strict

MetaValue = str | int | float | bool
TIME_UNITS = {"s": 1.0, "ms": 1e-3, "us": 1e-6, "min": 60.0}


# ---------------------------------------------------------------------------------------------- schema
class TimeSpec(Strict):
    """Where a stream's sample times come from: exactly one of ``column``, ``period`` or ``formula``."""

    column: str | None = Field(None, description="a column of time stamps, in `unit`")
    unit: Literal["s", "ms", "us", "min"] = Field("s", description="unit of the column or of the formula")
    period: Positive | None = Field(None, description="a fixed sample period, s: row k at k * period")
    formula: str | None = Field(None, description="an expression of row (0, 1, ...), the file's columns and "
                                "the trial's metadata, in `unit` (e.g. row * step_mm / speed_mm_s)")

    @model_validator(mode="after")
    def _one(self):
        given = [k for k in ("column", "period", "formula") if getattr(self, k) is not None]
        if len(given) != 1:
            raise ValueError("give exactly one of column, period, formula" + (f" (given: {', '.join(given)})" if given else ""))
        return self

    def describe(self) -> str:
        if self.column is not None:
            return f"column {self.column!r} ({self.unit})"
        if self.period is not None:
            return f"fixed period {self.period:g} s"
        return f"formula {self.formula} ({self.unit})"


class MissingSpec(Strict):
    """Rows that are lost samples although every cell holds a number."""

    zero_rows: bool = Field(False, description="a row whose value columns are all exactly zero is lost")
    sentinel: list[float] = Field(default_factory=list, description="a value column equal to one of these is lost")


class QuaternionSpec(Strict):
    """Orientation as a unit quaternion, by column names (scalar ``w``)."""

    w: str = Field(description="column of the scalar part w")
    x: str = Field(description="column of the x part")
    y: str = Field(description="column of the y part")
    z: str = Field(description="column of the z part")
    tol: Positive = Field(0.05, description="a quaternion whose length is further than this from 1 is lost")

    @property
    def columns(self) -> list[str]:
        return [self.w, self.x, self.y, self.z]


class DiscoverSpec(Strict):
    """Trials from file names: every file matching ``files`` is a trial."""

    files: str = Field(description="template relative to the mapping, e.g. exports/{id}_pose.csv; fields in "
                       "braces become the trial's id ({id}, required) and metadata")
    meta_file: str | None = Field(None, description="template of a per-trial command file (key,value lines, "
                                  "a header and one row, or YAML/JSON), relative to the mapping")
    meta: dict[str, MetaValue] = Field(default_factory=dict, description="metadata of every trial")


class FrameSpec(Strict):
    """The trial frame (:mod:`needlecli.io.frames`): origin at the reference stream's first valid pose,
    ``z`` along the initial insertion direction, the bending direction on ``-y``."""

    reference: str = Field(description="the stream giving the pose: a position sensor or truth (with x, y, z)")
    z: Literal["auto", "orientation", "path"] = Field(
        "auto", description="initial direction from the reference's orientation (its quaternion) or from the "
        "path's first chord; auto: the orientation where there is one")
    bend: Literal["auto", "orientation", "path"] = Field(
        "auto", description="bending direction (the roll that puts it on -y) from the orientations (body-frame "
        "change of the tangent) or from the path's deviation from its initial line; auto: the orientations "
        "where the reference has a quaternion")
    chord: Positive = Field(3.0, description="path length for directions from positions, length unit")


# ---------------------------------------------------------------------------------------------- values
def parse_value(text: str) -> MetaValue:
    """A metadata value from text: int, float, bool where it parses, else the stripped string."""
    s = str(text).strip()
    low = s.lower()
    if low in ("true", "false"):
        return low == "true"
    try:
        return int(s)
    except ValueError:
        pass
    try:
        v = float(s)
        return v if math.isfinite(v) else s
    except ValueError:
        return s


def factors_from_label(label: str) -> dict[str, MetaValue]:
    """Design factors from a label written ``name=value[, name=value ...]`` (``duty_cycle=0.25``); empty
    for any other label."""
    parts = [p for p in str(label).split(",")]
    pairs = [p.split("=", 1) for p in parts if "=" in p]
    if not pairs or len(pairs) != len(parts):
        return {}
    return {k.strip(): parse_value(v) for k, v in pairs if k.strip()}


#: the layouts of a command file :func:`read_meta_file` reads, as its errors name them
META_LAYOUTS = ("YAML/JSON mapping", "a header and one row per step", "name,value lines")


def read_meta_file(path: Path) -> dict[str, MetaValue]:
    """A per-trial command file as metadata, in one of three layouts, told apart by their content and
    named in every error (:data:`META_LAYOUTS`):

    * **YAML/JSON mapping**: a ``.yaml``, ``.yml`` or ``.json`` file, or any file whose text starts with
      ``{`` (one-line JSON): names to numbers, text or true/false. A nested value (a list, a mapping) is
      refused with its key; a key given twice with its line (the one YAML reader,
      :mod:`needlecli.io.yamlfile`).
    * **a header and one row per step** (comma, semicolon or tab separated): the header's names (no number
      among them), then one row of values, or one identical row per step (the per-trial layout of many
      lab exports): each column must hold one value in every row, which becomes the trial's metadata (a
      column that varies is an error naming it, as a ragged row or a name given twice in the header is).
      With two columns, the rows below the header must start with a number, or be identical and more than
      one (else the file is name,value lines); two lines of two texts (``needle,nitinol`` over
      ``medium,agar``) read either way, and are an error saying both readings.
    * **name,value lines** (``,``, ``=``, ``:``, tab or spaces between the two): a name given twice is an
      error naming its two lines.

    ``#`` comment lines and blank lines are skipped anywhere; line numbers in errors are the file's."""
    from needlecli.io.inputs import check_kind

    check_kind(path, "a command file")  # a regular file (never a FIFO that would wait for ever)
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as e:
        raise DataError(f"{path}: cannot read the command file ({e})") from None
    if path.suffix.lower() in (".yaml", ".yml", ".json") or text.lstrip().startswith(("{", "[")):
        return _meta_mapping(path, text)
    lines = [(n, ln) for n, ln in enumerate(text.splitlines(), 1) if ln.strip() and not ln.lstrip().startswith("#")]
    if not lines:
        raise DataError(f"{path}: the command file is empty")
    table = _meta_table(path, lines)
    if table is not None:
        return table
    out: dict[str, MetaValue] = {}
    first: dict[str, int] = {}
    for n, ln in lines:
        m = re.match(r"\s*([^,=:\t ]+)\s*(?:[,=:\t]|\s)\s*(.*?)\s*$", ln)
        if not m or m.group(2) == "":
            raise DataError(f"{path}: [line {n}] expected 'name value' (or name,value / name=value) as in name,value "
                            f"lines, got {ln.strip()!r:.60}; a command file holds {', '.join(META_LAYOUTS[:-1])} or "
                            f"{META_LAYOUTS[-1]}")
        name = m.group(1)
        if name in first:
            raise DataError(f"{path}: [line {n}, column 1] {name!r} is given twice (first on line {first[name]}): which "
                            "value holds is ambiguous")
        first[name] = n
        out[name] = parse_value(m.group(2))
    return out


def _meta_mapping(path: Path, text: str) -> dict[str, MetaValue]:
    """A YAML/JSON command file (:func:`read_meta_file`)."""
    from needlecli.io.yamlfile import parse_yaml

    data = parse_yaml(text, str(path), "a command file (YAML/JSON mapping)")
    out = {}
    for k, v in data.items():
        if not isinstance(v, (str, int, float, bool)):
            kind = ("a list" if isinstance(v, list) else "a mapping" if isinstance(v, dict) else "empty" if v is None
                    else f"a {type(v).__name__} ({v})")
            raise DataError(f"{path}: [{k}] is {kind}: a command file (YAML/JSON mapping) gives each name a number, "
                            "a text or true/false")
        out[str(k)] = v if not isinstance(v, str) else parse_value(v)
    return out


def _meta_table(path: Path, lines: list[tuple[int, str]]) -> dict[str, MetaValue] | None:
    """A header and one row per step (:func:`read_meta_file`): the constant columns, or None when the file
    is not in that layout."""
    if len(lines) < 2:
        return None
    sep = next((c for c in (",", ";", "\t") if c in lines[0][1]), None)
    if sep is None:
        return None
    rows = [[c.strip() for c in next(csv.reader([ln], delimiter=sep))] for _, ln in lines]
    head = rows[0]
    if len(head) < 2 or any(not h or _is_number(h) for h in head):
        return None
    if len(head) == 2:  # or name,value lines whose first value is a text
        if len(rows[1]) != 2 or not (all(_is_number(r[0]) for r in rows[1:] if r)
                                     or (len(rows) > 2 and all(r == rows[1] for r in rows[2:]))):
            if len(rows) == 2 and len(rows[1]) == 2:  # two texts over two texts: either reading holds
                raise DataError(f"{path}: [line {lines[1][0]}] two readings hold: name,value lines ({head[0]} = "
                                f"{head[1]!r}, {rows[1][0]} = {rows[1][1]!r}) or a header and one row ({head[0]} = "
                                f"{rows[1][0]!r}, {head[1]} = {rows[1][1]!r}); write it so that one does (name = value lines, "
                                "or a YAML/JSON mapping)")
            return None
    layout = META_LAYOUTS[1]
    seen: dict[str, int] = {}
    for j, h in enumerate(head, 1):
        if h in seen:
            raise DataError(f"{path}: [line {lines[0][0]}, column {j}] {h!r} is given twice in the header (columns "
                            f"{seen[h]} and {j}) of {layout}: which value holds is ambiguous")
        seen[h] = j
    for (n, _), r in zip(lines[1:], rows[1:]):
        if len(r) != len(head):
            raise DataError(f"{path}: [line {n}] has {len(r)} fields, the header has {len(head)} ({layout})")
    out = {}
    for j, h in enumerate(head):
        first = rows[1][j]
        for (n, _), r in zip(lines[2:], rows[2:]):
            if r[j] != first:
                raise DataError(f"{path}: [line {n}, column {h}] the column varies ({first!r} on line {lines[1][0]}, "
                                f"{r[j]!r} here): {layout} holds one value per column, the trial's metadata")
        out[h] = parse_value(first)
    return out


def _is_number(s: str) -> bool:
    try:
        float(s)
        return True
    except ValueError:
        return False


# ---------------------------------------------------------------------------------------------- formulas
_FUNCS = {"sqrt": np.sqrt, "abs": np.abs, "exp": np.exp, "log": np.log, "sin": np.sin, "cos": np.cos,
          "cumsum": np.cumsum, "round": np.round, "floor": np.floor, "min": np.minimum, "max": np.maximum}
_BINOPS = {ast.Add: np.add, ast.Sub: np.subtract, ast.Mult: np.multiply, ast.Div: np.true_divide,
           ast.Pow: np.power, ast.Mod: np.mod, ast.FloorDiv: np.floor_divide}


class Formula:
    """An arithmetic expression over named values (arrays or numbers), parsed once and checked: numbers,
    names, ``+ - * / // % **``, parentheses and the functions ``sqrt abs exp log sin cos cumsum round floor
    min max``; nothing else (no attribute access, no calls of anything else)."""

    def __init__(self, text: str, source: str, loc: tuple) -> None:
        self.text, self.source, self.loc = text, source, loc
        try:
            self.tree = ast.parse(str(text), mode="eval")
        except SyntaxError as e:
            raise ConfigError(source, loc, f"cannot parse the formula {text!r} ({e.msg})") from None
        self.names: list[str] = []
        self._check(self.tree.body)

    def _check(self, node) -> None:
        if isinstance(node, ast.BinOp) and type(node.op) in _BINOPS:
            self._check(node.left)
            self._check(node.right)
        elif isinstance(node, ast.UnaryOp) and isinstance(node.op, (ast.USub, ast.UAdd)):
            self._check(node.operand)
        elif isinstance(node, ast.Constant) and isinstance(node.value, (int, float)) and not isinstance(node.value, bool):
            pass
        elif isinstance(node, ast.Name):
            if node.id not in self.names:
                self.names.append(node.id)
        elif isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and node.func.id in _FUNCS and not node.keywords:
            for a in node.args:
                self._check(a)
        else:
            raise ConfigError(self.source, self.loc, f"formula {self.text!r}: {ast.unparse(node)!r} is not allowed "
                              f"(numbers, names, + - * / // % **, and {', '.join(_FUNCS)})")

    def __call__(self, env: dict, where: str = "") -> np.ndarray:
        missing = [n for n in self.names if n not in env]
        if missing:
            raise DataError(f"{where}: [formula {self.text}] unknown name {missing[0]!r} (known: {', '.join(sorted(env))})")

        def ev(node):
            if isinstance(node, ast.BinOp):
                return _BINOPS[type(node.op)](ev(node.left), ev(node.right))
            if isinstance(node, ast.UnaryOp):
                v = ev(node.operand)
                return -v if isinstance(node.op, ast.USub) else v
            if isinstance(node, ast.Constant):
                return float(node.value)
            if isinstance(node, ast.Name):
                v = env[node.id]
                if isinstance(v, (str, bool)):
                    raise DataError(f"{where}: [formula {self.text}] {node.id!r} is {v!r}, not a number")
                return np.asarray(v, dtype=float)
            return _FUNCS[node.func.id](*[ev(a) for a in node.args])

        with np.errstate(all="ignore"):
            return np.asarray(ev(self.tree.body), dtype=float)


def time_columns(spec: TimeSpec, meta_names, source: str, loc: tuple) -> tuple[list[str], Formula | None]:
    """The CSV columns a time spec reads (and its parsed formula)."""
    if spec.column is not None:
        return [spec.column], None
    if spec.formula is not None:
        f = Formula(spec.formula, source, loc)
        return [n for n in f.names if n != "row" and n not in meta_names], f
    return [], None


def stream_times(spec: TimeSpec, formula: Formula | None, n_rows: int, columns: dict, meta: dict, where: str) -> np.ndarray:
    """Times in s of ``n_rows`` rows (not checked for order here)."""
    if spec.period is not None:
        return spec.period * np.arange(n_rows, dtype=float)
    if spec.column is not None:
        return columns[spec.column] * TIME_UNITS[spec.unit]
    env = {k: v for k, v in meta.items()}
    env.update(columns)
    env["row"] = np.arange(n_rows, dtype=float)
    t = formula(env, where)
    return np.broadcast_to(t, (n_rows,)).astype(float) * TIME_UNITS[spec.unit]


# ---------------------------------------------------------------------------------------------- trials
def _template_regex(template: str) -> tuple[str, re.Pattern, list[str]]:
    """``(glob, regex, fields)`` of a file-name template with ``{field}`` parts."""
    fields = re.findall(r"\{([A-Za-z_][A-Za-z0-9_]*)\}", template)
    parts = re.split(r"\{[A-Za-z_][A-Za-z0-9_]*\}", template)
    glob = "*".join(parts)
    rx = ""
    for i, p in enumerate(parts):
        rx += re.escape(p)
        if i < len(fields):
            name = fields[i]
            rx += f"(?P={name})" if name in fields[:i] else f"(?P<{name}>[^/]+?)"
    return glob, re.compile(rx + r"\Z"), fields


def discover_trials(base: Path, spec: DiscoverSpec, source: str) -> list[tuple[str, Path, dict]]:
    """``(id, trial folder, metadata)`` of every file matching the template, sorted by id."""
    glob, rx, fields = _template_regex(spec.files)
    if "id" not in fields:
        raise ConfigError(source, ("discover", "files"), "the template must have an {id} field (the trial id)")
    out, seen = [], {}
    for p in sorted(base.glob(glob)):
        rel = p.relative_to(base).as_posix()
        m = rx.match(rel)
        if not m or not p.is_file():
            continue
        found = m.groupdict()
        tid = found.pop("id")
        if not re.fullmatch(r"[A-Za-z0-9_.\-]+", tid):
            raise DataError(f"{p}: the trial id {tid!r} from the file name is not a valid id (letters, digits, _ . -)")
        if tid in seen:
            raise DataError(f"{p}: trial id {tid!r} also comes from {seen[tid]}")
        seen[tid] = p
        meta: dict = dict(spec.meta)
        merge_meta(meta, {k: parse_value(v) for k, v in found.items()}, f"{p}: [file name]", "the mapping's discover.meta")
        if spec.meta_file:
            mf = base / _fill(spec.meta_file, {"id": tid, **found}, source, ("discover", "meta_file"))
            merge_meta(meta, read_meta_file(mf), f"{mf}:", f"the file name {p.name} or the mapping")
            meta["command_file"] = str(mf.relative_to(base)) if mf.is_relative_to(base) else str(mf)
        out.append((tid, p.parent, meta))
    if not out:
        raise DataError(f"{base / glob}: no file matches the trials' template {spec.files!r}")
    return sorted(out, key=lambda x: x[0])


def merge_meta(meta: dict, new: dict, where: str, before: str) -> None:
    """Add a trial's metadata from another place (in place): a name both give is an error unless they give
    the same value (``where``: the new place, in words; ``before``: the earlier ones)."""
    for k, v in new.items():
        if k in meta and (meta[k] != v or isinstance(meta[k], bool) != isinstance(v, bool)):
            raise DataError(f"{where} [{k}] is {v!r} here but {meta[k]!r} in {before}: which value holds is ambiguous")
        meta[k] = v


def _fill(template: str, fields: dict, source: str, loc: tuple) -> str:
    try:
        return template.format(**{k: v for k, v in fields.items()})
    except KeyError as e:
        raise ConfigError(source, loc, f"unknown field {{{e.args[0]}}} in {template!r} (fields: {', '.join(fields)})") from None
    except (ValueError, IndexError) as e:
        raise ConfigError(source, loc, f"bad template {template!r} ({e})") from None


def fill_file(template: str, tid: str, meta: dict, source: str, loc: tuple) -> str:
    """A stream's file name for one trial: ``{id}`` and any metadata field filled in."""
    if "{" not in template:
        return template
    return _fill(template, {"id": tid, **meta}, source, loc)


# ---------------------------------------------------------------------------------------------- samples
def missing_masks(values: np.ndarray, spec: MissingSpec | None) -> dict[str, np.ndarray]:
    """Per reason, the rows of ``values (M, k)`` that are lost samples although finite."""
    out = {}
    if spec is None:
        return out
    if spec.zero_rows and values.shape[1]:
        out["all-zero row"] = (values == 0).all(-1)
    for s in spec.sentinel:
        out[f"sentinel {s:g}"] = (values == s).any(-1)
    return out


def quaternion_masks(q: np.ndarray, tol: float) -> tuple[np.ndarray, np.ndarray]:
    """``(finite, not unit)`` masks of quaternions ``(M, 4)``."""
    fin = np.isfinite(q).all(-1)
    with np.errstate(invalid="ignore"):
        norm = np.linalg.norm(np.where(fin[:, None], q, 0.0), axis=-1)
    return fin, fin & (np.abs(norm - 1.0) > tol)


def order_rows(t: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """Rows to keep so that the times increase: every row when they already do; else the invalid rows
    (lost samples with an unusable time, e.g. an all-zero row whose time column is zero too, or empty) are
    dropped where they break the order. A valid sample is always kept: the caller checks the kept times."""
    keep = np.isfinite(t) | valid  # a valid sample without a usable time stays: the caller's check names it
    d = np.diff(t[keep])
    if (d > 0).all():
        return keep
    keep &= valid  # lost samples cannot be placed in time: dropped (and counted)
    return keep


def sample_rate(t: np.ndarray) -> float | None:
    """Rate in Hz from the median spacing of sample times (None with fewer than two)."""
    if len(t) < 2:
        return None
    d = float(np.median(np.diff(t)))
    return 1.0 / d if d > 0 else None


def first_valid_late(trial, fraction: float = 0.05, seconds: float = 1.0) -> list[str]:
    """Warnings for streams whose first valid sample comes late in a trial (later than ``seconds`` and
    than ``fraction`` of the trial): a filter or fit started at t = 0 would start from it silently."""
    out = []
    end = trial.end_time
    for name, s in trial.sensors.items():
        idx = np.nonzero(s.valid)[0]
        if not idx.size:
            out.append(f"{name}: no valid sample")
            continue
        t0 = float(s.t[idx[0]])
        if t0 > seconds and t0 > fraction * max(end, 1e-9):
            out.append(f"{name}: first valid sample at {t0:.3g} s of {end:.3g} s (row {int(idx[0])})")
    return out


def dumps(report: dict) -> str:
    return json.dumps(report, default=lambda o: o.item() if isinstance(o, np.generic) else str(o))


# ---------------------------------------------------------------------------------------------- trial start
def _first_valid(trial, name: str) -> tuple[float, int] | None:
    """``(time, row)`` of the first valid sample of stream ``name`` (the truth's first sample)."""
    if name == "truth":
        if trial.truth is None or not trial.truth.t.size:
            return None
        return float(trial.truth.t[0]), 0
    s = trial.sensors[name]
    idx = np.nonzero(s.valid)[0]
    return (float(s.t[idx[0]]), int(idx[0])) if idx.size else None


def _cut_sensor(s, keep: np.ndarray, t0: float) -> None:
    s.t, s.value, s.valid = s.t[keep] - t0, s.value[keep], s.valid[keep]
    if s.sigma is not None:
        s.sigma = s.sigma[keep]


def start_trial(trial, mode: str, stream: str, rotations: dict, report: dict) -> None:
    """Where the trial starts (``leading_invalid``), in place, said in ``report["start"]``.

    ``start``: at the first valid sample of ``stream``: every stream's earlier samples are cut and the
    times shifted so that it is t = 0 (an input keeps the value in effect then); ``trim``: that stream's
    leading invalid rows are dropped, the clock kept; ``keep``: as recorded."""
    first = _first_valid(trial, stream)
    if first is None:  # named with the stream's file, as read for this trial (a header only: 0 rows)
        read = (report.get("streams") or {}).get(stream) or {}
        rows = f" ({read['rows']} row(s) read)" if "rows" in read else ""
        raise DataError(f"{read.get('file') or report.get('mapping', 'the mapping')}: [trial {trial.id} -> {stream}] "
                        f"has no valid sample{rows}: nothing to start the trial at")
    t0, row = first
    rep: dict = {"mode": mode, "stream": stream, "first_valid_row": row, "first_valid_time_s": t0}
    if mode == "keep" or (row == 0 and (mode == "trim" or t0 == 0.0)):
        rep["what"] = ("as recorded" if mode == "keep" else "nothing to cut") + (
            f"; the first valid {stream} sample is at {t0:.6g} s" if t0 > 0 else "")
        report["start"] = rep
        return
    if mode == "trim":
        s = trial.sensors[stream] if stream != "truth" else None
        if s is not None:
            keep = np.arange(len(s.t)) >= row
            _cut_sensor(s, keep, 0.0)
            if stream in rotations:
                rotations[stream] = rotations[stream][keep]
        rep["what"] = f"{row} leading invalid rows of {stream} dropped; times as recorded"
        report["start"] = rep
        return
    cut = {}
    eps = 1e-9
    for name, s in trial.sensors.items():
        keep = s.t >= t0 - eps
        cut[name] = int((~keep).sum())
        _cut_sensor(s, keep, t0)
        if name in rotations:
            rotations[name] = rotations[name][keep]
    if trial.truth is not None:
        keep = trial.truth.t >= t0 - eps
        cut["truth"] = int((~keep).sum())
        trial.truth.t, trial.truth.state = trial.truth.t[keep] - t0, trial.truth.state[keep]
        if "truth" in rotations:
            rotations["truth"] = rotations["truth"][keep]
    for name, s in trial.inputs.items():
        i0 = max(int(np.searchsorted(s.t, t0 + eps, side="right")) - 1, 0)  # the value in effect at t0
        cut[f"input {name}"] = i0
        s.t, s.value = np.maximum(s.t[i0:] - t0, 0.0), s.value[i0:]
    rep["what"] = f"started at the first valid {stream} sample (row {row}, {t0:.6g} s): earlier samples cut, times shifted by {-t0:.6g} s"
    rep["cut"] = {k: v for k, v in cut.items() if v}
    report["start"] = rep


# ---------------------------------------------------------------------------------------------- trial frame
def frame_trial(trial, spec: FrameSpec, rotations: dict, report: dict, *, path: str, unit: str) -> None:
    """Express every stream of the trial in its own frame (:mod:`needlecli.io.frames`), in place:
    positions ``G (p - p0)``, rotations ``G R Rz(psi)``, directions ``G t``; said in ``report["frame"]``."""
    from needlecli.io.frames import bend_roll, body_bend, chord_pairs, chord_step, express, path_frame, pose_axes, rolled
    from needlecli.numerics import euler_xyz_to_matrix, matrix_to_euler_xyz, so3_log

    where = f"{path}: [trial {trial.id} -> frame]"
    ref = spec.reference
    if ref == "truth":
        if trial.truth is None:
            raise DataError(f"{where} the trial has no truth")
        names = list(trial.truth.names)
        pos = trial.truth.state[:, [names.index(a) for a in "xyz"]]
        ok = np.ones(len(pos), dtype=bool)
    else:
        s = trial.sensors[ref]
        names = list(s.names)
        if not {"x", "y", "z"} <= set(names):
            raise DataError(f"{where} sensor {ref!r} has channels {names}; the frame needs x, y, z")
        pos = s.value[:, [names.index(a) for a in "xyz"]]
        ok = s.valid.copy()
    if ok.sum() < 2:
        raise DataError(f"{where} fewer than two valid samples of {ref!r}")
    rot = rotations.get(ref)
    use_rot = rot is not None and spec.z in ("auto", "orientation")
    bend_rot = rot is not None and spec.bend in ("auto", "orientation")
    psi = 0.0
    info: dict = {"reference": ref}
    if bend_rot:
        k = chord_step(pos, ok, spec.chord)
        i, j, _, n = chord_pairs(pos, ok, k, 0.3 * spec.chord)
        if len(i) >= 3:
            psi, direction = bend_roll(body_bend(rot[i], rot[j], n))
            info["roll_psi_deg"] = round(float(np.degrees(psi)), 3)
            info["bend_direction_in_body_xy_deg"] = round(float(np.degrees(direction)), 3)
        else:
            info["roll"] = "none: too little path to see the bending direction"
    first = int(np.nonzero(ok)[0][0])
    if use_rot and not bend_rot:  # bend: path, seen in the first pose's body frame
        d = (pos[ok] - pos[first]) @ pose_axes(rot[first]).T
        d[:, 2] = 0.0  # the deviation from the initial tangent
        if np.linalg.norm(d.mean(0)) > 1e-9:
            psi, direction = bend_roll(d)
            info["roll_psi_deg"] = round(float(np.degrees(psi)), 3)
            info["bend_from"] = "mean deviation of the path from the initial tangent"
        else:
            info["roll"] = "none: a straight path shows no bending direction"
    if use_rot:
        G, p0 = pose_axes(rolled(rot[first], psi)), pos[first]
        info["z_from"] = f"orientation at the first valid pose (sample {first} of the trial)"
    else:
        try:
            G, p0, pinfo = path_frame(pos, ok, spec.chord)
        except ValueError as e:
            raise DataError(f"{where} {e}") from None
        info.update(pinfo)
        if rot is not None:  # the path gives the axes; the roll must still put the bending on -y
            info["note"] = "axes from the path; rotations rolled by psi"
    info["origin"] = [round(float(x), 6) for x in p0]
    info["origin_unit"] = unit
    info["G_rotvec_deg"] = np.degrees(so3_log(G)).round(3).tolist()
    # positions
    for name, s in trial.sensors.items():
        sn = list(s.names)
        if s.settings.get("type") == "position":
            if not {"x", "y", "z"} <= set(sn):
                raise DataError(f"{where} position sensor {name!r} has axes {sn}: a frame needs x, y, z")
            c = [sn.index(a) for a in "xyz"]
            p, _ = express(G, p0, s.value[:, c])
            s.value = s.value.copy()
            s.value[:, c] = np.where(s.valid[:, None], p, 0.0)
            if s.sigma is not None and not np.allclose(s.sigma[s.valid][:, c], s.sigma[s.valid][:, c[:1]]):
                raise DataError(f"{where} sensor {name!r}: per-axis sigmas cannot be rotated into the frame")
        elif s.settings.get("type") == "tangent":
            s.value = np.where(s.valid[:, None], s.value @ G.T, 0.0)
    if trial.truth is not None:
        tn = list(trial.truth.names)
        st = trial.truth.state.copy()
        if {"x", "y", "z"} <= set(tn):
            c = [tn.index(a) for a in "xyz"]
            st[:, c], _ = express(G, p0, st[:, c])
        if "truth" in rotations or {"alpha", "beta", "gamma"} <= set(tn):
            R = rotations.get("truth")
            if R is None:
                e = st[:, [tn.index(a) for a in ("alpha", "beta", "gamma")]]
                R = euler_xyz_to_matrix(e[:, 0], e[:, 1], e[:, 2])
            _, R2 = express(G, p0, rot=rolled(R, psi))
            st[:, [tn.index(a) for a in ("alpha", "beta", "gamma")]] = matrix_to_euler_xyz(R2)
            rn = [f"R{i}{j}" for i in range(1, 4) for j in range(1, 4)]
            if all(r in tn for r in rn):
                st[:, [tn.index(r) for r in rn]] = R2.reshape(-1, 9)
        trial.truth.state = st
    report["frame"] = info
