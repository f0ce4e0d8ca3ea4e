"""``needle sweep``: grid files, cells validated up front, seeds, executors that agree cell by cell
(local processes, a Dask cluster, inline), resume after an interrupted sweep, failing cells."""

from __future__ import annotations

import os
from pathlib import Path

import pandas as pd
import pytest
import yaml
from typer.testing import CliRunner

import needlecli.experiments.simulation.runner as runner
from needlecli.cli.app import app
from needlecli.errors import ConfigError
from needlecli.experiments.studies.sweep import (
    SEED_KEY,
    Grid,
    SweepError,
    derived_seed,
    grid_overrides,
    load_grid,
    plan_sweep,
    results_complete,
    run_sweep,
)

TINY = """\
format: 2
name: tiny_sweep
model: {type: modified_unicycle, params: {kappa: 0.005, beta_cut: 0.035}, param_std: {kappa: 0.001}}
inputs: {v: 1.5, u: 0.0}
sensors:
  - {name: us3d, type: position, rate: 2.0, sigma: 0.3}
  - {name: robot, type: encoder, rate: 50.0, channels: [roll], sigma: 0.0035}
  - {name: swe, type: elastography, rate: 1.0, sigma: 0.001}
observers:
  - name: ukf
    type: ukf
    q: {x: 1.4142135623730951e-2, y: 1.4142135623730951e-2, z: 1.4142135623730951e-2, alpha: 1.4142135623730951e-4,
        beta: 1.4142135623730951e-4, gamma: 3.5355339059327378e-3, kappa: 1.4142135623730951e-5}
    p0: {x: 1.0, y: 1.0, z: 1.0, alpha: 5.0e-3, beta: 5.0e-3, gamma: 0.1, kappa: 2.0e-6}
    init: {from: truth, std: {alpha: 0.0873, beta: 0.0873}, first_measurement: {x: us3d.x, y: us3d.y, z: us3d.z}}
  - {name: ol, type: open_loop}
runs: {count: 2, seed: 5}
stop: {depth: 3.0}
simulation: {dt: 0.02}
output: {store_every: 10, covariance: diag}
"""
GRID = """\
description: tiny curvature process noise sweep
grid:
  observers.0.q.kappa: [1.0e-6, 8.0e-6]
  runs.seed: range(2)
"""


def invoke(*args):
    return CliRunner().invoke(app, [str(a) for a in args])


@pytest.fixture()
def files(tmp_path: Path) -> tuple[Path, Path]:
    (tmp_path / "tiny.yaml").write_text(TINY)
    (tmp_path / "grid.yaml").write_text(GRID)
    return tmp_path / "tiny.yaml", tmp_path / "grid.yaml"


def table(out: Path) -> pd.DataFrame:
    return pd.read_csv(out / "sweep.csv").drop(columns=["seconds"])


def mtimes(out: Path) -> dict[str, int]:
    return {p.name: p.stat().st_mtime_ns for p in (out / "cells").glob("*.h5")}


# ---------------------------------------------------------------------------------------------- grid file
def test_grid_axes_cells_and_random_samples_make_the_product():
    g = Grid.model_validate({
        "cells": [{"observers.0.alpha": 1e-3}, {"observers.0.alpha": 1e-2}],
        "random": {"count": 3, "seed": 1, "params": {"observers.0.q.kappa": {"loguniform": [1e-7, 1e-5]}}},
        "grid": {"runs.seed": "range(1, 3)", "sensors.0.rate": {"linspace": [1.0, 2.0, 3]}},
    })
    ov = grid_overrides(g)
    assert len(ov) == 2 * 3 * 2 * 3
    assert ov[0] == {"observers.0.alpha": 1e-3, "observers.0.q.kappa": ov[0]["observers.0.q.kappa"],
                     "runs.seed": 1, "sensors.0.rate": 1.0}
    assert [o["sensors.0.rate"] for o in ov[:3]] == [1.0, 1.5, 2.0]  # the last axis varies fastest
    assert all(1e-7 <= o["observers.0.q.kappa"] < 1e-5 for o in ov)
    assert ov == grid_overrides(g)  # random samples are reproducible
    assert Grid.model_validate({"grid": {"a.b": {"geomspace": [1.0, 100.0, 3]}}}).grid["a.b"] == pytest.approx([1, 10, 100])


