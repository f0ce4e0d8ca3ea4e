"""Every call that depends on the operating system, each with its capability check and a plain fallback.

needlecli is tested and measured on Linux; on macOS and Windows every command takes the fallbacks below
(slower in places, never other numbers; not tested there: ``tests/test_platform.py`` takes the Linux-only
capabilities away on Linux). No other module of needlecli calls an operating-system-specific function
(``tests/test_architecture.py`` checks it with ``ast``): the decision "have it, or fall back" lives here,
once. The module is light (the standard library only, most of it imported when a function is called):
``needle --help`` imports it.

========================  ======================================  ============================================
capability [switch name]  used by                                 without it
========================  ======================================  ============================================
posix_fallocate (Linux,   reserve, has_positioned_io: the         the results file is built in memory (an HDF5
BSD) [fallocate]; pread,  results writer reserves the file's      file image) and written after: one more copy
pwrite, preadv            room, then HDF5 writes into it          of the arrays, their size again in memory; a
[positioned_io]           (io/results.py)                         full disk is still one clear error, nothing
                                                                  half-written

O_DIRECT (Linux)          open_direct: the arrays' whole blocks   every write goes through the page cache: the
[o_direct]                go to the disk past the page cache      same bytes, slower on virtual machines
                          (io/results.py)

statvfs (POSIX)           free_bytes: the room checked before     shutil.disk_usage (the same figure on Linux)
[statvfs]                 the work (io/atomic.py)

pathconf (POSIX)          max_name_length: a file name too long   255 bytes, the limit of the common file
[pathconf]                refused before the work (io/atomic.py)  systems

O_NONBLOCK (POSIX)        open_for_reading: every input opened    a plain open (Windows has no named pipes
[nonblocking]             without waiting, so that a named pipe   in the file system); a FIFO there would
                          with no writer is seen and refused      wait for its writer
                          (io/inputs.py)

/proc/meminfo (Linux)     available_memory: the memory check      sysconf's available pages (BSD), else no
[proc]                    before the work                         memory check (NEEDLECLI_MEMORY sets the
                          (experiments/config/budget.py)          limit by hand)

glibc mallopt (Linux)     malloc_tune: freed memory kept for      the C library's defaults: more page faults
[mallopt]                 reuse (cli/app.py memory_policy)        in fit-em, the same numbers

transparent huge pages    no_transparent_huge_pages: numpy's      nothing to do (numpy madvises huge pages on
(Linux) [huge_pages]      large arrays on 4 KB pages (cli/app.py  Linux only)
                          memory_policy)

sched_getaffinity         usable_cores: the kernels' worker       os.cpu_count: every core of the machine,
(Linux)                   threads (kernels/_threads.py)           also those a job scheduler did not give
[sched_getaffinity]

BLAS / OpenMP thread      one_thread_env, pin_thread_pools,       THREAD_ENV works everywhere; without
pools: THREAD_ENV,        thread_pools_limited (sweep's           threadpoolctl a BLAS loaded before the
threadpoolctl             workers), single_blas_thread (fit-em's  variables were set keeps its threads;
[threadpoolctl],          processes)                              without /proc OpenBLAS keeps its threads in
/proc/self/maps [proc] +                                          fit-em: slower on shared cores, the same
ctypes                                                            numbers

fork (Linux, BSD; not     fork_available: the kernels' warm-up    a first run compiles the observers' kernels
macOS, where a forked     process (kernels/__init__.py), fit-     itself, after the truth's (one core instead
child may crash in the    em's process per model                  of two); fit-em fits the models one after
system's libraries)       (experiments/studies/fit.py)            another on every core; the same numbers
[fork]

prctl PR_SET_PDEATHSIG    die_with_parent: the warm-up process    a warm-up process whose run was killed
(Linux) [prctl]           ends with its run                       outright finishes compiling into the cache,
                          (kernels/__init__.py)                   then ends

fcntl.flock (POSIX)       file_lock: numba's saves to the kernel  msvcrt.locking, else an exclusive lock file
[flock]; msvcrt.locking   cache, one process at a time            (O_EXCL); one that a process killed while
(Windows) [msvcrt]        (kernels/_jit.py)                       holding it leaves is broken when that
                                                                  process is gone, or after LOCK_STALE s

signals to a process:     send_self, pid_alive, parent_alive      signal.raise_signal for the process's own
kill, getppid of a re-    (io/atomic.py): the signal re-sent      signals; a killed run's temporary file is
parented child (POSIX)    from the unraisable hook, stale         removed after a day (STALE_AGE), not at
[posix_signals]           temporary files, sweep workers whose    once; a sweep worker whose parent was killed
                          parent died                             waits until it is ended

SIGINT, SIGTERM           STOP_SIGNALS: what stops a command      both exist on Linux, macOS and Windows
                          (exit 130, 143; io/atomic.py,           (SIGHUP and SIGKILL are not used: Windows
                          cli/app.py)                             has neither)
========================  ======================================  ============================================

**Taking a capability away** (a testing and debugging aid): the environment variable
``NEEDLECLI_PLATFORM_WITHOUT``, a comma-separated list of switch names (:data:`CAPABILITIES`, in
brackets above), makes each check answer "not here" as on a platform that lacks it: e.g.
``NEEDLECLI_PLATFORM_WITHOUT=o_direct,fallocate needle simulate ...`` writes the results file as on
macOS. ``NEEDLECLI_NO_DIRECT_IO=1`` is the older spelling of ``o_direct``. The checks also look each
capability up when they are called (``os``'s and ``fcntl``'s attributes, the C library's symbols through
``ctypes``), so that a capability removed before needlecli runs (``tests/test_platform.py`` deletes them
in a ``sitecustomize``) is seen as absent.
"""

