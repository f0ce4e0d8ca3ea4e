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

Verdicts, per quantity and trial (and pooled):

``identified``          the relative standard error is at most ``rse_max`` and, for a noise level,
                        scaling it by 10 and by 1/10 each costs at least ``nats`` of log-likelihood;
``weakly identified``   otherwise, with the reason (a relative SE above the threshold; a likelihood that
                        stays within ``nats`` over a decade: the data say little about it; or one that
                        rises by more than ``nats`` over the decade: the estimate is where EM stopped
                        moving or a floor held it, not the likelihood's maximum);
``not identified``      the information in that direction is not positive (a flat or non-concave
                        likelihood at the estimate);
``outside its bounds``  the estimate lies outside the bounds the quantity declares (a constant: its
                        model's parameter schema, e.g. ``speed_scale`` in (0, 2], ``kappa >= 0``; a
                        noise level: ``tr >= 0``): whatever the likelihood's curvature, such a value is
                        not a measurement of the model's constant but a sign that the model does not fit
                        the data (a path recorded in another frame), never "identified".

A stopping rule on relative change can stop in a flat direction: the EM's ``ok`` means the parameters
stopped moving, not that the data determine them; this is what says which do.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from needlecli.fitting.smoother import affine_loglik, eks, linearise, take_linearisation
from needlecli.fitting.statespace import DiscreteModel, MeasurementModel
from needlecli.models.base import state_blocks

IDENTIFIED = "identified"
WEAK = "weakly identified"
NOT_IDENTIFIED = "not identified"
OUTSIDE = "outside its bounds"


@dataclass(frozen=True)
class IdentifyOptions:
    """``rse_max``: largest relative standard error of an identified quantity; ``nats``: the log-likelihood
    a decade of a noise level must cost; ``step_log``: finite-difference step of the log scales; ``chunk``:
    evaluation points per batched filter pass (memory)."""

    rse_max: float = 0.5
    nats: float = 2.0
    step_log: float = 0.2
    chunk: int = 8


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
    """Per trial (leading axis N) and pooled.

    estimate (N, d) the quantities (constants; traces of Q blocks and R_j, not divided by their dimension);
    theta_step (N, d) the finite-difference steps; hessian (N, d, d) of the log-likelihood in theta;
    se (N, d) standard errors in the quantities' units; rse (N, d) relative; decade (N, d, 2) the
    log-likelihood lost when a noise level is multiplied by 10 and by 1/10 (NaN for constants); verdict,
    reason (N, d); pooled_se, pooled_rse (d,), pooled_verdict, pooled_reason (d,) from the summed
    information of the trials in ``used`` (N,).
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
    se = np.where(_is_scale(qs)[None, :], est * se_theta, se_theta)
    with np.errstate(all="ignore"):
        rse = np.abs(se / est)
    verdict, reason = _verdicts(qs, rse, decade, bad, o)
    _mark_outside(qs, est, verdict, reason)
    verdict[~ok], reason[~ok] = "", "trial not assessed (the fit failed)"
    used = ok & np.isfinite(H).all((-1, -2))
    pse, prse, pverdict, preason = _pooled(qs, est, H, decade, used, o)
    return Identifiability(qs, est, h, H, se, rse, decade, verdict, reason, used, pse, prse, pverdict, preason, l0)


def _pooled(qs, est, H, decade, used, o: IdentifyOptions):
    """Pooled SE, relative SE, verdict and reason ``(d,)`` from the summed information of the ``used`` trials."""
    d = len(qs)
    info = -np.nansum(np.where(used[:, None, None], H, 0.0), axis=0)
    pse_theta, pbad = _standard_errors(info[None])
    pest = np.nanmedian(np.where(used[:, None], est, np.nan), axis=0) if used.any() else np.full(d, np.nan)
    pse = np.where(_is_scale(qs), pest * pse_theta[0], pse_theta[0])
    with np.errstate(all="ignore"):
        prse = np.abs(pse / pest)
    pdec = np.nansum(np.where(used[:, None, None], decade, 0.0), axis=0)[None] if used.any() else np.full((1, d, 2), np.nan)
    pverdict, preason = _verdicts(qs, prse[None], pdec, pbad, o)
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
    """The assessment of the trials ``idx`` only: their rows, and the pooled figures from their summed
    information (what :func:`identify` gives on those trials alone: each trial's information is its own)."""
    idx = np.asarray(idx)
    rows = {k: getattr(idf, k)[idx] for k in ("estimate", "theta_step", "hessian", "se", "rse", "decade", "verdict",
                                              "reason", "used", "loglik")}
    pse, prse, pverdict, preason = _pooled(idf.quantities, rows["estimate"], rows["hessian"], rows["decade"],
                                           rows["used"], options)
    return Identifiability(idf.quantities, rows["estimate"], rows["theta_step"], rows["hessian"], rows["se"], rows["rse"],
                           rows["decade"], rows["verdict"], rows["reason"], rows["used"], pse, prse, pverdict, preason,
                           rows["loglik"])


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


def _verdicts(qs, rse, decade, bad, o: IdentifyOptions):
    """Verdicts and reasons ``(M, d)`` (module docstring)."""
    scale = _is_scale(qs)[None, :]
    with np.errstate(invalid="ignore"):
        big = ~(rse <= o.rse_max)
        flat_up, flat_down = ~(decade[..., 0] >= o.nats) & scale, ~(decade[..., 1] >= o.nats) & scale
    weak = (big | flat_up | flat_down) & ~bad
    verdict = np.where(bad, NOT_IDENTIFIED, np.where(weak, WEAK, IDENTIFIED)).astype(object)

    def why(m: int, k: int) -> str:  # the words for one cell
        if bad[m, k]:
            return "no positive information: the log-likelihood is flat or not concave at the estimate"
        parts = [f"relative SE {rse[m, k]:.2g} > {o.rse_max:g}"] if big[m, k] else []
        scaled = [(f, decade[m, k, i]) for i, f, on in ((0, "10", flat_up[m, k]), (1, "1/10", flat_down[m, k])) if on]
        flat = [f"x{f} costs {c:.2g} nats" for f, c in scaled if not c < -o.nats]
        rise = [f"x{f} raises it by {-c:.2g} nats" for f, c in scaled if c < -o.nats]
        if flat:
            parts.append(f"flat over a decade ({'; '.join(flat)}; < {o.nats:g})")
        if rise:  # the estimate is not where the likelihood peaks: EM stopped moving, or a floor holds it
            parts.append(f"not the log-likelihood's maximum ({'; '.join(rise)}: where EM stopped or a floor held it)")
        return "; ".join(parts)

    reason = np.array([[why(m, k) for k in range(rse.shape[1])] for m in range(rse.shape[0])], dtype=object).reshape(rse.shape)
    return verdict, reason
