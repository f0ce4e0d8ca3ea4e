"""The ``needle`` command-line interface (typer)."""
