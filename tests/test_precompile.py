"""``needle kernels compile`` and ``needle kernels status`` (issue 27: the compile moved to the install step).

The plan (which jobs a config gives, which it skips, their estimates, the order), the schedule's
closed form, what the commands say on an empty and on a full cache, a job that fails, and one real
compilation end to end: a truth-only config compiled ahead, after which its first run compiles nothing.
"""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest
from typer.testing import CliRunner

from needlecli import kernels
from needlecli.cli.app import app
from needlecli.experiments.studies import precompile
from needlecli.kernels import _cache

ROOT = Path(__file__).resolve().parents[1]
DEFAULT = ROOT / "configs" / "default.yaml"
STUDY = ROOT / "configs" / "em-magnetic-pratt2022" / "study.yaml"

TRUTH_ONLY = textwrap.dedent("""\
    name: truth_only
    model: {type: modified_unicycle, params: {kappa: 0.005, beta_cut: 0.035}}
    inputs: {v: 1.5, u: 0.0}
    sensors: [{name: us3d, type: position, rate: 2.0, sigma: 0.3}]
    runs: {count: 2, seed: 5}
    stop: {depth: 1.0}
    """)


@pytest.fixture()
def empty_cache(tmp_path, monkeypatch):
    monkeypatch.setenv("NEEDLECLI_KERNEL_CACHE", str(tmp_path / "kcache"))
    monkeypatch.delenv(kernels.ENV, raising=False)
    _cache._READY.clear()
    return tmp_path / "kcache"


def cli(*args):
    return CliRunner().invoke(app, [str(a) for a in args])


def test_each_config_gives_a_job_per_kind_of_work_and_skips_what_compiles_nothing(empty_cache, tmp_path):
    numpy = tmp_path / "numpy.yaml"
    numpy.write_text(TRUTH_ONLY + "simulation: {kernels: numpy}\n")
    truth = tmp_path / "truth.yaml"
    truth.write_text(TRUTH_ONLY)
    p = precompile.plan([DEFAULT, STUDY, numpy, truth])
    kinds = {(Path(j.config).name, j.kind) for j in p.jobs}
    assert kinds == {("default.yaml", "simulate"), ("study.yaml", "fit"), ("truth.yaml", "truth")}
    assert p.skipped == [f"{numpy}: kernels: numpy (nothing to compile)"]
    fit = next(j for j in p.jobs if j.kind == "fit")
    assert {kernels.TWINS[t].entry for t in ("kalman_filter_smoother", "truth", "linearise")} <= set(fit.entries)
    sim = next(j for j in p.jobs if j.kind == "simulate")
    assert ("ukf", "run") in sim.entries and ("truth", "advance") in sim.entries
    # a kernel two jobs share counts once, for the job that compiles longest (the fit: it holds the truth)
    assert fit.estimate == pytest.approx(kernels.compile_estimate(fit.entries) + precompile.BRIEF_SECONDS)
    assert sim.estimate == pytest.approx(kernels.compile_estimate([e for e in sim.entries if e not in fit.entries])
                                         + precompile.BRIEF_SECONDS)
    assert [j.kind for j in p.todo()][0] == "fit"  # the longest first


def test_nothing_to_do_when_the_cache_holds_every_kernel(empty_cache, monkeypatch):
    monkeypatch.setattr(_cache, "cached", lambda entry: True)
    assert precompile.plan([DEFAULT, STUDY]).todo() == []
    r = cli("kernels", "compile", DEFAULT, STUDY, "-q")
    assert r.exit_code == 0, r.output
    assert "kernels: compiled already for 2 config(s)" in r.output
    r = cli("kernels", "status", DEFAULT)
    assert r.exit_code == 0 and "NOT compiled" not in r.output and "ukf.run" in r.output


def test_without_numba_there_is_nothing_to_compile_and_the_install_goes_on(empty_cache, monkeypatch):
    from needlecli.kernels import dispatch

    monkeypatch.setattr(dispatch, "numba_available", lambda: False)
    monkeypatch.setattr(kernels, "numba_available", lambda: False)
    r = cli("kernels", "compile")
    assert r.exit_code == 0 and "numba is not installed: nothing to compile" in r.output
    assert not empty_cache.exists()


def test_on_the_numpy_path_there_is_nothing_to_compile(empty_cache, monkeypatch):
    monkeypatch.setenv(kernels.ENV, "numpy")
    r = cli("kernels", "compile", DEFAULT)
    assert r.exit_code == 0, r.output
    assert r.output.strip() == f"kernels: nothing to compile for 1 config(s): {DEFAULT}: {kernels.ENV}=numpy (nothing to compile)"
    assert not empty_cache.exists()


def test_status_names_what_an_empty_cache_lacks_and_exits_1(empty_cache):
    r = cli("kernels", "status", DEFAULT)
    assert r.exit_code == 1, r.output
    assert str(empty_cache) in r.output
    for name in ("truth.advance", "ukf.run", "metrics._state_errors"):
        assert any(name in line and "NOT compiled" in line for line in r.output.splitlines()), name
    assert "needle kernels compile" in r.output.splitlines()[-1]


