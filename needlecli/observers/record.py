"""What every observer's ``run`` keeps besides its maths: :class:`RunRecorder`.

An observer estimates; the recorder keeps the estimates on the problem's time grid, the covariances the
results file stores, the status of every run and the counters, and builds the :class:`Posterior`. It works
on all runs at once (``N`` runs, ``T`` grid steps, ``n`` recorded states). The built-in observers use it;
a plug-in observer uses it the same way and writes only its maths::

    rec = RunRecorder(problem, n, progress=progress)
    rec.record(0, x, P)                                   # the initial estimate, grid step 0
    for k in range(1, T):                                 # or any increasing filter ticks
        xn, Pn = my_step(x, P, ...)
        rec.check(k, xn, Pn, max_trace=1e8)               # non-finite or exploding: the run stops
        x, P = rec.hold(xn, x), rec.hold(Pn, P)           # a stopped run keeps its last good estimate
        rec.record(k, x, P)                               # grid steps since the last tick hold it
    return rec.posterior(names, units)

The contract:

- **Estimates.** :meth:`record` takes the estimate ``x (N, n)`` (and ``P (N, n, n)``) at grid step ``k``:
  the first at step 0, then at increasing steps (filter ticks). The grid steps between two records hold
  the earlier one (nothing is known before the tick that estimates it), and those after the last record
  hold it. Covariances are kept at grid steps ``0, s, 2s, ...`` (``problem.cov_stride``) in
  ``problem.cov_layout`` (``full``: ``(N, T', n, n)``; ``diag``: ``(N, T', n)``; ``none``: not kept),
  ``T' = ceil(T / s)``; an observer without a covariance says ``covariance=False``. Named per-step
  ``series`` (one value per run and step, e.g. a mode flag) are recorded and held the same way.
- **Whole trajectories.** An observer that estimates all ticks at once (a smoother) gives them to
  :meth:`record_all`; arrays a compiled kernel filled in the same shapes are taken by :meth:`adopt`.
- **Stopped runs.** :meth:`stop` gives the alive runs of a mask a status (``diverged``, ``singular``,
  ``unobservable``) and a reason; ``{t}`` in the reason, with an optional format (``{t:.2f}``), becomes
  the time of the grid step of the event, in s. The run is then no longer ``alive`` (a boolean ``(N,)``
  array updated in place, so that a reference to it stays current). :meth:`check` is the usual test:
  a finite estimate that left the model's domain is singular, a non-finite estimate or covariance trace,
  or a trace above ``max_trace``, diverged. :meth:`hold` keeps a stopped run's last good value;
  :meth:`stop_first` and :meth:`hold_from` do the same on whole trajectories.
- **Counters and extras.** :meth:`counter` gives an ``(N,)`` integer array stored under its name among
  the Posterior's extras (add to it in place); ``extras`` takes any further named array.
- **Progress.** With ``progress``, :meth:`record` reports ``progress(k, T - 1)`` about every 1 % of the grid
  (:meth:`posterior` the end, when the last record held to it).
- **The result.** :meth:`posterior` builds the :class:`Posterior` with the recorded arrays, the status and
  reason per run, the names, units and angle states of the recorded states, the extras and attributes.
"""

from __future__ import annotations

import re
from collections.abc import Callable, Mapping, Sequence

import numpy as np

from needlecli.observers.base import (
    STATUS_DIVERGED,
    STATUS_OK,
    STATUS_SINGULAR,
    EstimationProblem,
    Posterior,
    cov_steps,
    shrink_cov,
)

_TIME = re.compile(r"\{t(:[^{}]*)?\}")


def event_reason(reason: str, t: float) -> str:
    """``reason`` with each ``{t}`` (or ``{t:<format>}``, e.g. ``{t:.2f}``) replaced by the time ``t``;
    other braces are left as they are (a model's text may hold them)."""
    return _TIME.sub(lambda m: format(t, (m.group(1) or ":")[1:]), reason)


