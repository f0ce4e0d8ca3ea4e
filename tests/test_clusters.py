"""The page "Sweeps on a cluster" (docs/guide/clusters.md) cannot go stale: its SLURM scripts are valid
bash and, run as written with a stand-in for ``sbatch`` (each task of the array in a process of its own,
``SLURM_ARRAY_TASK_ID`` set, its output to its own file; then the dependent job), make on a tiny grid the
table of a sweep run in one process; the options of its dask-jobqueue example are options of ``needle
sweep``."""

from __future__ import annotations

import ast
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pandas as pd
import pytest
from typer.testing import CliRunner

from needlecli.cli.app import app

ROOT = Path(__file__).resolve().parents[1]
PAGE = ROOT / "docs" / "guide" / "clusters.md"
BLOCK = re.compile(r'^```(\w+) title="([^"]+)"\n(.*?)^```', re.S | re.M)

TINY = """\
format: 2
name: tiny_array
model: {type: modified_unicycle, params: {kappa: 0.005, beta_cut: 0.035}}
inputs: {v: 1.5, u: 0.0}
sensors:
  - {name: us3d, type: position, rate: 2.0, sigma: 0.3}
observers:
  - {name: ol, type: open_loop}
runs: {count: 2, seed: 5}
stop: {depth: 3.0}
simulation: {dt: 0.02}
output: {store_every: 10}
"""
GRID = """\
grid:
  sensors.0.sigma: [0.1, 0.3]
  runs.seed: range(2)
"""

#: sbatch as the scripts use it: --array=A-B runs the script once per index (its output to its own file),
#: --wrap runs the command; prints the job id (--parsable) or what sbatch says
SBATCH = """\
import os, subprocess, sys
args, opts, rest = sys.argv[1:], {}, []
while args:
    a = args.pop(0)
    if a == "--wrap":
        opts["wrap"] = args.pop(0)
    elif a.startswith("--"):
        k, _, v = a[2:].partition("=")
        opts[k] = v or True
    else:
        rest = [a, *args]
        break
with open("sbatch.log", "a") as log:
    if "wrap" in opts:
        with open("slurm-collect.out", "w") as out:
            rc = subprocess.run(["bash", "-c", opts["wrap"]], stdout=out, stderr=out).returncode
        log.write(f"wrap after {opts.get('dependency')}: exit {rc}\\n")
    else:
        lo, hi = map(int, opts["array"].split("-"))
        for t in range(lo, hi + 1):
            with open(f"slurm-4242_{t}.out", "w") as out:
                rc = subprocess.run(["bash", *rest], stdout=out, stderr=out,
                                    env={**os.environ, "SLURM_ARRAY_TASK_ID": str(t)}).returncode
            log.write(f"task {t}: exit {rc}\\n")
print("4242" if opts.get("parsable") else "Submitted batch job 4243")
"""


def scripts() -> dict[str, tuple[str, str]]:
    """``{title: (language, body)}`` of the page's titled code blocks."""
    return {m.group(2): (m.group(1), m.group(3)) for m in BLOCK.finditer(PAGE.read_text(encoding="utf-8"))}


BASH = pytest.mark.skipif(shutil.which("bash") is None, reason="needs bash")


@BASH
def test_the_slurm_scripts_are_valid_bash():
    found = scripts()
    for name in ("sweep_cell.sh", "submit.sh"):
        lang, body = found[name]
        assert lang == "bash", name
        r = subprocess.run(["bash", "-n"], input=body, text=True, capture_output=True)
        assert r.returncode == 0, f"{name}: {r.stderr}"
    assert "--cell \"$SLURM_ARRAY_TASK_ID\"" in found["sweep_cell.sh"][1]
    assert "--collect" in found["submit.sh"][1] and "--array=0-$((N - 1))" in found["submit.sh"][1]


@BASH
def test_the_slurm_scripts_run_a_grid_cell_by_cell_and_collect_its_table(tmp_path):
    found = scripts()
    (tmp_path / "tiny.yaml").write_text(TINY)
    (tmp_path / "grid.yaml").write_text(GRID)
    (tmp_path / "sweep_cell.sh").write_text(found["sweep_cell.sh"][1])
    submit = found["submit.sh"][1]
    for key, value in (("CONFIG", "tiny.yaml"), ("GRID", "grid.yaml"), ("DIR", "out")):
        submit, n = re.subn(rf"^{key}=.*$", f"{key}={value}", submit, flags=re.M)
        assert n == 1, key
    (tmp_path / "submit.sh").write_text(submit)
    bin_ = tmp_path / "bin"
    bin_.mkdir()
    (bin_ / "sbatch").write_text(f"#!{sys.executable}\n" + SBATCH)
    (bin_ / "needle").write_text(f'#!/bin/sh\nexec "{sys.executable}" -m needlecli "$@"\n')
    for f in bin_.iterdir():
        f.chmod(0o755)
    env = {**os.environ, "PATH": f"{bin_}{os.pathsep}{os.environ['PATH']}", "PYTHONPATH": str(ROOT)}
    r = subprocess.run(["bash", "submit.sh"], cwd=tmp_path, env=env, capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    assert r.stdout.splitlines() == ["Submitted batch job 4243", "sweep: 4 cells in job array 4242; table: "
                                     "out/sweep.csv"], r.stdout
    log = (tmp_path / "sbatch.log").read_text().splitlines()
    assert log == ["wrap after None: exit 0", *(f"task {t}: exit 0" for t in range(4)),
                   "wrap after afterany:4242: exit 0"], log  # the kernels compiled first, then the cells
    said = (tmp_path / "slurm-4242_2.out").read_text()
    assert said.startswith("cell 2 of 4 ok in "), said
    assert "cells: 4 (4 complete, 0 failed, 0 missing" in (tmp_path / "slurm-collect.out").read_text()
    one = CliRunner().invoke(app, ["sweep", str(tmp_path / "tiny.yaml"), "--grid", str(tmp_path / "grid.yaml"),
                                   "--out", str(tmp_path / "inline"), "--executor", "inline", "--quiet"])
    assert one.exit_code == 0, one.output
    pd.testing.assert_frame_equal(pd.read_csv(tmp_path / "out" / "sweep.csv").drop(columns=["seconds"]),
                                  pd.read_csv(tmp_path / "inline" / "sweep.csv").drop(columns=["seconds"]))


def test_the_dask_jobqueue_example_gives_needle_sweep_its_own_options():
    import click
    import typer.main

    lang, body = scripts()["sweep_on_dask.py"]
    assert lang == "python"
    lists = [[e.value for e in n.elts if isinstance(e, ast.Constant)] for n in ast.walk(ast.parse(body))
             if isinstance(n, ast.List)]
    words = next(w for w in lists if w[:2] == ["needle", "sweep"])
    command = typer.main.get_command(app)
    sweep = command.get_command(click.Context(command), "sweep")
    known = {o for p in sweep.params for o in p.opts}
    asked = [w for w in words if w.startswith("--")]
    assert asked and set(asked) <= known, set(asked) - known
    assert "--scheduler" in asked and "--executor" in asked
