"""The compiled kernels (``needlecli.kernels``) beyond the agreement of each twin with its reference
(``tests/test_twins.py``, every case through ``compare_compiled_and_reference``, which these tests use too):
sin and cos, the fused model step's fallback, whole UKF insertions, divergence and repairs, EM's fused
pass and its internals, the on-disk cache and the warm-up.

Tolerance 1e-10 (absolute, in the models' units) wherever the two compute the same thing in one go: a
model step, the truth simulation, a few filter ticks. A filter run of hundreds of ticks carries the
rounding of its first ticks along (the multi-rate UKF paper's alpha = 1e-3 weights residuals by 7e4, and the position
integrates the angles): there the kernel must agree with the numpy path as well as the numpy path agrees
with itself when only its sin and cos change by an ulp.
"""

from __future__ import annotations

import dataclasses
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("numba")

from needlecli import kernels  # noqa: E402
from needlecli.experiments.config.load import load_config  # noqa: E402
from needlecli.experiments.simulation.runner import run_experiment  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from twins import (  # noqa: E402
    assert_posteriors_agree,
    compare_compiled_and_reference,
    em_inputs,
    run_observer,
    ukf_config,
)

ROOT = Path(__file__).resolve().parents[1]


# ---------------------------------------------------------------------------------------------- sin, cos
def test_sincos_within_an_ulp_of_libm_and_libm_outside_its_range():
    from needlecli.kernels.models import sincos_rows

    rng = np.random.default_rng(0)
    x = np.concatenate([rng.uniform(-4, 4, 20000), rng.uniform(-1e5, 1e5, 20000),
                        np.arange(-64, 65) * (np.pi / 4), np.arange(-64, 65) * (np.pi / 4) + 1e-9,
                        [0.0, -0.0, 1e-300, 5e-324, 2e6, -3e8, 1e300, np.inf, -np.inf, np.nan]])
    SC = np.empty((2, x.size))
    sincos_rows(x[None, :], 0, 1, SC, x.size)
    with np.errstate(invalid="ignore"):  # sin(inf) is NaN
        s, c = np.array([np.sin(v) for v in x]), np.array([np.cos(v) for v in x])
    fin = np.isfinite(x)
    for got, ref in ((SC[0], s), (SC[1], c)):
        assert np.array_equal(np.isnan(got), np.isnan(ref))
        err = np.abs(got[fin] - ref[fin]) / np.spacing(np.maximum(np.abs(ref[fin]), 1e-300))
        small = np.abs(x[fin]) < 8.0  # angles as the models see them: 1 ulp; up to 1e6 rad: 2
        assert err[small].max() <= 1.0 and err.max() <= 2.0


# ---------------------------------------------------------------------------------------------- UKF
def test_ukf_divergence_and_status_as_numpy():
    """Runs that miss the first position samples (dropout) keep a covariance above the limit: they stop
    as diverged at the same tick, hold their last estimate; the others go on."""
    text = ukf_config(1, "depth: 0.09").replace("type: ukf\n", "type: ukf\n    max_cov_trace: 3.0\n")
    ref, _ = compare_compiled_and_reference("ukf", lambda s: run_observer(text, s), check=assert_posteriors_agree)
    assert (ref["status"] == "diverged").any() and (ref["status"] == "ok").any()


def test_ukf_cholesky_repairs_as_numpy():
    """A roll measured to 1e-9 rad leaves P at the edge of positive definiteness: each run repairs its
    factor once, in both paths. (Where a matrix sits exactly on the edge, whether its Cholesky fails is
    itself a matter of rounding: the repair counts may then differ by one.)"""
    text = ukf_config(1, "depth: 0.09").replace("robot: {sigma: 0.0035}", "robot: {sigma: 1.0e-9}")
    ref, _ = compare_compiled_and_reference("ukf", lambda s: run_observer(text, s), check=assert_posteriors_agree)
    assert (ref["extras"]["cholesky_repairs"] == 1).all()


def test_ukf_whole_insertion_within_the_references_own_rounding(monkeypatch):
    """The multi-rate UKF paper's Table 1 set-up over 30 mm (2,000 ticks): the kernel differs from the numpy path by no
    more than the numpy path differs from itself with numpy's sin and cos (within 2 ulp of its own)."""
    import needlecli.models.unicycle as unicycle

    monkeypatch.delenv(kernels.ENV, raising=False)

    def run(setting):
        cfg, text = load_config(ROOT / "configs/multirate-ukf-us3d/table1.yaml", runs=4,
                                overrides=["stop.depth=30", f"simulation.kernels={setting}"])
        return run_experiment(cfg, text, write=False).estimates["ukf"].state

    with monkeypatch.context() as m:
        m.setattr(unicycle, "sincos", lambda a: (np.sin(a), np.cos(a)))
        other = run("numpy")

    def check(ref, got):
        noise = np.abs(other - ref).max()
        assert 0 < noise < 1e-8
        assert np.abs(got - ref).max() <= 10 * noise

    compare_compiled_and_reference("ukf", run, check=check)


