"""Fault injection: ``needle simulate``, ``needle sweep``, ``needle crossval``, ``needle compare``, ``needle
log import-csv`` and ``needle fit-em`` killed at random points, and what is on disk after each kill checked.

    python tools/faults.py [--points 20] [--seed 0] [--executor local] [--work DIR] [--commands a,b]
                                                                                        (make faults)

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

* ``crossval``, ``compare`` (a folder of outputs: the results files, fits, tables, plots, written as one
  set), ``import-csv`` and ``fit-em`` (one file): the target holds an earlier complete output of another
  seed (or, for import-csv, another log). After each kill it holds exactly the earlier output (every file
  byte for byte, no file more) or exactly a complete new one (the files of an uninterrupted run, each
  HDF5 file's arrays equal to its own, each table and plot equal, runtimes aside), never a mix; the rest
  as for ``simulate`` (exit status, no temporary file after SIGTERM or SIGINT, a true message; after
  SIGKILL the temporary files are removed by the next write into their folders, and the folders the
  killed run made for them are empty).

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
#: the magnetic needle EM paper's EM on short simulated trials (every trial's fit converges), an observer to tune (crossval)
FIT_CONFIG = """\
name: faults_fit
model: {type: mnm, params: {c: 9.5}, initial_state: {hy: -1.0, By: -1.0}}
inputs: {v: 0.002, omega_B: [0.0, 0.0, 0.05]}
process_noise: {std: {px: 3.0e-5, py: 3.0e-5, hx: 2.0e-3, hy: 2.0e-3}}
sensors:
  - {name: camera, type: position, rate: 6.0, axes: [x, y], sigma: 5.2e-5}
  - {name: coils, type: bfield, rate: 18.0, sigma: 1.0e-4}
observers:
  - {name: model, type: open_loop}
runs: {count: RUNS, seed: 4}
stop: {time: 4.0}
simulation: {dt: 0.01}
fit:
  models: [mnm]
  q: {px: 1.0e-4, py: 1.0e-4, hx: 5.0e-3, hy: 5.0e-3}
  measurements: {camera: {sigma: 1.0e-4}, coils: {sigma: 3.0e-4}}
  init: {values: {hy: -1.0, c: 8.0}, first_measurement: {px: camera.x, py: camera.y}}
  em: {max_iter: 8, tol: 1.0}
  repeats: 1
"""
#: a lab's CSV exports: TRIALS trials of ROWS rows, the insertion speed and a tracker's positions
CSV_MAPPING = """\
description: faults
trials: TRIALS
inputs:
  v: {file: robot.csv, column: speed, unit: mm/s}
sensors:
  us:
    file: us.csv
    columns: {x: tx, y: ty, z: tz}
    units: [mm, mm, mm]
    sensor: {type: position, rate: 10.0, sigma: 0.3}
"""
#: files whose content holds runtimes: compared by their presence only
VOLATILE_FILES = ("compare.md", "compare.csv")
VOLATILE_DATASETS = ("compare/seconds",)


COMMANDS = ("simulate", "sweep", "crossval", "compare", "import-csv", "fit-em")


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
        return (f"{self.command:10s} #{self.index:02d} {self.signal:7s} after {self.delay:5.2f} s: exit {self.code:4d}, "
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
            if isinstance(obj, h5py.Dataset) and name not in VOLATILE_DATASETS:
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


# ---------------------------------------------------------------------------------------------- sets of outputs
def _snapshot(folder: Path) -> dict[str, bytes | None]:
    """Every file (its bytes) and folder (None) below ``folder``, by relative path."""
    if not folder.exists():
        return {}
    return {str(p.relative_to(folder)): (p.read_bytes() if p.is_file() else None) for p in sorted(folder.rglob("*"))}


def _same_as(path: Path, reference: Path) -> bool:
    """Whether ``path`` is ``reference``'s content as an uninterrupted run writes it (runtimes aside)."""
    if path.name in VOLATILE_FILES:
        return path.stat().st_size > 0
    if path.suffix == ".h5":
        try:
            return _arrays(path) == _arrays(reference)
        except Exception:  # noqa: BLE001 (a partial file is the failure this looks for)
            return False
    return path.read_bytes() == reference.read_bytes()


