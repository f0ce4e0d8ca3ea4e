"""needlecli.platform: each capability taken away (as macOS and Windows lack them) and its fallback.

The end-to-end test runs ``needle simulate``, ``evaluate`` and ``fit-em`` in processes from which
``posix_fallocate``, ``O_DIRECT``, ``statvfs``, ``pathconf``, ``sched_getaffinity``, ``fork``,
``fcntl.flock`` and the C library's ``mallopt`` and ``prctl`` were removed before needlecli was imported
(a ``sitecustomize`` on their ``PYTHONPATH``), and checks that they give what a run with every capability
gives. The unit tests check each fallback against what it stands for.
"""

from __future__ import annotations

import errno
import os
import signal
import subprocess
import sys
import textwrap
from pathlib import Path

import h5py
import numpy as np
import pytest

from needlecli import platform
from needlecli.errors import ConfigError

ROOT = Path(__file__).resolve().parent.parent

#: a sitecustomize that removes the capabilities named in $NEEDLECLI_TEST_TAKE_AWAY before anything runs
SITE = '''
"""Take capabilities away before needlecli is imported, as macOS and Windows lack them."""
import os

away = set(filter(None, os.environ.get("NEEDLECLI_TEST_TAKE_AWAY", "").split(",")))
if "statvfs" in away:  # shutil.disk_usage stays, as on Windows (where it does not go through os.statvfs)
    import shutil

    _statvfs = os.statvfs

    def _disk_usage(path):
        st = _statvfs(path)
        return shutil._ntuple_diskusage(st.f_blocks * st.f_frsize, (st.f_blocks - st.f_bfree) * st.f_frsize,
                                        st.f_bavail * st.f_frsize)

    shutil.disk_usage = _disk_usage
for name in sorted(away & {"posix_fallocate", "O_DIRECT", "statvfs", "pathconf", "sched_getaffinity", "fork"}):
    delattr(os, name)
if "flock" in away:
    import fcntl

    del fcntl.flock
if away & {"mallopt", "prctl"}:  # a C library without them (not glibc, not Linux)
    import ctypes

    class _CDLL(ctypes.CDLL):
        def __getitem__(self, name):
            if name in away:
                raise AttributeError(f"{name}: not in this C library")
            return super().__getitem__(name)

    ctypes.CDLL = _CDLL
'''
#: what the sitecustomize removes; fork separately (the warm-up's forked process is part of what is tested)
TAKEN = ("posix_fallocate", "O_DIRECT", "statvfs", "pathconf", "sched_getaffinity", "flock", "mallopt", "prctl")
#: what only the switch can take away (no module attribute to delete), also taken in the end-to-end test
SWITCHED = "proc,huge_pages,threadpoolctl,positioned_io,posix_signals"


def _env(tmp_path: Path, take_away=(), **extra) -> dict:
    site = tmp_path / "site"
    site.mkdir(exist_ok=True)
    (site / "sitecustomize.py").write_text(SITE)
    env = {k: v for k, v in os.environ.items() if k not in ("NEEDLECLI_KERNELS", platform.SWITCH, "NEEDLECLI_NO_DIRECT_IO")}
    env.update(PYTHONPATH=os.pathsep.join([str(site), str(ROOT)]), NEEDLECLI_TEST_TAKE_AWAY=",".join(take_away), **extra)
    return env


def _needle(args, env, cwd) -> subprocess.CompletedProcess:
    p = subprocess.run([sys.executable, "-m", "needlecli", *map(str, args), "-q"], env=env, cwd=cwd,
                       capture_output=True, text=True)
    assert p.returncode == 0 and "Traceback" not in p.stderr, (args, p.stderr[-3000:])
    return p


def _arrays(path: Path) -> dict:
    out = {}
    with h5py.File(path, "r") as f:
        f.visititems(lambda name, obj: out.__setitem__(name, obj[()]) if isinstance(obj, h5py.Dataset) else None)
    return out


def _assert_same_arrays(a: Path, b: Path) -> None:
    x, y = _arrays(a), _arrays(b)
    assert x.keys() == y.keys() and x
    for k in x:
        np.testing.assert_array_equal(x[k], y[k], err_msg=f"{a.name} {k}")