# ---------------------------------------------------------------------------------------------- selection
def test_config_key_selects_the_numpy_path(monkeypatch):
    import needlecli.kernels.ukf as ku

    monkeypatch.delenv(kernels.ENV, raising=False)
    monkeypatch.setattr(ku, "filter_runs", lambda *a, **k: pytest.fail("the kernel ran"))
    cfg, text = load_config(text=ukf_config(1, "time: 0.1") + "simulation: {dt: 0.01, kernels: numpy}\n")
    assert run_experiment(cfg, text, write=False).estimates["ukf"].status.size == 4


def test_needle_list_says_what_is_compiled():
    out = subprocess.run([sys.executable, "-m", "needlecli", "list"], capture_output=True, text=True, cwd=ROOT,
                         env={**os.environ, "PYTHONPATH": str(ROOT)}, check=True).stdout
    assert "kernels: auto" in out and "twin ukf (observers)" in out and "twin linearise (fitting)" in out
    out = subprocess.run([sys.executable, "-m", "needlecli", "list", "--details"], capture_output=True, text=True,
                         cwd=ROOT, env={**os.environ, "PYTHONPATH": str(ROOT)}, check=True).stdout
    assert "compiled models: binm, mnm, modified_unicycle, so3, unicycle" in out  # the models' declarations
    assert "model so3: " in out and "compiled equations so3" in out


def test_help_and_list_do_not_import_numba():
    code = ("import sys; sys.argv = ['needle', '--help']\nfrom needlecli.cli.app import run\n"
            "try:\n    run()\nexcept SystemExit:\n    pass\nprint('numba' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT,
                         env={**os.environ, "PYTHONPATH": str(ROOT)}, check=True).stdout
    assert out.strip().splitlines()[-1] == "False"


@pytest.mark.parametrize("where", ["checkout", "copy"])
def test_compiled_code_is_cached_on_disk(where, tmp_path):
    """A second process loads the kernels from the cache instead of compiling them: from this checkout
    and from a copy of the package elsewhere (as pip installs it)."""
    if where == "copy":
        import shutil

        shutil.copytree(ROOT / "needlecli", tmp_path / "site" / "needlecli",
                        ignore=shutil.ignore_patterns("__pycache__"))
        path = tmp_path / "site"
    else:
        path = ROOT
    code = ("from needlecli.kernels import core\ncore.wrap(7.0)\ns = core.wrap.stats\n"
            "print(sum(s.cache_hits.values()), sum(s.cache_misses.values()))")
    env = {**os.environ, "PYTHONPATH": str(path), "NEEDLECLI_KERNEL_CACHE": str(tmp_path / "cache")}
    runs = [subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=tmp_path, env=env,
                           check=True).stdout.split() for _ in range(2)]
    assert runs[0] == ["0", "1"] and runs[1] == ["1", "0"]


def test_first_run_compiles_the_observers_in_a_second_process(tmp_path):
    """On an empty kernel cache, a run compiles the UKF in a second process while it compiles the truth
    (kernels.warm_up): the run itself then loads the UKF from the cache (a cache hit, no compilation), and
    its estimates are those of a run on a warm cache, bit for bit. Concurrent saves to the cache are locked:
    a third run compiles nothing."""
    code = textwrap.dedent("""
        import sys, numpy as np
        from needlecli.experiments.config.load import load_config
        from needlecli.experiments.simulation.runner import run_experiment
        cfg, text = load_config(sys.argv[1], overrides=["runs.count=3", "stop.depth=5"])
        res = run_experiment(cfg, text, write=False)
        np.save(sys.argv[2], res.estimates["ukf"].state)
        from needlecli.kernels import ukf, truth
        s = ukf.run.stats
        print(sum(s.cache_hits.values()), sum(s.cache_misses.values()), sum(truth.advance.stats.cache_misses.values()))
    """)
    env = {**os.environ, "PYTHONPATH": str(ROOT), "NEEDLECLI_KERNEL_CACHE": str(tmp_path / "cache")}
    env.pop("NEEDLECLI_KERNELS", None)
    out = [subprocess.run([sys.executable, "-c", code, str(ROOT / "configs/multirate-ukf-us3d/table1.yaml"),
                           str(tmp_path / f"x{i}.npy")], capture_output=True, text=True, cwd=tmp_path, env=env,
                          check=True).stdout.split() for i in range(3)]
    assert out[0] == ["1", "0", "1"]  # the UKF from the cache the second process wrote; the truth compiled here
    assert out[1] == out[2] == ["1", "0", "0"]
    np.testing.assert_array_equal(np.load(tmp_path / "x0.npy"), np.load(tmp_path / "x1.npy"))
    assert not list((tmp_path / "cache").rglob("*.tmp.*"))  # every save complete


