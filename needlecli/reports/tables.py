"""Paper-form tables: pandas views of the error metrics, registered by name in :data:`TABLES`.

A table function takes the loaded results file and the errors of every observer and returns a
``DataFrame``; :func:`write_table` writes it as Markdown, CSV and LaTeX. Paper-specific tables (the high-gain observer paper
Table I, the multi-rate UKF paper's Table 1, the magnetic needle EM paper's Tables 1-3) register here from their own modules.
"""

from __future__ import annotations

import re
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pandas as pd

from needlecli.io.atomic import write_text_atomic
from needlecli.io.results import Group
from needlecli.metrics import ErrorSet
from needlecli.reports import TABLES

TableFn = Callable[[Group, dict[str, ErrorSet]], pd.DataFrame]

_QUANTITY_ORDER = ["E_xyz", "E_x", "E_y", "E_z", "E_lat", "E_ax", "E_alpha", "E_beta", "E_gamma", "E_R", "E_h", "E_B", "E_kappa"]


def order_quantities(names):
    """Quantities in the papers' order (position: its norm, per axis, across and along the needle; angles,
    rotation, vectors, curvature, the rest)."""
    return sorted(names, key=lambda q: (_QUANTITY_ORDER.index(q) if q in _QUANTITY_ORDER else 99, q))


def _finite(values: np.ndarray) -> np.ndarray:
    """The finite values, flat: the array itself (a view) when all are finite, as they mostly are (no copy
    of a thousand insertions' errors per quantity), the same numbers in the same order either way."""
    values = np.asarray(values)
    fin = np.isfinite(values)
    if fin.all():
        return values.reshape(-1)
    return values[fin]


def _rows(errors: dict[str, ErrorSet], stats: dict[str, Callable[[np.ndarray], float]]) -> pd.DataFrame:
    rows = []
    for obs, es in errors.items():
        for q in order_quantities(es.quantities):
            qe = es.quantities[q]
            v = _finite(qe.values)
            row = {"Observer": obs, "Quantity": f"{q} [{qe.unit}]"}
            for col, fn in stats.items():
                row[col] = fn(v) if v.size else np.nan
            row["Runs"] = count_cell(len(qe.runs), es.n_runs)
            rows.append(row)
        for q, why in es.not_computable.items():
            row = {"Observer": obs, "Quantity": f"{q}: not computable ({why})"}
            row.update({col: np.nan for col in stats})
            row["Runs"] = count_cell(0, es.n_runs)
            rows.append(row)
    cols = ["Observer", "Quantity", *stats, "Runs"]
    return pd.DataFrame(rows, columns=cols)


@TABLES.register("summary")
def summary_table(res: Group, errors: dict[str, ErrorSet]) -> pd.DataFrame:
    """Instantaneous estimation error over all kept runs and all time steps, the initial one included:
    Mean, Std, Max (the multi-rate UKF paper's statistics; its Table 1, table pose_curvature_error, counts only the steps after
    initialisation). The tip position error E_xyz is also given per axis (E_x, E_y, E_z) and, where the
    model has a needle axis, across it (E_lat, lateral) and along it (E_ax, axial), about the truth's
    tangent."""
    return _rows(errors, {"Mean": np.mean, "Std": np.std, "Max": np.max})


@TABLES.register("accuracy")
def accuracy_table(res: Group, errors: dict[str, ErrorSet]) -> pd.DataFrame:
    """Average absolute error, RMSE and standard deviation of every error quantity over all kept runs and
    time steps, in each quantity's own unit (the high-gain observer paper's statistics; its Table I itself, e_x in mm and
    e_beta in rad, is the table x_pitch_roll_error)."""
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
            rows.append({"Source": name, "Status": s, "Runs": count_cell(sel.sum(), len(st)),
                         "Stopped at [s]": stopped, "Reasons": "; ".join(reasons)})
    return pd.DataFrame(rows, columns=["Source", "Status", "Runs", "Stopped at [s]", "Reasons"])


def _float_format(x: float) -> str:
    """One number on its own (4 significant digits, small values in scientific notation). Tables use
    :func:`column_formatter` instead: one format per column."""
    if not np.isfinite(x):
        return "n/a"
    if x == 0:
        return "0"
    return f"{x:.4g}" if abs(x) >= 1e-3 else f"{x:.3e}"


def count_cell(kept: int, total: int) -> str:
    """The one form of a run (or trial) count in every table: ``kept/total``."""
    return f"{int(kept)}/{int(total)}"


