r"""What the data identify: a standard error and a verdict for every quantity an EM fit reports.

The quantities of a fit (per trial): each augmented constant (``c`` of the MNM, ``l_inv`` of the BiNM,
the curvature of a unicycle, ...), the trace of each block of ``Q`` that has process noise (states
grouped by their stem: ``px, py, pz -> p``; :func:`~needlecli.models.base.state_blocks`) and the trace of
each channel's ``R``. They are moved through one parameter each,

.. math::

    \theta = (c_1, \dots, c_p,\; s_1, \dots, s_B,\; r_1, \dots, r_J), \qquad
    Q(s) = D(s)\, \hat Q\, D(s), \; D = \mathrm{diag}(e^{s_b/2} \text{ on block } b), \qquad
    R_j(r) = e^{r_j} \hat R_j,

so that ``tr(Q_b)`` and ``tr(R_j)`` scale by ``e^{s_b}`` and ``e^{r_j}`` (correlations kept, every matrix
stays positive definite), and :math:`\ell(\theta)` is the log-likelihood of the trial's measurements under
the model linearised around the fit's smoothed trajectory (the affine model of EM's last E-step, whose
likelihood EM maximises), from the fit's settled initial state (the constants fixed at ``c``: zero
initial variance; their effect enters through the linearisation's Jacobians). The observed information is ``-H``, the Hessian of :math:`\ell` at the estimate by
central finite differences, second order also in the cross terms (every trial and every evaluation
point in one batched filter pass); the standard
error of each parameter is ``sqrt(diag((-H)^{-1}))`` (correlations included), of a trace ``tr * SE(s)``
(delta method). Pooled over trials, the information is summed: the standard error of a quantity the
trials share.

Verdicts, per quantity and trial, and per design group (the trials of one level of the design:
the magnetic needle EM paper's field strength, a real export's speed; pooled figures sum the information of a group's trials only,
never across levels whose quantities differ):

``identified``          the relative standard error is at most ``rse_max`` and, for a noise level,
                        scaling it by 10 and by 1/10 each costs at least ``nats`` of log-likelihood;
``EM stopped short of the maximum``
                        a decade of a noise level raises the log-likelihood by more than ``nats``, or (a
                        group) the mean Newton step of its trials from the estimates to their
                        log-likelihoods' maxima (:func:`newton_steps`, from the same evaluation points)
                        is more than ``z_max`` standard errors of that mean: the estimate is where EM
                        stopped moving, not the likelihood's maximum, and the reason says where that is;
``weakly identified``   otherwise, with the reason (a relative SE above the threshold; a likelihood that
                        stays within ``nats`` over a decade: the data say little about it; a floor that
                        held it; the trace of a unit vector's free process noise that lies mostly along the
                        vector, a direction the data do not see);
``not identified``      the information in that direction is not positive (a flat or non-concave
                        likelihood at the estimate);
``biased``              (groups, where the truth is known: simulated trials) the group's mean estimate
                        misses its truth by more than ``z_max`` standard errors (:func:`recovery`); never
                        "identified", whatever the curvature says (an information-based SE measures the
                        likelihood's curvature, not bias); the reason gives the miss and what the
                        assessment found that explains it.
``outside its bounds``  the estimate lies outside the bounds the quantity declares (a constant: its
                        model's parameter schema, e.g. ``speed_scale`` in (0, 2], ``kappa >= 0``; a
                        noise level: ``tr >= 0``): whatever the likelihood's curvature, such a value is
                        not a measurement of the model's constant but a sign that the model does not fit
                        the data (a path recorded in another frame), never "identified".

A stopping rule on relative change can stop in a flat direction: the EM's ``ok`` means the parameters
stopped moving, not that the data determine them; this is what says which do.
"""

from __future__ import annotations

import warnings
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from needlecli.fitting.smoother import affine_loglik, eks, linearise, take_linearisation
from needlecli.fitting.statespace import DiscreteModel, MeasurementModel
from needlecli.io.fit import BIASED, IDENTIFIED, NOT_IDENTIFIED, OUTSIDE, STOPPED_SHORT, VERDICTS, WEAK, verdict_text
from needlecli.models.base import state_blocks
from needlecli.numerics.recovery import recovery

#: the verdicts (their words are the fit file's: :mod:`needlecli.io.fit`)
__all__ = ["BIASED", "IDENTIFIED", "NOT_IDENTIFIED", "OUTSIDE", "STOPPED_SHORT", "VERDICTS", "WEAK", "recovery",
           "verdict_text"]


@dataclass(frozen=True)
class IdentifyOptions:
    """``rse_max``: largest relative standard error of an identified quantity; ``nats``: the log-likelihood
    a decade of a noise level must cost; ``step_log``: finite-difference step of the log scales; ``chunk``:
    evaluation points per batched filter pass (memory); ``z_max``, ``along_max``: below."""

    rse_max: float = 0.5
    nats: float = 2.0
    step_log: float = 0.2
    chunk: int = 8
    #: largest |estimate - truth| of a group, in standard errors, that is not "biased"
    z_max: float = 2.0
    #: largest fraction of a free unit vector's tr(Q) that may lie along the vector (unseen) for "identified"
    along_max: float = 0.1


