"""Every file a command reads, opened in one place and checked in three steps before anything is read:

1. **Its kind.** A regular file (a symbolic link is followed). A folder, a named pipe (FIFO), a device
   (``/dev/null``, ``/dev/zero``), a socket, a symbolic-link loop and a link to nothing are each one error
   naming the file. The file is opened without waiting (:func:`needlecli.platform.open_for_reading`), so
   that a FIFO with no writer is refused at once instead of blocking the command for ever.
2. **Its format.** An HDF5 file carries HDF5's signature (at byte 0, or 512, 1024, ... after a user
   block); a text file (YAML, CSV) is UTF-8 without NUL bytes, of a size the reader allows. A file that is
   not what it was given as is named with what it looks like instead: empty, text, a zip or gzip archive,
   an HDF5 file (and which of needlecli's: a results, fit or log file).
3. **Its layout** (:mod:`needlecli.io.layout`): checked by the reader of each kind of HDF5 file on the
   file :func:`open_hdf5` opened, attributes of the wrong type (an array ``format``, a list ``config``)
   named with their HDF5 path.

A file the command is writing itself, in its set of outputs not yet renamed into place
(:func:`needlecli.io.atomic.output_set`), is read from its complete temporary file
(:func:`~needlecli.io.atomic.staged_path`), under its own name in every message.

Errors are :class:`~needlecli.errors.DataError` ``<file>: <what is wrong>``, or what the reader's
``error`` makes of the message (a YAML file's :class:`~needlecli.errors.ConfigError`).
"""

from __future__ import annotations

import contextlib
import errno
import os
import stat
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from needlecli import platform
from needlecli.errors import DataError, NeedleError, shown
from needlecli.io.atomic import staged_path

HDF5_SIGNATURE = b"\x89HDF\r\n\x1a\n"
_SNIFF = 4096  # bytes read to tell what a file looks like

ErrorMaker = Callable[[str], NeedleError]


@dataclass(frozen=True)
class Input:
    """A file that passed the kind check: ``path`` as given (for messages), ``real`` where its content is
    (the same, or the temporary file of an output of this command's set), ``size`` in bytes."""

    path: Path
    real: Path
    size: int


def _error_for(path) -> ErrorMaker:
    return lambda message: DataError(f"{shown(path)}: {message}")


def _noun(what: str) -> str:
    return what.split(" ", 1)[1] if what.split(" ", 1)[0] in ("a", "an") else what


def check_kind(path: str | Path, what: str, *, error: ErrorMaker | None = None, missing: str | None = None) -> Input:
    """Step 1: ``path`` is a regular file that can be opened for reading (module docstring). ``what`` is
    what the command expects there (``"a results file"``), for the messages; ``missing`` the message when
    it does not exist (default ``no such <what>``)."""
    path = Path(path)
    error = error or _error_for(path)
    real = staged_path(path)
    try:
        fd = platform.open_for_reading(real)
    except OSError as e:
        raise error(_open_problem(real, e, what, missing)) from None
    try:
        st = os.fstat(fd)
    finally:
        os.close(fd)
    if not stat.S_ISREG(st.st_mode):
        raise error(f"{_kind_word(st.st_mode)}, not {what}: give a regular file")
    return Input(path, real, st.st_size)


def _open_problem(real: Path, e: OSError, what: str, missing: str | None) -> str:
    if e.errno == errno.ENOENT:
        if os.path.islink(real):
            return f"is a symbolic link to {shown(os.readlink(real))}, which does not exist"
        return missing or f"no such {_noun(what)}"
    if e.errno == errno.ELOOP:
        return "is a loop of symbolic links, not a file"
    if e.errno == errno.ENXIO:  # a socket (or a FIFO opened for writing): nothing to read
        return f"is a socket, not {what}: give a regular file"
    if e.errno == errno.EISDIR:
        return f"is a folder, not {what}"
    if e.errno in (errno.EACCES, errno.EPERM):
        return "cannot be read: permission denied"
    if e.errno == errno.ENOTDIR:
        return "cannot be read: a part of its path is a file, not a folder"
    return f"cannot be read: {' '.join((e.strerror or str(e)).split())}"


