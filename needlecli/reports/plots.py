"""PNG plots from a results file: error against depth, and trajectories."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from needlecli.io.atomic import atomic_path  # noqa: E402
from needlecli.io.results import Group  # noqa: E402
from needlecli.metrics import ErrorSet, depth_axis  # noqa: E402
from needlecli.reports import PLOTS  # noqa: E402, F401  (the registry of plots; the plots register in it)


def save_figure(fig, path: Path) -> Path:
    """Save a figure as PNG through a temporary file and a rename; close it."""
    try:
        with atomic_path(path) as tmp:
            fig.savefig(tmp, dpi=110, bbox_inches="tight", format="png")
    finally:
        plt.close(fig)
    return path


@PLOTS.register("error_vs_depth")
def error_vs_depth(res: Group, errors: dict[str, ErrorSet], path_stem: Path) -> Path | None:
    """Mean and 5-95 % band of each error quantity against inserted depth, one panel per quantity."""
    from needlecli.reports.tables import order_quantities

    quantities = order_quantities({q for es in errors.values() for q in es.quantities})
    if not quantities:
        return None
    depth = depth_axis(res)  # replayed trials each have their own depth: the axis is their mean
    unit = res.attrs.get("length_unit", "mm")
    fig, axes = plt.subplots(len(quantities), 1, figsize=(7, 2.2 * len(quantities)), sharex=True, squeeze=False)
    for ax, q in zip(axes[:, 0], quantities):
        for obs, es in errors.items():
            if q not in es.quantities or es.quantities[q].values.size == 0:
                continue
            qe = es.quantities[q]
            v = qe.values
            ax.plot(depth, np.nanmean(v, 0), label=obs)
            lo, hi = np.nanpercentile(v, [5, 95], axis=0)
            ax.fill_between(depth, lo, hi, alpha=0.2)
            ax.set_ylabel(f"{q} [{qe.unit}]")
        ax.grid(alpha=0.3)
    axes[0, 0].legend(loc="upper right", fontsize="small")
    axes[-1, 0].set_xlabel(f"inserted depth [{unit}]")
    fig.suptitle(f"{res.attrs.get('name', '')}: error against depth (mean, 5-95 % of runs)")
    return save_figure(fig, Path(f"{path_stem}_error_vs_depth.png"))


@PLOTS.register("trajectories")
def trajectories(res: Group, errors: dict[str, ErrorSet], path_stem: Path, max_runs: int = 10) -> Path | None:
    """Tip paths of the first runs in two projections, truth and every position estimate."""
    truth = res.data["truth"]
    names = list(truth.attrs["names"])
    axes_names = next((ax for ax in (("x", "y", "z"), ("px", "py", "pz")) if all(a in names for a in ax)), None)
    if axes_names is None:
        return None
    ix = [names.index(a) for a in axes_names]
    st = truth.data["state"][:max_runs]
    fig, axs = plt.subplots(1, 2, figsize=(11, 4))
    for k, (a, b) in enumerate(((2, 0), (2, 1))):
        ax = axs[k]
        for r in range(st.shape[0]):
            ax.plot(st[r, :, ix[a]], st[r, :, ix[b]], color="k", lw=0.8, alpha=0.7, label="truth" if r == 0 else None)
        for j, (obs, g) in enumerate(res.data.get("estimates", Group()).data.items()):
            en = list(g.attrs["names"])
            if not all(n in en for n in axes_names):
                continue
            e = g.data["state"][:max_runs]
            ei = [en.index(n) for n in axes_names]
            for r in range(e.shape[0]):
                ax.plot(e[r, :, ei[a]], e[r, :, ei[b]], color=f"C{j}", lw=0.8, ls="--",
                        label=obs if r == 0 else None)
        ax.set_xlabel(axes_names[a])
        ax.set_ylabel(axes_names[b])
        ax.grid(alpha=0.3)
    axs[0].legend(fontsize="small")
    fig.suptitle(f"{res.attrs.get('name', '')}: tip paths of the first {st.shape[0]} runs")
    return save_figure(fig, Path(f"{path_stem}_trajectories.png"))