def test_seed_rule(files, tmp_path):
    config, _ = files
    g = Grid.model_validate({"seed": 11, "grid": {"observers.0.q.kappa": [1e-6, 2e-6]}})
    common = plan_sweep(config, g, out_dir=tmp_path / "out")  # common random numbers by default
    assert [(c.seed, c.seed_from) for c in common] == [(11, "common"), (11, "common")]
    assert {yaml.safe_load(c.config_text)["runs"]["seed"] for c in common} == {11}
    unseeded = plan_sweep(config, Grid.model_validate({"grid": {"observers.0.q.kappa": [1e-6, 2e-6]}}),
                          out_dir=tmp_path / "out")
    assert {c.seed for c in unseeded} == {5}  # the sweep seed defaults to the config's runs.seed
    cells = plan_sweep(config, g.model_copy(update={"seeds": "derived"}), out_dir=tmp_path / "out")
    assert [c.seed_from for c in cells] == ["derived", "derived"]
    assert cells[0].seed == derived_seed(11, {"observers.0.q.kappa": 1e-6}) != cells[1].seed
    assert cells == plan_sweep(config, g.model_copy(update={"seeds": "derived"}), out_dir=tmp_path / "out")
    explicit = plan_sweep(config, Grid.model_validate({"grid": {SEED_KEY: [4, 9]}}), out_dir=tmp_path / "out")
    assert [(c.seed, c.seed_from) for c in explicit] == [(4, "grid"), (9, "grid")]
    assert yaml.safe_load(explicit[1].config_text)["runs"]["seed"] == 9


BAD_GRIDS = {
    "unknown key": ("grid: {runs.seed: [1]}\ncells_: []\n", "[cells_] unknown key"),
    "empty": ("seed: 3\n", "give at least one of grid, cells, random"),
    "bad range": ("grid: {runs.seed: 'range(x)'}\n", "range(stop)"),
    "empty axis": ("grid: {runs.seed: []}\n", "at least one value"),
    "key twice": ("fixed: {runs.count: 2}\ngrid: {runs.count: [1, 2]}\n", "runs.count is set in both fixed and grid"),
    "bad distribution": ("random: {count: 2, params: {runs.seed: {uniform: [2, 1]}}}\n", "lo < hi"),
    "not a path": ("grid: {'observers[0]': [1]}\n", "not a dotted config path"),
    "invalid value": ("grid: {observers.0.q.kappa: [1.0e-6, -1.0]}\n",
                      "cell 1 of 2 (observers.0.q.kappa = -1)"),
    "no such entry": ("grid: {observers.5.q.kappa: [1.0e-6]}\n", "[observers -> 5] no such list entry"),
    "unknown state": ("grid: {observers.0.q.kapa: [1.0e-6]}\n", "[observers -> 0 -> q -> kapa]"),
    "yaml": ("grid: {a: [1, 2}\n", "YAML syntax error"),
}


@pytest.mark.parametrize("name", list(BAD_GRIDS))
def test_bad_grid_is_one_clear_error_and_runs_nothing(files, tmp_path, name):
    config, _ = files
    text, expected = BAD_GRIDS[name]
    grid = tmp_path / "bad.yaml"
    grid.write_text(text)
    r = invoke("sweep", config, "--grid", grid, "--out", tmp_path / "out", "--executor", "inline", "--quiet")
    assert r.exit_code == 2, r.output
    assert expected in r.output and str(grid) in r.output
    assert "Traceback" not in r.output and len(r.output.strip().splitlines()) == 1
    assert not (tmp_path / "out").exists()


def test_missing_grid_file(files, tmp_path):
    with pytest.raises(ConfigError, match="no such file"):
        load_grid(tmp_path / "nope.yaml")


