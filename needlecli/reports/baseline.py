"""Regression baselines: stored expectations for table cells (value and tolerance), checked by
``needle evaluate RESULTS --baseline FILE.yaml`` (exit code 1 and a readable diff on a regression) and
written by ``--write-baseline FILE.yaml``::

    results: pose_curvature_error            # the experiment's name (checked)
    cells:
      - table: pose_curvature_error
        row: {Observer: ukf, Error: E_x,y,z (mm)}   # the table's text columns identify the row
        column: Mean
        value: 0.3595
        tol: 0.036                     # absolute tolerance
        check: both                    # both: |x - value| <= tol; max: x <= value + tol; min: x >= value - tol
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np
import pandas as pd
import yaml
from pydantic import Field, ValidationError, field_validator

from needlecli.errors import ConfigError
from needlecli.schema import NonNeg, Strict


class Cell(Strict):
    """One expected cell. Its value and tolerance are finite numbers (a NaN expectation is an error in
    the baseline, never a cell that holds); its table is one ``needle evaluate`` knows."""

    table: str
    row: dict[str, str | int | float]
    column: str
    value: float
    tol: NonNeg
    check: Literal["both", "max", "min"] = "both"

    @field_validator("table")
    @classmethod
    def _known(cls, v):
        from needlecli.reports import TABLES

        if v not in TABLES:
            raise ValueError(f"unknown table {v!r}; known: {', '.join(TABLES.names())}")
        return TABLES.canonical(v)


class Baseline(Strict):
    results: str | None = None
    cells: list[Cell] = Field(min_length=1)


@dataclass
class Failure:
    cell: Cell
    got: float | None
    why: str

    def line(self) -> str:
        key = ", ".join(f"{k}={v}" for k, v in self.cell.row.items())
        got = "missing" if self.got is None else f"{self.got:.6g}"
        return f"  {self.cell.table} [{key}] {self.cell.column}: expected {self.cell.value:.6g} +- {self.cell.tol:.3g} ({self.cell.check}), got {got}: {self.why}"


def load_baseline(path: str | Path) -> Baseline:
    from needlecli.io.yamlfile import read_yaml
    from needlecli.schema import validation_error

    path = Path(path)
    data, _ = read_yaml(path, "a baseline")
    try:
        return Baseline.model_validate(data)
    except ValidationError as e:
        raise validation_error(e, data, str(path), schema=Baseline) from None


def _key_columns(df: pd.DataFrame) -> list[str]:
    """Columns that identify a row: the table's ``attrs["keys"]`` if it declares them, else its text
    columns (counts such as ``Runs``, ``kept/total``, are values, not keys)."""
    if df.attrs.get("keys"):
        return list(df.attrs["keys"])
    return [c for c in df.columns if not pd.api.types.is_numeric_dtype(df[c]) and c not in COUNT_COLUMNS]


#: columns that hold counts in the form ``kept/total`` (compared by the kept count)
COUNT_COLUMNS = ("Runs", "Trials", "Converged")


def _value(v) -> float | None:
    if isinstance(v, str) and re.fullmatch(r"\s*\d+\s*/\s*\d+\s*", v):  # a count, kept/total: the kept
        return float(v.split("/")[0])
    try:
        return float(v)
    except (TypeError, ValueError):
        return None


def _find(df: pd.DataFrame, row: dict) -> pd.DataFrame:
    sel = np.ones(len(df), dtype=bool)
    for k, v in row.items():
        if k not in df.columns:
            return df.iloc[0:0]
        col = df[k]
        sel &= (col.astype(str) == str(v)).to_numpy() | (
            pd.api.types.is_numeric_dtype(col) and isinstance(v, (int, float)) and np.isclose(col.to_numpy(dtype=float), v)
        )
    return df[sel]


def compare(tables: dict[str, pd.DataFrame], baseline: Baseline, name: str | None = None,
            source: str = "baseline") -> list[Failure]:
    """Cells that regress, are missing, or are not finite (NaN fails a cell). ``source``: the baseline file."""
    out = []
    if baseline.results and name and baseline.results != name:
        raise ConfigError(str(source), ("results",), f"is for experiment {baseline.results!r}, these results are {name!r}")
    for cell in baseline.cells:
        df = tables.get(cell.table)
        if df is None or cell.column not in (df.columns if df is not None else []):
            out.append(Failure(cell, None, "table or column not computed"))
            continue
        rows = _find(df, cell.row)
        if len(rows) != 1:
            out.append(Failure(cell, None, f"{len(rows)} rows match"))
            continue
        got = _value(rows.iloc[0][cell.column])
        if got is None:
            out.append(Failure(cell, None, f"not a number ({rows.iloc[0][cell.column]!r})"))
        elif not math.isfinite(got):
            out.append(Failure(cell, got, "not finite"))
        elif cell.check == "both" and abs(got - cell.value) > cell.tol:
            out.append(Failure(cell, got, "outside the tolerance"))
        elif cell.check == "max" and got > cell.value + cell.tol:
            out.append(Failure(cell, got, "worse than allowed"))
        elif cell.check == "min" and got < cell.value - cell.tol:
            out.append(Failure(cell, got, "worse than allowed"))
    return out


def make_baseline(tables: dict[str, pd.DataFrame], name: str, rel: float, abs_tol: float) -> dict:
    """Expectations for every finite numeric cell: tolerance ``max(abs_tol, rel * |value|)``."""
    cells = []
    for tname, df in tables.items():
        keys = _key_columns(df)
        for _, r in df.iterrows():
            row = {k: (r[k].item() if hasattr(r[k], "item") else r[k]) for k in keys}
            for col in df.columns:
                if col in keys:
                    continue
                v = _value(r[col])
                if v is not None and math.isfinite(v):
                    cells.append({"table": tname, "row": row, "column": col, "value": float(f"{v:.6g}"),
                                  "tol": float(f"{max(abs_tol, rel * abs(v)):.3g}"), "check": "both"})
    return {"results": name, "cells": cells}


def write_baseline(path: str | Path, data: dict) -> None:
    from needlecli.reports.tables import _atomic_text

    header = "# needle evaluate --baseline: expected table cells (value, tolerance); written by --write-baseline\n"

    class _NoAliases(yaml.SafeDumper):
        def ignore_aliases(self, data):
            return True

    _atomic_text(Path(path), header + yaml.dump(data, Dumper=_NoAliases, sort_keys=False, allow_unicode=True))
