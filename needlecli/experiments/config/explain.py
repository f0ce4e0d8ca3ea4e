"""The config reference, from the schema itself (``needle explain [KEY.PATH]``): every field of a section
with its type, default, allowed values and description, so a user writes a config without reading the
source. The same walk writes the reference pages of the documentation (``--format md``).

A path names a section of the config (``sensors``, ``fit.em``, ``output``), a registered component in
a section that chooses one by ``type`` (``sensors.position``, ``observers.ukf``, ``model.mnm``,
``control.opacity_bz``), or a field below either (``observers.ukf.init``, ``model.mnm.params``,
``inputs.flips``: the kinds of input signals). Components of installed plug-ins are included.

``mapping`` names the other YAML a user writes: the CSV mapping of ``needle log import-csv``
(``needle explain mapping``, ``mapping.sensors.quaternion``), read from its schema
(:class:`needlecli.io.csv_import.Mapping`) the same way.
"""

from __future__ import annotations

import types
import typing
from dataclasses import dataclass, field
from typing import Any, Literal, Union

from pydantic import BaseModel
from pydantic.fields import FieldInfo
from pydantic_core import PydanticUndefined

from needlecli.errors import ConfigError, did_you_mean

#: the sections that choose a registered component by ``type`` (``model`` is one component)
COMPONENT_SECTIONS = ("model", "sensors", "observers", "control")
#: the first part of a path into the CSV mapping of ``needle log import-csv`` (not a config section)
MAPPING = "mapping"
MAPPING_DOC = ("The mapping YAML of `needle log import-csv`: which CSV files and columns make each input, sensor "
               "and the truth of every trial, in which units (converted to mm, rad, s; m with `length_unit: m`), "
               "where the times come from, which samples are lost, and the trial's frame. "
               "`needle explain mapping.<key>` for any key below.")


@dataclass
class FieldDoc:
    """One key: name (as written in YAML), type, default ("required" when none), allowed values,
    constraints, description, and the section below it (a nested schema), if any."""

    name: str
    type: str
    default: str
    description: str
    allowed: str = ""
    constraints: str = ""
    nested: Any = None


@dataclass
class SectionDoc:
    """A section: its path, what it is, its keys, and (for a component section) the types it may name."""

    path: str
    doc: str
    fields: list[FieldDoc] = field(default_factory=list)
    choices: dict[str, str] = field(default_factory=dict)  # type -> first line of its docstring
    choice_key: str = "type"  # what chooses among the choices: type, kind (inputs), device (an image section)


# ---------------------------------------------------------------------------------------------- types
def _is_model(t: Any) -> bool:
    return isinstance(t, type) and issubclass(t, BaseModel)


def _strip(t: Any) -> Any:
    """``Annotated[X, ...]`` -> X."""
    while typing.get_origin(t) is typing.Annotated:
        t = typing.get_args(t)[0]
    return t


def type_name(t: Any) -> str:
    """A readable type: ``number``, ``integer``, ``text``, ``true/false``, ``list of number``, a model's
    name, ``one of 'a', 'b'``, alternatives with ``or``."""
    t = _strip(t)
    origin = typing.get_origin(t)
    if t is type(None):
        return "null"
    if t is float:
        return "number"
    if t is int:
        return "integer"
    if t is str:
        return "text"
    if t is bool:
        return "true/false"
    if t is Any:
        return "any"
    if origin is Literal:
        return "one of " + ", ".join(repr(a) for a in typing.get_args(t))
    if origin in (Union, types.UnionType):
        parts = [type_name(a) for a in typing.get_args(t) if a is not type(None)]
        optional = type(None) in typing.get_args(t)
        return " or ".join(dict.fromkeys(parts)) + (" (or null)" if optional else "")
    if origin in (list, tuple):
        args = [a for a in typing.get_args(t) if a is not Ellipsis]
        if origin is tuple and len(args) > 1 and len(set(map(str, args))) == 1:
            return f"list of {len(args)} {type_name(args[0])}"
        return "list of " + (type_name(args[0]) if args else "any")
    if origin is dict:
        k, v = typing.get_args(t) or (str, Any)
        return f"mapping of {type_name(k)} to {type_name(v)}"
    if _is_model(t):
        return f"section ({t.__name__})"
    return getattr(t, "__name__", str(t))


