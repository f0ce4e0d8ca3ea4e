"""The grid file of a sweep (``GRID.yaml``): its schema, its axes, and the varying overrides it makes.

A grid makes *cells*, each a set of dotted overrides of the config (the keys of ``needle simulate
--set``). The cells are

    (each entry of ``cells``, or one empty cell) x (each of ``random.count`` samples, or one empty
    sample) x (the cartesian product of the ``grid`` axes, the last axis varying fastest)

with ``fixed`` applied to every cell first (:func:`grid_overrides` lists the varying part). A key may be
set in one part only; a bad grid is a :class:`~needlecli.errors.ConfigError` naming the file and key.
"""

from __future__ import annotations

import copy
import itertools
import math
import re
from pathlib import Path
from typing import Any, Literal

import numpy as np
from pydantic import Field, ValidationError, field_validator, model_validator

from needlecli.schema import MAX_SEED, Strict, validation_error

MAX_CELLS = 100_000

_KEY = re.compile(r"^[A-Za-z_][A-Za-z0-9_\-]*(\.[A-Za-z0-9_\-]+)*$")
_RANGE = re.compile(r"^\s*range\(\s*(-?\d{1,18})\s*(?:,\s*(-?\d{1,18})\s*)?(?:,\s*(-?\d{1,18})\s*)?\)\s*$")


def _check_keys(mapping: dict, what: str) -> dict:
    for k in mapping:
        if not isinstance(k, str) or not _KEY.match(k):
            raise ValueError(f"{what} key {k!r} is not a dotted config path like observers.0.q.kappa")
    return mapping


def _bounded(values: range) -> range:
    """A range of at most :data:`MAX_CELLS` values (its length is known before any value is made)."""
    try:
        what = f"{len(values):,} values" if len(values) > MAX_CELLS else ""
    except OverflowError:  # more than 2**63
        what = "more than 2**63 values"
    if what:
        raise ValueError(f"has {what}; a sweep makes at most {MAX_CELLS:,} cells")
    return values


def expand_axis(v: Any) -> list:
    """The values of one grid axis: a non-empty list; ``"range(stop)"`` / ``"range(start, stop[, step])"``;
    ``{range: [start, stop, step]}``; ``{linspace: [a, b, n]}``; ``{geomspace: [a, b, n]}`` (a, b > 0)."""
    if isinstance(v, str):
        m = _RANGE.match(v)
        if not m:
            raise ValueError(f"{v!r}: a string axis must be range(stop) or range(start, stop[, step]); "
                             "give other values as a list")
        a, b, c = (int(g) if g is not None else None for g in m.groups())
        args = (a,) if b is None else (a, b) if c is None else (a, b, c)
        if c == 0:
            raise ValueError("range step must not be 0")
        v = list(_bounded(range(*args)))
    elif isinstance(v, dict):
        if len(v) != 1 or next(iter(v)) not in ("range", "linspace", "geomspace"):
            raise ValueError("a mapping axis is one of {range: [start, stop, step]}, {linspace: [a, b, n]}, "
                             "{geomspace: [a, b, n]}")
        kind, args = next(iter(v.items()))
        if not isinstance(args, list) or not all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in args):
            raise ValueError(f"{kind}: needs a list of numbers")
        if kind == "range":
            if not 1 <= len(args) <= 3 or not all(isinstance(x, int) for x in args) or (len(args) == 3 and args[2] == 0):
                raise ValueError("range: needs 1 to 3 integers [start, stop, step], step not 0")
            v = list(_bounded(range(*args)))
        else:
            if len(args) != 3 or not isinstance(args[2], int) or args[2] < 1:
                raise ValueError(f"{kind}: needs [a, b, n] with an integer n >= 1")
            _bounded(range(args[2]))
            if kind == "geomspace" and (args[0] <= 0 or args[1] <= 0):
                raise ValueError("geomspace: a and b must be > 0")
            fn = np.linspace if kind == "linspace" else np.geomspace
            v = [float(x) for x in fn(args[0], args[1], args[2])]
    elif isinstance(v, list) and len(v) > MAX_CELLS:
        raise ValueError(f"has {len(v):,} values; a sweep makes at most {MAX_CELLS:,} cells")
    elif not isinstance(v, list):
        raise ValueError(f"an axis is a list of values, range(...), or a mapping (linspace, geomspace, range), "
                         f"not {type(v).__name__}")
    if not v:
        raise ValueError("an axis needs at least one value")
    return v


class Distribution(Strict):
    """One randomly sampled parameter: exactly one of the keys."""

    uniform: tuple[float, float] | None = Field(None, description="[lo, hi)")
    loguniform: tuple[float, float] | None = Field(None, description="[lo, hi), both > 0, uniform in log")
    normal: tuple[float, float] | None = Field(None, description="[mean, std]")
    integers: tuple[int, int] | None = Field(None, description="[lo, hi), integers")
    choice: list[Any] | None = Field(None, min_length=1, description="one of these values, equally likely")

    @model_validator(mode="after")
    def _one(self):
        given = [k for k in type(self).model_fields if getattr(self, k) is not None]
        if len(given) != 1:
            raise ValueError("give exactly one of uniform, loguniform, normal, integers, choice")
        k = given[0]
        v = getattr(self, k)
        if k in ("uniform", "loguniform", "integers") and not v[0] < v[1]:
            raise ValueError(f"{k}: needs lo < hi")
        if k == "loguniform" and v[0] <= 0:
            raise ValueError("loguniform: lo must be > 0")
        if k == "normal" and v[1] < 0:
            raise ValueError("normal: std must be >= 0")
        return self

    def sample(self, rng: np.random.Generator) -> Any:
        if self.uniform is not None:
            return float(rng.uniform(*self.uniform))
        if self.loguniform is not None:
            lo, hi = np.log(self.loguniform)
            return float(np.exp(rng.uniform(lo, hi)))
        if self.normal is not None:
            return float(rng.normal(*self.normal))
        if self.integers is not None:
            return int(rng.integers(*self.integers))
        return copy.deepcopy(self.choice[int(rng.integers(len(self.choice)))])


