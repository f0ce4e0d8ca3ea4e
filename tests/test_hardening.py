"""The hardening corpus (issue 16): bad inputs and damaged files of every class, each in one case of
``tests/hardening/<class>.yaml``, each run through the ``needle`` command and held to the promise: exit
code 2 (or what the case says), exactly one ``error:`` line on stderr naming the file and the key path or
HDF5 path, no traceback, no file and no temporary file left behind, and an earlier file at the target
unchanged.

A case::

    - id: rate_inf                          # unique in the corpus
      files:                                # made in the case's folder first (see BUILDERS)
        cfg.yaml: {config: tiny, set: {sensors.0.rate: .inf}}
      target: out.h5                        # optional: an earlier file there, which must stay as it was
      env: {NEEDLECLI_MEMORY: 1M}           # optional
      run: [simulate, "@cfg.yaml", --out, "@out.h5", --quiet]    # @name: a path in the case's folder
      expect: {file: cfg.yaml, key: sensors -> 0 -> rate, message: finite number}   # code: 2 by default

``expect`` may give ``hdf5`` (an HDF5 path in brackets) instead of ``key``, ``code`` and ``lines`` (the
lines on stderr, default 1); ``created`` lists files a successful case may make, ``warning`` what one of
its ``warning:`` lines on stderr must say; ``output`` texts the command's output must hold (stdout and stderr), ``absent`` texts it must not.

A case may also make the disk fail while the command writes: ``disk_full: k`` (the k-th file written
cannot be flushed to disk: ENOSPC, as a disk that fills up reports it), ``rename_fails: k`` (the k-th
rename of a complete file into place fails). Every case must end within :data:`PATIENCE` seconds (an input
that makes the command wait -- a named pipe with no writer -- is a failure, not a hang), and its output
must hold no control character (a name that holds one is shown escaped).
"""

from __future__ import annotations

import copy
import errno
import hashlib
import os
import re
import signal
import socket
import zipfile
from pathlib import Path

import h5py
import numpy as np
import pandas as pd
import pytest
import yaml
from typer.testing import CliRunner

from needlecli.cli.app import app
from needlecli.experiments.config.overrides import set_dotted

HERE = Path(__file__).parent / "hardening"
BASE = yaml.safe_load((HERE / "base.yaml").read_text())
CLASSES = sorted(HERE.glob("[0-9]*_*.yaml"), key=lambda p: int(p.name.split("_")[0]))
PATIENCE = 120  # s: longer is a command waiting for an input that never comes
CASES = [(p.stem, c) for p in CLASSES for c in yaml.safe_load(p.read_text())]


def invoke(args, env=None):
    return CliRunner().invoke(app, [str(a) for a in args], env=env, catch_exceptions=True)


class Waited(Exception):
    """A command still running after :data:`PATIENCE` seconds."""


def _waited(signum, frame):  # noqa: ARG001
    raise Waited(f"still running after {PATIENCE} s: waiting for an input?")


def invoke_patiently(args, env=None):
    old = signal.signal(signal.SIGALRM, _waited)
    signal.alarm(PATIENCE)
    try:
        return invoke(args, env)
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, old)


def fail_disk(monkeypatch, *, disk_full: int | None = None, rename_fails: int | None = None) -> None:
    """Make the k-th file written fail to be flushed (``disk_full``: ENOSPC) or the k-th rename into place
    fail (``rename_fails``: ENOSPC), for the one command the case runs."""
    import needlecli.io.atomic as atomic

    if disk_full:
        real_fsync, calls = atomic._fsync, [0]

        def fsync(p):
            calls[0] += 1
            if calls[0] == disk_full:
                raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(p))
            real_fsync(p)

        monkeypatch.setattr(atomic, "_fsync", fsync)
    if rename_fails:
        renames = [0]

        class Os:  # atomic's os, whose replace fails at the k-th call
            def __getattr__(self, name):
                return getattr(os, name)

            @staticmethod
            def replace(a, b):
                renames[0] += 1
                if renames[0] == rename_fails:
                    raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(b))
                os.replace(a, b)

        monkeypatch.setattr(atomic, "os", Os())