from __future__ import annotations

import contextlib
import errno
import os
import signal
import sys
from collections.abc import Iterator

from needlecli.errors import ConfigError

# ---------------------------------------------------------------------------------------------- the switch
SWITCH = "NEEDLECLI_PLATFORM_WITHOUT"
#: the capabilities :data:`SWITCH` can take away (the table of the module docstring)
CAPABILITIES = ("fallocate", "positioned_io", "o_direct", "statvfs", "pathconf", "proc", "mallopt",
                "huge_pages", "sched_getaffinity", "threadpoolctl", "fork", "prctl", "flock", "msvcrt",
                "posix_signals", "nonblocking")


def without(name: str) -> bool:
    """Whether :data:`SWITCH` takes capability ``name`` away. Raises :class:`ConfigError` for a name that
    is not one of :data:`CAPABILITIES` (a typo would otherwise test nothing)."""
    names = {n.strip().lower() for n in os.environ.get(SWITCH, "").split(",") if n.strip()}
    unknown = sorted(names - set(CAPABILITIES))
    if unknown:
        raise ConfigError(SWITCH, (), f"{', '.join(map(repr, unknown))}: not a capability; expected some of "
                          f"{', '.join(CAPABILITIES)}")
    return name in names


def check_switch() -> None:
    """Raise :class:`ConfigError` now if :data:`SWITCH` names something that is not a capability."""
    without("")


def _posix() -> bool:
    return os.name == "posix" and not without("posix_signals")


def _libc(symbol: str):
    """The C library's function ``symbol`` (through ``ctypes``), or None where it has none (or ``ctypes``
    cannot open the process's own symbols: Windows)."""
    if without(symbol):
        return None
    try:
        import ctypes

        return getattr(ctypes.CDLL(None), symbol)
    except (OSError, AttributeError, TypeError):
        return None


# ---------------------------------------------------------------------------------------------- files: room
def has_fallocate() -> bool:
    """Whether files can be given their room ahead (``os.posix_fallocate``: Linux, BSD)."""
    return hasattr(os, "posix_fallocate") and not without("fallocate")


def reserve(fd: int, size: int) -> bool:
    """Reserve ``size`` bytes for the file open as ``fd`` (``posix_fallocate``): True when done, so that
    writes within them cannot meet a full disk. False where the platform or the file system cannot
    (then nothing was done). A full disk (or any other failure) raises ``OSError``."""
    if not has_fallocate():
        return False
    try:
        os.posix_fallocate(fd, 0, size)
    except OSError as e:
        if e.errno not in (errno.EOPNOTSUPP, errno.EINVAL, errno.ENOSYS):
            raise
        return False
    return True


