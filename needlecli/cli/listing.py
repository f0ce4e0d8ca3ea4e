"""``needle list``: the registered models, sensors, pipelines, observers, controllers and tables."""

from __future__ import annotations

import typer

from needlecli.cli.app import app


@app.command("list")
def list_components() -> None:
    """List what configs can name."""
    from needlecli.control import CONTROLLERS
    from needlecli.models import MODELS
    from needlecli.observers import OBSERVERS
    from needlecli.reports import TABLES
    from needlecli.sensors import PIPELINES, SENSORS

    for title, reg in (("models", MODELS), ("sensors", SENSORS), ("pipelines", PIPELINES),
                       ("observers", OBSERVERS), ("controllers", CONTROLLERS), ("tables", TABLES)):
        typer.echo(f"{title}: {', '.join(reg.names())}")
    typer.echo("")
    for name in MODELS.names():
        m = MODELS.get(name)
        typer.echo(
            f"model {name}: state ({', '.join(m.state_names)}); inputs ({', '.join(m.input_names)}); "
            f"params ({', '.join(m.Params.model_fields)}); unit {m.length_unit}"
        )
    from needlecli import kernels  # what has a compiled path (imports no kernel)

    typer.echo("")
    for line in kernels.describe():
        typer.echo(line)
