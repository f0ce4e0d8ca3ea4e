"""PNG plots from a results file: error against depth, and trajectories; the style every plot shares.

Every figure of every study draws an observer in the same colour, line dashes and marker
(:func:`observer_look`: chosen from the observer's name alone, never from its place in a file, so the UKF
is the same colour in a comparison and in the next study), the truth in black, and gives every axis its
unit; two observers that share a colour differ in dashes and marker, and the markers of two curves fall at
different places, so a curve lying on another (the EKF's under the UKF's) stays visible. Legends sit
outside the data (:func:`outside_legend`). A plot function ``(results, errors, path_stem) -> Path | None``
returns None where it does not apply to the file (a fit-file figure on a results file), and raises
:class:`PlotSkipped` with the reason where it applies but its quantity cannot be computed or would be a
single point (a table line says it better): ``needle evaluate`` then writes nothing and logs the reason
once.
"""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from needlecli.io.atomic import atomic_path  # noqa: E402
from needlecli.io.results import Group  # noqa: E402
from needlecli.metrics import AXIS_QUANTITIES, ErrorSet, QuantityError  # noqa: E402
from needlecli.reports import PLOTS  # noqa: E402, F401  (the registry of plots; the plots register in it)

TRUTH_COLOUR = "k"
#: line styles that tell input cases (or other groups) of one observer apart; the colour stays the observer's
CASE_STYLES = ("-", "--", ":", "-.", (0, (5, 1, 1, 1, 1, 1)), (0, (1, 3)), (0, (8, 2)), (0, (3, 1, 3, 3)))
_LENGTH_TO_MM = {"mm": 1.0, "m": 1000.0, "cm": 10.0}


class PlotSkipped(Exception):
    """A plot that applies to the file but cannot be drawn from it: the message says why."""


#: observer colours: matplotlib's tab10 without its grey (the truth is black, sensor samples grey); an
#: observer (or fitted model) named ``name`` is drawn in ``OBSERVER_PALETTE[crc32(name, NAME_SALT) % 9]``
#: in every figure
OBSERVER_PALETTE = ("#1f77b4", "#ff7f0e", "#2ca02c", "#d62728", "#9467bd", "#8c564b", "#e377c2", "#bcbd22",
                    "#17becf")
#: the hash's starting value, chosen once so that the names that meet in one figure most often get
#: different colours: the built-in observer types (also their default names and those of needle compare:
#: the UKF blue, the open loop orange), the built-in models (fitted side by side), and the bundled
#: configs' tuned variants (ukf, ukf_em, ukf_gated, ...); tests/test_reports.py holds it
NAME_SALT = 5403
#: line dashes and markers, chosen from another part of the name's hash: observers that share a colour
#: differ in them, and curves on top of each other stay visible
OBSERVER_DASHES = ("-", (0, (6, 2)), (0, (2, 1.5)), (0, (8, 2, 2, 2)), (0, (4, 1.5, 1, 1.5, 1, 1.5)), (0, (3, 3)))
OBSERVER_MARKERS = ("o", "s", "^", "D", "v", "P", "X", "<")


def _name_hash(name: str) -> int:
    import zlib

    return zlib.crc32(str(name).encode("utf-8"), NAME_SALT)


def observer_colour(name: str) -> str:
    """The colour of observer (or fitted model) ``name`` in every figure: stable across files and studies
    (:data:`OBSERVER_PALETTE`, :data:`NAME_SALT`)."""
    return OBSERVER_PALETTE[_name_hash(name) % len(OBSERVER_PALETTE)]


#: markers on a curve of many points: about this many, each name's first at another eighth of the spacing
MARKERS_PER_CURVE = 8


