"""The one place that chooses between the numpy reference and a compiled twin, and the table of twins.

A *twin* is a compiled function (numba, :mod:`needlecli.kernels`) that computes what a numpy function of
the package computes, which stays the reference it is tested against. :data:`TWINS` lists every one: its
name, the reference and the compiled function (``module:qualname``, imported only when asked for), and what
it covers (the text of ``needle list`` and of ``docs/guide/kernels.md``).

Which path runs is decided from one explicit setting that the caller passes down from where it comes
from: ``simulation.kernels`` of the config (an observer reads it as ``problem.kernels``, the Kalman passes
of EM as ``DiscreteModel.kernels``), or the config recorded in a results file (``needle evaluate``):

``auto`` (the default)
    the compiled twin where a component has one and numba is installed;
``numba``
    the same, and an error when numba is missing;
``numpy``
    the reference everywhere: numba is never imported.

The environment variable ``NEEDLECLI_KERNELS`` (the same values) overrides the setting, for debugging
without editing a config; it is read here, in :func:`resolve`, and nowhere else.

A caller asks :func:`twin` for the compiled function and runs its reference where it gets None::

    fast = kernels.twin("rts_smoother", setting)
    if fast is not None:
        return SmoothResult(*fast(fwd, state_angles=state_angles))
    ...  # the numpy reference

What else a kernel needs to know about a component is declared by the component: a model's compiled
equations and the state indices they need (:class:`needlecli.models.Model`: ``compiled_equations``,
``compiled_margin``, ``param_states``, ``unit_vectors``), an observer's longest compilation for the
warm-up (``compiled_entry``), read through the registries.

This module is light: it imports neither numba nor a kernel.
"""

from __future__ import annotations

import functools
import importlib
import importlib.util
import os
from collections.abc import Callable
from dataclasses import dataclass

from needlecli.errors import NeedleError

MODES = ("auto", "numba", "numpy")
ENV = "NEEDLECLI_KERNELS"


class KernelError(NeedleError, RuntimeError):
    """A kernels setting that cannot be honoured: an unknown value, or ``numba`` without numba."""


@dataclass(frozen=True)
class Twin:
    """One compiled twin of a numpy function.

    Attributes
    ----------
    name : str
        What callers ask :func:`twin` for.
    group : str
        ``models``, ``truth``, ``observers``, ``fitting`` or ``metrics`` (the sections of ``needle list``).
    reference, compiled : str
        ``module:qualname`` of the numpy reference and of the compiled function a caller is given.
    covers : str
        What the compiled twin covers (and what runs on the numpy path even so).
    """

    name: str
    group: str
    reference: str
    compiled: str
    covers: str

    def load(self, which: str = "compiled") -> Callable:
        """The function ``which`` (``"compiled"`` or ``"reference"``), imported now."""
        module, _, qualname = getattr(self, which).partition(":")
        obj = importlib.import_module(module)
        for part in qualname.split("."):
            obj = getattr(obj, part)
        return obj


_K = "needlecli.kernels."
_NK = "needlecli.numerics.kalman:"

#: every compiled twin, by name
TWINS: dict[str, Twin] = {t.name: t for t in (
    Twin("model_step", "models", "needlecli.models.base:Model.step", _K + "models:step_fast",
         "one RK4 step of the models that declare compiled equations (Model.compiled_equations), with "
         "their projection (SO(3)), on lanes of states"),
    Twin("truth", "truth", "needlecli.experiments.simulation.truth:TruthSimulator.advance_to", _K + "truth:TruthKernel",
         "the truth simulation of every run: RK4, process noise, tissue schedules, singular and diverged runs; "
         "closed loops (control:) step the numpy model"),
    Twin("ukf", "observers", "needlecli.observers.ukf:UnscentedKalmanFilter.run", _K + "ukf:filter_runs",
         "the whole filter: predict, multi-rate updates with masks, gates, noise growing with distance, "
         "curvature reset and constraint, status, predictions; numpy: channels with a nonlinear h (tangent, "
         "field direction), in the needle's frame or one-sided, more than 4 channels, models without "
         "compiled equations"),
    Twin("pf", "observers", "needlecli.observers.pf:ParticleFilter._filter", _K + "pf:filter_runs",
         "the particle filters (pf, rbpf) whole: prediction with process noise from the same counter-based draws, "
         "dead particles, the updates (Gaussian, Student-t, gates, noise growing with distance, the Kalman "
         "update of the rbpf's positions), ESS, systematic resampling and roughening, the estimate; numpy: "
         "one-sided channels, h other than a selection or a unit vector of states, more than 4 channels, models "
         "without compiled equations"),
    Twin("kalman_forward_affine", "fitting", _NK + "kalman_forward_affine", _K + "kalman:kalman_forward_affine",
         "the affine Kalman filter of an iterated-EKS pass (joseph: false)"),
    Twin("kalman_loglik_affine", "fitting", _NK + "kalman_loglik_affine", _K + "kalman:kalman_forward_affine",
         "the log-likelihoods of identifiability's evaluation points, on their trial's linearisation read "
         "in place"),
    Twin("kalman_filter_smoother", "fitting", _NK + "kalman_filter_smoother", _K + "kalman:kalman_filter_smoother",
         "each pass of EM's iterated EKS as one kernel per block of 8 trials: the affine filter, the RTS "
         "smoother, and in the same pass the M-step sums, the smoothed standard deviations and a "
         "finiteness check"),
    Twin("rts_smoother", "fitting", _NK + "rts_smoother", _K + "kalman:rts_smoother",
         "the RTS smoother on a filter's output (the eks observer, Joseph-form passes)"),
    Twin("em_process_noise", "fitting", _NK + "em_process_noise", _K + "kalman:em_process_noise",
         "EM's M-step for Q from stored cross-covariances"),
    Twin("em_measurement_noise", "fitting", _NK + "em_measurement_noise", _K + "kalman:em_measurement_noise",
         "EM's M-step for each R_j from a stored smoother"),
    Twin("transition_all", "fitting", "needlecli.fitting.statespace:DiscreteModel.transition_all",
         _K + "kalman:transition_all",
         "RK4 with its exact Jacobian over every tick interval, of models whose compiled equations have "
         "it (mnm, binm) with their constant augmented; numpy: sensor states"),
    Twin("transition_one", "fitting", "needlecli.fitting.statespace:DiscreteModel.transition",
         _K + "kalman:transition_one", "the same, one interval (the first EKF pass of EM, the ekf and eks observers)"),
    Twin("linearise", "fitting", "needlecli.fitting.statespace:MeasurementModel.linearise", _K + "kalman:linearise",
         "measurement Jacobians by central differences of channels that select states or measure a unit "
         "vector of states (Model.unit_vectors); numpy: whitened, weighted, needle-frame and offset channels"),
    Twin("state_errors", "metrics", "needlecli.metrics.errors:compute_errors", _K + "metrics:state_errors",
         "the errors of the tables read in place from the state arrays: position norm, wrapped angles, the "
         "other states"),
    Twin("rotation_error", "metrics", "needlecli.numerics.rotations:rotation_angle", _K + "metrics:rotation_error",
         "the rotation error E_R from Euler angles without the rotation matrices; numpy: E_h, E_B"),
)}