# ---------------------------------------------------------------------------------------------- executors
def test_local_processes_and_dask_cluster_give_the_same_table(files, tmp_path):
    distributed = pytest.importorskip("distributed", reason="needs dask[distributed] (pip install 'needlecli[dask]')")
    config, grid = files
    local = tmp_path / "local"
    r = invoke("sweep", config, "--grid", grid, "--out", local, "--workers", "2", "--quiet")
    assert r.exit_code == 0, r.output
    assert "sweep_E_xyz_mean_vs_observers.0.q.kappa.png" in r.output
    assert (local / "sweep_E_xyz_mean_vs_observers.0.q.kappa.png").stat().st_size > 1000
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=False, protocol="tcp", host="127.0.0.1",
                                  dashboard_address=":0") as cluster:
        dask = tmp_path / "dask"
        r = invoke("sweep", config, "--grid", grid, "--out", dask, "--executor", "dask",
                   "--scheduler", cluster.scheduler_address, "--quiet")
        assert r.exit_code == 0, r.output
    a, b = table(local), table(dask)
    assert len(a) == 4 * 2 and set(a["status"]) == {"ok"}  # 4 cells x 2 observers
    pd.testing.assert_frame_equal(a, b)  # cell by cell, to the last digit
    assert sorted(mtimes(local)) == sorted(mtimes(dask))  # the same cell ids
    md = (local / "sweep.md").read_text()
    assert "E_xyz_mean" in md and "observers.0.q.kappa" in md


def test_dask_without_a_scheduler_reports_it(files, tmp_path, monkeypatch):
    pytest.importorskip("distributed", reason="needs dask[distributed]")
    monkeypatch.setattr("needlecli.experiments.studies.sweep.execution.CONNECT_TIMEOUT", "1s")
    config, grid = files
    r = invoke("sweep", config, "--grid", grid, "--out", tmp_path / "o", "--executor", "dask",
               "--scheduler", "tcp://127.0.0.1:9", "--quiet")
    assert r.exit_code == 2 and "cannot reach the Dask scheduler at tcp://127.0.0.1:9" in r.output


# ---------------------------------------------------------------------------------------------- resume, failures
def test_failing_cells_are_recorded_and_resume_reruns_only_unfinished_cells(files, tmp_path, monkeypatch):
    config, grid = files
    out = tmp_path / "out"
    real = runner.run_experiment
    calls: list[int] = []

    def aborting(cfg, text, **kw):  # the sweep is "killed" before the cells with seed 1 finish
        calls.append(cfg.runs.seed)
        if cfg.runs.seed == 1:
            raise RuntimeError("simulated crash of the cell")
        return real(cfg, text, **kw)

    monkeypatch.setattr(runner, "run_experiment", aborting)
    r = invoke("sweep", config, "--grid", grid, "--out", out, "--executor", "inline", "--quiet")
    assert r.exit_code == 1, r.output  # failed cells: exit 1, after every cell ran
    assert sorted(calls) == [0, 0, 1, 1]
    t = table(out)
    failed = t[t["status"] == "failed"]
    assert len(failed) == 4 and set(failed[SEED_KEY]) == {1}  # 2 cells x 2 observers
    assert failed["error"].str.contains("RuntimeError: simulated crash").all()
    assert set(t[t["status"] == "ok"][SEED_KEY]) == {0} and t[t["status"] == "ok"]["E_xyz_mean"].notna().all()
    errors = sorted((out / "cells").glob("*.error.txt"))
    assert len(errors) == 2 and "simulated crash" in errors[0].read_text() and "Traceback" in errors[0].read_text()
    before = mtimes(out)
    assert len(before) == 2

    calls.clear()
    monkeypatch.setattr(runner, "run_experiment", lambda cfg, text, **kw: (calls.append(cfg.runs.seed), real(cfg, text, **kw))[1])
    r = invoke("sweep", config, "--grid", grid, "--out", out, "--executor", "inline", "--resume")
    assert r.exit_code == 0, r.output
    assert sorted(calls) == [1, 1]  # only the unfinished cells ran again
    assert "2 run, 2 skipped as complete, 0 failed" in r.output
    after = mtimes(out)
    assert {k: after[k] for k in before} == before  # complete cells untouched
    assert not list((out / "cells").glob("*.error.txt"))
    t2 = table(out)
    assert set(t2["status"]) == {"ok"} and len(t2) == 8
    cols = [c for c in t.columns if c not in ("error", "failures")]
    pd.testing.assert_frame_equal(t2[t2[SEED_KEY] == 0][cols].reset_index(drop=True),
                                  t[t[SEED_KEY] == 0][cols].reset_index(drop=True))

    # a results file deleted or from another config is not complete; a truncated one neither
    victim = sorted((out / "cells").glob("*.h5"))[0]
    victim.unlink()
    other = sorted((out / "cells").glob("*.h5"))[0]
    other.write_bytes(other.read_bytes()[:1000])
    calls.clear()
    r = invoke("sweep", config, "--grid", grid, "--out", out, "--executor", "inline", "--resume", "--quiet")
    assert r.exit_code == 0 and len(calls) == 2, r.output
    calls.clear()
    r = invoke("sweep", config, "--grid", grid, "--out", out, "--executor", "inline", "--resume", "--quiet",
               "--set", "runs.count=1")  # every cell's config changed: all run again
    assert r.exit_code == 0 and len(calls) == 4, r.output


