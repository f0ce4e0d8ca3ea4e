"""The experiment runner: wires model, sensors and observers from a validated config, runs them on all
Monte-Carlo runs at once and writes the results file. It knows no component by name."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from needlecli import kernels
from needlecli.experiments.config.types import Stop
from needlecli.experiments.simulation import components
from needlecli.experiments.simulation.components import build_sensors
from needlecli.experiments.simulation.replay import replay_truth
from needlecli.experiments.simulation.truth import Truth, simulate_truth, stream
from needlecli.io.results import Group, root_attrs, write_atomic
from needlecli.observers import OBSERVERS, Channel, EstimationProblem, Posterior
from needlecli.observers.base import cov_steps
from needlecli.sensors import MeasurementStream
from needlecli.sensors.base import context_columns, inequality_function, measurement_function, sample_context

if TYPE_CHECKING:
    from needlecli.experiments.config.types import ExperimentConfig

Progress = Callable[[str, int, int], None]


@dataclass
class ExperimentResult:
    truth: Truth
    measurements: dict[str, MeasurementStream]
    estimates: dict[str, Posterior]
    path: Path | None
    control: dict[str, Group] = field(default_factory=dict)  # what each controller did (closed loops)
    tree: Group | None = None  # the results file's content, as written (tables need not read it back)


def default_output(cfg: ExperimentConfig) -> Path:
    return Path(cfg.output.path) if cfg.output.path else Path("results") / f"{cfg.name}.h5"


def simulate_and_measure(cfg: ExperimentConfig, *, progress: Callable[[int, int], None] | None = None,
                         measure_progress: Progress | None = None):
    """Simulate the truth of a config and measure it with every sensor: in open loop (the truth first,
    then each sensor from its own random stream) or, with a ``control:`` section, in closed loop
    (:func:`needlecli.experiments.simulation.closed_loop.simulate_closed_loop`). Returns ``(truth, sensors, streams, control)``,
    ``control`` the results group of each controller (empty in open loop). ``measure_progress(phase, done,
    total)`` hears from sensors whose pipeline takes long (rendered frames)."""
    if cfg.control:
        from needlecli.experiments.simulation.closed_loop import simulate_closed_loop

        return simulate_closed_loop(cfg, progress=progress)
    truth = components.simulated(cfg, "simulate", simulate_truth, cfg, progress=progress)
    sensors = build_sensors(cfg, truth.model)
    for s in sensors:
        if measure_progress is not None:
            s.progress = lambda k, n, _n=s.name: measure_progress(f"sensor {_n}", k, n)
    streams = {s.name: components.measure(s, truth, stream(cfg.runs.seed, f"sensor/{s.name}")) for s in sensors}
    return truth, sensors, streams, {}


def build_problem(cfg: ExperimentConfig, truth: Truth, sensors, streams: dict[str, MeasurementStream]) -> EstimationProblem:
    channels = {}
    for sensor in sensors:
        st = streams[sensor.name]
        h = measurement_function(sensor, truth.model)
        nominal = np.atleast_1d(np.asarray(st.sigma[0, 0] if st.sigma.size else np.zeros(len(st.names))))
        per_sample = bool(st.attrs.get("sigma_per_sample", False))  # recorded per-sample sigmas (replay)
        if per_sample:
            nominal = np.broadcast_to(np.asarray(st.attrs["nominal_sigma"], dtype=float), (len(st.names),)).copy()
        meas, ctx = context_columns(sensor)  # what each sample measures, and what is known with it
        sub = (lambda a: a) if ctx is None else (lambda a, _m=meas: np.ascontiguousarray(a[..., _m]))
        channels[sensor.name] = Channel(
            name=sensor.name, sensor_type=sensor.registered_name, t=st.t, t_available=st.t_available,
            index=st.index, value=sub(st.value), valid=st.valid, names=_pick(st.names, meas, ctx),
            units=_pick(st.units, meas, ctx), sigma=sub(nominal), angle=sub(sensor.angle_channels), h=h, attrs=st.attrs,
            h_for=lambda model, reading=None, _s=sensor: measurement_function(_s, model, reading),
            unit_vector=sensor.unit_vector, sample_sigma=sub(st.sigma) if per_sample else None,
            bound_for=lambda model, _s=sensor: inequality_function(_s, model),
            context=sample_context(sensor, st.value),
            context_names=() if ctx is None else _pick(st.names, ctx, ctx),
        )
    n_runs = truth.states.shape[0]
    return EstimationProblem(
        time=truth.time,
        inputs=truth.inputs,
        input_names=truth.model.input_names,
        depth=np.broadcast_to(truth.depth, (n_runs, len(truth.time))),
        channels=channels,
        model=truth.model,
        params=truth.model.param_arrays(),
        interfaces=truth.interfaces,
        initial_truth=truth.states[:, 0].copy(),
        initial_state=dict(cfg.model.initial_state),
        cov_stride=cfg.output.store_every,
        cov_layout=cfg.output.covariance,
        kernels=cfg.simulation.kernels,
    )


def _pick(names, idx, ctx) -> tuple:
    """``names`` at ``idx`` (all of them for a sensor without context channels, ``ctx`` None)."""
    return tuple(names) if ctx is None else tuple(names[i] for i in idx)


def run_experiment(
    cfg: ExperimentConfig,
    config_text: str,
    *,
    out: str | Path | None = None,
    write: bool = True,
    progress: Progress | None = None,
    base_dir: str | Path | None = None,
) -> ExperimentResult:
    """Simulate the truth and measure it with every sensor (or replay recorded trials from the config's
    ``source.logs``, relative to ``base_dir``), run every observer, write the results file."""
    seed = cfg.runs.seed
    control: dict[str, Group] = {}
    warm = warm_up_observers(cfg)
    try:
        if cfg.source is not None:  # recorded trials instead of a simulation
            truth, sensors, streams = replay_truth(cfg, Path(base_dir or "."))
        else:
            truth, sensors, streams, control = simulate_and_measure(
                cfg, progress=(lambda k, n: progress("truth", k, n)) if progress else None, measure_progress=progress)
        problem = build_problem(cfg, truth, sensors, streams)
        warm.wait()
    finally:
        warm.cancel()
    shared = shared_start(cfg, problem)
    estimates: dict[str, Posterior] = {}
    for o in cfg.observers:  # each run guarded and its posterior checked before anything is written
        obs = components.build_observer(o)
        cb = (lambda k, n, _name=obs.name: progress(f"observer {_name}", k, n)) if progress else None
        own = shared.problem_of(obs.name, problem)
        estimates[obs.name] = components.run_observer(obs, o, own, stream(seed, f"observer/{obs.name}"), progress=cb)
    path = tree = None
    if write:
        path = Path(out) if out is not None else default_output(cfg)
        tree = results_tree(cfg, config_text, truth, streams, estimates, sensors, control, starts=shared.starts())
        write_atomic(path, tree, compression=cfg.output.compression,
                     progress=(lambda k, n: progress("results file", k, n)) if progress else None)
    return ExperimentResult(truth=truth, measurements=streams, estimates=estimates, path=path, control=control,
                            tree=tree if write else None)


#: s per insertion-step that the numpy path takes more than the compiled one, for each component of a run
#: with a compiled twin (the truth, each such observer): Table 1's whole processes at 100 and at 1,000
#: runs give the same 7.3 us (docs/benchmarks.md); what a first run on a cold cache weighs against waiting
#: for the compilation (:func:`needlecli.kernels.on_cold`)
NUMPY_EXTRA_S = 7e-6


def warm_up_observers(cfg: ExperimentConfig) -> kernels.WarmUp:
    """What this run does about its compiled kernels on a cold cache (the first run after an install or a
    change of the kernels), decided at its first kernel not compiled (:func:`needlecli.kernels.on_cold`):

    * a run whose numpy path costs less than the compilation (``NUMPY_EXTRA_S`` per insertion-step of each
      component with a compiled twin, against this machine's compile times) takes the numpy path, while a
      process of its own compiles the kernels for the next run: this experiment shortened to one run of
      2 s, its tables included (:func:`_compile_briefly`); under ``auto`` and the cold policy
      ``background`` (``NEEDLECLI_COLD``), for simulated insertions;
    * otherwise it compiles them, on two cores: a second process compiles the observers' kernels on a
      short copy of the experiment (one run, 2 s, its truth and sensors on the numpy path) while this one
      compiles and runs the truth simulation (returned: :meth:`~needlecli.kernels.WarmUp.wait` before the
      observers run)."""
    setting = cfg.simulation.kernels
    if kernels.requested(setting) == "numpy" or not kernels.numba_available():
        return kernels.WarmUp()  # numpy: numba not even imported
    observers = observer_entries(cfg)
    truth, *entries = run_entries(cfg)
    tiny = brief_copy(cfg)
    if cfg.source is None:
        from needlecli.experiments.config.budget import estimate

        size = estimate(cfg)
        parts = (truth is not None) + sum(e is not None for e in observers)
        kernels.on_cold(entries=[truth, *entries], numpy_seconds=NUMPY_EXTRA_S * size.runs * size.steps * parts,
                        compile_for_next_run=_compile_briefly, args=(tiny,))
    else:  # recorded trials: no truth to simulate briefly
        kernels.on_cold(entries=entries)
    if cfg.source is not None or not cfg.observers or kernels.would_defer(setting) or not kernels.cold(observers):
        return kernels.WarmUp()
    return kernels.warm_up(_observe_briefly, tiny)


def observer_entries(cfg: ExperimentConfig) -> list[tuple[str, str] | None]:
    """The entry kernel of each observer of ``cfg`` (its declaration ``compiled_entry``: the kernel that
    compiles longest; None: none)."""
    return [OBSERVERS.get(o.type).compiled_entry for o in cfg.observers]


def truth_entry(cfg: ExperimentConfig) -> tuple[str, str] | None:
    """The entry kernel of ``cfg``'s truth simulation: None for recorded trials, a closed loop (its model
    steps on numpy) or a model without compiled equations."""
    if cfg.source is not None or cfg.control:
        return None
    from needlecli.models import MODELS

    return kernels.TWINS["truth"].entry if MODELS.get(cfg.model.type).compiled_equations else None


def run_entries(cfg: ExperimentConfig) -> list[tuple[str, str] | None]:
    """The entry kernels a run of ``cfg`` compiles: the truth's first (:func:`truth_entry`), then the
    observers' and the error tables'."""
    return [truth_entry(cfg), *observer_entries(cfg), kernels.TWINS["state_errors"].entry,
            kernels.TWINS["rotation_error"].entry]


def brief_copy(cfg: ExperimentConfig) -> ExperimentConfig:
    """``cfg`` shortened to one run of 2 s: what compiles every kernel of its runs with their argument
    types, in a few seconds of work (:func:`_compile_briefly`)."""
    return cfg.model_copy(update={"runs": cfg.runs.model_copy(update={"count": 1}), "stop": Stop(time=2.0)})


def _compile_briefly(cfg: ExperimentConfig) -> None:
    """The run of ``cfg`` and its summary table, its results file in a temporary folder: every kernel a run
    of this experiment compiles, with the argument types it has (:func:`warm_up_observers`)."""
    import tempfile

    from needlecli.reports.evaluate import results_tables

    with tempfile.TemporaryDirectory(prefix="needle-compile-") as d:
        res = run_experiment(cfg, "", out=Path(d) / "brief.h5")
        if cfg.observers:
            results_tables(res.tree, ["summary"], str(res.path))


def _observe_briefly(cfg: ExperimentConfig) -> None:
    """The observers of ``cfg`` on its truth simulated on the numpy path (:func:`warm_up_observers`)."""
    sim = cfg.model_copy(update={"simulation": cfg.simulation.model_copy(update={"kernels": "numpy"})})
    truth, sensors, streams, _ = simulate_and_measure(sim)
    problem = build_problem(cfg, truth, sensors, streams)
    shared = shared_start(cfg, problem)
    for o in cfg.observers:
        obs = components.build_observer(o)
        obs.run(shared.problem_of(obs.name, problem), stream(cfg.runs.seed, f"observer/{obs.name}"))


@dataclass
class SharedStart:
    """Where each observer of a study starts (``runs.common_start``): the reference's initial estimate
    ``start`` (its own draw from its own stream, made once; None: no shared start), the observers that
    start from it (``sharing``) and each observer's start in words (``start_of``).

    Attributes
    ----------
    reference : the observer whose initial estimate is shared ("" without one)
    start : the shared :class:`~needlecli.problem.CommonStart`, or None
    sharing : names of the observers that start from it (never the reference: it starts from its own
        init, which gives the same start, so that its results are those it has alone)
    own : names of the observers that start from their own init, in the config's order
    why : why there is no shared start ("" with one)
    """

    reference: str = ""
    start: object = None
    sharing: tuple[str, ...] = ()
    own: tuple[str, ...] = ()
    why: str = ""

    def problem_of(self, name: str, problem: EstimationProblem) -> EstimationProblem:
        """The problem observer ``name`` runs on: with the shared start, or ``problem`` as it is."""
        return dataclasses.replace(problem, start=self.start) if name in self.sharing else problem

    def start_of(self, name: str) -> str:
        """Observer ``name``'s start in words, for the results file and the tables."""
        if name == self.reference and self.start is not None:
            return "common (reference): its own init"
        if name in self.sharing:
            return f"common: {self.reference}'s initial estimate"
        return "own init" + (f" ({self.why})" if self.why else "")

    def starts(self) -> dict[str, str]:
        """Each observer's start in words (:meth:`start_of`); none for a study of one observer."""
        names = (self.reference,) * bool(self.reference) + self.sharing + self.own
        return {n: self.start_of(n) for n in names} if len(names) > 1 else {}


