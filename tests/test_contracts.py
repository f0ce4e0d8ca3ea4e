"""A component declares its whole contract (issue 24): what ``needle compare`` derives for an observer, what
``from_fit`` may set on it and its part in the common start are declared by the observer class and read
through the registry, so that a plug-in is on the same footing as the built-ins; ``needle fit-em
--model`` takes every model a fit section can fit.

The plug-in: a tiny package in a temporary folder (a ``dist-info`` with an entry point, no pip install)
registers a UKF variant under its own name; in subprocesses it joins ``needle compare`` with the built-in
UKF's derived settings and is tuned by ``from_fit`` exactly as the UKF is, with nothing in needlecli
naming it.
"""

from __future__ import annotations

import ast
import os
import re
import subprocess
import sys
from pathlib import Path

import h5py
import numpy as np
import pytest
import yaml
from typer.testing import CliRunner

from needlecli.cli.app import app
from needlecli.observers import OBSERVERS

ROOT = Path(__file__).resolve().parent.parent
PKG = ROOT / "needlecli"

# the tutorial's unicycle study, small: 2 insertions of 10 mm, a tracker at 5 Hz; its fit section fits
# the unicycle (fit.models: [unicycle])
SMALL = yaml.safe_load((ROOT / "configs" / "tutorials" / "fit_em.yaml").read_text())
SMALL["runs"]["count"] = 2
SMALL["stop"]["depth"] = 10.0

MY_UKF = '''\
"""A lab's UKF variant: the built-in UKF under its own name (its own settings type)."""
from typing import Literal

from needlecli.observers.ukf import UKFSettings, UnscentedKalmanFilter


class MyUKFSettings(UKFSettings):
    type: Literal["my_ukf"]


class MyUKF(UnscentedKalmanFilter):
    Settings = MyUKFSettings
'''


@pytest.fixture(scope="module")
def lab(tmp_path_factory) -> dict:
    """A folder on PYTHONPATH holding the distribution ``myukf`` (entry point needlecli.observers:
    my_ukf = myukf:MyUKF) and one that cannot be imported, the small config, and a fit file of it by
    ``needle fit-em --model unicycle``."""
    d = tmp_path_factory.mktemp("lab")
    site = d / "site"
    (site / "myukf").mkdir(parents=True)
    (site / "myukf" / "__init__.py").write_text(MY_UKF)
    info = site / "myukf-0.1.dist-info"
    info.mkdir()
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: myukf\nVersion: 0.1\n")
    (info / "entry_points.txt").write_text("[needlecli.observers]\nmy_ukf = myukf:MyUKF\n")
    (site / "brokenobs.py").write_text("import no_such_module_anywhere\n")  # and a plug-in that cannot load
    info = site / "brokenobs-0.1.dist-info"
    info.mkdir()
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: brokenobs\nVersion: 0.1\n")
    (info / "entry_points.txt").write_text("[needlecli.observers]\nbroken_obs = brokenobs:Nope\n")
    cfg = d / "small.yaml"
    cfg.write_text(yaml.safe_dump(SMALL, sort_keys=False))
    r = CliRunner().invoke(app, ["fit-em", str(cfg), "--model", "unicycle", "--out", str(d / "fit.h5"), "--quiet"])
    assert r.exit_code == 0, r.output
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(site), str(ROOT)])}
    return {"dir": d, "config": cfg, "fit": d / "fit.h5", "env": env}


def _needle(args, lab):
    return subprocess.run([sys.executable, "-m", "needlecli", *map(str, args)], env=lab["env"], cwd=lab["dir"],
                          capture_output=True, text=True)


def _observers(path: Path) -> dict[str, dict]:
    """Each observer's settings as the run wrote them out (the results file's config), by name."""
    with h5py.File(path) as f:
        data = yaml.safe_load(f.attrs["config"])
    return {o["name"]: o for o in data["observers"]}


def _without(settings: dict, *keys: str) -> dict:
    return {k: v for k, v in settings.items() if k not in keys}