# ---------------------------------------------------------------------------------------------- good inputs
@pytest.fixture(scope="session")
def good(tmp_path_factory) -> dict[str, Path]:
    """The valid files the cases damage: a results file, its log, a fit file, a baseline, a mapping."""
    d = tmp_path_factory.mktemp("good")
    (d / "tiny.yaml").write_text(yaml.safe_dump(BASE["tiny"], sort_keys=False))
    (d / "fit.yaml").write_text(yaml.safe_dump(BASE["fit"], sort_keys=False))
    (d / "fitok.yaml").write_text(yaml.safe_dump(_edited(BASE["fit"], BASE["fitok"]), sort_keys=False))
    for args in (["simulate", d / "tiny.yaml", "--out", d / "results.h5", "--quiet"],
                 ["log", "from-results", d / "results.h5", "--out", d / "log.h5"],
                 ["fit-em", d / "fit.yaml", "--out", d / "fit.h5", "--quiet"],
                 ["fit-em", d / "fitok.yaml", "--out", d / "fitok.h5", "--quiet"],
                 ["evaluate", d / "results.h5", "--out", d / "tables", "--no-plots", "--quiet",
                  "--write-baseline", d / "baseline.yaml"]):
        r = invoke(args)
        assert r.exit_code == 0, r.output
    return {"results": d / "results.h5", "log": d / "log.h5", "fit": d / "fit.h5", "fitok": d / "fitok.h5",
            "baseline": d / "baseline.yaml"}


# ---------------------------------------------------------------------------------------------- builders
def _edited(data: dict, spec: dict) -> dict:
    data = copy.deepcopy(data)
    for k, v in (spec.get("set") or {}).items():
        set_dotted(data, k, copy.deepcopy(v), "corpus")
    for k in spec.get("del") or []:
        *head, last = k.split(".")
        cur = data
        for part in head:
            cur = cur[int(part)] if isinstance(cur, list) else cur[part]
        del cur[int(last) if isinstance(cur, list) else last]
    return data


def build_config(case_dir: Path, spec: dict, good) -> str:
    """A config of base.yaml: ``tiny``, ``replay`` (of the good log, or ``log``), ``fit``, ``fitok`` (a fit
    that converges at once), ``crossval`` (``fitok`` with an observer to tune), ``from_fit`` (its observer
    tuned by the good ``fitok`` fit file); then ``set`` and ``del`` (dotted keys)."""
    if spec["config"] in ("fitok", "crossval", "from_fit"):
        base = _edited(BASE["fit"], BASE["fitok"])
        if spec["config"] != "fitok":
            base["observers"] = copy.deepcopy(BASE[spec["config"]]["observers"])
        if spec["config"] == "from_fit":
            base.pop("fit")
            base["observers"][0]["from_fit"]["file"] = str(good["fitok"])
    else:
        base = copy.deepcopy(BASE[spec["config"]])
    if spec["config"] == "replay":
        base["source"]["logs"] = [str(case_dir / spec.get("log", "log.h5"))] if spec.get("log") else [str(good["log"])]
    return yaml.safe_dump(_paths(_edited(base, spec), case_dir), sort_keys=False)


def _generated(kind: str, n: int | None) -> bytes:
    if kind == "deep_list":
        return ("a: " + "[" * (n or 20000) + "]" * (n or 20000) + "\n").encode()
    if kind == "deep_map":
        return ("".join("  " * i + f"k{i}:\n" for i in range(n or 100)) + "  " * (n or 100) + "x: 1\n").encode()
    if kind == "big_int":
        return yaml.safe_dump(BASE["tiny"], sort_keys=False).replace("seed: 1", "seed: " + "9" * (n or 5000)).encode()
    if kind == "zeros":
        return b"\0" * (n or 4096)
    if kind == "binary":
        return bytes(np.random.default_rng(n or 0).integers(0, 256, 8192, dtype=np.uint8))
    if kind == "huge":
        return b"# " + b"x" * (17 * 2**20) + b"\n"
    if kind == "latin1":
        return "name: caf\xe9\n".encode("latin-1")
    if kind == "laughs":
        lines = ["a0: &a0 [x, x, x, x, x, x, x, x, x, x]"]
        lines += [f"a{i}: &a{i} [" + ", ".join([f"*a{i - 1}"] * 10) + "]" for i in range(1, n or 7)]
        return ("\n".join(lines) + "\n").encode()
    raise ValueError(kind)