# ---------------------------------------------------------------------------------------------- EM passes
def _rel(a, b):
    a, b = np.asarray(a), np.asarray(b)
    return float(np.nanmax(np.abs(a - b)) / max(np.nanmax(np.abs(a)), 1e-300))


def _system(e, setting):
    """The system of :func:`twins.em_inputs` with the kernels setting ``setting``."""
    import copy

    dm = copy.copy(e["dm"])
    dm.kernels = setting
    return dm, [dataclasses.replace(mm, kernels=setting) for mm in e["meas"]]


@pytest.mark.parametrize("name", ["mnm", "binm"])
def test_em_pass_as_em_runs_it_equals_numpy(name):
    """One pass of EM as fit-em runs it, the setting in the system: linearisation (RK4 Jacobians,
    measurement Jacobians in tangent planes), the fused affine filter and RTS smoother, the M-step sums;
    to 1e-10 relative (an entry's difference to the largest entry of its array). Missing samples included."""
    from needlecli.fitting.smoother import affine_pass, linearise
    from needlecli.numerics.kalman import em_measurement_noise, em_process_noise

    e = em_inputs(name)
    S, zbar, Q, R, P0 = e["S"], e["zbar"], e["Q"], e["R"], e["P0"]

    def run(setting):
        dm, meas = _system(e, setting)
        lin = linearise(dm, meas, zbar)
        res = affine_pass(lin, dm, meas, S.m0, P0, Q, R, joseph=False)
        q = em_process_noise(res.sm, lin.A, lin.b, dm.dt, index=S.q_index, state_angles=dm.angles, kernels=dm.kernels)
        r = [em_measurement_noise(res.sm, mm.channel(R[j], lin.y[j]), lin.H[j], lin.d[j], kernels=dm.kernels)[0]
             for j, mm in enumerate(meas)]
        return {"A": lin.A, "b": lin.b, "H": lin.H, "y": lin.y, "m_pred": res.fwd.m_pred, "m_filt": res.fwd.m_filt,
                "loglik": res.fwd.loglik, "m": res.sm.m, "P": res.sm.P, "Q": q, "R": r,
                "repairs": res.fwd.repairs + res.sm.repairs}

    compare_compiled_and_reference("kalman_filter_smoother", run, atol=0.0, rtol=1e-10)