def _strs(a) -> list[str]:
    return [x.decode() if isinstance(x, bytes) else str(x) for x in a]


def test_fit_em_takes_every_model_a_fit_section_can_fit(lab, tmp_path):
    """--model unicycle on a config whose fit fits the unicycle (was: 'not one of mnm, binm, both')."""
    with h5py.File(lab["fit"]) as f:
        assert set(f["fit"]) == {"unicycle"} and _strs(f.attrs["models"]) == ["unicycle"]
        assert (f["fit/unicycle/status"][()].astype(str) == "ok").all()
    r = CliRunner().invoke(app, ["fit-em", str(lab["config"]), "--model", "bicycle", "--quiet"])
    assert r.exit_code == 2 and "--model" in r.output and "Traceback" not in r.output
    for accepted in ("unicycle", "mnm", "binm", "both"):  # the error names the accepted ones
        assert accepted in r.output
    r = CliRunner().invoke(app, ["fit-em", str(lab["config"]), "--model", "both", "--out", str(tmp_path / "b.h5"),
                                 "--quiet"])
    assert r.exit_code == 0, r.output  # both: every model of the config's fit section
    with h5py.File(tmp_path / "b.h5") as f:
        assert set(f["fit"]) == {"unicycle"}


def test_a_plugin_ukf_joins_compare_with_the_ukfs_derived_settings(lab):
    out = lab["dir"] / "cmp"
    p = _needle(["compare", lab["config"], "--observers", "ukf,my_ukf", "--out", out, "--quiet"], lab)
    assert p.returncode == 0, p.stderr
    path = out / "fit_em_compare.h5"
    obs = _observers(path)
    assert obs["my_ukf"]["type"] == "my_ukf" and obs["ukf"]["type"] == "ukf"
    assert _without(obs["my_ukf"], "type", "name") == _without(obs["ukf"], "type", "name")
    assert obs["ukf"]["measurements"]["tracker"]["sigma"] == 0.2 and "predict_at_depths" in obs["ukf"]  # derived
    with h5py.File(path) as f:
        g = f["compare"]
        rows = dict(zip(_strs(g["observer"][()]), zip(_strs(g["settings"][()]), _strs(g["start"][()]))))
        assert rows == {"ukf": ("defaults", "common (reference)"), "my_ukf": ("defaults", "common")}
        mine, builtin = f["estimates/my_ukf"], f["estimates/ukf"]
        assert set(mine) == set(builtin) and "state" in mine
        for k, v in builtin.items():  # the same start, the same filter: the same arrays
            if isinstance(v, h5py.Dataset):
                np.testing.assert_array_equal(mine[k][()], v[()], err_msg=k)
        assert f["estimates/my_ukf"].attrs["type"] == "my_ukf"
    assert "my_ukf" in p.stdout and "skipped: my_ukf" not in p.stdout
    # a plug-in installed beside the built-ins does not change a comparison that does not name it: the
    # reference with derived settings is still the built-in UKF's; a plug-in that cannot load is a skipped row
    p = _needle(["compare", lab["config"], "--observers", "high_gain,broken_obs", "--out", lab["dir"] / "hg", "--quiet"],
                lab)
    assert p.returncode == 0, p.stderr
    assert "skipped: broken_obs (broken_obs)" in p.stdout
    with h5py.File(lab["dir"] / "hg" / "fit_em_compare.h5") as f:  # high_gain gives no start of its own
        assert f["compare"].attrs["start"].startswith("ukf_reference's initial estimate")
        why = dict(zip(_strs(f["compare/skipped/observer"][()]), _strs(f["compare/skipped/reason"][()])))
        assert "brokenobs" in why["broken_obs"] and "no_such_module_anywhere" in why["broken_obs"]
        assert _strs(f["compare/start"][()]) == ["common; x, beta = 0"]


