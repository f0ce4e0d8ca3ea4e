"""Typed errors. Library code raises them; only the CLI turns them into messages and exit codes."""

from __future__ import annotations


class NeedleError(Exception):
    """Base of every error that is the user's to fix (bad config, bad data). Exit code 2."""

    exit_code = 2


class ConfigError(NeedleError):
    """A config file that does not parse or does not pass the schema.

    Parameters
    ----------
    source : str
        The file (or ``<string>``) the config came from.
    loc : tuple
        Key path inside the config, e.g. ``("sensors", 0, "rate")``.
    message : str
        What is wrong, in one line.
    """

    def __init__(self, source: str, loc: tuple = (), message: str = "") -> None:
        self.source = source
        self.loc = tuple(loc)
        self.message = message
        super().__init__(str(self))

    def __str__(self) -> str:
        where = f" [{' -> '.join(str(p) for p in self.loc)}]" if self.loc else ""
        return f"{self.source}:{where} {self.message}"


class DataError(NeedleError):
    """A results file or log that is missing, corrupt, truncated or holds bad values."""


class SweepError(NeedleError):
    """A sweep that cannot start: a bad grid, a cell whose config is invalid, an executor not available;
    or a sweep table asked for a metric or parameter it does not have."""
