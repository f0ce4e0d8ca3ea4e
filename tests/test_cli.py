"""End to end through the ``needle`` command: simulate -> results file -> evaluate, on a tiny experiment;
and the sensor clocks and noise of the statistical sensors."""

from __future__ import annotations

import datetime as dt
import math
import shutil
from pathlib import Path

import h5py
import numpy as np
import pytest
import yaml
from typer.testing import CliRunner

import needlecli
from needlecli.cli.app import app
from needlecli.experiments.config.load import load_config
from needlecli.experiments.simulation.runner import run_experiment
from needlecli.models import MODELS

TINY = """\
name: tiny
model: {type: modified_unicycle, params: {kappa: 0.004, beta_cut: 0.05}}
inputs: {v: 1.0, u: {kind: flips, at_depths: [2.5]}}
sensors:
  - {type: position, rate: 2, sigma: 0.3, latency: 0.05, growth: {transducer: [0, 0, 90], a: 1, d_max: 80}}
  - {type: encoder, rate: 20, channels: [roll, depth], sigma: [0.0035, 0.01]}
  - {type: elastography, rate: 1}
observers:
  - {type: open_loop, init: {std: {alpha: 0.05, beta: 0.05}}, q: {kappa: 1.0e-6}}
runs: {count: 3, seed: 7}
stop: {depth: 5}
simulation: {dt: 0.01}
"""
N, T = 3, 501  # 5 mm at 1 mm/s in steps of 0.01 s
STATES = MODELS.get("modified_unicycle").state_names
SENSOR_SHAPES = {"position": (11, 3), "encoder": (101, 2), "elastography": (6, 1)}  # (M, m)


def invoke(*args):
    return CliRunner().invoke(app, [str(a) for a in args])


def strings(v) -> list[str]:
    return [x.decode() if isinstance(x, bytes) else str(x) for x in np.atleast_1d(v)]


def attr(f: h5py.File, path: str, key: str):
    """An attribute documented for a dataset: on the dataset itself or, as written, on its group."""
    obj = f[path]
    return obj.attrs[key] if key in obj.attrs else obj.parent.attrs[key]


def datasets(path: Path) -> dict[str, np.ndarray]:
    out = {}
    with h5py.File(path, "r") as f:
        f.visititems(lambda name, obj: out.__setitem__(name, obj[()]) if isinstance(obj, h5py.Dataset) else None)
    return out


def simulate(cfg: Path, out: Path, *extra) -> Path:
    result = invoke("simulate", cfg, "--out", out, "--quiet", *extra)
    assert result.exit_code == 0, result.output + repr(result.exception)
    assert out.exists()
    return out


@pytest.fixture(scope="module")
def work(tmp_path_factory) -> Path:
    d = tmp_path_factory.mktemp("cli")
    (d / "tiny.yaml").write_text(TINY)
    return d


@pytest.fixture(scope="module")
def run(work: Path):
    """One simulation of the tiny experiment through the CLI: (result, results path)."""
    out = work / "res" / "tiny.h5"
    result = invoke("simulate", work / "tiny.yaml", "--out", out, "--quiet")
    assert result.exit_code == 0, result.output + repr(result.exception)
    return result, out


# ---------------------------------------------------------------------------------------------- simulate
def test_simulate_prints_summary_and_path(run):
    result, out = run
    assert "Traceback" not in result.output and "error:" not in result.output
    lines = result.stdout.splitlines()
    assert any(line.startswith("| Observer") for line in lines), result.stdout
    assert any("open_loop" in line and "E_xyz" in line for line in lines)
    assert lines[-1] == f"results: {out}"
    assert not [p for p in out.parent.iterdir() if p.name != out.name]  # no temporary file left


def test_results_root_attrs(run):
    _, out = run
    with h5py.File(out, "r") as f:
        a = f.attrs
        assert a["config"] == TINY
        assert int(a["seed"]) == 7
        assert a["needlecli_version"] == needlecli.__version__
        assert isinstance(a["git_hash"], str) and a["git_hash"]
        created = dt.datetime.fromisoformat(a["created"])
        assert abs((dt.datetime.now(dt.timezone.utc) - created).total_seconds()) < 3600