# ---------------------------------------------------------------------------------------------- end to end
def test_simulate_evaluate_fit_em_without_the_linux_only_capabilities(tmp_path):
    """simulate (on an empty kernel cache: the warm-up process without prctl, numba's saves locked without
    flock), evaluate and fit-em (without fork too: no warm-up, the models one after another) end with exit
    0 and the arrays and tables of a run with every capability."""
    config, study = ROOT / "configs/default.yaml", ROOT / "configs/em-magnetic-pratt2022/study.yaml"
    fit_args = ["--model", "both", "--set", "runs.count=4", "--set", "stop.time=3"]
    full = _env(tmp_path)
    _needle(["simulate", config, "--runs", 2, "--out", "full.h5"], full, tmp_path)
    _needle(["evaluate", "full.h5", "--out", "full_tables"], full, tmp_path)
    _needle(["fit-em", study, *fit_args, "--out", "full_fit.h5"], full, tmp_path)

    cache = tmp_path / "cache"
    bare = _env(tmp_path, TAKEN, NEEDLECLI_KERNEL_CACHE=str(cache), **{platform.SWITCH: SWITCHED})
    _needle(["simulate", config, "--runs", 2, "--out", "bare.h5"], bare, tmp_path)
    no_fork = _env(tmp_path, (*TAKEN, "fork"), **{platform.SWITCH: SWITCHED})
    _needle(["evaluate", "bare.h5", "--out", "bare_tables"], no_fork, tmp_path)
    _needle(["fit-em", study, *fit_args, "--out", "bare_fit.h5"], no_fork, tmp_path)

    _assert_same_arrays(tmp_path / "full.h5", tmp_path / "bare.h5")
    _assert_same_arrays(tmp_path / "full_fit.h5", tmp_path / "bare_fit.h5")
    tables = sorted(p.name for p in (tmp_path / "full_tables").iterdir() if p.suffix in (".csv", ".md", ".tex"))
    assert tables
    for name in tables:
        assert (tmp_path / "bare_tables" / name).read_text() == (tmp_path / "full_tables" / name).read_text(), name
    assert list(cache.rglob("*.nbi")), "the kernels were compiled into the empty cache"
    assert not list(cache.rglob("*.lock")) and not list(cache.rglob("*.excl")), "saves locked by lock files, removed"


def test_every_check_sees_a_capability_removed_before_needlecli_runs(tmp_path):
    """The checks look each capability up when called: what the sitecustomize removed is absent for them
    (and present without it, on Linux)."""
    code = ("from needlecli import platform as p\n"
            "print(p.has_fallocate(), p.has_direct_io(), p.has_flock(), p.has_mallopt(), p.fork_available(),"
            " p.free_bytes('.') is not None, p.max_name_length('.'))")
    runs = {}
    for name, take in (("full", ()), ("bare", (*TAKEN, "fork"))):
        runs[name] = subprocess.run([sys.executable, "-c", code], env=_env(tmp_path, take), cwd=tmp_path,
                                    capture_output=True, text=True, check=True).stdout.split()
    if not sys.platform.startswith("linux"):
        pytest.skip("the full set is Linux's")
    assert runs["full"][:6] == ["True"] * 6
    assert runs["bare"] == ["False"] * 5 + ["True", "255"]


# ---------------------------------------------------------------------------------------------- the switch
def test_the_switch_takes_capabilities_away_and_refuses_a_name_it_does_not_know(monkeypatch, tmp_path):
    monkeypatch.setenv(platform.SWITCH, "o_direct, fallocate")
    assert platform.without("fallocate") and platform.without("o_direct") and not platform.without("flock")
    assert not platform.has_fallocate() and platform.open_direct(tmp_path / "x") is None
    monkeypatch.setenv(platform.SWITCH, "fallocate,fallocat")
    with pytest.raises(ConfigError, match="'fallocat': not a capability"):
        platform.has_fallocate()
    p = subprocess.run([sys.executable, "-m", "needlecli", "list"], capture_output=True, text=True,
                       env={**os.environ, "PYTHONPATH": str(ROOT), platform.SWITCH: "flok"})
    assert p.returncode == 2 and p.stdout == ""
    assert p.stderr.startswith(f"error: {platform.SWITCH}: 'flok': not a capability") and p.stderr.count("\n") == 1


