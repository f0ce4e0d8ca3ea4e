"""The fit file of ``needle fit-em`` (docs/reference/fit-file.md): root attribute ``format = "needlecli-fit"``,
``version``. Written by :func:`needlecli.experiments.studies.fit.fit_tree` through
:func:`~needlecli.io.results.write_atomic`; read here, and checked when it is read (every reader: ``needle
evaluate``, ``from_fit`` of an observer or of a fit section, ``needle crossval``'s tuned observers):

* its structure against the documented layout (:data:`needlecli.io.layout.FIT`);
* its values (:func:`check_fit_values`): in every trial whose fit did not fail (status other than
  ``singular`` or ``diverged``, which may hold NaN from where they stopped), each ``Q`` and each channel's
  ``R`` finite, symmetric and positive semi-definite, each fitted constant finite; each ``R/<channel>`` a
  channel of ``/measurements``, of the shape of its components (``m x m``, or ``2 x 2`` for a direction,
  whose R is in its tangent plane: attribute ``coordinates``, or without it a 3-component channel's 2 x 2).

The first problem is a :class:`~needlecli.errors.DataError` naming the file and the HDF5 path:
``f.h5: [/fit/mnm/Q] trial 3: entry (2, 2) = -0.0001 < 0, a variance cannot be negative``. What the fit
must agree with in a config (its model's states, its channels the config's sensors) is checked where a
config takes it: :mod:`needlecli.experiments.config.from_fit`."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from needlecli.errors import DataError, shown

if TYPE_CHECKING:
    import h5py
from needlecli.io.layout import FIT, _what, check_layout, root_attribute
from needlecli.io.results import Group, _one_line, _read

FIT_FORMAT = "needlecli-fit"
FIT_VERSION = 1
#: statuses of a trial whose fit failed (needlecli.fitting.em): its matrices may hold NaN, and are not checked
FAILED = ("singular", "diverged")
#: tolerances of a noise matrix, relative to its largest variance (as an observer's covariances:
#: needlecli.observers.contract)
SYMMETRY_RTOL = 1e-6
PSD_RTOL = 1e-6

#: the verdicts of ``/fit/<model>/identifiability`` (:mod:`needlecli.fitting.identify` decides them; every
#: table that shows one reads it from the file)
IDENTIFIED = "identified"
WEAK = "weakly identified"
NOT_IDENTIFIED = "not identified"
STOPPED_SHORT = "EM stopped short of the maximum"
BIASED = "biased"
OUTSIDE = "outside its bounds"  # a value the quantity cannot take: never identified, whatever the curvature
#: the verdicts in the order a count lists them
VERDICTS = (IDENTIFIED, WEAK, STOPPED_SHORT, NOT_IDENTIFIED, BIASED, OUTSIDE)


def verdict_text(verdict: str, z: float = np.nan) -> str:
    """A verdict as tables print it: ``biased (estimate - truth = +6.4 SE)`` with the group's ``z``; the
    others as they are."""
    if verdict == BIASED and np.isfinite(z):
        return f"{BIASED} (estimate - truth = {z:+.1f} SE)"
    return verdict


def is_fit_file(path: str | Path) -> bool:
    """Whether ``path`` is an HDF5 file with the fit format (False for anything else, unreadable too)."""
    from needlecli.io.inputs import root_format

    return root_format(path) == "fit"


def read_fit(path: str | Path) -> Group:
    """Load a fit file completely, its kind and format checked first (:mod:`needlecli.io.inputs`). Raises
    :class:`DataError` for missing, corrupt or newer files and files of another kind."""
    from needlecli.io.inputs import describe, open_hdf5

    path = Path(path)
    try:
        with open_hdf5(path, "a fit file") as f:
            fmt = root_attribute(f, "format", "any", path)
            if isinstance(fmt, np.ndarray):  # an array where the documented text is: named with its path
                root_attribute(f, "format", "str", path)
            if not isinstance(fmt, str) or fmt != FIT_FORMAT or "fit" not in f or "time" not in f:
                raise DataError(f"{shown(path)}: not a needlecli fit file: it is {describe(path)} (format "
                                f"{_what(fmt) if fmt is not None else 'none'}, no /fit or /time)")
            version = f.attrs.get("version", 0)
            if not isinstance(version, (int, np.integer)):
                raise DataError(f"{path}: [/ attribute version] should be an integer, is {version!r:.40}")
            if int(version) > FIT_VERSION:
                raise DataError(f"{path}: fit file version {int(version)} is newer than this needlecli "
                                f"reads ({FIT_VERSION})")
            check_layout(f, FIT, path)
            check_fit_values(f, path)
            return _read(f)
    except DataError:
        raise
    except (OSError, KeyError, ValueError, TypeError, RuntimeError) as e:
        raise DataError(f"{path}: cannot read the fit file ({e.__class__.__name__}: {_one_line(e)})") from None


def _texts(v) -> list[str]:
    return [x.decode() if isinstance(x, bytes) else str(x) for x in np.atleast_1d(v)]


def check_fit_values(f: h5py.File, path: str | Path) -> None:
    """The values of an open fit file whose layout is checked (module docstring); a :class:`DataError`
    naming the HDF5 path at the first problem."""
    meas = f["measurements"] if "measurements" in f else None
    for model, g in f["fit"].items():
        where = f"/fit/{model}"
        status = np.array(_texts(g["status"][()]))
        use = ~np.isin(status, FAILED)  # (N,) the trials whose fit did not fail
        _noise_matrix(np.asarray(g["Q"][()], dtype=float), use, f"{where}/Q", path)
        if "constant" in g:
            for c, ds in g["constant"].items():
                v = np.asarray(ds[()], dtype=float)
                bad = np.flatnonzero(use & ~np.isfinite(v))
                if bad.size:
                    t = int(bad[0])
                    raise _fail(path, f"{where}/constant/{c}", f"trial {t}: {v[t]} is not finite, in a fit that "
                                f"did not fail (status {str(status[t])})")
        if "R" not in g:
            continue
        for ch, ds in g["R"].items():
            if ch.endswith("_guess"):
                continue
            at = f"{where}/R/{ch}"
            R = np.asarray(ds[()], dtype=float)
            if R.ndim != 3 or R.shape[0] != len(status):
                raise _fail(path, at, f"has shape {R.shape}, expected (N, m, m) with N = {len(status)} trials")
            if meas is not None:
                if ch not in meas:
                    raise _fail(path, at, f"channel {ch!r} is not one of the fit's measurements "
                                f"(/measurements: {', '.join(meas) or 'none'})")
                names = _texts(meas[ch].attrs.get("names", []))
                m = int(meas[ch]["value"].shape[-1])
                coords = ds.attrs.get("coordinates", "")
                coords = coords.decode() if isinstance(coords, bytes) else str(coords)
                # without the attribute (older files): a unit vector's 2 x 2
                direction = coords.startswith("tangent plane") or (not coords and m == 3 and R.shape[-1] == 2)
                want = m - 1 if direction else m
                if R.shape[1:] != (want, want):
                    what = (f"a direction's R in its tangent plane, {want} x {want}" if direction
                            else f"{want} x {want}, one row per component ({', '.join(names)})")
                    raise _fail(path, at, f"has matrices of {R.shape[1]} x {R.shape[2]}; channel {ch!r} has {m} "
                                f"components: expected {what}")
            _noise_matrix(R, use, at, path)


def _fail(path, where: str, msg: str) -> DataError:
    return DataError(f"{path}: [{where}] {msg}")


def _noise_matrix(A: np.ndarray, use: np.ndarray, where: str, path) -> None:
    """Noise matrices ``A (N, k, k)`` of the trials ``use (N,)``: finite, non-negative variances, symmetric
    (``|A - A^T| <= SYMMETRY_RTOL * s``) and positive semi-definite (eigenvalues ``>= -PSD_RTOL * s``), ``s``
    the matrix's largest variance; all trials at once."""
    idx = np.flatnonzero(use)
    if not idx.size or A.shape[-1] == 0:
        return
    B = A[idx]
    fin = np.isfinite(B)
    if not fin.all():
        r, i, j = (int(x) for x in np.argwhere(~fin)[0])
        raise _fail(path, where, f"trial {idx[r]}: entry ({i}, {j}) = {B[r, i, j]} is not finite, in a fit that did "
                    "not fail")
    diag = np.diagonal(B, axis1=-2, axis2=-1)
    if (diag < 0).any():
        r, i = (int(x) for x in np.argwhere(diag < 0)[0])
        raise _fail(path, where, f"trial {idx[r]}: entry ({i}, {i}) = {diag[r, i]:.6g} < 0: a variance cannot be "
                    "negative")
    scale = np.maximum(diag.max(axis=-1), np.finfo(float).tiny)  # (n,)
    asym = np.abs(B - np.swapaxes(B, -1, -2)) > SYMMETRY_RTOL * scale[:, None, None]
    if asym.any():
        r, i, j = (int(x) for x in np.argwhere(asym)[0])
        raise _fail(path, where, f"trial {idx[r]}: not symmetric: entry ({i}, {j}) = {B[r, i, j]:.6g} but ({j}, {i}) "
                    f"= {B[r, j, i]:.6g}")
    low = np.linalg.eigvalsh(B)[:, 0]  # (n,) the smallest eigenvalue of each
    bad = np.flatnonzero(low < -PSD_RTOL * scale)
    if bad.size:
        r = int(bad[0])
        raise _fail(path, where, f"trial {idx[r]}: not positive semi-definite: smallest eigenvalue {low[r]:.3g}, "
                    f"largest variance {scale[r]:.3g}")
