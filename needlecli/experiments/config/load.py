"""Loading an experiment config: read the YAML, apply ``--set`` overrides, validate it against the schema
(:mod:`.schema`) and check it across sections (inputs, sensors, observers and controllers against the
model), all before any work starts.

Errors are :class:`~needlecli.errors.ConfigError` naming the file and the key path, e.g.
``configs/x.yaml: [sensors -> 0 -> rate] Input should be greater than 0``.
"""

from __future__ import annotations

import copy
import logging
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import yaml
from pydantic import ValidationError

from needlecli.control import CONTROLLERS
from needlecli.errors import ConfigError, NeedleError, did_you_mean
from needlecli.experiments.config.budget import check_memory
from needlecli.experiments.config.from_fit import expand_from_fit
from needlecli.experiments.config.overrides import apply_overrides
from needlecli.experiments.config.schedule import signal_size
from needlecli.experiments.config.schema import all_tags, experiment_schema, used_types
from needlecli.experiments.config.types import CONFIG_FORMAT, Simulation
from needlecli.guard import Component
from needlecli.io.yamlfile import parse_yaml, read_text
from needlecli.models import MODELS, Model
from needlecli.observers import OBSERVERS
from needlecli.observers.base import Observer
from needlecli.registry import PluginError
from needlecli.schema import validation_error, validation_errors
from needlecli.sensors import PIPELINES, SENSORS

if TYPE_CHECKING:
    from needlecli.experiments.config.types import ExperimentConfig

log = logging.getLogger("needlecli")


def load_config(
    path: str | Path | None = None,
    *,
    text: str | None = None,
    overrides: list[str] | None = None,
    runs: int | None = None,
    seed: int | None = None,
    memory: bool = True,
) -> tuple[ExperimentConfig, str]:
    """Read, override and validate a config. Returns ``(config, raw_text)``. With ``memory`` (the
    default), an experiment that needs more memory than is available is refused too
    (:mod:`needlecli.experiments.config.budget`).

    Raises
    ------
    ConfigError
        Anything wrong with the file, with the file name and key path: the first problem
        (:func:`config_problems` gives them all).
    """
    return _load(path, text=text, overrides=overrides, runs=runs, seed=seed, memory=memory, problems=None)


def config_problems(path: str | Path, overrides: list[str] | None = None) -> list[NeedleError]:
    """Every problem of a config at once (``needle validate``): each key the schema refuses, then, when the
    schema holds, every problem across sections; the memory check only when nothing else is wrong. A
    file that cannot be read or parsed, or an override that cannot be applied, is one problem. Empty: valid."""
    return checked_config(path, overrides)[1]


def checked_config(path: str | Path, overrides: list[str] | None = None) -> tuple[ExperimentConfig | None,
                                                                                 list[NeedleError]]:
    """:func:`config_problems` with the validated config: ``(config, [])`` for a valid one (what ``needle
    validate`` analyses further), ``(None, problems)`` otherwise."""
    problems: list[NeedleError] = []
    loaded = None
    try:
        loaded = _load(path, overrides=overrides, problems=problems)
    except NeedleError as e:
        problems.append(e)
    return (loaded[0] if loaded is not None and not problems else None), problems


def _load(path, *, text=None, overrides=None, runs=None, seed=None, memory=True, problems=None):
    source = str(path) if path is not None else "<string>"
    if text is None:
        text = read_text(path)  # type: ignore[arg-type]
    data = copy.deepcopy(parse_yaml(text, source))
    changed = apply_overrides(data, overrides, source, runs=runs, seed=seed)
    upgraded = upgrade_format(data, source)
    fitted = expand_from_fit(data, source, Path(source).parent if path is not None else Path("."))
    types = used_types(data)
    try:
        schema = experiment_schema(types)
    except PluginError as e:  # a plug-in the config names cannot be loaded: say where it is named
        raise ConfigError(source, _named_at(data, e.name), str(e)) from None
    try:
        cfg = schema.model_validate(data)
    except ValidationError as e:
        if problems is None:
            raise validation_error(e, data, source, tags=all_tags(), schema=schema) from None
        problems.extend(validation_errors(e, data, source, tags=all_tags(), schema=schema))
        return None
    check_consistency(cfg, source, problems)
    if problems:
        return None
    for line in upgraded:  # said once the config holds (a bad config's one line is its error)
        log.warning("%s; write format: %d at the top of the config once it gives q per square-root second", line,
                    CONFIG_FORMAT)
    if memory:
        check_memory(cfg, source, Path(source).parent if source != "<string>" else Path("."))
    if changed or fitted or upgraded:  # the config as it ran: converted keys and from_fit's values written out,
        # what was converted and where the values came from above it
        text = "".join(f"# {line}\n" for line in upgraded + fitted) + yaml.safe_dump(data, sort_keys=False)
    return cfg, text