class RandomSamples(Strict):
    """``count`` random cells, each parameter drawn independently (numpy's PCG64 seeded by ``seed``,
    default: the grid's ``seed``, else 0, whatever the config's runs.seed)."""

    count: int = Field(ge=1, le=MAX_CELLS)
    seed: int | None = Field(None, ge=0, le=MAX_SEED, description="seed of the samples (default: the grid's seed, else 0)")
    params: dict[str, Distribution] = Field(min_length=1)

    @field_validator("params")
    @classmethod
    def _keys(cls, v):
        return _check_keys(v, "random.params")


class Grid(Strict):
    """A sweep's grid file (``GRID.yaml``). Keys are dotted config paths as in ``--set`` (list entries by
    number: ``observers.0.q.kappa``); values are YAML values. At least one of ``grid``, ``cells``,
    ``random``; the cells are the product of the three parts (see the module docstring).

    Example::

        description: curvature process noise of the multi-rate UKF paper's filter
        fixed: {runs.count: 10}
        grid:
          observers.0.q.kappa: [5.0e-7, 1.0e-6, 2.0e-6, 4.0e-6, 8.0e-6]
          runs.seed: range(10)
    """

    description: str = ""
    seed: int | None = Field(None, ge=0, le=MAX_SEED, description="sweep seed (default: the config's runs.seed)")
    seeds: Literal["common", "derived"] = Field(
        "common", description="seed of cells that do not set runs.seed: the sweep seed (common random numbers), "
        "or one derived per cell from its overrides")
    fixed: dict[str, Any] = Field(default_factory=dict, description="overrides applied to every cell")
    grid: dict[str, Any] = Field(default_factory=dict, description="axes: key -> values (cartesian product)")
    cells: list[dict[str, Any]] = Field(default_factory=list, description="explicit cells: key -> value each")
    random: RandomSamples | None = None

    @field_validator("fixed")
    @classmethod
    def _fixed(cls, v):
        return _check_keys(v, "fixed")

    @field_validator("grid")
    @classmethod
    def _grid(cls, v):
        _check_keys(v, "grid")
        out = {}
        for k, values in v.items():
            try:
                out[k] = expand_axis(values)
            except ValueError as e:
                raise ValueError(f"axis {k}: {e}") from None
        return out

    @field_validator("cells")
    @classmethod
    def _cells(cls, v):
        for i, c in enumerate(v):
            try:
                _check_keys(c, f"cell {i}:")
            except ValueError as e:
                raise ValueError(str(e)) from None
        return v

    @model_validator(mode="after")
    def _parts(self):
        if not self.grid and not self.cells and self.random is None:
            raise ValueError("give at least one of grid, cells, random")
        parts = {"fixed": set(self.fixed), "grid": set(self.grid),
                 "random": set(self.random.params) if self.random else set()}
        parts["cells"] = set().union(*(set(c) for c in self.cells)) if self.cells else set()
        names = list(parts)
        for i, a in enumerate(names):
            for b in names[i + 1 :]:
                both = sorted(parts[a] & parts[b])
                if both:
                    raise ValueError(f"key {both[0]} is set in both {a} and {b}")
        n = (len(self.cells) or 1) * (self.random.count if self.random else 1) * math.prod(len(x) for x in self.grid.values())
        if n > MAX_CELLS:
            raise ValueError(f"the grid makes {n:,} cells; at most {MAX_CELLS:,} (split the sweep)")
        return self


def load_grid(path: str | Path) -> Grid:
    """Read and validate a grid file. Raises :class:`ConfigError` naming the file and key."""
    from needlecli.io.yamlfile import read_yaml

    source = str(path)
    data, _ = read_yaml(path, "a sweep grid")
    try:
        return Grid.model_validate(data)
    except ValidationError as e:
        raise validation_error(e, data, source, schema=Grid) from None


def grid_overrides(grid: Grid) -> list[dict]:
    """The varying overrides of every cell, in sweep order."""
    entries = [dict(c) for c in grid.cells] or [{}]
    samples: list[dict] = [{}]
    if grid.random is not None:
        rng = np.random.default_rng(grid.random.seed if grid.random.seed is not None else (grid.seed or 0))
        samples = [{k: d.sample(rng) for k, d in grid.random.params.items()} for _ in range(grid.random.count)]
    axes = list(grid.grid)
    product = [dict(zip(axes, combo)) for combo in itertools.product(*(grid.grid[k] for k in axes))]
    return [{**e, **s, **p} for e in entries for s in samples for p in product]