def has_positioned_io() -> bool:
    """Whether reads and writes at an offset without moving the file position exist (``os.pread``,
    ``os.pwrite``, ``os.preadv``: Linux, BSD; the writer into reserved room uses them)."""
    return all(hasattr(os, f) for f in ("pread", "pwrite", "preadv")) and not without("positioned_io")


# ---------------------------------------------------------------------------------------------- files: direct I/O
def has_direct_io() -> bool:
    """Whether files can be opened for writes past the page cache (``O_DIRECT``: Linux), and are not kept
    from it (:data:`SWITCH`, or ``NEEDLECLI_NO_DIRECT_IO``)."""
    return bool(getattr(os, "O_DIRECT", 0)) and not os.environ.get("NEEDLECLI_NO_DIRECT_IO") \
        and not without("o_direct")


def open_direct(path, flags: int = os.O_WRONLY) -> int | None:
    """A descriptor of ``path`` opened with ``flags | O_DIRECT`` (offsets, lengths and buffer addresses of
    its writes must then be whole blocks, 4096 bytes), or None where the platform or the file system has
    no direct I/O (tmpfs and others): the caller then writes through its ordinary descriptor."""
    if not has_direct_io():
        return None
    try:
        return os.open(path, flags | os.O_DIRECT)
    except OSError:  # tmpfs and others: no O_DIRECT
        return None


# ---------------------------------------------------------------------------------------------- files: reading
def open_for_reading(path) -> int:
    """A read-only descriptor of ``path``, opened without waiting: ``O_NONBLOCK`` (POSIX), so that a named
    pipe (FIFO) with no writer opens at once and its kind can be checked (:mod:`needlecli.io.inputs`
    refuses it) instead of blocking for ever; on a regular file the flag changes nothing. Elsewhere (or
    without [nonblocking]) a plain read-only open. Raises ``OSError`` as ``os.open`` does (``ENXIO`` for a
    socket)."""
    flags = os.O_RDONLY | getattr(os, "O_BINARY", 0)
    if hasattr(os, "O_NONBLOCK") and not without("nonblocking"):
        flags |= os.O_NONBLOCK
    return os.open(path, flags)


# ---------------------------------------------------------------------------------------------- files: limits
def free_bytes(path) -> int | None:
    """Bytes free for an ordinary user on the file system of ``path`` (an existing file or folder):
    ``statvfs`` where it exists (POSIX), else ``shutil.disk_usage`` (Windows); None when it cannot be
    known (then the room is not checked before the work)."""
    import shutil

    usage = getattr(shutil, "disk_usage", None)
    try:
        if hasattr(os, "statvfs") and not without("statvfs"):
            st = os.statvfs(path)
            return st.f_bavail * st.f_frsize
        return usage(path).free if usage is not None else None
    except OSError:
        return None


def max_name_length(folder) -> int:
    """The longest file name (bytes) the file system of ``folder`` takes: ``pathconf`` where it exists
    (POSIX), else 255."""
    if hasattr(os, "pathconf") and not without("pathconf"):
        try:
            return os.pathconf(folder, "PC_NAME_MAX")
        except (OSError, ValueError):
            pass
    return 255


