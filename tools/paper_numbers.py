"""Every number a paper states, beside needlecli's over several seeds: run a paper's studies once per seed,
collect the numbers into its values file, and write the table into its page (``make papers``,
``make highgain-us2d-numbers``, ...).

    python tools/paper_numbers.py highgain-us2d             # run, collect, write the page
    python tools/paper_numbers.py highgain-us2d --reuse     # keep results files already there (same seed, config)
    python tools/paper_numbers.py highgain-us2d --render    # only write the page from the committed values file

A paper is named by its slug or its former name (``seed000``: :mod:`needlecli.papers`).

The numbers are data (``docs/papers/numbers/PAPER.yaml``, :mod:`needlecli.reports.papers`); the results
files go to ``results/papers/PAPER/`` (not committed); the values file
(``docs/papers/numbers/PAPER_values.yaml``) is, so that the page can be checked against it without a run.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import time
from pathlib import Path

import yaml

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from needlecli.papers import PAPERS, paper  # noqa: E402
from needlecli.reports import papers  # noqa: E402


def paths(paper: str) -> tuple[Path, Path]:
    d = ROOT / "docs" / "papers" / "numbers"
    return d / f"{paper}.yaml", d / f"{paper}_values.yaml"


def run_studies(numbers: dict, out_dir: Path, reuse: bool) -> tuple[dict, dict]:
    """Each run of the numbers file once per seed (``needle simulate`` or ``needle fit-em``); the files
    ``{run: {seed: path}}`` and the seconds each run took."""
    out_dir.mkdir(parents=True, exist_ok=True)
    files: dict[str, dict[int, Path]] = {}
    seconds: dict[str, list[float]] = {}
    for name, run in numbers["runs"].items():
        for seed in numbers["seeds"]:
            path = out_dir / f"{name}_s{seed}.h5"
            files.setdefault(name, {})[seed] = path
            if reuse and path.exists():
                continue
            cmd = ["needle", run.get("command", "simulate"), str(ROOT / run["config"]), "--set", f"runs.seed={seed}",
                   *[str(a) for a in run.get("args", [])], "--out", str(path), "--quiet"]
            print(" ".join(cmd), flush=True)
            t0 = time.perf_counter()
            subprocess.run(cmd, check=True, cwd=ROOT, stdout=subprocess.DEVNULL)
            seconds.setdefault(name, []).append(round(time.perf_counter() - t0, 1))
    return files, seconds


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("paper", help=", ".join(p.slug for p in PAPERS) + " (or a former name: "
                    + ", ".join(p.alias for p in PAPERS) + ")")
    ap.add_argument("--reuse", action="store_true", help="keep results files that exist")
    ap.add_argument("--render", action="store_true", help="only write the page from the committed values file")
    ap.add_argument("--out", default=None, help="folder of the results files (default results/papers/PAPER)")
    a = ap.parse_args(argv)
    try:
        a.paper = paper(a.paper).slug
    except KeyError as e:
        ap.error(str(e.args[0]))
    num_path, val_path = paths(a.paper)
    numbers = papers.load_numbers(num_path)
    if not a.render:
        files, seconds = run_studies(numbers, Path(a.out) if a.out else ROOT / "results" / "papers" / a.paper, a.reuse)
        values = papers.collect(numbers, files)
        from needlecli.provenance import git_hash  # noqa: PLC0415

        values["made_with"] = {"git": git_hash() or "unknown", "seconds": seconds}
        val_path.write_text(f"# made by `make {numbers['target']}` (tools/paper_numbers.py) from "
                            f"{num_path.relative_to(ROOT)}: do not edit\n"
                            + yaml.safe_dump(values, sort_keys=False, width=120), encoding="utf-8")
    values = yaml.safe_load(val_path.read_text(encoding="utf-8"))
    page = ROOT / numbers["page"]
    text = papers.write_blocks(page.read_text(encoding="utf-8"), numbers, values,
                               str(num_path.relative_to(ROOT)), str(val_path.relative_to(ROOT)))
    page.write_text(text, encoding="utf-8")
    print(f"{page.relative_to(ROOT)}: {len(numbers['numbers'])} numbers", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
