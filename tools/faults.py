"""Fault injection: ``needle simulate`` and ``needle sweep`` killed at random points, and what is on disk
after each kill checked.

    python tools/faults.py [--points 20] [--seed 0] [--executor local] [--work DIR]   (make faults)

For each kill point a fresh process is started and sent, after a random delay between 0 and 1.1 times
the length of an uninterrupted run, SIGKILL, SIGTERM or SIGINT (in turn). Then:

* ``simulate`` (the target holds an earlier, complete results file of another seed): the target is
  exactly the earlier file or a complete new one (every array equal to an uninterrupted run's), never
  a partial one; after SIGTERM or SIGINT the exit status is 143 or 130 (or the signal's own status when
  it came before the command had started: no file is open then), no temporary file is left, and the
  message says truly whether the target was replaced; after SIGKILL a temporary file may be left, and
  the next write into the folder removes it (its process is gone).
* ``sweep`` (in a fresh folder): every cell file present is a complete results file of its cell; once
  the killed process and its workers have ended, ``needle sweep --resume`` completes the sweep, leaves
  no temporary file, and its table equals an uninterrupted sweep's (runtimes aside).

Prints one line per kill point; exit status 1 if any check fails. ``tests/test_faults.py`` runs a few
points of each; ``make faults`` runs kill points until 20 of each stopped a running process.
"""

from __future__ import annotations

import argparse
import contextlib
import hashlib
import os
import shutil
import signal
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import h5py
import numpy as np
import pandas as pd

SIGNALS = (signal.SIGKILL, signal.SIGTERM, signal.SIGINT)
VOLATILE = {"created", "git_hash", "needlecli_version"}
SIMULATE_CONFIG = """\
name: faults
model: {type: unicycle, params: {kappa: 0.002}}
inputs: {v: 2.0, u: {kind: flips, at_times: [5.0]}}
sensors:
  - {name: us, type: position, rate: 20.0, sigma: 0.1}
observers:
  - {name: ol, type: open_loop, init: {from: truth, std: {alpha: 0.01}}}
runs: {count: RUNS, seed: 1}
stop: {time: 20.0}
simulation: {dt: 0.01}
output: {store_every: 1, covariance: full, tables: [summary]}
"""
SWEEP_CONFIG = """\
name: faults_sweep
model: {type: unicycle, params: {kappa: 0.002}}
inputs: {v: 2.0, u: 0.0}
sensors:
  - {name: us, type: position, rate: 10.0, sigma: 0.1}
observers:
  - {name: ol, type: open_loop, init: {from: truth, std: {alpha: 0.02}}}
runs: {count: 4, seed: 1}
stop: {time: 4.0}
simulation: {dt: 0.01}
"""
SWEEP_GRID = "grid:\n  runs.seed: range(SEEDS)\n  sensors.0.rate: [5.0, 10.0]\n"


@dataclass
class Point:
    command: str
    index: int
    signal: str
    delay: float
    code: int
    outcome: str  # what was found: earlier, new, cells complete, ...
    problems: list[str]

    def line(self) -> str:
        state = "ok" if not self.problems else "FAIL: " + "; ".join(self.problems)
        return (f"{self.command:8s} #{self.index:02d} {self.signal:7s} after {self.delay:5.2f} s: exit {self.code:4d}, "
                f"{self.outcome}: {state}")


def _needle(*args) -> list[str]:
    return [sys.executable, "-c", "from needlecli.cli.app import run; run()", *map(str, args)]


def _env() -> dict:
    env = dict(os.environ)
    root = str(Path(__file__).resolve().parent.parent)
    env["PYTHONPATH"] = root + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
    return env


def _run(args, cwd: Path, timeout: float = 300.0) -> subprocess.CompletedProcess:
    return subprocess.run(_needle(*args), cwd=cwd, env=_env(), capture_output=True, text=True, timeout=timeout)


def _arrays(path: Path) -> dict[str, str]:
    """Digest of every dataset and attribute of an HDF5 file (what differs between runs aside)."""
    out = {}
    with h5py.File(path, "r") as f:
        def visit(name, obj):
            if isinstance(obj, h5py.Dataset):
                v = obj[()]
                out[name] = hashlib.sha256(np.asarray(v).tobytes() if v.dtype.kind not in "OS" else
                                           repr(v.tolist()).encode()).hexdigest()
        f.visititems(visit)
        for k, v in f.attrs.items():
            if k not in VOLATILE:
                out[f"@{k}"] = repr(v.tolist() if hasattr(v, "tolist") else v)
    return out


def _temporaries(folder: Path) -> list[Path]:
    return sorted(p for p in folder.rglob("*.needle-tmp"))