def test_results_layout(run):
    _, out = run
    with h5py.File(out, "r") as f:
        time = f["time"][()]
        assert time.shape == (T,)
        assert time[0] == 0 and np.allclose(np.diff(time), 0.01)
        assert f["depth"].shape == (T,) and f["depth"][-1] >= 5 - 1e-9

        truth = f["truth/state"]
        assert truth.shape == (N, T, len(STATES))
        assert strings(attr(f, "truth/state", "names")) == list(STATES)
        assert strings(attr(f, "truth/state", "units")) == ["mm", "mm", "mm", "rad", "rad", "rad", "1/mm"]
        assert strings(f["truth/status"].asstr()[()]) == ["ok"] * N

        assert f["inputs/v"].shape == (N, T) and f["inputs/u"].shape == (N, T)
        assert np.all(f["inputs/v"][()] == 1.0)
        assert f["inputs/u"][()].max() == pytest.approx(np.pi)  # one flip at pi rad/s

        for name, (M, m) in SENSOR_SHAPES.items():
            g = f[f"measurements/{name}"]
            assert g["t"].shape == (M,), name
            assert g["value"].shape == (N, M, m), name
            assert g["valid"].shape == (N, M) and g["valid"].dtype == bool, name
            assert len(strings(attr(f, g.name + "/value", "names"))) == m, name
            assert len(strings(attr(f, g.name + "/value", "units"))) == m, name
            assert g["valid"][()].all()
            assert np.isfinite(g["value"][()]).all()
        assert strings(attr(f, "measurements/position/value", "names")) == ["x", "y", "z"]
        assert strings(attr(f, "measurements/position/value", "units")) == ["mm"] * 3
        assert strings(attr(f, "measurements/encoder/value", "names")) == ["roll", "depth"]
        assert strings(attr(f, "measurements/encoder/value", "units")) == ["rad", "mm"]
        assert np.allclose(f["measurements/encoder/t"][()], np.arange(101) * 0.05)

        est = f["estimates/open_loop"]
        assert est["state"].shape == (N, T, len(STATES))
        assert est["cov"].shape == (N, T, len(STATES), len(STATES))
        assert strings(attr(f, est.name + "/state", "names")) == list(STATES)
        assert attr(f, est.name + "/cov", "layout") == "full" and int(attr(f, est.name + "/cov", "stride")) == 1
        assert strings(est["status"].asstr()[()]) == ["ok"] * N
        cov = est["cov"][()]
        assert np.allclose(cov, np.swapaxes(cov, -1, -2))
        assert np.all(np.diagonal(cov, axis1=-2, axis2=-1) >= 0)


def test_latency_in_results(run):
    _, out = run
    with h5py.File(out, "r") as f:
        t, ta = f["measurements/position/t"][()], f["measurements/position/t_available"][()]
        assert np.allclose(t, np.arange(11) * 0.5)
        assert np.allclose(ta - t, 0.05)
        assert np.allclose(f["measurements/encoder/t_available"][()], f["measurements/encoder/t"][()])


def test_same_seed_same_results(run, work: Path):
    _, out = run
    again = simulate(work / "tiny.yaml", work / "again" / "tiny.h5")
    a, b = datasets(out), datasets(again)
    assert a.keys() == b.keys()
    for k in a:
        assert np.array_equal(a[k], b[k], equal_nan=a[k].dtype.kind == "f"), k


def test_seed_and_runs_override(run, work: Path):
    _, out = run
    other = simulate(work / "tiny.yaml", work / "other" / "tiny.h5", "--seed", "8", "--runs", "2")
    a, b = datasets(out), datasets(other)
    assert b["truth/state"].shape == (2, T, len(STATES))
    for name, (M, m) in SENSOR_SHAPES.items():
        assert b[f"measurements/{name}/value"].shape == (2, M, m)
    # another seed: other noise (the truth starts identical: no initial spread is configured)
    assert not np.allclose(a["measurements/position/value"][:2], b["measurements/position/value"])
    assert not np.allclose(a["measurements/encoder/value"][:2], b["measurements/encoder/value"])
    assert np.array_equal(a["time"], b["time"])
    with h5py.File(other, "r") as f:
        assert int(f.attrs["seed"]) == 8
        stored = yaml.safe_load(f.attrs["config"])
    assert stored["runs"] == {"count": 2, "seed": 8}  # the stored config is the one that ran


