"""The results file: one HDF5 file per experiment. Its layout is a public contract (docs/reference/results-file.md); change it only with a version bump of :data:`RESULTS_FORMAT`.

::

    /                         attrs: format, config (YAML), seed, needlecli_version, git_hash, created,
                                     name, model, length_unit, runs
    /time                     (T,) s
    /depth                    (T,) inserted length
    /truth/state              (N, T, n)          attrs names, units, angles
    /truth/status, /reason    (N,) str           ok | singular | diverged
    /truth/event_time         (N,) s             when a run stopped (NaN: it did not)
    /truth/params/<name>      (N, T)             model parameters along the run (tissue layers)
    /truth/interfaces         (K,)               tissue interface depths
    /inputs/<name>            (N, T[, k])        attrs unit
    /measurements/<sensor>/t, /t_available, /index   (M,)
    /measurements/<sensor>/value   (N, M, m)     attrs names, units, type, rate, latency, ...
    /measurements/<sensor>/valid   (N, M) bool
    /measurements/<sensor>/sigma   (N, M, m)
    /estimates/<observer>/state    (N, T, n)     attrs names, units, angles, type
    /estimates/<observer>/cov      (N, T', n, n) or (N, T', n)   attrs layout (full|diag), stride
    /estimates/<observer>/cov_index (T',)        indices of the time grid of the stored covariances
    /estimates/<observer>/status, /reason (N,) str
    /estimates/<observer>/<extra>  further arrays an observer reports
    /control/<controller>/command  (N, T)        closed loops only (config section control:): what a
    /control/<controller>/...                    controller applied, and from which samples
    /compare/...                   needle compare only: what it decided per observer run (K,) and skipped (S,)
    /crossval/...                  needle crossval's folds only: the fold's trials, tuned observers, constants
"""

from __future__ import annotations

import datetime as _dt
import itertools
import mmap
import os
from pathlib import Path

import h5py
import numpy as np

from needlecli import __version__, platform
from needlecli.errors import DataError, shown
from needlecli.io.atomic import atomic_path, deferred_signals, write_fd
from needlecli.io.layout import RESULTS, _what, check_layout, root_attribute
from needlecli.io.tree import Group
from needlecli.provenance import git_hash

RESULTS_FORMAT = 1
_STR = h5py.string_dtype("utf-8")


def _attr(v):
    if isinstance(v, (list, tuple)) and (not v or isinstance(v[0], str)):
        return np.array(list(v), dtype=_STR)
    if isinstance(v, np.ndarray) and v.dtype.kind in "UO":
        return v.astype(_STR)
    return v


COMPRESSION = ("auto", "gzip", "none")
_CHUNK_BYTES = 2**20  # target size of a chunk of a compressed dataset


def _repeat_axis(arr: np.ndarray) -> int | None:
    """The axis (0 or 1) along which ``arr`` (2-d or more) repeats (a broadcast, a value per run held over
    time), else None: gzip shrinks such arrays to almost nothing. Checked on a corner first."""
    for axis in (0, 1):
        if arr.strides[axis] == 0:
            return axis
    for axis in (0, 1):
        first = np.take(arr, [0], axis=axis)
        corner = tuple(slice(0, 8) for _ in range(arr.ndim))
        if (arr[corner] == first[corner]).all() and (arr == first).all():
            return axis
    return None


def _repeats(arr: np.ndarray) -> bool:
    return _repeat_axis(arr) is not None


