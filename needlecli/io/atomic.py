"""Writing files so that a reader never sees half of one and nothing earlier is lost, and saying truly
what is on disk when a command is stopped.

* **Atomic writes.** Every output goes to a temporary file beside its target
  (``.<name>.<host>-<pid>-<random>.needle-tmp``), is flushed to disk and renamed over the target when
  complete (:func:`atomic_path`, :func:`write_bytes_atomic`, :func:`write_text_atomic`). On any error, a
  signal or a full disk the temporary file is removed and the earlier file at the target is untouched; an
  ``OSError`` becomes one :class:`~needlecli.errors.OutputError` line naming the target (a full disk says
  so).
* **Checked before the work** (:func:`check_output_file`, :func:`check_output_dir`): the target is not a
  folder (or not a file), its name is not too long, the nearest existing folder is writable (a probe file
  is created and removed: this catches read-only file systems and immutable folders, even as root), an
  existing target may be replaced, and the file system has the room an estimate asks for.
* **Stale temporary files** of earlier runs that were killed (``SIGKILL``, a crash) are removed from a
  folder before it is written to: ours only, by their name, when the process named in it is gone (same
  host) or when older than :data:`STALE_AGE` (another host sharing the folder).
* **Signals.** :func:`handle_signals` makes ``SIGINT`` and ``SIGTERM`` the same
  :class:`~needlecli.errors.Interrupted` (exit codes 130 and 143). Inside :func:`deferred_signals`
  (while h5py builds a file, while a file is renamed into place) a signal is held and acted on when the
  section ends, so that it is never lost inside a library callback and the journal below is true.
* **One set** (:func:`output_set`): the outputs of one command are written as one set, all or nothing.
  Inside a set each file is complete in its temporary file when written, and every one is renamed into
  place only when the command has succeeded (signals held meanwhile); on an error, a signal or a full
  disk every temporary file of the set is removed, with the folders made for it, and nothing at the
  targets changed. A file of the set can be read back before then (:func:`staged_path`: the readers of
  :mod:`needlecli.io.inputs` take it from its temporary file), so that a command may read what it wrote
  (``needle compare`` its results file, ``needle crossval`` its trials and each fold's fit). Should a
  rename in the middle fail, the error lists what was renamed and what was not.
* **The journal** (:data:`JOURNAL`): the outputs a command checked before its work and those it completed,
  for the message of an interrupted command.
"""

from __future__ import annotations

import contextlib
import errno
import os
import re
import secrets
import signal
import socket
import sys
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

from needlecli import platform
from needlecli.errors import Interrupted, OutputError
from needlecli.schema import NAME_PATTERN

TMP_MARK = ".needle-tmp"
STALE_AGE = 24 * 3600.0  # s: a temporary file of another host (or of an unknown process) older than this is stale
_HOST = re.sub(r"[^A-Za-z0-9_]", "_", socket.gethostname() or "host")[:32]
_TMP_RE = re.compile(r"^\.(?P<name>.+)\.(?P<host>[A-Za-z0-9_]+)-(?P<pid>\d+)-[0-9a-f]{8}" + re.escape(TMP_MARK) + "$")
_CHUNK = 16 * 2**20  # bytes per write of a file image


# ---------------------------------------------------------------------------------------------- journal
@dataclass
class Journal:
    """What the current command meant to write (checked before its work) and what it completed."""

    planned: list[Path] = field(default_factory=list)
    written: list[Path] = field(default_factory=list)
    inflight: set[Path] = field(default_factory=set)

    def reset(self) -> None:
        self.planned.clear()
        self.written.clear()
        self.inflight.clear()

    def plan(self, path: Path) -> None:
        if path not in self.planned:
            self.planned.append(path)

    def remove_inflight(self) -> None:
        """Remove temporary files still open (an interrupted cleanup)."""
        for tmp in list(self.inflight):
            with contextlib.suppress(OSError):
                os.unlink(tmp)
            self.inflight.discard(tmp)

    def summary(self) -> str:
        """What is on disk, in words: what was completed, and which planned outputs were not written."""
        parts = []
        written = list(dict.fromkeys(self.written))
        if written:
            shown = ", ".join(str(p) for p in written[:3]) + (f" and {len(written) - 3} more" if len(written) > 3 else "")
            parts.append(f"written completely before it: {shown}")
        for p in self.planned:
            if p in written:
                continue
            inside = [w for w in written if p in w.parents]
            if inside:
                continue  # a folder some of whose files were written: listed above
            if p.is_file():
                parts.append(f"{p} not written (the earlier file there is unchanged)")
            else:
                parts.append(f"{p} not written")
        return "; ".join(parts) if parts else "no file was written"