@dataclass
class Quantity:
    """One reported quantity: ``kind`` constant | Q | R; ``index`` the state index (constant), the state
    indices of the block (Q), the channel's position (R), or ``(channel, components)`` for a block of a
    channel's R (a needle-frame channel: along, across)."""

    name: str
    kind: str
    index: object
    unit: str
    bounds: Bounds | None = None


@dataclass(frozen=True)
class Bounds:
    """The values a quantity may take: ``low`` to ``high``, each end open (excluded) or not."""

    low: float = -np.inf
    high: float = np.inf
    low_open: bool = False
    high_open: bool = False

    def outside(self, v: np.ndarray) -> np.ndarray:
        """Where finite values ``v`` (any shape) are outside (NaN is not)."""
        v = np.asarray(v, dtype=float)
        with np.errstate(invalid="ignore"):
            below = (v <= self.low) if self.low_open else (v < self.low)
            above = (v >= self.high) if self.high_open else (v > self.high)
        return np.isfinite(v) & (below | above)

    def __str__(self) -> str:
        lo = f"{'(' if self.low_open else '['}{self.low:g}" if np.isfinite(self.low) else "(-inf"
        hi = f"{self.high:g}{')' if self.high_open else ']'}" if np.isfinite(self.high) else "inf)"
        return f"{lo}, {hi}"


#: a noise level (the trace of a block of Q, of R_j): never negative
NOISE_BOUNDS = Bounds(low=0.0)


def parameter_bounds(model_cls, name: str) -> Bounds | None:
    """The bounds a model's parameter ``name`` declares in its schema (``Field(gt=0, le=2)``: (0, 2]), or
    None when it declares none."""
    f = model_cls.Params.model_fields.get(name)
    if f is None:
        return None
    b = {}
    for m in f.metadata:
        for key, side, is_open in (("gt", "low", True), ("ge", "low", False), ("lt", "high", True), ("le", "high", False)):
            v = getattr(m, key, None)
            if v is not None:
                b[side], b[f"{side}_open"] = float(v), is_open
    return Bounds(**b) if b else None


@dataclass
class Identifiability:
    """Per trial (leading axis N), per design group (leading axis G) and pooled over every trial.

    estimate (N, d) the quantities (constants; traces of Q blocks and R_j, not divided by their dimension);
    theta_step (N, d) the finite-difference steps; hessian (N, d, d) of the log-likelihood in theta;
    se (N, d) standard errors in the quantities' units; rse (N, d) relative; decade (N, d, 2) the
    log-likelihood lost when a noise level is multiplied by 10 and by 1/10 (NaN for constants); verdict,
    reason (N, d); pooled_se, pooled_rse (d,), pooled_verdict, pooled_reason (d,) from the summed
    information of the trials in ``used`` (N,) (every trial: kept for older readers; the tables pool
    within groups).

    truth (N, d) the true value where known (simulated trials; NaN otherwise); z (N, d) each trial's
    ``(estimate - truth) / se``; along (N, d) the fraction of a free unit vector's ``tr(Q)`` along the
    vector (NaN for other quantities); floored (N, d) an R on its floor; newton (N, d) the Newton step from
    the estimate to the maximum of the log-likelihood's quadratic model, in the parameters theta (a
    constant's unit; a noise level's log scale: the maximum at ``e^step`` times it); group (N,) each trial's design
    group, ``group_labels`` (G,); group_* (G, d): the median estimate, the SE and relative SE from the
    group's summed information, the mean truth, ``z`` of :func:`recovery`, the mean Newton step and its
    ``z`` (the step in standard errors of that mean), the verdict and reason (module docstring);
    group_trials (G,) the trials assessed per group.
    """

    quantities: list[Quantity]
    estimate: np.ndarray
    theta_step: np.ndarray
    hessian: np.ndarray
    se: np.ndarray
    rse: np.ndarray
    decade: np.ndarray
    verdict: np.ndarray
    reason: np.ndarray
    used: np.ndarray
    pooled_se: np.ndarray
    pooled_rse: np.ndarray
    pooled_verdict: np.ndarray
    pooled_reason: np.ndarray
    loglik: np.ndarray  # (N,) at the estimate
    truth: np.ndarray | None = None
    z: np.ndarray | None = None
    along: np.ndarray | None = None
    floored: np.ndarray | None = None
    newton: np.ndarray | None = None
    group: np.ndarray | None = None
    group_labels: list[str] = field(default_factory=list)
    group_estimate: np.ndarray | None = None
    group_se: np.ndarray | None = None
    group_rse: np.ndarray | None = None
    group_truth: np.ndarray | None = None
    group_z: np.ndarray | None = None
    group_newton: np.ndarray | None = None
    group_newton_z: np.ndarray | None = None
    group_verdict: np.ndarray | None = None
    group_reason: np.ndarray | None = None
    group_trials: np.ndarray | None = None

    @property
    def names(self) -> list[str]:
        return [q.name for q in self.quantities]