def column_formatter(values) -> Callable[[object], str]:
    """One number format for a whole column: integers when every value is whole; else fixed-point
    notation with 4 significant digits (0.3594, 15.09, 0.0001992), or, when a nonzero magnitude of the
    column is under 1e-4 or from 1e6 on, scientific notation with 4 significant digits for every value
    (never the two mixed in a column). Missing values are ``n/a``; text passes through."""
    nums = np.array([float(v) for v in values if _is_number(v)], dtype=float)
    fin = nums[np.isfinite(nums)]
    if fin.size and np.all(fin == np.round(fin)) and np.all(np.abs(fin) < 1e15):
        def fmt(x: float) -> str:
            return f"{x:.0f}"
    else:
        nz = np.abs(fin[fin != 0])
        lo, hi = (float(nz.min()), float(nz.max())) if nz.size else (1.0, 1.0)
        if lo < 1e-4 or hi >= 1e6:
            def fmt(x: float) -> str:
                return f"{x:.3e}"
        else:
            def fmt(x: float) -> str:
                if x == 0:
                    return "0"
                dec = int(max(0, 3 - np.floor(np.log10(abs(float(f"{x:.4g}"))))))  # 4 significant digits
                return f"{x:.{dec}f}"

    def cell(v) -> str:
        if isinstance(v, (bool, np.bool_)):
            return str(bool(v))
        if not _is_number(v):
            return "" if v is None else str(v)
        x = float(v)
        return fmt(x) if np.isfinite(x) else "n/a"

    return cell


def _is_number(v) -> bool:
    return isinstance(v, (int, float, np.integer, np.floating)) and not isinstance(v, (bool, np.bool_))


def formatted(df: pd.DataFrame) -> pd.DataFrame:
    """``df`` as text, each column in its one format (:func:`column_formatter`)."""
    return pd.DataFrame({c: [column_formatter(df[c].tolist())(v) for v in df[c].tolist()] for c in df.columns},
                        columns=df.columns, index=df.index)


def to_markdown(df: pd.DataFrame) -> str:
    """GitHub Markdown, each column in one number format."""
    return formatted(df).to_markdown(index=False, tablefmt="github", disable_numparse=True)


def to_terminal(df: pd.DataFrame, width: int, columns: list[str] | None = None, more: str = "") -> str:
    """``df`` as Markdown no wider than ``width`` characters (a terminal's): ``columns`` in their order of
    importance (default: the frame's), as many as fit (the first two always), each in its one format;
    a last line says how many were left out and where they are (``more``: e.g. "in sweep.csv")."""
    order = [c for c in (columns or list(df.columns)) if c in df.columns]
    keep = order[:2]
    for c in order[2:]:
        trial = keep + [c]
        if max(len(line) for line in to_markdown(df[trial]).splitlines()) > width:
            break
        keep = trial
    shown = [c for c in df.columns if c in keep] if columns is None else keep
    text = to_markdown(df[shown])
    left = len(df.columns) - len(shown)
    if left:
        text += f"\n({left} more column(s){' ' + more if more else ''})"
    return text


# LaTeX specials and the non-ASCII characters the tables use (pdflatex, OT1: < > | need math mode)
_LATEX = {"\\": r"\textbackslash{}", "&": r"\&", "%": r"\%", "$": r"\$", "#": r"\#", "_": r"\_",
          "{": r"\{", "}": r"\}", "~": r"\textasciitilde{}", "^": r"\textasciicircum{}", "<": r"$<$",
          ">": r"$>$", "|": r"$|$", "±": r"$\pm$", "°": r"$^\circ$", "µ": r"$\mu$", "μ": r"$\mu$",
          "×": r"$\times$", "≤": r"$\leq$", "≥": r"$\geq$", "–": "--", "—": "---", "·": r"$\cdot$",
          "√": r"$\surd$", "²": r"$^2$", "³": r"$^3$", "…": r"\ldots{}", "→": r"$\rightarrow$",
          "’": "'", "‘": "`", "“": "``", "”": "''"}

#: LaTeX packages the ``.tex`` tables need (named in each file's first line)
LATEX_PACKAGES = ("booktabs", "longtable")
LONG_TABLE_ROWS = 40  # longer tables are a longtable (breaks across pages) instead of a float


def latex_escape(text: str) -> str:
    """``text`` as LaTeX text for pdflatex: specials escaped, the tables' non-ASCII symbols as commands,
    any other non-ASCII character replaced by ``?`` (never a compile error)."""
    out = []
    for ch in str(text):
        if ch in _LATEX:
            out.append(_LATEX[ch])
        elif ord(ch) < 128:
            out.append(ch)
        else:
            out.append("?")
    return "".join(out)


