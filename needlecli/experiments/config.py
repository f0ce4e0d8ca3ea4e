"""The experiment config: a typed schema, validated in full before any work starts.

The schema is assembled from the registries, so a newly registered model, sensor or observer brings its
own settings schema with it. Errors are :class:`~needlecli.errors.ConfigError` naming the file and the
key path, e.g. ``configs/x.yaml: [sensors -> 0 -> rate] Input should be greater than 0``.
"""

from __future__ import annotations

import copy
import functools
from pathlib import Path
from typing import Annotated, Any, Literal, Union

import numpy as np
import yaml
from pydantic import Field, ValidationError, create_model, field_validator, model_validator

from needlecli.control import CONTROLLERS
from needlecli.errors import ConfigError
from needlecli.experiments.schedule import Signal, as_signal, signal_size
from needlecli.fitting.settings import FitSettings
from needlecli.models import MODELS, Model
from needlecli.observers import OBSERVERS
from needlecli.schema import NonNeg, Positive, Strict
from needlecli.sensors import PIPELINES, SENSORS


class TissueLayer(Strict):
    depth: NonNeg = Field(description="depth at which the layer starts (model length unit)")
    curvature: NonNeg = Field(description="value of the model's curvature parameter in this layer")


class Tissue(Strict):
    """Layers along the insertion; the model's curvature parameter follows the layer of the tip."""

    layers: list[TissueLayer] = Field(min_length=1)

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

    std: dict[str, NonNeg] = Field(default_factory=dict)


class Runs(Strict):
    count: int = Field(1, ge=1, le=1_000_000, description="number of Monte-Carlo runs")
    seed: int = Field(0, ge=0, description="seed of every random stream of the experiment")


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

    kind: Literal["polynomial"]
    sensor: str = Field(description="position sensor whose x (and y) samples are fitted")
    degree: int = Field(3, ge=1, le=12)


class Source(Strict):
    """Take the insertions from recorded logs instead of simulating them (paths relative to the config
    file). Inputs, sensor streams and (where recorded) the truth come from the logs."""

    logs: list[str] = Field(min_length=1)
    trials: list[str] | None = Field(None, description="trial ids to use (default: all)")
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
    covariance: Literal["full", "diag", "none"] = "full"
    compression: Literal["auto", "gzip", "none"] = Field(
        "auto", description="auto: gzip the arrays that repeat along an axis, store the others as they are; "
                            "gzip: every large array (smallest file, 10x the writing time); none")
    tables: list[str] = Field(default_factory=lambda: ["summary"], description="tables of needle evaluate")
    formats: list[Literal["md", "csv", "tex"]] = Field(default_factory=lambda: ["md", "csv", "tex"])


class ParamCases(Strict):
    """Per-run parameter cases (a factor of the experiment design, e.g. seed 004's field strengths, each
    with its own true ``c``). Runs cycle through the input cases fastest, then through these: run ``i``
    has input case ``i mod K_in`` and parameter case ``(i div K_in) mod K_p`` (``K_in = 1`` without input
    cases), so every combination occurs once in each block of ``K_in * K_p`` runs. A case sets some of
    the model's parameters; the others keep ``params``; ``param_std`` adds its spread on top."""

    cases: list[dict[str, float]] = Field(min_length=1)
    labels: list[str] | None = None

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
            raise ValueError(f"unknown state {unknown[0]!r} in {what}; states are {', '.join(state_names)}")
        return v

    class Spec(Strict):
        type: Literal[name]  # type: ignore[valid-type]
        params: cls.Params = Field(default_factory=cls.Params)  # type: ignore[name-defined]
        param_std: dict[str, NonNeg] = Field(default_factory=dict, description="per-run spread of params")
        initial_state: dict[str, float] = Field(default_factory=dict)
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
                        raise ValueError(f"case {i}: unknown parameter {k!r}; parameters are {', '.join(known) or 'none'}")
                try:
                    cls.Params(**case)
                except ValidationError as e:
                    err = e.errors()[0]
                    where = ".".join(str(p) for p in err["loc"])
                    raise ValueError(f"case {i}: {where}: {_message(err)}") from None
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
                    raise ValueError(f"unknown parameter {k!r}; parameters are {', '.join(known) or 'none'}")
            return v

    Spec.__name__ = f"Model_{name}"
    return Spec