def fit_quantities(dm: DiscreteModel, meas: Sequence[MeasurementModel], Q: np.ndarray,
                   held: Sequence[str] = ()) -> list[Quantity]:
    """The quantities of a fit: constants, the Q blocks with process noise (in any trial), each R_j;
    not those ``held`` at their initial guess (constants by name, a Q block when all its states are)."""
    out = [Quantity(c, "constant", dm.nx + i, dm.units[dm.nx + i], parameter_bounds(type(dm.model), c))
           for i, c in enumerate(dm.augment) if c not in held]
    for b, idx in state_blocks(dm.names, skip=dm.augment).items():
        if all(dm.names[i] in held for i in idx):
            continue
        if np.any(Q[:, idx][:, :, idx]):
            unit = dm.units[idx[0]]
            out.append(Quantity(f"tr(Q_{b})", "Q", idx, f"{unit}^2/s" if unit not in ("", "1") else "1/s", NOISE_BOUNDS))
    for j, mm in enumerate(meas):
        unit = mm.units[0] if getattr(mm, "units", None) else ""
        unit = f"{unit}^2" if unit not in ("", "1") else "1"
        if getattr(mm, "frame", "world") == "needle":  # along and across the needle: what the sensor's geometry separates
            out.append(Quantity(f"tr(R_{mm.name}_along)", "R", (j, [0]), unit, NOISE_BOUNDS))
            out.append(Quantity(f"tr(R_{mm.name}_across)", "R", (j, [1, 2]), unit, NOISE_BOUNDS))
        else:
            out.append(Quantity(f"tr(R_{mm.name})", "R", j, unit, NOISE_BOUNDS))
    return out


def _loglik(lin, dm, meas, x0, P0, Q, R, qs: list[Quantity], theta: np.ndarray, trial: np.ndarray,
            rows: np.ndarray | None = None) -> np.ndarray:
    """``l(theta)`` for evaluation points ``theta (M, d)`` of trials ``trial (M,)``, in one filter pass;
    ``rows (M,)``: the rows of ``lin`` and ``meas`` that hold those trials (default ``trial``: all trials)."""
    M = len(trial)
    m0 = x0[trial].copy()
    Qe = Q[trial].copy()
    Re = [r[trial].copy() for r in R]
    for k, q in enumerate(qs):
        if q.kind == "constant":
            m0[:, q.index] = theta[:, k]
        elif q.kind == "Q":
            d = np.ones((M, Qe.shape[-1]))
            d[:, q.index] = np.exp(0.5 * theta[:, k])[:, None]
            Qe = d[:, :, None] * Qe * d[:, None, :]
        elif isinstance(q.index, tuple):  # a block of components of R_j: D R_j D, D = e^(r/2) on the block
            j, comps = q.index
            d = np.ones((M, Re[j].shape[-1]))
            d[:, comps] = np.exp(0.5 * theta[:, k])[:, None]
            Re[j] = d[:, :, None] * Re[j] * d[:, None, :]
        else:
            Re[q.index] = Re[q.index] * np.exp(theta[:, k])[:, None, None]
    with np.errstate(all="ignore"):
        return affine_loglik(lin, dm, meas, m0, P0[trial], Qe, Re, rows=trial if rows is None else rows)


