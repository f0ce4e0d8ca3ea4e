"""The house rules, read from the source with ``ast``: no import cycle between needlecli's modules
(imports inside functions count; ``if TYPE_CHECKING:`` blocks do not), dependencies between the
packages point one way (the layers drawn in docs/layout.md), and ``needle --help`` loads no
numerical library."""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import pytest

PKG = Path(__file__).resolve().parent.parent / "needlecli"

#: each package (or top-level module) and the ones it may import: docs/layout.md's layer drawing, as data
LAYERS: dict[str, set[str]] = {
    "foundation": set(),  # errors, guard, registry, schema, provenance, platform, the package's __init__
    "kernels": {"foundation"},  # compiled numerics: import nothing of the package above them
    "numerics": {"kernels", "foundation"},
    "models": {"numerics", "foundation", "kernels"},
    "problem": {"models", "numerics", "foundation", "kernels"},  # problem.py, initial.py
    "sensors": {"models", "numerics", "foundation", "kernels"},
    "io": {"sensors", "models", "numerics", "foundation", "kernels"},
    "metrics": {"io", "models", "numerics", "foundation", "kernels"},
    "fitting": {"problem", "sensors", "io", "models", "numerics", "foundation", "kernels"},
    "observers": {"fitting", "problem", "sensors", "models", "numerics", "foundation", "kernels"},
    "control": {"sensors", "io", "models", "numerics", "foundation", "kernels"},
    "reports": {"metrics", "io", "sensors", "models", "numerics", "foundation", "kernels"},
    # experiments, split by role: what an experiment is, its insertions, studies over many of them
    "experiments.config": {"observers", "fitting", "control", "reports", "metrics", "problem", "sensors", "io",
                           "models", "numerics", "foundation", "kernels", "experiments"},
    "experiments.simulation": {"experiments.config", "observers", "fitting", "control", "reports", "metrics",
                               "problem", "sensors", "io", "models", "numerics", "foundation", "kernels",
                               "experiments"},
    "experiments.studies": {"experiments.simulation", "experiments.config", "observers", "fitting", "control",
                            "reports", "metrics", "problem", "sensors", "io", "models", "numerics", "foundation",
                            "kernels", "experiments"},
    "experiments": set(),  # the package's front door (a docstring)
    "cli": {"experiments.studies", "experiments.simulation", "experiments.config", "experiments", "observers",
            "fitting", "control", "reports", "metrics", "problem", "sensors", "io", "models", "numerics",
            "foundation", "kernels"},
}
FOUNDATION = {"needlecli", "needlecli.errors", "needlecli.guard", "needlecli.registry", "needlecli.schema", "needlecli.papers",
              "needlecli.provenance", "needlecli.platform"}


def module_name(path: Path) -> str:
    parts = path.relative_to(PKG.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _type_checking(node: ast.AST) -> bool:
    return isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test)


def imports_of(path: Path, modules: set[str]) -> set[str]:
    """The needlecli modules ``path`` imports anywhere (TYPE_CHECKING blocks aside), with the packages
    whose ``__init__`` an import runs."""
    tree = ast.parse(path.read_text())
    me = module_name(path)
    package = me if path.name == "__init__.py" else me.rpartition(".")[0]
    found: set[str] = set()

    def visit(node: ast.AST) -> None:
        if _type_checking(node):
            return
        if isinstance(node, ast.Import):
            found.update(a.name for a in node.names if a.name.split(".")[0] == "needlecli")
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")[: len(package.split(".")) - node.level + 1]
                name = ".".join(base + ([node.module] if node.module else []))
            else:
                name = node.module or ""
            if name.split(".")[0] == "needlecli":
                found.add(name)
                found.update(f"{name}.{a.name}" for a in node.names if f"{name}.{a.name}" in modules)
        for child in ast.iter_child_nodes(node):
            visit(child)

    visit(tree)
    out = set()
    for name in found:  # importing a.b.c runs a/__init__, a.b/__init__ too
        parts = name.split(".")
        out.update(".".join(parts[:i]) for i in range(1, len(parts) + 1))
    ancestors = {".".join(me.split(".")[:i]) for i in range(1, len(me.split(".")))}  # already importing
    return {m for m in out if m in modules and m != me and m not in ancestors}