JOURNAL = Journal()


# ---------------------------------------------------------------------------------------------- one set
def _key(path: str | Path) -> str:
    """One spelling of a target, whatever the spelling it was given in (relative, ``..``, a linked folder)."""
    p = Path(path)
    return os.path.join(os.path.realpath(p.parent), p.name)


@dataclass
class OutputSet:
    """The outputs of one command, written as one set (:func:`output_set`).

    ``staged``: target -> its complete temporary file beside it (its key: :func:`_key`), in the order
    written; ``made``: the folders made for them, outermost first; ``keep``: commit even though the
    command ends with an exception (a deliberate exit after complete outputs: a regression's exit 1)."""

    staged: dict[str, tuple[Path, Path]] = field(default_factory=dict)
    made: list[Path] = field(default_factory=list)
    keep: bool = False

    def stage(self, path: Path, tmp: Path) -> None:
        old = self.staged.pop(_key(path), None)  # written twice: the later one counts
        if old is not None:
            with contextlib.suppress(OSError):
                os.unlink(old[1])
            JOURNAL.inflight.discard(old[1])
        self.staged[_key(path)] = (path, tmp)

    def discard(self) -> None:
        """Remove every temporary file of the set and the folders made for it (those left empty)."""
        for _, tmp in self.staged.values():
            with contextlib.suppress(OSError):
                os.unlink(tmp)
            JOURNAL.inflight.discard(tmp)
        self.staged.clear()
        for d in reversed(self.made):
            with contextlib.suppress(OSError):
                os.rmdir(d)
        self.made.clear()

    def commit(self) -> None:
        """Rename every file into place (signals held until all are). A rename that fails removes the
        temporary files not yet renamed and raises :class:`OutputError` saying what was written and what
        was not."""
        items = list(self.staged.values())
        self.staged.clear()
        done: list[Path] = []
        with deferred_signals():
            for i, (path, tmp) in enumerate(items):
                try:
                    os.replace(tmp, path)
                except OSError as e:
                    rest = [p for p, _ in items[i:]]
                    for _, t in items[i:]:
                        with contextlib.suppress(OSError):
                            os.unlink(t)
                        JOURNAL.inflight.discard(t)
                    left = (f"{len(done)} of the {len(items)} outputs were written before it ({_listed(done)}); "
                            if done else "")
                    raise OutputError(path, f"cannot write: {_os_reason(e)}; {left}not written: {_listed(rest)} "
                                      "(an earlier file there is unchanged)") from None
                JOURNAL.inflight.discard(tmp)
                JOURNAL.written.append(path)
                done.append(path)
        self.made.clear()


def _listed(paths: list[Path], most: int = 4) -> str:
    shown = ", ".join(str(p) for p in paths[:most])
    return shown + (f" and {len(paths) - most} more" if len(paths) > most else "")


_SETS: list[OutputSet] = []


@contextlib.contextmanager
def output_set() -> Iterator[OutputSet]:
    """Write every file of the block as one set: renamed into place together when the block ends
    normally (or with :attr:`OutputSet.keep`), all removed when it ends with an error or a signal (the
    module docstring). Nested, the inner block belongs to the outer set."""
    if _SETS:
        yield _SETS[-1]
        return
    s = OutputSet()
    _SETS.append(s)
    try:
        yield s
    except BaseException:
        _SETS.remove(s)
        if not s.keep:
            with deferred_signals():
                s.discard()
            raise
        s.commit()
        raise
    _SETS.remove(s)
    s.commit()