def _kind_word(mode: int) -> str:
    if stat.S_ISDIR(mode):
        return "is a folder"
    if stat.S_ISFIFO(mode):
        return "is a named pipe (FIFO)"
    if stat.S_ISCHR(mode) or stat.S_ISBLK(mode):
        return "is a device"
    if stat.S_ISSOCK(mode):
        return "is a socket"
    return "is not a regular file"


def head(inp: Input, n: int = _SNIFF) -> bytes:
    """The first ``n`` bytes of a checked input."""
    fd = platform.open_for_reading(inp.real)
    try:
        return os.read(fd, n)
    finally:
        os.close(fd)


def looks_like(inp: Input) -> str:
    """What the content of ``inp`` looks like, in words: ``"empty"``, ``"an HDF5 file"``, ``"a zip
    archive"``, ``"a gzip archive"``, ``"text"``, ``"binary data"``."""
    if inp.size == 0:
        return "empty"
    if has_hdf5_signature(inp):
        return "an HDF5 file"
    raw = head(inp)
    if raw.startswith(b"PK\x03\x04") or raw.startswith(b"PK\x05\x06"):
        return "a zip archive"
    if raw.startswith(b"\x1f\x8b"):
        return "a gzip archive"
    if b"\0" not in raw:
        with contextlib.suppress(UnicodeDecodeError):
            raw.decode("utf-8")
            return "text"
        with contextlib.suppress(UnicodeDecodeError):  # a multi-byte character cut at the end of the head
            raw[:-3].decode("utf-8")
            return "text"
    return "binary data"


def has_hdf5_signature(inp: Input) -> bool:
    """Whether HDF5's signature is where HDF5 looks for it: byte 0, 512, 1024, 2048, ..."""
    fd = platform.open_for_reading(inp.real)
    try:
        at = 0
        while at + len(HDF5_SIGNATURE) <= inp.size:
            os.lseek(fd, at, os.SEEK_SET)
            if os.read(fd, len(HDF5_SIGNATURE)) == HDF5_SIGNATURE:
                return True
            at = 512 if at == 0 else 2 * at
        return False
    finally:
        os.close(fd)


# ---------------------------------------------------------------------------------------------- HDF5
def hdf5_input(path: str | Path, what: str, *, error: ErrorMaker | None = None) -> Input:
    """Steps 1 and 2 for an HDF5 file: a regular file with HDF5's signature; else one error saying what
    the file is instead (``r.h5: is text, not an HDF5 file: not a results file``)."""
    error = error or _error_for(path)
    inp = check_kind(path, what, error=error)
    if not has_hdf5_signature(inp):
        kind = looks_like(inp)
        shown_kind = "is empty" if kind == "empty" else f"is {kind}"
        raise error(f"{shown_kind}, not an HDF5 file: not {what}")
    return inp


@contextlib.contextmanager
def open_hdf5(path: str | Path, what: str, *, error: ErrorMaker | None = None) -> Iterator:
    """Open an HDF5 input read-only after :func:`hdf5_input`; an error HDF5 meets while opening it (a
    truncated or damaged file) is one line, ``<file>: cannot read <what> (...)``. Yields the ``h5py.File``."""
    import h5py

    error = error or _error_for(path)
    inp = hdf5_input(path, what, error=error)
    try:
        f = h5py.File(inp.real, "r")
    except (OSError, ValueError, RuntimeError) as e:
        raise error(f"cannot read the {_noun(what)} ({e.__class__.__name__}: {' '.join(str(e).split())[:300]})") from None
    with f:
        yield f