def graph() -> dict[str, set[str]]:
    files = {module_name(p): p for p in PKG.rglob("*.py")}
    mods = set(files)
    return {m: imports_of(p, mods) for m, p in files.items()}


def layer(module: str) -> str:
    if module in FOUNDATION:
        return "foundation"
    if module == "needlecli.__main__":
        return "cli"
    if module == "needlecli.initial":  # where an estimate starts: part of what observers and fits are given
        return "problem"
    parts = module.split(".")
    if parts[1] == "experiments" and len(parts) > 2:  # its rooms are layers of their own
        return f"experiments.{parts[2]}"
    return parts[1]


def find_cycle(g: dict[str, set[str]]) -> list[str] | None:
    state: dict[str, int] = {}
    stack: list[str] = []

    def dfs(m: str) -> list[str] | None:
        state[m] = 1
        stack.append(m)
        for d in sorted(g.get(m, ())):
            if state.get(d) == 1:
                return stack[stack.index(d):] + [d]
            if d not in state:
                c = dfs(d)
                if c:
                    return c
        stack.pop()
        state[m] = 2
        return None

    for m in sorted(g):
        if m not in state:
            c = dfs(m)
            if c:
                return c
    return None


def test_the_checker_finds_a_cycle():
    assert find_cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}}) == ["a", "b", "c", "a"]
    assert find_cycle({"a": {"b"}, "b": set()}) is None


def test_no_import_cycle():
    cycle = find_cycle(graph())
    assert cycle is None, "import cycle: " + " -> ".join(cycle)


def test_every_package_has_a_layer():
    assert {layer(m) for m in graph()} <= set(LAYERS)


def test_layers_point_one_way():
    assert find_cycle({k: set(v) - {k} for k, v in LAYERS.items()}) is None  # the drawing itself is a DAG
    wrong = sorted(f"{m} -> {d}" for m, deps in graph().items() for d in deps
                   if layer(d) != layer(m) and layer(d) not in LAYERS[layer(m)])
    assert not wrong, "imports against the layers:\n" + "\n".join(wrong)


HEAVY = ("numpy", "scipy", "pandas", "matplotlib", "cv2", "h5py", "numba", "dask", "pydantic", "yaml")


@pytest.mark.parametrize("argv", [["--help"], ["-h"], ["--version"], ["list"], ["simulate", "--help"], ["log", "-h"],
                                  ["fit-em", "--help"], ["crossval", "-h"]])