def test_covariance_diag_and_stride(run, work: Path):
    _, full = run
    out = simulate(work / "tiny.yaml", work / "diag" / "tiny.h5",
                   "--set", "output.covariance=diag", "--set", "output.store_every=5")
    with h5py.File(out, "r") as f, h5py.File(full, "r") as g:
        est = f["estimates/open_loop"]
        n = len(STATES)
        assert est["cov"].shape == (N, math.ceil(T / 5), n)
        assert attr(f, est.name + "/cov", "layout") == "diag" and int(attr(f, est.name + "/cov", "stride")) == 5
        assert np.array_equal(est["cov_index"][()], np.arange(0, T, 5))
        # the same numbers as the full covariances at those steps
        ref = np.diagonal(g["estimates/open_loop/cov"][()], axis1=-2, axis2=-1)[:, ::5]
        assert np.allclose(est["cov"][()], ref)
        assert np.array_equal(est["state"][()], g["estimates/open_loop/state"][()])


def test_covariance_none(work: Path):
    out = simulate(work / "tiny.yaml", work / "nocov" / "tiny.h5", "--set", "output.covariance=none", "--runs", "1")
    with h5py.File(out, "r") as f:
        assert "cov" not in f["estimates/open_loop"]
        assert f["estimates/open_loop/state"].shape == (1, T, len(STATES))


# ---------------------------------------------------------------------------------------------- evaluate
def test_evaluate_writes_tables_and_plots(run, work: Path):
    _, out = run
    dest = work / "eval"
    result = invoke("evaluate", out, "--out", dest)
    assert result.exit_code == 0, result.output + repr(result.exception)
    assert "## summary" in result.stdout and f"tables: {dest}" in result.stdout
    files = {p.name for p in dest.iterdir()}
    for table in ("summary", "accuracy", "status"):
        for ext in ("md", "csv", "tex"):
            assert f"tiny_{table}.{ext}" in files, files
    pngs = sorted(dest.glob("*.png"))
    assert pngs and all(p.stat().st_size > 1000 and p.read_bytes()[:4] == b"\x89PNG" for p in pngs)
    assert "open_loop" in (dest / "tiny_summary.csv").read_text()
    assert "\\begin{tabular}" in (dest / "tiny_summary.tex").read_text() or "tabular" in (
        dest / "tiny_summary.tex").read_text()


def test_evaluate_format_subset(run, work: Path):
    _, out = run
    dest = work / "eval_csv"
    result = invoke("evaluate", out, "--out", dest, "--format", "csv", "--tables", "summary", "--no-plots", "-q")
    assert result.exit_code == 0, result.output
    assert sorted(p.name for p in dest.iterdir()) == ["tiny_summary.csv"]


