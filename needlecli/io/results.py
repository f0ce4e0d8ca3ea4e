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
"""

from __future__ import annotations

import datetime as _dt
from pathlib import Path

import h5py
import numpy as np

from needlecli import __version__
from needlecli.errors import DataError
from needlecli.io.atomic import deferred_signals, write_bytes_atomic
from needlecli.io.layout import RESULTS, check_layout
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


def _repeats(arr: np.ndarray) -> bool:
    """Whether ``arr`` (2-d or more) repeats along its first or second axis (a broadcast, a value per run
    held over time): gzip shrinks such arrays to almost nothing, fast. Checked on a corner first."""
    if 0 in arr.strides:
        return True
    for axis in (0, 1):
        first = np.take(arr, [0], axis=axis)
        corner = tuple(slice(0, 8) for _ in range(arr.ndim))
        if (arr[corner] == first[corner]).all() and (arr == first).all():
            return True
    return False


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
        elif big and (compression == "gzip" or (compression == "auto" and _repeats(arr))):
            g.create_dataset(k, data=arr, chunks=True, compression="gzip", compression_opts=1, shuffle=True)
        else:
            g.create_dataset(k, data=arr)
        for ak, av in grp.dataset_attrs.get(k, {}).items():
            g[k].attrs[ak] = _attr(av)


def file_image(root: Group, compression: str = "auto", done=None) -> bytes:
    """The HDF5 file of ``root``, built in memory. HDF5 itself never writes to disk here: a full disk
    met inside it ends in a crash (h5py cannot recover from a failed write), and a signal that arrives
    inside one of its callbacks is lost; so signals are held while it runs (acted on when it is done).

    ``compression``: ``auto`` compresses (gzip, level 1, shuffled) the large arrays that repeat along an
    axis (broadcast inputs, parameters held over time, constant noise levels: 10 to 1000 times smaller
    at once) and stores the others as they are (simulated states and estimates shrink by a quarter only,
    at ten times the writing time); ``gzip`` every large array (the smallest files); ``none`` nothing.
    ``done(nbytes)``, if given, is called before each array is written (a progress bar's step)."""
    if compression not in COMPRESSION:
        raise ValueError(f"compression {compression!r}: expected one of {', '.join(COMPRESSION)}")
    with deferred_signals(), h5py.File(f"needle-image-{id(root)}", "w", driver="core", backing_store=False) as f:
        _write_group(f, root, compression, done)
        f.flush()
        return f.id.get_file_image()


def write_atomic(path: str | Path, root: Group, compression: str = "auto", progress=None) -> Path:
    """Write ``root`` to ``path``: the file is built in memory (:func:`file_image`), then written to a
    temporary file beside ``path`` and renamed over it (:func:`~needlecli.io.atomic.write_bytes_atomic`),
    so that a reader never sees a half-written file, a full disk is one clear error, and the earlier file
    at ``path`` is kept until the new one is complete. ``progress(done, total)`` (bytes: the arrays
    copied into the file, then the file written) reports how far it is."""
    if progress is None:
        return write_bytes_atomic(path, file_image(root, compression))
    raw = max(_nbytes(root), 1)
    state = {"built": 0}

    def built(n: int) -> None:
        state["built"] += n
        progress(state["built"], 2 * raw)

    image = file_image(root, compression, built)
    total = raw + max(len(image), 1)
    progress(raw, total)
    out = write_bytes_atomic(path, image, progress=lambda k: progress(raw + k, total))
    progress(total, total)
    return out


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
    """Load a results file completely, its structure checked first against the documented layout
    (:data:`needlecli.io.layout.RESULTS`). Raises :class:`DataError` for missing, corrupt or damaged files,
    naming the HDF5 path of the first problem."""
    path = Path(path)
    if not path.exists():
        raise DataError(f"{path}: no such results file")
    try:
        with h5py.File(path, "r") as f:
            fmt = f.attrs.get("format")
            if fmt is None or "truth" not in f or "time" not in f:
                raise DataError(f"{path}: not a needlecli results file (no format attribute, /time or /truth)")
            fmt = _decode(fmt)
            if isinstance(fmt, np.ndarray) or not isinstance(fmt, (int, np.integer)):
                raise DataError(f"{path}: [/ attribute format] should be the integer {RESULTS_FORMAT}, is {fmt!r:.40}")
            if int(fmt) > RESULTS_FORMAT:
                raise DataError(
                    f"{path}: results format {int(fmt)} is newer than this needlecli reads ({RESULTS_FORMAT})"
                )
            check_layout(f, RESULTS, path)
            return _read(f)
    except DataError:
        raise
    except (OSError, KeyError, ValueError, TypeError, RuntimeError) as e:
        raise DataError(f"{path}: cannot read the results file ({e.__class__.__name__}: {_one_line(e)})") from None
