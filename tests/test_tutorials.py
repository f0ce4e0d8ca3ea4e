"""The tutorials cannot go stale (issue 19): every ``console`` block of a tutorial page (and of Getting
started) is run, its ``$ needle ...`` commands in order in a fresh folder with the repository's configs,
and what each prints on stdout is compared with the lines the page shows: in order, word by word, numbers
within 1 % (``...`` on a line of its own skips any lines, ``…`` stands for one word, e.g. a runtime). A
``text`` block titled with a path (``title="results/x.md"``) is compared with that file the same way.
"""

from __future__ import annotations

import os
import re
import shlex
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from needlecli.cli.app import app

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"
PAGES = [DOCS / "getting-started.md", *sorted((DOCS / "tutorials").glob("*.md"))]
BLOCK = re.compile(r"^```(console|text title=\"([^\"]+)\")\n(.*?)^```", re.S | re.M)
REL_TOL = 0.01


def blocks(page: Path) -> list[tuple[str, str | None, str]]:
    """``(kind, file, body)`` of every checked block of a page, in order."""
    return [("console" if m.group(1) == "console" else "file", m.group(2), m.group(3))
            for m in BLOCK.finditer(page.read_text(encoding="utf-8"))]


def _number(tok: str) -> float | None:
    core = tok.strip(",;:()%*")
    try:
        return float(core) if re.fullmatch(r"[-+]?(\d+\.?\d*|\.\d+)(e[-+]?\d+)?", core) else None
    except ValueError:
        return None


def same_line(expected: str, actual: str) -> bool:
    """Word by word; numbers within the tolerance; ``…`` matches any one word."""
    e, a = expected.split(), actual.split()
    if len(e) != len(a):
        return False
    for x, y in zip(e, a):
        if x == "…" or x == y:
            continue
        nx, ny = _number(x), _number(y)
        if nx is None or ny is None or x.strip("0123456789.eE+-") != y.strip("0123456789.eE+-"):
            return False
        if abs(nx - ny) > REL_TOL * max(abs(nx), abs(ny)) + 1e-12:
            return False
    return True


def check_lines(expected: list[str], actual: list[str], what: str, skipping: bool = False) -> None:
    """Each expected line in order; ``...`` lets any lines pass (``skipping``: before the first too);
    other lines must follow directly."""
    i = 0
    for exp in expected:
        if exp.strip() == "...":
            skipping = True
            continue
        if not exp.strip():
            continue
        while i < len(actual) and not actual[i].strip():
            i += 1
        if skipping:
            j = next((k for k in range(i, len(actual)) if same_line(exp, actual[k])), None)
            assert j is not None, f"{what}: the page shows\n  {exp}\nbut it is not printed (from line {i}):\n" + \
                "\n".join(actual[i:i + 40])
            i, skipping = j + 1, False
        else:
            assert i < len(actual) and same_line(exp, actual[i]), \
                f"{what}: the page shows\n  {exp}\nthe command printed\n  {actual[i] if i < len(actual) else '(nothing)'}"
            i += 1


def commands(body: str) -> list[tuple[list[str], list[str]]]:
    """``(argv, expected lines)`` of each ``$ needle ...`` command of a console block."""
    out: list[tuple[list[str], list[str]]] = []
    for line in body.splitlines():
        if line.startswith("$ "):
            out.append((shlex.split(line[2:]), []))
        elif out:
            out[-1][1].append(line)
    return out


#: pages whose commands run elsewhere: own-data.md's by tests/test_owndata.py; own-observer.md's in a
#: process of their own, with the page's package installed (test_own_observer_page_installs_and_runs)
OWN_RUNNER = ("own-data.md", "own-observer.md")


def test_every_tutorial_is_checked():
    names = {p.name for p in PAGES}
    assert {"first-study.md", "adding-a-sensor.md", "comparing-observers.md", "fitting-em.md", "sweeps.md",
            "own-data.md", "own-observer.md"} <= names
    for p in PAGES:
        if p.name != "own-data.md":  # its commands are run by tests/test_owndata.py
            assert any(kind == "console" for kind, _, _ in blocks(p)), f"{p.name}: no console block"
    for cfg in (ROOT / "configs" / "tutorials").glob("*.yaml"):  # every tutorial config is used by a page
        assert any(f"configs/tutorials/{cfg.name}" in p.read_text() for p in PAGES), cfg.name


def test_the_matcher_holds_numbers_to_the_tolerance():
    assert same_line("| ukf | E_xyz [mm] | 0.2782 | 20/20 |", "| ukf | E_xyz [mm] | 0.2790 | 20/20 |")
    assert not same_line("| ukf | E_xyz [mm] | 0.2782 | 20/20 |", "| ukf | E_xyz [mm] | 0.2900 | 20/20 |")
    assert not same_line("| ukf | 20/20 |", "| ukf | 19/20 |")
    assert same_line("| ukf | … |", "| ukf | 0.0514 |") and not same_line("0.1 mm", "0.1 deg")
    with pytest.raises(AssertionError):
        check_lines(["a 1", "b 2"], ["a 1", "c 2"], "x")
    check_lines(["a 1", "...", "c 3.001"], ["a 1", "b 2", "c 3"], "x")


