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
    """``error: <message>`` on stderr, always one line (a library's message may hold newlines), and exit."""
    typer.echo(f"error: {' '.join(str(message).split())}", err=True)
    raise typer.Exit(code)


def _os_error(e: OSError) -> str:
    from needlecli.io.atomic import _os_reason

    where = f"{e.filename}: " if e.filename else ""
    return f"{where}{_os_reason(e)}"


def user_errors(fn: Callable) -> Callable:
    """Run a command with SIGINT and SIGTERM handled alike. A :class:`NeedleError` becomes ``error:
    <message>`` on stderr and exit code 2; an ``OSError`` (a file system's refusal) one line too; a signal
    exit code 130 (SIGINT) or 143 (SIGTERM), its temporary files removed, with what is on disk."""

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        from needlecli.io.atomic import JOURNAL, handle_signals, hold_signals, raised_signal, start_signals

        JOURNAL.reset()
        with handle_signals():
            try:
                start_signals()
                return fn(*args, **kwargs)
            except NeedleError as e:
                hold_signals()
                if isinstance(e, ComponentError) and raised_signal() is not None:  # a component swallowed a signal
                    _interrupted(raised_signal())
                JOURNAL.remove_inflight()
                fail(str(e), e.exit_code)
            except KeyboardInterrupt as e:  # Interrupted (SIGINT, SIGTERM), or Ctrl-C before the handlers
                hold_signals()
                _interrupted(e if isinstance(e, Interrupted) else Interrupted(2))
            except MemoryError:
                hold_signals()
                JOURNAL.remove_inflight()
                fail(f"out of memory (more than the memory the estimate checked was needed): {JOURNAL.summary()}")
            except OSError as e:
                hold_signals()
                JOURNAL.remove_inflight()
                fail(f"{_os_error(e)}; {JOURNAL.summary()}")
            except Exception as e:  # a library that wrapped the signal's exception in its own (RuntimeError)
                sig = wrapped_interrupt(e, Interrupted) or raised_signal()
                if sig is None:
                    raise
                hold_signals()
                _interrupted(sig)

    return wrapper


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


def setup_logging(quiet: bool, level: int = logging.INFO) -> None:
    """Log lines to stderr from ``level`` on; ``--quiet`` keeps only errors above warnings' level."""
    logging.basicConfig(
        level=max(logging.WARNING, level + 10) if quiet else level,
        format="%(message)s",
        stream=sys.stderr,
        force=True,
    )


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
