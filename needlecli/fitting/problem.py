"""From an :class:`~needlecli.observers.EstimationProblem` and a :class:`KalmanSetup` to the arrays the
filters need: the discrete system, the measurement channels on its ticks, and the initial guesses
(``x0``, ``P0``, ``Q_c``, each ``R_j``). Shared by the ``ekf``/``eks`` observers and ``needle fit-em``."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from needlecli.fitting.settings import KalmanSetup
from needlecli.fitting.statespace import DiscreteModel, MeasurementModel, make_ticks
from needlecli.initial import check_initial_sensors, check_initial_states, initial_covariance, initial_mean
from needlecli.models import MODELS, Model
from needlecli.numerics.needle_frame import AXES, reference_axis
from needlecli.problem import EstimationProblem


@dataclass
class System:
    """Everything a filter, smoother or EM run needs, for all runs.

    dm : the discrete system; meas : the channels used; m0 (N, n), P0 (n, n); Qc (n, n) per second;
    R : per channel (m, m); floors : per channel, an eigenvalue floor of R (EM) or None;
    q_index : states with process noise.
    """

    dm: DiscreteModel
    meas: list[MeasurementModel]
    m0: np.ndarray
    P0: np.ndarray
    Qc: np.ndarray
    R: list[np.ndarray]
    floors: list[float | None]
    q_index: tuple[int, ...]

    @property
    def names(self) -> tuple[str, ...]:
        return self.dm.names


def own_model(setup: KalmanSetup, experiment_model: Model, name: str | None = None) -> Model:
    """The filter's model: ``name`` (or ``setup.model``, or the experiment's), with the setup's parameters
    (over the experiment's when it is the same model). Keys of ``setup.params`` the model lacks are
    ignored (a fit section may name several models' parameters)."""
    cls = MODELS.get(name or setup.model) if (name or setup.model) else type(experiment_model)
    base = experiment_model.params.model_dump() if cls is type(experiment_model) else {}
    base.update({k: v for k, v in setup.params.items() if k in cls.Params.model_fields})
    return cls(cls.Params(**base))


def build_system(
    problem: EstimationProblem,
    setup: KalmanSetup,
    model: Model,
    augment: Sequence[str] = (),
    rng: np.random.Generator | None = None,
) -> System:
    """Build the system of ``model`` (the filter's own) on ``problem`` as ``setup`` says.

    Raises ValueError for settings that do not fit the problem (unknown channel, a channel the model
    cannot predict).
    """
    time = problem.time
    T = len(time)
    grid_dt = float(time[1] - time[0]) if T > 1 else 1.0
    # ---- channels
    names = list(setup.measurements) or [c for c, ch in problem.channels.items() if ch.h_for(model) is not None]
    chans = []
    for name in names:
        if name not in problem.channels:
            raise ValueError(f"no channel {name!r}; channels: {', '.join(problem.channels) or 'none'}")
        ch = problem.channels[name]
        h = ch.h_for(model)
        if h is None:
            raise ValueError(f"model {model.registered_name!r} cannot predict channel {name!r}")
        chans.append((name, ch, h))
    ticks = make_ticks(T, [ch.index for _, ch, _ in chans], setup.ticks, grid_dt)
    # ---- model inputs by name from the experiment's
    cols: list[int] = []
    for k in model.input_names:
        if k not in problem.model.input_names:
            raise ValueError(f"model {model.registered_name!r} needs input {k!r}, which the experiment lacks")
        sl = problem.model.input_slice(k)
        cols.extend(range(sl.start, sl.stop))
    inputs = np.ascontiguousarray(problem.inputs[..., cols])
    params = model.param_arrays()
    offsets = {name: setup.measurements[name].along_offset for name, _, _ in chans
               if name in setup.measurements and setup.measurements[name].along_offset is not None}
    for name in offsets:
        if tuple(problem.channels[name].names) != ("x", "y", "z") or not model.provides("tangent"):
            raise ValueError(f"channel {name!r}: along_offset needs a position with axes x, y, z and a model "
                             f"with a tangent (model {model.registered_name!r})")
    sensor_states = [(f"{name}_offset", model.length_unit, 0.0 if o.tau is None else 1.0 / o.tau)
                     for name, o in offsets.items()]
    dm = DiscreteModel(model, params, augment, grid_dt, ticks, inputs, setup.substeps, sensor_states,
                       kernels=problem.kernels)
    meas, R, floors = [], [], []
    for name, ch, h in chans:
        tick = np.searchsorted(ticks, ch.index)
        ok = (tick < len(ticks)) & (ticks[np.minimum(tick, len(ticks) - 1)] == ch.index)
        if not ok.all():  # cannot happen with make_ticks (every sample is a tick), kept as a guard
            raise ValueError(f"channel {name!r}: samples off the filter's ticks")
        m = len(ch.names)
        spec = setup.measurements.get(name)
        frame = spec.frame if spec is not None else "world"
        if frame == "needle" and (tuple(ch.names) != ("x", "y", "z") or not model.provides("tangent")):
            raise ValueError(f"channel {name!r}: frame needle needs a position with axes x, y, z and a model with a "
                             f"tangent (it has {', '.join(ch.names)}; model {model.registered_name!r})")
        scale = sample_scale(ch)
        if spec is not None and spec.growth is not None:
            scale = growth_scale(ch, spec.growth, scale)
        if scale is not None and (frame == "needle" or name in offsets):  # per-axis sigmas of the world's axes
            raise ValueError(f"channel {name!r}: per-sample sigmas (or growth) cannot be used with frame needle or "
                             "along_offset")
        mm = MeasurementModel(name, h, model.n, tick, ch.value, ch.valid, np.asarray(ch.angle, dtype=bool),
                              tuple(ch.names), tuple(ch.units), bool(ch.unit_vector), scale, frame,
                              model.tangent if frame == "needle" or name in offsets else None,
                              offset_index=dm.names.index(f"{name}_offset") if name in offsets else None,
                              kernels=problem.kernels)
        meas.append(mm)
        sigma = spec.sigma if spec is not None and spec.sigma is not None else ch.sigma
        sig = np.asarray(sigma, dtype=float)
        if sig.size not in (1, m):
            raise ValueError(f"channel {name!r}: sigma has {sig.size} entries for {m} components")
        sig = np.broadcast_to(sig, (m,))
        if mm.tangent:  # a measured direction: its 2 components across the direction, mean sigma
            sig = np.full(2, float(np.sqrt(np.mean(sig**2))))
        R.append(np.diag(sig**2))
        floors.append(spec.floor if spec is not None else None)
    # ---- process noise and initial guesses
    q = dict(setup.q)
    moving = {f"{c}_offset": o for c, o in offsets.items() if o.tau is not None}
    for k, o in moving.items():  # an Ornstein-Uhlenbeck offset: q^2 = 2 sigma^2 / tau keeps its variance sigma^2
        q[k] = o.sigma * np.sqrt(2.0 / o.tau)
    if setup.q:
        q_index = tuple(i for i, s in enumerate(dm.names) if s in q)
    else:
        q_index = tuple(range(dm.nx)) + tuple(dm.names.index(k) for k in moving)
    Qc = np.diag([q.get(s, 0.0) ** 2 for s in dm.names])
    m0 = initial_mean(setup.init, problem, model, model.param_arrays(), rng, augment=dm.augment)
    if offsets:
        m0 = np.concatenate([m0, np.tile([o.value for o in offsets.values()], (m0.shape[0], 1))], -1)
    for mm in meas:  # the reference axis of needle coordinates: given, or far from the initial tangent
        if mm.frame == "needle":
            spec = setup.measurements[mm.name]
            mm.frame_axis = (AXES.index(spec.across_axis) if spec.across_axis is not None
                             else reference_axis(model.tangent(m0[:, : dm.nx])))
    P0 = initial_covariance(setup.init, dm.names, setup.p0, 1e-18, start=problem.start)
    for c, o in offsets.items():  # the offset's prior: its stationary (or a constant's) variance
        k = dm.names.index(f"{c}_offset")
        P0[k, k] = max(o.sigma**2, 1e-18)
    return System(dm, meas, m0, P0, Qc, R, floors, q_index)


def sample_scale(ch) -> np.ndarray | None:
    """Each sample's noise std over the channel's nominal one, ``(N, M, m_used)`` (1 where not valid), from
    a channel's recorded per-sample sigmas; None without them. A measured direction is used in its tangent
    plane (2 components): one scale per sample, the rms over its components."""
    if getattr(ch, "sample_sigma", None) is None:
        return None
    s = np.asarray(ch.sample_sigma, dtype=float)
    ref = np.broadcast_to(np.asarray(ch.sigma, dtype=float), (s.shape[-1],))
    ok = ch.valid[..., None] & np.isfinite(s) & (s > 0)
    if not (ref > 0).all():
        ref = np.array([np.median(s[..., j][ok[..., j]]) if ok[..., j].any() else 1.0 for j in range(s.shape[-1])])
    w = np.where(ok, s / ref, 1.0)
    if ch.unit_vector and s.shape[-1] == 3:
        w = np.repeat(np.sqrt(np.mean(w**2, axis=-1, keepdims=True)), 2, axis=-1)
    return w


def growth_scale(ch, growth, scale: np.ndarray | None) -> np.ndarray:
    """Each sample's noise std over the channel's nominal one, ``(N, M, m)``, with a distance ``growth``
    (:class:`~needlecli.schema.DistanceGrowth`): its position components' by ``1 + a d / d_max`` at the
    sample's measured position (the UKF's R, :mod:`needlecli.observers.ukf`), times ``scale`` (recorded
    per-sample sigmas) where given; 1 where a sample is not valid."""
    cols = [i for i, c in enumerate(ch.names) if c in ("x", "y", "z")]
    value = np.asarray(ch.value, dtype=float)
    w = np.ones(value.shape) if scale is None else np.array(scale, dtype=float)
    if cols:
        with np.errstate(invalid="ignore"):
            f = growth.factor(value[..., cols], axes=[("x", "y", "z").index(ch.names[i]) for i in cols])
        f = np.where(ch.valid & np.isfinite(f), f, 1.0)
        w[..., cols] *= f[..., None]
    return w


def check_setup(setup: KalmanSetup, model_cls: type[Model], sensors: dict, augment: Sequence[str] = ()) -> list:
    """Config problems of a setup for one model: ``[(loc, message)]`` (the observers' ``check``)."""
    out = []
    names = tuple(model_cls.state_names) + tuple(augment)
    for a in augment:
        if a not in model_cls.Params.model_fields:
            out.append((("augment",), f"model {model_cls.registered_name!r} has no parameter {a!r}"))
        elif a in model_cls.state_names:
            out.append((("augment",), f"{a!r} is already a state of model {model_cls.registered_name!r}"))
    hint = tuple(model_cls.Params.model_fields)
    for where, keys in (("q", setup.q), ("p0", setup.p0)):
        for k in keys:
            if k not in names:
                out.append(((where, k), f"model {model_cls.registered_name!r} has no state {k!r}"
                            + (" (augment it to estimate a parameter)" if k in hint else "")))
    out += [(("init", *loc), msg) for loc, msg in check_initial_states(setup.init, names, model_cls.registered_name, hint)]
    for k in setup.params:
        if k not in model_cls.Params.model_fields:
            out.append((("params", k), f"model {model_cls.registered_name!r} has no parameter {k!r}"))
    out += check_channels(setup, model_cls, sensors)
    for name, spec in setup.measurements.items():  # EM's robust weights and sensor states: fit-em only
        for key in ("student_t",):
            if getattr(spec, key) is not None:
                out.append((("measurements", name, key), "is a setting of needle fit-em (the fit: section); "
                            "an observer takes what it fitted through from_fit"))
    return out


def check_channels(setup: KalmanSetup, model_cls: type[Model], sensors: dict) -> list:
    from needlecli.sensors.base import measurement_function

    out = []
    try:
        own = model_cls(model_cls.Params(**{k: v for k, v in setup.params.items() if k in model_cls.Params.model_fields}))
    except Exception as e:  # parameters out of the model's range
        return [(("params",), str(e).splitlines()[-1].strip())]
    for name, spec in setup.measurements.items():
        if name not in sensors:
            out.append((("measurements", name), f"no sensor named {name!r}; sensors: {', '.join(sensors) or 'none'}"))
            continue
        if measurement_function(sensors[name], own) is None:
            out.append((("measurements", name), f"model {model_cls.registered_name!r} cannot predict what sensor {name!r} measures"))
            continue
        m = len(sensors[name].channel_names)
        if spec.sigma is not None and np.size(spec.sigma) not in (1, m):
            out.append((("measurements", name, "sigma"), f"has {np.size(spec.sigma)} entries for {m} components"))
        if spec.frame == "needle" and (tuple(sensors[name].channel_names) != ("x", "y", "z") or not own.provides("tangent")):
            out.append((("measurements", name, "frame"), f"needle coordinates need a position with axes x, y, z and a "
                        f"model with a tangent (sensor {name!r}: {', '.join(sensors[name].channel_names)}; model "
                        f"{model_cls.registered_name!r})"))
        if spec.growth is not None and not {"x", "y", "z"} & set(sensors[name].channel_names):
            out.append((("measurements", name, "growth"), f"a distance law of a position's noise; sensor {name!r} "
                        f"measures {', '.join(sensors[name].channel_names)}"))
        if spec.growth is not None and (spec.frame == "needle" or spec.along_offset is not None):
            out.append((("measurements", name, "growth"), "a distance law of world-axis noise: not with frame: needle "
                        "or along_offset"))
        if spec.across_axis is not None and spec.frame != "needle":
            out.append((("measurements", name, "across_axis"), "is used only with frame: needle"))
        if spec.along_offset is not None and (tuple(sensors[name].channel_names) != ("x", "y", "z")
                                              or not own.provides("tangent")):
            out.append((("measurements", name, "along_offset"), "an offset along the needle needs a position with "
                        f"axes x, y, z and a model with a tangent (model {model_cls.registered_name!r})"))
    out += [(("init", *loc), msg) for loc, msg in check_initial_sensors(setup.init, sensors)]
    return out


def fit_augment(model_cls: type[Model], constants: Sequence[str] | None = None) -> tuple[str, ...]:
    """The constants EM estimates as augmented states: ``constants`` (the fit's ``constants:``, e.g.
    ``[kappa, speed_scale]``: those that are parameters of this model), by default the model's curvature
    parameter (the magnetic needle EM paper: ``c`` of the MNM, ``l_inv`` of the BiNM); never one the model carries as a state."""
    if constants is None:
        c = model_cls.curvature_param
        return (c,) if c is not None and c not in model_cls.state_names else ()
    return tuple(c for c in constants if c in model_cls.Params.model_fields and c not in model_cls.state_names)


def check_fit(fit, sensors: dict) -> list:
    """Problems of a config's ``fit:`` section: ``[(loc, message)]``. Keys of ``q``, ``p0`` and
    ``init`` may name the states and constants of any fitted model."""
    out = []
    classes = []
    for i, name in enumerate(fit.models):
        if name not in MODELS:
            out.append((("models", i), f"unknown model {name!r}; known: {', '.join(MODELS.names())}"))
        else:
            classes.append(MODELS.get(name))
    if fit.model is not None:
        out.append((("model",), "use 'models' (the models fit-em fits) in a fit section"))
    if not fit.q:
        out.append((("q",), "required key is missing: the initial guess of the process noise (std per state, "
                    "unit/sqrt(s)); the states it lists have process noise"))
    if out:
        return out
    for i, c in enumerate(fit.constants or []):
        if not any(c in cls.Params.model_fields for cls in classes):
            out.append((("constants", i), f"no fitted model ({', '.join(fit.models)}) has a parameter {c!r}"))
    known = set()
    for cls in classes:
        known |= set(cls.state_names) | set(fit_augment(cls, fit.constants))
    for where, keys in (("q", fit.q), ("p0", fit.p0), (("init", "std"), fit.init.std),
                        (("init", "values"), fit.init.values), (("init", "first_measurement"), fit.init.first_measurement)):
        for k in keys:
            if k not in known:
                loc = (where, k) if isinstance(where, str) else (*where, k)
                out.append((loc, f"no fitted model ({', '.join(fit.models)}) has a state or fitted constant {k!r}"))
    for k in fit.params:
        if not any(k in cls.Params.model_fields for cls in classes):
            out.append((("params", k), f"no fitted model has a parameter {k!r}"))
    for i, k in enumerate(fit.hold):
        if k not in known:
            out.append((("hold", i), f"no fitted model ({', '.join(fit.models)}) has a state or fitted constant {k!r}"))
        elif k not in fit.q and not any(k in fit_augment(cls) for cls in classes):
            out.append((("hold", i), f"{k!r} has no process noise (not in q) and is no fitted constant: nothing to hold"))
    out += _check_isotropic(fit, classes)
    for cls in classes:
        out += check_channels(fit, cls, sensors)
    return out


def _check_isotropic(fit, classes) -> list:
    """Problems of ``fit.isotropic``: each a block (a state stem) of a fitted model with at least two of its
    states in ``q``, none of them held."""
    from needlecli.models.base import state_blocks

    out = []
    blocks: dict[str, list[str]] = {}
    for cls in classes:
        for stem, idx in state_blocks(cls.state_names).items():
            blocks.setdefault(stem, [cls.state_names[i] for i in idx])
    for i, stem in enumerate(fit.isotropic):
        if stem not in blocks:
            out.append((("isotropic", i), f"no fitted model ({', '.join(fit.models)}) has a block {stem!r} of states; "
                        f"blocks: {', '.join(blocks)}"))
            continue
        noisy = [s for s in blocks[stem] if s in fit.q]
        if len(noisy) < 2:
            out.append((("isotropic", i), f"block {stem!r} has {len(noisy)} state(s) with process noise in q "
                        f"({', '.join(noisy) or 'none'}): nothing to tie"))
        held = [s for s in noisy if s in fit.hold]
        if held:
            out.append((("isotropic", i), f"block {stem!r} has held states ({', '.join(held)}): a tied block is fitted"))
    return out