def identify(
    dm: DiscreteModel,
    meas: Sequence[MeasurementModel],
    x0: np.ndarray,
    P0: np.ndarray,
    Q: np.ndarray,
    R: Sequence[np.ndarray],
    ok: np.ndarray,
    const_sd: np.ndarray | None = None,
    options: IdentifyOptions = IdentifyOptions(),
    zbar: np.ndarray | None = None,
    held: Sequence[str] = (),
    *,
    truth: np.ndarray | None = None,
    group: np.ndarray | None = None,
    group_labels: Sequence[str] | None = None,
    floors: Sequence[float | None] = (),
    tied: Sequence[str] = (),
) -> Identifiability:
    """Standard errors and verdicts of every quantity of a fit (module docstring).

    Parameters
    ----------
    dm, meas : the fitted system and its channels (N trials)
    x0 : (N, n) the settled initial state (constants included); P0 : (N, n, n) or (n, n) its prior
    Q : (N, n, n) fitted process noise per second; R : per channel (N, m, m) fitted measurement noise
    ok : (N,) trials to assess (the others get NaN and are left out of the pooled figures)
    const_sd : (N, p) a scale for the finite-difference step of each constant (e.g. its smoothed SD)
    zbar : (N, K+1, n) the trajectory the model is linearised around (the fit's smoothed one; default: an
        extended Kalman smoother's at the estimate)
    held : names of constants and states held at their initial guess (not fitted: not assessed)
    truth : (N, d) the true value of each quantity of :func:`fit_quantities` where known (simulated trials:
        :func:`true_quantities`), NaN elsewhere; None: unknown
    group : (N,) each trial's design group (indices into ``group_labels``); default one group of all trials
    floors : per channel, the floor EM held R_j's eigenvalues at (or None)
    tied : the Q blocks (stems) fitted as ``s I`` (``fit.isotropic``): their part along a unit vector is
        not free
    """
    o = options
    N, n = x0.shape
    P0 = np.array(np.broadcast_to(P0, (N, n, n)), dtype=float)
    for i in range(dm.nx, dm.nx + len(dm.augment)):  # the constants are parameters here: fixed in the filter
        P0[:, i, :] = 0.0
        P0[:, :, i] = 0.0
    if zbar is None:
        with np.errstate(all="ignore"):
            zbar = eks(dm, meas, x0, P0, Q, list(R)).sm.m
    zbar = np.where(np.isfinite(zbar), zbar, 0.0)  # failed trials (not assessed) stay finite
    lin = linearise(dm, meas, zbar)
    qs = fit_quantities(dm, meas, Q, held)
    d = len(qs)
    est = np.full((N, d), np.nan)
    h = np.full((N, d), o.step_log)
    theta0 = np.zeros((N, d))
    for k, q in enumerate(qs):
        if q.kind == "constant":
            c = x0[:, q.index]
            est[:, k] = theta0[:, k] = c
            scale = np.abs(const_sd[:, q.index - dm.nx]) if const_sd is not None else np.zeros(N)
            h[:, k] = np.where(np.isfinite(scale) & (scale > 0), 0.5 * scale, np.maximum(1e-3 * np.abs(c), 1e-9))
        elif q.kind == "Q":
            est[:, k] = np.trace(Q[:, q.index][:, :, q.index], axis1=-2, axis2=-1)
        elif isinstance(q.index, tuple):
            j, comps = q.index
            est[:, k] = np.trace(R[j][:, comps][:, :, comps], axis1=-2, axis2=-1)
        else:
            est[:, k] = np.trace(R[q.index], axis1=-2, axis2=-1)
    # evaluation points: the estimate, +-h_i, +-(h_i + h_j) (i < j), and a decade either way of each noise level
    pts = [np.zeros(d)]
    for i in range(d):
        for sgn in (1.0, -1.0):
            e = np.zeros(d)
            e[i] = sgn
            pts.append(e)
    pairs = [(i, j) for i in range(d) for j in range(i + 1, d)]
    for i, j in pairs:  # (+h_i, +h_j) and (-h_i, -h_j): the cross terms to second order
        for sgn in (1.0, -1.0):
            e = np.zeros(d)
            e[i] = e[j] = sgn
            pts.append(e)
    offsets = np.array(pts)  # in units of h
    decade_pts = []
    for k, q in enumerate(qs):
        if q.kind != "constant":
            for s in (np.log(10.0), -np.log(10.0)):
                e = np.zeros(d)
                e[k] = s
                decade_pts.append(e)
    decade_offsets = np.array(decade_pts).reshape(-1, d)  # absolute (log scale)
    idx = np.nonzero(ok)[0]
    E1, E2 = len(offsets), len(decade_offsets)
    ll = np.full((N, E1 + E2), np.nan)
    if idx.size:
        theta = np.concatenate([
            theta0[idx, None, :] + offsets[None] * h[idx, None, :],
            theta0[idx, None, :] + decade_offsets[None],
        ], axis=1)  # (Nok, E, d)
        E = E1 + E2
        # the points share their trial's linearisation: the assessed trials' rows, read in place
        lin_ok, meas_ok = take_linearisation(lin, idx), [mm.take(idx) for mm in meas]
        for a in range(0, E, o.chunk):
            sl = slice(a, min(a + o.chunk, E))
            te = theta[:, sl]
            trial = np.repeat(idx, te.shape[1])
            rows = np.repeat(np.arange(idx.size), te.shape[1])
            ll[idx, sl] = _loglik(lin_ok, dm, meas_ok, x0, P0, Q, R, qs, te.reshape(-1, d), trial,
                                  rows).reshape(len(idx), -1)
    l0 = ll[:, 0]
    lp, lm = ll[:, 1 : 1 + 2 * d : 2], ll[:, 2 : 2 + 2 * d : 2]
    H = np.full((N, d, d), np.nan)
    H[:, np.arange(d), np.arange(d)] = (lp - 2.0 * l0[:, None] + lm) / h**2
    for p, (i, j) in enumerate(pairs):
        lpp, lmm = ll[:, 1 + 2 * d + 2 * p], ll[:, 2 + 2 * d + 2 * p]
        H[:, i, j] = H[:, j, i] = (lpp + lmm - lp[:, i] - lm[:, i] - lp[:, j] - lm[:, j] + 2.0 * l0) / (2.0 * h[:, i] * h[:, j])
    decade = np.full((N, d, 2), np.nan)
    c = 0
    for k, q in enumerate(qs):
        if q.kind != "constant":
            decade[:, k, 0] = l0 - ll[:, E1 + c]
            decade[:, k, 1] = l0 - ll[:, E1 + c + 1]
            c += 2
    se_theta, bad = _standard_errors(-H)
    newton = newton_steps(-H, (lp - lm) / (2.0 * h))
    se = np.where(_is_scale(qs)[None, :], est * se_theta, se_theta)
    with np.errstate(all="ignore"):
        rse = np.abs(se / est)
    along = along_fraction(dm, qs, Q, zbar, tied)
    floored = on_floor(qs, R, floors)
    verdict, reason = _verdicts(qs, rse, decade, bad, o, floored=floored, along=along)
    _mark_outside(qs, est, verdict, reason)
    verdict[~ok], reason[~ok] = "", "trial not assessed (the fit failed)"
    used = ok & np.isfinite(H).all((-1, -2))
    pse, prse, pverdict, preason = _pooled(qs, est, H, decade, used, o)
    truth = np.full((N, d), np.nan) if truth is None else np.asarray(truth, dtype=float)
    with np.errstate(all="ignore"):
        z = (est - truth) / se
    idf = Identifiability(qs, est, h, H, se, rse, decade, verdict, reason, used, pse, prse, pverdict, preason, l0,
                          truth=truth, z=z, along=along, floored=floored, newton=newton)
    return with_groups(idf, np.zeros(N, dtype=np.int64) if group is None else group,
                       ["all trials"] if group_labels is None else group_labels, o)


