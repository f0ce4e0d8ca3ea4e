"""The truth simulation, compiled: every run's RK4 steps, process noise, parameter sync and domain checks
(:class:`needlecli.experiments.simulation.truth.TruthSimulator` without a ``before_step``, step for step).

Runs are the lanes (blocks of :data:`BLOCK` runs, spread over worker threads); the process noise is
drawn by the caller from the same generator in the same order as the numpy path (one
``standard_normal((steps, N, n))`` per chunk of steps is the same stream as one ``(N, n)`` draw per step).
"""

from __future__ import annotations

import math
from collections import namedtuple

import numpy as np

from needlecli.kernels._jit import jit
from needlecli.kernels._threads import blocks, parallel_for
from needlecli.kernels.channels import kernel_array
from needlecli.kernels.dispatch import KernelError
from needlecli.kernels.models import equation_id, step_fast

BLOCK = 32
OK, DIVERGED, SINGULAR = 0, 1, 2
MARGINS = {None: 0, "cos": 1, "perpendicular": 2}  # kinds of singularity (Model.compiled_margin)


def margin(model) -> tuple[int, np.ndarray]:
    """``(kind, states)`` of the model's declared singularity (:attr:`Model.compiled_margin`): kind 0 none,
    1 the cosine of ``states[0]``, 2 the |cos| of the angle between ``states[0:3]`` and ``states[3:6]``
    (and a step across their perpendicularity)."""
    decl = model.compiled_margin
    if decl is None:
        return 0, np.zeros(1, dtype=np.int64)
    kind, names = decl
    if kind not in MARGINS or len(names) != (1 if kind == "cos" else 6):
        raise KernelError(f"model {model.registered_name!r}: compiled_margin {decl!r} is none the kernels know: "
                          "('cos', (state,)) or ('perpendicular', (3 states, 3 states))")
    return MARGINS[kind], np.array([model.index(k) for k in names], dtype=np.int64)


#: the simulation's constants (numba takes a named tuple as an argument; defined at module level for the
#: cache): mid the compiled equations; u (1 or N, T, m); p_run (N, P); p_t (T,) the parameter
#: ``p_t_index`` along time (-1: none); sync_index the state that carries parameter ``sync_param`` (-1:
#: none); q (n,) noise std per step; dt; kind, margin the singularity and its states (:func:`margin`),
#: sing_thr, near_thr its thresholds
Stepper = namedtuple("Stepper", "mid u p_run p_t p_t_index sync_index sync_param q dt kind margin sing_thr near_thr")
#: what :func:`advance` updates: states (N, T, n); alive (N,) bool; status (N,) int; event (N,) the grid
#: index a run stopped at (-1: it did not)
Runs = namedtuple("Runs", "states alive status event")


