"""Signals and full disks (issue 16 item 7): SIGINT and SIGTERM handled alike (exit 130 / 143, temporary
files removed, a true message), a full disk reported in one line with nothing left on it, temporary
files of killed runs removed; and a short run of the fault injection of ``tools/faults.py`` (``make
faults`` runs at least 20 kill points of each command)."""

from __future__ import annotations

import importlib.util
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
spec = importlib.util.spec_from_file_location("faults", ROOT / "tools" / "faults.py")
faults = importlib.util.module_from_spec(spec)
sys.modules["faults"] = faults
spec.loader.exec_module(faults)

TINY = faults.SWEEP_CONFIG.replace("runs: {count: 4, seed: 1}", "runs: {count: RUNS, seed: 1}")


def needle(*args, cwd: Path, **kw) -> subprocess.CompletedProcess:
    return subprocess.run(faults._needle(*args), cwd=cwd, env=faults._env(), capture_output=True, text=True,
                          timeout=300, **kw)


def _can_mount() -> bool:
    if shutil.which("unshare") is None or os.geteuid() != 0:
        return False
    r = subprocess.run(["unshare", "-m", "sh", "-c", "mount -t tmpfs -o size=64k none /mnt"], capture_output=True)
    return r.returncode == 0


needs_mount = pytest.mark.skipif(not _can_mount(), reason="needs unshare and mount (a small file system of its own)")


def in_small_fs(folder: Path, size: str, script: str) -> subprocess.CompletedProcess:
    """Run ``script`` (sh) with a tmpfs of ``size`` mounted on ``folder``, in a mount namespace of its own
    (the file system vanishes with the process)."""
    folder.mkdir(parents=True, exist_ok=True)
    return subprocess.run(["unshare", "-m", "sh", "-c", f"mount -t tmpfs -o size={size} none {folder} && {script}"],
                          env=faults._env(), capture_output=True, text=True, timeout=300)


# ---------------------------------------------------------------------------------------------- signals
@pytest.mark.parametrize("sig, code", [(signal.SIGTERM, 143), (signal.SIGINT, 130)])
def test_signal_during_the_run_keeps_the_earlier_file(tmp_path, sig, code):
    cfg = tmp_path / "tiny.yaml"
    cfg.write_text(TINY.replace("RUNS", "3000"))  # a few seconds of work
    target = tmp_path / "out" / "r.h5"
    target.parent.mkdir()
    target.write_bytes(b"earlier results")
    p = subprocess.Popen(faults._needle("simulate", cfg, "--out", target), cwd=tmp_path, env=faults._env(),
                         stderr=subprocess.PIPE, text=True)
    first = p.stderr.readline()  # "simulating ...": the config and the output were checked, the work began
    assert first.startswith("simulating"), first
    p.send_signal(sig)
    _, err = p.communicate(timeout=120)
    assert p.returncode == code, err
    assert err.strip().splitlines()[-1] == (f"error: interrupted by {signal.Signals(sig).name}: {target} not written "
                                            "(the earlier file there is unchanged)")
    assert "Traceback" not in err
    assert target.read_bytes() == b"earlier results"
    assert [x.name for x in target.parent.iterdir()] == ["r.h5"]


def test_signal_held_while_the_file_is_built_then_acted_on(tmp_path, monkeypatch):
    """A signal that arrives while h5py builds the file is acted on when it is done, before anything is
    written: never lost in a library callback (exit 0 and the old file replaced, as before)."""
    import needlecli.io.results as results
    from needlecli.errors import Interrupted
    from needlecli.io.atomic import handle_signals, start_signals
    from needlecli.io.tree import Group

    target = tmp_path / "r.h5"
    target.write_bytes(b"earlier")
    real = results._write_group

    def write_then_signal(g, grp, *args):
        real(g, grp, *args)
        os.kill(os.getpid(), signal.SIGTERM)  # arrives inside the deferred section

    monkeypatch.setattr(results, "_write_group", write_then_signal)
    with handle_signals(), pytest.raises(Interrupted) as info:
        start_signals()
        results.write_atomic(target, Group(data={"time": np.arange(3.0)}))
    assert info.value.exit_code == 143
    assert target.read_bytes() == b"earlier"
    assert [x.name for x in tmp_path.iterdir()] == ["r.h5"]