@pytest.mark.parametrize("name", ["mnm", "binm"])
def test_em_fused_pass_writes_what_em_reads(name):
    """The compiled fused pass keeps the filter's covariances and the smoother's gains in the kernel (not
    written), makes the M-step sums instead of the cross-covariances, and the standard deviations and
    finiteness as it writes P (numpy's formulas, bit for bit, NaN included); the filter and the smoother
    on their own give its numbers bit for bit; the sums are used only for the linearisation they were made
    for; the log-likelihood alone is the full pass's, and on the trials' rows in place the rows' copied out."""
    from needlecli.fitting.smoother import affine_loglik, affine_pass, take_linearisation
    from needlecli.numerics.kalman import (
        em_measurement_noise,
        em_process_noise,
        kalman_filter_smoother,
        kalman_forward_affine,
        rts_smoother,
    )

    e = em_inputs(name)
    S, Q, R, P0, lb = e["S"], e["Q"], e["R"], e["P0"], e["lin"]
    dm, meas = _system(e, "numba")
    N = dm.N
    rb = affine_pass(lb, dm, meas, S.m0, P0, Q, R, joseph=False)
    assert rb.fwd.P_pred.shape[1] == rb.fwd.P_filt.shape[1] == rb.sm.G.shape[1] == rb.sm.C.shape[1] == 0
    assert rb.sm.q_sums is not None and rb.sm.r_sums is not None
    np.testing.assert_array_equal(rb.sm.sd, np.sqrt(np.maximum(np.diagonal(rb.sm.P, axis1=-2, axis2=-1), 1e-300)))
    np.testing.assert_array_equal(rb.sm.finite, np.isfinite(rb.sm.P).all((-1, -2, -3)))
    Qbad = Q.copy()
    Qbad[1] = np.inf  # trial 1's covariances become infinite, then NaN
    chans = [mm.channel(R[j], lb.y[j]) for j, mm in enumerate(meas)]
    with np.errstate(all="ignore"):
        _, smb = kalman_filter_smoother(S.m0, P0, Qbad, dm.dt, lb.A, lb.b, chans, lb.H, lb.d, state_angles=dm.angles,
                                        kernels="numba")
    assert smb.finite.tolist() == np.isfinite(smb.P).all((-1, -2, -3)).tolist() == [True, False] + [True] * (N - 2)
    with np.errstate(invalid="ignore"):
        np.testing.assert_array_equal(smb.sd, np.sqrt(np.maximum(np.diagonal(smb.P, axis1=-2, axis2=-1), 1e-300)))
    assert dataclasses.replace(smb, sd=None, finite=None).all_finite().tolist() == smb.finite.tolist()
    # the filter and the smoother on their own write them, and give the fused pass's numbers bit for bit
    fwd = kalman_forward_affine(S.m0, P0, Q, dm.dt, lb.A, lb.b, chans, lb.H, lb.d, state_angles=dm.angles,
                                kernels="numba")
    sm = rts_smoother(fwd, state_angles=dm.angles, kernels="numba")
    # the gains solve G_k P_{k+1|k} = P_{k|k} A_k^T (against numpy's LU the ill-conditioned directions of
    # P_{k+1|k} differ at 1e-6; the products the smoother makes of them agree: tests/twins.py)
    lhs = sm.G @ (0.5 * (fwd.P_pred[:, 1:] + np.swapaxes(fwd.P_pred[:, 1:], -1, -2)))
    assert _rel(fwd.P_filt[:, :-1] @ np.swapaxes(lb.A, -1, -2), lhs) < 1e-10
    for k in ("m_pred", "m_filt", "loglik", "repairs"):
        np.testing.assert_array_equal(getattr(fwd, k), getattr(rb.fwd, k))
    for k in ("m", "P", "repairs"):
        np.testing.assert_array_equal(getattr(sm, k), getattr(rb.sm, k))
    # the M-step's sums from the stored cross-covariances: those of the pass (summed in the other order)
    qb = em_process_noise(rb.sm, lb.A, lb.b, dm.dt, index=S.q_index, state_angles=dm.angles, kernels="numba")
    assert _rel(em_process_noise(sm, lb.A, lb.b, dm.dt, index=S.q_index, state_angles=dm.angles, kernels="numba"),
                qb) < 1e-12
    for j, ch in enumerate(chans):  # the measurement-noise sums of the stored smoother: the pass's
        got, cnt = em_measurement_noise(sm, ch, lb.H[j], lb.d[j], kernels="numba")
        want, cnt_b = em_measurement_noise(rb.sm, ch, lb.H[j], lb.d[j], kernels="numba")
        assert _rel(got, want) < 1e-12
        np.testing.assert_array_equal(cnt, cnt_b)
        other = em_measurement_noise(rb.sm, ch, lb.H[j] * (1.0 + 1e-9), lb.d[j], kernels="numba")[0]  # another
        assert _rel(other, want) > 0 and _rel(other, want) < 1e-6  # linearisation: computed, not the pass's sums
    with pytest.raises(ValueError, match="no cross-covariances"):  # sums of another linearisation: refused
        em_process_noise(rb.sm, lb.A * (1.0 + 1e-9), lb.b, dm.dt, index=S.q_index, state_angles=dm.angles,
                         kernels="numba")
    # the log-likelihood alone (identifiability's evaluation points): the full pass's, bit for bit
    np.testing.assert_array_equal(affine_loglik(lb, dm, meas, S.m0, P0, Q, R), rb.fwd.loglik)
    # many points on the trials' rows in place (identifiability): the rows copied out first, bit for bit
    rng = np.random.default_rng(6)
    rows = np.array([2, 0, 0, 5, 2, 3, 1, 5, 4])
    Qs = Q[rows] * rng.uniform(0.5, 2.0, (len(rows), 1, 1))
    Rs = [r[rows] * rng.uniform(0.5, 2.0, (len(rows), 1, 1)) for r in R]
    m0s = S.m0[rows] + 1e-4 * rng.standard_normal((len(rows), dm.n))
    for setting in ("numpy", "numba"):
        d, ms = _system(e, setting)
        copied = affine_loglik(take_linearisation(lb, rows), d.take(rows), [mm.take(rows) for mm in ms],
                               m0s, P0[rows], Qs, Rs)
        in_place = affine_loglik(lb, d, ms, m0s, P0[rows], Qs, Rs, rows=rows)
        np.testing.assert_array_equal(in_place, copied)