def _pooled(qs, est, H, decade, used, o: IdentifyOptions, floored=None, along=None):
    """Pooled SE, relative SE, verdict and reason ``(d,)`` from the summed information of the ``used`` trials
    (``floored``, ``along``: per trial, :func:`on_floor` and :func:`along_fraction`; any trial on its floor
    counts, the median fraction along a unit vector)."""
    d = len(qs)
    info = -np.nansum(np.where(used[:, None, None], H, 0.0), axis=0)
    pse_theta, pbad = _standard_errors(info[None])
    pest = np.nanmedian(np.where(used[:, None], est, np.nan), axis=0) if used.any() else np.full(d, np.nan)
    pse = np.where(_is_scale(qs), pest * pse_theta[0], pse_theta[0])
    with np.errstate(all="ignore"):
        prse = np.abs(pse / pest)
    pdec = np.nansum(np.where(used[:, None, None], decade, 0.0), axis=0)[None] if used.any() else np.full((1, d, 2), np.nan)
    pfl = None if floored is None else (floored & used[:, None]).any(0)[None]
    pal = None
    if along is not None and used.any():
        with np.errstate(all="ignore"), warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # a quantity without a fraction: all NaN
            pal = np.nanmedian(np.where(used[:, None], along, np.nan), axis=0)[None]
    pverdict, preason = _verdicts(qs, prse[None], pdec, pbad, o, floored=pfl, along=pal)
    _mark_outside(qs, pest[None], pverdict, preason)
    return pse, prse, pverdict[0], preason[0]


def _mark_outside(qs: list[Quantity], est: np.ndarray, verdict: np.ndarray, reason: np.ndarray) -> None:
    """The estimates ``est (M, d)`` outside their quantity's bounds get the verdict :data:`OUTSIDE` (in place,
    whatever the likelihood says), with the value and the bounds as the reason."""
    for k, q in enumerate(qs):
        if q.bounds is None:
            continue
        for m in np.flatnonzero(q.bounds.outside(est[:, k])):
            verdict[m, k] = OUTSIDE
            reason[m, k] = (f"{q.name} = {est[m, k]:.4g} is outside its bounds {q.bounds}: not a value of the "
                            "model's constant (does the model fit these data? a path recorded in another frame?)")


def take_trials(idf: Identifiability, idx: np.ndarray, options: IdentifyOptions = IdentifyOptions()) -> Identifiability:
    """The assessment of the trials ``idx`` only: their rows, and the pooled and group figures from their
    summed information (what :func:`identify` gives on those trials alone: each trial's information is
    its own)."""
    idx = np.asarray(idx)
    rows = {k: getattr(idf, k)[idx] for k in ("estimate", "theta_step", "hessian", "se", "rse", "decade", "verdict",
                                              "reason", "used", "loglik", "truth", "z", "along", "floored",
                                              "newton")}
    pse, prse, pverdict, preason = _pooled(idf.quantities, rows["estimate"], rows["hessian"], rows["decade"],
                                           rows["used"], options)
    sub = Identifiability(idf.quantities, rows.pop("estimate"), rows.pop("theta_step"), rows.pop("hessian"),
                          rows.pop("se"), rows.pop("rse"), rows.pop("decade"), rows.pop("verdict"), rows.pop("reason"),
                          rows.pop("used"), pse, prse, pverdict, preason, rows.pop("loglik"), **rows)
    return with_groups(sub, idf.group[idx], idf.group_labels, options)


