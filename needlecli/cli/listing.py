"""``needle list``: the registered models, sensors, pipelines, observers, controllers, tables and plots,
with the package that adds each one that is not needlecli's own (entry points)."""

from __future__ import annotations

import typer


def list_components(
    details: bool = typer.Option(False, "--details", "-d", help="Also each model's states, inputs, parameters "
                                 "and unit (imports the models)."),
) -> None:
    """List what configs can name (and which installed package adds a plug-in). Nothing is imported to
    print the names; --details loads the models.

    Example: needle list --details
    """
    from needlecli.control import CONTROLLERS
    from needlecli.models import MODELS
    from needlecli.observers import OBSERVERS
    from needlecli.reports import PLOTS, TABLES
    from needlecli.sensors import PIPELINES, SENSORS

    def named(reg, name: str) -> str:
        origin = reg.origin(name)
        return name if origin == "needlecli" else f"{name} ({origin})"

    registries = (("models", MODELS), ("sensors", SENSORS), ("pipelines", PIPELINES), ("observers", OBSERVERS),
                  ("controllers", CONTROLLERS), ("tables", TABLES), ("plots", PLOTS))
    for title, reg in registries:
        typer.echo(f"{title}: {', '.join(named(reg, n) for n in reg.names())}")
    from needlecli import kernels  # the table of compiled twins (imports neither numba nor a kernel)

    models = {}
    for name in (MODELS.names() if details else []):
        try:
            models[name] = MODELS.get(name)
        except Exception as e:  # noqa: BLE001 (a broken plug-in is reported below, not raised)
            typer.echo(f"model {name}: cannot be loaded ({e})", err=True)
    typer.echo("")  # the models with compiled equations: their own declaration (loaded with --details)
    with_twin = [n for n, m in models.items() if m.compiled_equations] if details else None
    for line in kernels.describe(models=with_twin):
        typer.echo(line)
    if not details:
        return
    typer.echo("")
    for name, m in models.items():
        twin = f"compiled equations {m.compiled_equations}" if m.compiled_equations else "numpy only"
        typer.echo(
            f"model {name}: state ({', '.join(m.state_names)}); inputs ({', '.join(m.input_names)}); "
            f"params ({', '.join(m.Params.model_fields)}); unit {m.length_unit}; {twin}"
        )
    broken = [e for _, reg in registries if reg is not MODELS for e in reg.load_all(plugins_only=True)]
    for e in broken:
        typer.echo(f"warning: {e}", err=True)