def test_fit_em_iterations_equal_numpy():
    """Three EM iterations (E-step, M-step, SQUAREM) of both models on 6 trials, the setting in the
    config (simulation.kernels, passed down to the systems): the same fit."""
    from needlecli.experiments.studies.fit import fit_trials, load_trials

    trials = load_trials(ROOT / "configs/em-magnetic-pratt2022/study.yaml",
                         overrides=["runs.count=6", "stop.time=4", "fit.em.max_iter=3"])

    def run(setting):
        cfg = trials.cfg.model_copy(update={"simulation": trials.cfg.simulation.model_copy(update={"kernels": setting})})
        return {name: mf.result for name, mf in fit_trials(dataclasses.replace(trials, cfg=cfg), workers=1).fits.items()}

    def check(ref, got):
        for name, a in ref.items():
            b = got[name]
            np.testing.assert_array_equal(a.iterations, b.iterations)
            np.testing.assert_array_equal(a.status, b.status)
            for k in ("Qc", "x0", "m", "P", "filtered", "ekf"):
                assert _rel(getattr(a, k), getattr(b, k)) < 1e-9, (name, k)
            assert all(_rel(x, y) < 1e-9 for x, y in zip(a.R, b.R))

    compare_compiled_and_reference("kalman_filter_smoother", run, check=check)


# ---------------------------------------------------------------------------------------------- results file
@pytest.mark.parametrize("mode", ["auto", "gzip", "none"])
def test_results_compression_where_it_pays(mode, tmp_path):
    """output.compression: ``auto`` gzips the arrays that repeat along an axis (inputs held the same for
    every run, per-run parameters, constant noise levels) and writes the others as they are; ``gzip``
    all large arrays; ``none`` nothing. The arrays read back are the same either way."""
    import h5py

    cfg, text = load_config(ROOT / "configs/multirate-ukf-us3d/table1.yaml", runs=6,
                            overrides=["stop.depth=20", f"output.compression={mode}"])
    res = run_experiment(cfg, text, out=tmp_path / "r.h5")
    with h5py.File(res.path) as f:
        filters = {k: f[k].compression for k in ("inputs/v", "truth/params/beta_cut", "measurements/robot/sigma",
                                                  "truth/state", "estimates/ukf/state")}
        np.testing.assert_array_equal(f["truth/state"][()], res.truth.states)
    want = {"auto": ["gzip"] * 3 + [None] * 2, "gzip": ["gzip"] * 5, "none": [None] * 5}[mode]
    assert list(filters.values()) == want


def test_results_file_the_same_however_written(tmp_path, monkeypatch):
    """The results file is written straight from the arrays into room reserved ahead (O_DIRECT for the
    arrays where the file system has it, else the page cache) or, where room cannot be reserved, built in
    memory first: every array reads back as it was, whichever way (and the first two give the same bytes);
    arrays repeating along an axis are gzipped with each distinct chunk compressed once."""
    import errno

    from needlecli.io import results
    from needlecli.io.tree import Group

    cfg, text = load_config(ROOT / "configs/multirate-ukf-us3d/table1.yaml", runs=5, overrides=["stop.depth=10"])
    res = run_experiment(cfg, text, write=False)
    from needlecli.experiments.simulation.runner import build_sensors, results_tree

    tree = results_tree(cfg, text, res.truth, res.measurements, res.estimates, build_sensors(cfg, res.truth.model))
    tree.data["extra"] = Group(data={"rows_alike": np.broadcast_to(np.arange(7000.0), (30, 7000)),
                                     "held": np.repeat(np.arange(30.0)[:, None], 9000, axis=1)})
    results.write_atomic(tmp_path / "direct.h5", tree)
    monkeypatch.setenv("NEEDLECLI_NO_DIRECT_IO", "1")
    results.write_atomic(tmp_path / "cached.h5", tree)

    def no_room(fd, offset, length):
        raise OSError(errno.EOPNOTSUPP, "not supported")

    monkeypatch.setattr(results.os, "posix_fallocate", no_room)
    results.write_atomic(tmp_path / "image.h5", tree)
    assert (tmp_path / "direct.h5").read_bytes() == (tmp_path / "cached.h5").read_bytes()

    def arrays(g, prefix=""):
        for k, v in g.data.items():
            if isinstance(v, Group):
                yield from arrays(v, f"{prefix}{k}/")
            else:
                yield prefix + k, np.asarray(v)

    want = dict(arrays(tree))
    for name in ("direct", "cached", "image"):
        got = dict(arrays(results.read_results(tmp_path / f"{name}.h5")))
        assert got.keys() == want.keys()
        for k, a in want.items():
            if a.dtype.kind in "UO":
                np.testing.assert_array_equal(got[k].astype(str), a.astype(str), err_msg=k)
            else:
                np.testing.assert_array_equal(got[k], a, err_msg=k)
    import h5py

    with h5py.File(tmp_path / "direct.h5") as f:
        assert f["extra/rows_alike"].compression == "gzip" and f["extra/held"].compression == "gzip"
        assert f["extra/rows_alike"].id.get_storage_size() < 1e5 and f["truth/state"].compression is None