def _path_csv(angle: float = 0.0, n: int = 41, step: float = 0.5, kappa: float = 0.01, noise: float = 0.02,
              seed: int = 1, speed: float = 2.0, q: list | None = None) -> tuple[str, float]:
    """A tracker's CSV (``t,tx,ty,tz``, mm) of a bevel-tip insertion: a circle of curvature ``kappa``
    bending toward -y, one sample per ``step`` mm at ``speed`` mm/s, started along the direction ``angle``
    degrees from +z (turned about x), with ``noise`` (mm) on each coordinate; ``q``: a quaternion ``[w, x, y,
    z]`` the tracker reports at every sample (columns ``qw,qx,qy,qz``). Returns the text and the last time."""
    s = step * np.arange(n)
    th = kappa * s
    pos = np.c_[np.zeros(n), (np.cos(th) - 1.0) / kappa, np.sin(th) / kappa]
    a = np.radians(angle)
    turn = np.array([[1.0, 0.0, 0.0], [0.0, np.cos(a), -np.sin(a)], [0.0, np.sin(a), np.cos(a)]])
    pos = pos @ turn.T + np.random.default_rng(seed).normal(0.0, noise, pos.shape)
    t = s / speed
    tail = "".join(f",{c:.9g}" for c in q) if q is not None else ""
    rows = "\n".join(f"{ti:.6g},{x:.6f},{y:.6f},{z:.6f}{tail}" for ti, (x, y, z) in zip(t, pos))
    return "t,tx,ty,tz" + (",qw,qx,qy,qz" if q is not None else "") + "\n" + rows + "\n", float(t[-1])


def _h5_value(v):
    if isinstance(v, list) and v and all(isinstance(x, str) for x in v):
        return np.array(v, dtype=h5py.string_dtype())
    return v


def damage(path: Path, ops: list) -> None:
    """Apply the damage ``ops`` of a case to an HDF5 file (see tests/hardening/5_damaged.yaml)."""
    after = []
    with h5py.File(path, "r+") as f:
        for op in ops:
            (kind, arg), = op.items()
            if kind == "delete":
                del f[arg]
            elif kind == "replace":  # [path, shape, dtype]
                p, shape, *rest = arg
                dtype = rest[0] if rest else "float"
                del f[p]
                if dtype == "str":
                    f.create_dataset(p, data=np.full(shape, "x", dtype=object), dtype=h5py.string_dtype())
                elif dtype == "compound":
                    f.create_dataset(p, shape=shape, dtype=np.dtype([("a", "f8"), ("b", "i4")]))
                else:
                    f.create_dataset(p, data=np.zeros(shape, dtype={"float": float, "int": np.int64, "bool": bool}[dtype]))
            elif kind == "group":
                del f[arg]
                f.create_group(arg)
            elif kind == "dataset":
                del f[arg]
                f.create_dataset(arg, data=np.zeros(3))
            elif kind == "softlink":
                p, target = arg
                if p in f or p in f.keys():
                    del f[p]
                f[p] = h5py.SoftLink(target)
            elif kind == "extlink":
                p, file, target = arg
                del f[p]
                f[p] = h5py.ExternalLink(file, target)
            elif kind == "hardlink":
                p, existing = arg
                f[p] = f[existing]
            elif kind == "attr":
                p, name, value = arg
                f[p].attrs[name] = _h5_value(_paths(value, path.parent))
            elif kind == "delattr":
                p, name = arg
                del f[p].attrs[name]
            elif kind == "set":  # [path, index, value]
                p, index, value = arg
                v = f[p][()]
                v.flat[index] = value
                del f[p]
                f.create_dataset(p, data=v)
            elif kind == "nest":
                p, depth = arg
                f.create_group(p + "".join(f"/g{i}" for i in range(depth)))
            elif kind == "compressed":  # rewritten in gzip-compressed chunks
                v = f[arg][()]
                del f[arg]
                f.create_dataset(arg, data=v, chunks=True, compression="gzip")
            elif kind == "datatype":
                f[arg] = np.dtype("f8")
            elif kind == "copy":  # [path, new path]: a dataset copied, its attributes too
                src, dst = arg
                f.copy(f[src], dst)
            elif kind == "texts":  # [path, [text, ...]]: a dataset of texts in place of what was there
                p, values = arg
                del f[p]
                f.create_dataset(p, data=np.array(values, dtype=object), dtype=h5py.string_dtype())
            else:
                after.append(op)
    for op in after:
        (kind, arg), = op.items()
        data = path.read_bytes()
        if kind == "truncate":
            path.write_bytes(data[: int(len(data) * arg)])
        elif kind == "corrupt_chunk":
            with h5py.File(path, "r") as f:
                info = f[arg].id.get_chunk_info(0)
                offset, size = info.byte_offset, info.size
            with path.open("r+b") as fh:
                fh.seek(offset)
                fh.write(b"\xff" * size)
        else:
            raise ValueError(kind)