def upgrade_format(data: dict, source: str) -> list[str]:
    """Bring a parsed config (with its overrides) written in an older format to :data:`CONFIG_FORMAT`, in
    place: each observer converts its own keys (:meth:`Observer.upgrade_settings
    <needlecli.observers.base.Observer.upgrade_settings>`: format 1's ukf ``q`` per filter tick becomes per
    square-root second), and ``format`` is set. The format is the config's ``format:``, 1 where it has
    none. Returns one line per observer converted (the loader logs each as a warning once the config is
    valid: its numbers now mean something else than its text says); none for a config in the current
    format."""
    if not isinstance(data, dict):
        return []
    given = data.get("format", 1)
    if given == CONFIG_FORMAT or given not in (1,) or isinstance(given, bool):
        return []  # current, or not a format at all: the schema says so
    sim = data.get("simulation") if isinstance(data.get("simulation"), dict) else {}
    dt = sim.get("dt", Simulation.model_fields["dt"].default)
    lines = []
    for i, obs in enumerate(data.get("observers") or []):
        if not isinstance(obs, dict) or not isinstance(obs.get("type"), str):
            continue
        try:
            cls = OBSERVERS.get(obs["type"])
        except (KeyError, PluginError):  # named where the schema is built
            continue
        name = obs.get("name") or obs["type"]
        for line in Component.of(OBSERVERS, obs["type"], str(name)).call(
                "upgrade_settings", lambda c=cls, o=obs: [str(x) for x in c.upgrade_settings(o, config_format=given, dt=dt)]):
            lines.append(f"{source}: [observers -> {i}] {name} ({obs['type']}): {line}")
    rest = {k: v for k, v in data.items() if k != "format"}
    data.clear()
    data.update({"format": CONFIG_FORMAT, **rest})  # first, as a config writes it
    return lines


def _named_at(data: dict, type_name: str) -> tuple:
    """The key path of the first component entry of a parsed config whose ``type`` is ``type_name``."""
    if isinstance(data.get("model"), dict) and data["model"].get("type") == type_name:
        return ("model", "type")
    for section in ("sensors", "observers", "control"):
        for i, entry in enumerate(data.get(section) or []):
            if isinstance(entry, dict) and entry.get("type") == type_name:
                return (section, i, "type")
    return ()


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