# ---------------------------------------------------------------------------------------------- files
def test_reserve_allocates_or_says_it_cannot(tmp_path, monkeypatch):
    """With posix_fallocate the blocks are allocated (st_blocks); without it nothing is done and False said;
    a file system without it is False; a full disk raises."""
    path = tmp_path / "f"
    fd = os.open(path, os.O_RDWR | os.O_CREAT)
    try:
        monkeypatch.setenv(platform.SWITCH, "fallocate")
        assert platform.reserve(fd, 1 << 20) is False and os.fstat(fd).st_size == 0
        monkeypatch.delenv(platform.SWITCH)
        if platform.has_fallocate() and platform.reserve(fd, 1 << 20):
            st = os.fstat(fd)
            assert st.st_size == 1 << 20 and st.st_blocks * 512 >= 1 << 20

        def fails(code):
            def fallocate(fd, offset, length):
                raise OSError(code, os.strerror(code))
            return fallocate

        monkeypatch.setattr(os, "posix_fallocate", fails(errno.EOPNOTSUPP), raising=False)
        assert platform.reserve(fd, 1 << 20) is False
        monkeypatch.setattr(os, "posix_fallocate", fails(errno.ENOSPC), raising=False)
        with pytest.raises(OSError, match=os.strerror(errno.ENOSPC)):
            platform.reserve(fd, 1 << 20)
        monkeypatch.delattr(os, "posix_fallocate", raising=False)
        assert platform.reserve(fd, 1 << 20) is False
    finally:
        os.close(fd)


def test_free_bytes_is_statvfs_else_shutils_disk_usage(tmp_path, monkeypatch):
    import shutil
    from collections import namedtuple

    st = namedtuple("st", "f_bavail f_frsize")(1234, 4096)
    monkeypatch.setattr(os, "statvfs", lambda path: st, raising=False)
    monkeypatch.setattr(shutil, "disk_usage", lambda path: shutil._ntuple_diskusage(10, 3, 777))
    assert platform.free_bytes(tmp_path) == 1234 * 4096
    monkeypatch.delattr(os, "statvfs")
    assert platform.free_bytes(tmp_path) == 777
    monkeypatch.delattr(shutil, "disk_usage")
    assert platform.free_bytes(tmp_path) is None  # unknown: no check of the room

    from needlecli.io.atomic import check_output_file

    check_output_file(tmp_path / "out.h5", size=10**18)  # more than any disk: not refused when unknown


def test_free_bytes_on_this_machine(tmp_path, monkeypatch):
    import shutil

    if not hasattr(os, "statvfs"):
        pytest.skip("POSIX")
    st = os.statvfs(tmp_path)
    want = st.f_bavail * st.f_frsize
    got = platform.free_bytes(tmp_path)
    monkeypatch.setenv(platform.SWITCH, "statvfs")
    fallback, usage = platform.free_bytes(tmp_path), shutil.disk_usage(tmp_path).free
    assert abs(got - want) < 2**26 and abs(fallback - usage) < 2**26 and abs(fallback - want) < 2**26  # others write


def test_max_name_length_is_pathconf_else_255(tmp_path, monkeypatch):
    """A file system with short names (pathconf's 143, eCryptfs) refuses a longer name before the work; without
    pathconf the limit is 255."""
    from needlecli.errors import OutputError
    from needlecli.io.atomic import check_output_file

    monkeypatch.setattr(os, "pathconf", lambda path, name: 143 if name == "PC_NAME_MAX" else 0, raising=False)
    assert platform.max_name_length(tmp_path) == 143
    with pytest.raises(OutputError, match="too long .200 bytes; at most 143"):
        check_output_file(tmp_path / ("x" * 197 + ".h5"))
    monkeypatch.delattr(os, "pathconf")
    assert platform.max_name_length(tmp_path) == 255
    check_output_file(tmp_path / ("x" * 197 + ".h5"))