def test_library_result_and_completeness(files, tmp_path):
    config, grid = files
    cells = plan_sweep(config, load_grid(grid), out_dir=tmp_path / "o", overrides=["runs.count=1"])
    res = run_sweep(cells[:1], out_dir=tmp_path / "o", executor="inline")
    assert res.ran == 1 and res.failed == 0 and results_complete(cells[0]) and not results_complete(cells[1])
    assert set(res.table["observer"]) == {"ukf", "ol"} and (res.table["runs"] == 1).all()
    assert res.units["E_xyz"] == "mm"
    with pytest.raises(SweepError, match="unknown executor"):
        run_sweep(cells[1:2], out_dir=tmp_path / "o", executor="threads")
    assert os.path.exists(tmp_path / "o" / "sweep.json")


def test_shipped_grid_makes_valid_cells(tmp_path):
    root = Path(__file__).resolve().parents[1]
    cells = plan_sweep(root / "configs/multirate-ukf-us3d/table1.yaml", load_grid(root / "configs/sweeps/multirate-ukf-us3d_q_kappa.yaml"),
                       out_dir=tmp_path)
    assert len(cells) == 50 and {c.seed for c in cells} == set(range(10))
    assert sorted({c.overrides["observers.0.q.kappa"] for c in cells}) == pytest.approx(
        [2e-6, 2e-6 * 10**0.5, 2e-5, 2e-5 * 10**0.5, 2e-4])
    assert all(yaml.safe_load(c.config_text)["runs"]["count"] == 10 for c in cells)


def test_dask_not_installed_is_a_clear_error(files, tmp_path, monkeypatch):
    import sys

    config, grid = files
    monkeypatch.setitem(sys.modules, "distributed", None)  # import distributed -> ImportError
    r = invoke("sweep", config, "--grid", grid, "--out", tmp_path / "o", "--executor", "dask", "--quiet")
    assert r.exit_code == 2 and "pip install 'needlecli[dask]'" in r.output, r.output


def test_sweep_reports_do_not_import_the_experiment_layer():
    """The table and plot read results files only: reports/sweep.py imports nothing from experiments or cli
    (at the top or inside a function)."""
    import ast

    import needlecli.reports.sweep as reports_sweep

    tree = ast.parse(Path(reports_sweep.__file__).read_text())
    imported = {n.module for n in ast.walk(tree) if isinstance(n, ast.ImportFrom) and n.module}
    imported |= {a.name for n in ast.walk(tree) if isinstance(n, ast.Import) for a in n.names}
    assert imported and not {m for m in imported if m.startswith(("needlecli.experiments", "needlecli.cli"))}


# ---------------------------------------------------------------------------------------------- common random numbers
#: TINY with an open loop that starts from the truth with 5 deg of noise on the angles, from its own start
#: (runs.common_start: none; shared, it would start from the UKF's first ultrasound sample): its errors come
#: from the truth and its own draws only, never from the sensors
TINY_OL = TINY.replace("  - {name: ol, type: open_loop}",
                       "  - {name: ol, type: open_loop, init: {from: truth, std: {alpha: 0.0873, beta: 0.0873}}}").replace(
    "runs: {count: 2, seed: 5}", "runs: {count: 2, seed: 5, common_start: none}")
METRICS = ["E_xyz_mean", "E_xyz_std", "E_xyz_max", "E_alpha_mean", "E_beta_mean", "E_kappa_mean"]


