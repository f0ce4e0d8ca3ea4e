"""What a swept key is: a readable name, a short description and its unit, from the config schema or the
model, so that tables and plots can say what their parameter axis holds.

The key is walked through the validated config (``observers.0.q.kappa``: the first observer's settings,
their ``q`` mapping, its ``kappa`` entry). The unit comes from

* the field's description in the schema, where it ends in a unit (``"sampling rate, Hz"``,
  ``"final inserted length, model length unit"``, ``"curvature noise std, 1/(model length unit)"``);
* for a mapping keyed by a model's states, parameters or inputs (``q``, ``p0``, ``init.std``,
  ``model.params``, ``param_std``, ``inputs``, ``process_noise.std``): the model's unit of that entry
  (the observer's own ``model`` where it names one), squared for a variance (``p0``) and per sqrt(s)
  where the description says ``unit/sqrt(s)``;
* for a noise std without a unit in its description: the units of the sensor's channels (the sensor of
  that name for an observer's ``measurements.<sensor>``), where they agree;
* a tissue layer's ``curvature``: the unit of the model's curvature parameter.

A key whose unit none of these tell (a count, a probability, a dimensionless gain) has ``unit`` empty.
"""

from __future__ import annotations

import re
from typing import TYPE_CHECKING, Any

from pydantic import BaseModel

from needlecli.models import MODELS

if TYPE_CHECKING:
    from needlecli.experiments.config.types import ExperimentConfig

_UNIT_WORDS = {"mm", "cm", "m", "s", "rad", "deg", "Hz", "mT", "T", "dB", "px", "grey", "level", "levels", "1", "unit"}
_PAREN = re.compile(r"\s+\(([^()]*)\)")  # a remark in brackets after a space (not the 1/(...) of a unit)
_LIST_SECTIONS = ("observers", "sensors", "control")


def _as_unit(text: str, length_unit: str) -> str | None:
    """``text`` as a unit (``model length unit`` replaced by the model's), or None if it is not one;
    ``unit`` stands for the unit of the entry a per-state field is keyed by."""
    cand = text.strip().replace("model length unit", length_unit)
    cand = re.sub(r"\((\w+)\)", r"\1", cand)  # 1/(mm) -> 1/mm
    tokens = [t for t in re.split(r"[/^*()\s]+|sqrt", cand) if t]
    return cand if tokens and all(t in _UNIT_WORDS or t.isdigit() for t in tokens) else None


def _unit_of_text(text: str, length_unit: str) -> str | None:
    """The unit a description gives: after its last comma (remarks in brackets dropped), else a remark in
    brackets that is a unit (``"depth at which the layer starts (model length unit)"``)."""
    text = text or ""
    plain = _PAREN.sub("", text).strip()
    if "," in plain:
        unit = _as_unit(plain.rsplit(",", 1)[1], length_unit)
        if unit is not None:
            return unit
    return next((u for u in (_as_unit(m, length_unit) for m in _PAREN.findall(text)) if u is not None), None)


def _description(text: str | None) -> str:
    """The description without its unit and remarks: ``"sampling rate, Hz"`` -> ``"sampling rate"``."""
    plain = _PAREN.sub("", text or "").strip()
    head, _, tail = plain.rpartition(",")
    return head.strip() if head and _as_unit(tail, "mm") is not None else plain


def _compound(unit: str) -> str:
    return f"({unit})" if re.search(r"[/ ]", unit) else unit


def _entry_unit(model_cls, name: str) -> str | None:
    """The unit of a model's state, parameter or input of this name."""
    if name in model_cls.state_names and len(model_cls.state_units) == len(model_cls.state_names):
        return model_cls.state_units[model_cls.state_names.index(name)]
    params = getattr(model_cls.Params, "model_fields", {})
    if name in params:
        return _unit_of_text(params[name].description or "", model_cls.length_unit)
    return model_cls.input_units.get(name)


def _field(obj: BaseModel, part: str) -> str | None:
    fields = type(obj).model_fields
    if part in fields:
        return part
    return next((n for n, f in fields.items() if f.alias == part), None)


def _sensor_units(cfg: ExperimentConfig, settings, model_cls) -> set[str]:
    from needlecli.sensors import SENSORS

    try:
        return set(SENSORS.get(settings.type)(settings, model_cls(cfg.model.params)).channel_units)
    except Exception:  # noqa: BLE001 (a sensor that cannot say: no unit)
        return set()


def describe_key(cfg: ExperimentConfig, key: str) -> dict[str, str]:
    """``{"name", "description", "unit"}`` of a dotted config key in a validated config ``cfg``.

    ``name`` is the key with a list entry replaced by its component's name (``observers.0.q.kappa`` ->
    ``ukf: q.kappa``); ``description`` the schema's description of the field (unit and remarks dropped);
    ``unit`` empty where neither the schema nor the model tells.
    """
    parts = key.split(".")
    mcls = MODELS.get(cfg.model.type)
    obj: Any = cfg
    component = comp_obj = field = owner = None
    entry = entry_field = None  # the mapping key walked last (a state, parameter, input or sensor name)
    walked = 0
    for i, part in enumerate(parts):
        if isinstance(obj, BaseModel):
            name = _field(obj, part)
            if name is None:
                break
            own = getattr(obj, "model", None)  # an observer's (or the fit's) own model
            if isinstance(own, str) and own in MODELS.names():
                mcls = MODELS.get(own)
            owner, field = obj, type(obj).model_fields[name]
            obj = getattr(obj, name)
        elif isinstance(obj, (list, tuple)) and part.isdigit() and int(part) < len(obj):
            obj = obj[int(part)]
            if i == 1 and parts[0] in _LIST_SECTIONS:
                comp_obj = obj
                component = getattr(obj, "name", None) or getattr(obj, "type", None) or part
        elif isinstance(obj, dict):  # an entry the config need not set yet
            entry, entry_field = part, field
            obj = obj.get(part)
        else:
            break
        walked += 1
    rest = ".".join(parts[2:]) if component is not None else ""
    name = f"{component}: {rest}" if rest else component or key
    text = field.description if field is not None else None
    if walked < len(parts) or field is None:
        return {"name": name, "description": _description(text), "unit": ""}

    unit = _unit_of_text(text or "", mcls.length_unit)
    relative = unit is not None and "unit" in re.split(r"[/^*()\s]+", unit)  # "unit/sqrt(s)": of the entry
    if unit is None or relative:
        unit = None
        base = _entry_unit(mcls, entry) if entry is not None else None
        if base is not None and entry_field is field:  # the value of a per-state / per-parameter mapping
            rule = text or type(owner).__doc__ or ""
            unit = (f"{_compound(base)}^2" if "variance" in rule else
                    f"{_compound(base)}/sqrt(s)" if "unit/sqrt(s)" in rule else base)
        elif base is not None and parts[-1] in ("value", "values"):  # inputs.v.value
            unit = base
        elif parts[-1] == "sigma":  # a noise std: the unit of the sensor's channels
            sensor = comp_obj if parts[0] == "sensors" else None
            if parts[0] == "observers" and entry is not None:
                sensor = next((s for s in cfg.sensors if (s.name or s.type) == entry), None)
            units = _sensor_units(cfg, sensor, mcls) if sensor is not None else set()
            unit = units.pop() if len(units) == 1 else None
        elif parts[0] == "tissue" and parts[-1] == "curvature" and mcls.curvature_param:
            unit = _entry_unit(mcls, mcls.curvature_param)
    return {"name": name, "description": _description(text), "unit": unit or ""}
