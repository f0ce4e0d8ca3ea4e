"""Planning a sweep: every cell's overrides, seed, config (validated), hash, id and results path, all
made before anything runs.

Seeds (``runs.seed`` of a cell). A sweep compares parameters, not luck: by default every cell draws the
same random numbers, and replicates are an explicit axis of seeds.

* a cell whose overrides set ``runs.seed`` (an axis ``runs.seed: range(10)``, a cell entry or ``fixed``)
  keeps it as given: with a seed axis, every combination of the other parameters runs on the same seeds,
  and the table and plot summarise over them (mean, std across seeds);
* otherwise, with ``seeds: common`` (the default), the cell uses the sweep seed: the grid's ``seed``,
  default the config's ``runs.seed`` (common random numbers: every cell sees the same insertions and the
  same noise draws of each component, so the differences between cells come from the overrides alone);
* with ``seeds: derived`` (asked for explicitly) ``seed = int(sha256("<sweep seed>:<overrides>")[:8],
  16) mod 2**31``, where ``<overrides>`` is the cell's varying overrides (not ``fixed``) as JSON with sorted
  keys: the cells draw different noise (their differences include luck), and the same cell gets the same
  seed in every sweep.

A cell's id is the first 10 hex digits of the sha256 of its overrides (with the seed) as JSON with sorted
keys. Its ``text_hash`` is the sha256 of the overridden config the same way (what its results file
holds); its ``config_hash``, what ``--resume`` and ``--collect`` compare, the sha256 of the *resolved*
config (every default filled in, as the code that runs it reads it) together with the needlecli version
and git commit that planned it (:func:`resume_key`): a cell computed before a default changed, or by
another needlecli, is not complete.
"""

from __future__ import annotations

import copy
import hashlib
import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import yaml

from needlecli.errors import ConfigError, NeedleError, SweepError
from needlecli.experiments.studies.sweep.describe import describe_key
from needlecli.experiments.studies.sweep.grid import Grid, grid_overrides
from needlecli.reports.sweep import SEED_KEY, format_value

if TYPE_CHECKING:
    from needlecli.experiments.config.types import ExperimentConfig


def _canonical(obj: Any) -> str:
    return json.dumps(obj, sort_keys=True, default=str, separators=(",", ":"))


def config_hash(data: dict) -> str:
    """sha256 of a config's data (after overrides) as JSON with sorted keys."""
    return hashlib.sha256(_canonical(data).encode()).hexdigest()


def resume_key(cfg: ExperimentConfig, ident: dict[str, str]) -> str:
    """sha256 of the resolved config ``cfg`` (every default included) and ``ident``, the needlecli version
    and git commit (:func:`needlecli.provenance.identity`), as JSON with sorted keys."""
    return config_hash({"config": cfg.model_dump(mode="json"), "needlecli": dict(ident)})


def derived_seed(sweep_seed: int, overrides: dict) -> int:
    """The seed of a cell that does not set runs.seed: ``int(sha256("<sweep seed>:<overrides JSON>")[:8],
    16) mod 2**31``."""
    h = hashlib.sha256(f"{sweep_seed}:{_canonical(overrides)}".encode()).hexdigest()
    return int(h[:8], 16) % (2**31)


@dataclass(frozen=True)
class Cell:
    """One experiment of a sweep (picklable: it is what a worker receives).

    ``overrides`` are the varying overrides (grid axes, cell entry, random sample) plus ``runs.seed``;
    ``fixed`` the overrides every cell shares; ``config_text`` the complete config with both applied;
    ``text_hash`` its hash, ``config_hash`` the resume key (:func:`resume_key`) and ``planned_by`` the
    needlecli that planned it (version, git commit).
    """

    index: int
    id: str
    overrides: dict
    fixed: dict
    seed: int
    seed_from: str  # "grid" (set by the cell), "derived" or "common"
    config_source: str  # the base config file (for messages and relative paths)
    config_text: str
    config_hash: str
    observers: tuple[str, ...]
    n_runs: int
    path: str  # DIR/cells/<id>.h5 (absolute)
    base_dir: str
    #: what each override key is: {key: {name, description, unit}} (:func:`.describe.describe_key`)
    param_info: dict = field(default_factory=dict)
    file_bytes: int = 0  # at most what its results file takes on disk (:mod:`needlecli.experiments.config.budget`)
    text_hash: str = ""
    planned_by: dict = field(default_factory=dict)

    def label(self) -> str:
        return ", ".join(f"{k} = {format_value(v)}" for k, v in self.overrides.items()) or "(no overrides)"


