"""The schema of an experiment config, assembled from the registries: a newly registered model, sensor,
observer or controller brings its own settings schema with it. Only the components a config names are
imported (:func:`used_types`); :func:`experiment_schema` without arguments is the whole schema.

The schema is a subclass of the config's static type,
:class:`~needlecli.experiments.config.types.ExperimentConfig`, whose component sections (``model``,
``sensors``, ``observers``, ``control``) become discriminated unions of the registered components' own
settings; the other sections are defined in :mod:`.types`.
"""

from __future__ import annotations

import functools
from typing import Annotated, Any, Literal, Union

from pydantic import Field, ValidationError, create_model, field_validator

from needlecli.control import CONTROLLERS
from needlecli.errors import did_you_mean
from needlecli.experiments.config.types import ExperimentConfig, ModelSpec
from needlecli.models import MODELS, Model
from needlecli.observers import OBSERVERS
from needlecli.registry import Registry
from needlecli.schema import error_message
from needlecli.sensors import SENSORS


def _model_spec(name: str, cls: type[Model]):
    """Config schema of ``model:`` for one registered model."""

    state_names = cls.state_names

    def _states(v: dict[str, float], what: str) -> dict[str, float]:
        unknown = [k for k in v if k not in state_names]
        if unknown:
            raise ValueError(f"unknown state {unknown[0]!r} in {what}; states are {', '.join(state_names)}"
                             + did_you_mean(unknown[0], state_names))
        return v

    class Spec(ModelSpec):
        type: Literal[name]  # type: ignore[valid-type]
        params: cls.Params = Field(default_factory=cls.Params, description="the model's parameters, lengths "  # type: ignore[name-defined]
                                   f"in {cls.length_unit} (needle explain model.{name}.params)")

        @field_validator("param_cases")
        @classmethod
        def _pc(cls_, v):
            if v is None:
                return v
            known = list(cls.Params.model_fields)
            for i, case in enumerate(v.cases):
                for k in case:
                    if k not in known:
                        raise ValueError(f"case {i}: unknown parameter {k!r}; parameters are {', '.join(known) or 'none'}"
                                         + did_you_mean(k, known))
                try:
                    cls.Params(**case)
                except ValidationError as e:
                    err = e.errors()[0]
                    where = ".".join(str(p) for p in err["loc"])
                    raise ValueError(f"case {i}: {where}: {error_message(err)}") from None
            return v

        @field_validator("initial_state")
        @classmethod
        def _x0(cls_, v):
            _states(v, "initial_state")
            for k, (lo, hi) in getattr(cls, "state_bounds", {}).items():
                if k in v and not lo < v[k] < hi:
                    raise ValueError(f"{k} = {v[k]} is outside ({lo:.6g}, {hi:.6g})")
            return v

        @field_validator("initial_std")
        @classmethod
        def _sx0(cls_, v):
            return _states(v, "initial_std")

        @field_validator("param_std")
        @classmethod
        def _sp(cls_, v):
            known = list(cls.Params.model_fields)
            for k in v:
                if k not in known:
                    raise ValueError(f"unknown parameter {k!r}; parameters are {', '.join(known) or 'none'}"
                                     + did_you_mean(k, known))
            return v

    Spec.__name__ = f"Model_{name}"
    return Spec


#: the sections whose entries choose a registered component by ``type``, and their registries
def _sections() -> dict[str, Registry]:
    return {"model": MODELS, "sensors": SENSORS, "observers": OBSERVERS, "control": CONTROLLERS}


def used_types(data: dict) -> dict[str, tuple[str, ...]]:
    """The registered types a parsed config names, per section (``{"observers": ("ukf",), ...}``); a
    section with an entry that names no known type gets every type, so that the schema explains it."""
    out = {}
    for section, reg in _sections().items():
        entries = data.get(section) if isinstance(data, dict) else None
        entries = [entries] if section == "model" else entries
        if not isinstance(entries, list):
            out[section] = tuple(reg.names())
            continue
        named = [e.get("type") if isinstance(e, dict) else None for e in entries]
        known = [t for t in named if isinstance(t, str) and t in reg]
        out[section] = tuple(sorted(set(known))) if known else tuple(reg.names())
    return out


def all_tags() -> dict[str, str]:
    """Every type name a section may use, as pydantic lists expected tags (``'a', 'b'``)."""
    return {section: ", ".join(repr(n) for n in reg.names()) for section, reg in _sections().items()}


@functools.cache
def _schema(types: tuple[tuple[str, tuple[str, ...]], ...]) -> type[ExperimentConfig]:
    chosen = dict(types)
    models = [_model_spec(n, MODELS.get(n)) for n in chosen["model"]]
    sensors = [SENSORS.get(n).Settings for n in chosen["sensors"]]
    observers = [OBSERVERS.get(n).Settings for n in chosen["observers"]]
    controllers = [CONTROLLERS.get(n).Settings for n in chosen["control"]]

    def union(items):
        return Annotated[Union[tuple(items)], Field(discriminator="type")] if items else dict

    model_t = union(models)
    sensor_t = union(sensors)
    observer_t = union(observers) if observers else Annotated[dict[str, Any], Field()]
    controller_t = union(controllers)

    def field(name: str, t):  # the base's field (default, description) with the components' own type
        info = ExperimentConfig.model_fields[name]
        kw = {"default_factory": info.default_factory} if info.default_factory is not None else {}
        return (t, Field(description=info.description, **kw))

    return create_model(
        "ExperimentConfig", __base__=ExperimentConfig,
        model=field("model", model_t),
        sensors=field("sensors", list[sensor_t]),  # type: ignore[valid-type]
        observers=field("observers", list[observer_t]),  # type: ignore[valid-type]
        control=field("control", list[controller_t]),  # type: ignore[valid-type]
    )


def experiment_schema(types: dict[str, tuple[str, ...]] | None = None) -> type[ExperimentConfig]:
    """The config schema with the component types ``types`` (per section, from :func:`used_types`), or
    with every registered one (which imports them all)."""
    if types is None:
        types = {section: tuple(reg.names()) for section, reg in _sections().items()}
    return _schema(tuple(sorted((k, tuple(v)) for k, v in types.items())))