@pytest.mark.parametrize("page", [p for p in PAGES if p.name not in OWN_RUNNER], ids=lambda p: p.stem)
def test_tutorial_commands_print_what_the_page_shows(page, tmp_path, monkeypatch):
    shutil.copytree(ROOT / "configs", tmp_path / "configs")
    monkeypatch.chdir(tmp_path)
    runner = CliRunner()
    ran = 0
    for kind, path, body in blocks(page):
        if kind == "file":
            check_lines(body.splitlines(), Path(path).read_text(encoding="utf-8").splitlines(), f"{page.name}: {path}",
                        skipping=True)  # a file's lines from wherever the page starts showing it
            continue
        for argv, expected in commands(body):
            assert argv[0] == "needle", f"{page.name}: a console block runs needle commands only: {argv}"
            r = runner.invoke(app, argv[1:])
            assert r.exit_code == 0, f"{page.name}: {' '.join(argv)} exited {r.exit_code}:\n{r.output}"
            check_lines(expected, r.stdout.splitlines(), f"{page.name}: {' '.join(argv)}")
            ran += 1
    assert ran >= 1


CODE = re.compile(r'^```(?:python|toml) title="([^"]+)"\n(.*?)^```', re.S | re.M)


def _install(project: Path) -> Path:
    """What ``pip install -e project`` makes of a package for ``importlib.metadata``: the folder on the path,
    a ``dist-info`` beside its code with the name, version and entry points of its ``pyproject.toml``."""
    tables: dict[str, dict[str, str]] = {}
    section = ""
    for line in (project / "pyproject.toml").read_text(encoding="utf-8").splitlines():  # (tomllib: Python 3.11)
        head = re.fullmatch(r"\[(.+)\]", line.strip())
        pair = re.fullmatch(r'"?([\w.-]+)"?\s*=\s*"([^"]*)"', line.strip())
        if head:
            section = head.group(1).replace('"', "")
        elif pair:
            tables.setdefault(section, {})[pair.group(1)] = pair.group(2)
    name, version = tables["project"]["name"], tables["project"]["version"]
    info = project / f"{name.replace('-', '_')}-{version}.dist-info"
    info.mkdir()
    (info / "METADATA").write_text(f"Metadata-Version: 2.1\nName: {name}\nVersion: {version}\n")
    groups = {k.removeprefix("project.entry-points."): v for k, v in tables.items() if k.startswith("project.entry-points.")}
    assert groups, "the package declares no entry point"
    (info / "entry_points.txt").write_text("".join(
        f"[{g}]\n" + "".join(f"{k} = {v}\n" for k, v in eps.items()) for g, eps in groups.items()))
    return project


def test_own_observer_page_installs_and_runs(tmp_path):
    """The page's files are the plug-in (written out as shown), installed as pip would (its entry points),
    and each ``$ needle ...`` of the page run in a process of its own (registries read entry points once
    per process) prints what the page shows; the results file holds the plug-in's estimates, checked by
    the observer contract on the way."""
    page = DOCS / "tutorials" / "own-observer.md"
    text = page.read_text(encoding="utf-8")
    files = CODE.findall(text)
    assert {p for p, _ in files} >= {"lab-observers/pyproject.toml", "lab-observers/lab_observers/alpha_beta.py"}
    for path, body in files:
        (tmp_path / path).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / path).write_text(body, encoding="utf-8")
    site = _install(tmp_path / "lab-observers")
    shutil.copytree(ROOT / "configs", tmp_path / "configs")
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(site), str(ROOT)]), "COLUMNS": "120"}
    ran = 0
    for kind, _, body in blocks(page):
        assert kind == "console"
        for argv, expected in commands(body):
            assert argv[0] == "needle", argv
            p = subprocess.run([sys.executable, "-m", "needlecli", *argv[1:]], cwd=tmp_path, env=env,
                               capture_output=True, text=True, timeout=600)
            assert p.returncode == 0, f"{' '.join(argv)} exited {p.returncode}:\n{p.stdout}\n{p.stderr}"
            check_lines(expected, p.stdout.splitlines(), f"{page.name}: {' '.join(argv)}")
            ran += 1
    assert ran >= 3
    import h5py

    with h5py.File(tmp_path / "results" / "tutorials" / "own_observer.h5") as f:
        g = f["estimates/ab"]
        assert g.attrs["type"] == "alpha_beta" and list(g.attrs["names"]) == ["x", "y", "z", "v_x", "v_y", "v_z"]
        assert "cov" not in g and np.isfinite(g["state"][()]).all()
    assert (tmp_path / "results" / "tutorials" / "own_observer_compare" / "compare.csv").exists()