def _outcome(root: Path, earlier: dict, reference: Path) -> tuple[str, list[str]]:
    """What ``root`` holds after a kill: the earlier set, a complete new set, or something else."""
    now = {k: v for k, v in _snapshot(root).items() if not k.endswith(".needle-tmp")}
    ref = _snapshot(reference)
    files = {k for k, v in now.items() if v is not None}
    if now == earlier:
        return "earlier output intact", []
    new_files = {k for k, v in ref.items() if v is not None}
    if files == new_files and all(_same_as(root / k, reference / k) for k in files):
        return "new output complete", []
    kept = sorted(k for k in files if earlier.get(k) == now[k])
    made = sorted(k for k in files if earlier.get(k) != now[k])
    missing = sorted(new_files - files)
    return "a MIX of earlier and new", [f"earlier files {kept[:4]}, new or changed {made[:4]}, missing {missing[:4]}"]


@dataclass
class SetCommand:
    """A command whose outputs are checked as a set: ``args(target, seed)`` its arguments writing to
    ``target`` (a folder, or a file in folder ``root``), ``prepare(work)`` its inputs."""

    name: str
    args: object  # (target: Path, variant: int) -> list
    prepare: object  # (work: Path) -> None
    file: str | None = None  # the output file's name in the target folder (one-file commands)


def _crossval_prepare(work: Path) -> None:
    (work / "cv.yaml").write_text(FIT_CONFIG.replace("RUNS", "3"))


def _compare_prepare(work: Path) -> None:
    (work / "cmp.yaml").write_text(SIMULATE_CONFIG.replace("RUNS", "40"))


def _fit_prepare(work: Path) -> None:
    (work / "fit.yaml").write_text(FIT_CONFIG.replace("RUNS", "4"))


def _csv_prepare(work: Path, trials: int = 12, rows: int = 4000) -> None:
    rng = np.random.default_rng(0)
    (work / "csv").mkdir(exist_ok=True)
    ids = []
    for k in range(trials):
        d = work / "csv" / f"t{k:02d}"
        d.mkdir(exist_ok=True)
        t = np.arange(rows) * 0.1
        (d / "robot.csv").write_text("t,speed\n" + "".join(f"{x:.1f},2\n" for x in t))
        z = 0.2 * np.arange(rows)
        xy = rng.normal(0.0, 0.3, (rows, 2))
        (d / "us.csv").write_text("t,tx,ty,tz\n" + "".join(f"{a:.1f},{b:.6f},{c:.6f},{e:.6f}\n"
                                                          for a, (b, c), e in zip(t, xy, z)))
        ids.append(f"  - {{id: t{k:02d}, dir: t{k:02d}}}")
    (work / "csv" / "mapping.yaml").write_text(CSV_MAPPING.replace("TRIALS", "\n" + "\n".join(ids)))
    (work / "tiny.yaml").write_text(SWEEP_CONFIG)


SET_COMMANDS = {
    "crossval": SetCommand("crossval", lambda t, v: ["crossval", "cv.yaml", "--observer", "model", "--folds", "3",
                                                     "--set", f"runs.seed={4 + v}", "--out", t, "--quiet"],
                           _crossval_prepare),
    "compare": SetCommand("compare", lambda t, v: ["compare", "cmp.yaml", "--observers", "ol,ekf", "--seed", 12 + v,
                                                   "--out", t, "--quiet"], _compare_prepare),
    "import-csv": SetCommand("import-csv", lambda t, v: (["log", "import-csv", "csv/mapping.yaml", "--out", t / "lab.h5"]
                                                          if v == 0 else ["simulate", "tiny.yaml", "--out", t / "lab.h5",
                                                                          "--quiet"]),
                             _csv_prepare, file="lab.h5"),
    "fit-em": SetCommand("fit-em", lambda t, v: ["fit-em", "fit.yaml", "--set", f"runs.seed={4 + v}", "--out",
                                                 t / "fit.h5", "--quiet"], _fit_prepare, file="fit.h5"),
}


