"""What a config's ``source:`` names: the recorded trials of its logs (read and checked once per version
of a file), their metadata as design columns, and the sensors the logs recorded. The config's checks
(:mod:`.load`, :mod:`.budget`) and the replay (:mod:`needlecli.experiments.simulation.replay`) share it.
"""

from __future__ import annotations

import functools
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from pydantic import ValidationError

from needlecli.errors import DataError
from needlecli.io.logs import Trial, design_factors, read_log
from needlecli.models import MODELS
from needlecli.sensors import SENSORS

if TYPE_CHECKING:
    from needlecli.experiments.config.types import ExperimentConfig


@functools.lru_cache(maxsize=8)
def _read_log_once(path: str, mtime_ns: int, size: int):
    """A log read and checked once per version of the file (a config's checks and its run share it)."""
    return read_log(path)


def _read_log(path: Path):
    from needlecli.io.atomic import staged_path

    try:
        st = staged_path(path).stat()  # this command's own log, not yet renamed into place: its temporary file
    except OSError:
        return read_log(path)  # says what is wrong with it
    return _read_log_once(str(path), st.st_mtime_ns, st.st_size)


def load_trials(cfg: ExperimentConfig, base_dir: Path) -> list[Trial]:
    trials: list[Trial] = []
    for p in cfg.source.logs:
        path = Path(p) if Path(p).is_absolute() else base_dir / p
        log = _read_log(path)
        for tr in log.trials:
            tr.meta.setdefault("log", str(path))
        trials.extend(log.trials)
    if cfg.source.trials is not None:
        by_id = {t.id: t for t in trials}
        missing = [t for t in cfg.source.trials if t not in by_id]
        if missing:
            raise DataError(f"{', '.join(cfg.source.logs)}: no trial {missing[0]!r}; trials: {', '.join(by_id)}")
        trials = [by_id[t] for t in cfg.source.trials]
    return trials


def trial_where(tr: Trial, what: str) -> str:
    return f"{tr.meta.get('log', '<log>')}: [trial {tr.id} -> {what}]"


#: metadata that describes how a trial was stored or imported rather than the experiment
_NOT_DESIGN = {"import_report", "config", "log", "source", "folder", "alignment", "design_factors"}


def trial_metadata(trials: list[Trial]) -> dict:
    """The trials' scalar metadata as columns ``name -> (N,)`` (numbers as floats, NaN where a trial lacks
    the key; otherwise strings, empty where missing), for grouping fits by them. Keys that say how the
    data were stored (the import report, JSON, long text) are left out. ``"design_factors"``: the keys
    any trial lists as its design factors."""
    keys: dict[str, None] = {}
    factors: dict[str, None] = {}
    for tr in trials:
        for k, v in tr.meta.items():
            if k in _NOT_DESIGN or isinstance(v, (list, dict, tuple)):
                continue
            if isinstance(v, str) and (len(v) > 120 or v[:1] in "[{"):
                continue
            keys[k] = None
        for k in design_factors(tr):
            factors[k] = None
    cols = {}
    for k in keys:
        vals = [tr.meta.get(k) for tr in trials]
        present = [v for v in vals if v is not None]
        if all(isinstance(v, (int, float, np.integer, np.floating)) and not isinstance(v, (bool, np.bool_))
               for v in present):
            cols[k] = np.array([np.nan if v is None else float(v) for v in vals])
        else:
            cols[k] = np.array(["" if v is None else str(v) for v in vals])
    return {"columns": cols, "design_factors": [k for k in factors if k in cols]}


def log_sensors(trials: list[Trial], model) -> list:
    """The sensors of the logs, from the first trial's settings; every trial must have the same ones."""
    names = list(trials[0].sensors)
    for tr in trials[1:]:
        for n in names:
            if n not in tr.sensors:
                raise DataError(f"{trial_where(tr, 'sensors')} missing channel {n!r} (trial {trials[0].id} has it)")
        for n in tr.sensors:
            if n not in names:
                raise DataError(f"{trial_where(tr, 'sensors')} channel {n!r} is in no other trial ({trials[0].id} lacks it)")
    out = []
    for name in names:
        settings = dict(trials[0].sensors[name].settings)
        settings["name"] = name
        stype = settings.get("type")
        if stype not in SENSORS:
            raise DataError(f"{trial_where(trials[0], f'sensor {name}')} unknown sensor type {stype!r}; known: {', '.join(SENSORS.names())}")
        cls = SENSORS.get(stype)
        try:
            sensor = cls(cls.Settings.model_validate(settings), model)
        except ValidationError as e:
            err = e.errors()[0]
            raise DataError(f"{trial_where(trials[0], f'sensor {name}')} settings: {'.'.join(map(str, err['loc']))}: {err['msg']}") from None
        except ValueError as e:
            raise DataError(f"{trial_where(trials[0], f'sensor {name}')} settings: {e}") from None
        problem = sensor.check_model()
        if problem:
            raise DataError(f"{trial_where(trials[0], f'sensor {name}')} {problem}")
        for tr in trials:
            st = tr.sensors[name]
            if tuple(st.names) != tuple(sensor.channel_names):
                raise DataError(f"{trial_where(tr, f'sensor {name}')} columns {list(st.names)}, expected {list(sensor.channel_names)}")
            if tuple(st.units) != tuple(sensor.channel_units):
                raise DataError(f"{trial_where(tr, f'sensor {name}')} units {list(st.units)} do not match {list(sensor.channel_units)}")
        out.append(sensor)
    return out


def replay_sensors(cfg: ExperimentConfig, base_dir: Path) -> list:
    """The sensors a replay config will have (reads and checks the logs)."""
    model = MODELS.get(cfg.model.type)(cfg.model.params)
    return log_sensors(load_trials(cfg, base_dir), model)
