"""The documentation site (issue 19): ``mkdocs build --strict`` (warnings are errors: a broken link, a
missing page, an API name that does not resolve) builds, with the reference pages generated from the CLI,
the schema and the registries at build time; README is a front page of at most 200 lines whose two
commands are the ones .ci/run runs, and every page it links to exists."""

from __future__ import annotations

import importlib.util
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def _need_mkdocs():
    missing = [m for m in ("mkdocs", "material", "mkdocstrings", "mkdocstrings_handlers.python", "pymdownx")
               if importlib.util.find_spec(m.split(".")[0]) is None]
    if missing:
        if os.environ.get("CI"):  # CI installs .[docs] (.ci/run): there the site must build
            pytest.fail(f"CI without the docs extra: {missing} not installed (pip install -e '.[docs]')")
        pytest.skip(f"mkdocs is not installed ({', '.join(missing)}): pip install -e '.[docs]'")


@pytest.fixture(scope="module")
def site(tmp_path_factory) -> Path:
    _need_mkdocs()
    out = tmp_path_factory.mktemp("site")
    env = {**os.environ, "PYTHONPATH": str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""),
           "NO_MKDOCS_2_WARNING": "1"}
    r = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "--site-dir", str(out)], cwd=ROOT,
                       env=env, capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stdout + r.stderr
    assert "WARNING" not in r.stderr, r.stderr
    return out


def _text(path: Path) -> str:
    return re.sub(r"<[^>]+>", " ", path.read_text(encoding="utf-8"))


def test_the_site_builds_strictly_with_every_page(site):
    for page in ("index.html", "getting-started/index.html", "tutorials/first-study/index.html",
                 "papers/seed000/index.html", "papers/seed001/index.html", "papers/seed003/index.html",
                 "papers/seed004/index.html", "real-data/index.html", "benchmarks/index.html", "layout/index.html",
                 "reference/results-file/index.html", "reference/log-file/index.html", "reference/fit-file/index.html"):
        assert (site / page).exists(), page


def test_the_generated_reference_is_complete(site):
    """Every command, every config section and key, every table and plot, and the plug-in contracts are
    on the built pages: generated from the code, so a new one cannot be missing."""
    import json

    # what the code has, read in a fresh process (as the build did: no test's own registrations)
    code = ("import json, typer\nfrom needlecli.cli.app import app\n"
            "from needlecli.experiments.config.explain import reference_pages\nfrom needlecli.reports import PLOTS, TABLES\n"
            "root = typer.main.get_command(app)\n"
            "cmds = [[n, list(getattr(c, 'commands', {}) or {})] for n, c in root.commands.items()]\n"
            "print(json.dumps({'cmds': cmds, 'pages': reference_pages(), 'names': TABLES.names() + PLOTS.names()}))")
    env = {**os.environ, "PYTHONPATH": str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", "")}
    have = json.loads(subprocess.run([sys.executable, "-c", code], cwd=ROOT, env=env, capture_output=True, text=True,
                                     check=True).stdout)
    commands = _text(site / "reference/commands/index.html")
    for name, subs in have["cmds"]:
        assert f"needle {name}" in commands, name
        for sub in subs:
            assert f"needle {name} {sub}" in commands, (name, sub)
    assert "--quiet" in commands and "Example:" in commands
    for name, md in have["pages"].items():
        html = _text(site / "reference/config" / name / "index.html") if name != "index" else \
            _text(site / "reference/config/index.html")
        for key in re.findall(r"^\| `([^`]+)` \|", md, re.M):
            assert key in html, (name, key)
    tables = _text(site / "reference/tables-plots/index.html")
    for n in have["names"]:
        assert n in tables, n
    api = _text(site / "reference/api/index.html")
    for name in ("Observer", "Model", "Sensor", "Pipeline", "Controller", "Registry", "EstimationProblem",
                 "InitialEstimate", "Posterior"):
        assert re.search(rf"\b{name}\b", api), name
    assert "Parameters" in api or "Returns" in api  # docstrings rendered, not only names


def test_pictures_are_committed_and_shown(site):
    for png in (ROOT / "docs").rglob("*.png"):
        assert png.stat().st_size > 10_000, png  # a plot with data, not a stub
    assert (site / "img" / "default_error_vs_depth.png").exists()


# ---------------------------------------------------------------------------------------------- README
def test_readme_is_a_front_page_with_the_two_commands():
    text = (ROOT / "README.md").read_text(encoding="utf-8")
    assert len(text.splitlines()) <= 200
    assert "pip install -e . && needle simulate configs/default.yaml" in text
    assert "pip install -e '.[test]' && python -m pytest" in text
    ci = (ROOT / ".ci" / "run").read_text()
    assert "python -m pip install -e '.[test]' && python -m pytest" in ci and "'.[docs]'" in ci
    assert "needle evaluate" in text and "docs/img/default_error_vs_depth.png" in text
    for link in re.findall(r"\]\((docs/[^)#]+)", text):
        assert (ROOT / link).exists(), link
    for seed in ("000", "001", "003", "004"):
        assert f"docs/papers/seed{seed}.md" in text, seed


# ---------------------------------------------------------------------------------------------- benchmarks
def test_the_benchmark_page_is_what_make_bench_wrote():
    """docs/benchmarks.md is the output of a whole ``make bench`` round (tools/bench_page.py), not a page
    written by hand: its mark, every benchmark's section and issue 14's targets with their verdicts."""
    sys.path.insert(0, str(ROOT / "tools"))
    import bench_page

    text = (ROOT / "docs" / "benchmarks.md").read_text(encoding="utf-8")
    assert text.startswith(bench_page.MARK)
    for name in bench_page.BENCHMARKS:
        assert f"\n## {name}\n" in text and (ROOT / "benchmarks" / f"{name}.py").exists(), name
    targets = text.split("## Issue 14's targets", 1)[1].split("\n## ", 1)[0]
    rows = [line for line in targets.splitlines() if line.startswith("| ")][2:]  # below the header
    assert len(rows) >= 7 and "FilterPy" in targets
    assert {line.rsplit("|", 2)[1].strip(" *") for line in rows} <= {"MET", "NOT MET", "printed"}
