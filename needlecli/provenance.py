"""Where a result comes from: the package version and its git commit (recorded in every results file,
printed by ``needle --version``, compared between a sweep's submitter and its workers). Light: the
standard library only.

``NEEDLECLI_REPORT_VERSION`` (``VERSION`` or ``VERSION GIT``), where set, replaces what this process
reports: a testing aid for a cluster whose workers run another needlecli than the submitter's.
"""

from __future__ import annotations

import functools
import os
import subprocess
from pathlib import Path

from needlecli import __version__

REPORT_ENV = "NEEDLECLI_REPORT_VERSION"


@functools.lru_cache(maxsize=1)
def _git_hash() -> str:
    here = Path(__file__).resolve().parent
    try:
        out = subprocess.run(
            ["git", "describe", "--always", "--dirty", "--abbrev=40"],
            cwd=here, capture_output=True, text=True, timeout=5, check=False,
        )
        return out.stdout.strip() or "unknown"
    except (OSError, subprocess.SubprocessError):
        return "unknown"


def _reported() -> list[str]:
    return os.environ.get(REPORT_ENV, "").split()


def version() -> str:
    """The package version this process reports."""
    r = _reported()
    return r[0] if r else __version__


def git_hash() -> str:
    """The package's git commit (``unknown`` outside a checkout), with ``-dirty`` for local changes."""
    r = _reported()
    return r[1] if len(r) > 1 else _git_hash()


def identity() -> dict[str, str]:
    """``{"version", "git"}``: what two processes must share to compute the same cells."""
    return {"version": version(), "git": git_hash()}


def describe(ident: dict[str, str]) -> str:
    """``needlecli <version> (git <hash>)`` of an :func:`identity`."""
    return f"needlecli {ident.get('version', '?')} (git {ident.get('git', '?')})"


def version_line() -> str:
    """``needlecli <version> (git <hash>)``."""
    return describe(identity())
