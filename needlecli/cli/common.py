"""What every command shares: turning typed errors into one-line messages and exit codes, progress."""

from __future__ import annotations

import contextlib
import functools
import logging
import sys
from collections.abc import Callable, Iterator
from typing import TYPE_CHECKING

import typer

from needlecli.errors import ComponentError, Interrupted, NeedleError
from needlecli.guard import wrapped_interrupt

if TYPE_CHECKING:
    from needlecli.experiments.config.types import ExperimentConfig

log = logging.getLogger("needlecli")


def fail(message: str, code: int = 2) -> None:
    """``error: <message>`` on stderr, always one line (a library's message may hold newlines; a name in it
    may hold control characters: :func:`~needlecli.errors.one_line` escapes them), and exit."""
    from needlecli.errors import one_line

    typer.echo(f"error: {one_line(message)}", err=True)
    raise typer.Exit(code)


def _os_error(e: OSError) -> str:
    from needlecli.errors import shown
    from needlecli.io.atomic import _os_reason

    where = f"{shown(e.filename)}: " if e.filename else ""
    return f"{where}{_os_reason(e)}"


def user_errors(fn: Callable | None = None, *, outputs: str = "set") -> Callable:
    """Run a command with SIGINT and SIGTERM handled alike. A :class:`NeedleError` becomes ``error:
    <message>`` on stderr and exit code 2; an ``OSError`` (a file system's refusal) one line too; a signal
    exit code 130 (SIGINT) or 143 (SIGTERM), its temporary files removed, with what is on disk.

    ``outputs``: ``"set"`` (the default) writes every output of the command as one set, all or nothing
    (:func:`needlecli.io.atomic.output_set`: renamed into place when the command has succeeded, or ended
    with exit code 0 or 1 after complete outputs -- a regression, a failed sweep cell); ``"each"`` keeps
    each file as it is completed (a sweep's cells, for ``--resume``), and an error then says which were.
    Warnings (log records, Python's and numpy's warnings) go through one channel (:data:`WARNINGS`): held
    while the command runs, printed after it succeeded unless ``--quiet``, dropped when it fails, so
    that its error line is all it prints."""
    if fn is None:
        return functools.partial(user_errors, outputs=outputs)
    if outputs not in ("set", "each"):
        raise ValueError(f"outputs={outputs!r}: expected 'set' or 'each'")

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        from needlecli.io.atomic import JOURNAL, handle_signals, hold_signals, output_set, raised_signal, start_signals

        JOURNAL.reset()
        WARNINGS.start()
        with handle_signals():
            try:
                start_signals()
                with output_set() if outputs == "set" else contextlib.nullcontext() as written:
                    try:
                        result = fn(*args, **kwargs)
                    except typer.Exit as e:
                        if e.exit_code in (0, 1) and written is not None:  # complete outputs, then a verdict
                            written.keep = True
                        raise
                WARNINGS.show()
                return result
            except typer.Exit as e:
                if e.exit_code in (0, 1):
                    WARNINGS.show()
                else:
                    WARNINGS.drop()
                raise
            except NeedleError as e:
                hold_signals()
                WARNINGS.drop()
                if isinstance(e, ComponentError) and raised_signal() is not None:  # a component swallowed a signal
                    _interrupted(raised_signal())
                JOURNAL.remove_inflight()
                fail(str(e) + _left(str(e)), e.exit_code)
            except KeyboardInterrupt as e:  # Interrupted (SIGINT, SIGTERM), or Ctrl-C before the handlers
                hold_signals()
                WARNINGS.drop()
                _interrupted(e if isinstance(e, Interrupted) else Interrupted(2))
            except MemoryError:
                hold_signals()
                WARNINGS.drop()
                JOURNAL.remove_inflight()
                fail(f"out of memory (more than the memory the estimate checked was needed): {JOURNAL.summary()}")
            except OSError as e:
                hold_signals()
                WARNINGS.drop()
                JOURNAL.remove_inflight()
                fail(f"{_os_error(e)}; {JOURNAL.summary()}")
            except Exception as e:  # a library that wrapped the signal's exception in its own (RuntimeError)
                sig = wrapped_interrupt(e, Interrupted) or raised_signal()
                if sig is None:
                    raise
                hold_signals()
                WARNINGS.drop()
                _interrupted(sig)
            finally:
                WARNINGS.stop()

    return wrapper


def _left(message: str) -> str:
    """What a failed command left (files it completed before the error, in the ``each`` mode), unless the
    message says it already."""
    from needlecli.io.atomic import JOURNAL

    written = [str(p) for p in dict.fromkeys(JOURNAL.written)]
    if not written or "written" in message:
        return ""
    shown_ = ", ".join(written[:3]) + (f" and {len(written) - 3} more" if len(written) > 3 else "")
    return f"; written completely before it: {shown_}"


