"""What an observer must return, checked against the problem it was given (every observer, built-in or a
plug-in, after every ``run``: :mod:`needlecli.experiments.simulation.components`).

A :class:`~needlecli.observers.base.Posterior` for an :class:`~needlecli.problem.EstimationProblem` of
``N`` runs on ``T`` grid times, with covariances kept every ``cov_stride``-th time (``K`` of them) in
the problem's ``cov_layout``:

- ``names`` (n texts) and ``units`` (n texts); ``angle_states`` among the names;
- ``state`` real numbers ``(N, T, n)``;
- ``cov`` real numbers ``(N, K, n, n)`` (layout ``full``) or ``(N, K, n)`` (``diag``), or None; None
  with layout ``none``;
- ``status`` and ``reason`` texts ``(N,)``;
- in every run whose status is ``ok``: ``state`` and ``cov`` finite (a run marked otherwise -- diverged,
  singular, unobservable -- may hold NaN from where it stopped), each covariance symmetric (``|P - P^T|
  <= SYMMETRY_RTOL * s``) and positive semi-definite (eigenvalues ``>= -PSD_RTOL * s``), ``s`` the
  largest variance of that matrix; variances of the ``diag`` layout ``>= -PSD_RTOL * s``;
- ``extras``: arrays (numbers, true/false values or texts) under names that are paths (``nis/us3d``) not
  taking a documented member's place nor nesting under another extra; the documented ones of a channel
  of the problem with their shapes: ``nis/<channel>`` ``(N, M)``, ``used/<channel>``,
  ``gated/<channel>``, ``bound_violated/<channel>`` ``(N,)``;
- ``attrs``: texts, numbers, true/false values, lists of them or arrays, under names other than the ones
  the results file gives every observer (``names``, ``units``, ``angles``, ``type``, ``layout``,
  ``stride``).

The first problem is returned in words (``"state of shape (2, 11, 3), expected (N, T, n) = (2, 11,
6)"``); the caller names the observer.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from needlecli.guard import texts, what
from needlecli.observers.base import STATUS_OK, Posterior, cov_steps
from needlecli.problem import CommonStart, EstimationProblem

SYMMETRY_RTOL = 1e-6
PSD_RTOL = 1e-6
#: arrays the results file writes for every observer: an extra may not take their place
RESERVED = ("state", "cov", "cov_index", "status", "reason")
RESERVED_ATTRS = ("names", "units", "angles", "type", "layout", "stride")
#: documented extras of a channel (docs/reference/results-file.md) -> their shape, by symbol
CHANNEL_EXTRAS = {"nis": ("N", "M"), "used": ("N",), "gated": ("N",), "bound_violated": ("N",)}
_CHUNK_BYTES = 32 * 2**20  # covariances checked in blocks of runs of about this size (bounded temporaries)


def check_posterior(post: object, problem: EstimationProblem) -> str | None:
    """The first way ``post`` breaks the observer contract for ``problem`` (module docstring), in words;
    None when it keeps it."""
    if not isinstance(post, Posterior):
        return f"{what(post)}, not a Posterior"
    N, T = problem.n_runs, len(problem.time)
    names = texts(post.names)
    if names is None:
        return f"names {what(post.names)}, not a list of texts"
    n = len(names)
    env = {"N": N, "T": T, "n": n, "K": len(cov_steps(T, problem.cov_stride))}
    units = texts(post.units)
    if units is None or len(units) != n:
        return (f"units {what(post.units)}, not a list of texts" if units is None
                else f"{len(units)} units for {n} names")
    angles = texts(post.angle_states)
    if angles is None or not set(angles) <= set(names):
        return (f"angle_states {what(post.angle_states)}, not a list of texts" if angles is None
                else f"angle_states {sorted(set(angles) - set(names))} that are not among its names")
    problem_ = (_array("state", post.state, ("N", "T", "n"), env, "real")
                or _array("status", post.status, ("N",), env, "text")
                or _array("reason", post.reason, ("N",), env, "text"))
    if problem_:
        return problem_
    layout = problem.cov_layout
    if post.cov is not None:
        if layout == "none":
            return "a covariance, but the problem keeps none (output.covariance: none)"
        want = ("N", "K", "n", "n") if layout == "full" else ("N", "K", "n")
        problem_ = _array("cov", post.cov, want, env, "real")
        if problem_:
            every = f"every {problem.cov_stride} steps" if problem.cov_stride > 1 else "every step"
            return problem_ + f" (K: the {T} times kept {every}; layout {layout})"
    ok = np.asarray(post.status) == STATUS_OK
    problem_ = _finite("state", np.asarray(post.state), ok)
    if problem_ is None and post.cov is not None:
        problem_ = _covariances(np.asarray(post.cov), ok, layout)
    return problem_ or _extras(post.extras, problem, env) or _attrs(post.attrs)


def check_start(start: object, problem: EstimationProblem) -> str | None:
    """The first way an initial estimate to share (``Observer.initial_estimate``) breaks its contract:
    None, or a :class:`~needlecli.problem.CommonStart` with ``k`` names, a finite ``mean (N, k)`` and a
    finite, symmetric, positive semi-definite ``cov (k, k)``."""
    if start is None:
        return None
    if not isinstance(start, CommonStart):
        return f"{what(start)}, not a CommonStart or None"
    names = texts(start.names)
    if names is None:
        return f"names {what(start.names)}, not a list of texts"
    env = {"N": problem.n_runs, "k": len(names)}
    problem_ = (_array("mean", start.mean, ("N", "k"), env, "real")
                or _array("cov", start.cov, ("k", "k"), env, "real"))
    if problem_:
        return problem_
    every = np.ones(1, dtype=bool)
    return (_finite("mean", start.mean, np.ones(problem.n_runs, dtype=bool))
            or _covariances(np.asarray(start.cov)[None, None], every, "full"))


# ---------------------------------------------------------------------------------------------- pieces
def _fmt(shape: tuple, env: dict) -> str:
    syms = "(" + ", ".join(shape) + ("," if len(shape) == 1 else "") + ")"
    vals = "(" + ", ".join(str(env[s]) for s in shape) + ("," if len(shape) == 1 else "") + ")"
    return f"{syms} = {vals}"


def _array(name: str, v: object, shape: tuple, env: dict, kind: str) -> str | None:
    """``v`` an array of ``kind`` (real numbers, texts) with ``shape`` (symbols of ``env``)."""
    if not isinstance(v, np.ndarray):
        return f"{name} {what(v)}, not an array"
    ok = v.dtype.kind in ("fiu" if kind == "real" else "USO")
    if not ok:
        return f"{name} of {v.dtype} values, expected {'real numbers' if kind == 'real' else 'texts'}"
    want = tuple(env[s] for s in shape)
    if v.shape != want:
        return f"{name} of shape {v.shape}, expected {_fmt(shape, env)}"
    return None


def _blocks(v: np.ndarray, copies: int = 1):
    """Slices of runs (the first axis of ``v``) of about :data:`_CHUNK_BYTES` of temporaries each, ``copies``
    temporaries the size of the block: many runs at once, vectorised inside (not a loop over runs)."""
    per_run = max(1, (v[0].size if len(v) else 1) * v.itemsize * copies)
    step = max(1, _CHUNK_BYTES // per_run)
    return [slice(i, min(i + step, len(v))) for i in range(0, len(v), step)]


def _finite(name: str, v: np.ndarray, ok: np.ndarray) -> str | None:
    """Every value of the runs marked ok finite (the first one that is not, else None)."""
    if not ok.any():
        return None
    for s in _blocks(v):
        fin = np.isfinite(v[s]).reshape(s.stop - s.start, -1).all(axis=1)
        bad = np.flatnonzero(ok[s] & ~fin)
        if bad.size:
            run = s.start + int(bad[0])
            at = (run,) + tuple(int(i) for i in np.argwhere(~np.isfinite(v[run]))[0])
            return f"{name}[{', '.join(map(str, at))}] = {v[at]} in run {run}, whose status is ok"
    return None


def _covariances(cov: np.ndarray, ok: np.ndarray, layout: str) -> str | None:
    """Covariances of the runs marked ok: finite, symmetric and positive semi-definite (``full``), or
    non-negative variances (``diag``). Each block of runs is laid out as ``(n, n, B)`` (one vector of
    ``B`` matrices per entry), so that every test is a few operations on long vectors."""
    problem = _finite("cov", cov, ok)
    if problem is not None or not ok.any():
        return problem
    for s in _blocks(cov, 3 if layout == "full" else 1):
        runs = np.arange(s.start, s.stop)[ok[s]]
        if not runs.size:
            continue
        block = cov[s][ok[s]] if not ok[s].all() else cov[s]
        K = block.shape[1]
        if layout == "diag":
            scale = np.maximum(np.max(block, axis=-1, keepdims=True), 0.0)
            bad = block < -PSD_RTOL * scale
            if bad.any():
                r, k, j = (int(x) for x in np.argwhere(bad)[0])
                return (f"a negative variance: cov[{runs[r]}, {k}, {j}] = {block[r, k, j]:.3g} "
                        f"(run {runs[r]}, stored time {k})")
            continue
        n = block.shape[-1]
        if n == 0:
            return None
        a = _entrywise(block.reshape(-1, n, n))  # (n, n, B)
        scale = np.maximum(np.max(np.abs(a[np.arange(n), np.arange(n)]), axis=0), np.finfo(float).tiny)  # (B,)
        asym = np.zeros_like(scale)
        for i in range(n):
            for j in range(i):
                np.maximum(asym, np.abs(a[i, j] - a[j, i]), out=asym)
        bad = np.flatnonzero(asym > SYMMETRY_RTOL * scale)
        if bad.size:
            r, k = divmod(int(bad[0]), K)
            return (f"a covariance that is not symmetric: run {runs[r]}, stored time {k}, "
                    f"max |P - P^T| = {asym[bad[0]] / scale[bad[0]]:.3g} times its largest variance")
        bad = np.flatnonzero(_smallest_pivot(a, PSD_RTOL * scale) <= 0)
        if bad.size:
            r, k = divmod(int(bad[0]), K)
            low = np.linalg.eigvalsh(block[r, k])[0] / scale[bad[0]]
            return (f"a covariance that is not positive semi-definite: run {runs[r]}, stored time {k}, "
                    f"smallest eigenvalue {low:.3g} times its largest variance")
    return None


def _entrywise(m: np.ndarray, step: int = 1024) -> np.ndarray:
    """``m`` ``(B, n, n)`` as a contiguous ``(n, n, B)`` float array, copied ``step`` matrices at a time (a
    transposition whose pieces stay in the cache: about twice as fast as one ``moveaxis`` copy)."""
    out = np.empty(m.shape[1:] + m.shape[:1])
    for i in range(0, len(m), step):
        out[..., i:i + step] = np.moveaxis(m[i:i + step], 0, -1)
    return out


def _smallest_pivot(a: np.ndarray, shift: np.ndarray) -> np.ndarray:
    """The smallest pivot of the LDL^T elimination of each ``P + shift I`` (``a`` ``(n, n, B)``: ``B``
    symmetric matrices entry by entry, its lower triangle read; overwritten): positive exactly where
    ``P + shift I`` is positive definite, i.e. where the smallest eigenvalue of ``P`` is above ``-shift``."""
    n = a.shape[0]
    for i in range(n):
        a[i, i] += shift
    low = np.full(a.shape[-1], np.inf)
    for k in range(n):
        piv = a[k, k]
        np.minimum(low, piv, out=low)
        inv = np.divide(1.0, piv, out=np.zeros_like(piv), where=piv > 0)  # (a failed pivot: refused already)
        for i in range(k + 1, n):
            f = a[i, k] * inv
            for j in range(k + 1, i + 1):
                a[i, j] -= f * a[j, k]
    return low


def _extras(extras: object, problem: EstimationProblem, env: dict) -> str | None:
    if not isinstance(extras, Mapping):
        return f"extras {what(extras)}, not a mapping of names to arrays"
    keys = list(extras)
    for key in keys:
        if not isinstance(key, str):
            return f"an extra named {key!r}, not a text"
        parts = key.split("/")
        if any(p in ("", ".", "..") for p in parts):
            return f"an extra named {key!r}: names are paths like 'nis/us3d'"
        if parts[0] in RESERVED:
            return f"an extra named {key!r}, which takes the place of the observer's {parts[0]!r}"
        v = extras[key]
        if not isinstance(v, np.ndarray) or v.dtype.kind not in "biufUSO":
            return f"extra {key!r} {what(v)}, not an array of numbers, true/false values or texts"
        if len(parts) == 2 and parts[0] in CHANNEL_EXTRAS and parts[1] in problem.channels:
            shape = CHANNEL_EXTRAS[parts[0]]
            local = {**env, "M": len(problem.channels[parts[1]].t)}
            if v.shape != tuple(local[s] for s in shape):
                return f"extra {key!r} of shape {v.shape}, expected {_fmt(shape, local)}"
    prefixes = {"/".join(k.split("/")[:i]) for k in keys for i in range(1, k.count("/") + 1)}
    nested = sorted(set(keys) & prefixes)
    if nested:
        return f"an extra named {nested[0]!r} and others below it ({nested[0]}/...): one is a group, not both"
    return None


def _attrs(attrs: object) -> str | None:
    if not isinstance(attrs, Mapping):
        return f"attrs {what(attrs)}, not a mapping"
    for key, v in attrs.items():
        if not isinstance(key, str) or key in RESERVED_ATTRS:
            return (f"an attribute named {key!r}, which the results file gives every observer"
                    if isinstance(key, str) else f"an attribute named {key!r}, not a text")
        if not _attribute_value(v):
            return f"attribute {key!r} {what(v)}: not a text, number, true/false value, list of them or array"
    return None


def _attribute_value(v: object) -> bool:
    if isinstance(v, (str, bool, int, float, np.generic)):
        return not isinstance(v, np.generic) or v.dtype.kind in "biufUS"
    if isinstance(v, np.ndarray):
        return v.dtype.kind in "biufUSO"
    if isinstance(v, (list, tuple)):
        return all(isinstance(x, str) for x in v) or all(
            isinstance(x, (bool, int, float, np.generic)) and not isinstance(x, str) for x in v)
    return False
