"""The config's static type: :class:`ExperimentConfig`, what every function that takes a validated config
is given, with each section typed (an editor follows ``cfg.runs.seed`` or ``cfg.simulation.dt``).

The sections that are not a component's settings are defined here. A component's section (``model``,
``sensors``, ``observers``, ``control``) is typed by its base (:class:`ModelSpec`,
:class:`~needlecli.sensors.SensorSettings`, :class:`~needlecli.observers.ObserverSettings`,
:class:`~needlecli.control.ControllerSettings`); the schema a config is validated with
(:func:`needlecli.experiments.config.schema.experiment_schema`) is a subclass of :class:`ExperimentConfig`
whose component sections are the registered components' own settings, so every validated config is an
``ExperimentConfig`` and carries the component's own settings class in those sections.
"""

from __future__ import annotations

from typing import Any, Literal

from pydantic import BaseModel, Field, field_validator, model_validator

from needlecli.control.base import ControllerSettings
from needlecli.errors import did_you_mean
from needlecli.experiments.config.schedule import Signal, as_signal
from needlecli.fitting.settings import FitSettings
from needlecli.observers.base import ObserverSettings
from needlecli.reports import TABLES
from needlecli.schema import MAX_SEED, NAME_PATTERN, NonNeg, Positive, Strict
from needlecli.sensors.base import SensorSettings


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
    observers: list[str] | None = Field(None, min_length=1, description="the observers that start from it instead of "
                                        "their own init (default: every other observer that can)")


class Runs(Strict):
    count: int = Field(1, ge=1, le=1_000_000, description="number of Monte-Carlo runs")
    seed: int = Field(0, ge=0, le=MAX_SEED, description="seed of every random stream of the experiment (stored "
                      "in the results file as a 64-bit integer)")
    common_start: Literal["shared", "none"] | CommonStartSettings = Field(
        "shared", description="where the observers of one study start: shared (the default: every observer that can "
        "starts from the initial estimate of the first observer that gives one, its own draw made once, as needle "
        "compare does), none (each from its own init), or {observer: NAME, observers: [...]} (that observer's "
        "estimate, shared by those named; default all the others that can)")

    @field_validator("common_start", mode="before")
    @classmethod
    def _null_is_none(cls, v):
        return "none" if v is None else v


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
    """The high-gain observer paper's reference where nothing better was recorded: polynomials in the inserted depth fitted
    to a position sensor's samples; x, y from the fits, beta = asin(dx/ds) and alpha = asin(-dy/ds / cos
    beta) from their slopes (s the depth, an arc length)."""

    kind: Literal["polynomial"] = Field(description="the reference: polynomial (fits in the depth), the only kind")
    sensor: str = Field(description="position sensor whose x (and y) samples are fitted")
    degree: int = Field(3, ge=1, le=12, description="degree of the polynomials in the depth (the high-gain observer paper: 5)")


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
            if name not in TABLES:  # a current name or a former one (TABLES.aliases)
                raise ValueError(f"unknown table {name!r}; known: {', '.join(known)}" + did_you_mean(name, known))
        return v


class ParamCases(Strict):
    """Per-run parameter cases (a factor of the experiment design, e.g. the magnetic needle EM paper's field strengths, each
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


class ModelSpec(Strict):
    """``model:``: the needle model, its parameters and initial state. Each registered model has its own
    subclass, with ``type`` its name and ``params`` its :class:`~needlecli.models.Model.Params`
    (:func:`needlecli.experiments.config.schema.experiment_schema`)."""

    type: str = Field(description="the model's registered name (needle list)")
    params: BaseModel = Field(description="the model's parameters")
    param_std: dict[str, NonNeg] = Field(default_factory=dict, description="per-run spread of params")
    initial_state: dict[str, float] = Field(default_factory=dict, description="initial true state by state name, "
                                            "in the state's unit (the others: the model's default pose)")
    initial_std: dict[str, NonNeg] = Field(default_factory=dict, description="per-run spread, truth")
    param_cases: ParamCases | None = Field(None, description="per-run parameter cases (design factor)")


#: the format of the configs this version reads (a config's ``format:``): 2, process noise ``q`` per
#: square-root second in every observer. Format 1 (a config without ``format:``) gave the UKF's ``q`` per
#: filter tick; :func:`needlecli.experiments.config.load.load_config` converts such a config on loading.
CONFIG_FORMAT = 2


class ExperimentConfig(Strict):
    """A validated experiment config (the static type of every ``cfg``)."""

    format: Literal[1, 2] = Field(
        CONFIG_FORMAT, description="the config's format: 2, the current (q of every observer per square-root "
        "second). A file without format: is read as format 1, whose unscented filter's q was per filter tick, "
        "and converted on loading to 2, with one note per observer converted (the results file keeps the converted config)")
    name: str = Field("experiment", pattern=NAME_PATTERN, max_length=100, description="names the results file: results/<name>.h5")
    description: str = Field("", description="what the experiment is, in words")
    model: ModelSpec = Field(description="the needle model: its type, parameters and initial state")
    inputs: dict[str, Signal] = Field(default_factory=dict, description="one entry per model input; a number is a constant")
    tissue: Tissue | None = Field(None, description="tissue layers along the insertion (the curvature follows the tip's layer)")
    process_noise: ProcessNoise = Field(default_factory=ProcessNoise, description="process noise of the truth (off by default)")
    sensors: list[SensorSettings] = Field(default_factory=list, description="emulated hardware measuring the truth")
    observers: list[ObserverSettings] = Field(default_factory=list, description="state estimators run on the measurements")
    control: list[ControllerSettings] = Field(
        default_factory=list, description="controllers closing a loop through a sensor (needlecli.control)")
    runs: Runs = Field(default_factory=Runs, description="Monte-Carlo runs and their seed")
    stop: Stop | None = Field(None, description="when an insertion ends")
    source: Source | None = Field(None, description="recorded logs to replay instead of simulating")
    simulation: Simulation = Field(default_factory=Simulation, description="the truth's integration")
    output: Output = Field(default_factory=Output, description="what the results file keeps and which tables")
    fit: FitSettings | None = Field(None, description="how needle fit-em fits the trials (the magnetic needle EM paper)")

    @field_validator("inputs", mode="before")
    @classmethod
    def _signals(cls, v: Any) -> Any:
        if isinstance(v, dict):
            return {k: as_signal(s) for k, s in v.items()}
        return v
