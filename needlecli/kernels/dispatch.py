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

**A cold cache** (the first run after an install or an edit of a kernel: nothing compiled yet). A command
that knows which kernels it needs asks :func:`cold_start` once, before its work, with what taking the
numpy path instead would cost it. Under ``auto`` and the cold policy ``background`` (the default;
``NEEDLECLI_COLD`` sets it, read in :func:`cold_policy` and nowhere else), when the numpy path costs less
than waiting for the compilation, the command runs on the numpy path (:func:`resolve` answers ``numpy``
for the rest of its work: its numbers are those of ``kernels: numpy``, bit for bit) while a process of its
own compiles the kernels for the next run (:func:`needlecli.kernels.compile_in_background`). Otherwise
(policy ``wait``, ``kernels: numba``, a larger job, or no process to spare) it compiles first and says so
once (:func:`announce`: "compiling kernels, once per install: about N s", N from this machine's own
earlier compilations, else :data:`COMPILE_SECONDS`).

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

import contextlib
import functools
import importlib
import importlib.util
import logging
import os
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass

from needlecli.errors import NeedleError

MODES = ("auto", "numba", "numpy")
ENV = "NEEDLECLI_KERNELS"
#: what ``auto`` does on a cold cache: ``background`` (numpy now, compile for the next run, where that is
#: the quicker) or ``wait`` (compile now: every run's numbers those of the compiled path)
COLD_ENV = "NEEDLECLI_COLD"
COLD_POLICIES = ("background", "wait")
#: the command that compiles the kernels ahead of the runs (README's install step), named where a run waits
AHEAD = "needle kernels compile"

log = logging.getLogger("needlecli")


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
    entry : tuple of str
        ``(module, function)`` of :mod:`needlecli.kernels`: the kernel whose compiled code in the on-disk
        cache says the twin is compiled (the one that takes longest to compile; :func:`cold`).
    """

    name: str
    group: str
    reference: str
    compiled: str
    covers: str
    entry: tuple[str, str]

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
         "their projection (SO(3)), on lanes of states", ("models", "step_fast")),
    Twin("truth", "truth", "needlecli.experiments.simulation.truth:TruthSimulator.advance_to", _K + "truth:TruthKernel",
         "the truth simulation of every run: RK4, process noise, tissue schedules, singular and diverged runs; "
         "closed loops (control:) step the numpy model", ("truth", "advance")),
    Twin("ukf", "observers", "needlecli.observers.ukf:UnscentedKalmanFilter.run", _K + "ukf:filter_runs",
         "the whole filter: predict, multi-rate updates with masks, gates, noise growing with distance, "
         "curvature reset and constraint, status, predictions; numpy: channels with a nonlinear h (tangent, "
         "field direction), in the needle's frame or one-sided, more than 4 channels, models without "
         "compiled equations", ("ukf", "run")),
    Twin("pf", "observers", "needlecli.observers.pf:ParticleFilter._filter", _K + "pf:filter_runs",
         "the particle filters (pf, rbpf) whole: prediction with process noise from the same counter-based draws, "
         "dead particles, the updates (Gaussian, Student-t, gates, noise growing with distance, the Kalman "
         "update of the rbpf's positions), ESS, systematic resampling and roughening, the estimate; numpy: "
         "one-sided channels, h other than a selection or a unit vector of states, more than 4 channels, models "
         "without compiled equations", ("pf", "run")),
    Twin("kalman_forward_affine", "fitting", _NK + "kalman_forward_affine", _K + "kalman:kalman_forward_affine",
         "the affine Kalman filter of an iterated-EKS pass (joseph: false)", ("kalman", "forward_affine")),
    Twin("kalman_loglik_affine", "fitting", _NK + "kalman_loglik_affine", _K + "kalman:kalman_forward_affine",
         "the log-likelihoods of identifiability's evaluation points, on their trial's linearisation read "
         "in place", ("kalman", "forward_affine")),
    Twin("kalman_filter_smoother", "fitting", _NK + "kalman_filter_smoother", _K + "kalman:kalman_filter_smoother",
         "each pass of EM's iterated EKS as one kernel per block of 8 trials: the affine filter, the RTS "
         "smoother, and in the same pass the M-step sums, the smoothed standard deviations and a "
         "finiteness check", ("kalman", "filter_smoother")),
    Twin("rts_smoother", "fitting", _NK + "rts_smoother", _K + "kalman:rts_smoother",
         "the RTS smoother on a filter's output (the eks observer, Joseph-form passes)", ("kalman", "rts")),
    Twin("em_process_noise", "fitting", _NK + "em_process_noise", _K + "kalman:em_process_noise",
         "EM's M-step for Q from stored cross-covariances", ("kalman", "process_noise_sums")),
    Twin("em_measurement_noise", "fitting", _NK + "em_measurement_noise", _K + "kalman:em_measurement_noise",
         "EM's M-step for each R_j from a stored smoother", ("kalman", "measurement_noise_sums")),
    Twin("transition_all", "fitting", "needlecli.fitting.statespace:DiscreteModel.transition_all",
         _K + "kalman:transition_all",
         "RK4 with its exact Jacobian over every tick interval, of models whose compiled equations have "
         "it (mnm, binm) with their constant augmented; numpy: sensor states", ("kalman", "transitions")),
    Twin("transition_one", "fitting", "needlecli.fitting.statespace:DiscreteModel.transition",
         _K + "kalman:transition_one", "the same, one interval (the first EKF pass of EM, the ekf and eks observers)", ("kalman", "transitions")),
    Twin("linearise", "fitting", "needlecli.fitting.statespace:MeasurementModel.linearise", _K + "kalman:linearise",
         "measurement Jacobians by central differences of channels that select states or measure a unit "
         "vector of states (Model.unit_vectors); numpy: whitened, weighted, needle-frame and offset channels", ("kalman", "fd_linearise")),
    Twin("state_errors", "metrics", "needlecli.metrics.errors:compute_errors", _K + "metrics:state_errors",
         "the errors of the tables read in place from the state arrays: position norm, wrapped angles, the "
         "other states", ("metrics", "_state_errors")),
    Twin("rotation_error", "metrics", "needlecli.numerics.rotations:rotation_angle", _K + "metrics:rotation_error",
         "the rotation error E_R from Euler angles without the rotation matrices; numpy: E_h, E_B", ("metrics", "euler_error_angles")),
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


# ---------------------------------------------------------------------------------------------- a cold cache
#: in force while a command runs on the numpy path because its kernels are compiling for the next run
_DEFERRED: list[bool] = [False]
#: the cold policy forced for a block (:func:`compile_now`), innermost last
_POLICY: list[str] = []


def cold_policy() -> str:
    """What ``auto`` does on a cold cache: ``background`` or ``wait`` (:data:`COLD_ENV`, default
    ``background``; ``wait`` inside :func:`compile_now`)."""
    if _POLICY:
        return _POLICY[-1]
    v = os.environ.get(COLD_ENV, "").strip().lower()
    if not v:
        return "background"
    if v not in COLD_POLICIES:
        raise KernelError(f"{COLD_ENV}={v!r}: expected one of {', '.join(COLD_POLICIES)}")
    return v


def deferred() -> bool:
    """Whether this process's command runs on the numpy path while its kernels compile for the next run."""
    return _DEFERRED[0]


