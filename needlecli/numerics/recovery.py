"""The recovery check of estimates whose truth is known (a simulated study): how far their mean lies from
the truth, in standard errors of that mean. Shared by the verdicts of a fit
(:mod:`needlecli.fitting.identify`) and the tables that pool several fit files (seeds) of one study."""

from __future__ import annotations

import numpy as np


def recovery(est: np.ndarray, se: np.ndarray, truth: np.ndarray) -> tuple[np.ndarray, ...]:
    r"""The recovery check of trials whose truth is known, per quantity: how far the mean estimate lies
    from the truth, in standard errors of that mean.

    With ``e_i = estimate_i - truth_i`` over the trials where both are finite (n of them), the miss is
    :math:`\bar e` and its standard error the larger of the two a reader could take: the trials' spread,
    ``SD(e) / sqrt(n)`` (n >= 2; Monte-Carlo, whatever the per-trial SEs say), and their information,
    ``sqrt(sum se_i^2) / n`` (the SE of a mean of independent estimates with those SEs). A bias is so
    claimed only when both see it; ``z = e_bar / SE``. Trials of several seeds of one design level are
    pooled by passing them together.

    Parameters
    ----------
    est, se, truth : (n_trials, d) estimates, their standard errors, the true values (NaN: unknown)

    Returns
    -------
    mean_truth, miss, se_of_mean, z : (d,) each, NaN where no trial has a truth
    """
    est, se, truth = (np.asarray(a, dtype=float) for a in (est, se, truth))
    e = est - truth
    fin = np.isfinite(e)
    n = fin.sum(0)
    with np.errstate(all="ignore"):
        mean_truth = np.where(fin, truth, 0.0).sum(0) / n
        miss = np.where(fin, e, 0.0).sum(0) / n
        spread = np.where(n >= 2, np.sqrt((np.where(fin, e - miss, 0.0) ** 2).sum(0) / (n - 1) / n), np.nan)
        s2 = np.where(fin, se**2, 0.0)
        info = np.where((np.isfinite(se) | ~fin).all(0), np.sqrt(s2.sum(0)) / n, np.nan)
        sem = np.fmax(spread, info)
        z = np.where(sem > 0, miss / sem, np.where(miss == 0, 0.0, np.nan))
    return mean_truth, miss, sem, z