def staged_path(path: str | Path) -> Path:
    """Where the content of ``path`` is now: the complete temporary file of an output of the set being
    written (not yet renamed into place), else ``path`` itself."""
    if _SETS:
        hit = _SETS[-1].staged.get(_key(path))
        if hit is not None:
            return hit[1]
    return Path(path)


# ---------------------------------------------------------------------------------------------- signals
class _SignalState:
    def __init__(self) -> None:
        self.deferring = 0
        self.pending: int | None = None
        self.installed = False
        self.raised: int | None = None  # the last signal raised as Interrupted in this command


_SIG = _SignalState()
_SIGNALS = platform.STOP_SIGNALS


def _handler(signum, frame) -> None:  # noqa: ARG001
    if _SIG.deferring:
        _SIG.pending = _SIG.pending or signum
        return
    _SIG.raised = signum
    raise Interrupted(signum)


def _unraisable(u) -> None:
    """``sys.unraisablehook`` while signals are handled: an :class:`Interrupted` raised where Python can only
    ignore an exception (a weakref callback or a ``__del__`` the garbage collector ran when the signal came)
    is not lost: the signal is sent again, from another thread 5 ms later (once this hook has returned), and acts at the
    next line of ordinary code (should it land in a finalizer again, it comes back here)."""
    if isinstance(u.exc_value, Interrupted) and _SIG.installed:
        t = threading.Timer(0.005, platform.send_self, (u.exc_value.signum,))  # after this hook returned
        t.daemon = True
        t.start()
        return
    _HOOK["previous"](u)


_HOOK: dict = {"previous": sys.unraisablehook}


def raised_signal() -> Interrupted | None:
    """The signal raised as :class:`Interrupted` in this command, if any: a library may have turned that
    exception into one of its own (pydantic, a class being created) on its way out."""
    return Interrupted(_SIG.raised) if _SIG.raised is not None else None


@contextlib.contextmanager
def handle_signals() -> Iterator[None]:
    """SIGINT and SIGTERM raise :class:`Interrupted` while the block runs (main thread only; elsewhere,
    and when already installed, nothing changes), from the moment the block calls :func:`start_signals`
    (a signal before that is held, so that it is raised where the command catches it). The earlier
    handlers come back afterwards; a signal that came while they were put back is passed on to them
    when the block ended normally."""
    if _SIG.installed or threading.current_thread() is not threading.main_thread():
        yield
        return
    old = {s: signal.getsignal(s) for s in _SIGNALS}
    _SIG.raised = None
    _SIG.deferring += 1  # released by start_signals
    for s in _SIGNALS:
        signal.signal(s, _handler)
    _HOOK["previous"], sys.unraisablehook = sys.unraisablehook, _unraisable
    _SIG.installed = True
    finished = False
    try:
        yield
        finished = True
    finally:
        _SIG.deferring += 1
        _SIG.installed = False
        sys.unraisablehook = _HOOK["previous"]
        for s, h in old.items():
            signal.signal(s, h)
        pending, _SIG.pending, _SIG.deferring = _SIG.pending, None, 0
        if pending is not None and finished:
            platform.send_self(pending)


def start_signals() -> None:
    """Inside :func:`handle_signals`, where the command can catch :class:`Interrupted`: signals act from
    now on (one held since the handlers were installed is raised here)."""
    if _SIG.deferring:
        _SIG.deferring -= 1
    if not _SIG.deferring and _SIG.pending is not None:
        signum, _SIG.pending = _SIG.pending, None
        raise Interrupted(signum)


def hold_signals() -> None:
    """Hold every further signal until :func:`handle_signals` ends (the command is ending anyway)."""
    _SIG.deferring += 1


_WORKER = {"busy": False, "process": False}