@contextlib.contextmanager
def file_lock(path, *, blocking: bool = True) -> Iterator[bool]:
    """Hold an exclusive lock named by the file ``path`` while the block runs: one process (or thread's
    block) at a time, across the processes of this machine, and of every machine that shares the file
    system where it locks (NFS, Lustre mounted with ``flock``). ``fcntl.flock`` on the file ``path``
    (created if missing) where it exists (POSIX) and the file system takes it; else ``msvcrt.locking`` of
    its first byte (Windows); else the exclusive creation of ``<path>.excl`` (removed afterwards; see
    :data:`LOCK_STALE`): also where ``flock`` is refused by the file system (a network file system
    without lock support, Lustre without ``-o flock``: ``ENOLCK``, ``EOPNOTSUPP``, ...). Waits as long as
    another holds it, or with ``blocking=False`` yields False at once when another does (the block then
    runs without the lock: the caller decides). Yields True when held."""
    path = os.fspath(path)
    if has_flock():
        import fcntl

        with open(path, "a") as lock:
            try:
                fcntl.flock(lock, fcntl.LOCK_EX | (0 if blocking else fcntl.LOCK_NB))
            except BlockingIOError:
                yield False
                return
            except OSError as e:
                if e.errno not in _NO_FLOCK:
                    raise
                lock.close()  # the file system takes no flock: the lock file's way
            else:
                try:
                    yield True
                finally:
                    fcntl.flock(lock, fcntl.LOCK_UN)
                return
    if has_msvcrt_locking():
        with _msvcrt_lock(path, blocking) as held:
            yield held
    else:
        with _exclusive_file_lock(path + ".excl", blocking) as held:
            yield held


#: errors of ``flock`` on a file system that takes no such lock (NFS without lockd, Lustre without -o flock)
_NO_FLOCK = {getattr(errno, n) for n in ("ENOLCK", "EOPNOTSUPP", "ENOTSUP", "ENOSYS", "EINVAL") if hasattr(errno, n)}


def has_flock() -> bool:
    """Whether ``fcntl.flock`` exists (POSIX)."""
    if without("flock"):
        return False
    try:
        import fcntl
    except ImportError:
        return False
    return hasattr(fcntl, "flock")


def has_msvcrt_locking() -> bool:
    """Whether ``msvcrt.locking`` exists (Windows)."""
    if without("msvcrt"):
        return False
    try:
        import msvcrt
    except ImportError:
        return False
    return hasattr(msvcrt, "locking")


_LOCK_POLL = 0.01  # s between attempts at a lock held by another


@contextlib.contextmanager
def _msvcrt_lock(path: str, blocking: bool = True) -> Iterator[bool]:
    import msvcrt
    import time

    fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o666)
    try:
        while True:
            try:
                msvcrt.locking(fd, msvcrt.LK_NBLCK, 1)  # the first byte (the file position is 0)
                break
            except OSError as e:
                if e.errno not in (errno.EACCES, getattr(errno, "EDEADLOCK", errno.EDEADLK)):
                    raise
                if not blocking:
                    yield False
                    return
                time.sleep(_LOCK_POLL)
        try:
            yield True
        finally:
            os.lseek(fd, 0, os.SEEK_SET)
            msvcrt.locking(fd, msvcrt.LK_UNLCK, 1)
    finally:
        os.close(fd)


#: s: an exclusive lock file older than this is taken as left by a process that is gone (saves of a
#: compiled kernel take well under a second; a compilation that takes longer than this may then run twice,
#: which costs only the time)
LOCK_STALE = 120.0


@contextlib.contextmanager
def _exclusive_file_lock(held: str, blocking: bool = True) -> Iterator[bool]:
    import socket
    import time

    me = f"{socket.gethostname()} {os.getpid()}\n"
    while True:
        try:
            fd = os.open(held, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)
            break
        except FileExistsError:
            _break_stale_lock(held)
            if not blocking and os.path.exists(held):
                yield False
                return
            time.sleep(_LOCK_POLL)
    try:
        os.write(fd, me.encode())
    finally:
        os.close(fd)
    try:
        yield True
    finally:
        with contextlib.suppress(OSError):
            os.unlink(held)


def _break_stale_lock(held: str) -> None:
    """Remove the lock file ``held`` if the process that made it (same host) is gone or it is older than
    :data:`LOCK_STALE`. Two processes breaking the same stale lock at the same instant may both go on."""
    import socket
    import time

    try:
        with open(held, encoding="utf-8") as f:
            host, _, pid = f.read().strip().rpartition(" ")
        age = time.time() - os.stat(held).st_mtime
    except (OSError, ValueError):
        return  # gone already (or unreadable: wait)
    dead = host == socket.gethostname() and pid.isdigit() and not pid_alive(int(pid))
    if dead or age > LOCK_STALE:
        with contextlib.suppress(OSError):
            os.unlink(held)