#: two processes that each hold the lock for a while once both are ready; each says which lock it took
LOCKER = textwrap.dedent("""
    import os, sys, time
    from needlecli import platform
    log, lock, me, other = sys.argv[1:]
    open(me, "w").close()
    while not os.path.exists(other):
        time.sleep(0.005)
    with platform.file_lock(lock):
        with open(log, "a") as f:
            f.write(f"in {os.getpid()}\\n")
        time.sleep(0.3)
        with open(log, "a") as f:
            f.write(f"out {os.getpid()}\\n")
    print(platform.has_flock(), platform.has_msvcrt_locking())
""")

#: Windows' msvcrt.locking for the test of its branch on Linux: a POSIX record lock of the same bytes
FAKE_MSVCRT = textwrap.dedent("""
    import errno, fcntl, os
    LK_UNLCK, LK_LOCK, LK_NBLCK, LK_RLCK, LK_NBRLCK = 0, 1, 2, 3, 4

    def locking(fd, mode, nbytes):
        pos = os.lseek(fd, 0, os.SEEK_CUR)
        if mode == LK_UNLCK:
            fcntl.lockf(fd, fcntl.LOCK_UN, nbytes, pos)
            return
        try:
            fcntl.lockf(fd, fcntl.LOCK_EX | fcntl.LOCK_NB, nbytes, pos)
        except OSError:
            raise OSError(errno.EACCES, "Permission denied") from None
""")


@pytest.mark.parametrize("kind", ["flock", "msvcrt", "exclusive file"])
def test_file_lock_excludes_a_second_process(kind, tmp_path):
    """Whichever way it locks (flock; msvcrt.locking, as on Windows; an O_EXCL lock file), a second process
    enters only when the first has left; the lock file of the last way is removed."""
    if kind != "msvcrt" and sys.platform == "win32":
        pytest.skip("POSIX")
    env = {**os.environ, "PYTHONPATH": str(ROOT), platform.SWITCH: "" if kind == "flock" else "flock"}
    if kind == "msvcrt":
        (tmp_path / "fake").mkdir()
        (tmp_path / "fake" / "msvcrt.py").write_text(FAKE_MSVCRT)
        env["PYTHONPATH"] = os.pathsep.join([str(tmp_path / "fake"), str(ROOT)])
    log, lock = tmp_path / "log", tmp_path / "index.lock"
    procs = [subprocess.Popen([sys.executable, "-c", LOCKER, str(log), str(lock), str(tmp_path / a), str(tmp_path / b)],
                              env=env, stdout=subprocess.PIPE, text=True) for a, b in (("a", "b"), ("b", "a"))]
    said = {p.communicate(timeout=60)[0].strip() for p in procs}
    assert all(p.returncode == 0 for p in procs)
    assert said == {{"flock": "True False", "msvcrt": "False True", "exclusive file": "False False"}[kind]}
    lines = log.read_text().split()
    pids = lines[1::2]
    assert lines[0::2] == ["in", "out", "in", "out"] and pids[0] == pids[1] and pids[2] == pids[3] != pids[0]
    assert not (tmp_path / "index.lock.excl").exists()


def test_an_exclusive_lock_file_left_by_a_killed_process_is_broken(tmp_path, monkeypatch):
    import socket
    import time

    held = tmp_path / "index.lock.excl"
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True,
                          check=True).stdout.strip()
    held.write_text(f"{socket.gethostname()} {os.getpid()}\n")
    platform._break_stale_lock(str(held))
    assert held.exists()  # its process runs: held
    old = time.time() - platform.LOCK_STALE - 10
    os.utime(held, (old, old))
    platform._break_stale_lock(str(held))
    assert not held.exists()  # older than LOCK_STALE
    held.write_text(f"{socket.gethostname()} {dead}\n")
    platform._break_stale_lock(str(held))
    assert not held.exists()  # its process is gone
    held.write_text(f"{socket.gethostname()} {dead}\n")
    monkeypatch.setenv(platform.SWITCH, "flock")
    with platform.file_lock(tmp_path / "index.lock"):  # waits for nothing
        assert held.read_text().split()[1] == str(os.getpid())
    assert not held.exists()


