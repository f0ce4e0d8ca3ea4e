"""A cold kernel cache (issue 27): a command never waits for a compilation it does not need.

The plan a command makes (:func:`needlecli.kernels.on_cold`) and the choice at its first kernel not
compiled (numpy now while the kernels compile in the background for the next run, or the compilation
first, said once); the process of its own that compiles (:func:`needlecli.platform.spawn_detached`, the
cache's lock); compilations of one kernel by several processes at once (each compiled once); an empty
cache end to end (``needle simulate``: the numbers of the numpy path, bit for bit, and a compiler left
running for the next run). Nothing here compiles a kernel of needlecli: every test takes seconds.
"""

from __future__ import annotations

import errno
import logging
import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import h5py
import numpy as np
import pytest

from needlecli import kernels, platform
from needlecli.kernels import _cache, dispatch

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture()
def empty_cache(tmp_path, monkeypatch):
    """An empty kernel cache, the cold policy ``background``, and no plan or numpy path left behind."""
    monkeypatch.setenv("NEEDLECLI_KERNEL_CACHE", str(tmp_path / "kcache"))
    monkeypatch.setenv(kernels.COLD_ENV, "background")
    monkeypatch.delenv(kernels.ENV, raising=False)
    yield tmp_path / "kcache"
    dispatch._PLAN.clear()
    dispatch.defer(False)


def plan(monkeypatch, numpy_seconds: float, started: list) -> None:
    """A command's plan whose background compilation is only recorded (nothing starts)."""
    monkeypatch.setattr(kernels, "compile_in_background", lambda fn, *a: started.append((fn, a)) or True)
    kernels.on_cold(entries=[kernels.TWINS["truth"].entry, ("ukf", "run")], numpy_seconds=numpy_seconds,
                    compile_for_next_run=print, args=("brief",))


# ---------------------------------------------------------------------------------------------- the choice
def test_a_small_job_takes_the_numpy_path_while_the_kernels_compile_for_the_next_run(empty_cache, monkeypatch,
                                                                                        caplog):
    started: list = []
    plan(monkeypatch, numpy_seconds=1.0, started=started)  # 1 s on numpy against ~30 s of compilation
    with caplog.at_level(logging.INFO, logger="needlecli"):
        assert kernels.twin("truth", "auto") is None  # the first twin not compiled decides: the numpy path
    assert started == [(print, ("brief",))] and kernels.deferred()
    assert "this run takes the numpy path" in caplog.text and "about 28 s" in caplog.text  # truth 10 + ukf 18
    assert kernels.resolve("auto") == "numpy" and kernels.twin("state_errors", "auto") is None  # the rest too
    assert kernels.resolve(None) == "numpy"
    assert kernels.resolve("numba") == "numba"  # asked for explicitly: compiled (and waits for it)
    with kernels.compile_now():  # a part that must take one path (EM, a sweep's cell): compiled
        assert kernels.resolve("auto") == "numba"
    assert kernels.deferred()
    kernels.on_cold(entries=[])  # the next command of this process plans afresh
    assert not kernels.deferred() and kernels.resolve("auto") == "numba"


def test_a_large_job_or_the_wait_policy_compiles_first_and_says_so_once(empty_cache, monkeypatch, caplog):
    started: list = []
    plan(monkeypatch, numpy_seconds=500.0, started=started)  # the numpy path would cost more than compiling
    assert kernels.twin("truth", "auto") is not None and not kernels.deferred() and not started
    for policy in ("wait", "background"):
        monkeypatch.setenv(kernels.COLD_ENV, policy)
        plan(monkeypatch, numpy_seconds=1.0 if policy == "background" else 0.0, started=started)
        if policy == "background":
            monkeypatch.setattr(platform, "fork_available", lambda: False)  # no process to spare: compile here
        assert kernels.twin("ukf", "auto") is not None and not started and not kernels.deferred()
    with caplog.at_level(logging.INFO, logger="needlecli"):
        dispatch.announce("ukf.run")
        dispatch.announce("truth.advance")
    assert caplog.text.count("compiling kernels, once per install: about") == 1  # once per command
    monkeypatch.setenv(kernels.COLD_ENV, "later")
    with pytest.raises(kernels.KernelError, match="NEEDLECLI_COLD='later'"):
        kernels.cold_policy()


