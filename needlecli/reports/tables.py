"""Paper-form tables: pandas views of the error metrics, registered by name in :data:`TABLES`.

A table function takes the loaded results file and the errors of every observer and returns a
``DataFrame``; :func:`write_table` writes it as Markdown, CSV and LaTeX. Paper-specific tables (seed 000
Table I, seed 003 Table 1, seed 004 Tables 1-3) register here from their own modules.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np
import pandas as pd

from needlecli.io.atomic import write_text_atomic
from needlecli.io.results import Group
from needlecli.metrics import ErrorSet
from needlecli.reports import TABLES

TableFn = Callable[[Group, dict[str, ErrorSet]], pd.DataFrame]

_QUANTITY_ORDER = ["E_xyz", "E_x", "E_y", "E_z", "E_alpha", "E_beta", "E_gamma", "E_R", "E_h", "E_B", "E_kappa"]


def order_quantities(names):
    """Quantities in the papers' order (position, angles, rotation, vectors, curvature, the rest)."""
    return sorted(names, key=lambda q: (_QUANTITY_ORDER.index(q) if q in _QUANTITY_ORDER else 99, q))


def _rows(errors: dict[str, ErrorSet], stats: dict[str, Callable[[np.ndarray], float]]) -> pd.DataFrame:
    rows = []
    for obs, es in errors.items():
        for q in order_quantities(es.quantities):
            qe = es.quantities[q]
            v = qe.values[np.isfinite(qe.values)]
            row = {"Observer": obs, "Quantity": f"{q} [{qe.unit}]"}
            for col, fn in stats.items():
                row[col] = fn(v) if v.size else np.nan
            row["Runs"] = f"{len(qe.runs)}/{es.n_runs}"
            rows.append(row)
        for q, why in es.not_computable.items():
            row = {"Observer": obs, "Quantity": f"{q}: not computable ({why})"}
            row.update({col: np.nan for col in stats})
            row["Runs"] = f"0/{es.n_runs}"
            rows.append(row)
    cols = ["Observer", "Quantity", *stats, "Runs"]
    return pd.DataFrame(rows, columns=cols)


@TABLES.register("summary")
def summary_table(res: Group, errors: dict[str, ErrorSet]) -> pd.DataFrame:
    """Instantaneous estimation error over all kept runs and time steps: Mean, Std, Max
    (the form of seed 003's Table 1)."""
    return _rows(errors, {"Mean": np.mean, "Std": np.std, "Max": np.max})


@TABLES.register("accuracy")
def accuracy_table(res: Group, errors: dict[str, ErrorSet]) -> pd.DataFrame:
    """Average absolute estimation error, RMSE and standard deviation (the form of seed 000's Table I)."""
    return _rows(
        errors,
        {
            "Average Absolute Estimation Error": lambda v: float(np.mean(np.abs(v))),
            "RMSE": lambda v: float(np.sqrt(np.mean(v**2))),
            "Standard Deviation": np.std,
        },
    )


@TABLES.register("status")
def status_table(res: Group, errors: dict[str, ErrorSet]) -> pd.DataFrame:
    """Runs per status for the truth and for each observer, with the reasons."""
    rows = []
    truth = res.data["truth"]
    groups = [("truth", truth)] + list(res.data.get("estimates", Group()).data.items())
    for name, g in groups:
        st, rs = g.data["status"], g.data["reason"]
        when = g.data.get("event_time")
        for s in np.unique(st):
            sel = st == s
            reasons = sorted({r for r in rs[sel] if r})
            stopped = ""
            if when is not None and s != "ok" and np.isfinite(when[sel]).any():
                w = when[sel][np.isfinite(when[sel])]
                stopped = f"{w.min():.2f}" if w.min() == w.max() else f"{w.min():.2f} to {w.max():.2f}"
            rows.append({"Source": name, "Status": s, "Runs": int(sel.sum()),
                         "Stopped at [s]": stopped, "Reasons": "; ".join(reasons)})
    return pd.DataFrame(rows, columns=["Source", "Status", "Runs", "Stopped at [s]", "Reasons"])


def _float_format(x: float) -> str:
    if not np.isfinite(x):
        return "n/a"
    if x == 0:
        return "0"
    return f"{x:.4g}" if abs(x) >= 1e-3 else f"{x:.3e}"


def to_markdown(df: pd.DataFrame) -> str:
    """GitHub Markdown with 4 significant digits (small values in scientific notation)."""
    shown = df.map(lambda v: _float_format(v) if isinstance(v, float) else v)
    return shown.to_markdown(index=False, tablefmt="github", disable_numparse=True)


def _atomic_text(path: Path, text: str) -> None:
    write_text_atomic(path, text)


def write_table(df: pd.DataFrame, stem: Path, formats: list[str], caption: str = "") -> list[Path]:
    """Write ``df`` as ``stem.md``, ``stem.csv``, ``stem.tex`` (those in ``formats``), each atomically."""
    out = []
    for fmt in formats:
        p = stem.with_suffix(f".{fmt}")
        if fmt == "md":
            text = (f"{caption}\n\n" if caption else "") + to_markdown(df) + "\n"
        elif fmt == "csv":
            text = df.to_csv(index=False)
        elif fmt == "tex":
            text = df.to_latex(index=False, float_format=_float_format, caption=caption or None, na_rep="n/a")
        else:
            raise ValueError(f"unknown table format {fmt!r}")
        _atomic_text(p, text)
        out.append(p)
    return out
