"""The fit file of ``needle fit-em`` (docs/reference/fit-file.md): root attribute ``format = "needlecli-fit"``,
``version``. Written by :func:`needlecli.experiments.studies.fit.fit_tree` through
:func:`~needlecli.io.results.write_atomic`; read here."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from needlecli.errors import DataError, shown
from needlecli.io.layout import FIT, _what, check_layout, root_attribute
from needlecli.io.results import Group, _one_line, _read

FIT_FORMAT = "needlecli-fit"
FIT_VERSION = 1


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
            return _read(f)
    except DataError:
        raise
    except (OSError, KeyError, ValueError, TypeError, RuntimeError) as e:
        raise DataError(f"{path}: cannot read the fit file ({e.__class__.__name__}: {_one_line(e)})") from None
