"""How far the compiled kernels' results are from the numpy path's, for every bundled config.

    python tools/kernel_agreement.py [--tol 1e-10] [--runs 2] [CONFIG ...]

Each config (default: all under ``configs/``, as ``tools/digests.py`` picks them) is simulated twice through
the ``needle`` command, with ``NEEDLECLI_KERNELS=numpy`` and with the kernels, and every numeric dataset
of the two results files is compared: the largest absolute difference and the largest one relative to the
dataset's largest magnitude. Non-numeric datasets and attributes must be equal. The table lists every
config with its worst dataset; datasets beyond ``--tol`` (relative) are listed after it. Exit 1 if any
non-numeric content differs (a status, a reason, a count). Counts (integer arrays) must be equal.

The UKF carries rounding amplified by its sigma-point weights (7e4 at alpha = 1e-3) along a run: whole
insertions agree to the numpy path's own reproducibility (``tests/test_kernels.py``), about 1e-8 mm,
not to 1e-10; this tool shows where each config stands.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import h5py
import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "tools"))
from digests import VOLATILE, configs  # noqa: E402


def simulate(cfg: Path, out: Path, mode: str, runs: int) -> str | None:
    cmd = ["needle", "simulate", str(cfg), "--out", str(out), "--quiet"]
    if "source:" not in cfg.read_text():
        cmd[3:3] = ["--runs", str(runs)]
    p = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, env={**os.environ, "NEEDLECLI_KERNELS": mode})
    return None if p.returncode == 0 else (p.stderr.strip().splitlines() or [f"exit {p.returncode}"])[-1]


def compare(a: Path, b: Path) -> tuple[list[tuple[str, float, float]], list[str]]:
    """``([(dataset, max abs diff, max rel diff)], [what differs that must be equal])``."""
    rows, bad = [], []
    with h5py.File(a) as fa, h5py.File(b) as fb:
        names: list[str] = []
        fa.visititems(lambda n, o: names.append(n) if isinstance(o, h5py.Dataset) else None)
        for n in names:
            if n not in fb:
                bad.append(f"{n}: missing")
                continue
            x, y = fa[n][()], fb[n][()]
            if x.shape != y.shape:
                bad.append(f"{n}: shape {x.shape} != {y.shape}")
            elif x.dtype.kind == "f":
                if not np.array_equal(np.isnan(x), np.isnan(y)):
                    bad.append(f"{n}: NaN in different places")
                    continue
                d = np.abs(np.where(np.isnan(x), 0.0, x - y))
                scale = np.nanmax(np.abs(x), initial=0.0)
                rows.append((n, float(d.max(initial=0.0)), float(d.max(initial=0.0) / scale) if scale else 0.0))
            elif not np.array_equal(x, y):
                bad.append(f"{n}: differs ({x.dtype})")
        for n in ["/", *names]:
            for k, v in fa[n].attrs.items():
                if k in VOLATILE or k not in fb[n].attrs:
                    continue
                if not np.array_equal(np.asarray(v), np.asarray(fb[n].attrs[k])):
                    bad.append(f"{n}@{k}: differs")
    return rows, bad


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("configs", nargs="*", type=Path)
    ap.add_argument("--tol", type=float, default=1e-10, help="relative tolerance to list datasets beyond")
    ap.add_argument("--runs", type=int, default=2)
    a = ap.parse_args()
    cfgs = [c.resolve() for c in a.configs] or configs()
    failed = False
    with tempfile.TemporaryDirectory() as d, ThreadPoolExecutor(2) as pool:
        d = Path(d)

        def one(cfg: Path):
            key = cfg.relative_to(ROOT).as_posix()
            outs = [d / (key.replace("/", "__") + f".{m}.h5") for m in ("numpy", "auto")]
            errs = [simulate(cfg, o, m, a.runs) for o, m in zip(outs, ("numpy", "auto"))]
            if any(errs):
                return key, None, [e for e in errs if e]
            return key, *compare(*outs)

        print(f"{'config':52s} {'worst dataset':38s} {'max abs':>9s} {'max rel':>9s}")
        for key, rows, bad in pool.map(one, cfgs):
            if rows is None:
                print(f"{key:52s} skipped: {bad[0]}")
                continue
            worst = max(rows, key=lambda r: r[2], default=("-", 0.0, 0.0))
            print(f"{key:52s} {worst[0][:38]:38s} {worst[1]:9.1e} {worst[2]:9.1e}")
            for n, da, dr in sorted(rows, key=lambda r: -r[2]):
                if dr > a.tol:
                    print(f"    {n:86s} {da:9.1e} {dr:9.1e}")
            for b in bad:
                print(f"    MUST BE EQUAL: {b}")
            failed |= bool(bad)
    sys.exit(1 if failed else 0)


if __name__ == "__main__":
    main()
