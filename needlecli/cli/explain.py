"""``needle explain [KEY.PATH]``: the config reference from the schema, in the terminal (or as Markdown)."""

from __future__ import annotations

from pathlib import Path

import typer

from needlecli.cli.common import user_errors


@user_errors
def explain(
    key: str = typer.Argument(None, help="A section, component or key: sensors, sensors.position, observers.ukf, "
                                         "model.mnm, observers.ukf.init, fit.em, inputs.flips (default: the top level); "
                                         "mapping, mapping.sensors, ...: the CSV mapping of needle log import-csv."),
    format_: str = typer.Option("text", "--format", "-f", help="text (the terminal) or md (Markdown)."),
    out: Path = typer.Option(None, "--out", "-o", help="With --format md and no KEY: write every reference page to this "
                                                       "folder (the config's and mapping.md)."),
) -> None:
    """Print the keys of a config section (or of the CSV mapping) with their type, default, allowed values
    and description.

    Example: needle explain observers.ukf
    """
    from needlecli.errors import ConfigError
    from needlecli.experiments.config.explain import as_markdown, as_text, explain, mapping_page, reference_pages

    if format_ not in ("text", "md"):
        raise ConfigError("--format", (), f"unknown format {format_!r}; use text or md")
    if out is not None:
        if format_ != "md" or key:
            raise ConfigError("--out", (), "writes the whole reference: use it with --format md and no KEY")
        from needlecli.errors import shown
        from needlecli.io.atomic import check_output_dir, write_text_atomic

        check_output_dir(out, what="the reference pages")
        pages = {**reference_pages(), "mapping": mapping_page()}
        for name, text in pages.items():
            write_text_atomic(out / f"{name}.md", text)
        typer.echo(f"reference: {len(pages)} page(s) in {shown(out)}")
        return
    sec = explain(key)
    typer.echo(as_markdown(sec) if format_ == "md" else as_text(sec))