def defer(on: bool) -> None:
    """Set by :func:`needlecli.kernels.cold_start` only: ``auto`` resolves to the numpy path while on."""
    _DEFERRED[0] = bool(on)


@contextlib.contextmanager
def compile_now() -> Iterator[None]:
    """Within the block, ``auto`` compiles what it needs (the cold policy ``wait``) and takes the compiled
    path even if the command began on the numpy one: a study whose parts must all take one path (EM's
    iterations, a sweep's cells, the background compilation itself)."""
    before = _DEFERRED[0]
    _POLICY.append("wait")
    _DEFERRED[0] = False
    try:
        yield
    finally:
        _POLICY.pop()
        _DEFERRED[0] = before


#: seconds each entry kernel takes to compile, with the kernels it calls, on the machine of
#: ``docs/benchmarks.md`` (2 cores, one compiling): the estimate a command prints until this machine has
#: compiled that kernel itself (then its own time, :func:`needlecli.kernels._cache.recorded_seconds`)
COMPILE_SECONDS = {
    "models.step_fast": 8.0, "truth.advance": 10.0, "ukf.run": 18.0, "pf.run": 18.0, "metrics._state_errors": 1.0,
    "metrics.euler_error_angles": 2.5, "kalman.filter_smoother": 20.0, "kalman.rts": 20.0,
    "kalman.forward_affine": 4.5, "kalman.transitions": 3.5, "kalman.fd_linearise": 1.5,
    "kalman.process_noise_sums": 2.0, "kalman.measurement_noise_sums": 1.0,
}


def compile_estimate(entries: Iterable[tuple[str, str]]) -> float:
    """Seconds to compile the kernels of ``entries`` (``(module, function)`` pairs) that the cache lacks:
    this machine's own times where it recorded them, else :data:`COMPILE_SECONDS` (5 s for another)."""
    from needlecli.kernels import _cache

    mine = _cache.recorded_seconds()
    todo = {f"{m}.{f}" for m, f in entries if not _cache.cached((m, f))}
    return float(sum(mine.get(k, COMPILE_SECONDS.get(k, 5.0)) for k in todo))