def build(case_dir: Path, name: str, spec, good) -> None:
    p = case_dir / name
    p.parent.mkdir(parents=True, exist_ok=True)
    if isinstance(spec, dict) and {"fifo", "socket", "dir", "symlink"} & set(spec) and p.is_file():
        p.unlink()  # a file an earlier builder made there (a mapping's CSV) becomes this instead
    if isinstance(spec, str):
        p.write_text(spec)
    elif "config" in spec:
        p.write_text(build_config(case_dir, spec, good))
    elif "text" in spec:
        p.write_text(spec["text"])
    elif "generate" in spec:
        p.write_bytes(_generated(spec["generate"], spec.get("n")))
    elif "copy" in spec:  # results | log | fit | baseline
        p.write_bytes(good[spec["copy"]].read_bytes())
        if spec.get("damage"):
            damage(p, spec["damage"])
    elif "mapping" in spec:  # a CSV export: mapping.yaml here, the CSV files beside it
        p.write_text(yaml.safe_dump(_edited(BASE["mapping"], spec), sort_keys=False))
        for fname, text in {**BASE["csv"], **(spec.get("csv") or {})}.items():
            (p.parent / fname).write_text(text)
    elif "baseline" in spec:
        data = yaml.safe_load(good["baseline"].read_text())
        p.write_text(yaml.safe_dump(_edited(data, spec), sort_keys=False))
    elif "ultrasteer" in spec:  # a fake data set folder: one trial, files as the case gives them
        folder = p / BASE["ultrasteer"]["folder"]
        folder.mkdir(parents=True)
        k = BASE["ultrasteer"]["frames"]
        files = {"FullStateGroundTruthPos.dat": "\n".join(f"0 0 {i}" for i in range(k)),
                 "FullStateGroundTruthRs.dat": "\n".join(" ".join(["1", "0", "0", "0", "1", "0", "0", "0", "1"][j]
                                                                   for _ in range(k)) for j in range(9))}
        files.update(spec["ultrasteer"] or {})
        for fname, text in files.items():
            (folder / fname).write_text(text if text.endswith("\n") else text + "\n")
    elif "yaml" in spec:  # a YAML file given in full (@name: a path in the case's folder), with set/del edits
        p.write_text(yaml.safe_dump(_paths(_edited(spec["yaml"], spec), case_dir), sort_keys=False))
    elif "imported" in spec:  # a log imported from a tracker's path (see _path_csv) by BASE's mapping
        src = case_dir / f".{name}.exports"
        src.mkdir()
        (src / "mapping.yaml").write_text(yaml.safe_dump(_edited(BASE["mapping"], spec["imported"]), sort_keys=False))
        path, end = _path_csv(**{k: v for k, v in spec["imported"].items() if k not in ("set", "del")})
        (src / "us.csv").write_text(path)
        (src / "robot.csv").write_text(f"t,speed\n0,2\n{end:g},2\n")
        r = invoke(["log", "import-csv", src / "mapping.yaml", "--out", p])
        assert r.exit_code == 0, r.output
    elif "dir" in spec:
        p.mkdir(exist_ok=True)
    elif "symlink" in spec:  # to a name in the case's folder (itself: a loop), or an absolute path (/dev/null)
        p.symlink_to(case_dir / spec["symlink"])
    elif "fifo" in spec:  # a named pipe nobody writes to
        os.mkfifo(p)
    elif "socket" in spec:  # a Unix socket's file (the socket itself closed)
        with socket.socket(socket.AF_UNIX) as sock:
            sock.bind(str(p))
    elif "zip" in spec:  # a zip archive holding a copy of a good file (or a text)
        with zipfile.ZipFile(p, "w") as z:
            z.writestr("inside", good[spec["zip"]].read_bytes() if spec["zip"] in good else spec["zip"])
    elif "hdf5" in spec:  # an HDF5 file of another program: datasets and attributes of its own
        with h5py.File(p, "w") as f:
            for k, v in (spec["hdf5"] or {"data": [1.0, 2.0]}).items():
                if k.startswith("@"):
                    f.attrs[k[1:]] = _h5_value(v)
                else:
                    f[k] = np.asarray(v)
    else:
        raise ValueError(f"unknown builder {spec}")


