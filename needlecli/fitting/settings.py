"""Config schemas of the extended Kalman filter/smoother observers (``ekf``, ``eks``) and of the ``fit:``
section that ``needle fit-em`` reads. Every setting is an explicit, documented key.

Units: process noise as a standard deviation per square-root second (``Q_c = diag(q^2)``, the interval
``dt`` gets ``Q_c dt``), as the truth's ``process_noise``; measurement noise as a standard deviation per
component; ``p0`` and ``floor`` as variances.
"""

from __future__ import annotations

from typing import Literal

from pydantic import Field

from needlecli.initial import InitialEstimate
from needlecli.schema import DistanceGrowth, NonNeg, Positive, Strict


class KalmanInit(InitialEstimate):
    """Initial estimate of ``needle fit-em`` (:class:`~needlecli.initial.InitialEstimate`), from the nominal
    state unless told otherwise: the model's default state with the config's ``model.initial_state``
    (what the experiment commands); ``values`` and ``first_measurement`` may name augmented constants;
    ``std`` gives the default P0 (no noise is drawn in a fit)."""

    from_: Literal["truth", "nominal"] = Field("nominal", alias="from", description=InitialEstimate.model_fields["from_"].description)


class AlongOffset(Strict):
    """An offset of a measured position along the needle's tangent, a state of the sensor that EM
    estimates (``h = p + o t``): the image plane of a 2D transverse ultrasound sits ahead of or behind the
    tip. An Ornstein-Uhlenbeck process of time constant ``tau`` (mean 0: the probe follows the tip; EM fits
    its process noise), or with ``tau: null`` a constant (EM estimates it through the initial state). The
    ``ekf`` and ``eks`` observers carry it as a state too (``from_fit`` gives them the fitted one)."""

    tau: Positive | None = Field(description="time constant of the offset, s; null: a constant")
    sigma: NonNeg = Field(description="std of the offset (model length unit): the process's stationary std "
                          "(EM's initial guess), or a constant's prior std (0: held at value)")
    value: float = Field(0.0, description="initial value (a constant's prior mean), model length unit")


class ChannelNoise(Strict):
    """How a filter treats one measurement channel (a sensor, by name)."""

    sigma: NonNeg | list[NonNeg] | None = Field(
        None, description="noise std per component (R = diag(sigma^2)); default: the sensor's nominal sigma")
    floor: NonNeg | None = Field(None, description="EM: floor on the eigenvalues of R (variance, unit^2)")
    frame: Literal["world", "needle"] = Field(
        "world", description="coordinates of sigma and R: world axes, or (a position) along the needle's tangent, "
        "then across it (needlecli.numerics.needle_frame): a 2D transverse ultrasound's error along the needle is "
        "where its image plane is, across it the image's resolution")
    across_axis: Literal["x", "y", "z"] | None = Field(
        None, description="frame: needle: the world axis a of the across directions e1 = a x t / |a x t|, "
                          "e2 = t x e1 (default: the axis least aligned with the initial tangent)")
    along_offset: AlongOffset | None = Field(
        None, description="a position offset along the needle's tangent, estimated as a state of the sensor")
    student_t: Positive | None = Field(
        None, description="EM: Student-t noise with these degrees of freedom (robust weights in the E-step: "
                          "outliers weigh less); off if unset")
    growth: DistanceGrowth | None = Field(
        None, description="a position's noise growing with the sample's distance to a transducer, sigma (1 + a d / "
                          "d_max) per sample (as the UKF's growth; world axes only)")


Ticks = Literal["grid", "measurements"] | Positive


class KalmanSetup(Strict):
    """What the EKF, the EKS and EM share: the filter's model, its discretisation, initial guesses."""

    model: str | None = Field(None, description="the filter's model (default: the experiment's)")
    params: dict[str, float] = Field(default_factory=dict, description="the filter's model parameters")
    ticks: Ticks = Field("grid", description="where the filter has a state: grid, measurements, or a rate (Hz)")
    substeps: int | None = Field(
        None, ge=1, le=1000,
        description="RK4 steps per tick interval with the interval's mean input (default: one per grid step)")
    q: dict[str, NonNeg] = Field(default_factory=dict, description="process noise std per state, unit/sqrt(s)")
    p0: dict[str, NonNeg] = Field(default_factory=dict, description="initial variance per state (and constant)")
    measurements: dict[str, ChannelNoise] = Field(
        default_factory=dict, description="channels used (default: every channel the model can predict)")
    init: KalmanInit = Field(default_factory=KalmanInit, description="the initial estimate (needlecli.initial): from "
                                                                     "the nominal state unless told otherwise, values, "
                                                                     "first_measurement, std as the default P0")


