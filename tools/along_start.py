"""``make real-start``: where the tip is along its path on resultsOrig, from the recording without the tracker
(docs/real-data.md, (a4)); needs ``make real`` first.

With the ultrasound read as a plane that sees the shaft and the inserted length (configs/real/
ukf_resultsorig_shaft.yaml, observer ``ukf_shaft_em``), the along-needle error is one constant: the
length's reference, the along position the tip had when counting began. The import takes it from the
first frame that saw the needle (its ultrasound point). This tool measures the other references the
recording offers without the tracker, each read from the ultrasound streams only (``plane``: the image
plane and the detector's verdict; ``inserted``: the length), and judges them against the tracker:

(1) the seen/lost verdicts against the tracker (a check, no filter): where the detector's boundary, the
    plane position at which the needle stops being seen, lies from the tracked tip at each change;
(2) the references, each a shift ``c`` of the length's reference along the insertion: the farthest plane
    position that saw the needle in the first sweep, the first sweep's seen/lost boundary, where its Doppler
    power falls to a fraction of its maximum so far (0.25, 0.5, 0.75), the verdicts'
    maximum-likelihood boundary (the filter's tip moved until the verdicts fit it best: probit, 1 mm;
    causal, from the verdicts up to each frame, and offline), the scan's mean (a probe centred on the tip);
    constant ones are run through the filter (the log's ``inserted`` reference moved by ``c``), the causal
    ones (a ``c`` per frame) applied to the filter's estimates as the along shift they make;
(3) EM's log-likelihood (configs/real/em_resultsorig_shaft.yaml) with the reference moved by ``c``: what EM
    estimating the start's along offset as a parameter would climb.

    python tools/along_start.py [--runs 4]      # tables in results/real/along_start
"""

from __future__ import annotations

import argparse
import csv
import subprocess
import sys
from pathlib import Path

import h5py
import numpy as np
import yaml
from scipy.stats import norm

ROOT = Path(__file__).resolve().parents[1]
REAL = ROOT / "results" / "real"
OUT = REAL / "along_start"
TRIAL = "resultsOrig"


def shifted_log(c: float, path: Path) -> Path:
    """resultsOrig alone, its ``inserted`` reference moved by ``c`` mm along the insertion direction."""
    from needlecli.io.logs import read_log, write_log

    log = read_log(REAL / "ultrasteer.h5")
    trials = log.trials if isinstance(log.trials, dict) else {t.id: t for t in log.trials}
    tr = trials[TRIAL]
    s = tr.sensors["inserted"]
    v = s.value.copy()
    v[:, 1:4] += c * v[:, 4:7]
    s.value = np.where(s.valid[:, None], v, 0.0)
    log.trials = {TRIAL: tr} if isinstance(log.trials, dict) else [tr]
    write_log(path, log)
    return path


def needle(*args: str) -> None:
    subprocess.run([sys.executable, "-m", "needlecli", *args], check=True, stdout=subprocess.DEVNULL)


def absolute(cfg: dict, src: Path) -> dict:
    for o in cfg.get("observers", []):
        if "from_fit" in o:
            o["from_fit"]["file"] = str((src.parent / o["from_fit"]["file"]).resolve())
    return cfg


def run_filter(c: float, runs: int, plane: bool = False) -> dict:
    """``ukf_shaft_em`` on resultsOrig with the reference moved by ``c`` (``plane``: with the image plane's
    one-sided bound too, channel ``plane``, sigma 1 mm): along (signed), across, E_xyz."""
    src = ROOT / "configs" / "real" / "ukf_resultsorig_shaft.yaml"
    cfg = absolute(yaml.safe_load(src.read_text()), src)
    obs = {o["name"]: o for o in cfg["observers"]}
    cfg["observers"] = [obs["ukf_gated"], obs["ukf_shaft_em"]]
    if plane:
        cfg["observers"][1]["measurements"]["plane"] = {"sigma": 1.0}
    cfg["source"] = {"logs": [str(shifted_log(c, OUT / f"log_{c:+.2f}.h5"))], "trials": [TRIAL] * runs}
    cfg["runs"] = {"seed": 8, "common_start": {"observer": "ukf_gated", "observers": ["ukf_shaft_em"]}}
    cfg["output"]["tables"] = ["real_error_along_across"]
    stem = OUT / f"filter_{c:+.2f}{'_plane' if plane else ''}"
    path = Path(f"{stem}.yaml")
    path.write_text(yaml.safe_dump(cfg, sort_keys=False))
    needle("simulate", str(path), "--out", f"{stem}.h5", "--quiet")
    needle("evaluate", f"{stem}.h5", "--out", str(stem),
           "--tables", "real_error_along_across", "--no-plots", "--quiet")
    table = next(stem.glob("*real_error_along_across.csv"))
    row = next(r for r in csv.DictReader(table.open()) if r["Source"] == "ukf_shaft_em")
    return {"along": float(row["Along mean (signed)"]), "across": float(row["Across mean"]),
            "E": float(row["E_xyz mean"])}


