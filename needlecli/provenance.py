"""Where a result comes from: the package version and its git commit (recorded in every results file,
printed by ``needle --version``, compared between a sweep's submitter and its workers). Light: the
standard library only.

``NEEDLECLI_REPORT_VERSION`` (``VERSION`` or ``VERSION GIT``), where set, replaces what this process
reports: a testing aid for a cluster whose workers run another needlecli than the submitter's.
"""

from __future__ import annotations

import functools
import hashlib
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
    """``{"version", "git"}``: what two processes must share to compute the same cells (a sweep's resume key,
    its workers against its submitter): the version, and the commit of the package's code with a hash of its
    uncommitted changes to the package's own files (:func:`code_state`; edits elsewhere in the checkout, of
    documents or tests, do not count)."""
    r = _reported()
    return {"version": version(), "git": r[1] if len(r) > 1 else _code_state()}


@functools.lru_cache(maxsize=1)
def _code_state() -> str:
    return code_state(Path(__file__).resolve().parent)


def code_state(package: Path) -> str:
    """The git commit of the checkout holding the folder ``package``, followed by ``+`` and 12 hex digits of
    the sha256 of the uncommitted changes to the files below ``package`` (their diff against the commit,
    and the content of those git does not track and does not ignore) where there are any: two checkouts
    give the same answer when their code is the same. ``unknown`` outside a checkout."""
    def git(*args: str) -> bytes | None:
        try:
            out = subprocess.run(["git", *args], cwd=package, capture_output=True, timeout=10, check=False)
        except (OSError, subprocess.SubprocessError):
            return None
        return out.stdout if out.returncode == 0 else None

    head = git("rev-parse", "HEAD")
    if not head:
        return "unknown"
    commit = head.decode().strip()
    diff = git("diff", "HEAD", "--binary", "--", ".") or b""
    untracked = (git("ls-files", "--others", "--exclude-standard", "-z", "--", ".") or b"").split(b"\0")
    h = hashlib.sha256(diff)
    for name in sorted(n for n in untracked if n):
        h.update(name + b"\0")
        try:
            h.update((package / name.decode()).read_bytes())
        except OSError:
            pass
    return commit if not diff and not any(untracked) else f"{commit}+{h.hexdigest()[:12]}"


def describe(ident: dict[str, str]) -> str:
    """``needlecli <version> (git <hash>)`` of an :func:`identity`."""
    return f"needlecli {ident.get('version', '?')} (git {ident.get('git', '?')})"


def version_line() -> str:
    """``needlecli <version> (git <hash>)``."""
    return describe(identity())
