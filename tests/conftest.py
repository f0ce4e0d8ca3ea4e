"""Shared fixtures: what several test modules fit or simulate once per session."""

from __future__ import annotations

import os
from pathlib import Path

import pytest
from typer.testing import CliRunner

from needlecli.cli.app import app

# The suite's numbers never depend on the state of the kernel cache: on a cold one, commands compile first
# (as `kernels: numba` would) instead of taking the numpy path while the kernels compile in the background
# (tests/test_cold_cache.py tests that, explicitly). Inherited by the commands the tests start.
os.environ.setdefault("NEEDLECLI_COLD", "wait")


@pytest.fixture(scope="session")
def seed004_fit(tmp_path_factory):
    """The magnetic needle EM paper's study, reduced to 6 trials (both models), fitted by needle fit-em."""
    d = tmp_path_factory.mktemp("ident")
    cfg = Path(__file__).resolve().parents[1] / "configs" / "em-magnetic-pratt2022" / "study.yaml"
    r = CliRunner().invoke(app, ["fit-em", str(cfg), "--model", "both", "--set", "runs.count=6",
                                 "--out", str(d / "fit.h5"), "--quiet"])
    assert r.exit_code == 0, r.output
    return d / "fit.h5"