def _models_in(t: Any) -> list[type[BaseModel]]:
    """The schemas a field's type holds (through Optional, list, dict values, unions)."""
    t = _strip(t)
    if _is_model(t):
        return [t]
    out = []
    for a in typing.get_args(t):
        out += _models_in(a)
    return out


def variants(models: list[type[BaseModel]]) -> tuple[str, dict[str, type[BaseModel]]] | None:
    """The schemas of a union chosen by a key (``device`` of an image section, ``kind`` of a signal):
    ``(key, {value: schema})``, or None when the union has no such key."""
    if len(models) < 2:
        return None
    for key in models[0].model_fields:
        values = {}
        for m in models:
            info = m.model_fields.get(key)
            lit = _strip(info.annotation) if info is not None else None
            if lit is None or typing.get_origin(lit) is not Literal or len(typing.get_args(lit)) != 1:
                break
            values[str(typing.get_args(lit)[0])] = m
        else:
            if len(values) == len(models):
                return (models[0].model_fields[key].alias or key), values
    return None


def _variants_section(path: str, models: list[type[BaseModel]]) -> SectionDoc:
    key, values = variants(models)  # type: ignore[misc]
    return SectionDoc(path=path, doc=f"One of the sections below, chosen by `{key}` (`needle explain {path}.<{key}>`).",
                      choices={v: _first_paragraph(m) for v, m in values.items()}, choice_key=key)


def _constraints(info: FieldInfo) -> str:
    words = {"ge": ">=", "gt": ">", "le": "<=", "lt": "<", "min_length": "at least {} entries",
             "max_length": "at most {} entries", "pattern": "matching {}"}
    parts = []
    for m in list(info.metadata) + [_strip(info.annotation)]:
        for k, sym in words.items():
            v = getattr(m, k, None)
            if v is not None and not callable(v):
                if k in ("min_length", "max_length") and _strip(info.annotation) is str:
                    sym = sym.replace("entries", "characters")
                parts.append(sym.format(v) if "{}" in sym else f"{sym} {v:g}" if isinstance(v, (int, float)) else f"{sym} {v}")
    for a in typing.get_args(info.annotation) if typing.get_origin(info.annotation) is typing.Annotated else ():
        for k, sym in words.items():
            v = getattr(a, k, None)
            if v is not None and not callable(v) and "{}" not in sym:
                parts.append(f"{sym} {v:g}" if isinstance(v, (int, float)) else f"{sym} {v}")
    return ", ".join(dict.fromkeys(parts))


def _default(info: FieldInfo) -> str:
    if info.default is not PydanticUndefined:
        return "null" if info.default is None else repr(info.default)
    if info.default_factory is not None:
        try:
            v = info.default_factory()
        except TypeError:
            return "(computed)"
        return repr(v.model_dump(by_alias=True)) if isinstance(v, BaseModel) else repr(v)
    return "required"


def _first_paragraph(obj: Any) -> str:
    doc = (getattr(obj, "__doc__", None) or "").strip()
    return " ".join(doc.split("\n\n")[0].split()) if doc else ""


def describe_model(m: type[BaseModel], path: str) -> SectionDoc:
    """Every field of a schema."""
    sec = SectionDoc(path=path, doc=_first_paragraph(m) if m.__doc__ != BaseModel.__doc__ else "")
    for name, info in m.model_fields.items():
        ann = info.annotation
        lit = _strip(ann)
        allowed = ""
        if typing.get_origin(lit) is Literal:
            allowed = ", ".join(repr(a) for a in typing.get_args(lit))
        nested = _models_in(ann)
        sec.fields.append(FieldDoc(
            name=info.alias or name, type=type_name(ann), default=_default(info),
            description=" ".join((info.description or "").split()), allowed=allowed, constraints=_constraints(info),
            nested=nested[0] if len(nested) == 1 else (nested or None),
        ))
    return sec


# ---------------------------------------------------------------------------------------------- paths
def _component_schemas(section: str) -> dict[str, type[BaseModel]]:
    """type -> settings schema of every registered component of a section (model: its ``model:`` spec)."""
    from needlecli.control import CONTROLLERS
    from needlecli.experiments.config.schema import _model_spec
    from needlecli.models import MODELS
    from needlecli.observers import OBSERVERS
    from needlecli.sensors import SENSORS

    reg = {"model": MODELS, "sensors": SENSORS, "observers": OBSERVERS, "control": CONTROLLERS}[section]
    out = {}
    for name, cls in reg.loaded().items():
        out[name] = _model_spec(name, cls) if section == "model" else cls.Settings
    return out