def test_a_compiled_kernel_or_one_its_job_did_not_use_is_not_cold(empty_cache, monkeypatch):
    started: list = []
    index = empty_cache / _cache.source_hash() / "kernels_x" / "truth.advance-51.py311.nbi"
    index.parent.mkdir(parents=True)
    index.write_bytes(b"")
    plan(monkeypatch, numpy_seconds=1.0, started=started)
    assert kernels.twin("truth", "auto") is not None and not started  # in the cache: compiled, no decision
    assert not kernels.cold([("truth", "advance"), None]) and kernels.cold([("ukf", "run")])
    _cache.record_unused([("ukf", "run")])  # asked for by a twin that did not cover its job: not missing
    assert kernels.twin("ukf", "auto") is not None and not started and not kernels.deferred()


def test_the_estimate_is_this_machines_own_once_it_compiled(empty_cache):
    assert kernels.compile_estimate([("ukf", "run")]) == dispatch.COMPILE_SECONDS["ukf.run"]
    _cache.record_seconds("ukf.run", 41.0)
    assert kernels.compile_estimate([("ukf", "run"), ("kalman", "new_kernel")]) == 41.0 + 5.0


def test_the_first_compilation_of_a_command_says_so_and_is_recorded(empty_cache, caplog):
    """The compile listener of needlecli.kernels._jit: a kernel of needlecli compiled (a stand-in here)
    announces the wait once and records how long it took."""
    import numba

    from needlecli.kernels import _jit  # noqa: F401  (registers the listener)

    def stand_in(x):
        return x + 1.0

    stand_in.__module__ = "needlecli.kernels.standin"
    kernels.on_cold(entries=[])
    with caplog.at_level(logging.INFO, logger="needlecli"):
        assert numba.njit(stand_in)(1.0) == 2.0
    assert caplog.text.count("compiling kernels, once per install: about") == 1
    assert "standin.stand_in" in _cache.recorded_seconds()


# ---------------------------------------------------------------------------------------------- the processes
def test_spawn_detached_outlives_the_caller_in_a_session_of_its_own(tmp_path):
    flag = tmp_path / "done"

    def work():
        time.sleep(1.0)
        flag.write_text(f"{os.getpid()} {os.getsid(0)}")

    t0 = time.monotonic()
    pid = platform.spawn_detached(work)
    assert pid is not None and time.monotonic() - t0 < 1.0  # returned before the work ended
    deadline = time.monotonic() + 20
    while not flag.exists() and time.monotonic() < deadline:
        time.sleep(0.05)
    me, session = map(int, flag.read_text().split())
    assert me == pid and session != os.getsid(0)  # a session of its own: a Ctrl-C here does not reach it
    assert platform.spawn_detached(work, ready=lambda: False) is None  # not ready: nothing runs


def test_one_background_compilation_at_a_time_holding_the_caches_lock(empty_cache, tmp_path):
    ran = tmp_path / "ran"

    def job(n):
        with open(ran, "a") as f:
            f.write(f"{n}\n")
        time.sleep(1.5)

    assert kernels.compile_in_background(job, 1)
    assert kernels.compiling() and int(_cache.lock_path().read_text()) > 0  # the compiler's pid
    assert kernels.compile_in_background(job, 2)  # one runs already: that one serves
    assert kernels.wait_for_compile(timeout=30) and not kernels.compiling()
    assert ran.read_text().split() == ["1"]


def test_file_lock_falls_back_where_the_file_system_refuses_flock(tmp_path, monkeypatch):
    """NFS without lock support, Lustre without -o flock: flock raises ENOLCK; the lock file's way then."""
    if not platform.has_flock():
        pytest.skip("no flock here")
    import fcntl

    def refused(fd, op):
        raise OSError(errno.ENOLCK, "No locks available")

    monkeypatch.setattr(fcntl, "flock", refused)
    lock = tmp_path / "index.lock"
    with platform.file_lock(lock) as held:
        assert held and (tmp_path / "index.lock.excl").exists()
        with platform.file_lock(lock, blocking=False) as again:
            assert not again
    assert not (tmp_path / "index.lock.excl").exists()


#: a module of kernels compiled into needlecli's cache (the @jit of needlecli.kernels._jit); its
#: compilation takes a second or so (a long body), so that two processes started together overlap
KERNEL = '''
import os, sys, time
from pathlib import Path
from needlecli.kernels._jit import jit
{body}
go = Path(sys.argv[1])
while not go.exists():
    time.sleep(0.01)
big(1.0)
print(sum(big.stats.cache_misses.values()), sum(big.stats.cache_hits.values()))
'''