def _describe(cfg: ExperimentConfig, key: str) -> dict[str, str]:
    try:
        return describe_key(cfg, key)
    except Exception:  # noqa: BLE001 (a label must not stop a sweep: the key as it was given, no unit)
        return {"name": key, "description": "", "unit": ""}


def _n_runs(cfg: ExperimentConfig) -> int:
    """Runs of a cell's experiment as far as the config tells (replayed logs: the trials named, else 0)."""
    if cfg.source is None:
        return int(cfg.runs.count)
    return len(cfg.source.trials or [])



def plan_sweep(
    config: str | Path,
    grid: Grid,
    *,
    out_dir: str | Path,
    overrides: list[str] | None = None,
    grid_source: str = "grid",
) -> list[Cell]:
    """Make every cell of a sweep and validate its config (all before anything runs).

    ``overrides`` (``key=value`` strings, as ``--set``) join ``grid.fixed``. Raises :class:`SweepError`
    naming the cell, its overrides and the config key at fault.
    """
    from needlecli.experiments.config.budget import estimate
    from needlecli.experiments.config.load import load_config
    from needlecli.experiments.config.overrides import parse_override, set_dotted
    from needlecli.io.yamlfile import read_yaml
    from needlecli.provenance import identity

    ident = identity()
    config = Path(config)
    source = str(config)
    base, _ = read_yaml(config)
    fixed = dict(grid.fixed)
    for ov in overrides or []:
        k, v = parse_override(ov, source)
        fixed[k] = v
    cells_dir = Path(out_dir).resolve() / "cells"
    base_seed = (base.get("runs") or {}).get("seed", 0) if isinstance(base.get("runs"), dict) else 0
    sweep_seed = grid.seed if grid.seed is not None else int(base_seed or 0)
    cells: list[Cell] = []
    seen: dict[str, int] = {}
    all_ov = grid_overrides(grid)
    for i, varying in enumerate(all_ov):
        ov = dict(varying)
        if SEED_KEY in ov or SEED_KEY in fixed:
            seed_from = "grid"
            seed = ov.get(SEED_KEY, fixed.get(SEED_KEY))
        elif grid.seeds == "common":
            seed_from, seed = "common", sweep_seed
            ov[SEED_KEY] = seed
        else:
            seed_from, seed = "derived", derived_seed(sweep_seed, varying)
            ov[SEED_KEY] = seed
        where = f"{grid_source}: cell {i} of {len(all_ov)} ({', '.join(f'{k} = {format_value(v)}' for k, v in varying.items()) or 'no overrides'})"
        data = copy.deepcopy(base)
        try:
            for k, v in {**fixed, **ov}.items():
                set_dotted(data, k, copy.deepcopy(v), source)
            cell_text = yaml.safe_dump(data, sort_keys=False)
            cfg, cell_text = load_config(config, text=cell_text)
        except ConfigError as e:
            raise SweepError(f"{where}: {e}") from None
        except NeedleError as e:  # a replay config whose logs are bad
            raise SweepError(f"{where}: {e}") from None
        h = config_hash(yaml.safe_load(cell_text))
        key = resume_key(cfg, ident)
        cid = hashlib.sha256(_canonical(ov).encode()).hexdigest()[:10]
        if cid in seen:
            raise SweepError(f"{where}: the same overrides as cell {seen[cid]}; each cell must differ")
        seen[cid] = i
        cells.append(Cell(
            index=i, id=cid, overrides=ov, fixed=fixed, seed=int(cfg.runs.seed), seed_from=seed_from,
            config_source=str(config.resolve()), config_text=cell_text, config_hash=key, text_hash=h, planned_by=ident,
            observers=tuple(o.name or o.type for o in cfg.observers), n_runs=_n_runs(cfg),
            path=str(cells_dir / f"{cid}.h5"), base_dir=str(config.resolve().parent),
            param_info={k: _describe(cfg, k) for k in ov},
            file_bytes=estimate(cfg, config.resolve().parent).file_bytes,
        ))
    return cells