def test_cells_share_random_numbers_by_default(tmp_path):
    """Changing only a sensor the open loop does not use leaves its errors unchanged, to the last digit:
    every cell runs on the same seed, so the cells differ by their overrides alone."""
    config = tmp_path / "tiny_ol.yaml"
    config.write_text(TINY_OL)
    grid = tmp_path / "us_sigma.yaml"
    grid.write_text("grid: {sensors.0.sigma: [0.1, 0.6]}\n")  # us3d: the UKF's position sensor
    r = invoke("sweep", config, "--grid", grid, "--out", tmp_path / "crn", "--executor", "inline", "--quiet")
    assert r.exit_code == 0, r.output
    t = table(tmp_path / "crn")
    assert set(t[SEED_KEY]) == {5}  # the config's runs.seed, in every cell
    ol, ukf = t[t["observer"] == "ol"], t[t["observer"] == "ukf"]
    assert len(ol) == 2 and (ol["E_xyz_mean"] > 0.05).all()  # an error to compare, not zero
    assert (ol[METRICS].iloc[0] == ol[METRICS].iloc[1]).all()
    assert ukf["E_xyz_mean"].iloc[0] != ukf["E_xyz_mean"].iloc[1]  # the UKF does see the sensor

    # asked for, derived seeds give each cell its own noise: the open loop's errors then move with luck
    grid.write_text("seeds: derived\ngrid: {sensors.0.sigma: [0.1, 0.6]}\n")
    r = invoke("sweep", config, "--grid", grid, "--out", tmp_path / "derived", "--executor", "inline", "--quiet")
    assert r.exit_code == 0, r.output
    t = table(tmp_path / "derived")
    ol = t[t["observer"] == "ol"]
    assert t[SEED_KEY].nunique() == 2 and ol["E_xyz_mean"].iloc[0] != ol["E_xyz_mean"].iloc[1]


def test_plot_has_error_bars_over_replicate_seeds_and_the_parameter_with_its_unit(tmp_path):
    from needlecli.reports.sweep import sweep_figure

    config = tmp_path / "tiny_ol.yaml"
    config.write_text(TINY_OL)
    grid = Grid.model_validate({"description": "q_kappa", "fixed": {"runs.count": 1},
                                "grid": {"observers.0.q.kappa": [1e-6, 8e-6], SEED_KEY: "range(3)"}})
    res = run_sweep(plan_sweep(config, grid, out_dir=tmp_path / "o"), out_dir=tmp_path / "o", executor="inline")
    assert res.failed == 0
    fig = sweep_figure(res.table, metric="E_xyz_mean", param="observers.0.q.kappa", units=res.units, title="q_kappa")
    ax = fig.axes[0]
    assert ax.get_xlabel() == "ukf: q.kappa (process noise std per state) [(1/mm)/sqrt(s)]"
    assert ax.get_ylabel() == "E_xyz, mean over runs and time steps [mm]"
    assert "mean over 3 seeds, bars: \u00b11 std" in ax.get_title() and "the same seeds at every point" in ax.get_title()
    csv = pd.read_csv(tmp_path / "o" / "sweep.csv")
    drawn = {c.get_label(): c for c in ax.containers}
    assert sorted(drawn) == ["ol", "ukf"]
    for obs, c in drawn.items():
        expected = csv[csv["observer"] == obs].groupby("observers.0.q.kappa")["E_xyz_mean"]
        x, y = c.lines[0].get_data()
        assert list(x) == pytest.approx([1e-6, 8e-6]) and list(y) == pytest.approx(list(expected.mean()))
        half = [(seg[1, 1] - seg[0, 1]) / 2 for seg in c.lines[2][0].get_segments()]
        assert half == pytest.approx(list(expected.std(ddof=1)))  # +-1 std across the 3 seeds
        assert min(half) > 0
    import matplotlib.pyplot as plt

    plt.close(fig)
    md = (tmp_path / "o" / "sweep.md").read_text()
    assert "`observers.0.q.kappa`: ukf: q.kappa (process noise std per state) [(1/mm)/sqrt(s)]" in md


