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
    """Noise growing with distance from a transducer: ``sigma = (1 + a d / d_max) sigma_c`` (the multi-rate UKF paper)."""

    transducer: tuple[float, float, float] = Field(description="transducer position, model length unit")
    a: NonNeg = Field(1.0, description="growth coefficient (dimensionless): sigma is (1 + a) times sigma_c at d_max")
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
        cur = _child(cur, part)
    return tuple(out)


def _child(data: Any, part: Any) -> Any:
    """``data[part]`` of parsed YAML (a mapping's key, a list's index), or None where there is none."""
    if isinstance(data, dict):
        return data.get(part)
    if isinstance(data, list) and isinstance(part, int) and part < len(data):
        return data[part]
    return None


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


def _schemas(t: Any) -> list[type[BaseModel]]:
    """The schemas a field's type holds (through Annotated, Optional, unions)."""
    while typing.get_origin(t) is Annotated:
        t = typing.get_args(t)[0]
    if isinstance(t, type) and issubclass(t, BaseModel):
        return [t]
    if typing.get_origin(t) in (Union, types.UnionType):
        return [m for a in typing.get_args(t) for m in _schemas(a)]
    return []


def _member(models: list[type[BaseModel]], data: Any, key: Any = None) -> type[BaseModel] | None:
    """The member of a union of schemas that ``data`` chose (by its ``type``, ``kind`` or ``device``: a
    one-value Literal field), else the one that has ``key``, else the first."""
    if isinstance(data, dict):
        for m in models:
            for name, info in m.model_fields.items():
                lit = info.annotation
                if typing.get_origin(lit) is typing.Literal and len(typing.get_args(lit)) == 1 and \
                        data.get(info.alias or name) == typing.get_args(lit)[0]:
                    return m
    having = [m for m in models if any((i.alias or n) == key for n, i in m.model_fields.items())]
    return (having or models or [None])[0]


def keys_at(schema: type[BaseModel], data: Any, loc: tuple) -> list[str]:
    """The keys the schema allows at ``loc`` (a key path as the user wrote it, without the last key) of
    the config ``data``: what an unknown key there may have been meant to be. Empty when it is no section."""
    t: Any = schema
    for part in loc:
        while typing.get_origin(t) is Annotated:
            t = typing.get_args(t)[0]
        models = _schemas(t)
        if models:
            m = _member(models, data, part)
            info = next((i for n, i in m.model_fields.items() if (i.alias or n) == part), None)
            if info is None:
                return []
            t = info.annotation
        else:
            args = [a for a in typing.get_args(t) if a is not type(None) and a is not Ellipsis]
            origin = typing.get_origin(t)
            if origin in (Union, types.UnionType):  # e.g. list | None: the container member
                args = [a for a in args if typing.get_origin(a) in (list, tuple, dict)]
                t = args[0] if args else None
                origin = typing.get_origin(t)
                args = [a for a in typing.get_args(t) if a is not Ellipsis] if t is not None else []
            if origin in (list, tuple) and isinstance(part, int) and args:
                t = args[min(part, len(args) - 1)] if origin is tuple else args[0]
            elif origin is dict and len(args) == 2:
                t = args[1]
            else:
                return []
        data = _child(data, part)
    models = _schemas(t)
    m = _member(models, data) if models else None
    return [i.alias or n for n, i in m.model_fields.items()] if m is not None else []


def _suggestion(err: dict, loc: tuple, data: Any, schema: type[BaseModel] | None) -> str:
    """A did-you-mean for an unknown key (the schema's keys there) or an unknown type (the known ones)."""
    from needlecli.errors import did_you_mean

    if err.get("type") == "extra_forbidden" and schema is not None and loc:
        return did_you_mean(loc[-1], keys_at(schema, data, loc[:-1]))
    if err.get("type") == "union_tag_invalid":
        ctx = err.get("ctx", {})
        known = [k.strip().strip(chr(39)) for k in str(ctx.get("expected_tags", "")).split(",")]
        return did_you_mean(ctx.get("tag"), known)
    return ""


def validation_errors(e: ValidationError, data: Any, source: str, prefix: tuple = (),
                      tags: dict[str, str] | None = None, schema: type[BaseModel] | None = None) -> list[ConfigError]:
    """Every problem of a failed validation of ``data`` (from file ``source``), each a ConfigError with its
    key path as written in the file (under ``prefix``) and, given the ``schema`` that failed, a "did you
    mean" for a misspelt key or type.

    ``tags`` lists every type a top-level section may name (``{"observers": "'ekf', 'ukf'"}``) where the
    schema was built of the types the file names only: an unknown type then lists them all.
    """
    errs = e.errors()
    for err in errs:
        if err.get("type") == "union_tag_invalid" and tags and err["loc"] and err["loc"][0] in tags:
            err["ctx"] = {**err.get("ctx", {}), "expected_tags": tags[err["loc"][0]]}
    out = []
    for err in _pick_errors(errs):
        loc = _location(err, data)
        out.append(ConfigError(source, tuple(prefix) + loc, error_message(err) + _suggestion(err, loc, data, schema)))
    return out


def validation_error(e: ValidationError, data: Any, source: str, prefix: tuple = (),
                     tags: dict[str, str] | None = None, schema: type[BaseModel] | None = None) -> ConfigError:
    """The first problem of :func:`validation_errors` as one ConfigError, with how many more problems there
    are (``needle validate`` lists them all)."""
    errs = validation_errors(e, data, source, prefix, tags, schema)
    first = errs[0]
    more = f" (and {len(errs) - 1} more problem{'s' if len(errs) > 2 else ''})" if len(errs) > 1 else ""
    return ConfigError(first.source, first.loc, first.message + more)