def test_a_plugin_ukf_is_tuned_by_from_fit_as_the_ukf_is(lab):
    data = dict(SMALL)
    ff = {"file": str(lab["fit"]), "model": "unicycle", "pick": "median"}
    data["observers"] = [{"name": "builtin", "type": "ukf", "rate": 5.0, "from_fit": ff},
                         {"name": "lab", "type": "my_ukf", "rate": 5.0, "from_fit": ff}]
    cfg = lab["dir"] / "tuned.yaml"
    cfg.write_text(yaml.safe_dump(data, sort_keys=False))
    out = lab["dir"] / "tuned.h5"
    p = _needle(["simulate", cfg, "--out", out, "--quiet"], lab)
    assert p.returncode == 0, p.stderr
    obs = _observers(out)
    assert "from_fit" not in obs["lab"] and "from_fit" not in obs["builtin"]  # expanded
    assert _without(obs["lab"], "type", "name") == _without(obs["builtin"], "type", "name")
    with h5py.File(lab["fit"]) as f:  # q per square-root second, the fit's sqrt(Q_ii), whatever the filter's rate
        g = f["fit/unicycle"]
        names = _strs(g.attrs["names"])
        Q = np.median(g["Q"][()], axis=0)
        kappa = float(np.median(g["constant/kappa"][()]))
    assert obs["lab"]["q"]["x"] == pytest.approx(np.sqrt(Q[names.index("x"), names.index("x")]), rel=1e-12)
    assert obs["lab"]["params"]["kappa"] == pytest.approx(kappa, rel=1e-12)
    assert len(obs["lab"]["measurements"]["tracker"]["sigma"]) == 3


def _strings(path: Path) -> list[tuple[int, str]]:
    """The string constants of a module that are not docstrings, with their line."""
    tree = ast.parse(path.read_text())
    docs = set()
    for node in ast.walk(tree):
        body = getattr(node, "body", None)
        if isinstance(body, list) and body and isinstance(body[0], ast.Expr) and isinstance(body[0].value, ast.Constant):
            docs.add(id(body[0].value))
    return [(n.lineno, n.value) for n in ast.walk(tree)
            if isinstance(n, ast.Constant) and isinstance(n.value, str) and id(n) not in docs]


def test_no_observer_type_is_named_outside_its_own_module():
    """The studies, the config (from_fit) and the reports read what they need of an observer through the
    registry: no string in experiments/ or reports/ names a built-in observer type."""
    names = OBSERVERS.builtin_names()
    token = re.compile(r"(?<!\w)(" + "|".join(map(re.escape, names)) + r")(?!\w)")
    found = []
    for folder in ("experiments", "reports"):
        for path in sorted((PKG / folder).rglob("*.py")):
            found += [f"{path.relative_to(ROOT)}:{line}: {text[:60]!r}" for line, text in _strings(path)
                      if token.search(text)]
    assert not found, "\n".join(found)


def test_what_an_observer_declares_is_read_through_the_registry():
    """Each built-in's declarations, as compare and from_fit used to hard-code them."""
    takes = {t: OBSERVERS.get(t).fit_takes for t in OBSERVERS.builtin_names()}
    assert {t for t, v in takes.items() if v is not None} == {"ukf", "ekf", "eks", "open_loop"}
    assert [t for t, v in takes.items() if v is not None and v.sensor_states] == ["ekf", "eks"]
    assert not takes["open_loop"].measurements and takes["ukf"].measurements
    assert [t for t in OBSERVERS.builtin_names() if OBSERVERS.get(t).default_reference] == ["ukf"]
    assert [t for t in OBSERVERS.builtin_names() if OBSERVERS.get(t).model_only] == ["open_loop"]
    hg = OBSERVERS.get("high_gain")
    s = hg.Settings.model_validate({"type": "high_gain", **hg.derived_settings(None)})
    assert hg.prescribed_start(s) == "x, beta = 0"
    assert hg.prescribed_start(hg.Settings.model_validate({"type": "high_gain"})) is None
    assert OBSERVERS.get("so3_invariant").derived_settings(None) == {}  # the schema's defaults