def to_latex(df: pd.DataFrame, caption: str = "", label: str = "") -> str:
    """A LaTeX table (booktabs rules; a ``longtable`` beyond :data:`LONG_TABLE_ROWS` rows) with every
    name, header, cell and the caption escaped, numbers in the column formats of the Markdown."""
    shown = formatted(df)
    align = "".join("r" if pd.api.types.is_numeric_dtype(df[c]) and not pd.api.types.is_bool_dtype(df[c]) else "l"
                    for c in df.columns) or "l"
    head = " & ".join(latex_escape(c) for c in df.columns) + r" \\"
    body = [" & ".join(latex_escape(v) for v in row) + r" \\" for row in shown.itertuples(index=False)]
    cap = latex_escape(" ".join(caption.split()))
    lab = rf"\label{{{re.sub(r'[^A-Za-z0-9:.-]', '-', label)}}}" if label else ""
    long = len(df) > LONG_TABLE_ROWS
    needs = r"\usepackage{booktabs}" + (r" and \usepackage{longtable}" if long else "")
    lines = [f"% needlecli table; needs {needs}"]
    if long:
        lines += [rf"\begin{{longtable}}{{{align}}}"]
        if cap or lab:
            lines += [rf"\caption{{{cap}}}{lab} \\"]
        lines += [r"\toprule", head, r"\midrule", r"\endfirsthead", r"\toprule", head, r"\midrule", r"\endhead",
                  r"\bottomrule", r"\endfoot", *body, r"\end{longtable}"]
    else:
        lines += [r"\begin{table}[htbp]", r"\centering"]
        if cap or lab:
            lines += [rf"\caption{{{cap}}}{lab}"]
        lines += [rf"\begin{{tabular}}{{{align}}}", r"\toprule", head, r"\midrule", *body, r"\bottomrule",
                  r"\end{tabular}", r"\end{table}"]
    return "\n".join(lines) + "\n"


#: significant digits of a number in a CSV file: the data's precision, without the last bits of rounding
#: (60, not 60.00000000000378)
CSV_DIGITS = 12


def _csv_number(v):
    return float(f"{v:.{CSV_DIGITS}g}") if isinstance(v, (float, np.floating)) and np.isfinite(v) else v


def to_csv(df: pd.DataFrame) -> str:
    """``df`` as CSV, every number to :data:`CSV_DIGITS` significant digits (the one place a CSV's numbers
    are formatted; whole numbers without a decimal point), missing values empty."""
    out = df.copy()
    for c in out.columns:
        if pd.api.types.is_float_dtype(out[c]) or out[c].dtype == object:
            out[c] = [_csv_number(v) for v in out[c].tolist()]
    return out.to_csv(index=False, float_format=f"%.{CSV_DIGITS}g")


def _atomic_text(path: Path, text: str) -> None:
    write_text_atomic(path, text)


def write_table(df: pd.DataFrame, stem: Path, formats: list[str], caption: str = "") -> list[Path]:
    """Write ``df`` as ``stem.md``, ``stem.csv``, ``stem.tex`` (those in ``formats``), each atomically;
    the Markdown and the LaTeX carry the same caption and the same number formats."""
    out = []
    for fmt in formats:
        p = stem.with_suffix(f".{fmt}")
        if fmt == "md":
            text = (f"{caption}\n\n" if caption else "") + to_markdown(df) + "\n"
        elif fmt == "csv":
            text = to_csv(df)
        elif fmt == "tex":
            text = to_latex(df, caption, label=f"tab:{stem.name}")
        else:
            raise ValueError(f"unknown table format {fmt!r}")
        _atomic_text(p, text)
        out.append(p)
    return out


def starts_note(res: Group) -> str:
    """Which start each observer of a results file had (``/estimates/<observer>`` attribute ``start``,
    written by the runner from ``runs.common_start``), in one sentence; empty for one observer or a file
    that does not say."""
    starts = {n: str(g.attrs["start"]) for n, g in res.data.get("estimates", Group()).data.items()
              if isinstance(g, Group) and "start" in g.attrs}
    if len(starts) < 2:
        return ""
    ref = next((n for n, s in starts.items() if s.startswith("common (reference)")), None)
    own = [n for n, s in starts.items() if s.startswith("own")]
    if ref is None:
        why = next((s[s.index("(") + 1: -1] for s in starts.values() if "(" in s), "")
        return f"Start: each observer from its own init{f' ({why})' if why else ''}."
    sharing = [n for n, s in starts.items() if n != ref and s.startswith("common")]
    out = f"Start: {', '.join(sharing)} from {ref}'s initial estimate (its own draw, made once; runs.common_start)."
    return out + (f" From their own init: {', '.join(own)}." if own else "")


def table_caption(name: str, df: pd.DataFrame, res: Group | None = None) -> str:
    """A table's caption: the first paragraph of its function's docstring, what a replay compared
    against, which start each observer had (:func:`starts_note`, tables with an ``Observer`` column) and
    what the table measured on this file (``df.attrs["note"]``)."""
    doc = " ".join((TABLES.get(name).__doc__ or "").strip().split("\n\n")[0].split())
    if res is not None and res.attrs.get("source") == "replay":
        doc += f" Replayed logs; errors against: {res.attrs.get('truth_kind', 'the logs')}."
    if res is not None and "Observer" in df.columns and (starts := starts_note(res)):
        doc += f" {starts}"
    note = df.attrs.get("note")
    return f"{doc} {note}" if note else doc