def root_format(path: str | Path) -> str | None:
    """Which of needlecli's HDF5 files ``path`` is, by its root attributes, without judging it further:
    ``"results"``, ``"fit"``, ``"log"``, ``"hdf5"`` (another program's), or None when it is not a readable
    HDF5 file at all (see :func:`hdf5_input` for why)."""
    try:
        with open_hdf5(path, "an HDF5 file") as f:
            fmt = f.attrs.get("format")
            names = set(f.keys())
    except NeedleError:
        return None
    if isinstance(fmt, bytes):
        fmt = fmt.decode("utf-8", "replace")
    if isinstance(fmt, np.ndarray) and fmt.dtype.kind in "OSU":  # a damaged text format: which one it meant
        texts = {x.decode("utf-8", "replace") if isinstance(x, bytes) else str(x) for x in fmt.ravel()}
        fmt = next((t for t in ("needlecli-fit", "needlecli-log") if t in texts), fmt)
    if isinstance(fmt, str):
        return {"needlecli-fit": "fit", "needlecli-log": "log"}.get(fmt, "hdf5")
    if isinstance(fmt, (int, np.integer)) and not isinstance(fmt, bool) or (fmt is not None and "truth" in names):
        return "results"  # a results file's format is its version number
    return "hdf5"


def describe(path: str | Path) -> str:
    """What ``path`` is, in words, for a message saying it is not what a command takes: ``a results file
    (needle simulate)``, ``a log file``, ``a fit file (needle fit-em)``, ``an HDF5 file of another
    program``, ``a folder``, ``empty``, ``text``, ``a zip archive``, ..."""
    try:
        inp = check_kind(path, "a file")
    except NeedleError:
        try:
            st = os.stat(staged_path(path))
        except OSError as e:
            return {errno.ELOOP: "a loop of symbolic links"}.get(e.errno, "a file that cannot be read")
        return _kind_word(st.st_mode).removeprefix("is ")
    kind = looks_like(inp)
    if kind != "an HDF5 file":
        return kind
    return {"results": "a results file (needle simulate)", "fit": "a fit file (needle fit-em)",
            "log": "a log file", "hdf5": "an HDF5 file of another program"}.get(root_format(path) or "", kind)


# ---------------------------------------------------------------------------------------------- text
def read_text(path: str | Path, what: str, *, limit: int, error: ErrorMaker | None = None,
              missing: str | None = None, form: str = "a text file") -> str:
    """Steps 1 and 2 for a text file: a regular file of at most ``limit`` bytes, UTF-8 without NUL bytes
    (a byte-order mark is dropped). ``form`` names the format in messages (``"a YAML file"``)."""
    error = error or _error_for(path)
    inp = check_kind(path, what, error=error, missing=missing)
    fd = platform.open_for_reading(inp.real)
    try:
        raw = os.read(fd, 65536)  # binary content shows at once (an HDF5 file)
        if b"\0" not in raw and len(raw) == 65536:
            chunks = [raw]
            total = len(raw)
            while total <= limit:
                b = os.read(fd, min(1 << 20, limit + 1 - total))
                if not b:
                    break
                chunks.append(b)
                total += len(b)
            raw = b"".join(chunks)
    except OSError as e:
        raise error(f"cannot read the file: {' '.join((e.strerror or str(e)).split())}") from None
    finally:
        os.close(fd)
    if len(raw) > limit:
        raise error(f"is larger than {limit // 2**20} MiB: not {what} ({form})")
    nul = raw.find(b"\0")
    if nul >= 0:
        kind = describe(path) if has_hdf5_signature(inp) else looks_like(inp)
        seen = f": it is {kind}" if kind not in ("binary data", "text") else ""
        raise error(f"is not a text file (a NUL byte at byte {nul}{seen}): not {what} ({form})")
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as e:
        raise error(f"is not a UTF-8 text file (byte {e.start}): not {what} ({form})") from None
    return text[1:] if text.startswith("\ufeff") else text