def shared_start(cfg: ExperimentConfig, problem: EstimationProblem) -> SharedStart:
    """Which observers of ``cfg`` share one start (``runs.common_start``): ``shared`` (the default) the
    initial estimate of the config's first observer that gives one (``Observer.initial_estimate``), shared
    by every other observer that can take it (``Observer.takes_common_start``), as ``needle compare`` does;
    ``none`` each its own; ``{observer, observers}`` the named one's, shared by those named (default:
    every other that can take it). The reference draws its start from its own stream, so that its own
    results do not change."""
    cs = cfg.runs.common_start
    names = [o.name or o.type for o in cfg.observers]
    if cs == "none" or len(names) < 2:
        why = "runs.common_start: none" if cs == "none" and len(names) > 1 else ""
        return SharedStart(own=tuple(names), why=why)
    candidates = cfg.observers if cs == "shared" else [o for o in cfg.observers if (o.name or o.type) == cs.observer]
    ref, start = "", None
    for o in candidates:
        name = o.name or o.type
        start = components.initial_estimate(o, problem, stream(cfg.runs.seed, f"observer/{name}"))
        if start is not None:
            ref = name
            break
    if start is None:
        return SharedStart(own=tuple(names), why="no observer gives an initial estimate to share")
    wanted = set(names) if cs == "shared" or cs.observers is None else set(cs.observers)
    sharing = tuple(n for o, n in zip(cfg.observers, names)
                    if n != ref and n in wanted and OBSERVERS.get(o.type).takes_common_start)
    own = tuple(n for n in names if n != ref and n not in sharing)
    return SharedStart(reference=ref, start=start, sharing=sharing, own=own)