# ---------------------------------------------------------------------------------------------- memory, threads
def test_available_memory_is_memavailable_else_sysconf_else_unknown(monkeypatch):
    if not os.path.exists("/proc/meminfo"):
        pytest.skip("Linux")
    with open("/proc/meminfo") as f:
        avail = next(int(line.split()[1]) * 1024 for line in f if line.startswith("MemAvailable:"))
    assert abs(platform.available_memory() - avail) < 2**28  # other processes allocate meanwhile
    monkeypatch.setenv(platform.SWITCH, "proc")
    monkeypatch.setattr(os, "sysconf", lambda name: {"SC_AVPHYS_PAGES": 1000, "SC_PAGE_SIZE": 4096}[name])
    assert platform.available_memory() == 4096000
    monkeypatch.delattr(os, "sysconf")
    assert platform.available_memory() is None


def test_malloc_tune_only_with_glibc_and_no_malloc_variable(monkeypatch):
    for k in [k for k in os.environ if k.startswith("MALLOC_")]:
        monkeypatch.delenv(k)
    monkeypatch.setenv(platform.SWITCH, "mallopt")
    assert not platform.has_mallopt() and not platform.malloc_tune(mmap_threshold=1 << 20, trim_threshold=1 << 20,
                                                                     top_pad=1 << 20)
    monkeypatch.delenv(platform.SWITCH)
    monkeypatch.setenv("MALLOC_ARENA_MAX_", "2")
    assert not platform.malloc_tune(mmap_threshold=1 << 20, trim_threshold=1 << 20, top_pad=1 << 20)


def test_usable_cores_is_the_affinity_else_every_core(monkeypatch):
    if hasattr(os, "sched_getaffinity"):
        assert platform.usable_cores() == len(os.sched_getaffinity(0))
    monkeypatch.setattr(os, "cpu_count", lambda: 64)
    monkeypatch.delattr(os, "sched_getaffinity", raising=False)
    assert platform.usable_cores() == 64
    monkeypatch.setattr(os, "cpu_count", lambda: None)
    assert platform.usable_cores() == 1


def test_one_thread_env_sets_and_restores(monkeypatch):
    monkeypatch.setenv("OMP_NUM_THREADS", "7")
    monkeypatch.delenv("MKL_NUM_THREADS", raising=False)
    with platform.one_thread_env():
        assert all(os.environ[k] == "1" for k in platform.THREAD_ENV)
    assert os.environ["OMP_NUM_THREADS"] == "7" and "MKL_NUM_THREADS" not in os.environ


# ---------------------------------------------------------------------------------------------- processes, signals
def test_fork_available_and_the_warm_up_without_it(monkeypatch):
    from needlecli import kernels

    if sys.platform.startswith("linux"):
        assert platform.fork_available()
    monkeypatch.setattr(sys, "platform", "darwin")
    assert not platform.fork_available()  # a forked child may crash in macOS's libraries
    monkeypatch.undo()
    monkeypatch.delattr(os, "fork", raising=False)
    assert not platform.fork_available()
    called = []
    w = kernels.warm_up(called.append, 1)
    w.wait()
    assert w._proc is None and called == []  # no second process: the run compiles everything itself


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="prctl is Linux's")
@pytest.mark.parametrize("switch", ["", "prctl"])
def test_die_with_parent_sets_pdeathsig(switch):
    """PR_GET_PDEATHSIG (prctl option 2) reads back SIGTERM after die_with_parent; nothing without prctl."""
    code = ("import ctypes\nfrom needlecli import platform\nprint(platform.die_with_parent())\n"
            "s = ctypes.c_int()\nctypes.CDLL(None).prctl(2, ctypes.byref(s))\nprint(s.value)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True,
                         env={**os.environ, "PYTHONPATH": str(ROOT), platform.SWITCH: switch}).stdout.split()
    assert out == ["True", str(int(signal.SIGTERM)) if not switch else "0"]


