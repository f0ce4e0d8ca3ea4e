"""What a user reads (issue 26, item 7): numbers in every CSV to 12 significant digits (60, not
60.00000000000378: formatted at the one writer), and ``needle sweep`` printing no more of its table than
the terminal holds (the full table is in the files)."""

from __future__ import annotations

import numpy as np
import pandas as pd
from typer.testing import CliRunner

from needlecli.cli.app import app
from needlecli.reports.tables import to_terminal, write_table


def test_csv_numbers_are_rounded_at_the_writer(tmp_path):
    df = pd.DataFrame({"Observer": ["ukf", "ekf"], "insertion [mm]": [60.00000000000378, 59.99999999999997],
                       "mixed": [0.1 + 0.2, "n/a"], "runs": [20, 20], "mean": [1.23456789012345e-7, np.nan]})
    (path,) = write_table(df, tmp_path / "t", ["csv"])
    lines = path.read_text().splitlines()
    assert lines == ["Observer,insertion [mm],mixed,runs,mean", "ukf,60,0.3,20,1.23456789012e-07", "ekf,60,n/a,20,"]
    back = pd.read_csv(path)
    np.testing.assert_allclose(back["insertion [mm]"], df["insertion [mm]"], rtol=1e-12)


def test_the_terminal_form_fits_the_width():
    df = pd.DataFrame({f"col{i}": [1.5 * i, 2.25 * i] for i in range(30)})
    text = to_terminal(df, 80, more="in t.csv")
    *table, last = text.splitlines()
    assert all(len(line) <= 80 for line in table) and len(table) == 4
    assert last.endswith("more column(s) in t.csv)")
    assert to_terminal(df.iloc[:, :2], 80) == to_terminal(df.iloc[:, :2], 10)  # the first two always


TINY = """\
format: 2
name: tiny_terminal
model: {type: modified_unicycle, params: {kappa: 0.005, beta_cut: 0.035}}
inputs: {v: 1.5, u: 0.0}
sensors:
  - {name: us3d, type: position, rate: 2.0, sigma: 0.3}
observers:
  - {name: ol, type: open_loop, init: {from: truth, std: {alpha: 0.05}}}
runs: {count: 2, seed: 5}
stop: {depth: 2.0}
simulation: {dt: 0.02}
output: {covariance: none}
"""


def test_sweep_prints_a_table_as_wide_as_the_terminal(tmp_path):
    config, grid = tmp_path / "tiny.yaml", tmp_path / "grid.yaml"
    config.write_text(TINY)
    grid.write_text("grid: {sensors.0.sigma: [0.1, 0.3], runs.seed: range(2)}\n")
    r = CliRunner().invoke(app, ["sweep", str(config), "--grid", str(grid), "--out", str(tmp_path / "o"),
                                 "--executor", "inline"], env={"COLUMNS": "120"})
    assert r.exit_code == 0, r.output
    table = [ln for ln in r.stdout.splitlines() if ln.startswith("|")]
    assert len(table) == 6 and all(len(ln) <= 120 for ln in table), table
    head = [c.strip() for c in table[0].strip("|").split("|")]
    assert head[:5] == ["cell", "sensors.0.sigma", "runs.seed", "status", "observer"] and "E_xyz_mean" in head
    assert any("more column(s) in" in ln and "sweep.csv" in ln for ln in r.stdout.splitlines())
    full = pd.read_csv(tmp_path / "o" / "sweep.csv")
    assert len(full.columns) > len(head) and "E_xyz_max" in full.columns