def _choices(section: str) -> dict[str, str]:
    from needlecli.control import CONTROLLERS
    from needlecli.models import MODELS
    from needlecli.observers import OBSERVERS
    from needlecli.sensors import SENSORS

    reg = {"model": MODELS, "sensors": SENSORS, "observers": OBSERVERS, "control": CONTROLLERS}[section]
    return {n: _first_paragraph(c) for n, c in reg.loaded().items()}


def _signal_kinds() -> dict[str, type[BaseModel]]:
    from needlecli.experiments.config import schedule

    out = {}
    for m in _models_in(schedule.Signal):
        kind = m.model_fields["kind"].annotation
        out[typing.get_args(kind)[0]] = m
    return out


def mapping_schema() -> type[BaseModel]:
    """The schema of the CSV mapping (``needle log import-csv``)."""
    from needlecli.io.csv_import import Mapping

    return Mapping


def explain(path: str | None = None) -> SectionDoc:
    """The reference of the config at ``path`` (module docstring), or of the CSV mapping for a path that
    starts with ``mapping``. Raises ConfigError for a path that names nothing (with what is there)."""
    from needlecli.experiments.config.schema import experiment_schema

    parts = path.split(".") if path else []
    if parts[:1] == [MAPPING]:
        if len(parts) == 1:
            sec = describe_model(mapping_schema(), MAPPING)
            sec.doc = MAPPING_DOC
            return sec
        return _walk(mapping_schema(), parts, [MAPPING], 1, sections=False)
    root = experiment_schema()
    if not path:
        sec = describe_model(root, "")
        for f in sec.fields:  # a component section: the types it may name, not their schemas' class names
            if f.name in COMPONENT_SECTIONS:
                kinds = ", ".join(_choices(f.name))
                f.type = (f"a section chosen by type ({kinds})" if f.name == "model"
                          else f"list of entries, each chosen by type ({kinds})")
            elif f.name == "inputs":
                f.type = f"mapping of input name to a number, a list or a signal ({', '.join(_signal_kinds())})"
        sec.doc = ("An experiment config: YAML, validated in full before any work (unknown keys are errors). "
                   "Units: mm, rad, s (the magnetic models: m). `needle explain <section>` for any section below; "
                   "`needle explain mapping` for the CSV mapping of `needle log import-csv`.")
        return sec
    return _walk(root, parts, [], 0, sections=True)


def _walk(root: type[BaseModel], parts: list[str], where: list[str], i: int, sections: bool) -> SectionDoc:
    """The section or key ``parts[i:]`` below ``root`` (reached by ``where``); ``sections``: the
    config's top level, whose component sections and inputs choose their schema by type or kind."""
    cur: Any = root
    while i < len(parts):
        p = parts[i]
        where.append(p)
        if sections and not where[:-1] and p in COMPONENT_SECTIONS:
            schemas = _component_schemas(p)
            if i + 1 == len(parts):  # the section: the keys every entry has, and the types it may name
                sec = _section_of(p, schemas)
                return sec
            t = parts[i + 1]
            if t not in schemas:
                what = {"model": "model", "sensors": "sensor", "observers": "observer", "control": "controller"}[p]
                raise ConfigError("needle explain", tuple(where), f"no {what} type {t!r}; known: {', '.join(sorted(schemas))}"
                                  + did_you_mean(t, schemas))
            cur = schemas[t]
            where.append(t)
            i += 2
            continue
        if sections and where == ["inputs"] and cur is root:
            kinds = _signal_kinds()
            if i + 1 == len(parts):
                sec = SectionDoc(path="inputs", doc="One entry per model input (`inputs.<name>`): a number or list "
                                 "(a constant), or a signal of one of the kinds below (`kind:`).",
                                 choices={k: _first_paragraph(m) for k, m in kinds.items()}, choice_key="kind")
                return sec
            cur = _pick(kinds, parts[i + 1], where, "input kind", "kinds")
            i += 2
            continue
        fields = {(info.alias or n): info for n, info in cur.model_fields.items()}
        if p not in fields:
            raise ConfigError("needle explain", tuple(where), f"no key {p!r} here; keys: {', '.join(fields)}"
                              + did_you_mean(p, fields))
        nested = _models_in(fields[p].annotation)
        if not nested:
            sec = describe_model(cur, ".".join(where[:-1]))
            sec.fields = [f for f in sec.fields if f.name == p]
            return sec
        chosen = variants(nested)
        if chosen is not None:  # a union chosen by a key: name the variant next (sensors.position.image.us3d)
            key, by_value = chosen
            if i + 1 == len(parts):
                return _variants_section(".".join(where), nested)
            cur = _pick(by_value, parts[i + 1], where, key, key)
            i += 2
            continue
        cur = nested[0]
        i += 1
    return describe_model(cur, ".".join(where))


