"""The schema of an experiment config, assembled from the registries: a newly registered model, sensor,
observer or controller brings its own settings schema with it. Only the components a config names are
imported (:func:`used_types`); :func:`experiment_schema` without arguments is the whole schema.

Every section of the config that is not a component's settings is defined here.
"""

from __future__ import annotations

import functools
from typing import Annotated, Any, Literal, Union

from pydantic import Field, ValidationError, create_model, field_validator, model_validator

from needlecli.control import CONTROLLERS
from needlecli.errors import did_you_mean
from needlecli.experiments.schedule import Signal, as_signal
from needlecli.fitting.settings import FitSettings
from needlecli.models import MODELS, Model
from needlecli.observers import OBSERVERS
from needlecli.registry import Registry
from needlecli.reports import TABLES
from needlecli.schema import MAX_SEED, NAME_PATTERN, NonNeg, Positive, Strict, error_message
from needlecli.sensors import SENSORS


class TissueLayer(Strict):
    depth: NonNeg = Field(description="depth at which the layer starts (model length unit)")
    curvature: NonNeg = Field(description="value of the model's curvature parameter in this layer")


class Tissue(Strict):
    """Layers along the insertion; the model's curvature parameter follows the layer of the tip."""

    layers: list[TissueLayer] = Field(min_length=1, description="the layers in order of depth, the first at depth 0, "
                                                              "each with the curvature parameter's value in it")

    @field_validator("layers")
    @classmethod
    def _ordered(cls, v):
        if v[0].depth != 0:
            raise ValueError("the first layer must start at depth 0")
        if any(b.depth <= a.depth for a, b in zip(v, v[1:])):
            raise ValueError("layer depths must increase strictly")
        return v


class ProcessNoise(Strict):
    """Process noise added to the truth after each step: std per state in unit/sqrt(s) (scaled by
    sqrt(dt), so results do not depend on the step). Off unless given."""

    std: dict[str, NonNeg] = Field(default_factory=dict, description="std per state, unit/sqrt(s) (the state's "
                                                              "unit per square-root second, by state name)")


class CommonStartSettings(Strict):
    """Observers that start from another's initial estimate (its own draw, made once): common random
    numbers for the start, as ``needle compare`` does for every observer."""

    observer: str = Field(description="the observer whose initial estimate (mean of every run and covariance) is shared")
    observers: list[str] = Field(min_length=1, description="the observers that start from it instead of their own init")


class Runs(Strict):
    count: int = Field(1, ge=1, le=1_000_000, description="number of Monte-Carlo runs")
    seed: int = Field(0, ge=0, le=MAX_SEED, description="seed of every random stream of the experiment (stored "
                      "in the results file as a 64-bit integer)")
    common_start: CommonStartSettings | None = Field(
        None, description="observers that start from the same initial estimate as another (default: each its own)")


class Stop(Strict):
    """When an insertion ends: at a final depth or after a duration (exactly one)."""

    depth: Positive | None = Field(None, description="final inserted length, model length unit")
    time: Positive | None = Field(None, description="duration, s")

    @model_validator(mode="after")
    def _one(self):
        if (self.depth is None) == (self.time is None):
            raise ValueError("give exactly one of depth, time")
        return self


class PolynomialReference(Strict):
    """Seed 000's reference where nothing better was recorded: polynomials in the inserted depth fitted
    to a position sensor's samples; x, y from the fits, beta = asin(dx/ds) and alpha = asin(-dy/ds / cos
    beta) from their slopes (s the depth, an arc length)."""

    kind: Literal["polynomial"] = Field(description="the reference: polynomial (fits in the depth), the only kind")
    sensor: str = Field(description="position sensor whose x (and y) samples are fitted")
    degree: int = Field(3, ge=1, le=12, description="degree of the polynomials in the depth (seed 000: 5)")


class Source(Strict):
    """Take the insertions from recorded logs instead of simulating them (paths relative to the config
    file). Inputs, sensor streams and (where recorded) the truth come from the logs."""

    logs: list[str] = Field(min_length=1, description="log files (needlecli-log HDF5), paths relative to the config "
                                                  "file; their trials become the runs")
    trials: list[str] | None = Field(None, min_length=1, description="trial ids to use (default: all)")
    reference: PolynomialReference | None = Field(
        None, description="what errors are computed against when the logs have no truth (default: the logs' truth)"
    )


class Simulation(Strict):
    dt: Positive = Field(0.01, le=1.0, description="integration step of the truth, s")
    kernels: Literal["auto", "numba", "numpy"] = Field(
        "auto", description="compiled kernels where a component has them (auto, numba) or the numpy reference "
                            "(numpy); the environment variable NEEDLECLI_KERNELS overrides")


class Output(Strict):
    path: str | None = Field(None, description="results file (default results/<name>.h5)")
    store_every: int = Field(1, ge=1, description="store covariances every k-th step")
    covariance: Literal["full", "diag", "none"] = Field("full", description="observer covariances kept: full (n x n), "
                                                        "diag (the variances: n per step), none (tables consistency "
                                                        "and nees_vs_depth need one)")
    compression: Literal["auto", "gzip", "none"] = Field(
        "auto", description="auto: gzip the arrays that repeat along an axis, store the others as they are; "
                            "gzip: every large array (smallest file, 10x the writing time); none")
    tables: list[str] = Field(default_factory=lambda: ["summary"], description="tables of needle evaluate")
    formats: list[Literal["md", "csv", "tex"]] = Field(default_factory=lambda: ["md", "csv", "tex"],
                                                       description="formats of the tables of needle evaluate: md "
                                                                   "(Markdown), csv, tex (LaTeX, booktabs)")

    @field_validator("tables")
    @classmethod
    def _known_tables(cls, v):
        known = TABLES.names()
        for name in v:
            if name not in known:
                raise ValueError(f"unknown table {name!r}; known: {', '.join(known)}" + did_you_mean(name, known))
        return v