class RunRecorder:
    """The bookkeeping of an observer's run over ``N`` runs at once (module docstring for the contract).

    Parameters
    ----------
    problem : EstimationProblem
        Gives the time grid ``(T,)``, the number of runs ``N`` and the covariances to keep
        (``cov_stride``, ``cov_layout``).
    n : int
        Number of recorded states (the columns of ``x``).
    covariance : bool
        Whether the observer has a covariance to record (False: the Posterior has none, whatever the layout).
    series : mapping of name to dtype, optional
        Further per-step values, ``(N,)`` at each record, kept as ``(N, T)`` arrays in :attr:`series`.
    progress : callable ``(done, total)``, optional
        Told about every 1 % of the grid steps recorded.

    Attributes
    ----------
    states : (N, T, n) ndarray
    cov : (N, T', n, n) or (N, T', n) ndarray, or None
    cov_index : (T',) ndarray
        The grid steps at which covariances are kept.
    status, reason : (N,) object ndarray
        ``ok`` and ``""`` until a run stops.
    alive : (N,) bool ndarray
        Runs not stopped; updated in place.
    event : (N,) int ndarray
        The grid step at which a run stopped (-1: it did not, or its event has no time).
    extras : dict of str to ndarray
        Counters and further arrays, stored under the observer's group.
    """

    def __init__(self, problem: EstimationProblem, n: int, *, covariance: bool = True,
                 series: Mapping[str, type | np.dtype] | None = None,
                 progress: Callable[[int, int], None] | None = None) -> None:
        self.time = np.asarray(problem.time)
        N, T = int(problem.n_runs), len(self.time)
        self.n_runs, self.n_steps, self.n = N, T, int(n)
        self.cov_stride = int(problem.cov_stride)
        self.cov_layout = problem.cov_layout if covariance else "none"
        self.cov_index = cov_steps(T, self.cov_stride)
        self.states = np.empty((N, T, self.n))
        self.cov: np.ndarray | None = None
        if self.cov_layout == "full":
            self.cov = np.empty((N, len(self.cov_index), self.n, self.n))
        elif self.cov_layout == "diag":
            self.cov = np.empty((N, len(self.cov_index), self.n))
        elif self.cov_layout != "none":
            raise ValueError(f"covariance layout {self.cov_layout!r}: 'full', 'diag' or 'none'")
        self.series = {name: np.empty((N, T), dtype=dt) for name, dt in (series or {}).items()}
        self.status = np.full(N, STATUS_OK, dtype=object)
        self.reason = np.full(N, "", dtype=object)
        self.alive = np.ones(N, dtype=bool)
        self.event = np.full(N, -1, dtype=np.int64)
        self.extras: dict[str, np.ndarray] = {}
        self._progress = progress
        self._every = max(1, (T - 1) // 100)
        self._report = self._every  # the next grid step to report
        self._last = -1  # the last recorded grid step
        self._last_cov: np.ndarray | None = None  # its covariance, in the stored layout

    # ------------------------------------------------------------------ estimates
    def record(self, k: int, x: np.ndarray, P: np.ndarray | None = None, **series: np.ndarray) -> None:
        """Record the estimate at grid step ``k``: ``x (N, n)``, ``P (N, n, n)`` (needed when covariances
        are kept) and each named series ``(N,)``. Steps since the previous record hold that one."""
        k = int(k)
        if not (self._last < k < self.n_steps) or (self._last < 0 and k != 0):
            raise ValueError(f"estimate recorded at grid step {k}: the first at 0, then increasing steps below "
                             f"{self.n_steps} (the last was {self._last})")
        if set(series) != set(self.series):
            raise ValueError(f"series recorded: {', '.join(sorted(series)) or 'none'}; declared: "
                             f"{', '.join(sorted(self.series)) or 'none'}")
        if self.cov is not None and P is None:
            raise ValueError(f"covariance layout {self.cov_layout!r} keeps covariances: record P with x")
        self._hold_until(k)
        self.states[:, k] = x
        for name, v in series.items():
            self.series[name][:, k] = v
        if self.cov is not None:
            kept = shrink_cov(P, self.cov_layout)
            if k % self.cov_stride == 0:
                self.cov[:, k // self.cov_stride] = kept
                self._last_cov = self.cov[:, k // self.cov_stride]
            else:  # a copy: the caller may change P in place later
                self._last_cov = np.array(kept, copy=True)
        self._last = k
        if self._progress is not None and k > 0 and (k >= self._report or k == self.n_steps - 1):
            self._progress(k, self.n_steps - 1)
            self._report = (k // self._every + 1) * self._every

    def _hold_until(self, k: int) -> None:
        """Grid steps after the last record and before ``k`` hold the last record."""
        lo, hi, last = self._last + 1, k - 1, self._last
        if last < 0 or hi < lo:
            return
        self.states[:, lo : hi + 1] = self.states[:, last, None]
        for a in self.series.values():
            a[:, lo : hi + 1] = a[:, last, None]
        if self.cov is not None:
            s = self.cov_stride
            first, end = -(-lo // s), hi // s + 1  # the kept slots among lo..hi
            if first < end:
                self.cov[:, first:end] = self._last_cov[:, None]

    def record_all(self, ticks: np.ndarray, x: np.ndarray | None = None, P: np.ndarray | None = None, *,
                   state: np.ndarray | None = None) -> None:
        """Record every tick at once (:meth:`record` over ``ticks``, vectorised).

        Parameters
        ----------
        ticks : (K,) int ndarray
            Increasing grid steps of the estimates.
        x : (N, K, n) ndarray, optional
            The estimates at the ticks, held between them (or ``state``, not both).
        P : (N, K, n, n) ndarray, optional
            The covariances at the ticks; a kept step takes the one of the last tick at or before it.
        state : (N, T, n) ndarray, optional
            The estimate at every grid step (e.g. carried by a model between the ticks).
        """
        if (x is None) == (state is None):
            raise ValueError("record_all takes the estimates at the ticks (x) or on the whole grid (state)")
        ticks = np.asarray(ticks)
        at = np.clip(np.searchsorted(ticks, np.arange(self.n_steps), side="right") - 1, 0, len(ticks) - 1)
        states = x[:, at] if state is None else state
        self._check_shape("state", states, (self.n_runs, self.n_steps, self.n))
        self.states = states
        if self.cov is not None:
            if P is None:
                raise ValueError(f"covariance layout {self.cov_layout!r} keeps covariances: record P with x")
            self.cov = shrink_cov(P[:, at[self.cov_index]], self.cov_layout)
        self._last = self.n_steps - 1

    def adopt(self, state: np.ndarray, cov: np.ndarray | None = None) -> None:
        """Take arrays filled elsewhere (a compiled kernel) in the recorder's shapes: ``state (N, T, n)``,
        ``cov`` as :attr:`cov` (None when covariances are not kept)."""
        self._check_shape("state", state, self.states.shape)
        if (cov is None) != (self.cov is None):
            raise ValueError(f"covariance layout {self.cov_layout!r}: "
                             f"{'no covariance expected' if self.cov is None else 'covariances expected'}")
        if cov is not None:
            self._check_shape("cov", cov, self.cov.shape)
        self.states, self.cov = state, cov
        self._last = self.n_steps - 1

    @staticmethod
    def _check_shape(what: str, a: np.ndarray, shape: tuple) -> None:
        if np.shape(a) != tuple(shape):
            raise ValueError(f"{what} of shape {np.shape(a)}, expected {tuple(shape)}")

    # ------------------------------------------------------------------ stopped runs
    def stop(self, k: int | np.ndarray | None, mask: np.ndarray, status: str,
             reason: str | Sequence[str]) -> np.ndarray:
        """Stop the alive runs of ``mask (N,)`` at grid step ``k`` (an int, ``(N,)`` steps per run, or None
        for an event without a time) with ``status`` and ``reason`` (a text, ``{t}`` in it the event's time,
        or one text per run). Returns the runs stopped now, ``(N,)`` bool."""
        new = self.alive & np.asarray(mask, dtype=bool)
        if not new.any():
            return new
        self.status[new] = status
        texts = np.broadcast_to(np.asarray(reason, dtype=object), (self.n_runs,))
        if k is None:
            self.reason[new] = texts[new]
        elif np.ndim(k) == 0:
            self.event[new] = int(k)
            if isinstance(reason, str):  # one text for every run: formatted once
                self.reason[new] = event_reason(reason, self.time[int(k)])
            else:
                self.reason[new] = [event_reason(r, self.time[int(k)]) for r in texts[new]]
        else:
            steps = np.broadcast_to(np.asarray(k, dtype=np.int64), (self.n_runs,))
            self.event[new] = steps[new]
            self.reason[new] = [event_reason(r, self.time[j]) for r, j in zip(texts[new], steps[new])]
        self.alive &= ~new
        return new

    def check(self, k: int, x: np.ndarray, P: np.ndarray | None = None, *, singular: np.ndarray | None = None,
              max_trace: float | None = None, singular_reason: str = "left the model's domain (t = {t:.2f} s)",
              diverged_reason: str = "non-finite or exploding estimate at t = {t:.2f} s") -> np.ndarray:
        """The usual checks at grid step ``k``: a finite estimate ``x (N, m)`` (and trace of ``P (N, m, m)``)
        where ``singular (N,)`` is set (the model's domain left) is singular; a non-finite one, or a trace
        above ``max_trace``, diverged. Returns the runs stopped now."""
        with np.errstate(invalid="ignore", over="ignore"):
            finite = np.isfinite(x).all(-1)
            exploding = np.zeros(self.n_runs, dtype=bool)
            if P is not None:
                tr = np.trace(P, axis1=-2, axis2=-1)
                finite = finite & np.isfinite(tr)
                if max_trace is not None:
                    exploding = tr > max_trace
        new = np.zeros(self.n_runs, dtype=bool)
        if singular is not None:
            new |= self.stop(k, singular & finite, STATUS_SINGULAR, singular_reason)
        return new | self.stop(k, ~finite | exploding, STATUS_DIVERGED, diverged_reason)

    def hold(self, new: np.ndarray, old: np.ndarray, *, axis: int = 0) -> np.ndarray:
        """``new`` for the alive runs, ``old`` (the last good value) for the stopped ones; the runs along
        ``axis`` of both."""
        if self.alive.all():
            return new
        shape = [1] * np.ndim(new)
        shape[axis] = self.n_runs
        return np.where(self.alive.reshape(shape), new, old)

    def stop_first(self, steps: np.ndarray, events: Sequence[tuple[np.ndarray, str, str]]) -> np.ndarray:
        """:meth:`stop` on whole trajectories: ``events`` are ``(mask (N, K), status, reason)`` in order of
        precedence at the ``K`` ticks of grid steps ``steps (K,)``; an alive run stops at its first tick
        where any mask is set, with the first event set there. Returns that tick's index ``(N,)`` (-1: the
        run did not stop)."""
        steps = np.asarray(steps)
        bad = np.zeros((self.n_runs, len(steps)), dtype=bool)
        for mask, _, _ in events:
            bad |= mask
        bad &= self.alive[:, None]
        hit = bad.any(1)
        first = np.where(hit, np.argmax(bad, 1), -1)
        at = steps[np.maximum(first, 0)]
        rows = np.arange(self.n_runs)
        for mask, status, reason in events:
            self.stop(at, hit & mask[rows, np.maximum(first, 0)], status, reason)
        return first

    @staticmethod
    def hold_from(a: np.ndarray, first: np.ndarray) -> np.ndarray:
        """``a (N, K, ...)`` with each run's entries from index ``first (N,)`` on (-1: none) replaced, in place,
        by the entry before it (the first entry where ``first`` is 0): a stopped run holds its last good
        estimate. Returns ``a``."""
        first = np.asarray(first)
        runs, ticks = np.nonzero(np.arange(a.shape[1])[None, :] >= np.where(first < 0, a.shape[1], first)[:, None])
        if runs.size:
            a[runs, ticks] = a[runs, np.maximum(first[runs] - 1, 0)]
        return a

    # ------------------------------------------------------------------ counters and the result
    def counter(self, name: str) -> np.ndarray:
        """An ``(N,)`` int64 counter stored as extra ``name`` (the same array on every call)."""
        return self.extras.setdefault(name, np.zeros(self.n_runs, dtype=np.int64))

    def posterior(self, names: Sequence[str], units: Sequence[str], *, angle_states: Sequence[str] = (),
                  extras: Mapping[str, np.ndarray] | None = None, attrs: Mapping | None = None,
                  state: np.ndarray | None = None) -> Posterior:
        """The :class:`Posterior`: the recorded states (or ``state (N, T, n')``, e.g. the recorded ones
        transformed back, with ``n'`` names), covariances, status and reason per run, the counters and
        ``extras``, ``attrs``."""
        if self._last < 0:
            raise ValueError("no estimate recorded")
        self._hold_until(self.n_steps)
        if self._progress is not None and self._last < self.n_steps - 1:  # held to the end: done
            self._progress(self.n_steps - 1, self.n_steps - 1)
            self._last = self.n_steps - 1
        state = self.states if state is None else state
        if not len(names) == len(units) == np.shape(state)[-1]:
            raise ValueError(f"{len(names)} names and {len(units)} units for {np.shape(state)[-1]} states")
        return Posterior(
            state=state,
            cov=self.cov,
            status=self.status.astype(str),
            reason=self.reason.astype(str),
            names=names,
            units=units,
            angle_states=angle_states,
            extras={**self.extras, **(extras or {})},
            attrs=dict(attrs or {}),
        )