def _kill_after(cmd: list[str], cwd: Path, delay: float, sig: int, group: bool) -> tuple[int, str]:
    p = subprocess.Popen(cmd, cwd=cwd, env=_env(), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                         start_new_session=group)
    try:
        p.wait(timeout=delay)
    except subprocess.TimeoutExpired:
        os.kill(p.pid, sig)
    try:
        out, err = p.communicate(timeout=300)
    except subprocess.TimeoutExpired:  # it (or a worker holding its stderr) hangs: a failure, reported
        with contextlib.suppress(ProcessLookupError):
            os.killpg(p.pid, signal.SIGKILL) if group else p.kill()
        out, err = p.communicate()
        return -1000, err + "\nHUNG: still running 300 s after the signal"
    if group:  # the killed sweep's worker processes: wait until they are gone, as a user would
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline:
            try:
                os.killpg(p.pid, 0)
            except ProcessLookupError:
                break
            time.sleep(0.05)
        else:
            os.killpg(p.pid, signal.SIGKILL)
            err += "\nHUNG: worker processes still running 60 s after the signal"
    return p.returncode, err


def _timed(args, work: Path) -> float:
    """How long an uninterrupted run of ``args`` takes (s)."""
    t0 = time.perf_counter()
    r = _run(args, work)
    assert r.returncode == 0, r.stderr
    return time.perf_counter() - t0


def _kill_points(points: int, rng: np.random.Generator, length: float, out: list):
    """``(index, signal, delay)`` of each kill point: the signals in turn, delays in [0, 1.1 length), until
    ``points`` of them stopped a live process (a signal after the command had finished, exit 0, is
    checked too but does not count; at most 3 x ``points`` in all)."""
    i = 0
    while _live(out) < points and i < 3 * points:
        yield i, SIGNALS[i % len(SIGNALS)], float(rng.uniform(0.0, 1.1 * length))
        i += 1


def _live(out: list) -> int:
    """How many kill points stopped a process that was still running."""
    return sum(p.code != 0 for p in out)


def _status_problems(sig: int, code: int, err: str) -> tuple[list[str], bool]:
    """What is wrong with how a killed process ended, and whether it was stopped while Python started."""
    problems = ["a process hung"] if "HUNG:" in err else []
    early = _while_python_started(sig, code, err)
    if code not in _expected_codes(sig) and not early:
        problems.append(f"exit status {code}")
    return problems, early


def _expected_codes(sig: int) -> set[int]:
    return {0, -sig, 128 + sig} if sig != signal.SIGKILL else {0, -signal.SIGKILL}


def _while_python_started(sig: int, code: int, err: str) -> bool:
    """SIGINT in the first tens of milliseconds, while the interpreter starts and before any code of
    needlecli runs: Python's own KeyboardInterrupt (exit 1); no file can be open then."""
    last = [ln for ln in err.splitlines() if ln.strip()]
    return sig == signal.SIGINT and code in (1, -2) and bool(last) and last[-1] == "KeyboardInterrupt"


# ---------------------------------------------------------------------------------------------- simulate
def simulate_faults(work: Path, points: int, rng: np.random.Generator, runs: int = 60) -> list[Point]:
    from needlecli.io.atomic import remove_stale
    from needlecli.io.results import read_results

    work.mkdir(parents=True, exist_ok=True)
    cfg = work / "simulate.yaml"
    cfg.write_text(SIMULATE_CONFIG.replace("RUNS", str(runs)))
    earlier, reference = work / "earlier.h5", work / "reference.h5"
    _timed(["simulate", cfg, "--out", earlier, "--seed", "11", "--quiet"], work)
    length = _timed(["simulate", cfg, "--out", reference, "--seed", "12", "--quiet"], work)
    ref = _arrays(reference)
    earlier_bytes = earlier.read_bytes()
    out = []
    for i, sig, delay in _kill_points(points, rng, length, out):
        folder = work / f"simulate_{i:02d}"
        shutil.rmtree(folder, ignore_errors=True)
        folder.mkdir()
        target = folder / "results.h5"
        target.write_bytes(earlier_bytes)
        code, err = _kill_after(_needle("simulate", cfg, "--out", target, "--seed", "12", "--quiet"), work, delay,
                                sig, group=False)
        problems, early = _status_problems(sig, code, err)
        if not target.is_file():
            problems.append("the target is gone")
            outcome = "nothing"
        elif target.read_bytes() == earlier_bytes:
            outcome = "earlier file intact" + (" (stopped while Python started)" if early else "")
        else:
            try:
                read_results(target)
                outcome = "new file complete" if _arrays(target) == ref else "new file DIFFERS"
            except Exception as e:  # noqa: BLE001 (a partial file is the failure this looks for)
                outcome = f"PARTIAL file ({type(e).__name__})"
            if outcome != "new file complete":
                problems.append(outcome)
        temps = _temporaries(folder)
        if temps and sig != signal.SIGKILL:
            problems.append(f"temporary files left: {[t.name for t in temps]}")
        if temps:  # after SIGKILL: the next write into the folder removes them (their process is gone)
            remove_stale(folder, force=True)
            if _temporaries(folder):
                problems.append("a killed run's temporary file was not removed")
            outcome += f", {len(temps)} temporary file(s) of the killed run removed"
        if code in (130, 143):
            last = [ln for ln in err.splitlines() if ln.strip()]
            line = last[-1] if last else ""
            if not line.startswith(f"error: interrupted by {signal.Signals(sig).name}"):
                problems.append(f"message {line!r}")
            elif outcome.startswith("earlier") and not (f"{target} not written" in line or "no file was written" in line):
                problems.append(f"the message does not say the target is unchanged: {line!r}")
            elif outcome.startswith("new") and f"written completely before it: {target}" not in line:
                problems.append(f"the message does not say the target was written: {line!r}")
            if "Traceback" in err:
                problems.append("a traceback")
        out.append(Point("simulate", i, signal.Signals(sig).name, delay, code, outcome, problems))
    return out