class ParamCases(Strict):
    """Per-run parameter cases (a factor of the experiment design, e.g. seed 004's field strengths, each
    with its own true ``c``). Runs cycle through the input cases fastest, then through these: run ``i``
    has input case ``i mod K_in`` and parameter case ``(i div K_in) mod K_p`` (``K_in = 1`` without input
    cases), so every combination occurs once in each block of ``K_in * K_p`` runs. A case sets some of
    the model's parameters; the others keep ``params``; ``param_std`` adds its spread on top."""

    cases: list[dict[str, float]] = Field(min_length=1, description="one mapping per case of parameter name to "
                                                                  "value (the parameter's unit); unnamed parameters "
                                                                  "keep params")
    labels: list[str] | None = Field(None, description="a name per case for tables and legends (default: its values); "
                                                       "labels written name=value (duty_cycle=0.2) become design "
                                                       "factors of a log made by needle log from-results")

    @model_validator(mode="after")
    def _check(self):
        if self.labels is not None and len(self.labels) != len(self.cases):
            raise ValueError(f"labels has {len(self.labels)} entries for {len(self.cases)} cases")
        return self

    def case_labels(self) -> list[str]:
        if self.labels is not None:
            return list(self.labels)
        return [", ".join(f"{k} = {v:g}" for k, v in c.items()) or "nominal" for c in self.cases]


def _model_spec(name: str, cls: type[Model]):
    """Config schema of ``model:`` for one registered model."""

    state_names = cls.state_names

    def _states(v: dict[str, float], what: str) -> dict[str, float]:
        unknown = [k for k in v if k not in state_names]
        if unknown:
            raise ValueError(f"unknown state {unknown[0]!r} in {what}; states are {', '.join(state_names)}"
                             + did_you_mean(unknown[0], state_names))
        return v

    class Spec(Strict):
        type: Literal[name]  # type: ignore[valid-type]
        params: cls.Params = Field(default_factory=cls.Params, description="the model's parameters, lengths "  # type: ignore[name-defined]
                                   f"in {cls.length_unit} (needle explain model.{name}.params)")
        param_std: dict[str, NonNeg] = Field(default_factory=dict, description="per-run spread of params")
        initial_state: dict[str, float] = Field(default_factory=dict, description="initial true state by state name, "
                                                "in the state's unit (the others: the model's default pose)")
        initial_std: dict[str, NonNeg] = Field(default_factory=dict, description="per-run spread, truth")
        param_cases: ParamCases | None = Field(None, description="per-run parameter cases (design factor)")

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
def _schema(types: tuple[tuple[str, tuple[str, ...]], ...]) -> type[Strict]:
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

    class Base(Strict):
        name: str = Field("experiment", pattern=NAME_PATTERN, max_length=100, description="names the results file: results/<name>.h5")
        description: str = Field("", description="what the experiment is, in words")
        model: model_t = Field(description="the needle model: its type, parameters and initial state")  # type: ignore[valid-type]
        inputs: dict[str, Signal] = Field(default_factory=dict, description="one entry per model input; a number is a constant")
        tissue: Tissue | None = Field(None, description="tissue layers along the insertion (the curvature follows the tip's layer)")
        process_noise: ProcessNoise = Field(default_factory=ProcessNoise, description="process noise of the truth (off by default)")
        sensors: list[sensor_t] = Field(default_factory=list, description="emulated hardware measuring the truth")  # type: ignore[valid-type]
        observers: list[observer_t] = Field(default_factory=list, description="state estimators run on the measurements")  # type: ignore[valid-type]
        control: list[controller_t] = Field(  # type: ignore[valid-type]
            default_factory=list, description="controllers closing a loop through a sensor (needlecli.control)")
        runs: Runs = Field(default_factory=Runs, description="Monte-Carlo runs and their seed")
        stop: Stop | None = Field(None, description="when an insertion ends")
        source: Source | None = Field(None, description="recorded logs to replay instead of simulating")
        simulation: Simulation = Field(default_factory=Simulation, description="the truth's integration")
        output: Output = Field(default_factory=Output, description="what the results file keeps and which tables")
        fit: FitSettings | None = Field(None, description="how needle fit-em fits the trials (seed 004)")

        @field_validator("inputs", mode="before")
        @classmethod
        def _signals(cls, v):
            if isinstance(v, dict):
                return {k: as_signal(s) for k, s in v.items()}
            return v

    return create_model("ExperimentConfig", __base__=Base)


def experiment_schema(types: dict[str, tuple[str, ...]] | None = None) -> type[Strict]:
    """The config schema with the component types ``types`` (per section, from :func:`used_types`), or
    with every registered one (which imports them all)."""
    if types is None:
        types = {section: tuple(reg.names()) for section, reg in _sections().items()}
    return _schema(tuple(sorted((k, tuple(v)) for k, v in types.items())))