def _arg(a, case_dir: Path) -> str:
    """``@name``: ``name`` in the case's folder; ``%c300rest``: 300 times ``c``, then ``rest``, there."""
    if isinstance(a, str) and a.startswith("@"):
        return str(case_dir / a[1:])
    m = re.fullmatch(r"%(.)(\d+)(.*)", a) if isinstance(a, str) else None
    if m:
        return str(case_dir / (m[1] * int(m[2]) + m[3]))
    return str(a)


def _paths(v, case_dir: Path):
    if isinstance(v, dict):
        return {k: _paths(x, case_dir) for k, x in v.items()}
    if isinstance(v, list):
        return [_paths(x, case_dir) for x in v]
    return _arg(v, case_dir) if isinstance(v, str) and v.startswith("@") else v


def _snapshot(root: Path) -> dict[str, str]:
    out = {}
    for p in sorted(root.rglob("*")):
        rel = str(p.relative_to(root))
        if p.is_symlink():
            out[rel] = "link"
        elif p.is_file():
            out[rel] = hashlib.sha256(p.read_bytes()).hexdigest()
        else:
            out[rel] = "dir"
    return out


# ---------------------------------------------------------------------------------------------- the corpus
def test_corpus_is_large_and_covers_every_class():
    ids = [c["id"] for _, c in CASES]
    assert len(ids) == len(set(ids)), "case ids must be unique"
    per_class = {}
    for cls, _ in CASES:
        per_class[cls] = per_class.get(cls, 0) + 1
    assert len(CASES) >= 150, per_class
    assert {c.split("_")[0] for c in per_class} >= {"1", "2", "3", "4", "5", "6", "8", "9", "10", "11"}, per_class
    assert all(n >= 10 for n in per_class.values()), per_class


