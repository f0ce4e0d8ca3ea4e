"""Where the compiled kernels are cached on disk, what is in the cache, and how long compiling took here.

Light: the standard library only (numba is neither imported nor needed), so that a command can ask
whether its kernels are compiled -- and take the numpy path without importing numba when they are not
(:func:`needlecli.kernels.dispatch.twin`).

The directory is ``$NEEDLECLI_KERNEL_CACHE`` if set, else ``$NUMBA_CACHE_DIR/needlecli`` if that is set,
else ``~/.cache/needlecli/numba`` (``$XDG_CACHE_HOME`` respected), and inside it a folder named after a
hash of the kernel sources and numba's version (:func:`cache_dir`): an edit of a kernel or another numba
starts an empty cache, and an installed package and an editable checkout each find their own. On a
cluster the root may be on shared storage (a network file system): saves and compilations are locked
per function (:mod:`needlecli.kernels._patch_cache_lock`), so that the workers of every node compile
each kernel once.

Beside numba's files the folder holds two of needlecli's own:

``needlecli-compiling.lock``
    held (an exclusive lock) by a process compiling this folder's kernels in the background for the
    next run (:func:`needlecli.kernels.compile_in_background`);
``needlecli-unused.json``
    the entry kernels a background compilation's job asked for (their twins) but never called (a twin
    that does not cover the configuration: a UKF with a nonlinear channel): not taken as missing, so
    that such a configuration is not taken for a cold cache at every run;
``needlecli-compile-seconds.json`` (in the root, shared by every install)
    how long each entry kernel took to compile on this machine (written by every compilation), from
    which a command that must wait says for how long, and the next install's estimate is this machine's.
"""

from __future__ import annotations

import contextlib
import functools
import hashlib
import json
import os
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
LOCK_NAME = "needlecli-compiling.lock"
SECONDS_NAME = "needlecli-compile-seconds.json"
UNUSED_NAME = "needlecli-unused.json"


@functools.lru_cache(maxsize=1)
def numba_version() -> str:
    """numba's version as installed (read from its metadata, numba not imported); ``none`` without it."""
    from importlib import metadata

    try:
        return metadata.version("numba")
    except metadata.PackageNotFoundError:
        return "none"


def source_hash() -> str:
    """A hash of every kernel module's source (and numba's version)."""
    h = hashlib.sha256(numba_version().encode())
    for p in sorted(HERE.glob("*.py")):
        h.update(p.name.encode())
        h.update(p.read_bytes())
    return h.hexdigest()[:16]


def cache_root() -> Path:
    """The cache's root, from the environment (see the module docstring)."""
    if os.environ.get("NEEDLECLI_KERNEL_CACHE"):
        return Path(os.environ["NEEDLECLI_KERNEL_CACHE"])
    if os.environ.get("NUMBA_CACHE_DIR"):
        return Path(os.environ["NUMBA_CACHE_DIR"]) / "needlecli"
    base = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache")
    return base / "needlecli" / "numba"


_HASH: list[str] = []


def cache_dir() -> Path:
    """The folder of this install's compiled kernels (the root's environment read at each call; the
    sources' hash once per process)."""
    if not _HASH:
        _HASH.append(source_hash())
    return cache_root() / _HASH[0]


_READY: set[tuple[str, str, str]] = set()


def cached(entry: tuple[str, str]) -> bool:
    """Whether the cache holds the compiled code of ``entry``, a ``(module, function)`` pair of
    :mod:`needlecli.kernels` (``("ukf", "run")``): numba's index file of that function. Once seen, it
    stays so for the process."""
    d = cache_dir()
    key = (str(d), *entry)
    if key in _READY:
        return True
    module, function = entry
    if d.is_dir() and any(d.rglob(f"{module}.{function}-*.nbi")):
        _READY.add(key)
        return True
    return False


def lock_path() -> Path:
    return cache_dir() / LOCK_NAME


# ---------------------------------------------------------------------------------------------- compile times
def recorded_seconds() -> dict[str, float]:
    """``{"module.function": seconds}`` of the compilations recorded on this machine (any install)."""
    try:
        doc = json.loads((cache_root() / SECONDS_NAME).read_text(encoding="utf-8"))
        return {str(k): float(v) for k, v in doc.items()} if isinstance(doc, dict) else {}
    except (OSError, ValueError, TypeError):
        return {}


def record_seconds(name: str, seconds: float) -> None:
    """Add one compilation's duration to the record (a lost update costs only an estimate)."""
    from needlecli.platform import file_lock

    root = cache_root()
    with contextlib.suppress(OSError):
        root.mkdir(parents=True, exist_ok=True)
        path = root / SECONDS_NAME
        with file_lock(str(path) + ".lock"):
            doc = recorded_seconds()
            doc[name] = round(float(seconds), 2)
            tmp = path.with_name(f".{path.name}.{os.getpid()}.{time.monotonic_ns()}")
            tmp.write_text(json.dumps(doc, indent=1, sort_keys=True) + "\n", encoding="utf-8")
            os.replace(tmp, path)


# ---------------------------------------------------------------------------------------------- asked for, not used
def unused() -> set[tuple[str, str]]:
    """The entries recorded as asked for but not compiled by a finished background compilation."""
    try:
        doc = json.loads((cache_dir() / UNUSED_NAME).read_text(encoding="utf-8"))
        return {tuple(e.split(".", 1)) for e in doc if isinstance(e, str) and "." in e}
    except (OSError, ValueError, TypeError):
        return set()


def record_unused(entries) -> None:
    """Add ``entries`` (``(module, function)`` pairs) to the record of those not used (see the docstring)."""
    from needlecli.platform import file_lock

    names = {f"{m}.{f}" for m, f in entries}
    if not names:
        return
    with contextlib.suppress(OSError):
        path = cache_dir() / UNUSED_NAME
        with file_lock(str(path) + ".lock"):
            known = {f"{m}.{f}" for m, f in unused()}
            tmp = path.with_name(f".{path.name}.{os.getpid()}.{time.monotonic_ns()}")
            tmp.write_text(json.dumps(sorted(known | names), indent=1) + "\n", encoding="utf-8")
            os.replace(tmp, path)