# ---------------------------------------------------------------------------------------------- groups
def with_groups(idf: Identifiability, group: np.ndarray, labels: Sequence[str],
                o: IdentifyOptions = IdentifyOptions()) -> Identifiability:
    """``idf`` with its figures per design group (:class:`Identifiability`'s ``group_*``): each group's
    information summed over its assessed trials only, where its log-likelihoods peak (:func:`newton_steps`),
    its recovery (:func:`~needlecli.numerics.recovery.recovery`) where the truth is known, and its verdict
    (module docstring). Groups without a trial keep their label and NaN figures."""
    qs = idf.quantities
    group = np.asarray(group, dtype=np.int64)
    G, d = len(labels), len(qs)
    est = np.full((G, d), np.nan)
    gse, grse, gtruth, gz, gnewton, gnewton_z = (np.full((G, d), np.nan) for _ in range(6))
    gverdict = np.full((G, d), "", dtype=object)
    greason = np.full((G, d), "no trial assessed", dtype=object)
    n = np.zeros(G, dtype=np.int64)
    scale = _is_scale(qs)
    for g in range(G):
        sel = idf.used & (group == g)
        n[g] = sel.sum()
        if not n[g]:
            continue
        est[g] = np.nanmedian(np.where(sel[:, None], idf.estimate, np.nan), axis=0)
        gse[g], grse[g], info_v, info_r = _pooled(qs, idf.estimate, idf.hessian, idf.decade, sel, o,
                                                  floored=idf.floored, along=idf.along)
        gtruth[g], _, _, gz[g] = recovery(idf.estimate[sel], idf.se[sel], idf.truth[sel])
        if idf.newton is not None:  # the mean step to the maximum, in SE of that mean (a truth of no step)
            with np.errstate(all="ignore"):
                se_theta = np.where(scale[None, :], idf.se / idf.estimate, idf.se)[sel]
            _, gnewton[g], _, gnewton_z[g] = recovery(idf.newton[sel], se_theta, np.zeros_like(se_theta))
        floored = idf.floored[sel].any(0) if idf.floored is not None else np.zeros(d, dtype=bool)
        for k in range(d):
            v, r = _with_newton(qs[k], info_v[k], info_r[k], gnewton[g, k], gnewton_z[g, k], int(n[g]), o,
                                bool(floored[k]))
            gverdict[g, k], greason[g, k] = _with_recovery(v, r, idf, sel, k, gz[g, k], gnewton[g, k], o)
        _mark_outside(qs, est[g : g + 1], gverdict[g : g + 1], greason[g : g + 1])  # whatever else was found
    idf.group, idf.group_labels = group, [str(x) for x in labels]
    idf.group_estimate, idf.group_se, idf.group_rse, idf.group_truth, idf.group_z = est, gse, grse, gtruth, gz
    idf.group_newton, idf.group_newton_z = gnewton, gnewton_z
    idf.group_verdict, idf.group_reason, idf.group_trials = gverdict, greason, n
    return idf


def _peak(q: Quantity, shift: float) -> str:
    """Where a log-likelihood peaks, from the estimate: ``x0.83 of the estimate`` or ``+0.2 1/m from it``."""
    return f"x{np.exp(shift):.2g} of the estimate" if q.kind != "constant" else f"{shift:+.3g} {q.unit} from the estimate"


def _with_newton(q: Quantity, verdict: str, reason: str, shift: float, z: float, n: int,
                 o: IdentifyOptions, floored: bool = False) -> tuple[str, str]:
    """A group's verdict once the distance to the likelihood's maximum is in: where the mean Newton step of
    its trials lies more than ``z_max`` standard errors of that mean from the estimate, "EM stopped short
    of the maximum", with where the maximum is. Not for a noise level whose step leaves the decade either
    way (the quadratic model is out of its range there; the decade test, which evaluates the likelihood
    at x10 and x1/10, decides), nor below a floor that held it (then: held by its floor)."""
    if not (np.isfinite(z) and abs(z) > o.z_max) or verdict == NOT_IDENTIFIED:
        return verdict, reason
    if q.kind != "constant" and abs(shift) > np.log(10.0):
        return verdict, reason
    words = f"the log-likelihood peaks at {_peak(q, shift)} (Newton step, {z:+.1f} SE over {n} trials)"
    if floored and shift < 0:
        if "floor" in reason:
            return verdict, reason
        return (WEAK if verdict == IDENTIFIED else verdict,
                "; ".join(r for r in (reason, f"held by its floor ({words}, below it)") if r))
    return STOPPED_SHORT, "; ".join(r for r in (words, reason if verdict != IDENTIFIED else "") if r)