def test_processes_compiling_one_kernel_at_once_compile_it_once(tmp_path):
    lines = "\n".join(f"    x = x * 1.0000001 + {i}.0" for i in range(400))
    (tmp_path / "bigkernel.py").write_text(KERNEL.replace("{body}", f"@jit\ndef big(x):\n{lines}\n    return x\n"))
    env = {**os.environ, "NEEDLECLI_KERNEL_CACHE": str(tmp_path / "kcache"),
           "PYTHONPATH": os.pathsep.join([str(ROOT), str(tmp_path)])}
    go = tmp_path / "go"
    procs = [subprocess.Popen([sys.executable, str(tmp_path / "bigkernel.py"), str(go)], env=env, cwd=tmp_path,
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True) for _ in range(2)]
    time.sleep(3.0)  # both imported numba and wait
    go.write_text("")
    outs = [p.communicate(timeout=120) for p in procs]
    assert all(p.returncode == 0 for p in procs), [o[1][-2000:] for o in outs]
    counts = sorted(tuple(map(int, o[0].split())) for o in outs)
    assert counts == [(0, 1), (1, 0)], counts  # one compiled it, the other loaded what the first saved


# ---------------------------------------------------------------------------------------------- end to end
TINY = textwrap.dedent("""\
    name: tiny_cold
    model: {type: modified_unicycle, params: {kappa: 0.005, beta_cut: 0.035}}
    inputs: {v: 1.5, u: 0.0}
    sensors:
      - {name: us3d, type: position, rate: 2.0, sigma: 0.3}
      - {name: robot, type: encoder, rate: 50.0, channels: [roll], sigma: 0.0035}
    observers:
      - name: ukf
        type: ukf
        q: {x: 2.0e-3, y: 2.0e-3, z: 2.0e-3, alpha: 2.0e-5, beta: 2.0e-5, gamma: 5.0e-4, kappa: 2.0e-6}
        p0: {x: 1.0, y: 1.0, z: 1.0, alpha: 5.0e-3, beta: 5.0e-3, gamma: 0.1, kappa: 2.0e-6}
        init: {from: truth, std: {alpha: 0.0873, beta: 0.0873}, first_measurement: {x: us3d.x, y: us3d.y, z: us3d.z}}
    runs: {count: 3, seed: 5}
    stop: {depth: 2.0}
    simulation: {dt: 0.02}
    """)


def _arrays(path: Path) -> dict:
    out = {}
    with h5py.File(path, "r") as f:
        f.visititems(lambda name, obj: out.__setitem__(name, obj[()]) if isinstance(obj, h5py.Dataset) else None)
    return out


def test_a_first_run_on_an_empty_cache_takes_the_numpy_path_and_leaves_a_compiler(tmp_path):
    (tmp_path / "tiny.yaml").write_text(TINY)
    cache = tmp_path / "kcache"
    env = {**os.environ, "NEEDLECLI_KERNEL_CACHE": str(cache), kernels.COLD_ENV: "background",
           "PYTHONPATH": str(ROOT)}
    env.pop(kernels.ENV, None)
    cmd = [sys.executable, "-m", "needlecli", "simulate", "tiny.yaml"]
    first = subprocess.run([*cmd, "--out", "first.h5"], env=env, cwd=tmp_path, capture_output=True, text=True)
    lock = next(cache.rglob(_cache.LOCK_NAME), None)
    pid = int(lock.read_text()) if lock is not None and lock.read_text().strip() else None
    try:
        assert first.returncode == 0, first.stderr[-3000:]
        assert "kernels not compiled yet: this run takes the numpy path" in first.stderr
        assert "compiling kernels" not in first.stderr  # it did not wait
        assert pid is not None and platform.pid_alive(pid)  # compiling for the next run, after this one ended
        numpy = subprocess.run([*cmd, "--out", "numpy.h5", "-q"], env={**env, kernels.ENV: "numpy"}, cwd=tmp_path,
                               capture_output=True, text=True)
        assert numpy.returncode == 0, numpy.stderr[-3000:]
    finally:
        if pid is not None and platform.pid_alive(pid):  # the compiler this test started: ended by its pid
            os.kill(pid, signal.SIGTERM)
            deadline = time.monotonic() + 20
            while platform.pid_alive(pid) and time.monotonic() < deadline:
                time.sleep(0.1)
    a, b = _arrays(tmp_path / "first.h5"), _arrays(tmp_path / "numpy.h5")
    assert a.keys() == b.keys() and a
    for k in a:  # the numbers of the numpy path, bit for bit
        np.testing.assert_array_equal(a[k], b[k], err_msg=k)