PARAM_UNITS = {
    "observers.0.q.kappa": ("ukf: q.kappa", "(1/mm)/sqrt(s)"),  # per square-root second, as the truth's
    "observers.0.p0.alpha": ("ukf: p0.alpha", "rad^2"),
    "observers.0.init.std.alpha": ("ukf: init.std.alpha", "rad"),
    "observers.0.measurements.us3d.sigma": ("ukf: measurements.us3d.sigma", "mm"),
    "observers.1.q.x": ("ol: q.x", "mm/sqrt(s)"),
    "sensors.0.sigma": ("us3d: sigma", "mm"),
    "sensors.1.sigma": ("robot: sigma", "rad"),
    "sensors.2.sigma": ("swe: sigma", "1/mm"),
    "sensors.0.rate": ("us3d: rate", "Hz"),
    "sensors.0.dropout": ("us3d: dropout", ""),
    "model.params.kappa": ("model.params.kappa", "1/mm"),
    "model.param_std.kappa": ("model.param_std.kappa", "1/mm"),
    "process_noise.std.kappa": ("process_noise.std.kappa", "(1/mm)/sqrt(s)"),
    "inputs.v": ("inputs.v", "mm/s"),
    "stop.depth": ("stop.depth", "mm"),
    "simulation.dt": ("simulation.dt", "s"),
    "runs.count": ("runs.count", ""),
}


def test_swept_keys_are_named_with_their_units(files, tmp_path):
    """Units from the schema's descriptions or the model (states, parameters, inputs, the sensors'
    channels), checked against the models' own unit attributes."""
    from needlecli.experiments.config.load import load_config
    from needlecli.experiments.studies.sweep.describe import describe_key
    from needlecli.models import MODELS

    config, _ = files
    values = {"observers.0.measurements.us3d.sigma": 0.3, "inputs.v": 1.0, "runs.count": 1, "stop.depth": 2.0,
              "simulation.dt": 0.02, "sensors.0.rate": 2.0, "sensors.0.dropout": 0.0}
    cell = {k: values.get(k, 1e-3) for k in PARAM_UNITS}
    (c,) = plan_sweep(config, Grid.model_validate({"cells": [cell]}), out_dir=tmp_path)
    assert {k: (v["name"], v["unit"]) for k, v in c.param_info.items() if k != SEED_KEY} == PARAM_UNITS
    model = MODELS.get("modified_unicycle")
    assert PARAM_UNITS["observers.0.q.kappa"][1] == f"({model.state_units[model.state_names.index('kappa')]})/sqrt(s)"
    assert PARAM_UNITS["inputs.v"][1] == model.input_units["v"]

    root = Path(__file__).resolve().parents[1]
    cfg, _ = load_config(root / "configs/em-magnetic-pratt2022/t2prelim.yaml")  # a model in metres
    mnm = MODELS.get(cfg.model.type)
    assert mnm.length_unit == "m"
    assert describe_key(cfg, "stop.depth")["unit"] == "m" and describe_key(cfg, "sensors.0.sigma")["unit"] == "m"
    assert describe_key(cfg, "model.params.c")["unit"] == "1/m"


# ---------------------------------------------------------------------------------------------- on a cluster
ROOT = Path(__file__).resolve().parents[1]

#: a lab's observer (an entry point of a package on PYTHONPATH): the open loop with a setting whose default
#: the test changes (GAIN), and one that kills its worker process (die: "once:<file>" the first time, or
#: "always")
LAB = '''\
import os, signal
from pathlib import Path
from typing import Literal
from needlecli.observers.open_loop import OpenLoop, OpenLoopSettings

class LabSettings(OpenLoopSettings):
    type: Literal["lab_ol"]
    gain: float = GAIN
    die: str = ""

class LabOL(OpenLoop):
    Settings = LabSettings

    def run(self, problem, rng, progress=None):
        die = self.settings.die
        if die == "always" or (die.startswith("once:") and not Path(die[5:]).exists()):
            if die.startswith("once:"):
                Path(die[5:]).write_text("died once")
            os.kill(os.getpid(), signal.SIGKILL)
        return super().run(problem, rng, progress)
'''