# ---------------------------------------------------------------------------------------------- memory
def available_memory() -> int | None:
    """Bytes of memory a new process may use: ``MemAvailable`` of ``/proc/meminfo`` (Linux), else the
    pages ``sysconf`` says are available (BSD), else None (unknown: macOS, Windows)."""
    if not without("proc"):
        try:
            with open("/proc/meminfo") as f:
                for line in f:
                    if line.startswith("MemAvailable:"):
                        return int(line.split()[1]) * 1024
        except (OSError, ValueError, IndexError):
            pass
    try:
        return os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (OSError, ValueError, AttributeError):
        return None


def no_transparent_huge_pages() -> None:
    """numpy's large arrays on ordinary pages, not madvised transparent huge pages (numpy does that on
    Linux only), unless ``NUMPY_MADVISE_HUGEPAGE`` says otherwise: set for a numpy imported later, and
    applied to one imported already."""
    if without("huge_pages"):
        return
    os.environ.setdefault("NUMPY_MADVISE_HUGEPAGE", "0")
    if "numpy" in sys.modules and os.environ["NUMPY_MADVISE_HUGEPAGE"] == "0":  # imported before
        setter = getattr(sys.modules["numpy"]._core.multiarray, "_set_madvise_hugepage", None)
        if setter is not None:
            setter(False)


def has_mallopt() -> bool:
    """Whether the C library is glibc's with ``mallopt`` (Linux)."""
    return sys.platform == "linux" and _libc("mallopt") is not None


def malloc_tune(*, mmap_threshold: int, trim_threshold: int, top_pad: int) -> bool:
    """Set glibc's ``M_MMAP_THRESHOLD``, ``M_TRIM_THRESHOLD`` and ``M_TOP_PAD`` (bytes; in this order);
    True when done. Nothing where the C library is not glibc, or where a ``MALLOC_*_`` variable of the
    environment tunes glibc already (the user's choice wins)."""
    if sys.platform != "linux" or any(k.startswith("MALLOC_") and k.endswith("_") for k in os.environ):
        return False
    mallopt = _libc("mallopt")
    if mallopt is None:  # not glibc
        return False
    M_TRIM_THRESHOLD, M_TOP_PAD, M_MMAP_THRESHOLD = -1, -2, -3
    mallopt(M_MMAP_THRESHOLD, mmap_threshold)
    mallopt(M_TRIM_THRESHOLD, trim_threshold)
    mallopt(M_TOP_PAD, top_pad)
    return True


# ---------------------------------------------------------------------------------------------- threads
def usable_cores() -> int:
    """The cores this process may run on: its CPU affinity (Linux), else every core of the machine; at most
    its control group's CPU quota, rounded up (Linux: a batch scheduler's or a container's limit,
    :func:`cpu_quota`)."""
    if hasattr(os, "sched_getaffinity") and not without("sched_getaffinity"):
        n = len(os.sched_getaffinity(0))
    else:
        n = os.cpu_count() or 1
    quota = cpu_quota()
    return max(1, min(n, quota) if quota is not None else n)


def cpu_quota() -> int | None:
    """The CPU quota of this process's control group in whole cores, rounded up (cgroup v2 ``cpu.max``,
    v1 ``cpu.cfs_quota_us`` / ``cpu.cfs_period_us``: what SLURM, Kubernetes or ``docker --cpus`` set), or
    None where there is none or it cannot be read (not Linux, no ``/proc``)."""
    if without("proc") or not sys.platform.startswith("linux"):
        return None
    import math

    try:
        with open("/proc/self/cgroup", encoding="utf-8") as f:
            lines = f.read().splitlines()
    except OSError:
        return None
    for line in lines:  # "0::/path" (v2) or "4:cpu,cpuacct:/path" (v1)
        _, controllers, rel = (line.split(":", 2) + ["", ""])[:3]
        try:
            if controllers == "":
                with open(f"/sys/fs/cgroup{rel}/cpu.max", encoding="utf-8") as f:
                    quota, period = (f.read().split() + ["100000"])[:2]
                if quota != "max":
                    return max(1, math.ceil(int(quota) / int(period)))
            elif "cpu" in controllers.split(","):
                base = next((f"/sys/fs/cgroup/{d}{rel}" for d in ("cpu,cpuacct", "cpu", "cpuacct,cpu")
                             if os.path.isdir(f"/sys/fs/cgroup/{d}{rel}")), None)
                if base is None:
                    continue
                with open(f"{base}/cpu.cfs_quota_us", encoding="utf-8") as f:
                    quota_us = int(f.read())
                with open(f"{base}/cpu.cfs_period_us", encoding="utf-8") as f:
                    period_us = int(f.read())
                if quota_us > 0 and period_us > 0:
                    return max(1, math.ceil(quota_us / period_us))
        except (OSError, ValueError):
            continue
    return None


