"""The ``needle`` command: one typer app, each subcommand a function in its own module of this package.

The modules import only typer and the standard library at the top; each command imports what it needs
when it runs, so that ``needle --help`` starts at once (none of numpy, scipy, pandas, h5py, pydantic,
matplotlib, OpenCV is loaded to print it). Dependencies point one way: this module imports the command
modules, never the reverse.
"""

from __future__ import annotations

import typer
import typer.core

from needlecli.cli import (
    characterize,
    compare,
    crossval,
    evaluate,
    explain,
    fit_em,
    imports,
    kernels,
    listing,
    log,
    simulate,
    sweep,
    validate,
)


class OneLineErrors(typer.core.TyperGroup):
    """The ``needle`` group, whose usage errors keep the one-line contract of every other error: ``error:
    <the option or argument>: <what is wrong> (needle CMD -h)``, exit code 2, instead of click's boxed or
    three-line message (a value out of range, a missing argument, an unknown option)."""

    def main(self, args=None, prog_name=None, complete_var=None, standalone_mode=True, **extra):  # noqa: D102
        import importlib
        import sys

        click = importlib.import_module(typer.Exit.__module__)  # typer's click (its own copy in typer >= 0.2x)
        echo = typer.echo
        if not standalone_mode:
            return super().main(args=args, prog_name=prog_name, complete_var=complete_var, standalone_mode=False,
                                **extra)
        try:
            rv = super().main(args=args, prog_name=prog_name, complete_var=complete_var, standalone_mode=False,
                              **extra)
        except click.NoArgsIsHelpError as e:  # `needle` or `needle log` alone: the help
            e.show()
            sys.exit(e.exit_code)
        except click.ClickException as e:
            from needlecli.errors import one_line

            ctx = getattr(e, "ctx", None)
            hint = f" ({ctx.command_path} -h)" if ctx is not None else ""
            echo(f"error: {one_line(e.format_message())}{hint}", err=True)
            sys.exit(e.exit_code)
        except click.Abort:
            echo("error: aborted", err=True)
            sys.exit(1)
        sys.exit(rv if isinstance(rv, int) else 0)  # a command's typer.Exit(code) comes back as its code


app = typer.Typer(
    cls=OneLineErrors,
    name="needle",
    help="Batch experiments with steerable-needle models, emulated sensors and observers.\n\n"
         "Example: needle simulate configs/default.yaml && needle evaluate results/default.h5",
    no_args_is_help=True,
    pretty_exceptions_enable=False,
    add_completion=True,  # --install-completion / --show-completion for the user's shell
    context_settings={"help_option_names": ["-h", "--help"]},
)


def _version(value: bool) -> None:
    if value:
        from needlecli.provenance import version_line

        typer.echo(version_line())
        raise typer.Exit()


@app.callback()
def main(
    version: bool = typer.Option(False, "--version", callback=_version, is_eager=True, help="Show the version and git commit."),
) -> None:
    """needle: simulate insertions, run observers, fit models, write tables in the papers' form."""


app.command()(simulate.simulate)
app.command()(evaluate.evaluate)
app.command()(validate.validate)
app.command("list")(listing.list_components)
app.command()(explain.explain)
app.command("fit-em")(fit_em.fit_em_cmd)
app.command()(crossval.crossval)
app.command()(compare.compare)
app.command()(sweep.sweep)
app.command("characterize-sensor")(characterize.characterize_sensor)
app.add_typer(log.log_app, name="log")
app.add_typer(imports.import_app, name="import")
app.add_typer(kernels.kernels_app, name="kernels")


def _quiet_exit(signum, frame) -> None:  # noqa: ARG001
    """Before and after a command's own handling (needlecli.io.atomic.handle_signals) no file is open:
    SIGINT and SIGTERM end the process at once with 128 + the signal, the one line saying what is on disk
    (what the command completed, if it ran), without a traceback."""
    import os
    import signal
    import sys

    journal = getattr(sys.modules.get("needlecli.io.atomic"), "JOURNAL", None)  # None: not (fully) imported yet
    done = journal.summary() if journal is not None else "no file was written"
    os.write(2, f"error: interrupted by {signal.Signals(signum).name}: {done}\n".encode())
    os._exit(128 + signum)


def memory_policy() -> None:
    """How this process gets memory: first-touched memory is the slow part of the machines needlecli is
    measured on (virtual, shared), so it asks for fresh memory less often. The same numbers either way:
    only how memory is mapped changes. Set before numpy is imported; inherited by the processes a
    command forks (fit-em's models, sweep's local workers). Each is a no-op where the platform lacks it
    (:mod:`needlecli.platform`).

    * No transparent huge pages for numpy's large arrays (unless ``NUMPY_MADVISE_HUGEPAGE`` says so): the
      first touch of each madvised 2 MB page waits for the kernel to compact memory, 0.05 to 1.8 s of
      system time for a 300 MB array, varying from run to run, against 0.12 to 0.16 s with 4 KB pages
      (measured alternately in fresh processes); user time is the same.
    * glibc keeps the memory freed (unless a ``MALLOC_*_`` variable says otherwise): blocks under 32 MB
      from the heap, which is not trimmed, so that the arrays of one EM pass reuse the pages of the last
      one instead of faulting fresh ones in (fit-em of the magnetic needle EM paper: 1.6 million page faults -> 0.7 million,
      2.9 -> 1.25 s of system time; its peak resident memory 640 -> 720 MB)."""
    from needlecli import platform

    platform.no_transparent_huge_pages()
    platform.malloc_tune(mmap_threshold=32 << 20,  # glibc's largest
                         trim_threshold=1 << 30, top_pad=64 << 20)


def run() -> None:
    import signal

    from needlecli import platform
    from needlecli.errors import NeedleError

    try:
        platform.check_switch()
    except NeedleError as e:
        typer.echo(f"error: {e}", err=True)
        raise SystemExit(e.exit_code) from None
    memory_policy()
    for s in platform.STOP_SIGNALS:
        signal.signal(s, _quiet_exit)
    app()