@pytest.fixture()
def lab(tmp_path) -> dict:
    """TINY with the lab's observer, the package on PYTHONPATH (commands run in processes of their own:
    registries read entry points once per process)."""
    site = tmp_path / "site"
    info = site / "labobs-0.1.dist-info"
    info.mkdir(parents=True)
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: labobs\nVersion: 0.1\n")
    (info / "entry_points.txt").write_text("[needlecli.observers]\nlab_ol = labobs:LabOL\n")
    (site / "labobs.py").write_text(LAB.replace("GAIN", "1.0"))
    (tmp_path / "tiny.yaml").write_text(TINY.replace("  - {name: ol, type: open_loop}", "  - {name: lab, type: lab_ol}"))
    (tmp_path / "grid.yaml").write_text(GRID)
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(site), str(ROOT)])}
    return {"dir": tmp_path, "site": site, "env": env}


def needle(env, cwd, *args):
    import subprocess
    import sys

    return subprocess.run([sys.executable, "-m", "needlecli", *map(str, args)], env=env, cwd=cwd, capture_output=True,
                          text=True)


def test_cell_by_cell_in_separate_processes_then_collect_gives_the_local_sweeps_table(files, tmp_path):
    """A job array: each cell by its index in a process of its own (``--cell I``), then ``--collect``:
    the table of a local sweep, to the last digit; the collect of a partial sweep says what is missing."""
    config, grid = files
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    n = needle(env, tmp_path, "sweep", config, "--grid", grid, "--dry-run", "--quiet")
    assert n.returncode == 0 and n.stdout.strip() == "4", n.stderr
    arr = tmp_path / "array"
    for i in (0, 2, 3):
        r = needle(env, tmp_path, "sweep", config, "--grid", grid, "--out", arr, "--cell", i)
        assert r.returncode == 0 and r.stdout.startswith(f"cell {i} of 4 ok in "), r.stderr
    r = invoke("sweep", config, "--grid", grid, "--out", arr, "--collect")
    assert r.exit_code == 1 and "3 complete, 0 failed, 1 missing" in r.output  # a partial table: exit 1
    assert (table(arr)["status"] == "not run").sum() == 2  # the missing cell's 2 observers
    r = needle(env, tmp_path, "sweep", config, "--grid", grid, "--out", arr, "--cell", 1)
    assert r.returncode == 0, r.stderr
    again = needle(env, tmp_path, "sweep", config, "--grid", grid, "--out", arr, "--cell", 1, "--resume")
    assert again.stdout.startswith("cell 1 of 4 complete from an earlier run"), again.stdout
    bad = needle(env, tmp_path, "sweep", config, "--grid", grid, "--out", arr, "--cell", 4)
    assert bad.returncode == 2 and bad.stderr.strip() == "error: --cell 4: the grid has 4 cell(s), numbered 0 to 3"
    r = invoke("sweep", config, "--grid", grid, "--out", arr, "--collect", "--quiet")
    assert r.exit_code == 0, r.output
    local = tmp_path / "local"
    r = invoke("sweep", config, "--grid", grid, "--out", local, "--workers", "2", "--quiet")
    assert r.exit_code == 0, r.output
    pd.testing.assert_frame_equal(table(arr), table(local))
    assert (arr / "sweep_E_xyz_mean_vs_observers.0.q.kappa.png").exists()


def test_a_worker_running_another_needlecli_is_refused_naming_it(files, tmp_path):
    distributed = pytest.importorskip("distributed", reason="needs dask[distributed] (pip install 'needlecli[dask]')")
    from needlecli.provenance import REPORT_ENV

    config, grid = files
    with distributed.LocalCluster(n_workers=1, threads_per_worker=1, processes=True, dashboard_address=":0",
                                  env={REPORT_ENV: "9.9.9 0123abc"}) as cluster:
        r = needle({**os.environ, "PYTHONPATH": str(ROOT)}, tmp_path, "sweep", config, "--grid", grid, "--out",
                   tmp_path / "o", "--executor", "dask", "--scheduler", cluster.scheduler_address, "--quiet")
    lines = r.stderr.strip().splitlines()
    assert r.returncode == 2 and len(lines) == 1, r.stderr
    assert lines[0].startswith("error: dask worker tcp://") and "runs needlecli 9.9.9 (git 0123abc)" in lines[0]
    assert not list((tmp_path / "o" / "cells").glob("*.h5"))  # no cell ran