@pytest.mark.parametrize("processes, expected", [(1, 21.0), (2, 11.0), (3, 10.0), (8, 10.0)])
def test_the_schedule_gives_the_longest_job_first_to_the_first_free_process(processes, expected):
    assert precompile.makespan([1.0, 10.0, 4.0, 6.0], processes) == expected


def test_a_bad_config_is_one_error_line_before_any_work(empty_cache, tmp_path):
    bad = tmp_path / "bad.yaml"
    bad.write_text(TRUTH_ONLY.replace("rate: 2.0", "rate: -2.0"))
    r = cli("kernels", "compile", DEFAULT, bad)
    assert r.exit_code == 2
    assert r.output.startswith("error: ") and "rate" in r.output and len(r.output.strip().splitlines()) == 1
    assert not empty_cache.exists()  # nothing compiled


def test_a_failed_job_is_named_with_exit_code_1(empty_cache, monkeypatch):
    def run(jobs, processes, progress=None):
        return [precompile.Outcome(jobs[0], float("nan"), "ValueError: broken"),
                *(precompile.Outcome(j, 1.0) for j in jobs[1:])]

    monkeypatch.setattr(precompile, "run", run)
    r = cli("kernels", "compile", DEFAULT, STUDY, "-q")
    assert r.exit_code == 1
    assert r.output.strip() == f"error: {STUDY}: compiling for its fit failed: ValueError: broken"


def test_a_config_compiled_ahead_runs_first_without_compiling(tmp_path):
    """End to end, in processes as a user runs them: ``needle kernels compile`` on an empty cache (one job:
    the truth kernel), then the config's first run leaves every cache file as it was."""
    (tmp_path / "truth.yaml").write_text(TRUTH_ONLY)
    cache = tmp_path / "kcache"
    env = {**os.environ, "NEEDLECLI_KERNEL_CACHE": str(cache), kernels.COLD_ENV: "background",
           "PYTHONPATH": str(ROOT)}
    env.pop(kernels.ENV, None)
    needle = [sys.executable, "-m", "needlecli"]
    c = subprocess.run([*needle, "kernels", "compile", "truth.yaml", "--jobs", "2"], env=env, cwd=tmp_path,
                       capture_output=True, text=True)
    assert c.returncode == 0, c.stderr[-3000:]
    assert "compiling kernels, once per install: about" in c.stderr and "[1/1] compiled for truth.yaml (truth)" in c.stderr
    assert "1 of 1 entry kernel(s) in the cache" in c.stdout
    before = {p: p.stat().st_mtime_ns for p in cache.rglob("*") if p.is_file() and "needlecli-" not in p.name}
    first = subprocess.run([*needle, "simulate", "truth.yaml", "--out", "a.h5"], env=env, cwd=tmp_path,
                           capture_output=True, text=True)
    assert first.returncode == 0, first.stderr[-3000:]
    assert "compiling kernels" not in first.stderr and "takes the numpy path" not in first.stderr
    after = {p: p.stat().st_mtime_ns for p in cache.rglob("*") if p.is_file() and "needlecli-" not in p.name}
    assert after == before and before
    again = subprocess.run([*needle, "kernels", "status", "truth.yaml"], env=env, cwd=tmp_path, capture_output=True,
                           text=True)
    assert again.returncode == 0 and "truth.advance" in again.stdout and "NOT" not in again.stdout


@pytest.mark.skipif(not hasattr(os, "killpg"), reason="a terminal's process group (POSIX) is what Ctrl-C reaches")
def test_ctrl_c_ends_the_jobs_still_compiling_and_exits_130(tmp_path):
    """Ctrl-C reaches the terminal's whole process group; the jobs' processes leave it to the command,
    which ends them (none goes on compiling into the cache) and says it was interrupted."""
    import signal
    import time

    (tmp_path / "truth.yaml").write_text(TRUTH_ONLY)
    env = {**os.environ, "NEEDLECLI_KERNEL_CACHE": str(tmp_path / "kcache"), "PYTHONPATH": str(ROOT)}
    p = subprocess.Popen([sys.executable, "-m", "needlecli", "kernels", "compile", "truth.yaml", str(DEFAULT),
                          "--jobs", "1"],
                         env=env, cwd=tmp_path, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                         start_new_session=True)
    deadline = time.monotonic() + 60
    while not list((tmp_path / "kcache").rglob("*.nbi")) and time.monotonic() < deadline and p.poll() is None:
        time.sleep(0.1)  # until a job is compiling (numba wrote an index)
    os.killpg(p.pid, signal.SIGINT)
    t0 = time.monotonic()
    _, err = p.communicate(timeout=60)
    assert p.returncode == 130, err
    assert time.monotonic() - t0 < 5  # at once (0.3 s here), not after the next job (9 s here before the fix)
    assert err.strip().splitlines()[-1].startswith("error: interrupted by SIGINT")
    deadline = time.monotonic() + 20  # (multiprocessing's resource tracker ends when it sees the command end)
    while time.monotonic() < deadline:
        try:
            os.killpg(p.pid, 0)
        except ProcessLookupError:  # no process of the group is left: none goes on compiling
            break
        time.sleep(0.2)
    else:
        pytest.fail("a process of the command's group outlived it by 20 s")