def set_faults(command: str, work: Path, points: int, rng: np.random.Generator) -> list[Point]:
    """Kill points of a command whose outputs are one set (or one file): the target folder holds an
    earlier complete output; after each kill it holds exactly that or exactly a complete new one."""
    from needlecli.io.atomic import remove_stale

    spec = SET_COMMANDS[command]
    work.mkdir(parents=True, exist_ok=True)
    spec.prepare(work)
    target = work / "target"  # every run writes here: the paths its outputs hold are the same
    shutil.rmtree(target, ignore_errors=True)
    _timed(spec.args(target, 1), work)  # the earlier output (another seed or input)
    earlier = _snapshot(target)
    shutil.rmtree(target)
    length = _timed(spec.args(target, 0), work)
    reference = work / "reference"
    shutil.rmtree(reference, ignore_errors=True)
    target.rename(reference)
    out = []
    for i, sig, delay in _kill_points(points, rng, length, out):
        shutil.rmtree(target, ignore_errors=True)
        _restore(target, earlier)
        code, err = _kill_after(_needle(*spec.args(target, 0)), work, delay, sig, group=False)
        problems, early = _status_problems(sig, code, err)
        temps = _temporaries(target)
        if temps and sig != signal.SIGKILL:
            problems.append(f"temporary files left: {[t.name for t in temps]}")
        if temps:  # after SIGKILL: the next write into each folder removes them (their process is gone)
            for folder in {t.parent for t in temps}:
                remove_stale(folder, force=True)
            if _temporaries(target):
                problems.append("a killed run's temporary file was not removed")
        _prune_empty(target, earlier, reference)
        outcome, why = _outcome(target, earlier, reference)
        problems += why
        if outcome.startswith("a MIX"):
            problems.append(outcome)
        if early:
            outcome += " (stopped while Python started)"
        if temps:
            outcome += f", {len(temps)} temporary file(s) of the killed run removed"
        if code in (130, 143):
            last = [ln for ln in err.splitlines() if ln.strip()]
            line = last[-1] if last else ""
            if not line.startswith(f"error: interrupted by {signal.Signals(sig).name}"):
                problems.append(f"message {line!r}")
            elif outcome.startswith("earlier") and "written completely" in line:
                problems.append(f"the message says files were written: {line!r}")
            elif outcome.startswith("new") and "written completely before it" not in line:
                problems.append(f"the message does not say the outputs were written: {line!r}")
            if "Traceback" in err:
                problems.append("a traceback")
        out.append(Point(command, i, signal.Signals(sig).name, delay, code, outcome, problems))
    return out


def _restore(target: Path, snapshot: dict) -> None:
    target.mkdir(parents=True, exist_ok=True)
    for rel, data in snapshot.items():
        p = target / rel
        if data is None:
            p.mkdir(parents=True, exist_ok=True)
        else:
            p.parent.mkdir(parents=True, exist_ok=True)
            p.write_bytes(data)


def _prune_empty(target: Path, earlier: dict, reference: Path) -> None:
    """After SIGKILL the folders a killed run made for its temporary files may be left, empty: removed here
    as a user would (a folder of the earlier or the new output is kept)."""
    keep = set(earlier) | set(_snapshot(reference))
    for p in sorted(target.rglob("*"), key=lambda q: -len(q.parts)):
        if p.is_dir() and not any(p.iterdir()) and str(p.relative_to(target)) not in keep:
            p.rmdir()


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
    ap.add_argument("--commands", default=",".join(COMMANDS), help=f"some of {', '.join(COMMANDS)}")
    a = ap.parse_args(argv)
    a.work = a.work.resolve()
    commands = [c.strip() for c in a.commands.split(",") if c.strip()]
    unknown = [c for c in commands if c not in COMMANDS]
    if unknown:
        ap.error(f"unknown command {unknown[0]!r}; use some of {', '.join(COMMANDS)}")
    rng = np.random.default_rng(a.seed)
    points = []
    for c in commands:
        if c == "simulate":
            points += simulate_faults(a.work / "simulate", a.points, rng)
        elif c == "sweep":
            points += sweep_faults(a.work / "sweep", a.points, rng, a.executor)
        else:
            points += set_faults(c, a.work / c, a.points, rng)
        for p in points:
            if p.command == c:
                print(p.line(), flush=True)
    bad = [p for p in points if p.problems]
    print(f"{len(points) - len(bad)} of {len(points)} kill points held")
    for command in commands:
        mine = [p for p in points if p.command == command]
        print(f"{command}: {_live(mine)} of {len(mine)} kill points stopped a running process"
              f" (the others came after it had finished)")
    short = [c for c in commands if _live([p for p in points if p.command == c]) < a.points]
    if short:
        print(f"fewer than {a.points} kill points stopped a running {' and '.join(short)}")
    return 1 if bad or short else 0


if __name__ == "__main__":
    sys.exit(main())