def _repeat_chunks(shape: tuple[int, ...], itemsize: int, axis: int) -> tuple[int, ...]:
    """Chunks of about :data:`_CHUNK_BYTES` for an array repeating along ``axis``: whole along the axes
    after the first two, so that chunks at different positions along ``axis`` hold the same values."""
    rest = int(np.prod(shape[2:], dtype=np.int64)) * itemsize
    per = max(1, _CHUNK_BYTES // max(rest, 1))  # elements of the first two axes per chunk
    if axis == 0:  # rows all alike: whole rows of the second axis if they fit
        c1 = min(shape[1], per)
        c0 = min(shape[0], max(1, per // c1))
    else:  # each row constant along axis 1: as many rows as fit with a long run of axis 1
        c0 = min(shape[0], 64)
        c1 = min(shape[1], max(1, per // c0))
    return (c0, c1) + tuple(shape[2:])


def _write_repeating(g: h5py.Group, k: str, arr: np.ndarray, axis: int) -> None:
    """A gzipped dataset of an array repeating along ``axis``: each distinct chunk compressed once (by HDF5,
    from the array), then its bytes written at every position along ``axis`` where it recurs. The file is
    the one HDF5 would write chunk by chunk; the work is that of one row of chunks."""
    chunks = _repeat_chunks(arr.shape, arr.dtype.itemsize, axis)
    d = g.create_dataset(k, shape=arr.shape, dtype=arr.dtype, chunks=chunks, compression="gzip",
                         compression_opts=1, shuffle=True)
    n_along = -(-arr.shape[axis] // chunks[axis])
    grid = [range(0, arr.shape[i], chunks[i]) for i in range(arr.ndim)]
    grid[axis] = range(0, 1)
    for start in itertools.product(*grid):
        region = tuple(slice(o, o + c) for o, c in zip(start, chunks))
        d[region] = arr[region]
        if n_along > 1:
            mask, raw = d.id.read_direct_chunk(start)
            for i in range(1, n_along):
                offset = list(start)
                offset[axis] = i * chunks[axis]
                d.id.write_direct_chunk(tuple(offset), raw, mask)


def _nbytes(grp: Group) -> int:
    """The bytes of every array below ``grp`` (what building its file has to copy)."""
    return sum(_nbytes(v) if isinstance(v, Group) else np.asarray(v).nbytes for v in grp.data.values())


def _write_group(g: h5py.Group, grp: Group, compression: str = "auto", done=None) -> None:
    for k, v in grp.attrs.items():
        g.attrs[k] = _attr(v)
    for k, v in grp.data.items():
        if isinstance(v, Group):
            _write_group(g.create_group(k), v, compression, done)
            continue
        arr = np.asarray(v)
        if done is not None:
            done(arr.nbytes)
        big = arr.ndim >= 2 and arr.size > 4096
        if arr.dtype.kind in "UO":
            g.create_dataset(k, data=arr.astype(str).astype(_STR), dtype=_STR)
        elif big and compression != "none" and (axis := _repeat_axis(arr)) is not None:
            _write_repeating(g, k, arr, axis)
        elif big and compression == "gzip":
            g.create_dataset(k, data=arr, chunks=True, compression="gzip", compression_opts=1, shuffle=True)
        else:
            g.create_dataset(k, data=arr)
        for ak, av in grp.dataset_attrs.get(k, {}).items():
            g[k].attrs[ak] = _attr(av)


def _size_bound(grp: Group) -> int:
    """An upper bound of the size of the HDF5 file of ``grp`` (any compression): the arrays' bytes as they
    are, plus generous room for HDF5's own structures, attributes and strings."""
    total = 1 << 20
    for v in grp.attrs.values():
        total += 4096 + 2 * len(str(v).encode())
    for k, v in grp.data.items():
        if isinstance(v, Group):
            total += _size_bound(v)
            continue
        arr = np.asarray(v)
        total += 64 * 1024 + arr.nbytes // 64  # a chunk index, deflate's worst case (under 0.1 %)
        if arr.dtype.kind in "UO":
            total += sum(len(str(x).encode()) + 32 for x in arr.ravel())
        else:
            total += arr.nbytes
        for av in grp.dataset_attrs.get(k, {}).values():
            total += 4096 + 2 * len(str(av).encode())
    return total


def file_image(root: Group, compression: str = "auto", done=None) -> bytes:
    """The HDF5 file of ``root``, built in memory, for file systems that cannot reserve room ahead (see
    :func:`write_atomic`). HDF5 itself never writes to disk here: a full disk met inside it ends in a
    crash (h5py cannot recover from a failed write), and a signal that arrives inside one of its callbacks
    is lost; so signals are held while it runs (acted on when it is done).

    ``compression``: ``auto`` compresses (gzip, level 1, shuffled) the large arrays that repeat along an
    axis (broadcast inputs, parameters held over time, constant noise levels: 10 to 1000 times smaller
    at once) and stores the others as they are (simulated states and estimates shrink by a quarter only,
    at ten times the writing time); ``gzip`` every large array (the smallest files); ``none`` nothing.
    ``done(nbytes)``, if given, is called before each array is written (a progress bar's step)."""
    if compression not in COMPRESSION:
        raise ValueError(f"compression {compression!r}: expected one of {', '.join(COMPRESSION)}")
    with deferred_signals(), h5py.File(f"needle-image-{id(root)}", "w", driver="core", backing_store=False,
                                       block_size=min(1 << 26, max(1 << 16, _size_bound(root)))) as f:
        _write_group(f, root, compression, done)
        f.flush()
        return f.id.get_file_image()


_ALIGN = 4096  # O_DIRECT: file offsets, lengths and buffer addresses in whole blocks
_BOUNCE = 8 * 2**20  # the aligned buffer the arrays go through on their way to the disk


class _Reserved:
    """The file object HDF5 writes through (h5py's ``fileobj`` driver): positioned reads and writes on a
    descriptor whose room has been reserved; the size HDF5 sees is what it has written.

    With ``direct`` (a second descriptor of the file opened ``O_DIRECT``) the whole blocks of a large write
    (an array's data) go to the disk without the page cache, through an aligned buffer: an array is copied
    once, not into cache pages that the kernel must first find and later write back (which costs more than
    the copy on virtual machines, where fresh memory is slow), and the final ``fsync`` has little left to
    do. The ends of such a write, and everything small (HDF5's own structures), take the page cache."""

    def __init__(self, fd: int, direct: int | None = None) -> None:
        self.fd, self.pos, self.end = fd, 0, 0
        self.direct = direct
        self._bounce: mmap.mmap | None = None

    def seek(self, pos: int, whence: int = 0) -> int:
        self.pos = pos if whence == 0 else self.pos + pos if whence == 1 else self.end + pos
        return self.pos

    def tell(self) -> int:
        return self.pos

    def read(self, n: int = -1) -> bytes:
        b = os.pread(self.fd, (self.end - self.pos) if n < 0 else n, self.pos)
        self.pos += len(b)
        return b

    def readinto(self, buf) -> int:
        k = os.preadv(self.fd, [buf], self.pos)
        self.pos += k
        return k

    def _pwrite(self, fd: int, view: memoryview, at: int) -> None:
        done = 0
        while done < len(view):
            done += os.pwrite(fd, view[done:], at + done)

    def write(self, b) -> int:
        view = memoryview(b).cast("B")
        n, at = len(view), self.pos
        lo = -at % _ALIGN  # bytes up to the first whole block
        hi = (at + n) // _ALIGN * _ALIGN - at  # ... and to the end of the last one
        if self.direct is None or hi - lo < _BOUNCE // 4:
            self._pwrite(self.fd, view, at)
        else:
            self._pwrite(self.fd, view[:lo], at)
            if self._bounce is None:
                self._bounce = mmap.mmap(-1, _BOUNCE)
            bounce = memoryview(self._bounce)
            for i in range(lo, hi, _BOUNCE):
                k = min(_BOUNCE, hi - i)
                bounce[:k] = view[i : i + k]
                self._pwrite(self.direct, bounce[:k], at + i)
            self._pwrite(self.fd, view[hi:], at + hi)
        self.pos = at + n
        self.end = max(self.end, self.pos)
        return n

    def truncate(self, size: int | None = None) -> int:
        size = self.pos if size is None else int(size)
        os.ftruncate(self.fd, size)
        self.end = size
        return size

    def flush(self) -> None:
        pass

    def close(self) -> None:
        if self._bounce is not None:
            self._bounce.close()
            self._bounce = None


def write_atomic(path: str | Path, root: Group, compression: str = "auto", progress=None) -> Path:
    """Write ``root`` to ``path``, so that a reader never sees a half-written file, a full disk is one clear
    error, and the earlier file at ``path`` is kept until the new one is complete: the file is written to
    a temporary file beside ``path`` and renamed over it (:func:`~needlecli.io.atomic.atomic_path`).

    HDF5 must never meet a full disk (it cannot recover from a failed write): the room for the whole file
    (:func:`_size_bound`, more than it needs) is reserved first (:func:`needlecli.platform.reserve`,
    ``posix_fallocate``: a full disk fails there, before HDF5 starts), then HDF5 writes the arrays straight
    from memory into it (one copy, no file image; signals held while it works; the arrays' whole blocks
    past the page cache where :func:`needlecli.platform.open_direct` can) and the file is cut to its size.
    Where the platform (macOS, Windows) or the file system cannot reserve room, the file is built in
    memory and written after (:func:`file_image`).

    ``progress(done, total)`` (bytes: the arrays copied into the file, and the file image written where
    one is built) reports how far it is."""
    if compression not in COMPRESSION:
        raise ValueError(f"compression {compression!r}: expected one of {', '.join(COMPRESSION)}")
    path = Path(path)
    raw = max(_nbytes(root), 1)
    state = {"built": 0, "total": raw}

    def built(n: int) -> None:
        state["built"] += n
        progress(min(state["built"], state["total"]), state["total"])

    done = built if progress is not None else None
    with atomic_path(path) as tmp:
        fd = os.open(tmp, os.O_RDWR)
        try:
            if platform.has_positioned_io() and platform.reserve(fd, _size_bound(root)):
                direct = platform.open_direct(tmp)  # a second descriptor, for the arrays' whole blocks
                target = _Reserved(fd, direct)
                try:
                    with deferred_signals(), h5py.File(target, "w") as f:
                        _write_group(f, root, compression, done)
                finally:
                    target.close()
                    if direct is not None:
                        os.close(direct)
            else:
                state["total"] = 2 * raw
                image = file_image(root, compression, done)
                total = state["total"] = raw + max(len(image), 1)
                if progress is not None:
                    progress(raw, total)
                write_fd(fd, image, (lambda k: progress(raw + k, total)) if progress is not None else None)
        finally:
            os.close(fd)
    if progress is not None:
        progress(state["total"], state["total"])
    return path


def root_attrs(config_text: str, seed: int, extra: dict | None = None) -> dict:
    out = {
        "format": RESULTS_FORMAT,
        "config": config_text,
        "seed": seed,
        "needlecli_version": __version__,
        "git_hash": git_hash(),
        "created": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
    }
    out.update(extra or {})
    return out


# ---------------------------------------------------------------------------------------------- reading
def _decode(v):
    if isinstance(v, bytes):
        return v.decode()
    if isinstance(v, np.ndarray) and v.dtype.kind in "OS":
        return np.array([x.decode() if isinstance(x, bytes) else x for x in v.ravel()]).reshape(v.shape)
    return v


def _read(g: h5py.Group) -> Group:
    out = Group(attrs={k: _decode(v) for k, v in g.attrs.items()})
    for k, v in g.items():
        if isinstance(v, h5py.Group):
            out.data[k] = _read(v)
        else:
            arr = v[()]
            out.data[k] = _decode(arr) if (v.dtype.kind in "OS") else arr
    return out


def _one_line(e: BaseException) -> str:
    return " ".join(str(e).split())[:300]


def read_results(path: str | Path) -> Group:
    """Load a results file completely: its kind and format checked first (:mod:`needlecli.io.inputs`), then
    its structure against the documented layout (:data:`needlecli.io.layout.RESULTS`). Raises
    :class:`DataError` for missing, corrupt or damaged files and files of another kind, naming the HDF5
    path of the first problem."""
    from needlecli.io.inputs import describe, open_hdf5

    path = Path(path)
    try:
        with open_hdf5(path, "a results file") as f:
            fmt = root_attribute(f, "format", "any", path)
            missing = [n for n in ("time", "truth") if n not in f]
            if fmt is None or missing:
                kind = describe(path)
                what = "" if kind.startswith("a results file") else f": it is {kind}"
                lacks = "no format attribute" if fmt is None else "no " + " or ".join("/" + m for m in missing)
                raise DataError(f"{shown(path)}: not a needlecli results file{what} ({lacks})")
            if isinstance(fmt, bool) or not isinstance(fmt, int):
                raise DataError(f"{shown(path)}: [/ attribute format] should be the integer {RESULTS_FORMAT}, is "
                                f"{_what(fmt)}")
            if fmt > RESULTS_FORMAT:
                raise DataError(f"{shown(path)}: results format {fmt} is newer than this needlecli reads "
                                f"({RESULTS_FORMAT})")
            check_layout(f, RESULTS, path)
            return _read(f)
    except DataError:
        raise
    except (OSError, KeyError, ValueError, TypeError, RuntimeError) as e:
        raise DataError(f"{shown(path)}: cannot read the results file ({e.__class__.__name__}: {_one_line(e)})") from None
