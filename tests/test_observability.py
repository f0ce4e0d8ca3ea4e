"""What the tables do not say (issue 26, item 4): the tip position error per axis and across / along the
true needle axis, checked against a tangent computed here from the truth's angles; and the warning of
``needle validate`` and ``needle compare`` when the sensors cannot observe a state a table reports (a 2D
probe and z), from the linearised model along the nominal insertion."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import pytest
import yaml
from typer.testing import CliRunner

from needlecli.cli.app import app
from needlecli.experiments.config.load import load_config
from needlecli.experiments.simulation.observability import unobservable_states
from needlecli.experiments.simulation.runner import run_experiment
from needlecli.io.results import read_results
from needlecli.metrics import compute_errors
from needlecli.reports.tables import TABLES

ROOT = Path(__file__).resolve().parents[1]


def _config(axes: list[str]) -> dict:
    return {
        "format": 2,
        "name": "probe",
        "model": {"type": "modified_unicycle", "params": {"kappa": 0.01, "beta_cut": 0.035}},
        "inputs": {"v": 1.5, "u": 0.0},
        "sensors": [{"name": "probe", "type": "position", "rate": 10.0, "axes": axes, "sigma": 0.05},
                    {"name": "robot", "type": "encoder", "rate": 100.0, "channels": ["roll"], "sigma": 0.0035}],
        "observers": [{"name": "ukf", "type": "ukf",
                       "q": {"x": 0.01, "y": 0.01, "z": 0.01, "alpha": 1e-4, "beta": 1e-4, "gamma": 1e-3, "kappa": 1e-5},
                       "p0": {"x": 1.0, "y": 1.0, "z": 1.0, "alpha": 1e-3, "beta": 1e-3, "gamma": 1e-2, "kappa": 1e-6},
                       "init": {"from": "truth", "std": {"z": 0.8, "alpha": 0.02, "beta": 0.02}}}],
        "runs": {"count": 4, "seed": 11},
        "stop": {"depth": 12.0},
        "output": {"store_every": 10},
    }


@pytest.fixture(scope="module")
def probe2d(tmp_path_factory) -> Path:
    d = tmp_path_factory.mktemp("probe2d")
    cfg, text = load_config(text=yaml.safe_dump(_config(["x", "y"]), sort_keys=False))
    return run_experiment(cfg, text, out=d / "probe.h5").path


def test_position_errors_per_axis_and_across_and_along_the_needle(probe2d):
    res = read_results(probe2d)
    es = compute_errors(res)["ukf"]
    names = list(res.data["truth"].attrs["names"])
    truth = np.asarray(res.data["truth"].data["state"])
    est = np.asarray(res.data["estimates"].data["ukf"].data["state"])
    e = est[..., :3] - truth[..., :3]  # x, y, z first
    for i, a in enumerate("xyz"):
        np.testing.assert_allclose(es.quantities[f"E_{a}"].values, np.abs(e[..., i]), rtol=0, atol=1e-12)
    a, b = truth[..., names.index("alpha")], truth[..., names.index("beta")]
    t = np.stack([np.sin(b), -np.sin(a) * np.cos(b), np.cos(a) * np.cos(b)], -1)  # R = Rx(a) Ry(b) Rz(g): R e3
    along = np.sum(e * t, -1)
    across = np.linalg.norm(e - along[..., None] * t, axis=-1)
    np.testing.assert_allclose(es.quantities["E_ax"].values, np.abs(along), rtol=0, atol=1e-12)
    np.testing.assert_allclose(es.quantities["E_lat"].values, across, rtol=0, atol=1e-12)
    # with a 2D probe the z error stays the start's (no sensor sees z), the lateral one shrinks to the probe's
    z = es.quantities["E_z"].values
    np.testing.assert_allclose(z[:, -1], z[:, 0], atol=0.01)  # mm: the estimated pitch moves it a little
    assert z[:, 0].mean() > 0.3 and es.quantities["E_lat"].values[:, -1].mean() < 0.1
    table = TABLES.get("summary")(res, compute_errors(res))
    rows = [q.split(" ")[0] for q in table.loc[table["Observer"] == "ukf", "Quantity"]]
    assert rows[:6] == ["E_xyz", "E_x", "E_y", "E_z", "E_lat", "E_ax"], rows


def test_the_linearised_insertion_finds_what_the_sensors_cannot_see():
    # x alone (the high-gain observer paper's simulation) with the roll at 0: the needle bends in the y-z plane, which x does not see
    for axes, unseen in ((["x", "y"], ["z"]), (["x", "y", "z"], []), (["x"], ["y", "z", "alpha", "kappa"])):
        data = _config(axes)
        cfg, _ = load_config(text=yaml.safe_dump(data, sort_keys=False))
        found = unobservable_states(cfg)
        assert [u.state for u in found if not u.partners] == unseen, (axes, [u.message() for u in found])
    # constraints are not unknowns: a unit heading's norm, a rotation's orthogonality
    cfg, _ = load_config(ROOT / "configs" / "examples" / "mnm_s_turn.yaml", memory=False)
    assert [u.state for u in unobservable_states(cfg)] == ["pz"]  # a camera's x, y and the field coils
    cfg, _ = load_config(ROOT / "configs" / "so3-invariant" / "helix.yaml", memory=False)
    assert unobservable_states(cfg) == []


def test_validate_and_compare_warn_about_z_with_a_2d_probe(tmp_path, caplog):
    two = tmp_path / "probe2d.yaml"
    two.write_text(yaml.safe_dump(_config(["x", "y"]), sort_keys=False))
    three = tmp_path / "probe3d.yaml"
    three.write_text(yaml.safe_dump(_config(["x", "y", "z"]), sort_keys=False))
    from needlecli.experiments.studies.compare import compare_observers

    with caplog.at_level(logging.WARNING, logger="needlecli"):  # before a command resets the log's handlers
        compare_observers(two, observers=["ukf"], runs=2, out_dir=tmp_path / "cmp")
    assert any("[sensors] state z is not observed" in r.getMessage() for r in caplog.records)
    r = CliRunner().invoke(app, ["validate", str(two), str(three)])
    assert r.exit_code == 0, r.output
    warnings = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert len(warnings) == 1 and warnings[0].startswith(f"warning: {two}: [sensors] state z is not observed")
    assert "probe (x, y)" in warnings[0] and "E_xyz" in warnings[0]
    assert r.stdout.splitlines() == [f"ok: {two}", f"ok: {three}"]
    r = CliRunner().invoke(app, ["validate", str(two), "--quiet"])
    assert r.exit_code == 0 and not r.output.strip()