@functools.cache
def _schema(registry_key: tuple) -> type[Strict]:
    models = [_model_spec(n, MODELS.get(n)) for n in MODELS.names()]
    sensors = [SENSORS.get(n).Settings for n in SENSORS.names()]
    observers = [OBSERVERS.get(n).Settings for n in OBSERVERS.names()]
    controllers = [CONTROLLERS.get(n).Settings for n in CONTROLLERS.names()]

    def union(items):
        return Annotated[Union[tuple(items)], Field(discriminator="type")] if items else dict

    model_t = union(models)
    sensor_t = union(sensors)
    observer_t = union(observers) if observers else Annotated[dict[str, Any], Field()]
    controller_t = union(controllers)

    class Base(Strict):
        name: str = Field("experiment", pattern=r"^[A-Za-z0-9_.\-]+$")
        description: str = ""
        model: model_t  # type: ignore[valid-type]
        inputs: dict[str, Signal] = Field(default_factory=dict)
        tissue: Tissue | None = None
        process_noise: ProcessNoise = Field(default_factory=ProcessNoise)
        sensors: list[sensor_t] = Field(default_factory=list)  # type: ignore[valid-type]
        observers: list[observer_t] = Field(default_factory=list)  # type: ignore[valid-type]
        control: list[controller_t] = Field(  # type: ignore[valid-type]
            default_factory=list, description="controllers closing a loop through a sensor (needlecli.control)")
        runs: Runs = Field(default_factory=Runs)
        stop: Stop | None = None
        source: Source | None = None
        simulation: Simulation = Field(default_factory=Simulation)
        output: Output = Field(default_factory=Output)
        fit: FitSettings | None = Field(None, description="how needle fit-em fits the trials (seed 004)")

        @field_validator("inputs", mode="before")
        @classmethod
        def _signals(cls, v):
            if isinstance(v, dict):
                return {k: as_signal(s) for k, s in v.items()}
            return v

    return create_model("ExperimentConfig", __base__=Base)


def experiment_schema() -> type[Strict]:
    """The current schema (rebuilt when a component is registered)."""
    key = (tuple(MODELS.names()), tuple(SENSORS.names()), tuple(OBSERVERS.names()), tuple(CONTROLLERS.names()))
    return _schema(key)


# ---------------------------------------------------------------------------------------------- loading
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
    for t, name in ((bool, "true/false"), (int, "a number"), (float, "a number"), (str, "a string"),
                    (list, "a list"), (dict, "a mapping"), (type(None), "empty (null)")):
        if isinstance(v, t):
            return f"{name} {v!r}" if isinstance(v, (str, int, float)) and not isinstance(v, bool) else name
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


def _message(err: dict) -> str:
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
    msg = msg.replace(" after validation", "")
    return " ".join(msg.split())  # one line


class _UniqueKeyLoader(yaml.SafeLoader):
    """The safe loader, but a key given twice in one mapping is an error (YAML keeps the last)."""

    def construct_mapping(self, node, deep=False):
        seen = set()
        for key_node, _ in node.value:  # the keys written in this mapping, before '<<' merges add theirs
            if key_node.tag == "tag:yaml.org,2002:merge":
                continue
            key = self.construct_object(key_node, deep=deep)
            if isinstance(key, (str, int, float, bool)) and key in seen:
                raise yaml.constructor.ConstructorError(
                    None, None, f"key {key!r} is given twice in the same mapping", key_node.start_mark
                )
            seen.add(key)
        return super().construct_mapping(node, deep=deep)


