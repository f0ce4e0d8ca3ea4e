"""Typed errors. Library code raises them; only the CLI turns them into messages and exit codes."""

from __future__ import annotations


def shown(name: object) -> str:
    """A file name, a path or a name as a message shows it: as it is when every character is printable,
    else quoted with its control characters escaped (``'bad\\nname.yaml'``), so that a name holding a
    newline or a terminal's escape sequence can neither split a message's line nor act on the terminal."""
    text = str(name)
    return text if text.isprintable() else repr(text)


def one_line(message: object) -> str:
    """A message as one line: a library's wrapped lines (a newline followed by indentation) joined with
    a space, runs of spaces made one, and every other character that is not printable escaped
    (``\\n``, ``\\x1b``): what a name in the message holds is shown, never acted on."""
    import re

    text = re.sub(r"[ \t]*\r?\n[ \t]+", " ", str(message).strip())
    text = re.sub(r" {2,}", " ", text)
    return "".join(c if c.isprintable() else repr(c)[1:-1] for c in text)


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
        return f"{shown(self.source)}:{where} {self.message}"


class DataError(NeedleError):
    """A results file or log that is missing, corrupt, truncated or holds bad values."""


class SweepError(NeedleError):
    """A sweep that cannot start: a bad grid, a cell whose config is invalid, an executor not available;
    or a sweep table asked for a metric or parameter it does not have."""


class OutputError(NeedleError):
    """An output that cannot be written: a folder given for a file, a read-only place, a name too long, a
    full disk. Raised before the work where it can be seen then (the checks of :mod:`needlecli.io.atomic`)."""

    def __init__(self, path, message: str) -> None:
        self.path = path
        self.message = message
        super().__init__(f"{shown(path)}: {message}")


class ComponentError(NeedleError):
    """A component (model, sensor, pipeline, observer, controller: built-in or a plug-in) that failed in a
    call -- raised, or called ``sys.exit`` -- or returned something that breaks its contract (a shape
    that does not fit the problem, NaN in a run it marked ok, a covariance that is not symmetric positive
    semi-definite). Raised by :mod:`needlecli.guard`; one line, exit code 2.

    Parameters
    ----------
    component : str
        The component, its config name and type, and its package:
        ``"observer 'my' (type bad_ukf, package needle-bad-ukf)"``.
    reason : str
        What went wrong, starting with the call: ``"run raised ValueError: ..."``,
        ``"run returned state of shape (2, 11, 3), expected (N, T, n) = (2, 11, 6)"``.
    """

    def __init__(self, component: str, reason: str) -> None:
        self.component = component
        self.reason = reason
        super().__init__(f"{component}: {reason}")

    def __reduce__(self):  # a sweep's worker process sends it back to the parent
        return type(self), (self.component, self.reason)


class Interrupted(KeyboardInterrupt):
    """SIGINT or SIGTERM while a command runs (both handled the same way). Exit code 128 + the signal:
    130 for SIGINT, 143 for SIGTERM. ``hint`` may say how to carry on (``--resume``)."""

    def __init__(self, signum: int, hint: str = "") -> None:
        import signal

        super().__init__(signum)
        self.signum = int(signum)
        self.name = signal.Signals(signum).name
        self.exit_code = 128 + self.signum
        self.hint = hint


def did_you_mean(word: object, candidates) -> str:
    """``"; did you mean 'rate'?"`` when ``word`` is a likely misspelling of one of ``candidates`` (difflib's
    closest match, case-insensitive), else ``""``: appended to a message about an unknown key or name."""
    import difflib

    if not isinstance(word, str) or not word:
        return ""
    names = [str(c) for c in candidates if str(c) != word]
    lower = {n.lower(): n for n in names}
    hit = difflib.get_close_matches(word.lower(), list(lower), n=1, cutoff=0.6)
    return f"; did you mean {lower[hit[0]]!r}?" if hit else ""