def em_loglik(c: float) -> float:
    src = ROOT / "configs" / "real" / "em_resultsorig_shaft.yaml"
    cfg = yaml.safe_load(src.read_text())
    cfg["source"]["logs"] = [str(shifted_log(c, OUT / f"log_{c:+.2f}.h5"))]
    path = OUT / f"em_{c:+.2f}.yaml"
    path.write_text(yaml.safe_dump(cfg, sort_keys=False))
    needle("fit-em", str(path), "--out", str(OUT / f"em_{c:+.2f}.h5"), "--quiet")
    with h5py.File(OUT / f"em_{c:+.2f}.h5") as f:
        ll = np.ravel(f["fit/unicycle/history/loglik"][:])
    return float(ll[np.isfinite(ll)][-1])


def ml_shift(g: np.ndarray, seen: np.ndarray, sigma: float = 1.0) -> float:
    """The shift ``c`` of the estimated tip that makes the verdicts likeliest: seen says ``g + c >= 0``, lost
    ``g + c < 0`` (``g (K,)`` the plane's offset from the estimated tip, ahead negative), probit ``sigma``."""
    cs = np.linspace(-15.0, 15.0, 3001)
    z = (g[None, :] + cs[:, None]) / sigma
    return float(cs[np.argmax(np.where(seen[None, :], norm.logcdf(z), norm.logcdf(-z)).sum(1))])


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=4, help="draws of the start per filter run (make real: 20)")
    args = ap.parse_args(argv)
    OUT.mkdir(parents=True, exist_ok=True)
    lines = []
    with h5py.File(REAL / "ukf_resultsorig_shaft.h5") as f:
        idx = f["measurements/plane/index"][:]
        pl = f["measurements/plane/value"][0]  # (K, 5): nx ny nz d seen, the same in every run
        t = f["time"][:][idx]
        est = f["estimates/ukf_shaft_em/state"][:, idx, :3]  # (N, K, 3): the filter's tip (no tracker)
        truth = f["truth/state"][:, idx]  # (N, K, 7): the tracker, for judging only
    n, d, seen = pl[:, :3], pl[:, 3], pl[:, 4] > 0.5
    a, b = truth[..., 3], truth[..., 4]
    tan = np.stack([np.sin(b), -np.sin(a) * np.cos(b), np.cos(a) * np.cos(b)], -1)
    al0 = np.sum((est - truth[..., :3]) * tan, -1)
    ac0 = np.linalg.norm(est - truth[..., :3] - al0[..., None] * tan, axis=-1)

    # (1) the detector's boundary against the tracked tip (a check against the tracker, never a filter)
    g_true = np.sum(n * truth[0, :, :3], -1) - d  # > 0: the tip past the plane
    ch = np.nonzero(seen[1:] != seen[:-1])[0]
    lines += ["(1) The detector's seen/lost boundary against the tracked tip: at each change of verdict the",
              "plane's offset from the tracker's tip before and after (negative: the plane ahead of it), mm", "",
              "| frame | t [s] | change | before | after | boundary (midpoint) |", "| --- | --- | --- | --- | --- | --- |"]
    for k in ch:
        lines.append(f"| {k + 1} | {t[k + 1]:.1f} | {'seen -> lost' if seen[k] else 'lost -> seen'} | "
                     f"{g_true[k]:+.2f} | {g_true[k + 1]:+.2f} | {(g_true[k] + g_true[k + 1]) / 2:+.2f} |")
    mid = (g_true[ch] + g_true[ch + 1]) / 2
    for lo, hi in ((0, 30), (30, 61)):
        m = (t[ch + 1] >= lo) & (t[ch + 1] < hi)
        lines.append(f"\n{lo}-{hi} s: boundary {mid[m].mean():+.2f} mm from the tracked tip (mean of {m.sum()}, "
                     f"range {mid[m].min():+.2f} to {mid[m].max():+.2f})")

    # (2) references from the ultrasound alone: shifts c of the length's reference along the insertion
    g_est = (np.sum(n * est, -1) - d).mean(0)  # the plane's offset from the filter's tip, mean over the draws
    first_lost = int(np.nonzero(~seen)[0][0])
    causal_ml = np.array([ml_shift(g_est[: k + 1], seen[: k + 1]) for k in range(len(t))])
    causal_scan = -np.cumsum(g_est) / np.arange(1, len(t) + 1)
    constant = {
        "first frame that saw the needle (the import's reference)": 0.0,
        f"farthest plane that saw the needle in the first sweep (known at {t[first_lost]:.1f} s)":
            float(-g_est[:first_lost].min()),
        f"the first sweep's seen/lost boundary (known at {t[first_lost]:.1f} s)":
            float(-(g_est[first_lost - 1] + g_est[first_lost]) / 2),
        "the verdicts' boundary, maximum likelihood over the whole trial (offline)": ml_shift(g_est, seen),
        "the scan's mean over the whole trial, a probe centred on the tip (offline)": float(causal_scan[-1]),
    }
    rows = []
    for label, c in constant.items():
        r = run_filter(round(c, 2), args.runs)
        rows.append((label, "filter run", c, r["along"], r["across"], r["E"]))
    r = run_filter(0.0, args.runs, plane=True)
    rows.append(("the first frame that saw the needle, the image plane's bound added (channel plane, sigma 1 mm)",
                 "filter run", 0.0, r["along"], r["across"], r["E"]))
    from needlecli.io import ultrasteer as us_io

    raw = next(r for r in us_io.find_trials(us_io.default_data_dir()) if r.id == TRIAL)
    power = raw.doppler[np.nonzero(raw.ok)[0][0]:][: len(t)]  # the kept frames, as the log's
    for frac in (0.25, 0.5, 0.75):
        k, w = us_io.doppler_edge(power, frac)
        c = np.where(np.arange(len(t)) >= k, -((1.0 - w) * g_est[k - 1] + w * g_est[k]), 0.0)
        al = al0 + c[None, :]
        rows.append((f"the first sweep's Doppler power at {frac:g} of its maximum so far (known at {t[k]:.2f} s"
                     + ("; channel inserted_edge" if frac == 0.5 else "") + ")", "shift of the estimates", float(c[-1]), float(al.mean()),
                     float(ac0.mean()), float(np.hypot(al, ac0).mean())))
    for label, c in (("the verdicts' boundary, maximum likelihood from the verdicts up to each frame (causal)",
                      causal_ml), ("the scan's mean up to each frame, a probe centred on the tip (causal)",
                                   causal_scan)):
        al = al0 + c[None, :]
        rows.append((label, "shift of the estimates", float(c[-1]), float(al.mean()), float(ac0.mean()),
                     float(np.hypot(al, ac0).mean())))
    lines += ["", "(2) The length's reference from the ultrasound alone, ukf_shaft_em against the tracker, mm "
              f"({args.runs} draws of the start; a causal reference's c at the trial's end)", "",
              "| reference | how measured | c [mm] | along (signed) | across | E_xyz |", "| --- | --- | --- | --- | --- | --- |"]
    lines += [f"| {r[0]} | {r[1]} | {r[2]:+.2f} | {r[3]:+.2f} | {r[4]:.2f} | {r[5]:.2f} |" for r in rows]

    # (3) EM's log-likelihood against the reference's shift
    lines += ["", "(3) EM's log-likelihood (configs/real/em_resultsorig_shaft.yaml) with the reference moved by c", "",
              "| c [mm] | log-likelihood |", "| --- | --- |"]
    for c in (-2.0, 0.0, 2.0, 4.0):
        lines.append(f"| {c:+.1f} | {em_loglik(c):.3f} |")
    text = "\n".join(lines) + "\n"
    (OUT / "along_start.md").write_text(text)
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