def _pick(by_value: dict, v: str, where: list[str], what: str, plural: str):
    """The schema named ``v`` among ``by_value`` (added to the path ``where``), or an error listing them."""
    if v not in by_value:
        raise ConfigError("needle explain", tuple(where), f"no {what} {v!r}; {plural}: {', '.join(by_value)}"
                          + did_you_mean(v, by_value))
    where.append(v)
    return by_value[v]


def _section_of(section: str, schemas: dict[str, type[BaseModel]]) -> SectionDoc:
    """A component section: the keys every type has (from the contract's base settings) and the types."""
    from needlecli.control import ControllerSettings
    from needlecli.observers import ObserverSettings
    from needlecli.sensors import SensorSettings

    base = {"sensors": SensorSettings, "observers": ObserverSettings, "control": ControllerSettings}.get(section)
    docs = {"model": "The needle model (`type`) and its parameters; `needle explain model.<type>` for one.",
            "sensors": "Emulated hardware, a list; every entry has the keys below, and those of its `type` "
                       "(`needle explain sensors.<type>`).",
            "observers": "State estimators, a list; every entry has the keys below, and those of its `type` "
                         "(`needle explain observers.<type>`).",
            "control": "Controllers closing a loop through a sensor, a list (`needle explain control.<type>`)."}
    sec = describe_model(base, section) if base is not None else SectionDoc(path=section, doc="")
    sec.doc = docs[section]
    sec.choices = _choices(section)
    return sec


# ---------------------------------------------------------------------------------------------- output
def as_text(sec: SectionDoc, width: int = 100) -> str:
    import textwrap

    out = [f"{sec.path or 'config'}: {sec.doc}" if sec.doc else (sec.path or "config")]
    for f in sec.fields:
        head = f"  {f.name}: {f.type}" + (f"  [default {f.default}]" if f.default != "required" else "  [required]")
        out.append(head)
        extra = "; ".join(x for x in (f.constraints,) if x)
        body = f.description + (f" ({extra})" if extra else "")
        if body:
            out.append(textwrap.fill(body, width, initial_indent="      ", subsequent_indent="      "))
    if sec.choices:
        out.append(f"  {sec.choice_key}s:")
        for k, v in sec.choices.items():
            out.append(textwrap.fill(f"{k}: {v}", width, initial_indent="    ", subsequent_indent="      "))
    return "\n".join(out)


def _md_text(s: str) -> str:
    """Markdown text: angle brackets outside `code` escaped (results/<name>.h5 is no HTML tag)."""
    parts = s.split("`")
    return "`".join(p.replace("<", "&lt;").replace(">", "&gt;") if i % 2 == 0 else p for i, p in enumerate(parts))


def _md_cell(s: str) -> str:
    return _md_text(s.replace("|", "\\|").replace("\n", " "))


def as_markdown(sec: SectionDoc, level: int = 2) -> str:
    title = f"`{sec.path}`" if sec.path else "The config"
    out = [f"{'#' * level} {title}", ""]
    if sec.doc:
        out += [_md_text(sec.doc), ""]
    if sec.fields:
        out += ["| key | type | default | description |", "| --- | --- | --- | --- |"]
        for f in sec.fields:
            desc = f.description + (f" ({f.constraints})" if f.constraints else "")
            out.append(f"| `{f.name}` | {_md_cell(f.type)} | `{_md_cell(f.default)}` | {_md_cell(desc)} |")
        out.append("")
    if sec.choices:
        out += [f"| {sec.choice_key} | what it is |", "| --- | --- |"]
        out += [f"| `{k}` | {_md_cell(v)} |" for k, v in sec.choices.items()]
        out.append("")
    return "\n".join(out)