def check_consistency(cfg: ExperimentConfig, source: str, problems: list | None = None) -> None:
    """Checks across sections: inputs against the model, sensors and observers against the model. The
    first problem is raised; with a ``problems`` list every problem is appended to it instead (a check
    that needs an earlier section to be right is skipped when that section is not)."""

    def report(loc: tuple, msg: str) -> None:
        err = ConfigError(source, loc, msg)
        if problems is None:
            raise err
        problems.append(err)

    model_cls = MODELS.get(cfg.model.type)
    model = model_cls(cfg.model.params)
    # inputs
    inputs_ok = True
    for name, sig in cfg.inputs.items():
        if name not in model_cls.input_names:
            report(("inputs", name), f"model {cfg.model.type!r} has no input {name!r}; inputs are "
                   + ", ".join(model_cls.input_names) + did_you_mean(name, model_cls.input_names))
            inputs_ok = False
            continue
        size = model_cls.input_sizes[name]
        if signal_size(sig) != size:
            report(("inputs", name), f"needs {size} value(s) per sample, got {signal_size(sig)}")
            inputs_ok = False
        if getattr(sig, "kind", "") == "flips" and sig.at_depths is not None and name == model_cls.insertion_input:
            report(("inputs", name), "the insertion input cannot be triggered by depth")
            inputs_ok = False
        if getattr(sig, "kind", "") == "cases" and name == model_cls.insertion_input:
            report(("inputs", name), "the insertion input cannot differ between runs (cases)")
            inputs_ok = False
    n_cases = {len(sig.cases) for sig in cfg.inputs.values() if getattr(sig, "kind", "") == "cases"}
    if len(n_cases) > 1:
        report(("inputs",), f"inputs given as cases must have the same number of cases, not {sorted(n_cases)}")
    if cfg.source is not None:
        for key in ("inputs", "sensors", "tissue", "stop"):
            if getattr(cfg, key):
                report((key,), "comes from the logs when the config has a source; remove it")
        if cfg.process_noise.std:
            report(("process_noise",), "comes from the logs when the config has a source; remove it")
        if cfg.model.param_cases is not None:
            report(("model", "param_cases"), "describes simulated runs; a config with a source has none")
        if cfg.control:
            report(("control",), "cannot close a loop on recorded logs (their inputs were applied "
                   "when they were recorded); remove it, or simulate the experiment instead")
    elif cfg.stop is None:
        report(("stop",), "required key is missing (or give a source of recorded logs)")
    elif model_cls.insertion_input not in cfg.inputs:
        report(("inputs", model_cls.insertion_input), "required key is missing (insertion speed)")
    elif cfg.stop.depth is not None and inputs_ok:
        v = np.asarray(cfg.inputs[model_cls.insertion_input].model_dump().get("value", 1.0), dtype=float)
        if getattr(cfg.inputs[model_cls.insertion_input], "kind", "") == "constant" and np.all(v <= 0):
            report(("stop", "depth"), "the insertion speed is not positive: the depth is never reached")
        elif not _depth_reachable(cfg.inputs[model_cls.insertion_input], cfg.stop.depth):
            report(("stop", "depth"), "the insertion schedule ends without reaching this depth")
    # parameter cases: the curvature parameter cannot follow tissue layers and cases at once
    pc = cfg.model.param_cases
    if pc is not None and cfg.tissue is not None and any(model_cls.curvature_param in c for c in pc.cases):
        report(("model", "param_cases"),
               f"{model_cls.curvature_param!r} follows the tissue layers; it cannot also differ by case")
    # process noise
    for k in cfg.process_noise.std:
        if k not in model_cls.state_names:
            report(("process_noise", "std", k), f"model {cfg.model.type!r} has no state {k!r}"
                   + did_you_mean(k, model_cls.state_names))
    # tissue
    if cfg.tissue is not None and model_cls.curvature_param is None:
        report(("tissue",), f"model {cfg.model.type!r} has no curvature parameter for tissue layers")
    # sensors
    names = {}
    sensors_ok = True
    if cfg.source is not None:  # the logs' sensors; reading them checks the logs before any work
        from needlecli.experiments.config.logs import replay_sensors

        base = Path(source).parent if source != "<string>" else Path(".")
        names.update({sn.name: sn for sn in replay_sensors(cfg, base)})
        ref = cfg.source.reference
        if ref is not None and (ref.sensor not in names or names[ref.sensor].registered_name != "position"
                                or "x" not in names[ref.sensor].channel_names):
            report(("source", "reference", "sensor"), f"needs a position sensor with x in the logs, not {ref.sensor!r}"
                   + did_you_mean(ref.sensor, names))
    for i, s in enumerate(cfg.sensors):
        try:
            sensor = SENSORS.get(s.type)(s, model)
        except ValueError as e:  # settings that contradict each other, e.g. 2 sigmas for 3 axes
            key = str(e).split()[0] if str(e) else ""
            loc = ("sensors", i) + ((key,) if key in type(s).model_fields else ())
            report(loc, str(e))
            sensors_ok = False
            continue
        if sensor.name in names:
            report(("sensors", i, "name"), f"sensor name {sensor.name!r} is used twice")
            sensors_ok = False
            continue
        names[sensor.name] = sensor
        problem = sensor.check_model()
        if problem:
            report(("sensors", i, "type"), problem)
        try:
            pipe = PIPELINES.get(s.pipeline)
        except KeyError as e:
            report(("sensors", i, "pipeline"), str(e.args[0]) + did_you_mean(s.pipeline, PIPELINES.names()))
            continue
        if not pipe.accepts(s.type):
            report(("sensors", i, "pipeline"), f"pipeline {s.pipeline!r} cannot make {s.type!r} measurements")
    if not sensors_ok:  # observers, controllers and the fit name sensors: not checked against a partial set
        return
    # observers
    obs_names = set()
    for i, o in enumerate(cfg.observers):
        if isinstance(o, dict):  # no observer registered at all
            report(("observers", i), "no observers are available in this version")
            continue
        cls = OBSERVERS.get(o.type)
        name = o.name or o.type
        if name in obs_names:
            report(("observers", i, "name"), f"observer name {name!r} is used twice")
        obs_names.add(name)
        for loc, msg in _checked(Component.of(OBSERVERS, o.type, name), cls.check, o, model, names):
            report(("observers", i) + loc, msg + _hint(msg, names))
    cs = cfg.runs.common_start
    if not isinstance(cs, str):  # shared, none: nothing named to check
        by_name = {o.name or o.type: o for o in cfg.observers if not isinstance(o, dict)}
        known = True
        for loc, name in [(("runs", "common_start", "observer"), cs.observer)] + [
                (("runs", "common_start", "observers", i), n) for i, n in enumerate(cs.observers or [])]:
            if name not in by_name:
                report(loc, f"no observer named {name!r}; observers: {', '.join(by_name)}" + did_you_mean(name, by_name))
                known = False
        if known:
            if OBSERVERS.get(by_name[cs.observer].type).initial_estimate.__func__ is Observer.initial_estimate.__func__:
                report(("runs", "common_start", "observer"),
                       f"observer {cs.observer!r} ({by_name[cs.observer].type}) gives no initial estimate to share")
            for i, n in enumerate(cs.observers or []):
                if not OBSERVERS.get(by_name[n].type).takes_common_start:
                    report(("runs", "common_start", "observers", i),
                           f"observer {n!r} ({by_name[n].type}) cannot start from another's estimate")
    # control: closed loops through a sensor measured while the truth is simulated
    check_control(cfg, model, names, source, report)
    # the fit section (needle fit-em)
    if cfg.fit is not None:
        from needlecli.fitting.problem import check_fit

        for loc, msg in check_fit(cfg.fit, names):
            report(("fit",) + tuple(loc), msg + _hint(msg, names))