#: environment variables that size the thread pools of BLAS / OpenMP in a process started after they are set
THREAD_ENV = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "VECLIB_MAXIMUM_THREADS",
              "NUMEXPR_NUM_THREADS", "BLIS_NUM_THREADS")


@contextlib.contextmanager
def one_thread_env() -> Iterator[None]:
    """:data:`THREAD_ENV` set to 1 while the block runs (processes started in it inherit them)."""
    old = {k: os.environ.get(k) for k in THREAD_ENV}
    os.environ.update({k: "1" for k in THREAD_ENV})
    try:
        yield
    finally:
        for k, v in old.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


def _threadpool_limits():
    if without("threadpoolctl"):
        return None
    try:
        from threadpoolctl import threadpool_limits
    except ImportError:
        return None
    return threadpool_limits


def pin_thread_pools() -> None:
    """This process's BLAS / OpenMP pools at one thread from now on: :data:`THREAD_ENV` (for libraries
    not loaded yet) and threadpoolctl, if installed (for those loaded already)."""
    for k in THREAD_ENV:
        os.environ[k] = "1"
    limits = _threadpool_limits()
    if limits is not None:
        limits(limits=1)


@contextlib.contextmanager
def thread_pools_limited(n: int = 1) -> Iterator[None]:
    """The loaded BLAS / OpenMP pools at ``n`` threads while the block runs (threadpoolctl, if installed;
    else nothing)."""
    limits = _threadpool_limits()
    if limits is None:
        yield
        return
    with limits(limits=n):
        yield


_BLAS_SETTERS = ("scipy_openblas_set_num_threads64_", "scipy_openblas_set_num_threads",
                 "openblas_set_num_threads64_", "openblas_set_num_threads")


@contextlib.contextmanager
def single_blas_thread() -> Iterator[None]:
    """Run with one OpenBLAS thread per loaded OpenBLAS (restored after), found in ``/proc/self/maps``
    and set through ``ctypes``. A no-op where the library or its setter cannot be found (not Linux,
    another BLAS)."""
    found = []
    try:
        import ctypes

        paths = []
        if not without("proc"):
            with open("/proc/self/maps", encoding="utf-8") as f:
                paths = sorted({line.split()[-1] for line in f if "openblas" in line.lower() and "/" in line})
        for path in paths:
            lib = ctypes.CDLL(path)
            for name in _BLAS_SETTERS:
                if hasattr(lib, name):
                    getter = getattr(lib, name.replace("set_num_threads", "get_num_threads"), None)
                    before = int(getter()) if getter is not None else None
                    getattr(lib, name)(1)
                    found.append((getattr(lib, name), before))
                    break
    except OSError:
        pass
    try:
        yield
    finally:
        for setter, before in found:
            if before is not None:
                setter(before)


# ---------------------------------------------------------------------------------------------- processes
def fork_available() -> bool:
    """Whether this process may be forked (``multiprocessing``'s ``fork`` start method): Linux and BSD.
    Not macOS, where a forked child may crash in the system's libraries (Python starts processes by
    ``spawn`` there), nor Windows."""
    if without("fork") or not hasattr(os, "fork") or sys.platform == "darwin":
        return False
    import multiprocessing as mp

    return "fork" in mp.get_all_start_methods()