def _worker_handler(signum, frame) -> None:
    if not _WORKER["busy"]:  # idle: nothing is being written
        os._exit(128 + signum)
    _handler(signum, frame)


def _watch_parent(parent: int) -> None:
    """A worker whose parent is gone (killed with SIGKILL) stops as if it got SIGTERM, instead of waiting
    for tasks for ever."""
    while platform.parent_alive(parent):
        time.sleep(0.5)
    platform.send_self(signal.SIGTERM)


def install_worker_signals() -> None:
    """In a worker process (a sweep's): SIGINT and SIGTERM stop the task (:func:`worker_task`) with
    :class:`Interrupted`, so that what it writes removes its temporary file, and then the process; an
    idle worker just ends. So does a worker whose parent process died."""
    if threading.current_thread() is threading.main_thread():
        for s in _SIGNALS:
            signal.signal(s, _worker_handler)
        _WORKER["process"] = True
        import multiprocessing

        parent = multiprocessing.parent_process()  # the process that started this one, even if already gone
        parent_pid = parent.pid if parent is not None and parent.pid else platform.parent_pid()
        threading.Thread(target=_watch_parent, args=(parent_pid,), daemon=True, name="needle-parent").start()


@contextlib.contextmanager
def worker_task() -> Iterator[None]:
    """Mark a worker busy with a task (see :func:`install_worker_signals`); in a worker process, a task
    stopped by a signal ends the process once its temporary files are removed."""
    _WORKER["busy"] = True
    try:
        yield
    except Interrupted as e:
        if _WORKER["process"]:
            JOURNAL.remove_inflight()
            os._exit(e.exit_code)
        raise
    finally:
        _WORKER["busy"] = False


@contextlib.contextmanager
def deferred_signals() -> Iterator[None]:
    """Hold SIGINT / SIGTERM while the block runs; one that came is raised when the outermost block ends."""
    _SIG.deferring += 1
    try:
        yield
    finally:
        _SIG.deferring -= 1
    if not _SIG.deferring and _SIG.pending is not None:
        signum, _SIG.pending = _SIG.pending, None
        raise Interrupted(signum)


# ---------------------------------------------------------------------------------------------- temporaries
def temp_path(path: Path) -> Path:
    """A temporary name beside ``path`` that says whose it is (host, process) and fits any file system."""
    return path.parent / f".{path.name[:120]}.{_HOST}-{os.getpid()}-{secrets.token_hex(4)}{TMP_MARK}"


_swept: set[Path] = set()


def remove_stale(folder: Path, *, force: bool = False) -> list[Path]:
    """Remove this tool's temporary files in ``folder`` left by runs that were killed: those of a process
    of this host that no longer runs, and any older than :data:`STALE_AGE`. Once per folder and process
    unless ``force``. Returns what was removed."""
    folder = Path(folder)
    key = folder.resolve() if folder.exists() else folder
    if key in _swept and not force:
        return []
    _swept.add(key)
    removed = []
    try:
        entries = list(os.scandir(folder))
    except OSError:
        return removed
    now = time.time()
    for e in entries:
        m = _TMP_RE.match(e.name)
        if not m:
            continue
        try:
            age = now - e.stat(follow_symlinks=False).st_mtime
        except OSError:
            continue
        pid = int(m["pid"])
        mine = m["host"] == _HOST
        stale = (mine and pid != os.getpid() and not platform.pid_alive(pid)) or age > STALE_AGE
        if stale:
            with contextlib.suppress(OSError):
                os.unlink(e.path)
                removed.append(Path(e.path))
    return removed


# ---------------------------------------------------------------------------------------------- checks before the work
def _os_reason(e: OSError) -> str:
    if e.errno == errno.ENOSPC:
        return "no space left on the device (the disk is full)"
    if e.errno == errno.EDQUOT:
        return "the disk quota is exceeded"
    if e.errno == errno.EROFS:
        return "the file system is read-only"
    if e.errno == errno.ENAMETOOLONG:
        return "the name is too long for the file system"
    if e.errno in (errno.EACCES, errno.EPERM):
        return "permission denied"
    return " ".join((e.strerror or str(e)).split())