class EMSettings(Strict):
    """Expectation-maximisation (the magnetic needle EM paper, Algorithm 1)."""

    max_iter: int = Field(100, ge=1, le=10_000, description="EM iterations at most (the magnetic needle EM paper: 100)")
    tol: Positive = Field(1e-3, description="stop when no variance of Q or any R_j changed by more than this "
                          "relative amount (largest |log| eigenvalue of old^-1 new)")
    estep_max: int = Field(10, ge=1, le=1000, description="IEKS passes per E-step at most")
    estep_tol: Positive = Field(0.05, description="the IEKS has settled when x0 and the trajectory move less "
                                "than this many standard deviations")
    update_x0: bool = Field(True, description="x0 <- x_0|N in the E-step (the magnetic needle EM paper)")
    relin_tol: NonNeg = Field(0.5, description="re-linearise when the trajectory moved more than this many "
                              "standard deviations from the last linearisation point (0: every iteration); "
                              "the last E-step is always exact")
    q_floor: NonNeg = Field(0.0, description="floor on the eigenvalues of the fitted Q block, unit^2/s")
    ll_noise: Positive = Field(1e-8, description="a log-likelihood decrease larger than this relative amount "
                               "is reported")
    accelerate: bool = Field(True, description="SQUAREM extrapolation of Q and R_j (log-matrices), with a "
                             "fall-back to the plain EM step when it lowers the likelihood")
    reweight_max: int = Field(50, ge=1, le=1000, description="Student-t channels (measurements.<c>.student_t): "
                              "EM passes at most, each with the robust weights of the previous one")
    reweight_tol: Positive = Field(0.01, description="Student-t channels: stop when no sample's weight moved "
                                   "by more than this (and no R_j by more than tol)")


class IdentifySettings(Strict):
    """What the data identify (:mod:`needlecli.fitting.identify`): standard errors from the observed
    information of the EKF log-likelihood at the fit, and a verdict per quantity."""

    enabled: bool = Field(True, description="assess every fitted quantity after EM (adds about 50 filter passes)")
    rse_max: Positive = Field(0.5, description="largest relative standard error of an identified quantity")
    nats: Positive = Field(2.0, description="log-likelihood a decade of a noise level must cost to be identified")
    z_max: Positive = Field(2.0, description="simulated trials: a design group's mean estimate further than this "
                            "many standard errors from its truth is 'biased' (never 'identified')")


class Regression(Strict):
    """A regression of a fitted constant on a design factor (the fit file's ``fit_regression`` table)."""

    constant: str = Field(description="a fitted constant (kappa, speed_scale, c, ...)")
    factor: str = Field(description="a trial metadata key with numbers (duty_cycle, speed_mm_s, ...)")


class FitDesign(Strict):
    """How ``needle evaluate`` groups and regresses the fitted constants by the trials' metadata (from the
    logs: design factors of a CSV mapping, a data set's speed, ...). Default: every design factor."""

    group_by: list[str] = Field(default_factory=list, description="metadata keys of the fit_by_design table")
    regress: list[Regression] = Field(default_factory=list, description="regressions of fit_regression")


class FitSettings(KalmanSetup):
    """The ``fit:`` section of a config: how ``needle fit-em`` fits every trial.

    The model's constants in ``constants`` (default: its curvature, ``c`` of the MNM, ``l_inv`` of the BiNM,
    ``kappa`` of the unicycle; e.g. ``[kappa, speed_scale]``) are augmented states;
    ``q`` holds the initial guess of the process noise and names the states that have process noise
    (the others' rows and columns of Q stay zero; default: every model state); ``measurements`` the
    initial guesses of each R_j and their floors; ``init.values`` and ``p0`` may name any fitted model's
    states and constants (each model takes those it has).
    """

    models: list[str] = Field(default_factory=lambda: ["mnm", "binm"], min_length=1,
                              description="models fitted by default (needle fit-em --model)")
    hold: list[str] = Field(default_factory=list, description="states whose process noise, and constants, held at "
                            "their initial guess, not fitted (e.g. taken from another fit with from_fit)")
    isotropic: list[str] = Field(
        default_factory=list, description="blocks of Q by their stem (h for hx, hy, hz) fitted as a multiple of the "
        "identity over the block's states with process noise, uncorrelated with the other states: for a unit "
        "vector (the MNM's h and B) the data see only the noise across it, and a free block keeps its variance "
        "along the vector near the initial guess (tr(Q) with it)")
    constants: list[str] | None = Field(
        None, description="model parameters EM estimates as constant states (default: the curvature parameter; "
        "e.g. [kappa, speed_scale] for a needle that slips)")
    design: FitDesign = Field(default_factory=FitDesign, description="tables by the trials' design factors")
    ticks: Ticks = Field("measurements", description="where the filter has a state: grid (every grid step), "
                                                     "measurements (the times of the samples used), or a rate in Hz "
                                                     "plus those times")
    substeps: int | None = Field(1, ge=1, le=1000, description="RK4 steps per tick interval with the interval's mean "
                                                               "input (null: one per grid step)")
    em: EMSettings = Field(default_factory=EMSettings, description="the EM iterations: limits, tolerances, "
                                                                   "acceleration")
    identify: IdentifySettings = Field(default_factory=IdentifySettings, description="standard errors and verdicts")
    store: Literal["full", "diag"] = Field("diag", description="smoothed covariances in the fit file")
    repeats: int = Field(100, ge=1, le=100_000, description="re-simulations per parameter for 'SD as trajectory error'")
