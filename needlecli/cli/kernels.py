"""``needle kernels ...``: the compiled kernels' on-disk cache: compile ahead of the runs, and say what it holds."""

from __future__ import annotations

from pathlib import Path

import typer

from needlecli.cli.common import fail, log, setup_logging, user_errors

kernels_app = typer.Typer(help="The compiled kernels: compile them once per install, ahead of the runs, and "
                               "say what the cache holds.\n\n"
                               "Example: needle kernels compile", no_args_is_help=True)

_CONFIGS_HELP = ("Experiment configs (.yaml) whose kernels to compile (default: the bundled default study, "
                 "the magnetic needle EM paper's fit and the particle filters' Table 1: every compiled twin).")


@kernels_app.command("compile")
@user_errors
def compile_cmd(
    configs: list[Path] = typer.Argument(None, metavar="[CONFIG]...", help=_CONFIGS_HELP),
    jobs: int = typer.Option(0, "--jobs", "-j", min=0, help="Processes compiling at once (0: one per usable core)."),
    quiet: bool = typer.Option(False, "--quiet", "-q", help="No log lines (errors still)."),
) -> None:
    """Compile the kernels that the configs' runs and fits use, on every core: no later run waits.

    README's install step; on a cluster, the job before the array. Each config's simulation and fit run
    briefly with every kernel compiled into the on-disk cache; what the cache holds already is loaded, not
    compiled again. A line per finished job; the last line says what the cache holds.

    Example: needle kernels compile configs/default.yaml configs/em-magnetic-pratt2022/study.yaml
    """
    setup_logging(quiet)
    import time

    from needlecli import kernels, platform
    from needlecli.errors import shown
    from needlecli.experiments.studies import precompile

    if not kernels.numba_available():  # not an error: README's install command goes on to its first run
        typer.echo("kernels: numba is not installed: nothing to compile, every run takes the numpy path "
                   "(pip install numba for the compiled kernels)")
        return
    paths = list(configs) if configs else precompile.bundled_configs()
    plan = precompile.plan(paths)
    if not plan.jobs:
        typer.echo(f"kernels: nothing to compile for {len(paths)} config(s): " + "; ".join(plan.skipped))
        return
    for line in plan.skipped:
        log.info("skipped %s", line)
    todo = plan.todo()
    cache = shown(kernels_cache_dir())
    if not todo:
        typer.echo(f"kernels: compiled already for {len(paths)} config(s), {len(plan.entries())} entry kernel(s) "
                   f"(cache: {cache})")
        return
    processes = jobs or platform.usable_cores()
    estimate = precompile.makespan([j.estimate for j in todo], processes)
    log.info("compiling kernels, once per install: about %.0f s (%d job(s) on %d process(es))", max(1.0, estimate),
             len(todo), min(processes, len(todo)))
    t0 = time.perf_counter()

    def done(o, k, n):
        if o.error is None:
            log.info("[%d/%d] compiled for %s in %.0f s", k, n, o.job.label, o.seconds)

    outcomes = precompile.run(todo, processes, progress=done)
    failed = [o for o in outcomes if o.error is not None]
    if failed:
        o = failed[0]
        fail(f"{shown(o.job.config)}: compiling for its {o.job.kind} failed: {o.error}"
             + (f" (and {len(failed) - 1} more job(s))" if len(failed) > 1 else ""), code=1)
    rows = precompile.status(plan.entries())
    missing = [name for name, ok, _ in rows if not ok]
    typer.echo(f"kernels: compiled for {len(paths)} config(s) in {time.perf_counter() - t0:.0f} s; "
               f"{len(rows) - len(missing)} of {len(rows)} entry kernel(s) in the cache (cache: {cache})"
               + (f"; not compiled (their twins do not cover these configs: the numpy path): {', '.join(missing)}"
                  if missing else ""))


@kernels_app.command("status")
@user_errors
def status_cmd(
    configs: list[Path] = typer.Argument(None, metavar="[CONFIG]...", help=_CONFIGS_HELP),
) -> None:
    """Say which of the kernels the configs use the cache holds; exit code 1 when one is missing.

    For each entry kernel: compiled or not, and how long it took to compile on this machine. A missing
    one is compiled by the run that first needs it (or that run takes the numpy path while it compiles).

    Example: needle kernels status configs/default.yaml
    """
    setup_logging(False)
    from needlecli import kernels
    from needlecli.errors import shown
    from needlecli.experiments.studies import precompile

    paths = list(configs) if configs else precompile.bundled_configs()
    plan = precompile.plan(paths)
    typer.echo(f"cache: {shown(kernels_cache_dir())} (numba {'installed' if kernels.numba_available() else 'NOT installed'})")
    for line in plan.skipped:
        typer.echo(f"skipped {line}")
    rows = precompile.status(plan.entries())
    for name, ok, seconds in rows:
        took = f"{seconds:.1f} s to compile here" if seconds is not None else "compile time not recorded here"
        typer.echo(f"  {name:<32} {'compiled' if ok else 'NOT compiled':<13} {took}")
    missing = sum(not ok for _, ok, _ in rows)
    if missing:
        typer.echo(f"{missing} of {len(rows)} not compiled: needle kernels compile "
                   + " ".join(shown(p) for p in (configs or [])))
        raise typer.Exit(1)


def kernels_cache_dir() -> Path:
    from needlecli.kernels import _cache

    return _cache.cache_dir()