@jit
def advance(lo, hi, st, runs, k0, k1, noise):
    """Fill ``runs.states[lo:hi, k0 + 1 : k1 + 1]`` from ``runs.states[lo:hi, k0]`` (runs in lanes of
    :data:`BLOCK`) with the :data:`Stepper` ``st``; ``noise (k1 - k0, N, n)`` standard normal draws (shape
    (0, 0, 0): no process noise). Releases the GIL.
    """
    mid, u, p_run, p_t, p_t_index, dt = st.mid, st.u, st.p_run, st.p_t, st.p_t_index, st.dt
    sync_index, sync_param, q = st.sync_index, st.sync_param, st.q
    kind, mi, sing_thr, near_thr = st.kind, st.margin, st.sing_thr, st.near_thr
    states, alive, status, event = runs.states, runs.alive, runs.status, runs.event
    n = states.shape[2]
    m = u.shape[2]
    P = p_run.shape[1]
    use_q = noise.shape[0] > 0
    X = np.zeros((n, BLOCK))
    X0 = np.zeros((n, BLOCK))
    U = np.zeros((m, BLOCK))
    Pm = np.zeros((P, BLOCK))
    W = np.zeros((4, max(n, 6), BLOCK))
    for r0 in range(lo, hi, BLOCK):
        nb = min(BLOCK, hi - r0)
        for i in range(nb):
            for c in range(n):
                X[c, i] = states[r0 + i, k0, c]
            for c in range(P):
                Pm[c, i] = p_run[r0 + i, c]
        for k in range(k0, k1):
            for i in range(nb):
                ru = r0 + i if u.shape[0] > 1 else 0
                for c in range(m):
                    U[c, i] = u[ru, k, c]
                if p_t_index >= 0:
                    Pm[p_t_index, i] = p_t[k]
                for c in range(n):
                    X0[c, i] = X[c, i]
            step_fast(mid, X, U, Pm, dt, min(BLOCK, (nb + 3) // 4 * 4), W)  # whole vectors (lanes past nb: finite)
            for i in range(nb):
                r = r0 + i
                if use_q:
                    for c in range(n):
                        X[c, i] = X[c, i] + q[c] * noise[k - k0, r, c]
                if sync_index >= 0:
                    X[sync_index, i] = p_t[k + 1] if p_t_index == sync_param else p_run[r, sync_param]
                if alive[r]:
                    finite = True
                    for c in range(n):
                        if not np.isfinite(X[c, i]):
                            finite = False
                    sing = False
                    near = False
                    if kind == 1:
                        sing = not math.cos(X[mi[0], i]) > sing_thr
                        near = not math.cos(X0[mi[0], i]) > near_thr
                    elif kind == 2:
                        sing = not _bh_margin(X, i, mi) > sing_thr
                        near = not _bh_margin(X0, i, mi) > near_thr
                        d0 = X0[mi[0], i] * X0[mi[3], i] + X0[mi[1], i] * X0[mi[4], i] + X0[mi[2], i] * X0[mi[5], i]
                        d1 = X[mi[0], i] * X[mi[3], i] + X[mi[1], i] * X[mi[4], i] + X[mi[2], i] * X[mi[5], i]
                        if d0 * d1 < 0.0:
                            sing = True
                    if sing or not finite:
                        alive[r] = False
                        status[r] = SINGULAR if (sing or (not finite and near)) else DIVERGED
                        event[r] = k + 1
                if not alive[r]:
                    for c in range(n):
                        X[c, i] = X0[c, i]
                for c in range(n):
                    states[r, k + 1, c] = X[c, i]


@jit
def _bh_margin(X, i, mi):
    h0, h1, h2 = X[mi[0], i], X[mi[1], i], X[mi[2], i]
    b0, b1, b2 = X[mi[3], i], X[mi[4], i], X[mi[5], i]
    d = h0 * b0 + h1 * b1 + h2 * b2
    return abs(d) / (math.sqrt(h0 * h0 + h1 * h1 + h2 * h2) * math.sqrt(b0 * b0 + b1 * b1 + b2 * b2))


# ---------------------------------------------------------------------------------------------- the seam
_CHUNK_ELEMENTS = 4_000_000  # noise drawn per chunk: at most this many numbers (32 MB)


class TruthKernel:
    """Advances a :class:`~needlecli.experiments.simulation.truth.TruthSimulator` (no ``before_step``) with
    :func:`advance`, writing into its arrays exactly what its numpy loop writes."""

    def __init__(self, sim) -> None:
        model = sim.model
        N, T = sim.n_runs, sim.T
        names = list(model.param_arrays())
        p_run = np.empty((N, max(len(names), 1)))
        p_t = np.zeros(T)
        p_t_index = -1
        for j, k in enumerate(names):
            a = sim.params_t[k]
            if a.ndim == 2:  # along time: the tissue schedule, the same for every run
                if a.strides[0] != 0 and not (a == a[:1]).all():
                    raise ValueError("a parameter that differs between runs along time")
                p_t = kernel_array(a[0], dtype=float)
                p_t_index = j
                p_run[:, j] = a[:, 0]
            else:
                p_run[:, j] = np.broadcast_to(a, (N,))
        carried = list(model.param_states.items())  # a parameter the model carries as a state (one at most)
        if len(carried) > 1:
            raise KernelError(f"model {model.registered_name!r}: param_states: the compiled truth syncs one parameter "
                              "state at most")
        u = sim.u
        kind, mi = margin(model)
        u3 = kernel_array(u[:1] if u.strides[0] == 0 else u, dtype=float)
        sync_index = model.index(carried[0][1]) if carried else -1
        sync_param = names.index(carried[0][0]) if carried else -1
        self.stepper = Stepper(equation_id(model), u3, p_run, p_t, p_t_index, sync_index, sync_param,
                               kernel_array(sim.q, dtype=float), float(sim.dt), kind, mi,
                               float(model.singular_threshold), float(model.near_singular_threshold))
        self.code = np.zeros(N, dtype=np.int64)
        self.event_k = np.full(N, -1, dtype=np.int64)

    def advance_to(self, sim, k: int) -> None:
        N, n = sim.n_runs, sim.model.n
        # few chunks (each waits for the slowest worker): ~20 progress updates, noise at most 32 MB at a time
        chunk = max(1, min(-(-(sim.T - 1) // 20), _CHUNK_ELEMENTS // max(N * n, 1)))
        empty = np.zeros((0, 0, 0))
        model = sim.model
        # one buffer for the draws of every chunk (the same numbers as fresh arrays): memory first touched
        # costs more than the draws on virtual machines, and a fresh 32 MB array per chunk is 20 of them
        buf = np.empty((min(chunk, k - sim.k), N, n)) if sim.use_q and k > sim.k else empty
        while sim.k < k:
            k0 = sim.k
            k1 = min(k, k0 + chunk)
            noise = sim.rng_q.standard_normal(out=buf[: k1 - k0]) if sim.use_q else empty
            parallel_for(advance, blocks(N, per_thread=2, minimum=BLOCK),
                         (self.stepper, Runs(sim.states, sim.alive, self.code, self.event_k), k0, k1, noise))
            sim.k = k1
            sim.acted = k1 - 1
            if sim.progress is not None:
                sim.progress(k1, sim.T - 1)
        new = (self.code != OK) & (sim.status == "ok")
        if new.any():
            sing = new & (self.code == SINGULAR)
            div = new & (self.code == DIVERGED)
            sim.status[sing] = "singular"
            sim.reason[sing] = model.singular_reason
            sim.status[div] = "diverged"
            sim.reason[div] = "non-finite truth state"
            sim.event[new] = sim.time[self.event_k[new]]
        sim.x = sim.states[:, sim.k]
