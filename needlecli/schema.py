"""Shared pieces of the typed config schema (pydantic, unknown keys rejected everywhere), and how its
errors read: :func:`validation_error` turns pydantic's errors into one :class:`~needlecli.errors.ConfigError`
naming the file and the key path as the user wrote it."""

from __future__ import annotations

import functools
import types
import typing
from typing import Annotated, Any, Union

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from needlecli.errors import ConfigError

#: what every config section (and every file mapping, grid, baseline) is validated with: unknown keys are
#: errors, values are frozen, types are strict (a string is not a number, true is not 1.0, 4.0 is not a
#: count) and every number is finite (NaN and infinity are rejected wherever a number is expected)
STRICT_CONFIG = ConfigDict(extra="forbid", frozen=True, strict=True, allow_inf_nan=False)


def _has_tuple(tp: Any) -> bool:
    """Whether a field's annotation is (or may be, in a union) a fixed-length tuple."""
    origin = typing.get_origin(tp)
    if origin is tuple:
        return True
    if origin is Annotated:
        return _has_tuple(typing.get_args(tp)[0])
    if origin in (Union, types.UnionType):
        return any(_has_tuple(a) for a in typing.get_args(tp))
    return False


@functools.cache
def _tuple_fields(cls: type) -> frozenset[str]:
    return frozenset(k for k, f in cls.model_fields.items() if _has_tuple(f.annotation))


class Strict(BaseModel):
    """Base of every config section: unknown keys are errors, values are frozen after validation, types
    are strict and numbers finite (:data:`STRICT_CONFIG`). YAML has no tuples: a list given for a
    fixed-length field (``transducer: [0, 0, 90]``) is taken as one, its entries still validated strictly."""

    model_config = STRICT_CONFIG

    @model_validator(mode="before")
    @classmethod
    def _lists_as_tuples(cls, data: Any) -> Any:
        if isinstance(data, dict):
            fields = _tuple_fields(cls)
            if any(isinstance(data.get(k), list) for k in fields):
                data = {k: tuple(v) if k in fields and isinstance(v, list) else v for k, v in data.items()}
        return data


#: the largest seed a results file can store (a 64-bit signed integer attribute)
MAX_SEED = 2**63 - 1

#: names that become HDF5 group names and parts of file names (sensors, observers, controllers, trials)
NAME_PATTERN = r"^[A-Za-z0-9_][A-Za-z0-9_.\-]*$"
Name = Annotated[str, Field(pattern=NAME_PATTERN, max_length=100)]


NonNeg = Annotated[float, Field(ge=0.0)]
Positive = Annotated[float, Field(gt=0.0)]
Probability = Annotated[float, Field(ge=0.0, lt=1.0)]


class DistanceGrowth(Strict):
    """Noise growing with distance from a transducer: ``sigma = (1 + a d / d_max) sigma_c`` (seed 003)."""

    transducer: tuple[float, float, float] = Field(description="transducer position, model length unit")
    a: NonNeg = 1.0
    d_max: Positive = Field(80.0, description="normalising distance, model length unit")

    def factor(self, position: np.ndarray, axes: list[int] | None = None) -> np.ndarray:
        """``1 + a d / d_max`` for positions ``(..., 3)`` (or ``(..., len(axes))`` of those axes)."""
        tr = np.asarray(self.transducer) if axes is None else np.asarray(self.transducer)[axes]
        d = np.linalg.norm(np.asarray(position) - tr, axis=-1)
        return 1.0 + self.a * d / self.d_max


# ------------------------------------------------------------------------------ how errors read
_TYPE_ERRORS = {
    "float_type": "a number", "int_type": "an integer", "string_type": "a string", "bool_type": "true or false",
    "list_type": "a list", "tuple_type": "a list", "dict_type": "a mapping", "model_type": "a mapping",
    "model_attributes_type": "a mapping",
}


def _member_tag(part: Any) -> bool:
    """Whether a location part is a label pydantic gives a member of a (non-tagged) union."""
    return isinstance(part, str) and (
        "[" in part or part.startswith("constrained-") or part in ("float", "int", "str", "bool", "function-after")
    )


def _pick_errors(errs: list[dict]) -> list[dict]:
    """Drop errors of union members the value plainly is not (``sigma: -1`` for ``float | list[float]``
    yields 'should be a valid list' besides the real problem); when every member rejects the value's
    type, keep one error saying what was allowed."""
    groups: dict[tuple, list[dict]] = {}
    for e in errs:
        i = next((j for j, part in enumerate(e["loc"]) if _member_tag(part)), None)
        if i is not None:
            groups.setdefault(tuple(e["loc"][:i]), []).append(e)
    out, seen = [], set()
    for e in errs:
        i = next((j for j, part in enumerate(e["loc"]) if _member_tag(part)), None)
        group = groups.get(tuple(e["loc"][:i])) if i is not None else None
        if not group or len({g["loc"][i] for g in group}) < 2:
            out.append(e)
            continue
        def plain(g, i=i):
            return g["type"] in _TYPE_ERRORS and len(g["loc"]) == i + 1
        real = [g for g in group if not plain(g)]
        if real:
            if e in real:
                out.append(e)
        elif id(group) not in seen:
            seen.add(id(group))
            wanted = " or ".join(dict.fromkeys(_TYPE_ERRORS[g["type"]] for g in group))
            out.append({**e, "type": "union_type", "msg": f"should be {wanted}, not {_yaml_type(e.get('input'))}"})
    return out or errs


