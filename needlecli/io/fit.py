"""The fit file of ``needle fit-em`` (docs/reference/fit-file.md): root attribute ``format = "needlecli-fit"``,
``version``. Written by :func:`needlecli.experiments.studies.fit.fit_tree` through
:func:`~needlecli.io.results.write_atomic`; read here."""

from __future__ import annotations

from pathlib import Path

import h5py
import numpy as np

from needlecli.errors import DataError
from needlecli.io.layout import FIT, check_layout
from needlecli.io.results import Group, _one_line, _read

FIT_FORMAT = "needlecli-fit"
FIT_VERSION = 1

#: the verdicts of ``/fit/<model>/identifiability`` (:mod:`needlecli.fitting.identify` decides them; every
#: table that shows one reads it from the file)
IDENTIFIED = "identified"
WEAK = "weakly identified"
NOT_IDENTIFIED = "not identified"
STOPPED_SHORT = "EM stopped short of the maximum"
BIASED = "biased"
#: the verdicts in the order a count lists them
VERDICTS = (IDENTIFIED, WEAK, STOPPED_SHORT, NOT_IDENTIFIED, BIASED)


def verdict_text(verdict: str, z: float = np.nan) -> str:
    """A verdict as tables print it: ``biased (estimate - truth = +6.4 SE)`` with the group's ``z``; the
    others as they are."""
    if verdict == BIASED and np.isfinite(z):
        return f"{BIASED} (estimate - truth = {z:+.1f} SE)"
    return verdict


def is_fit_file(path: str | Path) -> bool:
    """Whether ``path`` is an HDF5 file with the fit format (False for anything else, unreadable too)."""
    try:
        with h5py.File(path, "r") as f:
            fmt = f.attrs.get("format")
            return (fmt.decode() if isinstance(fmt, bytes) else fmt) == FIT_FORMAT
    except (OSError, ValueError):
        return False


def read_fit(path: str | Path) -> Group:
    """Load a fit file completely. Raises :class:`DataError` for missing, corrupt or newer files."""
    path = Path(path)
    if not path.exists():
        raise DataError(f"{path}: no such fit file")
    try:
        with h5py.File(path, "r") as f:
            fmt = f.attrs.get("format")
            fmt = fmt.decode() if isinstance(fmt, bytes) else fmt
            if fmt != FIT_FORMAT or "fit" not in f or "time" not in f:
                raise DataError(f"{path}: not a needlecli fit file (format {fmt!r}, no /fit or /time)")
            version = f.attrs.get("version", 0)
            if not isinstance(version, (int, np.integer)):
                raise DataError(f"{path}: [/ attribute version] should be an integer, is {version!r:.40}")
            if int(version) > FIT_VERSION:
                raise DataError(f"{path}: fit file version {int(version)} is newer than this needlecli "
                                f"reads ({FIT_VERSION})")
            check_layout(f, FIT, path)
            return _read(f)
    except DataError:
        raise
    except (OSError, KeyError, ValueError, TypeError, RuntimeError) as e:
        raise DataError(f"{path}: cannot read the fit file ({e.__class__.__name__}: {_one_line(e)})") from None