GROUPS = ("models", "truth", "observers", "fitting", "metrics")


# ---------------------------------------------------------------------------------------------- the choice
@functools.lru_cache(maxsize=1)
def numba_available() -> bool:
    """Whether numba can be imported (looked up, not imported)."""
    return importlib.util.find_spec("numba") is not None


def requested(setting: str | None = None) -> str:
    """The mode asked for: ``NEEDLECLI_KERNELS`` if set, else ``setting``, else ``auto``."""
    env = os.environ.get(ENV, "").strip().lower()
    if env:
        if env not in MODES:
            raise KernelError(f"{ENV}={env!r}: expected one of {', '.join(MODES)}")
        return env
    if setting is None:
        return "auto"
    if setting not in MODES:
        raise KernelError(f"kernels: {setting!r}: expected one of {', '.join(MODES)}")
    return setting


def resolve(setting: str | None = None) -> str:
    """The path a run takes for ``setting`` (``auto``, ``numba``, ``numpy`` or None for ``auto``):
    ``"numba"`` (compiled twins where they exist) or ``"numpy"`` (the reference everywhere).

    Raises
    ------
    KernelError
        An unknown value, or ``numba`` asked for and numba not installed.
    """
    m = requested(setting)
    if m == "numpy":
        return "numpy"
    if numba_available():
        return "numba"
    if m == "numba":
        raise KernelError("compiled kernels asked for (kernels: numba) but numba is not installed: pip install numba")
    return "numpy"


def compiled(setting: str | None = None) -> bool:
    """Whether components with a compiled twin use it (:func:`resolve`)."""
    return resolve(setting) == "numba"


def twin(name: str, setting: str | None) -> Callable | None:
    """The compiled function of twin ``name`` if ``setting`` resolves to compiled kernels, else None (the
    caller runs its numpy reference). Where the twin covers only some configurations the caller checks
    those too (:data:`TWINS` says which)."""
    t = TWINS[name]
    return t.load("compiled") if compiled(setting) else None


# ---------------------------------------------------------------------------------------------- what is compiled
def describe(setting: str | None = None, models: list[str] | None = None) -> list[str]:
    """Lines for ``needle list``: which path a run would take now, and what each twin covers (``models``:
    those with compiled equations, when the caller has loaded them)."""
    try:
        m = requested(setting)
    except KernelError as e:
        m = f"invalid ({e})"
    state = "numba " + ("available" if numba_available() else "NOT installed: every run takes the numpy path")
    lines = [f"kernels: {m} ({ENV} or simulation.kernels: auto | numba | numpy); {state}",
             "  compiled models: " + (", ".join(models) if models is not None
                                      else "those declaring compiled equations (needle list --details names them)")]
    for group in GROUPS:
        for t in TWINS.values():
            if t.group == group:
                lines.append(f"  twin {t.name} ({group}): {t.covers}")
    return lines


def markdown_table() -> str:
    """The twins as a Markdown table (``docs/guide/kernels.md`` holds it; a test checks that it is this)."""
    rows = ["| twin | part | numpy reference | compiled | covers |", "| --- | --- | --- | --- | --- |"]
    for group in GROUPS:
        for t in TWINS.values():
            if t.group == group:
                rows.append(f"| `{t.name}` | {group} | `{t.reference}` | `{t.compiled}` | {t.covers} |")
    return "\n".join(rows)
