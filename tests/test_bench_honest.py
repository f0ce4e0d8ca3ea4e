"""The FilterPy comparison of the benchmarks is honest (issue 15, item 7): FilterPy's fx is the model written
as FilterPy users write it, scalar ``math`` on one state, never needlecli's batched model code, and its
estimate agrees with needlecli's UKF on the same insertion and data."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

pytest.importorskip("filterpy", reason="FilterPy is optional (pip install -e '.[bench]')")

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))

import bench_ukf  # noqa: E402

from needlecli.experiments.config.load import load_config  # noqa: E402
from needlecli.models.base import Model  # noqa: E402


def test_filterpy_runs_without_needlecli_model_code_and_agrees(monkeypatch):
    cfg, text = load_config(ROOT / "configs" / "multirate-ukf-us3d" / "table1.yaml", runs=2, overrides=["stop.depth=6"])
    _, res = bench_ukf.time_study(cfg, text, 1)
    _, obs_name, post = bench_ukf.time_ukf(cfg, res, 1)

    def forbidden(*a, **k):
        raise AssertionError("FilterPy's fx called needlecli's model code")

    for name in ("step", "f", "f_components"):
        monkeypatch.setattr(type(res.truth.model), name, forbidden, raising=False)
        monkeypatch.setattr(Model, name, forbidden, raising=False)
    steps = len(res.truth.time) - 1
    _, est, _ = bench_ukf.filterpy_run(cfg, res, obs_name, 0, steps)
    diff, _ = bench_ukf.agreement(est, post.state[0, : steps + 1])
    assert diff < 1e-6  # mm