def _yaml_type(v: Any) -> str:
    if isinstance(v, float) and not np.isfinite(v):
        return "NaN (.nan)" if np.isnan(v) else f"{'-' if v < 0 else ''}infinity (.inf)"
    for t, name in ((bool, f"{str(v).lower()} (true/false)"), (int, "a number"), (float, "a number"),
                    (str, "a string"), (list, "a list"), (tuple, "a list"), (dict, "a mapping"),
                    (type(None), "empty (null)")):
        if isinstance(v, t):
            if isinstance(v, str):
                return f"{name} {v[:40]!r}" + ("..." if len(v) > 40 else "")
            return f"{name} {v!r}" if isinstance(v, (int, float)) and not isinstance(v, bool) else name
    return type(v).__name__


def _strip_tags(loc: tuple, data: Any) -> tuple:
    """Drop discriminator tags and union-member labels that pydantic inserts into locations."""
    out = []
    cur = data
    shorthand = False  # a constant signal written as a bare number or list: no 'value' key to name
    for part in loc:
        if not (isinstance(cur, dict) and part in cur):
            if isinstance(cur, dict) and isinstance(part, str) and part in (cur.get("type"), cur.get("kind"), cur.get("device")):
                continue
            if _member_tag(part) or part == "constant" or (shorthand and part == "value"):
                shorthand = part == "constant" and not isinstance(cur, dict)
                continue
        out.append(part)
        if isinstance(cur, dict):
            cur = cur.get(part)
        elif isinstance(cur, list) and isinstance(part, int) and part < len(cur):
            cur = cur[part]
        else:
            cur = None
    return tuple(out)


def _location(err: dict, data: Any) -> tuple:
    loc = _strip_tags(tuple(err["loc"]), data)
    if err.get("type") in ("union_tag_invalid", "union_tag_not_found"):
        loc += (err.get("ctx", {}).get("discriminator", "type").strip(chr(39)),)
    elif err.get("type") == "missing" and loc and isinstance(loc[-1], int):
        loc = loc[:-1]  # a fixed-length list with too few entries
    return loc


def error_message(err: dict) -> str:
    """One pydantic error as one line in the user's words."""
    msg = err.get("msg", "invalid value")
    if msg.startswith("Value error, "):
        msg = msg[len("Value error, ") :]
    if err.get("type") == "extra_forbidden":
        msg = "unknown key"
    elif err.get("type") == "missing":
        loc = err.get("loc", ())
        msg = f"too few entries (entry {loc[-1]} is missing)" if loc and isinstance(loc[-1], int) else (
            "required key is missing")
    elif err.get("type") == "union_tag_invalid":
        ctx = err.get("ctx", {})
        msg = f"unknown {ctx.get('discriminator', 'type').strip(chr(39))} {ctx.get('tag')!r}; known: {ctx.get('expected_tags')}"
    elif err.get("type") == "union_tag_not_found":
        msg = f"required key {err.get('ctx', {}).get('discriminator', '').strip(chr(39))!r} is missing"
    elif err.get("type") in ("dict_type", "model_type", "model_attributes_type"):
        loc = err.get("loc", ())
        what = "a number, a list or a mapping with 'kind'" if len(loc) == 2 and loc[0] == "inputs" else "a mapping"
        msg = f"should be {what}, not {_yaml_type(err.get('input'))}"
    elif err.get("type") in ("list_type", "tuple_type"):
        msg = f"should be a list, not {_yaml_type(err.get('input'))}"
    elif err.get("type") == "int_type" and isinstance(err.get("input"), float) and not isinstance(err.get("input"), bool):
        msg = f"should be an integer, not {err['input']!r} (write a whole number without a decimal point)"
    elif err.get("type") in _TYPE_ERRORS:
        msg = f"should be {_TYPE_ERRORS[err['type']]}, not {_yaml_type(err.get('input'))}"
    elif err.get("type") == "finite_number":
        msg = f"should be a finite number, not {_yaml_type(err.get('input'))}"
    elif err.get("type") == "string_pattern_mismatch" and err.get("ctx", {}).get("pattern") == NAME_PATTERN:
        msg = (f"{_yaml_type(err.get('input'))} is not a plain name: use letters, digits and _ . - "
               "(it names groups and files)")
    msg = msg.replace(" after validation", "")
    if msg.startswith("Input should be "):
        msg = msg[len("Input "):]
    return " ".join(msg.split())  # one line


def validation_error(e: ValidationError, data: Any, source: str, prefix: tuple = (),
                     tags: dict[str, str] | None = None) -> ConfigError:
    """The first problem of a failed validation of ``data`` (from file ``source``) as a ConfigError, its
    key path as written in the file (under ``prefix``), with how many more problems there are.

    ``tags`` lists every type a top-level section may name (``{"observers": "'ekf', 'ukf'"}``) where the
    schema was built of the types the file names only: an unknown type then lists them all.
    """
    errs = e.errors()
    for err in errs:
        if err.get("type") == "union_tag_invalid" and tags and err["loc"] and err["loc"][0] in tags:
            err["ctx"] = {**err.get("ctx", {}), "expected_tags": tags[err["loc"][0]]}
    errs = _pick_errors(errs)
    err = errs[0]
    more = f" (and {len(errs) - 1} more problem{'s' if len(errs) > 2 else ''})" if len(errs) > 1 else ""
    return ConfigError(source, tuple(prefix) + _location(err, data), error_message(err) + more)