def _interrupted(sig: Interrupted) -> None:
    from needlecli.io.atomic import JOURNAL

    JOURNAL.remove_inflight()
    hint = f"; {sig.hint}" if sig.hint else ""
    fail(f"interrupted by {sig.name}: {JOURNAL.summary()}{hint}", sig.exit_code)


def check_results_target(cfg: ExperimentConfig, target, base_dir, what: str = "the results file"):
    """Before the work: ``target`` can be written and its file system has room for the results file (the
    estimate of :mod:`needlecli.experiments.config.budget`). Returns the estimate."""
    from needlecli.experiments.config.budget import estimate
    from needlecli.io.atomic import check_output_file

    est = estimate(cfg, base_dir)
    check_output_file(target, what=what, size=est.file_bytes)
    return est


class WarningChannel(logging.Handler):
    """The one channel of a command's warnings: log records at WARNING and above, Python's warnings and
    numpy's RuntimeWarnings (through :func:`logging.captureWarnings`), and what a library logs. Held while
    the command runs; :func:`user_errors` prints them (``warning: ...``, one line each) after a command
    that succeeded and drops them when it fails, so that a failed command prints its one error line and
    nothing before it. ``--quiet`` silences them (:func:`setup_logging`)."""

    def __init__(self) -> None:
        super().__init__(level=logging.WARNING)
        self.held: list[str] = []

    def emit(self, record: logging.LogRecord) -> None:
        from needlecli.errors import one_line

        try:
            text = record.getMessage()
        except Exception:  # noqa: BLE001 (a record whose arguments do not format: show it as it came)
            text = str(record.msg)
        if record.name == "py.warnings":  # "file:line: Category: message\n  source line"
            text = text.strip().splitlines()[0] if text.strip() else text
            parts = text.split(": ", 2)
            text = parts[-1] + (f" ({parts[1]})" if len(parts) == 3 else "")
        line = f"warning: {one_line(text)}"
        if line not in self.held:
            self.held.append(line)

    def start(self) -> None:
        self.held.clear()
        logging.captureWarnings(True)
        root = logging.getLogger()
        if self not in root.handlers:
            root.addHandler(self)

    def stop(self) -> None:
        """After the command: Python's warnings shown by Python again (held ones are printed or dropped)."""
        self.held.clear()
        logging.captureWarnings(False)

    def take(self) -> list[str]:
        lines, self.held = self.held, []
        return lines

    def show(self) -> None:
        """Print what is held (the command succeeded)."""
        for line in self.take():
            typer.echo(line, err=True)

    def flush(self) -> None:
        """Nothing: held lines are printed by :meth:`show` only (``logging.shutdown`` flushes every handler)."""

    def drop(self) -> None:
        self.held.clear()


WARNINGS = WarningChannel()


class _BelowWarnings(logging.Filter):
    def filter(self, record: logging.LogRecord) -> bool:
        return record.levelno < logging.WARNING


def setup_logging(quiet: bool, level: int = logging.INFO) -> None:
    """Log lines to stderr from ``level`` on, at once; warnings and errors through :data:`WARNINGS` (after
    the command); ``--quiet`` keeps only errors above warnings' level."""
    root = logging.getLogger()
    for h in list(root.handlers):
        root.removeHandler(h)
    now = logging.StreamHandler(_Stderr())
    now.setFormatter(logging.Formatter("%(message)s"))
    now.addFilter(_BelowWarnings())
    root.addHandler(now)
    root.addHandler(WARNINGS)
    root.setLevel(logging.ERROR if quiet else level)


class _Stderr:
    """sys.stderr as it is when a line is written (a test runner replaces it per command)."""

    def write(self, text: str) -> int:
        return sys.stderr.write(text)

    def flush(self) -> None:
        sys.stderr.flush()


@contextlib.contextmanager
def progress_bar(enabled: bool) -> Iterator[Callable[[str, int, int], None] | None]:
    """A progress bar on stderr; yields ``update(phase, done, total)`` or None when disabled."""
    if not enabled:
        yield None
        return
    from rich.console import Console
    from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

    console = Console(stderr=True)
    with Progress(
        TextColumn("{task.description:<24}"),
        BarColumn(),
        TextColumn("{task.percentage:>5.1f}%"),
        TimeElapsedColumn(),
        TimeRemainingColumn(),
        console=console,
        transient=False,
    ) as bar:
        tasks: dict[str, int] = {}

        def update(phase: str, done: int, total: int) -> None:
            if phase not in tasks:
                tasks[phase] = bar.add_task(phase, total=total)
            bar.update(tasks[phase], completed=done, total=total)

        yield update