def _with_recovery(verdict: str, reason: str, idf: Identifiability, sel: np.ndarray, k: int, z: float,
                   shift: float, o: IdentifyOptions) -> tuple[str, str]:
    """A group's verdict and reason once its recovery check is in: ``biased`` beyond ``z_max``, with the
    miss and what the assessment measured as its cause (EM stopped short: the Newton step to the
    likelihood's maximum covers the miss; a floor; a unit vector's unseen part), else the information's
    verdict."""
    if not (np.isfinite(z) and abs(z) > o.z_max):
        return verdict, reason
    q = idf.quantities[k]
    e = idf.estimate[sel, k]
    t = idf.truth[sel, k]
    fin = np.isfinite(e) & np.isfinite(t)
    em, tm = float(np.mean(e[fin])), float(np.mean(t[fin]))
    miss = em - tm
    pct = f", {100.0 * miss / tm:+.0f} % of the truth {tm:.3g}" if tm else ""
    parts = [f"estimate - truth = {z:+.1f} SE ({miss:+.3g}{pct}, {int(fin.sum())} trials)"]
    if verdict != IDENTIFIED:
        parts.append(f"{verdict}: {reason}" if reason else verdict)
    with np.errstate(all="ignore"):
        to_truth = np.log(tm / em) if q.kind != "constant" else tm - em  # the step that would reach the truth
        covered = shift / to_truth
    if np.isfinite(covered):
        where = "" if verdict == STOPPED_SHORT else f"the log-likelihood peaks at {_peak(q, shift)} (Newton step); "
        parts.append(f"{where}the step goes {100.0 * covered:.0f} % of the way to the truth: " +
                     ("the likelihood's maximum lies near the truth, EM stopped short of it" if covered >= 0.5
                      else "the likelihood's maximum itself misses the truth"))
    floored = idf.floored[sel, k] if idf.floored is not None else np.zeros(0, dtype=bool)
    if floored.any() and "floor" not in reason:
        parts.append(f"on its floor in {int(floored.sum())} of {int(sel.sum())} trials: the floor cuts the "
                     "estimates from below")
    return BIASED, "; ".join(parts)


# ---------------------------------------------------------------------------------------------- causes
def along_fraction(dm: DiscreteModel, qs: list[Quantity], Q: np.ndarray, zbar: np.ndarray,
                   tied: Sequence[str] = ()) -> np.ndarray:
    """``(N, d)``: for each Q block that is one of the model's unit vectors (``unit_vectors``: the MNM's
    heading and field) fitted free (not in ``tied``), the fraction of its trace along the vector, averaged
    over the trajectory ``zbar (N, K+1, n)``: ``mean_k u_k^T Q_b u_k / tr(Q_b)``. The model holds the
    vector's length and the data see directions only: that part of the trace is not measured (it stays
    near EM's initial guess). NaN for every other quantity."""
    N = Q.shape[0]
    out = np.full((N, len(qs)), np.nan)
    vectors = getattr(dm.model, "unit_vectors", {}) or {}
    for k, q in enumerate(qs):
        if q.kind != "Q" or q.name[len("tr(Q_"):-1] in tied:
            continue
        names = {dm.names[i] for i in q.index}
        if not any(names == set(v) for v in vectors.values()):
            continue
        idx = list(q.index)
        u = zbar[..., idx]
        with np.errstate(all="ignore"):
            u = u / np.linalg.norm(u, axis=-1, keepdims=True)
            Qb = Q[:, idx][:, :, idx]
            along = np.einsum("nki,nij,nkj->nk", u, Qb, u).mean(-1)
            out[:, k] = along / np.trace(Qb, axis1=-2, axis2=-1)
    return out


def on_floor(qs: list[Quantity], R: Sequence[np.ndarray], floors: Sequence[float | None], tol: float = 1e-3) -> np.ndarray:
    """``(N, d)``: an R quantity whose channel has an eigenvalue on its floor (within ``tol``)."""
    N = R[0].shape[0] if len(R) else 0
    out = np.zeros((N, len(qs)), dtype=bool)
    for k, q in enumerate(qs):
        if q.kind != "R":
            continue
        j = q.index[0] if isinstance(q.index, tuple) else q.index
        fl = floors[j] if j < len(floors) else None
        if fl is None or not fl > 0:
            continue
        Rj = np.asarray(R[j], dtype=float)
        fin = np.isfinite(Rj).all((-1, -2))
        w = np.full(Rj.shape[:-1], np.inf)
        if fin.any():
            w[fin] = np.linalg.eigvalsh(Rj[fin])
        out[:, k] = (w <= fl * (1.0 + tol)).any(-1)
    return out


def _is_scale(qs: list[Quantity]) -> np.ndarray:
    return np.array([q.kind != "constant" for q in qs])


