"""What a user sees in the outputs of ``needle evaluate``, checked: figures (every panel holds data, every
line and legend entry drawn, one colour per observer, units on every axis, no blank band under the
title) and LaTeX tables (each compiles with pdflatex). Shared by the test modules."""

from __future__ import annotations

import os
import shutil
import subprocess
from pathlib import Path

import matplotlib
import numpy as np
import pytest
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.image import AxesImage

PDFLATEX = shutil.which("pdflatex")
# CI installs pdflatex (.ci/run); elsewhere the LaTeX tests skip with the reason
needs_pdflatex = pytest.mark.skipif(PDFLATEX is None and not os.environ.get("CI"),
                                    reason="pdflatex not installed (apt-get install texlive-latex-base texlive-latex-recommended)")


def capture_figures(monkeypatch, render: bool = True) -> list[Figure]:
    """Record every figure saved from now on (its artists stay inspectable after ``plt.close``); with
    ``render=False`` the PNG is not rendered (an empty file is written: quicker)."""
    saved: list[Figure] = []
    original = Figure.savefig

    def savefig(self, *args, **kwargs):
        saved.append(self)
        return original(self, *args, **kwargs) if render else None

    monkeypatch.setattr(Figure, "savefig", savefig)
    return saved


def _finite_points(line) -> int:
    x, y = (np.asarray(a, dtype=float) for a in line.get_data())
    if x.shape != y.shape:
        x, y = np.broadcast_arrays(x, y)
    return int(np.sum(np.isfinite(x) & np.isfinite(y)))


def _is_reference_line(ax, line) -> bool:
    """axhline / axvline: drawn in axes coordinates on one axis (no data of their own)."""
    return line.get_transform() != ax.transData


def figure_problems(fig: Figure, colours: dict[str, str], max_gap_in: float = 0.3, layout: bool = True) -> list[str]:
    """Everything a reader would find wrong with ``fig`` (empty list: none); ``layout``: also render it
    and measure the band under its title (slower)."""
    title = fig._suptitle.get_text() if fig._suptitle is not None else (fig.axes[0].get_title() if fig.axes else "?")
    out = []
    drawn: dict[str, int] = {}  # gid -> finite points over the figure
    for k, ax in enumerate(fig.axes):
        where = f"{title!r} panel {k}"
        images = [a for a in ax.get_children() if isinstance(a, AxesImage)]
        data_lines = [ln for ln in ax.lines if not _is_reference_line(ax, ln)]
        for ln in data_lines:
            n = _finite_points(ln)
            if n == 0:
                out.append(f"{where}: a line ({ln.get_label()!r}) without a finite point")
            gid = ln.get_gid()
            if gid:
                drawn[gid] = drawn.get(gid, 0) + n
                if gid.startswith("observer:"):
                    obs = gid.split(":", 1)[1]
                    want = matplotlib.colors.to_hex(colours[obs])
                    got = matplotlib.colors.to_hex(ln.get_color())
                    if got != want:
                        out.append(f"{where}: {obs} drawn in {got}, its colour is {want}")
        if not images and not any(_finite_points(ln) >= 1 for ln in data_lines):
            out.append(f"{where}: no data")
        for axis, shared in (("x", ax.get_shared_x_axes()), ("y", ax.get_shared_y_axes())):
            labels = [getattr(a, f"get_{axis}label")() for a in shared.get_siblings(ax)]  # shared: one label
            label = next((lb for lb in labels if lb), "")
            if not (label and "[" in label and "]" in label):
                out.append(f"{where}: {axis} axis {label!r} has no unit")
    legends = list(fig.legends) + [ax.get_legend() for ax in fig.axes if ax.get_legend() is not None]
    for leg in legends:
        for text in leg.get_texts():
            t = text.get_text()
            if t in colours and drawn.get(f"observer:{t}", 0) == 0:
                out.append(f"{title!r}: the legend lists {t}, which is not drawn")
            if (t.startswith("truth") or t.startswith("reference")) and drawn.get("truth", 0) == 0:
                out.append(f"{title!r}: the legend lists {t!r}, which is not drawn")
    if "half turn" in title or any("half turn" in x.get_text() for leg in legends for x in leg.get_texts()):
        if not any(_is_reference_line(ax, ln) for ax in fig.axes for ln in ax.lines):
            out.append(f"{title!r}: claims half turns it does not draw")
    if layout and fig._suptitle is not None and fig.axes:
        fig.set_dpi(30)  # the layout in inches does not depend on it; a coarse rendering is quicker
        canvas = FigureCanvasAgg(fig)  # a closed figure keeps its artists, not its canvas
        canvas.draw()
        r = canvas.get_renderer()
        below = fig._suptitle.get_window_extent(r).y0
        top = max(ax.get_tightbbox(r).y1 for ax in fig.axes)
        gap = (below - top) / fig.dpi
        if gap > max_gap_in:
            out.append(f"{title!r}: a blank band of {gap:.2f} in under the title")
    return out


def compile_tables(tex_files: list[Path], workdir: Path) -> None:
    """Compile every table in one document with pdflatex (the packages the files name in their first
    line); fails with the log's first error and the file it came from."""
    assert tex_files, "no .tex tables to compile"
    packages = set()
    for p in tex_files:
        first = p.read_text().splitlines()[0]
        packages |= {w.split("}")[0] for w in first.split(r"\usepackage{")[1:]}
    body = "\n".join(rf"\input{{{p.resolve()}}}\clearpage" for p in tex_files)
    doc = workdir / "tables.tex"
    doc.write_text("\\documentclass{article}\n" + "".join(rf"\usepackage{{{pkg}}}" + "\n" for pkg in sorted(packages))
                   + "\\begin{document}\n" + body + "\n\\end{document}\n")
    r = subprocess.run([PDFLATEX or "pdflatex", "-interaction=nonstopmode", "-halt-on-error", doc.name],
                       cwd=workdir, capture_output=True, text=True, timeout=120)
    if r.returncode != 0:
        lines = r.stdout.splitlines()
        err = next((i for i, ln in enumerate(lines) if ln.startswith("!")), len(lines) - 20)
        opened = [ln for ln in lines[:err] if ".tex" in ln]
        raise AssertionError("pdflatex failed in " + (opened[-1] if opened else "?") + ":\n" + "\n".join(lines[err:err + 12]))
    assert (workdir / "tables.pdf").exists()