def observer_look(name: str, n: int | None = None) -> dict:
    """Colour, dashes and marker of ``name``'s artists (``color``, ``ls``, ``marker``, ``markevery``), the
    same in every figure. The markers: on a curve of ``n`` points about :data:`MARKERS_PER_CURVE` of them,
    every ``n // 8`` points from an offset that depends on the name (so that two curves on top of each
    other show both); without ``n``, every 12 % of the curve's drawn length."""
    h = _name_hash(name) // len(OBSERVER_PALETTE)
    k = h // len(OBSERVER_DASHES)
    if n is None:
        every = (0.015 * (k % 8), 0.12)
    else:
        step = max(1, int(n) // MARKERS_PER_CURVE)
        every = ((k % 8) * step // 8, step)
    return {"color": observer_colour(name), "ls": OBSERVER_DASHES[h % len(OBSERVER_DASHES)],
            "marker": OBSERVER_MARKERS[k % len(OBSERVER_MARKERS)], "markevery": every}


def observer_colours(res: Group) -> dict[str, str]:
    """The colour of every observer of a results file (``/estimates``) or of every fitted model of a fit
    file (``/fit``): :func:`observer_colour` of each name (not its place in the file)."""
    group = res.data.get("fit") if res.attrs.get("format") == "needlecli-fit" else res.data.get("estimates")
    names = list(group.data) if isinstance(group, Group) else []
    return {n: observer_colour(n) for n in names}


def observer_style(obs: str, *, line: bool = True, ls=None, n: int | None = None) -> dict:
    """Keywords of an observer's artists: its look (:func:`observer_look`; ``n``: the curve's number of
    points) and a ``gid`` naming it (the tests read it). ``line=False``: colour, marker and gid only (error
    bars, scatter); ``ls``: a line style that means something else in the figure (an input case), in
    place of the observer's dashes."""
    look = observer_look(obs, n)
    out = {"color": look["color"], "marker": look["marker"], "gid": f"observer:{obs}"}
    if line:
        out.update(ls=look["ls"] if ls is None else ls, markevery=look["markevery"], ms=4)
    return out


def outside_legend(fig, handles, labels, ncol: int = 4):
    """One legend for the figure, under its panels: never over the data."""
    handles, labels = list(handles), list(labels)
    return fig.legend(handles, labels, loc="outside lower center", ncol=max(1, min(len(labels), ncol)), fontsize="small")


def beside_legend(ax, fontsize: str = "small"):
    """A panel's own legend, to the right of the panel (the constrained layout of :func:`subplots` makes
    room for it): never over the data."""
    return ax.legend(loc="upper left", bbox_to_anchor=(1.02, 1.0), borderaxespad=0.0, fontsize=fontsize)


def subplots(*args, **kwargs):
    """``plt.subplots`` with the constrained layout: titles, legends and labels get the room they need
    and no more (no blank band under a figure title)."""
    kwargs.setdefault("layout", "constrained")
    return plt.subplots(*args, **kwargs)


def save_figure(fig, path: Path) -> Path:
    """Save a figure as PNG through a temporary file and a rename; close it."""
    try:
        with atomic_path(path) as tmp:
            fig.savefig(tmp, dpi=110, bbox_inches="tight", format="png")
    finally:
        plt.close(fig)
    return path


def length_scale(res: Group) -> float:
    """Factor from the results file's length unit to mm (plots draw lengths in mm)."""
    return _LENGTH_TO_MM.get(str(res.attrs.get("length_unit", "mm")), 1.0)


def run_depths(res: Group) -> np.ndarray:
    """The inserted depth ``(N, T)`` of every run (simulated runs share one, replayed trials each have
    their own), in the model's length unit."""
    depth = np.asarray(res.data["depth"], dtype=float)
    n = res.data["truth"].data["state"].shape[0]
    return np.broadcast_to(depth, (n, depth.shape[-1])) if depth.ndim == 1 else depth


def curve_against_depth(depth: np.ndarray, values: np.ndarray, bins: int = 60):
    """Mean and 5-95 % band over runs of ``values (n, T)`` against ``depth (n, T)``, from the samples that
    exist (finite) only. Where every run has its samples at the same steps (a simulation, or one recording
    replayed several times) the curve is taken at those steps; otherwise (replayed trials with truth only
    at their own tracker frames) the samples are pooled in depth bins. Returns ``(d, mean, lo, hi, kind)``,
    ``kind`` saying which; empty arrays when there is no sample."""
    fin = np.isfinite(values) & np.isfinite(depth)
    cols = np.nonzero(fin.any(0))[0]
    empty = np.zeros(0)
    if cols.size == 0:
        return empty, empty, empty, empty, "none"
    if fin[:, cols].all():
        v, d = values[:, cols], depth[:, cols].mean(0)
        lo, hi = np.percentile(v, [5, 95], axis=0)
        return d, v.mean(0), lo, hi, "steps"
    d_all, v_all = depth[fin], values[fin]
    edges = np.linspace(d_all.min(), d_all.max() + 1e-9, min(bins, max(2, cols.size)) + 1)
    which = np.clip(np.searchsorted(edges, d_all, side="right") - 1, 0, len(edges) - 2)
    counts = np.bincount(which, minlength=len(edges) - 1)
    has = np.nonzero(counts)[0]
    mean = np.bincount(which, v_all, minlength=len(edges) - 1)[has] / counts[has]
    lo = np.array([np.percentile(v_all[which == b], 5) for b in has])  # a loop over depth bins, not runs
    hi = np.array([np.percentile(v_all[which == b], 95) for b in has])
    centres = 0.5 * (edges[:-1] + edges[1:])[has]
    return centres, mean, lo, hi, "bins"


def _band_words(kinds: set[str]) -> str:
    if kinds == {"bins"}:
        return "mean and 5-95 % of the samples per depth bin (truth only at some frames)"
    if "bins" in kinds:
        return "mean and 5-95 % over runs (binned in depth where truth exists only at some frames)"
    return "mean and 5-95 % over runs"


@PLOTS.register("error_vs_depth")
def error_vs_depth(res: Group, errors: dict[str, ErrorSet], path_stem: Path) -> Path | None:
    """Mean and 5-95 % band of each error quantity against inserted depth, one panel per quantity, from
    the steps where truth exists; one colour per observer, one legend for all panels. The per-axis
    position errors of an observer whose E_xyz is drawn are left to the tables (E_lat and E_ax are drawn)."""
    from needlecli.reports.tables import order_quantities

    shown = {obs: {q: qe for q, qe in es.quantities.items()  # per-axis errors where the norm is drawn: the tables
                   if np.isfinite(qe.values).any() and not (q in AXIS_QUANTITIES and "E_xyz" in es.quantities)}
             for obs, es in errors.items()}
    quantities = order_quantities({q for qs in shown.values() for q in qs})
    if not quantities:
        raise PlotSkipped("no error quantity could be computed (no truth where any observer estimated)")
    depth = run_depths(res)
    unit = res.attrs.get("length_unit", "mm")
    fig, axes = subplots(len(quantities), 1, figsize=(7, 1.9 * len(quantities) + 0.9), sharex=True, squeeze=False)
    kinds: set[str] = set()
    handles = {}
    for ax, q in zip(axes[:, 0], quantities):
        for obs in errors:
            qe: QuantityError | None = shown[obs].get(q)
            if qe is None or qe.values.size == 0:
                continue
            d, m, lo, hi, kind = curve_against_depth(depth[qe.runs], qe.values)
            if d.size == 0:
                continue
            kinds.add(kind)
            st = observer_style(obs, n=d.size)
            (line,) = ax.plot(d, m, lw=1.3, label=obs, **st)
            ax.fill_between(d, lo, hi, alpha=0.18, color=st["color"], lw=0)
            handles.setdefault(obs, line)
            ax.set_ylabel(f"{q} [{qe.unit}]")
        ax.grid(alpha=0.3)
    axes[-1, 0].set_xlabel(f"inserted depth [{unit}]")
    outside_legend(fig, handles.values(), handles.keys())
    fig.suptitle(f"{res.attrs.get('name', '')}: error against depth ({_band_words(kinds)})", fontsize=10)
    return save_figure(fig, Path(f"{path_stem}_error_vs_depth.png"))


_POSITION_AXES = (("x", "y", "z"), ("px", "py", "pz"))


@PLOTS.register("trajectories")
def trajectories(res: Group, errors: dict[str, ErrorSet], path_stem: Path, max_runs: int = 10) -> Path | None:
    """Tip paths of the first runs in two projections (z-x and z-y, mm): the truth where it exists (a
    replayed trial: its reference frames, joined) and every observer that estimates the position."""
    truth = res.data["truth"]
    names = list(truth.attrs["names"])
    axes_names = next((ax for ax in _POSITION_AXES if all(a in names for a in ax)), None)
    if axes_names is None:
        return None
    scale = length_scale(res)
    ix = [names.index(a) for a in axes_names]
    st = truth.data["state"][:max_runs][..., ix] * scale
    n_runs = st.shape[0]
    kind = str(res.attrs.get("truth_kind", "simulation"))
    truth_label = "truth" if kind == "simulation" else f"reference ({kind})"
    estimates = [(obs, g) for obs, g in res.data.get("estimates", Group()).data.items()
                 if all(n in list(g.attrs["names"]) for n in axes_names)]
    fig, axs = subplots(1, 2, figsize=(11, 4.2))
    drawn = {}
    for k, (a, b) in enumerate(((2, 0), (2, 1))):
        ax = axs[k]
        for r in range(n_runs):
            fin = np.isfinite(st[r, :, a]) & np.isfinite(st[r, :, b])
            if fin.sum() >= 2:
                (line,) = ax.plot(st[r, fin, a], st[r, fin, b], color=TRUTH_COLOUR, lw=0.9, alpha=0.8,
                                  label=truth_label if truth_label not in drawn else None, gid="truth")
                drawn.setdefault(truth_label, line)
        for obs, g in estimates:
            en = list(g.attrs["names"])
            e = g.data["state"][:max_runs][..., [en.index(n) for n in axes_names]] * scale
            for r in range(e.shape[0]):
                fin = np.isfinite(e[r, :, a]) & np.isfinite(e[r, :, b])
                if fin.sum() >= 2:
                    (line,) = ax.plot(e[r, fin, a], e[r, fin, b], lw=0.8, label=obs if obs not in drawn else None,
                                      **observer_style(obs, n=int(fin.sum())))
                    drawn.setdefault(obs, line)
        ax.set_xlabel(f"{axes_names[a]} [mm]")
        ax.set_ylabel(f"{axes_names[b]} [mm]")
        ax.grid(alpha=0.3)
    if not drawn:
        plt.close(fig)
        raise PlotSkipped("neither the truth nor any estimate has a finite tip position")
    outside_legend(fig, drawn.values(), drawn.keys(), ncol=5)
    fig.suptitle(f"{res.attrs.get('name', '')}: tip paths of the first {n_runs} runs", fontsize=10)
    return save_figure(fig, Path(f"{path_stem}_trajectories.png"))


def draw_plots(res: Group, errors, path_stem: Path, names=None, options: dict | None = None) -> list[Path]:
    """Draw the registered plots (or ``names``) of a results or fit file, with keyword ``options`` per plot
    name; a plot that cannot be drawn is not written, and the log says why, once per plot."""
    import logging

    log = logging.getLogger("needlecli")
    out = []
    for name in names if names is not None else PLOTS.names():
        try:
            p = PLOTS.get(name)(res, errors, path_stem, **((options or {}).get(name) or {}))
        except PlotSkipped as e:
            log.info("plot %s: not written (%s)", name, e)
            continue
        if p is not None:
            log.info("plot: %s", p)
            out.append(p)
    return out