def _nearest_existing(path: Path) -> Path:
    p = path
    while not os.path.lexists(p):
        if p.parent == p:
            break
        p = p.parent
    return p


def _probe(folder: Path, target: Path) -> None:
    """Create and remove a temporary file in ``folder``: proves that files can be made there."""
    probe = temp_path(folder / "probe")
    try:
        fd = os.open(probe, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    except OSError as e:
        raise OutputError(target, f"cannot write in {folder}: {_os_reason(e)}") from None
    os.close(fd)
    with contextlib.suppress(OSError):
        os.unlink(probe)


def human_bytes(n: float) -> str:
    for unit in ("bytes", "kB", "MB", "GB", "TB", "PB"):
        if abs(n) < 1000 or unit == "PB":
            return f"{n:.0f} {unit}" if unit == "bytes" else f"{n:.3g} {unit}"
        n /= 1000.0
    return f"{n:.3g} PB"


def free_space(folder: Path) -> int | None:
    """Bytes free for an ordinary user on the file system of ``folder`` (None if unknown)."""
    return platform.free_bytes(folder)


def _check_names(path: Path, target: Path, last: str = "folder") -> None:
    """Every part of ``path`` fits the file system's name length (before any call that would fail on it);
    ``last``: what its last part names (file or folder)."""
    for i, part in enumerate(path.parts):
        if len(part.encode()) > 255:
            what = last if i == len(path.parts) - 1 else "folder"
            raise OutputError(target if len(str(target)) < 300 else f"{str(target)[:120]}...",
                              f"the {what} name {part[:40]!r}... is too long ({len(part.encode())} bytes; at most 255)")


def _check_parents(path: Path, target: Path, what: str) -> Path:
    """The nearest existing ancestor of ``path``: a folder we can write in."""
    _check_names(path, target)
    base = _nearest_existing(path)
    if not base.is_dir():
        raise OutputError(target, f"cannot make {what} here: {base} is a file, not a folder")
    return base


def _check_room(folder: Path, target: Path, size: int | None, what: str) -> None:
    if size is None:
        return
    free = free_space(folder)
    if free is not None and size > free:
        raise OutputError(target, f"{what} needs up to {human_bytes(size)} on disk, {human_bytes(free)} are free "
                          f"there: free some space or choose another --out")


def check_output_file(path: str | Path, *, what: str = "the file", size: int | None = None) -> Path:
    """Check, before any work, that ``path`` can be written as a file (see the module docstring); record it
    in the journal. ``size`` is what it may need on disk. Raises :class:`OutputError`."""
    path = Path(path)
    _check_names(path, path, last="file")
    if path.name in ("", ".", ".."):
        raise OutputError(path, f"is a folder; give a file name for {what}")
    if path.is_dir():
        raise OutputError(path, f"is a folder; give a file name for {what} (e.g. {path / 'name'})")
    base = _check_parents(path.parent, path, what)
    folder = path.parent if path.parent.is_dir() else base
    limit = platform.max_name_length(folder)
    if len(path.name.encode()) > limit:
        raise OutputError(path, f"the file name is too long ({len(path.name.encode())} bytes; at most {limit})")
    if path.exists():
        if not path.is_file():
            raise OutputError(path, f"exists and is not a regular file; cannot replace it with {what}")
        if not os.access(path, os.W_OK):
            raise OutputError(path, "exists and cannot be replaced (read-only or immutable)")
    _probe(folder, path)
    _check_room(folder, path, size, what)
    remove_stale(folder)
    JOURNAL.plan(path)
    return path


def check_output_dir(path: str | Path, *, what: str = "the outputs", size: int | None = None) -> Path:
    """Check, before any work, that files can be written in folder ``path`` (made if missing); record it."""
    path = Path(path)
    _check_names(path, path)
    if path.exists() and not path.is_dir():
        raise OutputError(path, f"is a file, not a folder for {what}")
    base = _check_parents(path, path, what)
    folder = path if path.is_dir() else base
    _probe(folder, path)
    _check_room(folder, path, size, what)
    if path.is_dir():
        remove_stale(path)
    JOURNAL.plan(path)
    return path


def output_stem(name, fallback: str) -> str:
    """The stem of output file names taken from a file's contents (a results file's ``name``): used as
    it is only when it is a plain name (letters, digits, ``_ . -``, not starting with a dot, at most 100
    characters), else ``fallback`` (the file's own stem) with everything else replaced by ``_``. Never a
    path: an absolute or ``../`` name cannot put outputs outside the folder asked for."""
    if isinstance(name, str) and re.fullmatch(NAME_PATTERN, name) and len(name) <= 100:
        return name
    plain = re.sub(r"[^A-Za-z0-9_.\-]", "_", str(fallback))[:100].lstrip(".")
    return plain or "results"


# ---------------------------------------------------------------------------------------------- writing
@contextlib.contextmanager
def atomic_path(path: str | Path) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; on success rename it to ``path`` (inside :func:`output_set`:
    when the whole set is complete), on error (a signal too) remove it. An ``OSError`` becomes
    :class:`OutputError` naming ``path``."""
    path = Path(path)
    current = _SETS[-1] if _SETS else None
    missing = []
    p = path.parent
    while not os.path.lexists(p) and p.parent != p:
        missing.append(p)
        p = p.parent
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise OutputError(path, f"cannot make the folder {path.parent}: {_os_reason(e)}") from None
    if current is not None:
        current.made.extend(reversed(missing))
    remove_stale(path.parent)
    tmp = temp_path(path)
    with deferred_signals():
        try:
            fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)  # the umask applies, as to any new file
        except OSError as e:
            raise OutputError(path, f"cannot write: {_os_reason(e)}") from None
        os.close(fd)
        JOURNAL.inflight.add(tmp)
    try:
        yield tmp
        with deferred_signals():
            _fsync(tmp)
            if current is not None:  # renamed with the rest of its set
                current.stage(path, tmp)
            else:
                os.replace(tmp, path)
                JOURNAL.inflight.discard(tmp)
                JOURNAL.written.append(path)
    except BaseException as e:
        with deferred_signals():
            with contextlib.suppress(OSError):
                os.unlink(tmp)
            JOURNAL.inflight.discard(tmp)
            if current is None:  # the folders made for it (a set removes its own with the rest)
                for d in missing:
                    with contextlib.suppress(OSError):
                        os.rmdir(d)
        if isinstance(e, OSError) and not isinstance(e, OutputError):
            kept = " (the earlier file there is unchanged)" if path.is_file() else ""
            raise OutputError(path, f"cannot write: {_os_reason(e)}; nothing was written{kept}") from None
        raise


def _fsync(p: Path) -> None:
    fd = os.open(p, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def write_fd(fd: int, data: bytes | memoryview, progress=None) -> None:
    """Write ``data`` to descriptor ``fd`` in pieces (a signal between them stops the write cleanly);
    ``progress(bytes written)`` after each piece, if given."""
    view = memoryview(data)
    for i in range(0, len(view), _CHUNK):
        chunk = view[i : i + _CHUNK]
        while chunk:
            n = os.write(fd, chunk)
            chunk = chunk[n:]
        if progress is not None:
            progress(min(i + _CHUNK, len(view)))


def write_bytes_atomic(path: str | Path, data: bytes | memoryview, progress=None) -> Path:
    """Write ``data`` to ``path`` atomically, in pieces (a signal between them stops the write cleanly);
    ``progress(bytes written)`` after each piece, if given."""
    with atomic_path(path) as tmp:
        fd = os.open(tmp, os.O_WRONLY | os.O_TRUNC)
        try:
            write_fd(fd, data, progress)
        finally:
            os.close(fd)
    return Path(path)


def write_text_atomic(path: str | Path, text: str) -> Path:
    return write_bytes_atomic(path, text.encode("utf-8"))
