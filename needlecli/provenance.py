"""Where a result comes from: the package version and its git commit (recorded in every results file,
printed by ``needle --version``). Light: the standard library only."""

from __future__ import annotations

import subprocess
from pathlib import Path

from needlecli import __version__


def git_hash() -> str:
    """The package's git commit (``unknown`` outside a checkout), with ``-dirty`` for local changes."""
    here = Path(__file__).resolve().parent
    try:
        out = subprocess.run(
            ["git", "describe", "--always", "--dirty", "--abbrev=40"],
            cwd=here, capture_output=True, text=True, timeout=5, check=False,
        )
        return out.stdout.strip() or "unknown"
    except (OSError, subprocess.SubprocessError):
        return "unknown"


def version_line() -> str:
    """``needlecli <version> (git <hash>)``."""
    return f"needlecli {__version__} (git {git_hash()})"