def _checked(component: Component, check, settings, model, sensors) -> list[tuple[tuple, str]]:
    """A component's ``check(settings, model, sensors)``, guarded (:mod:`needlecli.guard`: a failure is
    one line naming it and its package): its problems as ``[(loc, message)]``."""
    return component.call("check", lambda: [(tuple(loc), str(msg)) for loc, msg in check(settings, model, sensors)])


def _hint(msg: str, sensors: dict) -> str:
    """A did-you-mean for a check's message about an unknown name: "no sensor named 'x'" (the config's
    sensors), "model 'm' has no state 'x'" or "... no parameter 'x'" (that model's states, parameters)."""
    import re

    if "did you mean" in msg:
        return ""
    hit = re.search(r"no sensor named '([^']*)'", msg)
    if hit:
        return did_you_mean(hit.group(1), sensors)
    hit = re.search(r"model '([^']*)' has no (state|parameter) '([^']*)'", msg)
    if hit and hit.group(1) in MODELS:
        m = MODELS.get(hit.group(1))
        return did_you_mean(hit.group(3), m.state_names if hit.group(2) == "state" else m.Params.model_fields)
    return ""


def check_control(cfg: ExperimentConfig, model: Model, sensors: dict, source: str, report=None) -> None:
    """The ``control:`` entries: unique names, an existing sensor that can be measured in the loop, what
    the controller type needs (its ``check``), one controller per thing it sets, one sensor in the loop.
    ``report(loc, message)`` takes each problem (default: raise the first)."""
    if report is None:
        def report(loc: tuple, msg: str) -> None:
            raise ConfigError(source, loc, msg)

    names: set[str] = set()
    acting: dict[str, int] = {}
    loop_sensor = None
    for i, c in enumerate(cfg.control):
        cls = CONTROLLERS.get(c.type)
        name = c.name or c.type
        if name in names:
            report(("control", i, "name"), f"controller name {name!r} is used twice")
        names.add(name)
        if c.sensor not in sensors:
            known = ", ".join(sorted(sensors)) or "none"
            report(("control", i, "sensor"), f"no sensor named {c.sensor!r}; sensors are {known}"
                   + did_you_mean(c.sensor, sensors))
            continue
        problems = _checked(Component.of(CONTROLLERS, c.type, name), cls.check, c, model, sensors)
        for loc, msg in problems:
            report(("control", i) + loc, msg)
        if problems:
            continue
        sensor = sensors[c.sensor]
        if not PIPELINES.get(sensor.settings.pipeline).live:
            report(("control", i, "sensor"), f"sensor {c.sensor!r} (pipeline "
                   f"{sensor.settings.pipeline!r}) cannot be measured while the truth is simulated")
        if cls.acts_on in acting:
            report(("control", i, "type"),
                   f"sets {cls.acts_on}, as control entry {acting[cls.acts_on]} does; one controller each")
        acting[cls.acts_on] = i
        if loop_sensor is not None and c.sensor != loop_sensor:
            report(("control", i, "sensor"), f"every controller must read the same sensor "
                   f"(one sensor is measured in the loop), here {loop_sensor!r}")
        loop_sensor = c.sensor