def spawn_detached(fn, *args, ready=None) -> int | None:
    """Run ``fn(*args)`` in a process of its own that outlives this one (a forked grandchild in a new
    session: a Ctrl-C in this command's terminal does not stop it; it is nobody's zombie), its output to
    nowhere, and return its pid once it has started; it ends when ``fn`` returns or raises. ``ready()``,
    if given, runs in that process first: when it returns False the process ends at once and None is
    returned. None also where processes cannot be forked (:func:`fork_available`): the caller does the
    work itself. Used for the background compilation of the kernels for the next run
    (:func:`needlecli.kernels.compile_in_background`)."""
    if not fork_available():
        return None
    r, w = os.pipe()
    try:
        pid = os.fork()
    except OSError:
        os.close(r)
        os.close(w)
        return None
    if pid == 0:  # the child: a new session, then the grandchild that does the work
        try:
            os.close(r)
            os.setsid()
            if os.fork() == 0:
                try:
                    signal.signal(signal.SIGINT, signal.SIG_IGN)
                    signal.signal(signal.SIGHUP, signal.SIG_IGN)
                    devnull = os.open(os.devnull, os.O_RDWR)
                    for fd in (0, 1, 2):
                        os.dup2(devnull, fd)
                    go = ready is None or ready()
                    os.write(w, str(os.getpid() if go else 0).encode())
                    os.close(w)
                    if go:
                        fn(*args)
                except BaseException:  # noqa: BLE001  (nobody to tell: the work's own files say what it did)
                    pass
                finally:
                    os._exit(0)
        finally:
            os._exit(0)  # the child ends at once: the grandchild is re-parented (no zombie)
    os.close(w)
    try:
        os.waitpid(pid, 0)
        with os.fdopen(r, "rb") as f:
            got = f.read().strip()
    except OSError:
        return None
    return int(got) if got.isdigit() and int(got) > 0 else None


_HELD_LOCKS: list = []


def hold_lock(path) -> bool:
    """Take the exclusive lock :func:`file_lock` names by ``path`` without waiting, and keep it until this
    process ends (the kernel releases a ``flock`` then, even after SIGKILL; a lock file is taken as stale
    once its process is gone). False when another holds it."""
    cm = file_lock(path, blocking=False)
    if cm.__enter__():
        _HELD_LOCKS.append(cm)
        return True
    cm.__exit__(None, None, None)
    return False


def lock_held(path) -> bool:
    """Whether another process (or another :func:`hold_lock` of this one) holds the lock of ``path``."""
    if not os.path.exists(path) and not os.path.exists(os.fspath(path) + ".excl"):
        return False
    with file_lock(path, blocking=False) as got:
        return not got


def die_with_parent() -> bool:
    """In a forked child: ask the kernel to send this process ``SIGTERM`` when its parent ends
    (``prctl(PR_SET_PDEATHSIG)``, Linux). Returns False when the parent has ended already (this process
    was re-parented before it asked: it should end now), else True (also where it cannot be asked)."""
    prctl = _libc("prctl") if sys.platform == "linux" else None
    if prctl is None:
        return True
    prctl(1, int(signal.SIGTERM))  # PR_SET_PDEATHSIG
    return os.getppid() != 1


def pid_alive(pid: int) -> bool:
    """Whether process ``pid`` of this machine runs (signal 0, POSIX). True where it cannot be known
    (Windows, where ``os.kill`` would end the process)."""
    if not _posix():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def parent_alive(parent: int) -> bool:
    """Whether the parent process ``parent`` (its pid) still runs: this process has not been re-parented
    (POSIX); elsewhere :func:`pid_alive`."""
    return os.getppid() == parent if _posix() else pid_alive(parent)


def parent_pid() -> int:
    """The pid of the process that started this one."""
    return os.getppid()


# ---------------------------------------------------------------------------------------------- signals
#: the signals that stop a command (exit 130 and 143); both exist on Linux, macOS and Windows
STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM)


def send_self(signum: int) -> None:
    """Send signal ``signum`` to this process: to the process (``kill``, POSIX), so that whichever thread
    sends it, the main thread's blocking call is interrupted and its handler runs; elsewhere
    ``signal.raise_signal``."""
    if _posix():
        os.kill(os.getpid(), signum)
    else:
        signal.raise_signal(signum)