def parse_yaml(text: str, source: str) -> dict:
    try:
        data = yaml.load(text, Loader=_UniqueKeyLoader)  # noqa: S506 (a SafeLoader)
    except yaml.YAMLError as e:
        mark = getattr(e, "problem_mark", None)
        where = f"line {mark.line + 1}, column {mark.column + 1}: " if mark is not None else ""
        problem = getattr(e, "problem", None) or str(e).splitlines()[0]
        ctx, cmark = getattr(e, "context", None), getattr(e, "context_mark", None)
        if ctx and cmark is not None and mark is not None and cmark.line != mark.line:
            problem += f" ({ctx} that starts at line {cmark.line + 1})"
        what = "YAML error" if isinstance(e, yaml.constructor.ConstructorError) else "YAML syntax error"
        raise ConfigError(source, (), f"{what} at {where}{problem}") from None
    if data is None:
        raise ConfigError(source, (), "the file is empty")
    if not isinstance(data, dict):
        raise ConfigError(source, (), f"a config must be a mapping of keys, not {type(data).__name__}")
    return data


def set_dotted(data: dict, dotted: str, value: Any, source: str) -> None:
    """Apply one ``--set key.path=value`` override (list indices as numbers)."""
    parts = dotted.split(".")
    cur: Any = data
    for i, part in enumerate(parts):
        last = i == len(parts) - 1
        key: Any = int(part) if part.isdigit() and isinstance(cur, list) else part
        if isinstance(cur, list):
            if not isinstance(key, int) or key >= len(cur):
                raise ConfigError(source, tuple(parts[: i + 1]), "no such list entry to override")
        elif not isinstance(cur, dict):
            raise ConfigError(source, tuple(parts[:i]), "is not a mapping; cannot override below it")
        if last:
            cur[key] = value
        else:
            if isinstance(cur, dict) and key not in cur:
                cur[key] = {}
            cur = cur[key]


def load_config(
    path: str | Path | None = None,
    *,
    text: str | None = None,
    overrides: list[str] | None = None,
    runs: int | None = None,
    seed: int | None = None,
):
    """Read, override and validate a config. Returns ``(config, raw_text)``.

    Raises
    ------
    ConfigError
        Anything wrong with the file, with the file name and key path.
    """
    source = str(path) if path is not None else "<string>"
    if text is None:
        try:
            text = Path(path).read_text(encoding="utf-8")  # type: ignore[arg-type]
        except FileNotFoundError:
            raise ConfigError(source, (), "no such file") from None
        except (OSError, UnicodeDecodeError) as e:
            raise ConfigError(source, (), f"cannot read the file: {e}") from None
    data = parse_yaml(text, source)
    data = copy.deepcopy(data)
    for ov in overrides or []:
        if "=" not in ov:
            raise ConfigError(source, (), f"override {ov!r} is not of the form key.path=value")
        k, v = ov.split("=", 1)
        set_dotted(data, k.strip(), yaml.safe_load(v), source)
    if runs is not None:
        data.setdefault("runs", {})
        if isinstance(data["runs"], dict):
            data["runs"]["count"] = runs
    if seed is not None:
        data.setdefault("runs", {})
        if isinstance(data["runs"], dict):
            data["runs"]["seed"] = seed
    schema = experiment_schema()
    try:
        cfg = schema.model_validate(data)
    except ValidationError as e:
        errs = _pick_errors(e.errors())
        err = errs[0]
        more = f" (and {len(errs) - 1} more problem{'s' if len(errs) > 2 else ''})" if len(errs) > 1 else ""
        raise ConfigError(source, _location(err, data), _message(err) + more) from None
    check_consistency(cfg, source)
    if overrides or runs is not None or seed is not None:
        text = yaml.safe_dump(data, sort_keys=False)
    return cfg, text


def _depth_reachable(sig, depth: float) -> bool:
    """Whether an insertion-speed schedule ever reaches ``depth`` (a schedule whose last value is not
    positive must get there before its last change; else the simulation would grow without end)."""
    if getattr(sig, "kind", "") == "piecewise":
        tk = np.asarray(sig.times, dtype=float)
        vk = np.asarray(sig.values, dtype=float).reshape(len(tk), -1)[:, 0]
        if vk[-1] > 0:
            return True
        mid = 0.5 * (vk[1:] + vk[:-1]) if sig.interp == "linear" else vk[:-1]
        inner = float(np.sum(mid * np.diff(tk)))
        return vk[0] * tk[0] + inner >= depth - 1e-9
    if getattr(sig, "kind", "") == "flips":
        return sig.base > 0 or (sig.at_times is not None and len(sig.at_times) * sig.angle >= depth)
    return True


