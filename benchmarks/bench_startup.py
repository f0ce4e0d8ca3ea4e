"""Start-up of the ``needle`` command, as a user meets it: whole processes, each the best of several runs,
as a ratio against ``python -c "import typer"`` measured in the same run (issue 13's target: at most 4x
for ``needle --help``, ``needle --version`` and ``needle list``).

    python benchmarks/bench_startup.py [--repeats 7]
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import time

TARGET = 4.0


def best_of(cmd: list[str], repeats: int) -> float:
    best = float("inf")
    for _ in range(repeats):
        t0 = time.perf_counter()
        subprocess.run(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, check=True)
        best = min(best, time.perf_counter() - t0)
    return best


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=7)
    args = ap.parse_args()
    needle = shutil.which("needle")
    base = [needle] if needle else [sys.executable, "-m", "needlecli"]
    print(f"load average {os.getloadavg()[0]:.2f} on {os.cpu_count()} CPUs; best of {args.repeats} whole processes")
    ref = best_of([sys.executable, "-c", "import typer"], args.repeats)
    label = 'python -c "import typer"'
    print(f"{label:<28} {ref * 1e3:7.0f} ms   (reference)")
    worst = 0.0
    for cmd in (["--help"], ["--version"], ["list"]):
        t = best_of(base + cmd, args.repeats)
        worst = max(worst, t / ref)
        print(f"{'needle ' + ' '.join(cmd):<28} {t * 1e3:7.0f} ms   {t / ref:4.2f}x the reference (target <= {TARGET:g}x)")
    print(f"start-up: {'met' if worst <= TARGET else 'NOT met'} (worst {worst:.2f}x)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