@pytest.mark.parametrize("cls, case", CASES, ids=[f"{cls.split('_')[0]}-{c['id']}" for cls, c in CASES])
def test_case(cls, case, good, tmp_path, monkeypatch):
    case_dir = tmp_path / "case"
    case_dir.mkdir()
    for name, spec in (case.get("files") or {}).items():
        build(case_dir, name, spec, good)
    earlier = None
    if case.get("target"):
        t = case_dir / case["target"]
        t.parent.mkdir(parents=True, exist_ok=True)
        t.write_bytes(b"an earlier file: must stay as it is\n")
        earlier = t.read_bytes()
    before = _snapshot(case_dir)
    env = {k: str(v) for k, v in (case.get("env") or {}).items()}
    fail_disk(monkeypatch, disk_full=case.get("disk_full"), rename_fails=case.get("rename_fails"))
    result = invoke_patiently([_arg(a, case_dir) for a in case["run"]], env=env or None)
    exp = case["expect"]
    out = result.output
    assert not isinstance(result.exception, Waited), result.exception
    assert "Traceback" not in out, out
    raw = sorted({c for c in out if not c.isprintable() and c != "\n"})
    assert not raw, f"control characters {raw} in the output: {out!r}"
    for sub in exp.get("output", []):
        assert sub in out, f"{sub!r} not in the output: {out!r}"
    for sub in exp.get("absent", []):
        assert sub not in out, f"{sub!r} in the output: {out!r}"
    assert result.exit_code == exp.get("code", 2), (result.exit_code, out, result.exception)
    assert isinstance(result.exception, SystemExit) or result.exception is None, repr(result.exception)
    err = [ln for ln in result.stderr.splitlines() if ln.strip()]
    if exp.get("code", 2) == 2:
        lines = [ln for ln in err if ln.startswith("error: ")]
        assert len(lines) == 1 and len(err) == exp.get("lines", 1), result.stderr
        line = lines[0]
        if os.environ.get("CORPUS_SHOW"):  # CORPUS_SHOW=1 pytest -s tests/test_hardening.py: what users see
            print(f"\n{case['id']}: {line}")
        if exp.get("file"):
            assert exp["file"] in line, f"file {exp['file']!r} not named: {line}"
        if exp.get("key"):
            assert f"[{exp['key']}]" in line, f"key path [{exp['key']}] not in {line!r}"
        if exp.get("hdf5"):  # the HDF5 path in brackets, alone or with an attribute's name
            assert re.search(r"\[" + re.escape(exp["hdf5"]) + r"(\]| attribute )", line), \
                f"HDF5 path [{exp['hdf5']}] not in {line!r}"
        for sub in np.atleast_1d(exp.get("message", [])):
            assert str(sub) in line, f"{sub!r} not in {line!r}"
        for jargon in ("Value error", "union_tag", "function-after", "[key]", "Errno"):
            assert jargon not in line, line
    for sub in np.atleast_1d(exp.get("warning", [])):  # what a command that succeeds must warn about
        assert any(ln.startswith("warning: ") and str(sub) in ln for ln in err), f"no warning {sub!r}: {result.stderr}"
    after = _snapshot(case_dir)
    made = sorted(set(after) - set(before))
    allowed = [str(Path(c)) for c in exp.get("created", [])]
    made = [m for m in made if not any(m == a or m.startswith(a + os.sep) for a in allowed)]
    assert made == [], f"left behind: {made}"
    assert not [k for k in after if k.endswith(".needle-tmp")], after
    changed = [k for k in before if after.get(k) != before[k]]
    assert changed == [], f"changed: {changed}"
    if earlier is not None:
        assert (case_dir / case["target"]).read_bytes() == earlier
    for extra in exp.get("outside", []):  # a path outside the case folder that must not appear
        assert not Path(extra.replace("@", str(case_dir))).exists()


# ---------------------------------------------------------------------------------------------- what is written
def test_csv_units_follow_their_columns(tmp_path):
    """``units`` lists one unit per column of ``columns`` in their order, whatever the sensor's channel
    order: z in metres is converted, x and y in mm are not."""
    build(tmp_path, "map/mapping.yaml", {"mapping": True, "set": {"sensors.us.columns": {"z": "tz", "x": "tx", "y": "ty"},
                                                                   "sensors.us.units": ["m", "mm", "mm"]}}, None)
    (tmp_path / "map" / "us.csv").write_text("t,tx,ty,tz\n0,1,2,3\n1,1,2,4\n")
    r = invoke(["log", "import-csv", tmp_path / "map" / "mapping.yaml", "--out", tmp_path / "l.h5"])
    assert r.exit_code == 0, r.output
    from needlecli.io.logs import read_log

    s = read_log(tmp_path / "l.h5").trials[0].sensors["us"]
    assert s.names == ("x", "y", "z")
    assert np.allclose(s.value, [[1, 2, 3000], [1, 2, 4000]])


