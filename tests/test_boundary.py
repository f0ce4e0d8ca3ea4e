"""Components are checked at the boundary (issue 24, item 2): a plug-in that fails, calls ``sys.exit``,
returns what breaks its role's contract, or whose entry point is not a class, is one ``error:`` line
naming it and its package, exit 2, no traceback and nothing written; ``needle compare`` makes its row say
why and runs the others. Each plug-in is a distribution of its own in a temporary folder on the
subprocess's PYTHONPATH (no pip install)."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from needlecli.errors import ComponentError
from needlecli.guard import Component, failure
from needlecli.registry import PluginError, Registry

ROOT = Path(__file__).resolve().parent.parent

CONFIG = """\
name: bound
model: {type: unicycle, params: {kappa: 0.004}}
inputs: {v: 2.0, u: 0.0}
sensors: [{name: us, type: %(sensor)s, rate: 5.0, sigma: 0.2}]
observers: [{name: mine, type: %(observer)s}%(others)s]
runs: {count: 3, seed: 1}
stop: {time: 2.0}
simulation: {kernels: numpy}
output: {store_every: 2}
"""

#: an observer that holds the model's default state with unit covariances, then breaks its contract as
#: BODY says (``x`` state (N, T, n), ``cov`` (N, K, n, n), ``status``, ``reason`` (N,))
OBSERVER = '''\
import sys
from typing import Literal
import numpy as np
from needlecli.observers import OBSERVERS, Observer, ObserverSettings, Posterior

class Settings(ObserverSettings):
    type: Literal["%(type)s"]

class Bad(Observer):
    Settings = Settings
    def run(self, problem, rng, progress=None):
        m = problem.model
        N, T, n = problem.n_runs, len(problem.time), m.n
        x = np.broadcast_to(m.initial_state(problem.params), (N, T, n)).copy()
        K = len(range(0, T, problem.cov_stride))
        cov = np.broadcast_to(np.eye(n), (N, K, n, n)).copy()
        status, reason = np.full(N, "ok"), np.full(N, "")
%(body)s
        return Posterior(state=x, cov=cov, status=status, reason=reason, names=m.state_names,
                         units=m.state_units, angle_states=m.angle_states)
'''

CASES = {  # case -> (body of run, what the error line says)
    "shape": ("x = x[..., :-1]", "run returned state of shape (3, 201, 5), expected (N, T, n) = (3, 201, 6)"),
    "nan": ("x[1, 4, 2] = np.nan", "state[1, 4, 2] = nan in run 1, whose status is ok"),
    "asymmetric": ("cov[2, 3, 0, 1] = 0.5", "a covariance that is not symmetric: run 2, stored time 3"),
    "indefinite": ("cov[0, 5] = -np.eye(n)", "a covariance that is not positive semi-definite: run 0, stored time 5"),
    "exit": ("sys.exit(0)", "run called sys.exit(0)"),
    "raises": ("raise ValueError('boom from the lab')", "run raised ValueError: boom from the lab"),
}

#: a position sensor whose h gives one channel fewer than it names
SENSOR = '''\
from typing import Literal
import numpy as np
from needlecli.sensors import SENSORS, Sensor, SensorSettings

class Settings(SensorSettings):
    type: Literal["short_position"]
    sigma: float = 0.1

class ShortPosition(Sensor):
    Settings = Settings
    channel_names = ("x", "y", "z")
    channel_units = ("mm", "mm", "mm")
    def h(self, x):
        return x[..., :2]
    def sigma(self, truth, idx):
        return np.full(2, self.settings.sigma)
'''


def _config(observer: str, sensor: str = "position", others: str = "") -> str:
    return CONFIG % {"observer": observer, "sensor": sensor, "others": others}


def _dist(site: Path, dist: str, module: str, source: str, entry_points: str) -> None:
    """A distribution ``dist`` in ``site``: ``module.py`` and its dist-info with ``entry_points``."""
    (site / f"{module}.py").write_text(source)
    info = site / f"{dist}-0.1.dist-info"
    info.mkdir(parents=True)
    (info / "METADATA").write_text(f"Metadata-Version: 2.1\nName: {dist}\nVersion: 0.1\n")
    (info / "entry_points.txt").write_text(textwrap.dedent(entry_points))


def _env(site: Path) -> dict:
    return {**os.environ, "PYTHONPATH": os.pathsep.join([str(site), str(ROOT)])}


def _needle(args, site: Path, cwd: Path) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "needlecli", *args], env=_env(site), cwd=cwd,
                          capture_output=True, text=True)


def _observer_plugin(tmp_path: Path, case: str) -> tuple[Path, str]:
    site = tmp_path / "site"
    site.mkdir()
    dist, typ = f"needle-bad-{case}", f"bad_{case}"
    body = textwrap.indent(CASES[case][0], " " * 8)
    _dist(site, dist, f"bad_{case}", OBSERVER % {"type": typ, "body": body},
          f"[needlecli.observers]\n{typ} = bad_{case}:Bad\n")
    return site, typ


def _simulate_fails(tmp_path: Path, site: Path, config: str, *says: str) -> str:
    """``needle simulate`` exits 2 with one ``error:`` line holding ``says``, no traceback, and leaves the
    earlier results file at its path as it was."""
    cfg = tmp_path / "bound.yaml"
    cfg.write_text(config)
    out = tmp_path / "bound.h5"
    out.write_bytes(b"the earlier results file")
    p = _needle(["simulate", str(cfg), "--out", str(out), "--quiet"], site, tmp_path)
    lines = p.stderr.strip().splitlines()
    assert p.returncode == 2, p.stderr
    assert len(lines) == 1 and lines[0].startswith("error: "), p.stderr
    assert "Traceback" not in p.stderr + p.stdout
    for s in says:
        assert s in lines[0], lines[0]
    assert out.read_bytes() == b"the earlier results file"
    assert sorted(x.name for x in tmp_path.iterdir()) == ["bound.h5", "bound.yaml", "site"]  # nothing else
    return lines[0]


# ---------------------------------------------------------------------------------------------- simulate
@pytest.mark.parametrize("case", list(CASES))
def test_bad_plugin_observer_is_one_line_and_writes_nothing(tmp_path, case):
    site, typ = _observer_plugin(tmp_path, case)
    _simulate_fails(tmp_path, site, _config(typ),
                    f"error: observer 'mine' (type {typ}, package needle-bad-{case}): ", CASES[case][1])


def test_nan_in_a_run_marked_diverged_is_kept(tmp_path):
    """The counterpart of case ``nan``: a run the observer marks diverged may hold NaN from where it stopped."""
    site = tmp_path / "site"
    site.mkdir()
    body = textwrap.indent("x[1, 4:] = np.nan\ncov[1, 2:] = np.nan\nstatus[1] = 'diverged'\nreason[1] = 'lost'", " " * 8)
    _dist(site, "needle-nan-diverged", "nan_diverged", OBSERVER % {"type": "nan_diverged", "body": body},
          "[needlecli.observers]\nnan_diverged = nan_diverged:Bad\n")
    cfg = tmp_path / "ok.yaml"
    cfg.write_text(_config("nan_diverged"))
    p = _needle(["simulate", str(cfg), "--out", str(tmp_path / "ok.h5"), "--quiet"], site, tmp_path)
    assert p.returncode == 0, p.stderr
    assert (tmp_path / "ok.h5").is_file()


@pytest.mark.parametrize("value, is_what", [("def make(settings):\n    return None\n", "is a function"),
                                             ("VALUE = 3\n", "is an int (3)")])
def test_entry_point_that_is_not_a_class(tmp_path, value, is_what):
    site = tmp_path / "site"
    site.mkdir()
    attr = "make" if value.startswith("def") else "VALUE"
    _dist(site, "needle-not-a-class", "notaclass", value, f"[needlecli.observers]\nodd = notaclass:{attr}\n")
    line = _simulate_fails(tmp_path, site, _config("odd"),
                           "[observers -> 0 -> type] observer type 'odd' of package 'needle-not-a-class' "
                           f"(entry point needlecli.observers: notaclass:{attr}): {is_what}, not a subclass of Observer")
    assert line.startswith(f"error: {tmp_path / 'bound.yaml'}: ")


def test_plugin_sensor_of_the_wrong_shape(tmp_path):
    site = tmp_path / "site"
    site.mkdir()
    _dist(site, "needle-short-sensor", "short_sensor", SENSOR,
          "[needlecli.sensors]\nshort_position = short_sensor:ShortPosition\n")
    _simulate_fails(tmp_path, site, _config("open_loop", sensor="short_position"),
                    "error: sensor 'us' (type short_position, package needle-short-sensor): measure returned "
                    "value of shape (3, 11, 2), expected (N, M, m) = (3, 11, 3)")


# ---------------------------------------------------------------------------------------------- compare
@pytest.mark.parametrize("case", ["exit", "shape"])
def test_compare_keeps_going_and_its_row_says_why(tmp_path, case):
    site, typ = _observer_plugin(tmp_path, case)
    cfg = tmp_path / "bound.yaml"
    cfg.write_text(_config(typ, others=", {name: ol, type: open_loop}"))
    out = tmp_path / "cmp"
    p = _needle(["compare", str(cfg), "--observers", "mine,ol", "--out", str(out), "--quiet"], site, tmp_path)
    assert p.returncode == 0, p.stderr
    assert "Traceback" not in p.stderr + p.stdout
    rows = pd.read_csv(out / "compare.csv").set_index("observer")
    assert CASES[case][1] in rows.loc["mine", "failure_reasons"]
    assert rows.loc["mine", "runs_failed"] == 3
    assert rows.loc["ol", "runs_failed"] == 0 and np.isfinite(rows.loc["ol", "E_xyz_mean"])
    assert "mine: " + CASES[case][1] in " ".join(p.stdout.split())


# ---------------------------------------------------------------------------------------------- the guard
def test_guard_passes_interrupts_and_user_errors_through():
    comp = Component("observer", "mine", "bad", "needle-bad")

    def fails(e):
        def f():
            raise e
        return f

    for e in (KeyboardInterrupt(), MemoryError(), ComponentError("x", "y")):
        with pytest.raises(type(e)):
            comp.call("run", fails(e))
    wrapped = RuntimeError("a library's own")  # a signal a library turned into its own exception
    wrapped.__context__ = KeyboardInterrupt()
    with pytest.raises(RuntimeError):
        comp.call("run", fails(wrapped))
    with pytest.raises(ComponentError) as info:
        comp.call("run", fails(SystemExit("bye")))
    assert str(info.value) == "observer 'mine' (type bad, package needle-bad): run called sys.exit('bye')"
    assert failure(ValueError("two\nlines")) == "raised ValueError: two lines"


def test_registry_declares_what_its_components_are(tmp_path, monkeypatch):
    """Tables and plots are functions; classes of a registry subclass its base (named lazily)."""
    site = tmp_path / "site"
    site.mkdir()
    _dist(site, "needle-lab-tables", "labtables", "def table(results, errors):\n    return None\nN = 3\n",
          "[needlecli.test_tables]\ngood = labtables:table\nnumber = labtables:N\n"
          "[needlecli.test_classes]\nfn = labtables:table\nexc = builtins:ValueError\n")
    monkeypatch.syspath_prepend(str(site))
    tables = Registry("table", group="needlecli.test_tables", base=callable)
    assert tables.get("good").__name__ == "table"
    with pytest.raises(PluginError, match=r"table 'number' of package 'needle-lab-tables' \(entry point "
                       r"needlecli.test_tables: labtables:N\): is an int \(3\), not a function"):
        tables.get("number")
    classes = Registry("observer type", group="needlecli.test_classes", base="needlecli.observers.base:Observer")
    with pytest.raises(PluginError, match="is a function, not a subclass of Observer"):
        classes.get("fn")
    with pytest.raises(PluginError, match="is the class ValueError, not a subclass of Observer"):
        classes.get("exc")
    assert classes.kind == "observer" and tables.kind == "table"
