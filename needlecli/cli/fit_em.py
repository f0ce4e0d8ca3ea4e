"""``needle fit-em CONFIG...``: EM as in the magnetic needle EM paper on every trial of an experiment, for each model to fit."""

from __future__ import annotations

from pathlib import Path

import typer

from needlecli.cli.common import check_results_target, fail, log, progress_bar, setup_logging, user_errors


@user_errors(outputs="each")  # one fit file per source, each kept when complete
def fit_em_cmd(
    sources: list[Path] = typer.Argument(..., metavar="CONFIG_OR_LOG...", help="Experiment configs (.yaml); "
                                         "recorded trials through a config with `source: {logs: [...]}`."),
    model: str = typer.Option(None, "--model", "-m", help="Models to fit, comma-separated: any registered model "
                              "(needle list; e.g. unicycle, mnm), or both: every model of the config's fit.models (the "
                              "default)."),
    out: Path = typer.Option(None, "--out", "-o", help="Fit file (default: results/NAME_fit.h5; one source only)."),
    set_: list[str] = typer.Option([], "--set", help="Override a config key: --set fit.em.max_iter=50"),
    quiet: bool = typer.Option(False, "--quiet", "-q", help="No progress bar or log lines."),
) -> None:
    """Fit, for each model of the config's fit section (or those of --model): the process noise Q of the
    states the section names in q, the noise R_j of each measurement channel, and the model constants in
    fit.constants (default: the model's curvature; any parameter, e.g. kappa and speed_scale of a bevel-tip
    unicycle, c of the MNM), to every trial by EM with the iterated extended Kalman smoother; write the
    fits, smoothed trajectories and convergence histories to one HDF5 file per config (needle evaluate
    FIT.h5 gives its tables).

    Example: needle fit-em configs/tutorials/fit_em.yaml --out results/tutorials/fit_em_fit.h5
    """
    import numpy as np

    from needlecli.errors import shown
    from needlecli.experiments.studies.fit import (
        default_fit_output,
        fit_models_option,
        fit_tree,
        fit_trials,
        load_fit_config,
        load_trials,
    )
    from needlecli.io.results import write_atomic

    setup_logging(quiet)
    if out is not None and len(sources) > 1:
        fail("--out: give one source with --out (each source gets its own fit file)")
    models = fit_models_option(model)
    for src in sources:  # every config and output checked before the first fit
        cfg, _ = load_fit_config(src, overrides=set_)
        check_results_target(cfg, out if out is not None else default_fit_output(cfg), src.parent, what="the fit file")
    for src in sources:
        trials = load_trials(src, overrides=set_)
        cfg = trials.cfg
        target = out if out is not None else default_fit_output(cfg)
        n = trials.truth.states.shape[0]
        log.info("fitting %d trial(s) of %s (%s)", n, cfg.name, "simulated" if trials.simulated else "recorded")
        with progress_bar(not quiet) as bar:
            result = fit_trials(trials, models=models, progress=bar)
            tree = fit_tree(result)
            write_atomic(target, tree, progress=(lambda k, n: bar("fit file", k, n)) if bar else None)
        ids = trials.truth.trial_ids or [f"run {i}" for i in range(n)]
        if not quiet:
            for name, mf in result.fits.items():
                r = mf.result
                st, counts = np.unique(r.status, return_counts=True)
                summary = ", ".join(f"{c} {s}" for s, c in zip(st, counts))
                consts = ", ".join(f"{c} mean {np.nanmean(r.x0[r.status == 'ok', mf.system.dm.nx + i]):.4g}"
                                   for i, c in enumerate(mf.system.dm.augment)) if (r.status == "ok").any() else ""
                typer.echo(f"{name}: {summary}; iterations median {int(np.median(r.iterations))}, "
                           f"max {int(r.iterations.max())}; {consts}; {mf.seconds:.1f} s")
                for s in ("singular", "diverged"):
                    for i in np.nonzero(r.status == s)[0][:5]:
                        typer.echo(f"  trial {ids[i]}: {s}: {r.reason[i]}")
                line = ll_decrease_line(r)
                if line:
                    typer.echo(f"  {line}")
            from needlecli.reports.design import warning_summary

            for line in warning_summary(tree, statuses=False):  # R on its floor, Q nearly singular, kappa < 0
                typer.echo(f"  warning: {line}")
        typer.echo(f"fit: {shown(target)}")


#: a drop of the log-likelihood up to this fraction of the trial's whole rise over the fit is negligible
LL_DROP_NEGLIGIBLE = 0.01


def ll_decrease_line(r) -> str:
    """What the fit's decreases of the log-likelihood beyond numerical noise mean, or "" when there are
    none: how many, in how many trials, and the largest drop against that trial's whole rise over the fit
    (the last log-likelihood minus the first): negligible up to :data:`LL_DROP_NEGLIGIBLE` of it (EM on a
    linearisation that moves between iterations is not exactly monotone), else a step back worth a look.
    ``r``: an :class:`~needlecli.fitting.em.EMResult`."""
    import numpy as np

    dec = np.nonzero(r.ll_decreases > 0)[0]
    if not dec.size:
        return ""
    ll = np.asarray(r.history.get("loglik", np.full((len(r.ll_decreases), 0), np.nan)), dtype=float)
    rise = np.full(len(r.ll_decreases), np.nan)
    for i in dec:  # a loop over the few trials with a decrease, not over runs of a computation
        v = ll[i][np.isfinite(ll[i])] if ll.ndim == 2 and ll.shape[1] else np.zeros(0)
        if v.size > 1:
            rise[i] = v[-1] - v[0]
    with np.errstate(invalid="ignore", divide="ignore"):
        share = np.where(rise[dec] > 0, r.ll_worst_drop[dec] / rise[dec], np.inf)
    k = dec[int(np.argmax(share))]
    head = (f"the log-likelihood decreased beyond numerical noise in {int(r.ll_decreases.sum())} iteration(s) of "
            f"{dec.size} trial(s)")
    worst = float(share.max())
    if np.isfinite(worst) and worst <= LL_DROP_NEGLIGIBLE:
        return (f"{head}; the largest drop is {100 * worst:.2g} % of its trial's rise over the fit "
                f"({r.ll_worst_drop[k]:.3g} of {rise[k]:.4g}): negligible (EM on a moving linearisation is not "
                "exactly monotone)")
    what = f"{100 * worst:.2g} % of its trial's rise over the fit" if np.isfinite(worst) else "more than its trial rose"
    return (f"{head}; the largest drop, {r.ll_worst_drop[k]:.3g}, is {what}: not negligible, look at those trials "
            "(table fit_status, fit file /fit/<model>/history/loglik)")
