"""The table of compiled twins (``needlecli.kernels.TWINS``): each twin agrees with its numpy reference
on every case of it (tests/twins.py, through one helper: ``compare_compiled_and_reference``), a twin
without a case fails, and the choice between them is made from the setting passed down: ``kernels:
numpy`` runs the reference everywhere and imports no numba at all."""

from __future__ import annotations

import ast
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from needlecli import kernels

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(Path(__file__).resolve().parent))

numba = pytest.importorskip("numba")

from twins import CASES, compare_compiled_and_reference, compiled_models  # noqa: E402

ALL = [(name, cid) for name in kernels.TWINS for cid in CASES.get(name, {})]


@pytest.mark.parametrize("name,case_id", ALL, ids=[f"{n}:{c}" for n, c in ALL])
def test_twin_agrees_with_its_reference(name, case_id):
    run, opts = CASES[name][case_id]
    compare_compiled_and_reference(name, run, **opts)


def test_every_twin_has_a_case():
    """A twin added to the table needs a case in tests/twins.py (and a case names a twin of the table)."""
    missing = sorted(set(kernels.TWINS) - {n for n, c in CASES.items() if c})
    assert not missing, f"twins without a case in tests/twins.py: {missing}"
    assert set(CASES) <= set(kernels.TWINS), f"cases of no twin: {sorted(set(CASES) - set(kernels.TWINS))}"


def test_table_names_functions_that_exist():
    for t in kernels.TWINS.values():
        assert callable(t.load("reference")), t.reference
        assert callable(t.load("compiled")), t.compiled
        assert t.group in ("models", "truth", "observers", "fitting", "metrics") and t.covers


def test_models_declare_equations_the_kernels_have():
    """The compiled models are those whose class declares compiled equations (read through the registry),
    each a set of equations of the kernels, with what the kernels read declared by the model too; each one
    is a case of the model-step twin."""
    from needlecli.kernels.models import MODEL_IDS
    from needlecli.kernels.truth import margin
    from needlecli.models import MODELS

    names = compiled_models()
    assert set(names) == {"unicycle", "modified_unicycle", "so3", "mnm", "binm"}
    for name in names:
        cls = MODELS.get(name)
        assert cls.compiled_equations in MODEL_IDS, name
        margin(cls())  # a singularity the kernels know, on states the model has
        for p, s in cls.param_states.items():
            assert p in cls.Params.model_fields and s in cls.state_names
        for q, states in cls.unit_vectors.items():
            assert cls.provides(q) and set(states) <= set(cls.state_names)
    assert set(names) <= set(CASES["model_step"])


def test_observers_declare_their_longest_compilation():
    """The warm-up compiles what the observers declare (``compiled_entry``, read through the registry)."""
    from needlecli.observers import OBSERVERS

    entries = {n: getattr(OBSERVERS.get(n), "compiled_entry", None) for n in OBSERVERS.builtin_names()}
    assert entries["ukf"] == ("ukf", "run") and entries["eks"] == ("kalman", "filter_smoother")
    for n, e in entries.items():
        if e is not None:
            module, fn = e
            assert hasattr(__import__(f"needlecli.kernels.{module}", fromlist=[fn]), fn), n


def test_docs_hold_the_table():
    """docs/guide/kernels.md shows the twins as the table says (kernels.markdown_table: one source)."""
    assert kernels.markdown_table() in (ROOT / "docs/guide/kernels.md").read_text()


def test_the_environment_is_read_in_one_place():
    """``NEEDLECLI_KERNELS`` is read by needlecli.kernels.dispatch alone, where the setting is resolved; no
    module keeps a setting of its own (a context variable)."""
    readers = []
    for path in (ROOT / "needlecli").rglob("*.py"):
        tree = ast.parse(path.read_text())
        for node in ast.walk(tree):
            if isinstance(node, ast.Constant) and node.value == kernels.ENV and not _in_docstring(node, tree):
                readers.append(path.relative_to(ROOT).as_posix())
            if isinstance(node, (ast.Import, ast.ImportFrom)) and any(a.name == "contextvars" or a.name == "ContextVar"
                                                                     for a in node.names):
                if "kernels" in path.parts:
                    readers.append(f"{path.relative_to(ROOT).as_posix()} (a context variable)")
    assert sorted(set(readers)) == ["needlecli/kernels/dispatch.py"]