def check_consistency(cfg, source: str) -> None:
    """Checks across sections: inputs against the model, sensors and observers against the model."""
    model_cls = MODELS.get(cfg.model.type)
    model = model_cls(cfg.model.params)
    # inputs
    for name, sig in cfg.inputs.items():
        if name not in model_cls.input_names:
            raise ConfigError(
                source, ("inputs", name), f"model {cfg.model.type!r} has no input {name!r}; inputs are "
                + ", ".join(model_cls.input_names)
            )
        size = model_cls.input_sizes[name]
        if signal_size(sig) != size:
            raise ConfigError(source, ("inputs", name), f"needs {size} value(s) per sample, got {signal_size(sig)}")
        if getattr(sig, "kind", "") == "flips" and sig.at_depths is not None and name == model_cls.insertion_input:
            raise ConfigError(source, ("inputs", name), "the insertion input cannot be triggered by depth")
        if getattr(sig, "kind", "") == "cases" and name == model_cls.insertion_input:
            raise ConfigError(source, ("inputs", name), "the insertion input cannot differ between runs (cases)")
    n_cases = {len(sig.cases) for sig in cfg.inputs.values() if getattr(sig, "kind", "") == "cases"}
    if len(n_cases) > 1:
        raise ConfigError(source, ("inputs",), f"inputs given as cases must have the same number of cases, not {sorted(n_cases)}")
    if cfg.source is not None:
        for key in ("inputs", "sensors", "tissue", "stop"):
            if getattr(cfg, key):
                raise ConfigError(source, (key,), "comes from the logs when the config has a source; remove it")
        if cfg.process_noise.std:
            raise ConfigError(source, ("process_noise",), "comes from the logs when the config has a source; remove it")
        if cfg.model.param_cases is not None:
            raise ConfigError(source, ("model", "param_cases"), "describes simulated runs; a config with a source has none")
        if cfg.control:
            raise ConfigError(source, ("control",), "cannot close a loop on recorded logs (their inputs were applied "
                              "when they were recorded); remove it, or simulate the experiment instead")
    elif cfg.stop is None:
        raise ConfigError(source, ("stop",), "required key is missing (or give a source of recorded logs)")
    elif model_cls.insertion_input not in cfg.inputs:
        raise ConfigError(source, ("inputs", model_cls.insertion_input), "required key is missing (insertion speed)")
    if cfg.stop is not None and cfg.stop.depth is not None and cfg.source is None:
        v = np.asarray(cfg.inputs[model_cls.insertion_input].model_dump().get("value", 1.0), dtype=float)
        if getattr(cfg.inputs[model_cls.insertion_input], "kind", "") == "constant" and np.all(v <= 0):
            raise ConfigError(source, ("stop", "depth"), "the insertion speed is not positive: the depth is never reached")
        if not _depth_reachable(cfg.inputs[model_cls.insertion_input], cfg.stop.depth):
            raise ConfigError(source, ("stop", "depth"), "the insertion schedule ends without reaching this depth")
    # parameter cases: the curvature parameter cannot follow tissue layers and cases at once
    pc = cfg.model.param_cases
    if pc is not None and cfg.tissue is not None and any(model_cls.curvature_param in c for c in pc.cases):
        raise ConfigError(source, ("model", "param_cases"),
                          f"{model_cls.curvature_param!r} follows the tissue layers; it cannot also differ by case")
    # process noise
    for k in cfg.process_noise.std:
        if k not in model_cls.state_names:
            raise ConfigError(source, ("process_noise", "std", k), f"model {cfg.model.type!r} has no state {k!r}")
    # tissue
    if cfg.tissue is not None and model_cls.curvature_param is None:
        raise ConfigError(source, ("tissue",), f"model {cfg.model.type!r} has no curvature parameter for tissue layers")
    # sensors
    names = {}
    if cfg.source is not None:  # the logs' sensors; reading them checks the logs before any work
        from needlecli.experiments.replay import replay_sensors

        base = Path(source).parent if source != "<string>" else Path(".")
        names.update({sn.name: sn for sn in replay_sensors(cfg, base)})
        ref = cfg.source.reference
        if ref is not None and (ref.sensor not in names or names[ref.sensor].registered_name != "position"
                                or "x" not in names[ref.sensor].channel_names):
            raise ConfigError(source, ("source", "reference", "sensor"), f"needs a position sensor with x in the logs, not {ref.sensor!r}")
    for i, s in enumerate(cfg.sensors):
        try:
            sensor = SENSORS.get(s.type)(s, model)
        except ValueError as e:  # settings that contradict each other, e.g. 2 sigmas for 3 axes
            key = str(e).split()[0] if str(e) else ""
            loc = ("sensors", i) + ((key,) if key in type(s).model_fields else ())
            raise ConfigError(source, loc, str(e)) from None
        if sensor.name in names:
            raise ConfigError(source, ("sensors", i, "name"), f"sensor name {sensor.name!r} is used twice")
        names[sensor.name] = sensor
        problem = sensor.check_model()
        if problem:
            raise ConfigError(source, ("sensors", i, "type"), problem)
        try:
            pipe = PIPELINES.get(s.pipeline)
        except KeyError as e:
            raise ConfigError(source, ("sensors", i, "pipeline"), str(e.args[0])) from None
        if not pipe.accepts(s.type):
            raise ConfigError(source, ("sensors", i, "pipeline"), f"pipeline {s.pipeline!r} cannot make {s.type!r} measurements")
    # observers
    obs_names = set()
    for i, o in enumerate(cfg.observers):
        if isinstance(o, dict):  # no observer registered at all
            raise ConfigError(source, ("observers", i), "no observers are available in this version")
        cls = OBSERVERS.get(o.type)
        name = o.name or o.type
        if name in obs_names:
            raise ConfigError(source, ("observers", i, "name"), f"observer name {name!r} is used twice")
        obs_names.add(name)
        for loc, msg in cls.check(o, model, names):
            raise ConfigError(source, ("observers", i) + tuple(loc), msg)
    # control: closed loops through a sensor measured while the truth is simulated
    check_control(cfg, model, names, source)
    # the fit section (needle fit-em)
    if cfg.fit is not None:
        from needlecli.fitting.problem import check_fit

        for loc, msg in check_fit(cfg.fit, names):
            raise ConfigError(source, ("fit",) + tuple(loc), msg)