# ---------------------------------------------------------------------------------------------- sweep
def _table(folder: Path) -> pd.DataFrame:
    df = pd.read_csv(folder / "sweep.csv")
    return df.drop(columns=[c for c in ("seconds",) if c in df.columns]).sort_values(list(df.columns[:3])).reset_index(drop=True)


def sweep_faults(work: Path, points: int, rng: np.random.Generator, executor: str = "local", seeds: int = 4) -> list[Point]:
    from needlecli.io.results import read_results

    work.mkdir(parents=True, exist_ok=True)
    cfg, grid = work / "sweep.yaml", work / "grid.yaml"
    cfg.write_text(SWEEP_CONFIG)
    grid.write_text(SWEEP_GRID.replace("SEEDS", str(seeds)))
    args = ["sweep", cfg, "--grid", grid, "--executor", executor, "--workers", "2", "--quiet"]
    length = _timed([*args, "--out", work / "sweep_reference"], work)
    ref = _table(work / "sweep_reference")
    out = []
    for i, sig, delay in _kill_points(points, rng, length, out):
        folder = work / f"sweep_{i:02d}"
        shutil.rmtree(folder, ignore_errors=True)
        code, err = _kill_after(_needle(*args, "--out", folder), work, delay, sig, group=True)
        problems, early = _status_problems(sig, code, err)
        cells = sorted((folder / "cells").glob("*.h5")) if (folder / "cells").is_dir() else []
        for c in cells:
            try:
                read_results(c)
            except Exception as e:  # noqa: BLE001
                problems.append(f"PARTIAL cell {c.name} ({type(e).__name__})")
        temps = _temporaries(folder) if folder.exists() else []
        if temps and sig != signal.SIGKILL:
            problems.append(f"temporary files left: {[t.name for t in temps]}")
        if code in (130, 143):
            last = [ln for ln in err.splitlines() if ln.strip()]
            line = last[-1] if last else ""
            started = (folder / "sweep.json").exists()  # the cells were planned: the message says how to go on
            if not line.startswith(f"error: interrupted by {signal.Signals(sig).name}") \
                    or (started and "--resume" not in line and "written completely" not in line):
                problems.append(f"message {line!r}")
        resumed = _run([*args, "--out", folder, "--resume"], work)
        if resumed.returncode != 0:
            problems.append(f"--resume exit {resumed.returncode}: {resumed.stderr.strip()[-200:]}")
        elif not _table(folder).equals(ref):
            problems.append("the resumed table differs from an uninterrupted sweep's")
        if _temporaries(folder):
            problems.append("temporary files left after --resume")
        outcome = ("stopped while Python started, " if early else "") + f"{len(cells)} complete cell(s) kept" + \
            (f", {len(temps)} temporary file(s)" if temps else "") + ", resumed to the same table"
        out.append(Point("sweep", i, signal.Signals(sig).name, delay, code, outcome, problems))
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--points", type=int, default=20, help="kill points per command (default 20)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--executor", default="local", help="the sweep's executor (local, inline)")
    ap.add_argument("--work", type=Path, default=Path("results") / "faults")
    a = ap.parse_args(argv)
    a.work = a.work.resolve()
    rng = np.random.default_rng(a.seed)
    points = simulate_faults(a.work / "simulate", a.points, rng) + sweep_faults(a.work / "sweep", a.points, rng, a.executor)
    for p in points:
        print(p.line())
    bad = [p for p in points if p.problems]
    print(f"{len(points) - len(bad)} of {len(points)} kill points held")
    for command in ("simulate", "sweep"):
        mine = [p for p in points if p.command == command]
        print(f"{command}: {_live(mine)} of {len(mine)} kill points stopped a running process"
              f" (the others came after it had finished)")
    short = [c for c in ("simulate", "sweep") if _live([p for p in points if p.command == c]) < a.points]
    if short:
        print(f"fewer than {a.points} kill points stopped a running {' and '.join(short)}")
    return 1 if bad or short else 0


if __name__ == "__main__":
    sys.exit(main())