def _in_docstring(node, tree) -> bool:
    for n in ast.walk(tree):
        if isinstance(n, (ast.Module, ast.FunctionDef, ast.ClassDef)) and n.body:
            first = n.body[0]
            if isinstance(first, ast.Expr) and first.value is node:
                return True
    return False


def test_resolution(monkeypatch):
    """auto and numba: compiled (numba is installed); numpy: the reference; the environment variable
    overrides the setting; a wrong value is the user's error (one line), naming where it comes from."""
    monkeypatch.delenv(kernels.ENV, raising=False)
    assert [kernels.resolve(s) for s in (None, "auto", "numba", "numpy")] == ["numba", "numba", "numba", "numpy"]
    assert kernels.twin("rts_smoother", "numpy") is None and kernels.twin("rts_smoother", "auto") is not None
    monkeypatch.setenv(kernels.ENV, "numpy")
    assert kernels.resolve("numba") == "numpy" and kernels.twin("ukf", "auto") is None
    monkeypatch.setenv(kernels.ENV, "fast")
    from needlecli.errors import NeedleError

    with pytest.raises(NeedleError, match="NEEDLECLI_KERNELS='fast'"):
        kernels.resolve("auto")
    monkeypatch.delenv(kernels.ENV)
    with pytest.raises(NeedleError, match="kernels: 'fast'"):
        kernels.resolve("fast")
    with pytest.raises(KeyError):
        kernels.twin("no such twin", "auto")


def test_a_wrong_environment_value_is_one_line(tmp_path):
    env = {**os.environ, "PYTHONPATH": str(ROOT), kernels.ENV: "fast"}
    p = subprocess.run([sys.executable, "-m", "needlecli", "simulate", str(ROOT / "configs/multirate-ukf-us3d/table1.yaml"),
                        "--runs", "1", "--set", "stop.depth=1", "--out", str(tmp_path / "r.h5"), "-q"],
                       capture_output=True, text=True, env=env)
    assert p.returncode == 2, p.stderr
    assert p.stderr.strip().splitlines() == ["error: NEEDLECLI_KERNELS='fast': expected one of auto, numba, numpy"]
    assert not list(tmp_path.iterdir())


# ---------------------------------------------------------------------------------------------- numpy: no numba
NO_NUMBA = textwrap.dedent("""
    import sys
    from needlecli.cli.app import run
    sys.argv = ["needle", *sys.argv[1:]]
    try:
        run()
    except SystemExit as e:
        assert not e.code, e.code
    print("numba" in sys.modules)
""")


def _needle_imports_numba(args, extra_env=None) -> bool:
    env = {k: v for k, v in os.environ.items() if k != kernels.ENV}
    env.update({"PYTHONPATH": str(ROOT), **(extra_env or {})})
    p = subprocess.run([sys.executable, "-c", NO_NUMBA, *map(str, args)], capture_output=True, text=True, env=env,
                       cwd=ROOT)
    assert p.returncode == 0, p.stderr[-2000:]
    return p.stdout.strip().splitlines()[-1] == "True"