def test_a_signal_inside_a_finalizer_is_not_lost():
    """A signal that arrives while the garbage collector runs a finalizer raises Interrupted where Python
    can only ignore it; it is sent again and interrupts the command at the next line (a sweep once
    finished all its cells after a SIGTERM lost this way)."""
    from needlecli.errors import Interrupted
    from needlecli.io.atomic import handle_signals, start_signals

    class Finalized:
        def __del__(self):
            os.kill(os.getpid(), signal.SIGTERM)
            for _ in range(1000):  # the handler runs here, inside the finalizer
                pass

    reached = []
    with handle_signals(), pytest.raises(Interrupted) as info:
        start_signals()
        x = Finalized()
        del x
        time.sleep(0.5)
        reached.append(True)
    assert info.value.exit_code == 143 and not reached


def test_sweep_interrupted_says_how_to_resume(tmp_path):
    cfg, grid = tmp_path / "tiny.yaml", tmp_path / "grid.yaml"
    cfg.write_text(TINY.replace("RUNS", "300"))
    grid.write_text("grid:\n  runs.seed: range(40)\n")
    out = tmp_path / "sweep"
    p = subprocess.Popen(faults._needle("sweep", cfg, "--grid", grid, "--out", out, "--executor", "inline", "--quiet"),
                         cwd=tmp_path, env=faults._env(), stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline and len(list((out / "cells").glob("*.h5"))) < 2:
        time.sleep(0.05)
    p.send_signal(signal.SIGTERM)
    _, err = p.communicate(timeout=120)
    assert p.returncode == 143, err
    line = err.strip().splitlines()[-1]
    assert line.startswith("error: interrupted by SIGTERM: written completely before it: ") and "--resume" in line
    assert not list(out.rglob("*.needle-tmp"))


# ---------------------------------------------------------------------------------------------- temporaries
def test_a_signal_before_the_command_runs_is_raised_where_it_is_caught():
    """A signal between installing the handlers and the command's body is held, then raised inside the
    command (where the message is made), never in between (click would say 'Aborted!', exit 1)."""
    from needlecli.errors import Interrupted
    from needlecli.io.atomic import handle_signals, start_signals

    with handle_signals():
        os.kill(os.getpid(), signal.SIGINT)  # held
        with pytest.raises(Interrupted) as info:
            start_signals()
    assert info.value.exit_code == 130


def test_stale_temporaries_of_killed_runs_are_removed(tmp_path):
    from needlecli.io.atomic import _HOST, STALE_AGE, TMP_MARK, remove_stale

    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    folder = tmp_path / "out"
    folder.mkdir()
    killed = folder / f".r.h5.{_HOST}-{dead.pid}-0123abcd{TMP_MARK}"  # this host, its process is gone
    alive = folder / f".r.h5.{_HOST}-{os.getppid()}-0123abcd{TMP_MARK}"  # a process that still runs
    other_new = folder / f".r.h5.otherhost-12-0123abcd{TMP_MARK}"  # another host: judged by age only
    other_old = folder / f".r.h5.otherhost-13-0123abcd{TMP_MARK}"
    foreign = folder / ".r.h5.abcdefgh.tmp"  # not ours
    for p in (killed, alive, other_new, other_old, foreign):
        p.write_bytes(b"partial")
    old = time.time() - STALE_AGE - 60
    os.utime(other_old, (old, old))
    removed = remove_stale(folder, force=True)
    assert sorted(removed) == sorted([killed, other_old])
    assert sorted(p.name for p in folder.iterdir()) == sorted(p.name for p in (alive, other_new, foreign))


def test_the_next_run_removes_a_killed_runs_temporary(tmp_path):
    cfg = tmp_path / "tiny.yaml"
    cfg.write_text(TINY.replace("RUNS", "2"))
    folder = tmp_path / "out"
    folder.mkdir()
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    from needlecli.io.atomic import _HOST, TMP_MARK

    left = folder / f".r.h5.{_HOST}-{dead.pid}-89abcdef{TMP_MARK}"
    left.write_bytes(b"what a SIGKILL left")
    r = needle("simulate", cfg, "--out", folder / "r.h5", "--quiet", cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    assert [p.name for p in folder.iterdir()] == ["r.h5"]


# ---------------------------------------------------------------------------------------------- full disks
@needs_mount
def test_full_disk_refused_before_the_work(tmp_path):
    cfg = tmp_path / "tiny.yaml"
    cfg.write_text(TINY.replace("RUNS", "200"))
    small = tmp_path / "small"
    script = f"{sys.executable} -c 'from needlecli.cli.app import run; run()' simulate {cfg} --out {small}/r.h5 --quiet"
    r = in_small_fs(small, "256k", script + f"; echo rc=$?; ls -A {small}")
    assert "rc=2" in r.stdout, r.stdout + r.stderr
    assert r.stdout.strip().endswith("rc=2"), r.stdout  # nothing listed in the folder
    assert r.stderr.strip().startswith(f"error: {small}/r.h5: the results file needs up to ") and \
        "free there: free some space or choose another --out" in r.stderr, r.stderr


@needs_mount
def test_disk_full_while_writing_is_one_error_and_leaves_nothing(tmp_path):
    """The disk fills while the file is written (after the checks): one OutputError, the temporary file
    removed, the earlier file kept; HDF5 never meets the full disk (it would crash)."""
    small = tmp_path / "small"
    code = (
        "import numpy as np\n"
        "from needlecli.io.results import write_atomic\n"
        "from needlecli.io.tree import Group\n"
        "from needlecli.errors import OutputError\n"
        f"t = '{small}/r.h5'\n"
        "open(t, 'wb').write(b'earlier')\n"
        "try:\n"
        "    write_atomic(t, Group(data={'x': np.random.default_rng(0).random((400, 1000))}))\n"
        "except OutputError as e:\n"
        "    print('error:', e)\n"
    )
    r = in_small_fs(small, "1m", f"{sys.executable} -c \"{code}\"; echo rc=$?; ls -A {small}; cat {small}/r.h5")
    lines = r.stdout.strip().splitlines()
    assert lines[0] == (f"error: {small}/r.h5: cannot write: no space left on the device (the disk is full); "
                        "nothing was written (the earlier file there is unchanged)"), r.stdout + r.stderr
    assert lines[1:] == ["rc=0", "r.h5", "earlier"], r.stdout
    assert r.stderr == "", r.stderr


@needs_mount
def test_read_only_file_system_refused_before_the_work(tmp_path):
    cfg = tmp_path / "tiny.yaml"
    cfg.write_text(TINY.replace("RUNS", "2"))
    ro = tmp_path / "ro"
    ro.mkdir()
    r = subprocess.run(["unshare", "-m", "sh", "-c", f"mount -t tmpfs -o ro none {ro} && {sys.executable} -c "
                        f"'from needlecli.cli.app import run; run()' simulate {cfg} --out {ro}/r.h5 --quiet"],
                       env=faults._env(), capture_output=True, text=True, timeout=120)
    assert r.returncode == 2
    assert r.stderr.strip() == f"error: {ro}/r.h5: cannot write in {ro}: the file system is read-only"


# ---------------------------------------------------------------------------------------------- fault injection
def test_fault_injection_simulate(tmp_path):
    points = faults.simulate_faults(tmp_path, 3, np.random.default_rng(3), runs=20)
    assert all(not p.problems for p in points), "\n".join(p.line() for p in points)


def test_fault_injection_sweep_and_resume(tmp_path):
    points = faults.sweep_faults(tmp_path, 2, np.random.default_rng(4), executor="inline", seeds=2)
    assert all(not p.problems for p in points), "\n".join(p.line() for p in points)


# ---------------------------------------------------------------------------------------------- refusing file systems
def _chattr(flag: str, path: Path) -> bool:
    return shutil.which("chattr") is not None and subprocess.run(["chattr", flag, str(path)],
                                                                 capture_output=True).returncode == 0


@pytest.mark.parametrize("what", ["file", "folder"])
def test_immutable_target_refused_before_the_work(tmp_path, what):
    cfg = tmp_path / "tiny.yaml"
    cfg.write_text(TINY.replace("RUNS", "2"))
    folder = tmp_path / "out"
    folder.mkdir()
    target = folder / "r.h5"
    target.write_bytes(b"earlier")
    locked = target if what == "file" else folder
    if not _chattr("+i", locked):
        pytest.skip("chattr +i is not available here")
    try:
        r = needle("simulate", cfg, "--out", target, "--quiet", cwd=tmp_path)
    finally:
        _chattr("-i", locked)
    assert r.returncode == 2
    want = ("exists and cannot be replaced (read-only or immutable)" if what == "file"
            else f"cannot write in {folder}: permission denied")
    assert r.stderr.strip() == f"error: {target}: {want}", r.stderr
    assert target.read_bytes() == b"earlier" and [p.name for p in folder.iterdir()] == ["r.h5"]


# ---------------------------------------------------------------------------------------------- one set of outputs
def test_a_set_is_renamed_into_place_together_and_readable_before(tmp_path):
    """Inside a set each file is complete in its temporary file, readable through the input opener under
    its own name, and nothing is at the targets until the set ends; then all of them are."""
    from needlecli.io.atomic import output_set, staged_path, write_text_atomic
    from needlecli.io.inputs import read_text

    out = tmp_path / "new" / "folder"
    with output_set():
        write_text_atomic(out / "a.txt", "first\n")
        write_text_atomic(out / "sub" / "b.txt", "second\n")
        write_text_atomic(out / "a.txt", "first, again\n")  # written twice: the later one counts
        assert not (out / "a.txt").exists() and not (out / "sub" / "b.txt").exists()
        assert staged_path(out / "a.txt") != out / "a.txt"
        assert read_text(out / "a.txt", "a text", limit=100) == "first, again\n"
    assert (out / "a.txt").read_text() == "first, again\n" and (out / "sub" / "b.txt").read_text() == "second\n"
    assert sorted(p.name for p in out.rglob("*")) == ["a.txt", "b.txt", "sub"]


def test_a_set_that_fails_leaves_nothing_not_even_its_folders(tmp_path):
    from needlecli.errors import DataError
    from needlecli.io.atomic import JOURNAL, output_set, write_text_atomic

    (tmp_path / "keep.txt").write_text("earlier")
    JOURNAL.reset()
    with pytest.raises(DataError), output_set():
        write_text_atomic(tmp_path / "keep.txt", "new")
        write_text_atomic(tmp_path / "a" / "b" / "c.txt", "new")
        raise DataError("a later step fails")
    assert [p.name for p in tmp_path.iterdir()] == ["keep.txt"]
    assert (tmp_path / "keep.txt").read_text() == "earlier" and not JOURNAL.inflight and not JOURNAL.written


def test_a_set_kept_after_a_verdict(tmp_path):
    """A command that ends with exit code 1 after its outputs are complete (a regression) keeps them."""
    from needlecli.io.atomic import output_set, write_text_atomic

    class Verdict(Exception):
        pass

    with pytest.raises(Verdict), output_set() as s:
        write_text_atomic(tmp_path / "t.md", "table\n")
        s.keep = True
        raise Verdict
    assert (tmp_path / "t.md").read_text() == "table\n"


def test_a_rename_that_fails_in_the_middle_says_what_was_written(tmp_path, monkeypatch):
    import errno

    import needlecli.io.atomic as atomic
    from needlecli.errors import OutputError

    calls = [0]
    real = os.replace

    def replace(a, b):
        calls[0] += 1
        if calls[0] == 2:
            raise OSError(errno.EACCES, "Permission denied", str(b))
        real(a, b)

    with pytest.raises(OutputError) as info, atomic.output_set():
        for name in ("a", "b", "c"):
            atomic.write_text_atomic(tmp_path / name, name)
        monkeypatch.setattr(atomic.os, "replace", replace)
    monkeypatch.undo()
    assert str(info.value) == (f"{tmp_path / 'b'}: cannot write: permission denied; 1 of the 3 outputs were written "
                               f"before it ({tmp_path / 'a'}); not written: {tmp_path / 'b'}, {tmp_path / 'c'} (an "
                               "earlier file there is unchanged)")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a"]


# ---------------------------------------------------------------------------------------------- the newer commands
@pytest.mark.parametrize("command, points", [("compare", 2), ("import-csv", 2), ("fit-em", 2), ("crossval", 1)])
def test_fault_injection_of_a_set_of_outputs(tmp_path, command, points):
    found = faults.set_faults(command, tmp_path, points, np.random.default_rng(5))
    assert all(not p.problems for p in found), "\n".join(p.line() for p in found)