def test_help_loads_no_numerical_library(argv):
    heavy = set(HEAVY)
    code = ("import sys\nfrom needlecli.cli.app import run\n"
            f"sys.argv = ['needle', *{argv!r}]\n"
            "try:\n    run()\nexcept SystemExit:\n    pass\n"
            "print(' '.join(sorted({m.split('.')[0] for m in sys.modules})))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    loaded = set(out.strip().splitlines()[-1].split())
    assert not loaded & heavy, f"needle {' '.join(argv)} loads {sorted(loaded & heavy)}"


def test_builtin_tables_name_what_the_modules_register():
    """Each registry's table of built-ins (name -> module) is what the modules register: importing every
    module of needlecli registers nothing the table does not list, and each name where the table says."""
    import importlib
    import pkgutil

    import needlecli
    from needlecli.control import CONTROLLERS
    from needlecli.models import MODELS
    from needlecli.observers import OBSERVERS
    from needlecli.reports import PLOTS, TABLES
    from needlecli.sensors import PIPELINES, SENSORS
    from needlecli.sensors.imaging.base import DEVICES

    registries = (MODELS, SENSORS, PIPELINES, OBSERVERS, CONTROLLERS, TABLES, PLOTS, DEVICES)
    for reg in registries:
        for name in reg.builtin_names():
            obj = reg.get(name)
            assert getattr(obj, "__module__", "") == reg._builtins[name], (reg.what, name, obj.__module__)
    for m in pkgutil.walk_packages(needlecli.__path__, "needlecli."):
        if not m.name.endswith("__main__"):  # that one runs the command
            importlib.import_module(m.name)
    for reg in registries:
        extra = set(reg._items) - set(reg.builtin_names()) - set(reg.plugins())
        extra = {n for n in extra if getattr(reg._items[n], "__module__", "").startswith("needlecli.")}  # not tests' own
        assert not extra, f"{reg.what}: registered by a module but not in the table of built-ins: {sorted(extra)}"


def test_every_config_argument_is_typed():
    """A function that takes the validated config says so (``cfg: ExperimentConfig``), so that an editor
    follows ``cfg.runs.seed``; read from the source with ``ast``."""
    untyped = []
    for path in PKG.rglob("*.py"):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                for a in node.args.posonlyargs + node.args.args + node.args.kwonlyargs:
                    if a.arg in ("cfg", "config") and (a.annotation is None or (a.arg == "cfg" and "ExperimentConfig"
                                                                                 not in ast.unparse(a.annotation))):
                        untyped.append(f"{path.relative_to(PKG.parent)}:{node.lineno} {node.name}({a.arg})")
    assert not untyped, "config arguments without their type:\n" + "\n".join(untyped)


#: what only needlecli/platform.py may use: modules of one operating system, ``os`` functions some platforms
#: lack (or where they mean something else: ``os.kill`` ends a process on Windows), the C library's symbols
PLATFORM_MODULES = {"fcntl", "msvcrt", "ctypes", "resource", "termios", "winreg", "_winapi", "threadpoolctl"}
PLATFORM_NAMES = {"posix_fallocate", "O_DIRECT", "statvfs", "pathconf", "sched_getaffinity", "sysconf", "getppid",
                  "prctl", "mallopt", "flock", "lockf", "get_all_start_methods", "raise_signal",
                  "_set_madvise_hugepage"}
PLATFORM_OS = {"kill", "fork", "forkpty", "killpg", "setsid", "nice", "uname", "name"}  # as attributes of ``os``


def platform_uses(tree: ast.AST) -> list[tuple[int, str]]:
    """The operating-system-specific names a module's code uses (docstrings and comments aside): imports of
    :data:`PLATFORM_MODULES`, attributes (or ``getattr`` strings) of :data:`PLATFORM_NAMES`, ``os.<one of
    PLATFORM_OS>``, ``sys.platform``, paths under ``/proc/``."""
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found += [(node.lineno, f"import {a.name}") for a in node.names if a.name.split(".")[0] in PLATFORM_MODULES]
        elif isinstance(node, ast.ImportFrom) and not node.level and (node.module or "").split(".")[0] in PLATFORM_MODULES:
            found.append((node.lineno, f"from {node.module} import"))
        elif isinstance(node, ast.ImportFrom) and node.module == "os":
            found += [(node.lineno, f"from os import {a.name}") for a in node.names
                      if a.name in PLATFORM_NAMES | PLATFORM_OS]
        elif isinstance(node, ast.Attribute):
            base = node.value.id if isinstance(node.value, ast.Name) else ""
            if node.attr in PLATFORM_NAMES or (base == "os" and node.attr in PLATFORM_OS) \
                    or (base == "sys" and node.attr == "platform"):
                found.append((node.lineno, ast.unparse(node)))
        elif isinstance(node, ast.Constant) and isinstance(node.value, str):
            if node.value in PLATFORM_NAMES or node.value.startswith("/proc/"):
                found.append((node.lineno, repr(node.value)))
    return sorted(found)


def test_the_platform_check_finds_each_kind_of_use():
    code = ("import fcntl\nfrom ctypes import CDLL\nos.posix_fallocate(fd, 0, 1)\ngetattr(os, 'O_DIRECT', 0)\n"
            "os.kill(1, 0)\nsys.platform\nopen('/proc/meminfo')\nlib.mallopt(1, 2)\n"
            "'os.statvfs(path) in a docstring'\np.kill()\nx.name\nos.pread(fd, 1, 0)\n")
    assert [line for line, _ in platform_uses(ast.parse(code))] == [1, 2, 3, 4, 5, 6, 7, 8]


def test_operating_system_calls_only_in_the_platform_module():
    """Every call that depends on the operating system is made in needlecli/platform.py, with its capability
    check and its fallback (issue 24): no other module uses those names."""
    wrong = [f"{path.relative_to(PKG.parent)}:{line}: {what}" for path in sorted(PKG.rglob("*.py"))
             if path != PKG / "platform.py" for line, what in platform_uses(ast.parse(path.read_text()))]
    assert not wrong, "operating-system-specific calls outside needlecli/platform.py:\n" + "\n".join(wrong)
