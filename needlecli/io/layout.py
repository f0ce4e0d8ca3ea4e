"""The documented structure of the files this tool reads (docs/reference/: results-file.md,
fit-file.md, log-file.md), checked once when a file is opened, before anything is read from it.

A layout is a tree of :class:`G` (groups) and :class:`D` (datasets) with their attributes (:class:`A`).
Shapes are written with symbols (``("N", "T", "n")``): the first dataset or attribute that has a symbol
binds it (``/time`` binds ``T``, the names of ``/truth`` bind ``n``), every later one must agree; symbols
bound inside one member of a ``"*"`` group (one sensor, one observer) stay local to it. Checked:

- the objects: a group where a group is documented, a dataset where a dataset is; required members
  present; no soft or external links and no object reached twice (a results file holds neither: a
  soft-link cycle or a dangling external link is refused, never followed); nesting at most
  :data:`MAX_DEPTH` deep;
- datasets: their type (numbers, integers, booleans, text) and shape;
- attributes: present, of their type (text, integer, number, a list of names of a given length);
- a few values that other arrays point with: ``/time`` finite and increasing, sample and covariance
  indices inside ``/time``.

The first problem is a :class:`~needlecli.errors.DataError` naming the file and the HDF5 path, in one
line: ``r.h5: [/truth/state] has shape (3, 10), expected (N, T, n) = (3, 11, 6)``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from needlecli.errors import DataError, shown

MAX_DEPTH = 8
_KINDS = {"float": "fiub", "num": "fiub", "int": "iu", "bool": "b", "str": "OSU", "any": None}
_KIND_WORDS = {"float": "numbers", "num": "numbers", "int": "integers", "bool": "true/false values", "str": "text"}


@dataclass(frozen=True)
class A:
    """An attribute: ``kind`` str | int | num | bool | strs (a list of names, ``length`` a symbol) | any."""

    kind: str
    length: str | None = None
    optional: bool = False


@dataclass(frozen=True)
class D:
    """A dataset of ``kind`` (float, int, bool, str, num, any) and one of ``shapes`` (tuples of symbols,
    numbers, ``"*"`` for any length); ``index`` names the symbol its values index into (``"T"``)."""

    kind: str
    shapes: tuple = ()
    optional: bool = False
    attrs: dict = field(default_factory=dict)
    index: str | None = None
    increasing: bool = False


@dataclass(frozen=True)
class G:
    """A group: its members (``"*"``: every other member, each one checked in its own scope) and
    attributes; ``open`` groups may hold members the layout does not name (an observer's extras)."""

    members: dict = field(default_factory=dict)
    attrs: dict = field(default_factory=dict)
    optional: bool = False
    open: bool = True


def _s(*shapes):
    return tuple(tuple(s) for s in shapes)


NAMES = {"names": A("strs", "n"), "units": A("strs", "n", optional=True)}

RESULTS = G(attrs={
    "format": A("int"), "config": A("str"), "seed": A("int", optional=True), "name": A("str", optional=True),
    "model": A("str", optional=True), "length_unit": A("str", optional=True), "runs": A("int", optional=True),
    "source": A("str", optional=True), "truth_kind": A("str", optional=True), "dt": A("num", optional=True),
}, members={
    "time": D("float", _s(("T",)), increasing=True),
    "truth": G(attrs={**NAMES, "angles": A("strs", optional=True)}, members={
        "state": D("float", _s(("N", "T", "n"))),
        "status": D("str", _s(("N",))),
        "reason": D("str", _s(("N",))),
        "event_time": D("float", _s(("N",)), optional=True),
        "end_time": D("float", _s(("N",)), optional=True),
        "trial_id": D("str", _s(("N",)), optional=True),
        "param_case": D("int", _s(("N",)), optional=True),
        "interfaces": D("float", _s(("*",)), optional=True),
        "params": G(optional=True, open=False, members={"*": D("float", _s(("N", "T"), ("N",)))}),
    }),
    "depth": D("float", _s(("T",), ("N", "T"))),
    "inputs": G(optional=True, open=False, members={
        "case": D("int", _s(("N",)), optional=True),
        "*": D("float", _s(("N", "T"), ("N", "T", "*"))),
    }),
    "measurements": G(optional=True, open=False, members={"*": G(attrs={
        "names": A("strs", "m"), "units": A("strs", "m", optional=True), "type": A("str", optional=True),
    }, members={
        "t": D("float", _s(("M",))),
        "t_available": D("float", _s(("M",)), optional=True),
        "index": D("int", _s(("M",)), index="T"),
        "value": D("float", _s(("N", "M", "m"))),
        "valid": D("bool", _s(("N", "M"))),
        "sigma": D("float", _s(("N", "M", "m")), optional=True),
        "t_original": D("float", _s(("N", "M")), optional=True),
    })}),
    "estimates": G(optional=True, open=False, members={"*": G(attrs={
        "names": A("strs", "k"), "units": A("strs", "k", optional=True), "angles": A("strs", optional=True),
        "type": A("str", optional=True),
    }, members={
        "state": D("float", _s(("N", "T", "k"))),
        "status": D("str", _s(("N",))),
        "reason": D("str", _s(("N",))),
        "cov_index": D("int", _s(("C",)), optional=True, index="T"),
        "cov": D("float", _s(("N", "C", "k", "k"), ("N", "C", "k")), optional=True),
    })}),
    "control": G(optional=True, open=False, members={"*": G(members={
        "command": D("float", _s(("N", "T")), optional=True),
    })}),
    # needle compare only: what the comparison decided per observer (K observers run, S skipped)
    "compare": G(optional=True, attrs={"start": A("str", optional=True), "prediction_fraction": A("num", optional=True),
                                      "sensors": A("strs", optional=True)}, members={
        "observer": D("str", _s(("K",))),
        "type": D("str", _s(("K",))),
        "settings": D("str", _s(("K",))),
        "start": D("str", _s(("K",))),
        "causal": D("bool", _s(("K",))),
        "model": D("str", _s(("K",)), optional=True),
        "seconds": D("float", _s(("K",))),
        "error": D("str", _s(("K",))),
        "skipped": G(optional=True, open=False, members={
            "observer": D("str", _s(("S",))), "type": D("str", _s(("S",))), "reason": D("str", _s(("S",))),
        }),
    }),
    # needle crossval only (its folds' results files): the fold, and each held-out trial's group
    "crossval": G(optional=True, attrs={"fold": A("int"), "model": A("str"), "train": A("strs"), "test": A("strs"),
                                       "tuned": A("strs", optional=True), "group_by": A("str", optional=True)}, members={
        "group": D("str", _s(("*",)), optional=True),  # in the order of attribute test
        "constants": G(optional=True, attrs={"trials_ok": A("int"), "trials": A("int")}, members={
            "name": D("str", _s(("P",))), "median": D("float", _s(("P",))), "se": D("float", _s(("P",))),
        }),
        # predictions from the held-out trials' own poses, per pose source (truth or an observer)
        "from_pose": G(optional=True, open=False, members={"*": G(attrs={
            "depths": A("any"), "pose_from": A("str"), "skipped": A("any", optional=True),
        }, members={
            "start_index": D("int", _s(("N", "D"))),
            "index": D("int", _s(("K",)), index="T"),
            "*": G(attrs={"names": A("strs", "k", optional=True), "units": A("strs", "k", optional=True)}, members={
                "state": D("float", _s(("N", "D", "K", "k")), optional=True),
                "status": D("str", _s(("N", "D"))),
                "reason": D("str", _s(("N", "D"))),
            }),
        })}),
    }),
})

FIT = G(attrs={
    "format": A("str"), "version": A("int"), "config": A("str"), "name": A("str", optional=True),
    "model": A("str", optional=True), "models": A("strs", optional=True), "runs": A("int", optional=True),
}, members={
    "time": D("float", _s(("T",)), increasing=True),
    "inputs": G(optional=True, open=False, members={
        "case": D("int", _s(("N",)), optional=True),
        "*": D("float", _s(("N", "T"), ("N", "T", "*"))),
    }),
    "truth": G(optional=True, attrs={**NAMES}, members={
        "state": D("float", _s(("N", "T", "n")), optional=True),
        "status": D("str", _s(("N",)), optional=True),
        "reason": D("str", _s(("N",)), optional=True),
        "trial_id": D("str", _s(("N",)), optional=True),
        "param_case": D("int", _s(("N",)), optional=True),
        "params": G(optional=True, open=False, members={"*": D("float", _s(("N",), ("N", "T")))}),
    }),
    "measurements": G(optional=True, open=False, members={"*": G(attrs={"names": A("strs", "m")}, members={
        "t": D("float", _s(("M",))),
        "index": D("int", _s(("M",)), index="T"),
        "value": D("float", _s(("N", "M", "m"))),
        "valid": D("bool", _s(("N", "M"))),
    })}),
    "fit": G(open=False, members={"*": G(attrs={"names": A("strs", "k"), "units": A("strs", "k", optional=True)},
                                         members={
        "ticks": D("int", _s(("K",)), index="T"),
        "state": D("float", _s(("N", "K", "k"))),
        "var": D("float", _s(("N", "K", "k")), optional=True),
        "cov": D("float", _s(("N", "K", "k", "k")), optional=True),
        "filtered": D("float", _s(("N", "K", "k")), optional=True),
        "ekf_state": D("float", _s(("N", "K", "k")), optional=True),
        "x0": D("float", _s(("N", "k"))),
        "Q": D("float", _s(("N", "k", "k"))),
        "status": D("str", _s(("N",))),
        "reason": D("str", _s(("N",))),
        "iterations": D("int", _s(("N",)), optional=True),
        "constant": G(optional=True, open=False, members={"*": D("float", _s(("N",)))}),
        "R": G(optional=True, open=False, members={"*": D("float", _s(("N", "*", "*"), ("*", "*")))}),
        "history": G(optional=True, open=False, members={"*": D("num", _s(("N", "I"), ("N", "I", "*")))}),
        # what the data identify (docs/reference/fit-file.md); its recovery and design groups are additions
        "identifiability": G(optional=True, attrs={"quantities": A("strs", "d"), "group_labels": A("strs", "G", optional=True)},
                             members={
            "estimate": D("float", _s(("N", "d"))),
            "verdict": D("str", _s(("N", "d"))),
            "used": D("bool", _s(("N",))),
            "truth": D("float", _s(("N", "d")), optional=True),
            "group": D("int", _s(("N",)), optional=True),
            "group_verdict": D("str", _s(("G", "d")), optional=True),
            "group_reason": D("str", _s(("G", "d")), optional=True),
            "group_z": D("float", _s(("G", "d")), optional=True),
        }),
    })}),
})

LOG = G(attrs={"format": A("str"), "version": A("int")}, members={
    "trials": G(open=False, members={"*": G(members={
        "inputs": G(optional=True, open=False, members={"*": G(attrs={"unit": A("str", optional=True),
                                                                       "kind": A("str", optional=True)}, members={
            "t": D("float", _s(("K",))),
            "value": D("float", _s(("K",), ("K", "*"))),
        })}),
        "sensors": G(open=False, members={"*": G(attrs={
            "names": A("strs", "m", optional=True), "units": A("strs", "m", optional=True),
            "sensor": A("str", optional=True)}, members={
            "t": D("float", _s(("M",))),
            "value": D("float", _s(("M",), ("M", "m"))),
            "valid": D("bool", _s(("M",)), optional=True),
            "sigma": D("float", _s(("M",), ("M", "m")), optional=True),
        })}),
        "truth": G(optional=True, attrs={"names": A("strs", "n"), "units": A("strs", optional=True)}, members={
            "t": D("float", _s(("L",))),
            "state": D("float", _s(("L", "n"))),
        }),
    })}),
})


# ---------------------------------------------------------------------------------------------- checking
class _Check:
    def __init__(self, path: Path) -> None:
        self.path = path
        self.seen: set = set()

    def fail(self, where: str, msg: str) -> DataError:
        return DataError(f"{shown(self.path)}: [{where or '/'}] {' '.join(msg.split())}")

    # ---- attributes
    def attrs(self, obj, spec: dict, where: str, env: dict) -> None:
        try:
            names = set(obj.attrs.keys())
        except (OSError, RuntimeError, KeyError) as e:
            raise self.fail(where, f"its attributes cannot be read ({_reason(e)})") from None
        for name, a in spec.items():
            if name not in names:
                if a.optional:
                    continue
                raise self.fail(where, f"missing attribute {name!r}")
            try:
                v = obj.attrs[name]
            except (OSError, RuntimeError, TypeError, ValueError) as e:
                raise self.fail(where, f"attribute {name!r} cannot be read ({_reason(e)})") from None
            self.attr_value(v, a, f"{where or '/'} attribute {name}", env)

    def attr_value(self, v, a: A, where: str, env: dict) -> None:
        v = _decode(v)
        if a.kind == "any":
            return
        if a.kind == "strs":
            items = [v] if isinstance(v, str) else (list(v) if isinstance(v, np.ndarray) and v.ndim == 1 else None)
            if items is None or not all(isinstance(x, str) for x in items):
                raise self.fail(where, f"should be a list of names, is {_what(v)}")
            if a.length:
                self.bind(env, a.length, len(items), where, f"{len(items)} names")
            return
        scalar = v.item() if isinstance(v, np.ndarray) and v.shape == () else v
        if isinstance(scalar, np.generic):
            scalar = scalar.item()
        ok = {"str": isinstance(scalar, str),
              "int": isinstance(scalar, int) and not isinstance(scalar, bool),
              "num": isinstance(scalar, (int, float)) and not isinstance(scalar, bool),
              "bool": isinstance(scalar, bool)}[a.kind]
        if not ok:
            want = {"str": "a text", "int": "an integer", "num": "a number", "bool": "true or false"}[a.kind]
            raise self.fail(where, f"should be {want}, is {_what(v)}")

    # ---- symbols
    def bind(self, env: dict, sym: str, n: int, where: str, what: str) -> None:
        if sym in env and env[sym][0] != n:
            raise self.fail(where, f"has {what}, but {env[sym][1]} give {sym} = {env[sym][0]}")
        env.setdefault(sym, (n, where))

    # ---- objects
    def member(self, g: h5py.Group, name: str, where: str):
        """The object ``name`` of ``g`` after checking its link (hard links only)."""
        try:
            link = g.get(name, getlink=True)
        except (OSError, RuntimeError, KeyError, ValueError) as e:
            raise self.fail(where, f"cannot be read ({_reason(e)})") from None
        if isinstance(link, h5py.SoftLink):
            raise self.fail(where, f"is a soft link to {link.path!r}; these files hold no links")
        if isinstance(link, h5py.ExternalLink):
            raise self.fail(where, f"is an external link to {link.filename}:{link.path}; these files hold no links")
        try:
            obj = g[name]
        except (OSError, RuntimeError, KeyError, ValueError) as e:
            raise self.fail(where, f"cannot be read ({_reason(e)})") from None
        key = _ident(obj)
        if key is not None:
            if key in self.seen:
                raise self.fail(where, "is the same object as another path of the file (a hard link); "
                                "these files hold no links")
            self.seen.add(key)
        return obj

    def group(self, g, spec: G, where: str, env: dict, depth: int) -> None:
        if depth > MAX_DEPTH:
            raise self.fail(where, f"groups nested deeper than {MAX_DEPTH} levels")
        self.attrs(g, spec.attrs, where, env)
        try:
            names = list(g.keys())
        except (OSError, RuntimeError, KeyError) as e:
            raise self.fail(where, f"cannot be listed ({_reason(e)})") from None
        named = [k for k in spec.members if k != "*"]
        for k in named:
            sub = spec.members[k]
            if k not in names:
                if not sub.optional:
                    kind = "group" if isinstance(sub, G) else "dataset"
                    raise self.fail(where, f"missing {kind} {k!r}")
                continue
            self.node(g, k, sub, _join(where, k), env, depth)
        rest = [k for k in names if k not in spec.members]
        star = spec.members.get("*")
        for k in rest:
            if star is not None:
                self.node(g, k, star, _join(where, k), dict(env), depth)
            elif spec.open:
                self.free(g, k, _join(where, k), depth)
            else:
                raise self.fail(_join(where, k), "is not part of the documented layout")

    def node(self, g, name: str, spec, where: str, env: dict, depth: int) -> None:
        obj = self.member(g, name, where)
        if isinstance(spec, G):
            if not isinstance(obj, h5py.Group):
                raise self.fail(where, f"is a {_kind(obj)}, expected a group")
            self.group(obj, spec, where, env, depth + 1)
        else:
            if not isinstance(obj, h5py.Dataset):
                raise self.fail(where, f"is a {_kind(obj)}, expected a dataset")
            self.dataset(obj, spec, where, env)

    def free(self, g, name: str, where: str, depth: int) -> None:
        """A member the layout does not describe: walked for links and depth only."""
        obj = self.member(g, name, where)
        if isinstance(obj, h5py.Group):
            if depth + 1 > MAX_DEPTH:
                raise self.fail(where, f"groups nested deeper than {MAX_DEPTH} levels")
            for k in list(obj.keys()):
                self.free(obj, k, _join(where, k), depth + 1)
        elif not isinstance(obj, h5py.Dataset):
            raise self.fail(where, f"is a {_kind(obj)}, expected a group or a dataset")

    def dataset(self, ds: h5py.Dataset, spec: D, where: str, env: dict) -> None:
        try:
            dtype, shape = ds.dtype, tuple(ds.shape) if ds.shape is not None else None
        except (OSError, RuntimeError, TypeError, ValueError) as e:
            raise self.fail(where, f"cannot be read ({_reason(e)})") from None
        kinds = _KINDS[spec.kind]
        if kinds is not None:
            kind = dtype.kind
            if kind == "O" and h5py.check_string_dtype(dtype) is None:
                kind = "?"
            if kind not in kinds or (spec.kind != "str" and dtype.kind in "OSU"):
                raise self.fail(where, f"holds {_dtype_words(dtype)}, expected {_KIND_WORDS[spec.kind]}")
        if shape is None:
            raise self.fail(where, "holds no data (an empty dataset)")
        if spec.shapes:
            self.shape(shape, spec.shapes, where, env)
        self.attrs(ds, spec.attrs, where, env)
        if spec.increasing or spec.index:
            self.values(ds, spec, where, env)

    def shape(self, shape: tuple, shapes: tuple, where: str, env: dict) -> None:
        errors = []
        for want in shapes:
            if len(want) != len(shape):
                errors.append(want)
                continue
            trial = dict(env)
            ok = True
            for sym, n in zip(want, shape):
                if sym == "*":
                    continue
                if isinstance(sym, int):
                    ok = ok and sym == n
                elif sym in trial and trial[sym][0] != n:
                    ok = False
                else:
                    trial.setdefault(sym, (n, where))
            if ok:
                env.update({k: v for k, v in trial.items() if k not in env})
                return
            errors.append(want)
        alts = " or ".join(_fmt_shape(w, env) for w in shapes)
        if any(len(w) == len(shape) for w in shapes):
            raise self.fail(where, f"has shape {shape}, expected {alts}")
        raise self.fail(where, f"has shape {shape} ({len(shape)} dimensions), expected {alts}")

    def values(self, ds: h5py.Dataset, spec: D, where: str, env: dict) -> None:
        try:
            v = np.asarray(ds[()])
        except (OSError, RuntimeError, TypeError, ValueError) as e:
            raise self.fail(where, f"cannot be read ({_reason(e)})") from None
        if spec.increasing:
            bad = np.nonzero(~np.isfinite(v))[0]
            if bad.size:
                raise self.fail(where, f"entry {bad[0]} is not finite ({v[bad[0]]})")
            back = np.nonzero(np.diff(v) <= 0)[0]
            if back.size:
                raise self.fail(where, f"does not increase at entry {back[0] + 1} ({v[back[0]]:.6g} -> {v[back[0] + 1]:.6g})")
        if spec.index and spec.index in env and v.size:
            n = env[spec.index][0]
            bad = np.nonzero((v < 0) | (v >= n))[0]
            if bad.size:
                raise self.fail(where, f"entry {bad[0]} is {v.flat[bad[0]]}, outside the {n} steps of /time")


def _join(where: str, name: str) -> str:
    return f"{where}/{name}" if where and where != "/" else f"/{name}"


def _ident(obj):
    try:
        return hash(obj.id)
    except (TypeError, ValueError, RuntimeError):
        return None


def _kind(obj) -> str:
    if isinstance(obj, h5py.Group):
        return "group"
    if isinstance(obj, h5py.Dataset):
        return "dataset"
    if isinstance(obj, h5py.Datatype):
        return "named data type"
    return type(obj).__name__


def _decode(v):
    if isinstance(v, bytes):
        try:
            return v.decode()
        except UnicodeDecodeError:
            return v
    if isinstance(v, np.ndarray) and v.dtype.kind in "OS":
        return np.array([x.decode(errors="replace") if isinstance(x, bytes) else x for x in v.ravel()],
                        dtype=object).reshape(v.shape)
    return v


def _what(v: Any) -> str:
    if isinstance(v, np.generic):
        v = v.item()
    if isinstance(v, str):
        return f"the text {v[:30]!r}"
    if isinstance(v, np.ndarray):
        return f"an array of shape {v.shape} ({_dtype_words(v.dtype)})" if v.ndim else f"{v.item()!r}"
    return repr(v)[:40]


def _dtype_words(dtype) -> str:
    k = dtype.kind
    if k == "f":
        return "floating-point numbers"
    if k in "iu":
        return "integers"
    if k == "b":
        return "true/false values"
    if k in "OSU":
        return "text" if k != "O" or h5py.check_string_dtype(dtype) is not None else "objects"
    if k == "V":
        return "compound or opaque records"
    return f"values of type {dtype}"


def _fmt_shape(want: tuple, env: dict) -> str:
    """``(N, T, n) = (3, 11, 6)``: the symbols, and the values of those already bound ('?' the others)."""
    def one(items) -> str:
        return "(" + ", ".join(items) + ("," if len(items) == 1 else "") + ")"

    text = one([str(s) for s in want])
    if any(isinstance(s, str) and s in env for s in want):
        text += " = " + one([str(env[s][0]) if isinstance(s, str) and s in env else "?" if isinstance(s, str) and s != "*"
                             else str(s) for s in want])
    return text


def _reason(e: BaseException) -> str:
    text = " ".join(str(e).split())
    return text[:200] or type(e).__name__


def check_layout(f: h5py.File, layout: G, path: str | Path) -> None:
    """Check an open HDF5 file against ``layout``; raise :class:`DataError` at the first problem."""
    _Check(Path(path)).group(f, layout, "", {}, 0)


def root_attribute(f: h5py.File, name: str, kind: str, path: str | Path):
    """The root attribute ``name`` of an open file (decoded; a numpy scalar as a Python one), None when
    absent; one of the wrong type (an array where a text or an integer is documented, a list ``config``)
    is a :class:`DataError` naming it: ``r.h5: [/ attribute format] should be an integer, is an array of
    shape (2,) (integers)``. ``kind``: as :class:`A`'s (``int``, ``str``, ``num``, ``any``)."""
    check = _Check(Path(path))
    try:
        if name not in f.attrs:
            return None
        v = f.attrs[name]
    except (OSError, RuntimeError, KeyError, TypeError, ValueError) as e:
        raise check.fail("/ attribute " + name, f"cannot be read ({_reason(e)})") from None
    check.attr_value(v, A(kind), f"/ attribute {name}", {})
    v = _decode(v)
    if isinstance(v, np.ndarray) and v.shape == ():
        v = v.item()
    return v.item() if isinstance(v, np.generic) else v