@pytest.mark.parametrize("switch", ["", "posix_signals"])
def test_send_self_from_another_thread_reaches_the_main_threads_handler(switch):
    """The signal re-sent from the unraisable hook's timer thread: the main thread, asleep, is woken and its
    handler runs (kill to the process on POSIX; raise_signal where signals cannot be sent to a process)."""
    code = textwrap.dedent("""
        import signal, threading, time
        from needlecli import platform
        got = []
        signal.signal(signal.SIGTERM, lambda s, f: got.append(s))
        threading.Timer(0.05, platform.send_self, (signal.SIGTERM,)).start()
        t0 = time.monotonic()
        while not got and time.monotonic() - t0 < 20:
            time.sleep(0.01)
        print(got)
    """)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True,
                         env={**os.environ, "PYTHONPATH": str(ROOT), platform.SWITCH: switch}).stdout.strip()
    assert out == f"[{int(signal.SIGTERM)}]"


def test_pid_alive_and_parent_alive(monkeypatch):
    gone = subprocess.Popen([sys.executable, "-c", "pass"])
    gone.wait()
    if os.name == "posix":
        assert platform.pid_alive(os.getpid()) and not platform.pid_alive(gone.pid)
        assert platform.parent_alive(os.getppid()) and not platform.parent_alive(gone.pid)
    monkeypatch.setenv(platform.SWITCH, "posix_signals")  # as on Windows: unknown is alive
    assert platform.pid_alive(gone.pid) and platform.parent_alive(os.getpid())


def test_cpu_quota_reads_the_control_groups_limit_and_falls_back_to_none(monkeypatch):
    """What SLURM, Kubernetes or docker --cpus set, read from a stand-in of /proc and /sys/fs/cgroup
    (cgroup v2 and v1), rounded up to whole cores; None without a limit, without /proc (the capability
    taken away) or off Linux, and usable_cores then keeps the affinity."""
    import io

    files: dict[str, str] = {}

    def fake_open(path, *a, **k):
        if str(path) not in files:
            raise FileNotFoundError(path)
        return io.StringIO(files[str(path)])

    monkeypatch.setattr(platform, "open", fake_open, raising=False)
    monkeypatch.setattr(platform.sys, "platform", "linux")
    files.update({"/proc/self/cgroup": "0::/slurm/job_7\n", "/sys/fs/cgroup/slurm/job_7/cpu.max": "150000 100000\n"})
    assert platform.cpu_quota() == 2  # 1.5 cores, rounded up
    monkeypatch.setattr(os, "cpu_count", lambda: 64)
    monkeypatch.delattr(os, "sched_getaffinity", raising=False)
    assert platform.usable_cores() == 2
    files["/sys/fs/cgroup/slurm/job_7/cpu.max"] = "max 100000\n"
    assert platform.cpu_quota() is None and platform.usable_cores() == 64
    files.clear()
    files.update({"/proc/self/cgroup": "4:cpu,cpuacct:/docker/abc\n",
                  "/sys/fs/cgroup/cpu,cpuacct/docker/abc/cpu.cfs_quota_us": "50000\n",
                  "/sys/fs/cgroup/cpu,cpuacct/docker/abc/cpu.cfs_period_us": "100000\n"})
    monkeypatch.setattr(os.path, "isdir", lambda p: p == "/sys/fs/cgroup/cpu,cpuacct/docker/abc")
    assert platform.cpu_quota() == 1
    files["/sys/fs/cgroup/cpu,cpuacct/docker/abc/cpu.cfs_quota_us"] = "-1\n"  # v1: no limit
    assert platform.cpu_quota() is None
    files["/sys/fs/cgroup/cpu,cpuacct/docker/abc/cpu.cfs_quota_us"] = "50000\n"
    monkeypatch.setenv(platform.SWITCH, "proc")  # the capability taken away
    assert platform.cpu_quota() is None
    monkeypatch.delenv(platform.SWITCH)
    monkeypatch.setattr(platform.sys, "platform", "darwin")
    assert platform.cpu_quota() is None and platform.usable_cores() == 64