# ---------------------------------------------------------------------------------------------- a command's plan
#: the command's plan for a cold cache (:func:`on_cold`): numpy_seconds, estimate, entries, fn, args, decided
_PLAN: dict = {}
#: the entry kernels asked for by :func:`twin` in this process (a background compilation records those it did
#: not compile as unused by its job: :func:`needlecli.kernels._cache.record_unused`)
REQUESTED: set[tuple[str, str]] = set()


def on_cold(*, entries: Iterable[tuple[str, str] | None] = (), numpy_seconds: float = float("inf"),
            compile_for_next_run: Callable | None = None, args: tuple = ()) -> None:
    """The plan of the command that is starting, for when a twin it asks for is not compiled yet: the
    kernels it probably needs (``entries``, ``(module, function)`` pairs: for the estimate of the
    compilation and its message), what the numpy path would cost it more than the compiled one
    (``numpy_seconds``), and the job that compiles its kernels for the next run (``compile_for_next_run(*args)``,
    e.g. the command on a short copy of its experiment). Decided at the first twin that is not compiled
    (:func:`twin`), once per command: the numpy path for the rest of the command while that job runs in the
    background (:func:`would_defer`), else the compilation now. Clears the numpy path of an earlier
    command of this process."""
    wanted = sorted({e for e in entries if e is not None})
    _DEFERRED[0] = False
    _ANNOUNCED[0] = False
    _PLAN.clear()
    _PLAN.update(numpy_seconds=float(numpy_seconds), entries=wanted, estimate=compile_estimate(wanted),
                 fn=compile_for_next_run, args=tuple(args), decided=False)


def would_defer(setting: str | None) -> bool:
    """Whether the command's plan (:func:`on_cold`) takes the numpy path at its first twin not compiled:
    ``auto``, the cold policy ``background``, a job to compile with, processes that can be forked, and
    the numpy path quicker than the estimated compilation."""
    from needlecli import platform

    return (bool(_PLAN) and _PLAN["fn"] is not None and requested(setting) == "auto"
            and cold_policy() == "background" and _PLAN["numpy_seconds"] < _PLAN["estimate"]
            and platform.fork_available())


def _ready(entry: tuple[str, str]) -> bool:
    from needlecli.kernels import _cache

    return _cache.cached(entry) or entry in _cache.unused()


def _decide(setting: str | None, entry: tuple[str, str]) -> bool:
    """At the first twin of the command that is not compiled: True when the command goes on on the numpy
    path (a background compilation started, or one runs already)."""
    _PLAN["decided"] = True
    if not would_defer(setting):
        return False
    from needlecli.kernels import compile_in_background

    if not compile_in_background(_PLAN["fn"], *_PLAN["args"]):
        return False
    _DEFERRED[0] = True
    log.info("kernels not compiled yet: this run takes the numpy path (the numbers of kernels: numpy) while they "
             "compile in the background for the next run, once per install: about %.0f s (%s=wait compiles "
             "first; %s compiles ahead)", max(1.0, _PLAN["estimate"]), COLD_ENV, AHEAD)
    return True


_ANNOUNCED: list[bool] = [False]


def announce(function: str | None = None) -> None:
    """Say once per command that it waits for a compilation (the first compilation of a kernel in the
    process calls this: :mod:`needlecli.kernels._jit`), and for about how long: the command's planned
    kernels that are not compiled, else ``function`` (``module.function``)."""
    if _ANNOUNCED[0]:
        return
    _ANNOUNCED[0] = True
    entries = list(_PLAN.get("entries", ()))
    if function is not None and "." in function:
        entries.append(tuple(function.split(".", 1)))
    log.info("compiling kernels, once per install: about %.0f s (%s compiles ahead)",
             max(1.0, compile_estimate(entries)), AHEAD)


def resolve(setting: str | None = None) -> str:
    """The path a run takes for ``setting`` (``auto``, ``numba``, ``numpy`` or None for ``auto``):
    ``"numba"`` (compiled twins where they exist) or ``"numpy"`` (the reference everywhere; also ``auto``
    while the command runs on the numpy path during a background compilation, :func:`deferred`).

    Raises
    ------
    KernelError
        An unknown value, or ``numba`` asked for and numba not installed.
    """
    m = requested(setting)
    if m == "numpy" or (m == "auto" and _DEFERRED[0]):
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
    those too (:data:`TWINS` says which). The first twin of a command that is not compiled yet decides the
    command's plan (:func:`on_cold`): None from then on if it goes on on the numpy path."""
    t = TWINS[name]
    if not compiled(setting):
        return None
    REQUESTED.add(t.entry)
    if _PLAN and not _PLAN["decided"] and not _ready(t.entry) and _decide(setting, t.entry):
        return None  # the numpy path while the kernels compile for the next run
    return t.load("compiled")


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