def test_the_commands_memory_policy():
    """``needle`` maps numpy's large arrays on ordinary pages unless the user asks for huge ones, with or
    without a glibc MALLOC_ variable set (then glibc's heap is left as it is; needlecli.cli.app.memory_policy)."""
    code = ("from needlecli.cli.app import memory_policy\nmemory_policy()\nimport numpy\n"
            "print(numpy._core.multiarray._get_madvise_hugepage())")
    env = {k: v for k, v in os.environ.items() if k != "NUMPY_MADVISE_HUGEPAGE" and not k.startswith("MALLOC_")}
    env["PYTHONPATH"] = str(ROOT)
    for extra, want in (({}, "False"), ({"NUMPY_MADVISE_HUGEPAGE": "1"}, "True"),
                        ({"MALLOC_ARENA_MAX_": "2"}, "False")):
        out = subprocess.run([sys.executable, "-c", code], env={**env, **extra}, capture_output=True, text=True,
                             check=True).stdout.strip()
        assert out == want, (extra, out)


def test_a_kernels_argument_types_do_not_depend_on_how_the_caller_made_its_arrays():
    """numba types an array by its layout and its flags: a read-only or broadcast input would compile a
    kernel again (the RTS smoother's and the filter-smoother's records once did). Every wrapper takes its
    arrays through kernel_array, so the records of a Kalman pass have one type for any such input."""
    import numba

    from needlecli.kernels.channels import kernel_array
    from needlecli.kernels.kalman import _forward_inputs
    from needlecli.numerics.kalman import Channel

    ro = np.broadcast_to(np.eye(3), (4, 3, 3))
    a = kernel_array(ro, dtype=float)
    assert a.flags.writeable and a.flags.c_contiguous
    fresh = np.zeros((4, 3))
    assert kernel_array(fresh, dtype=float) is fresh  # no copy where none is needed

    N, n, K = 4, 3, 5
    rng = np.random.default_rng(0)

    def frozen(x):
        x = np.array(x)
        x.flags.writeable = False
        return x

    def records(P0, Qc, A):
        ch = Channel(np.arange(K + 1), rng.normal(size=(N, K + 1, 1)), np.ones((N, K + 1), bool), np.eye(1))
        H, d = [np.ones((N, K + 1, 1, n))], [np.zeros((N, K + 1, 1))]
        return _forward_inputs(np.zeros((N, n)), P0, Qc, np.full(K, 0.1), A, np.zeros((N, K, n)), [ch], H, d, None,
                               N, np.arange(N, dtype=np.int64))

    base = records(np.eye(n), np.eye(n), np.tile(np.eye(n), (N, K, 1, 1)))
    for P0, Qc, A in [(np.tile(np.eye(n), (N, 1, 1)), np.eye(n), np.tile(np.eye(n), (N, K, 1, 1))),
                      (frozen(np.tile(np.eye(n), (N, 1, 1))), frozen(np.tile(np.eye(n), (N, 1, 1))),
                       frozen(np.tile(np.eye(n), (N, K, 1, 1)))),
                      (np.eye(n), np.eye(n), np.broadcast_to(np.eye(n), (N, K, n, n)))]:
        other = records(P0, Qc, A)
        assert [numba.typeof(r) for r in other] == [numba.typeof(r) for r in base]