def test_kernels_numpy_imports_no_numba(tmp_path):
    """``simulation.kernels: numpy`` (a config's, from --set) runs needle simulate, needle evaluate (from the
    results file's recorded config) and needle fit-em without importing numba at all; the environment
    variable does the same for a config that says auto."""
    out = tmp_path / "r.h5"
    assert not _needle_imports_numba(["simulate", ROOT / "configs/multirate-ukf-us3d/table1.yaml", "--runs", "2", "--set",
                                      "stop.depth=5", "--set", "simulation.kernels=numpy", "--out", out, "-q"])
    assert not _needle_imports_numba(["evaluate", out, "--out", tmp_path / "t", "--no-plots", "-q"])
    assert not _needle_imports_numba(["fit-em", ROOT / "configs/em-magnetic-pratt2022/study.yaml", "--set", "runs.count=2", "--set",
                                      "stop.time=2", "--set", "fit.em.max_iter=2", "--set", "simulation.kernels=numpy",
                                      "--out", tmp_path / "f.h5", "-q"])
    assert not _needle_imports_numba(["simulate", ROOT / "configs/multirate-ukf-us3d/table1.yaml", "--runs", "2", "--set",
                                      "stop.depth=5", "--out", tmp_path / "e.h5", "-q"], {kernels.ENV: "numpy"})
    # the same commands with the default setting do use the kernels (the test above can fail)
    assert _needle_imports_numba(["evaluate", tmp_path / "e.h5", "--out", tmp_path / "t2", "--no-plots", "-q"])


# ---------------------------------------------------------------------------------------------- plug-ins
PLUGIN = textwrap.dedent('''
    from needlecli.models.unicycle import ModifiedUnicycle


    class LabCompiled(ModifiedUnicycle):
        """The modified unicycle under a lab's name: its compiled twin is its declaration (inherited)."""


    class LabNumpy(ModifiedUnicycle):
        """The same equations, declared without a compiled twin."""

        compiled_equations = None
''')

RUN_PLUGIN = textwrap.dedent("""
    import sys
    sys.path.insert(0, sys.argv[1])
    from twins import ukf_config
    import needlecli.kernels.truth as kt
    import needlecli.kernels.ukf as ku
    from needlecli.experiments.config.load import load_config
    from needlecli.experiments.simulation.runner import run_experiment

    calls = []
    real_ukf, real_truth = ku.filter_runs, kt.TruthKernel
    ku.filter_runs = lambda *a, **k: (calls.append("ukf"), real_ukf(*a, **k))[1]
    kt.TruthKernel = lambda sim: (calls.append("truth"), real_truth(sim))[1]
    text = ukf_config(0, "depth: 0.09").replace("type: modified_unicycle", "type: " + sys.argv[2])
    cfg, text = load_config(text=text)
    res = run_experiment(cfg, text, write=False)
    print(res.truth.model.registered_name, sorted(set(calls)))
""")


def test_a_plugin_model_declares_its_compiled_twin(tmp_path):
    """A lab's model (an entry point) has the kernels its class declares, as a built-in does: the compiled
    truth and UKF for the one that declares the modified unicycle's equations, the numpy path for the
    one that declares none."""
    pkg = tmp_path / "labpkg"
    pkg.mkdir()
    (pkg / "__init__.py").write_text(PLUGIN)
    info = tmp_path / "labpkg-0.1.dist-info"
    info.mkdir()
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: labpkg\nVersion: 0.1\n")
    (info / "entry_points.txt").write_text("[needlecli.models]\nlab_compiled = labpkg:LabCompiled\n"
                                           "lab_numpy = labpkg:LabNumpy\n")
    env = {k: v for k, v in os.environ.items() if k != kernels.ENV}
    env["PYTHONPATH"] = os.pathsep.join([str(tmp_path), str(ROOT)])
    out = {}
    for name in ("lab_compiled", "lab_numpy"):
        p = subprocess.run([sys.executable, "-c", RUN_PLUGIN, str(Path(__file__).resolve().parent), name],
                           capture_output=True, text=True, env=env, cwd=tmp_path)
        assert p.returncode == 0, p.stderr[-3000:]
        out[name] = p.stdout.strip().splitlines()[-1]
    assert out == {"lab_compiled": "lab_compiled ['truth', 'ukf']", "lab_numpy": "lab_numpy []"}