def check_control(cfg, model: Model, sensors: dict, source: str) -> None:
    """The ``control:`` entries: unique names, an existing sensor that can be measured in the loop, what
    the controller type needs (its ``check``), one controller per thing it sets, one sensor in the loop."""
    names: set[str] = set()
    acting: dict[str, int] = {}
    loop_sensor = None
    for i, c in enumerate(cfg.control):
        cls = CONTROLLERS.get(c.type)
        name = c.name or c.type
        if name in names:
            raise ConfigError(source, ("control", i, "name"), f"controller name {name!r} is used twice")
        names.add(name)
        if c.sensor not in sensors:
            known = ", ".join(sorted(sensors)) or "none"
            raise ConfigError(source, ("control", i, "sensor"), f"no sensor named {c.sensor!r}; sensors are {known}")
        for loc, msg in cls.check(c, model, sensors):
            raise ConfigError(source, ("control", i) + tuple(loc), msg)
        sensor = sensors[c.sensor]
        if not PIPELINES.get(sensor.settings.pipeline).live:
            raise ConfigError(source, ("control", i, "sensor"), f"sensor {c.sensor!r} (pipeline "
                              f"{sensor.settings.pipeline!r}) cannot be measured while the truth is simulated")
        if cls.acts_on in acting:
            raise ConfigError(source, ("control", i, "type"),
                              f"sets {cls.acts_on}, as control entry {acting[cls.acts_on]} does; one controller each")
        acting[cls.acts_on] = i
        if loop_sensor is not None and c.sensor != loop_sensor:
            raise ConfigError(source, ("control", i, "sensor"), f"every controller must read the same sensor "
                              f"(one sensor is measured in the loop), here {loop_sensor!r}")
        loop_sensor = c.sensor