def test_resume_runs_again_the_cells_whose_defaults_or_needlecli_changed(lab):
    d, env = lab["dir"], lab["env"]
    args = ("sweep", "tiny.yaml", "--grid", "grid.yaml", "--out", "out", "--executor", "inline", "--quiet")
    assert needle(env, d, *args).returncode == 0
    before = mtimes(d / "out")
    r = needle(env, d, *args, "--resume")
    assert r.returncode == 0 and mtimes(d / "out") == before, r.stderr  # nothing changed: nothing ran
    (lab["site"] / "labobs.py").write_text(LAB.replace("GAIN", "2.0"))  # a default the configs do not set
    r = needle(env, d, *args, "--resume")
    after = mtimes(d / "out")
    assert r.returncode == 0 and all(after[k] != before[k] for k in before), r.stderr  # every cell ran again
    r = needle({**env, "NEEDLECLI_REPORT_VERSION": "0.2.0"}, d, *args, "--resume")  # another needlecli
    assert r.returncode == 0 and all(mtimes(d / "out")[k] != after[k] for k in after), r.stderr


def test_a_dead_local_worker_fails_only_its_own_cell_after_one_retry(lab):
    """One cell kills its worker process the first time (it passes when run again), one every time (it
    fails, twice); the others are not touched; outside a terminal, one line per finished cell."""
    d, env = lab["dir"], lab["env"]
    (d / "grid.yaml").write_text(f"""\
cells:
  - {{observers.1.die: "once:{d / 'died'}"}}
  - {{observers.1.die: always}}
  - {{observers.1.die: ""}}
  - {{observers.1.die: "", observers.0.q.kappa: 8.0e-6}}
""")
    r = needle(env, d, "sweep", "tiny.yaml", "--grid", "grid.yaml", "--out", "out", "--workers", "2")
    assert r.returncode == 1, r.stderr
    t = table(d / "out")
    status = t.groupby("cell")["status"].first()
    assert sorted(status) == ["failed", "ok", "ok", "ok"] and (d / "died").exists()
    failed = t[t["status"] == "failed"]
    assert failed["error"].str.contains("its worker process ended (exit code -9), 2 time", regex=False).all()
    import re

    done = [ln for ln in r.stderr.splitlines() if re.match(r"cell \d/4 (ok|failed) in ", ln)]
    assert len(done) == 4, r.stderr
    assert sum("running it again" in ln for ln in r.stderr.splitlines()) == 2, r.stderr  # each dying cell once
    r = needle(env, d, "sweep", "tiny.yaml", "--grid", "grid.yaml", "--out", "out", "--resume", "--quiet")
    assert r.returncode == 1 and len(list((d / "out" / "cells").glob("*.error.txt"))) == 1  # beside the failed one


def test_the_code_state_counts_the_packages_own_changes_only(tmp_path):
    """What a sweep's resume key and its workers compare: the commit, and a hash of uncommitted changes to
    the package's files only; the same code gives the same answer, other code another."""
    import shutil
    import subprocess

    from needlecli.provenance import code_state

    if shutil.which("git") is None:
        pytest.skip("needs git")
    env = {**os.environ, "GIT_AUTHOR_NAME": "t", "GIT_AUTHOR_EMAIL": "t@t", "GIT_COMMITTER_NAME": "t",
           "GIT_COMMITTER_EMAIL": "t@t"}

    def git(*args):
        subprocess.run(["git", *args], cwd=tmp_path, env=env, check=True, capture_output=True)

    pkg = tmp_path / "pkg"
    pkg.mkdir()
    (pkg / "a.py").write_text("X = 1\n")
    (tmp_path / "notes.md").write_text("notes\n")
    git("init", "-q")
    git("add", ".")
    git("commit", "-qm", "first")
    clean = code_state(pkg)
    assert len(clean) == 40 and "+" not in clean
    (tmp_path / "notes.md").write_text("other notes\n")  # outside the package: not its code
    assert code_state(pkg) == clean
    (pkg / "a.py").write_text("X = 2\n")
    two = code_state(pkg)
    assert two.startswith(clean + "+") and len(two) == 41 + 12
    (pkg / "a.py").write_text("X = 3\n")
    assert code_state(pkg) not in (clean, two)  # other uncommitted code: another state
    (pkg / "a.py").write_text("X = 2\n")
    assert code_state(pkg) == two  # the same code: the same state
    (pkg / "b.py").write_text("Y = 1\n")  # a new file of the package, not yet added
    assert code_state(pkg) not in (clean, two)
