"""Evaluation of a results file: errors -> tables (Markdown, CSV, LaTeX) and plots (PNG)."""

from __future__ import annotations

import logging
from pathlib import Path

import pandas as pd

from needlecli.errors import DataError
from needlecli.io.atomic import output_stem
from needlecli.io.fit import is_fit_file
from needlecli.io.results import Group, read_results
from needlecli.metrics import compute_errors
from needlecli.reports.tables import TABLES, table_caption, write_table

log = logging.getLogger("needlecli")


def configured_tables_of(path: str | Path) -> list[str]:
    """The tables a results file's config asks for, or every fit table of a fit file."""
    if is_fit_file(path):
        from needlecli.io.fit import read_fit
        from needlecli.reports.seed004 import default_fit_tables

        return default_fit_tables(read_fit(path))
    return configured_tables(read_results(path))


def experiment_name(path: str | Path) -> str:
    """The ``name`` attribute of a results or fit file (the file is checked in full: a damaged one is an
    error here, before anything is written)."""
    if is_fit_file(path):
        from needlecli.io.fit import read_fit

        return str(read_fit(path).attrs.get("name", ""))
    return str(read_results(path).attrs.get("name", ""))


def configured_tables(res) -> list[str]:
    """The tables the experiment's config asks for (``output.tables``), else the summary."""
    from needlecli.errors import ConfigError
    from needlecli.io.yamlfile import parse_yaml

    try:
        cfg = parse_yaml(str(res.attrs.get("config", "")), "the results file's config")
        out = cfg.get("output") if isinstance(cfg.get("output"), dict) else {}
        names = out.get("tables") if isinstance(out.get("tables"), list) else None
    except ConfigError:
        names = None
    return [n for n in (names or ["summary", "accuracy", "status"]) if isinstance(n, str) and n in TABLES]


def evaluate_results(
    path: str | Path,
    *,
    tables: list[str] | None = None,
    out_dir: str | Path | None = None,
    formats: list[str] | None = None,
    plots: bool = False,
    design: dict | None = None,
) -> dict[str, pd.DataFrame]:
    """Compute the tables of a results file (or of a fit file of ``needle fit-em``: the magnetic needle EM paper's tables and
    those by the trials' design, ``design``: ``group_by``, ``regress``); write them (and plots) to
    ``out_dir`` when given."""
    path = Path(path)
    if is_fit_file(path):
        from needlecli.reports.seed004 import evaluate_fit

        return evaluate_fit(path, tables=tables, out_dir=out_dir, formats=formats, plots=plots, design=design)
    if design and any(design.values()):
        raise DataError(f"{path}: --group-by and --regress group the fitted constants of a fit file (needle fit-em); "
                        "this is a results file")
    res = read_results(path)
    out = results_tables(res, tables or configured_tables(res), str(path))
    errors = out.pop("__errors__")
    if out_dir is not None:
        out_dir = Path(out_dir)
        stem = output_stem(res.attrs.get("name"), path.stem)
        for name, df in out.items():
            write_table(df, out_dir / f"{stem}_{name}", formats or ["md", "csv", "tex"], caption=df.attrs["caption"])
        if plots:
            from needlecli.reports.plots import draw_plots

            draw_plots(res, errors, out_dir / stem)
    return out


def results_tables(res: Group, names: list[str], source: str) -> dict[str, pd.DataFrame]:
    """The tables ``names`` of a results file's content (read from the file, or the very tree a run has
    just written: ``needle simulate`` prints its summary without reading 66 MB back), each with its
    caption; ``"__errors__"`` holds the errors they were computed from."""
    from needlecli.reports import FIT_TABLE_NAMES

    try:
        errors = compute_errors(res)
    except KeyError as e:  # a readable HDF5 file that lacks part of the layout
        raise DataError(f"{source}: incomplete results file (missing {e})") from None
    names = [TABLES.canonical(n) for n in names]
    for name in names:
        if name in FIT_TABLE_NAMES:
            raise DataError(f"{source}: table {name!r} needs a fit file of needle fit-em; this is a results file")
    out: dict[str, pd.DataFrame] = {}
    for name in names:
        out[name] = df = TABLES.get(name)(res, errors)
        df.attrs["caption"] = table_caption(name, df, res)
    out["__errors__"] = errors
    return out