def test_output_names_never_leave_the_folder(good, tmp_path):
    """A results file whose ``name`` is a path: its tables go to --out under the file's own stem."""
    r = tmp_path / "r.h5"
    r.write_bytes(good["results"].read_bytes())
    with h5py.File(r, "r+") as f:
        f.attrs["name"] = str(tmp_path / "elsewhere" / "evil")
    res = invoke(["evaluate", r, "--out", tmp_path / "tables", "--no-plots", "--quiet"])
    assert res.exit_code == 0, res.output
    assert not (tmp_path / "elsewhere").exists()
    assert sorted(p.name for p in (tmp_path / "tables").iterdir()) == sorted(
        f"r_{t}.{x}" for t in ("summary", "status") for x in ("md", "csv", "tex"))


def test_a_nan_measured_value_fails_its_cell(good):
    """A baseline cell whose measured value is NaN fails ("not finite"), never holds."""
    from needlecli.reports.baseline import compare, load_baseline
    from needlecli.reports.evaluate import evaluate_results

    baseline = load_baseline(good["baseline"])
    tables = evaluate_results(good["results"], tables=["summary", "status"])
    assert compare(tables, baseline, "tiny") == []
    cell = baseline.cells[0]
    df = tables[cell.table]
    df.loc[(df[list(cell.row)] == pd.Series(cell.row)).all(axis=1), cell.column] = np.nan
    failures = compare(tables, baseline, "tiny")
    assert [f.cell for f in failures] == [cell] and failures[0].why == "not finite"


def test_every_replay_config_has_a_baseline():
    root = Path(__file__).resolve().parents[1]
    for cfg in sorted((root / "configs" / "replay").glob("*.yaml")):
        baseline = root / "datasets" / "baselines" / f"{cfg.stem}.yaml"
        assert baseline.is_file(), f"make regress needs {baseline}"
        r = invoke(["validate", cfg])
        assert r.exit_code == 0, r.output


# ---------------------------------------------------------------------------------------------- one channel of warnings
def _warn_then(monkeypatch, error: bool):
    """evaluate's first read made to warn (Python's and numpy's warnings, a log record), then to fail."""
    import logging
    import warnings

    import needlecli.reports.evaluate as ev

    real = ev.experiment_name

    def name(path):
        warnings.warn("a library's own warning", UserWarning, stacklevel=1)
        np.mean(np.array([]))  # numpy: RuntimeWarning, mean of an empty slice
        logging.getLogger("needlecli").warning("a weakly identified fit")
        if error:
            from needlecli.errors import DataError

            raise DataError(f"{path}: [/truth] something is wrong")
        return real(path)

    monkeypatch.setattr(ev, "experiment_name", name)


@pytest.mark.parametrize("quiet", [True, False])
def test_warnings_never_come_before_the_error_line(good, tmp_path, monkeypatch, quiet):
    _warn_then(monkeypatch, error=True)
    r = invoke(["evaluate", good["results"], "--out", tmp_path / "t", "--no-plots"] + (["--quiet"] if quiet else []))
    assert r.exit_code == 2
    assert [ln for ln in r.stderr.splitlines() if ln.strip()] == [f"error: {good['results']}: [/truth] something is wrong"]


def test_warnings_after_a_command_that_succeeded_and_never_with_quiet(good, tmp_path, monkeypatch):
    _warn_then(monkeypatch, error=False)
    r = invoke(["evaluate", good["results"], "--out", tmp_path / "t", "--no-plots", "--quiet"])
    assert r.exit_code == 0 and "warning" not in r.stderr.lower(), r.stderr
    r = invoke(["evaluate", good["results"], "--out", tmp_path / "u", "--no-plots"])
    assert r.exit_code == 0, r.output
    warned = [ln for ln in r.stderr.splitlines() if ln.startswith("warning: ")]
    assert warned[0] == "warning: a library's own warning (UserWarning)", r.stderr
    assert "warning: Mean of empty slice (RuntimeWarning)" in warned and warned[-1] == "warning: a weakly identified fit"
    assert r.stderr.rstrip().endswith(warned[-1])  # after the command's own lines
