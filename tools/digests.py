"""Array digests of every bundled config, for refactors that must not change results.

    python tools/digests.py write digests.json     # before the change
    python tools/digests.py check digests.json     # after: every array and attribute the same

Each config under ``configs/`` is simulated with few runs (``--runs 2``) through the ``needle`` command,
and every dataset and attribute of its results file is hashed (its bytes, dtype and shape), except what
differs between any two runs (creation time, version, git hash). Configs that replay recorded data
need their logs (``make datasets`` ships the synthetic ones; the ultrasteer log comes from ``make real``);
a config whose logs are absent is listed as skipped. Sweep grids are not experiment configs and are
skipped.
"""

from __future__ import annotations

import hashlib
import json
import os
import subprocess
import sys
import tempfile
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import h5py
import numpy as np

ROOT = Path(__file__).resolve().parent.parent
VOLATILE = {"created", "version", "git_hash", "git_dirty", "needlecli_version"}
RUNS = 2


def _text(x) -> str:
    """A string value with the checkout's own path replaced (a config's from_fit notes name the fit file by
    its absolute path): two checkouts at different paths give the same digests."""
    return (x.decode() if isinstance(x, bytes) else str(x)).replace(str(ROOT), "<checkout>")


def _hash_value(v) -> str:
    a = np.asarray(v)
    if a.dtype.kind in "OSU":
        a = np.asarray([_text(x) for x in a.ravel()]).reshape(a.shape)
    h = hashlib.sha256(f"{a.dtype.str}{a.shape}".encode())
    h.update(np.ascontiguousarray(a).tobytes() if a.dtype.kind != "U" else "\x00".join(a.ravel()).encode())
    return h.hexdigest()[:16]


def file_digest(path: Path) -> dict[str, str]:
    out: dict[str, str] = {}

    def attrs(name, obj):
        for k, v in obj.attrs.items():
            if k not in VOLATILE:
                out[f"{name}@{k}"] = _hash_value(v)

    with h5py.File(path, "r") as f:
        attrs("/", f)

        def visit(name, obj):
            if isinstance(obj, h5py.Dataset):
                out[name] = _hash_value(obj[()])
            attrs(name, obj)

        f.visititems(visit)
    return out


def configs() -> list[Path]:
    return sorted(p for p in (ROOT / "configs").rglob("*.yaml") if "sweeps" not in p.parts)


def digest_config(cfg: Path, tmp: Path) -> tuple[str, dict | str]:
    out = tmp / (cfg.relative_to(ROOT / "configs").as_posix().replace("/", "__") + ".h5")
    cmd = ["needle", "simulate", str(cfg), "--runs", str(RUNS), "--out", str(out), "--quiet"]
    text = cfg.read_text()
    if "source:" in text:  # replays: their trial count comes from the logs
        cmd = ["needle", "simulate", str(cfg), "--out", str(out), "--quiet"]
    # on a cold kernel cache a command may take the numpy path while its kernels compile for the next run
    # (other bits, needlecli.kernels.dispatch): the digests are always those of the compiled path
    env = {**os.environ, "NEEDLECLI_COLD": "wait"}
    p = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, env=env)
    key = cfg.relative_to(ROOT).as_posix()
    if p.returncode != 0:
        return key, "skipped: " + _text((p.stderr.strip().splitlines() or [f"exit {p.returncode}"])[-1])
    return key, file_digest(out)


def collect() -> dict:
    with tempfile.TemporaryDirectory() as d, ThreadPoolExecutor(2) as pool:
        return dict(pool.map(lambda c: digest_config(c, Path(d)), configs()))


def _current(key: str) -> str:
    """A digest's key under a paper's current name: ``configs/seed003/table1.yaml`` and
    ``configs/replay/seed003_like.yaml`` (its former name, :mod:`needlecli.papers`) are
    ``configs/multirate-ukf-us3d/table1.yaml`` and ``configs/replay/multirate-ukf-us3d_like.yaml``, so that
    digests written before the renaming compare with the same configs (whose ``name`` and ``config``
    attributes, and a replay's log path, moved)."""
    sys.path.insert(0, str(ROOT))
    from needlecli.papers import PAPERS  # noqa: PLC0415

    parts = key.split("/")
    for p in PAPERS:
        parts = [p.slug + part.removeprefix(p.alias) if part.startswith(p.alias) else part for part in parts]
    return "/".join(parts)


def main(argv: list[str]) -> int:
    if len(argv) != 2 or argv[0] not in ("write", "check"):
        print(__doc__)
        return 2
    mode, path = argv[0], Path(argv[1])
    now = collect()
    if mode == "write":
        path.write_text(json.dumps(now, indent=1, sort_keys=True))
        ok = sum(isinstance(v, dict) for v in now.values())
        print(f"{ok} config(s) digested, {len(now) - ok} skipped -> {path}")
        for k, v in now.items():
            if not isinstance(v, dict):
                print(f"  {k}: {v}")
        return 0
    before = {_current(k): v for k, v in json.loads(path.read_text()).items()}
    bad = 0
    for key in sorted(set(before) | set(now)):
        a, b = before.get(key), now.get(key)
        if isinstance(a, dict) and isinstance(b, dict):
            diff = sorted(k for k in set(a) | set(b) if a.get(k) != b.get(k))
            if diff:
                bad += 1
                print(f"CHANGED {key}: {len(diff)} item(s): {', '.join(diff[:8])}")
        elif a != b:
            bad += 1
            print(f"CHANGED {key}: {str(a)[:60]} -> {str(b)[:60]}")
    print(f"{len(now)} config(s): {'all identical' if not bad else f'{bad} differ'}")
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
