"""Closed-loop experiments: the truth simulated as a stepper, the controllers' sensor measured in the
same pass, frame by frame, and the controllers acting between grid steps.

The sensor in the loop measures once (its random stream ``sensor/<name>``, as in open loop); its
pipeline's ``geometry(j)`` advances the simulation lazily to the sample's grid index and the device's
``on_frame`` hands the sample to the controllers, whose commands act from the first grid time at or after
the sample's availability. That pass is the measurement stream recorded in the results file. The other
sensors measure the finished truth as in open loop, each from its own stream.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from needlecli.experiments.simulation import components
from needlecli.experiments.simulation.truth import TruthSimulator, stream

if TYPE_CHECKING:
    from needlecli.experiments.config.types import ExperimentConfig


def simulate_closed_loop(cfg: ExperimentConfig, *, progress=None):
    """Simulate, measure and control every run of a config with a ``control:`` section.

    Returns ``(truth, sensors, streams, control)``: ``control`` maps each controller's name to the
    :class:`~needlecli.io.results.Group` of what it did.
    """
    seed = cfg.runs.seed
    sim = components.simulated(cfg, "simulate", TruthSimulator, cfg, progress=progress)
    model = sim.model
    sensors = components.build_sensors(cfg, model)
    by_name = {s.name: s for s in sensors}
    controllers = [components.GuardedController(c, model) for c in cfg.control]  # every call guarded
    in_loop = {c.settings.sensor for c in controllers}
    if len(in_loop) != 1:  # the config check says so already
        raise ValueError("every controller must read the same sensor")
    loop_sensor = by_name[next(iter(in_loop))]
    idx = loop_sensor.sample_indices(sim.time)
    t_available = sim.time[idx] + loop_sensor.settings.latency
    for c in controllers:
        c.start(sim.time, sim.n_runs, idx, t_available)

    def before_step(k, x):
        for c in controllers:
            x = c.before_step(k, x)
        return x

    def on_frame(j, outputs):
        for c in controllers:
            c.on_sample(j, outputs)
            k = c.first_action(j)
            if k <= sim.acted:  # a command for a grid time already stepped from
                raise c.component.broke("first_action", f"grid index {k} for sample {j}, but the simulation "
                                        f"has stepped from index {sim.acted}")

    sim.before_step = before_step
    # the pass (the model stepped between the samples, the controllers called from on_frame, each guarded)
    live = components.sensor_component(loop_sensor)
    finish = live.call("measure_live", loop_sensor.measure_live, sim, stream(seed, f"sensor/{loop_sensor.name}"), on_frame)
    truth = components.simulated(cfg, "simulate", sim.finish)
    streams = {}
    for s in sensors:
        streams[s.name] = (components.measured(s, "measure_live", finish, truth) if s is loop_sensor
                           else components.measure(s, truth, stream(seed, f"sensor/{s.name}")))
    return truth, sensors, streams, {c.name: c.results(truth) for c in controllers}