def _standard_errors(info: np.ndarray, flat: float = 1e-10) -> tuple[np.ndarray, np.ndarray]:
    """``sqrt(diag(info^-1))`` for informations ``(M, d, d)``, and the parameters that lie mostly in
    directions without positive information (eigenvalues at most ``flat`` times the largest): NaN
    standard errors there, the others from the pseudo-inverse over the informative directions."""
    M, d, _ = info.shape
    se = np.full((M, d), np.nan)
    bad = np.ones((M, d), dtype=bool)
    finite = np.isfinite(info).all((-1, -2))
    if finite.any():
        w, V = np.linalg.eigh(0.5 * (info[finite] + np.swapaxes(info[finite], -1, -2)))
        pos = w > flat * np.maximum(w[:, -1:], 0.0)
        inv_w = np.where(pos, 1.0 / np.where(pos, w, 1.0), 0.0)
        var = np.einsum("mkj,mj,mkj->mk", V, inv_w, V)
        weak = np.einsum("mkj,mj->mk", V**2, (~pos).astype(float)) > 0.5
        se[finite] = np.where(weak, np.nan, np.sqrt(np.maximum(var, 0.0)))
        bad[finite] = weak
    return se, bad


def newton_steps(info: np.ndarray, grad: np.ndarray, flat: float = 1e-10) -> np.ndarray:
    """Newton steps ``info^-1 grad`` ``(M, d)`` from the estimates to the maxima of the log-likelihoods'
    quadratic models (``info (M, d, d)`` minus the Hessians, ``grad (M, d)`` the gradients), over the
    directions with positive information only (the pseudo-inverse of :func:`_standard_errors`); NaN where
    the information is not finite. At a maximum the step is zero; where EM stopped short of it, the step
    says where the maximum lies."""
    M, d = grad.shape
    out = np.full((M, d), np.nan)
    finite = np.isfinite(info).all((-1, -2)) & np.isfinite(grad).all(-1)
    if finite.any():
        w, V = np.linalg.eigh(0.5 * (info[finite] + np.swapaxes(info[finite], -1, -2)))
        pos = w > flat * np.maximum(w[:, -1:], 0.0)
        inv_w = np.where(pos, 1.0 / np.where(pos, w, 1.0), 0.0)
        out[finite] = np.einsum("mkj,mj,mlj,ml->mk", V, inv_w, V, grad[finite])
    return out


def _verdicts(qs, rse, decade, bad, o: IdentifyOptions, floored=None, along=None):
    """Verdicts and reasons ``(M, d)`` (module docstring); ``floored`` (M, d): an R on its floor (a rise at
    x1/10 is then the floor's doing, not EM's); ``along`` (M, d): :func:`along_fraction`."""
    scale = _is_scale(qs)[None, :]
    floored = np.zeros(rse.shape, dtype=bool) if floored is None else np.asarray(floored, dtype=bool)
    along = np.full(rse.shape, np.nan) if along is None else np.asarray(along, dtype=float)
    with np.errstate(invalid="ignore"):
        big = ~(rse <= o.rse_max)
        flat_up, flat_down = ~(decade[..., 0] >= o.nats) & scale, ~(decade[..., 1] >= o.nats) & scale
        rise_up, rise_down = (decade[..., 0] < -o.nats) & scale, (decade[..., 1] < -o.nats) & scale
        unseen = along > o.along_max
    stopped = (rise_up | (rise_down & ~floored)) & ~bad
    weak = (big | flat_up | flat_down | unseen) & ~bad & ~stopped
    verdict = np.where(bad, NOT_IDENTIFIED, np.where(stopped, STOPPED_SHORT, np.where(weak, WEAK, IDENTIFIED))).astype(object)

    def why(m: int, k: int) -> str:  # the words for one cell
        if bad[m, k]:
            return "no positive information: the log-likelihood is flat or not concave at the estimate"
        parts = [f"relative SE {rse[m, k]:.2g} > {o.rse_max:g}"] if big[m, k] else []
        scaled = [(f, decade[m, k, i]) for i, f, on in ((0, "10", flat_up[m, k]), (1, "1/10", flat_down[m, k])) if on]
        flat = [f"x{f} costs {c:.2g} nats" for f, c in scaled if not c < -o.nats]
        rise = [(f, -c) for f, c in scaled if c < -o.nats]
        if flat:
            parts.append(f"flat over a decade ({'; '.join(flat)}; < {o.nats:g})")
        held = [f"x{f} raises it by {c:.2g} nats" for f, c in rise if f == "1/10" and floored[m, k]]
        short = [f"x{f} raises it by {c:.2g} nats" for f, c in rise if not (f == "1/10" and floored[m, k])]
        if short:  # the estimate is not where the likelihood peaks: EM stopped moving there
            parts.append(f"not the log-likelihood's maximum ({'; '.join(short)})")
        if held:
            parts.append(f"held by its floor ({'; '.join(held)})")
        if unseen[m, k]:
            parts.append(f"{100.0 * along[m, k]:.0f} % of its trace lies along the unit vector, which the data do not "
                         "see (the model holds its length): that part stays near EM's initial guess (fit.isotropic "
                         "ties it to the directions across)")
        return "; ".join(parts)

    reason = np.array([[why(m, k) for k in range(rse.shape[1])] for m in range(rse.shape[0])], dtype=object).reshape(rse.shape)
    return verdict, reason