def results_tree(cfg: ExperimentConfig, config_text, truth: Truth, streams, estimates, sensors, control=None,
                 starts: dict[str, str] | None = None) -> Group:
    """The results file's content; ``starts``: each observer's start in words (its ``start`` attribute)."""
    model = truth.model
    n_runs, T = truth.states.shape[:2]
    root = Group(
        attrs=root_attrs(
            config_text,
            cfg.runs.seed,
            {
                "name": cfg.name,
                "model": model.registered_name,
                "length_unit": model.length_unit,
                "runs": n_runs,
                "dt": cfg.simulation.dt,
                "source": "replay" if cfg.source is not None else "simulation",
                "truth_kind": truth.truth_kind,
            },
        )
    )
    root.data["time"] = truth.time
    root.data["depth"] = truth.depth
    root.data["truth"] = Group(
        data={
            "state": truth.states,
            "status": truth.status,
            "reason": truth.reason,
            "event_time": truth.event_time,
            "end_time": truth.valid_until if truth.end_time is not None else np.full(n_runs, truth.time[-1]),
            "params": Group(data={k: np.ascontiguousarray(v) for k, v in truth.params.items()}),
            "interfaces": truth.interfaces,
        },
        attrs={"names": model.state_names, "units": model.state_units, "angles": model.angle_states},
        dataset_attrs={"state": {"names": model.state_names, "units": model.state_units,
                                 "angles": model.angle_states}},
    )
    inputs = Group()
    for k, v in truth.input_dict().items():
        inputs.data[k] = v[..., 0] if v.shape[-1] == 1 else v
    if truth.case is not None:
        inputs.data["case"] = truth.case
        inputs.attrs["case_labels"] = truth.case_labels
    for k in model.input_names:
        inputs.attrs[f"{k}_unit"] = model.input_units[k]
        inputs.dataset_attrs[k] = {"unit": model.input_units[k]}
    root.data["inputs"] = inputs
    if truth.trial_ids is not None:
        root.data["truth"].data["trial_id"] = np.array(truth.trial_ids)
    if truth.param_case is not None:
        root.data["truth"].data["param_case"] = truth.param_case
        root.data["truth"].dataset_attrs["param_case"] = {"labels": truth.param_case_labels}
    meas = Group()
    for s in sensors:
        st = streams[s.name]
        attrs = {k: v for k, v in st.attrs.items() if not isinstance(v, np.ndarray)}
        data = {
            "t": st.t, "t_available": st.t_available, "index": st.index,
            "value": st.value, "valid": st.valid, "sigma": st.sigma,
        }
        data.update({k: v for k, v in st.attrs.items() if isinstance(v, np.ndarray)})
        meas.data[s.name] = Group(data=data, attrs={"names": st.names, "units": st.units, **attrs},
                                  dataset_attrs={"value": {"names": st.names, "units": st.units}})
    root.data["measurements"] = meas
    est = Group()
    for name, post in estimates.items():
        data = {"state": post.state, "status": post.status, "reason": post.reason}
        attrs = {"names": post.names, "units": post.units, "angles": post.angle_states,
                 "type": next(o.type for o in cfg.observers if (o.name or o.type) == name),
                 "layout": cfg.output.covariance, "stride": cfg.output.store_every}
        if post.cov is not None:
            data["cov"] = post.cov
            data["cov_index"] = cov_steps(T, cfg.output.store_every)
        data.update(post.extras)
        attrs.update(post.attrs)
        if starts and name in starts:
            attrs["start"] = starts[name]
        ds = {"state": {"names": post.names, "units": post.units, "angles": post.angle_states}}
        if post.cov is not None:
            ds["cov"] = {"layout": cfg.output.covariance, "stride": cfg.output.store_every}
        est.data[name] = Group(data=data, attrs=attrs, dataset_attrs=ds)
    root.data["estimates"] = est
    if control:  # closed loops only: what each controller did
        root.data["control"] = Group(data=dict(control))
    return root