def one_error(result, *must) -> str:
    assert result.exit_code == 2, result.output
    assert "Traceback" not in result.output
    lines = [line for line in result.output.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("error: "), result.output
    for s in must:
        assert s in lines[0], lines[0]
    return lines[0]


def test_evaluate_missing_file(tmp_path: Path):
    one_error(invoke("evaluate", tmp_path / "nothing.h5", "--out", tmp_path / "ev"), "nothing.h5", "no such")
    assert not (tmp_path / "ev").exists()


def test_evaluate_garbage_file(tmp_path: Path):
    bad = tmp_path / "garbage.h5"
    bad.write_bytes(np.random.default_rng(0).bytes(4096))
    one_error(invoke("evaluate", bad, "--out", tmp_path / "ev"), "garbage.h5")


def test_evaluate_truncated_file(run, tmp_path: Path):
    _, out = run
    bad = tmp_path / "truncated.h5"
    bad.write_bytes(out.read_bytes()[: out.stat().st_size // 2])
    one_error(invoke("evaluate", bad, "--out", tmp_path / "ev"), "truncated.h5")


def test_evaluate_foreign_hdf5(tmp_path: Path):
    bad = tmp_path / "foreign.h5"
    with h5py.File(bad, "w") as f:
        f["x"] = np.arange(3)
    one_error(invoke("evaluate", bad), "foreign.h5", "not a needlecli results file")


def test_evaluate_incomplete_results(run, tmp_path: Path):
    _, out = run
    bad = tmp_path / "incomplete.h5"
    shutil.copy(out, bad)
    with h5py.File(bad, "a") as f:
        del f["truth"].attrs["names"]
    one_error(invoke("evaluate", bad, "--out", tmp_path / "ev"), "incomplete.h5")


# ---------------------------------------------------------------------------------------------- failures, dry run
def test_simulate_bad_config_writes_nothing(tmp_path: Path):
    cfg = tmp_path / "bad.yaml"
    cfg.write_text(TINY.replace("rate: 20", "rate: -20"))
    folder = tmp_path / "out"
    folder.mkdir()
    one_error(invoke("simulate", cfg, "--out", folder / "r.h5", "--quiet"), "bad.yaml", "[sensors -> 1 -> rate]")
    assert list(folder.iterdir()) == []


def test_simulate_missing_config(tmp_path: Path):
    one_error(invoke("simulate", tmp_path / "none.yaml", "--out", tmp_path / "r.h5"), "none.yaml", "no such file")
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("exc, code", [(RuntimeError("disk on fire"), 1), (KeyboardInterrupt(), 130)])
def test_failed_write_leaves_old_results_and_no_temporary(work: Path, tmp_path: Path, monkeypatch, exc, code):
    import needlecli.io.results as results

    folder = tmp_path / "out"
    folder.mkdir()
    (folder / "r.h5").write_bytes(b"previous results")
    real = results._write_group

    def broken(g, grp, *_):
        real(g, results.Group(data={"time": np.arange(3.0)}))  # something is on disk already
        raise exc

    monkeypatch.setattr(results, "_write_group", broken)
    result = invoke("simulate", work / "tiny.yaml", "--out", folder / "r.h5", "--quiet", "--runs", "1")
    assert result.exit_code == code
    if code == 130:
        assert result.output.strip() == (f"error: interrupted by SIGINT: {folder / 'r.h5'} not written "
                                         "(the earlier file there is unchanged)")
    assert [p.name for p in folder.iterdir()] == ["r.h5"]
    assert (folder / "r.h5").read_bytes() == b"previous results"


def test_results_file_mode_follows_umask(run):
    import os

    _, out = run
    umask = os.umask(0)
    os.umask(umask)
    assert out.stat().st_mode & 0o777 == 0o666 & ~umask


def test_dry_run_writes_nothing(work: Path, tmp_path: Path):
    folder = tmp_path / "out"
    result = invoke("simulate", work / "tiny.yaml", "--out", folder / "r.h5", "--dry-run", "--runs", "5")
    assert result.exit_code == 0, result.output
    assert "valid" in result.stdout and "5 run(s)" in result.stdout and "modified_unicycle" in result.stdout
    assert not folder.exists()
    assert list(tmp_path.iterdir()) == []


def test_list_models():
    result = invoke("list", "--details")
    assert result.exit_code == 0, result.output
    for name in ("unicycle", "modified_unicycle", "so3", "mnm", "binm"):
        assert f"model {name}:" in result.stdout
    for line in ("models:", "sensors:", "observers:", "pipelines:", "tables:"):
        assert line in result.stdout
    assert "open_loop" in result.stdout and "position" in result.stdout


def test_version():
    result = invoke("--version")
    assert result.exit_code == 0 and needlecli.__version__ in result.stdout


# ---------------------------------------------------------------------------------------------- sensor clocks and noise
def measure(sensors: str, *, runs: int = 2, time: float = 10.0, seed: int = 0):
    text = (
        "model: {type: unicycle, params: {kappa: 0.002}}\n"
        "inputs: {v: 1.0}\n"
        f"sensors:\n{sensors}"
        f"runs: {{count: {runs}, seed: {seed}}}\n"
        f"stop: {{time: {time}}}\n"
        "simulation: {dt: 0.01}\n"
    )
    cfg, text = load_config(text=text)
    return run_experiment(cfg, text, write=False)


def test_clock_1hz_on_10s():
    res = measure("  - {type: position, rate: 1}\n")
    st = res.measurements["position"]
    assert len(res.truth.time) == 1001
    assert np.allclose(st.t, np.arange(11.0))
    assert np.array_equal(st.index, np.arange(11) * 100)
    assert st.value.shape == (2, 11, 3)


def test_clock_start_and_latency():
    res = measure("  - {type: encoder, rate: 4, start: 0.5, latency: 0.3, channels: [depth]}\n")
    st = res.measurements["encoder"]
    assert np.allclose(st.t, 0.5 + 0.25 * np.arange(39))  # 0.5 .. 10.0
    assert np.allclose(st.t_available, st.t + 0.3)
    # the depth the encoder reads is the depth at acquisition, not at availability
    assert np.allclose(np.nanmean(st.value[..., 0], 0), st.t, atol=0.01)


def test_dropout_half():
    res = measure("  - {type: encoder, rate: 100, channels: [depth], dropout: 0.5}\n", runs=20)
    st = res.measurements["encoder"]
    assert st.valid.shape == (20, 1001)
    assert abs(st.valid.mean() - 0.5) < 0.02
    assert np.isnan(st.value[~st.valid]).all() and np.isfinite(st.value[st.valid]).all()
    # dropouts are independent between runs and samples
    assert 0.4 < st.valid[:, :500].mean() < 0.6 and 0.4 < st.valid[:, 500:].mean() < 0.6
    assert not np.array_equal(st.valid[0], st.valid[1])


def test_noise_std_matches_sigma():
    res = measure("  - {type: position, rate: 100, sigma: 0.3}\n"
                  "  - {type: encoder, rate: 100, channels: [roll, depth], sigma: [0.01, 0.02]}\n", runs=20)
    st = res.measurements["position"]
    r = st.value - res.truth.states[:, st.index, 0:3]
    assert r.size == 20 * 1001 * 3
    assert np.allclose(r.reshape(-1, 3).std(0), 0.3, rtol=0.03)
    assert np.allclose(r.reshape(-1, 3).mean(0), 0.0, atol=0.01)
    assert np.all(st.sigma == 0.3)
    enc = res.measurements["encoder"]
    roll = enc.value[..., 0] - res.truth.states[:, enc.index, 5]
    depth = enc.value[..., 1] - res.truth.depth[enc.index]
    assert roll.std() == pytest.approx(0.01, rel=0.03)
    assert depth.std() == pytest.approx(0.02, rel=0.03)


def test_position_sigma_grows_with_distance():
    sigma, a, d_max = 0.2, 1.5, 10.0
    growth = f"{{transducer: [0, 0, 0], a: {a}, d_max: {d_max}}}"
    res = measure(f"  - {{type: position, rate: 100, sigma: {sigma}, growth: {growth}}}\n", runs=20)
    st = res.measurements["position"]
    p = res.truth.states[:, st.index, 0:3]
    d = np.linalg.norm(p, axis=-1)  # distance to the transducer at the origin: 0 .. 10 mm
    expected = (1 + a * d / d_max)[..., None] * sigma
    assert np.allclose(st.sigma, expected)
    assert st.sigma[:, 0] == pytest.approx(sigma) and np.allclose(st.sigma[:, -1], (1 + a * 10 / d_max) * sigma,
                                                                    rtol=1e-3)
    r = st.value - p
    assert (r / st.sigma).std() == pytest.approx(1.0, rel=0.02)
    near, far = r[:, :200], r[:, -200:]  # first and last 2 s
    assert near.std() == pytest.approx(np.sqrt(np.mean(expected[:, :200] ** 2)), rel=0.05)
    assert far.std() == pytest.approx(np.sqrt(np.mean(expected[:, -200:] ** 2)), rel=0.05)


def test_sensor_streams_do_not_depend_on_other_sensors():
    one = measure("  - {type: position, rate: 10}\n", seed=3)
    two = measure("  - {type: encoder, rate: 10}\n  - {type: position, rate: 10}\n", seed=3)
    assert np.array_equal(one.measurements["position"].value, two.measurements["position"].value)
