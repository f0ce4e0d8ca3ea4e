"""Components from other installed packages (entry points): a plug-in observer runs in a config, a broken
plug-in is one error line naming its package where it is used and breaks nothing else, and the example
package under examples/ installs with pip and runs (its own tests included)."""

from __future__ import annotations

import os
import site
import subprocess
import sys
import textwrap
import venv
from pathlib import Path

import h5py
import pytest

ROOT = Path(__file__).resolve().parent.parent
EXAMPLE = ROOT / "examples" / "needle-cv-observer"

CONFIG = """\
name: plug
model: {type: unicycle, params: {kappa: 0.004}}
inputs: {v: 2.0, u: 0.0}
sensors: [{name: us, type: position, rate: 5.0, sigma: 0.2}]
observers: [{name: mine, type: %s}, {name: ol, type: open_loop}]
runs: {count: 3, seed: 1}
stop: {time: 2.0}
"""

GOOD = '''\
from typing import Literal
import numpy as np
from needlecli.observers import OBSERVERS, Observer, ObserverSettings, Posterior

class Settings(ObserverSettings):
    type: Literal["nominal_start"]

class NominalStart(Observer):
    """Holds the model's default state: a minimal observer."""
    Settings = Settings
    def run(self, problem, rng, progress=None):
        m = problem.model
        x = np.broadcast_to(m.initial_state(problem.params), (problem.n_runs, len(problem.time), m.n)).copy()
        return Posterior(state=x, cov=None, status=np.full(problem.n_runs, "ok"), reason=np.full(problem.n_runs, ""),
                         names=m.state_names, units=m.state_units, angle_states=m.angle_states)
'''


def _dist(site: Path, dist: str, entry_points: str) -> None:
    info = site / f"{dist}-0.1.dist-info"
    info.mkdir(parents=True)
    (info / "METADATA").write_text(f"Metadata-Version: 2.1\nName: {dist}\nVersion: 0.1\n")
    (info / "entry_points.txt").write_text(textwrap.dedent(entry_points))


@pytest.fixture
def plugins(tmp_path) -> dict:
    """A folder on PYTHONPATH with two installed distributions: one good observer, one that cannot import."""
    site = tmp_path / "site"
    site.mkdir()
    (site / "goodplug.py").write_text(GOOD)
    (site / "brokenplug.py").write_text("import no_such_module_anywhere\n")
    _dist(site, "goodplug", "[needlecli.observers]\nnominal_start = goodplug:NominalStart\n")
    _dist(site, "brokenplug", "[needlecli.observers]\nbroken_obs = brokenplug:Nope\n")
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(site), str(ROOT)])}
    return {"env": env, "dir": tmp_path}


def _needle(args, env, cwd):
    return subprocess.run([sys.executable, "-m", "needlecli", *args], env=env, cwd=cwd, capture_output=True, text=True)


def test_plugin_observer_runs_in_a_config(plugins):
    cfg = plugins["dir"] / "plug.yaml"
    cfg.write_text(CONFIG % "nominal_start")
    out = plugins["dir"] / "plug.h5"
    p = _needle(["simulate", str(cfg), "--out", str(out), "--quiet"], plugins["env"], plugins["dir"])
    assert p.returncode == 0, p.stderr
    with h5py.File(out) as f:
        assert f["estimates/mine"].attrs["type"] == "nominal_start"
        assert f["estimates/mine/state"].shape == f["estimates/ol/state"].shape
    listing = _needle(["list"], plugins["env"], plugins["dir"])  # names only: nothing is imported
    assert listing.returncode == 0 and not listing.stderr
    assert "nominal_start (goodplug)" in listing.stdout and "broken_obs (brokenplug)" in listing.stdout
    listing = _needle(["list", "--details"], plugins["env"], plugins["dir"])  # loads them: one warning line
    assert listing.returncode == 0
    warn = [ln for ln in listing.stderr.splitlines() if "brokenplug" in ln]
    assert len(warn) == 1 and "cannot be imported" in warn[0] and "no_such_module_anywhere" in warn[0]


def test_broken_plugin_is_one_line_where_used(plugins):
    cfg = plugins["dir"] / "broken.yaml"
    cfg.write_text(CONFIG % "broken_obs")
    p = _needle(["simulate", str(cfg), "--quiet"], plugins["env"], plugins["dir"])
    assert p.returncode == 2
    lines = p.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"error: {cfg}: [observers -> 0 -> type] "), p.stderr
    assert "brokenplug" in lines[0] and "no_such_module_anywhere" in lines[0]
    assert "Traceback" not in p.stderr
    # ... and does not break the configs that do not use it, nor the other commands
    ok = _needle(["validate", str(ROOT / "configs" / "default.yaml")], plugins["env"], plugins["dir"])
    assert ok.returncode == 0, ok.stderr


def test_unknown_type_lists_plugins_too(plugins):
    cfg = plugins["dir"] / "typo.yaml"
    cfg.write_text(CONFIG % "nominal_strat")
    p = _needle(["validate", str(cfg)], plugins["env"], plugins["dir"])
    assert p.returncode == 2 and "nominal_start" in p.stderr and "ukf" in p.stderr


@pytest.mark.skipif(not (EXAMPLE / "pyproject.toml").exists(), reason="the example package is not in this checkout")
def test_example_package_installs_and_runs(tmp_path):
    """pip install -e the example plug-in into a fresh environment that sees this needlecli, then run a
    config that names its observer, and the package's own tests."""
    env_dir = tmp_path / "venv"
    venv.EnvBuilder(with_pip=False).create(env_dir)
    py = env_dir / ("Scripts" if os.name == "nt" else "bin") / "python"
    # The new environment sees this interpreter's packages (needlecli, pip, setuptools, wheel): made from
    # inside a venv, ``system_site_packages`` would give the *base* interpreter's site-packages instead
    # (no wheel there, an old setuptools), so the outer ones are added as site directories (their .pth
    # files, the editable install's among them, are processed).
    inner = subprocess.run([str(py), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                           capture_output=True, text=True, check=True).stdout.strip()
    outer = [p for p in [*site.getsitepackages(), site.getusersitepackages()] if Path(p).is_dir()]
    Path(inner).mkdir(parents=True, exist_ok=True)
    (Path(inner) / "outer_site.pth").write_text("".join(f"import site; site.addsitedir({p!r})\n" for p in outer))
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "VIRTUAL_ENV")}
    if os.environ.get("PYTHONPATH"):  # a worktree that shadows the installed needlecli
        env["PYTHONPATH"] = os.environ["PYTHONPATH"]
    pip = subprocess.run([str(py), "-m", "pip", "install", "--no-deps", "--no-build-isolation", "--no-index", "-q",
                          "-e", str(EXAMPLE)], env=env, capture_output=True, text=True)
    assert pip.returncode == 0, pip.stderr
    out = tmp_path / "cv.h5"
    p = subprocess.run([str(py), "-m", "needlecli", "simulate", str(EXAMPLE / "cv_study.yaml"), "--runs", "4",
                        "--set", "stop.depth=20", "--out", str(out), "--quiet"], env=env, capture_output=True, text=True)
    assert p.returncode == 0, p.stderr
    assert "cv" in p.stdout  # the summary table lists the plug-in's observer
    with h5py.File(out) as f:
        assert f["estimates/cv"].attrs["type"] == "cv_kf"
    t = subprocess.run([str(py), "-m", "pytest", "-q", "-p", "no:cacheprovider", str(EXAMPLE / "tests")],
                       env=env, capture_output=True, text=True, cwd=tmp_path)
    assert t.returncode == 0, t.stdout + t.stderr