def reference_pages() -> dict[str, str]:
    """The whole reference as Markdown pages (``--format md``): the top level and every section, every
    component type of every section, every input kind, and every nested section below them."""
    pages: dict[str, str] = {}
    top = explain(None)
    body = [as_markdown(top, 1)]
    seen: set[str] = set()

    def walk(sec: SectionDoc, level: int, into: list[str]) -> None:
        _walk_nested(sec, level, into, seen)

    for f in top.fields:
        if f.name in COMPONENT_SECTIONS:
            parts = [as_markdown(explain(f.name), 1)]
            for t in explain(f.name).choices:
                sec = explain(f"{f.name}.{t}")
                parts.append(as_markdown(sec, 2))
                walk(sec, 3, parts)
            pages[f.name] = "\n".join(parts)
        elif f.name == "inputs":
            parts = [as_markdown(explain("inputs"), 1)]
            for k in explain("inputs").choices:
                sec = explain(f"inputs.{k}")
                parts.append(as_markdown(sec, 2))
                walk(sec, 3, parts)
            pages["inputs"] = "\n".join(parts)
        elif f.nested is not None:
            sec = explain(f.name)
            parts = [as_markdown(sec, 1)]
            walk(sec, 2, parts)
            pages[f.name] = "\n".join(parts)
    pages["index"] = "\n".join(body)
    return pages


def _walk_nested(sec: SectionDoc, level: int, into: list[str], seen: set[str]) -> None:
    """Append the Markdown of every section nested below ``sec``'s keys to ``into``, depth first (each
    path once: ``seen``)."""
    for f in sec.fields:
        models = f.nested if isinstance(f.nested, list) else ([f.nested] if f.nested is not None else [])
        base = f"{sec.path}.{f.name}" if sec.path else f.name
        chosen = variants(models)
        if chosen is not None and base not in seen:  # the variants' list, then each variant
            seen.add(base)
            into.append(as_markdown(_variants_section(base, models), level))
        names = chosen[1] if chosen is not None else {}
        by_model = {id(m): v for v, m in names.items()}
        for m in models:
            p = base
            if len(models) > 1:
                p += f".{by_model[id(m)]}" if id(m) in by_model else f" ({m.__name__})"
            if p in seen:
                continue
            seen.add(p)
            sub = describe_model(m, p)
            into.append(as_markdown(sub, level))
            _walk_nested(sub, min(level + 1, 6), into, seen)


def mapping_page() -> str:
    """The CSV mapping's reference as one Markdown page: its keys, then every section below them
    (``needle explain mapping --format md`` prints the first part; ``--out`` writes it as ``mapping.md``)."""
    top = explain(MAPPING)
    parts = [as_markdown(top, 1)]
    _walk_nested(top, 2, parts, set())
    return "\n".join(parts)


def undocumented() -> list[str]:
    """Every key of the whole schema (all sections, all component types, all nested sections) that has
    no description: the test of the reference keeps this empty."""
    missing: list[str] = []
    seen: set[int] = set()

    def check(m: type[BaseModel], path: str) -> None:
        if id(m) in seen:
            return
        seen.add(id(m))
        for name, info in m.model_fields.items():
            key = f"{path}.{info.alias or name}" if path else (info.alias or name)
            if name == "type" and path.split(".")[0] in COMPONENT_SECTIONS:
                continue  # the discriminator: documented by the type's own description
            if name == "kind" and path.startswith("inputs"):
                continue
            if not (info.description or "").strip():
                missing.append(key)
            for sub in _models_in(info.annotation):
                check(sub, key)

    from needlecli.experiments.config.schema import experiment_schema

    root = experiment_schema()
    for name, info in root.model_fields.items():
        if not (info.description or "").strip():
            missing.append(name)
        if name in COMPONENT_SECTIONS:
            for t, m in _component_schemas(name).items():
                check(m, f"{name}.{t}")
        elif name == "inputs":
            for k, m in _signal_kinds().items():
                check(m, f"inputs.{k}")
        else:
            for sub in _models_in(info.annotation):
                check(sub, name)
    return missing
