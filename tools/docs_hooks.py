"""mkdocs hooks (``hooks:`` in mkdocs.yml): the reference pages that are generated at every build, so
that they cannot go stale. Nothing here is written into ``docs/``; the pages exist only in the build.

* ``reference/config/*.md``: every key of the config schema, from the schema itself
  (:func:`needlecli.experiments.config.explain.reference_pages`, what ``needle explain --format md --out DIR``
  writes);
* ``reference/commands.md``: every command with its arguments and options, read from the typer app
  (click introspection of :data:`needlecli.cli.app.app`: what ``needle CMD --help`` prints);
* ``reference/tables-plots.md``: the tables and plots registries (``needle evaluate --tables``), each
  entry's description from its own docstring.

``benchmarks.md`` is not made here: ``make bench`` writes it into ``docs/`` from what the benchmarks print
(``tools/bench_page.py``), since it holds measurements of a machine, not facts of the code.
"""

from __future__ import annotations

import inspect
import re

from mkdocs.structure.files import File


def on_files(files, config):
    """Add the generated pages to the build."""
    pages = {}
    from needlecli.experiments.config.explain import reference_pages

    for name, text in reference_pages().items():
        pages[f"reference/config/{name}.md"] = _config_intro(name) + text
    pages["reference/commands.md"] = commands_page()
    pages["reference/tables-plots.md"] = tables_page()
    for uri, text in pages.items():
        old = files.get_file_from_path(uri)
        if old is not None:
            files.remove(old)
        files.append(File.generated(config, uri, content=text))
    return files


def _config_intro(name: str) -> str:
    if name != "index":
        return ""
    return ("<!-- generated at build time from the config schema (tools/docs_hooks.py); "
            "the same as needle explain --format md --out DIR -->\n\n")


# ---------------------------------------------------------------------------------------------- commands
def _commands():
    import typer

    from needlecli.cli.app import app

    root = typer.main.get_command(app)

    def walk(c, path):
        yield path, c
        for name, sub in (getattr(c, "commands", None) or {}).items():
            yield from walk(sub, [*path, name])

    return root, list(walk(root, []))


def _md(s: str) -> str:
    """Text for a Markdown table cell: pipes escaped, angle brackets not taken for HTML."""
    return " ".join(str(s).split()).replace("|", "\\|").replace("<", "&lt;").replace(">", "&gt;")


def _help_text(doc: str) -> str:
    """A command's docstring as Markdown: paragraphs as they are, the ``Example:`` line as a code block."""
    out = []
    for para in inspect.cleandoc(doc or "").split("\n\n"):
        para = " ".join(para.split())
        if para.startswith("Example: "):
            out.append("Example:\n\n```bash\n" + para[len("Example: "):] + "\n```")
        elif para:
            out.append(_md(para).replace("\\|", "|"))
    return "\n\n".join(out)


def _param_row(p) -> str:
    import click

    if isinstance(p, click.Argument) or getattr(p, "param_type_name", "") == "argument":
        name = f"`{p.human_readable_name}`" + (" (one or more)" if p.nargs == -1 else "")
        kind = "argument"
    else:
        names = list(p.opts) + list(getattr(p, "secondary_opts", []) or [])
        name = ", ".join(f"`{o}`" for o in names)
        kind = "flag" if getattr(p, "is_flag", False) else (p.type.name if p.type is not None else "")
        if getattr(p, "multiple", False):
            kind += ", repeatable"
    default = ""
    if not p.required and p.default not in (None, (), []) and not callable(p.default):
        default = f"`{p.default}`" if not isinstance(p.default, bool) or not getattr(p, "is_flag", False) else (
            f"`{'on' if p.default else 'off'}`")
    req = "required" if p.required else default
    return f"| {name} | {_md(kind)} | {req} | {_md(getattr(p, 'help', '') or '')} |"


def commands_page() -> str:
    import click

    root, cmds = _commands()
    out = ["# Commands", "",
           "<!-- generated at build time from the CLI itself (tools/docs_hooks.py): what `needle CMD --help` "
           "prints -->", "",
           "Every command of `needle`, read from the command-line application at build time: its help, its "
           "arguments and options with their types and defaults. `-h` is short for `--help` everywhere; "
           "`needle --install-completion` installs shell completion; `needle --version` prints the version "
           "and the git commit.", ""]
    for path, cmd in cmds:
        name = " ".join(["needle", *path])
        level = "#" * min(2 + max(len(path) - 1, 0), 4)
        out += [f"{level} `{name}`", ""]
        ctx = click.Context(cmd, info_name=name)
        usage = " ".join(cmd.collect_usage_pieces(ctx))
        out += [f"```text\nUsage: {name} {usage}\n```", ""]
        doc = cmd.help or ""
        if doc:
            out += [_help_text(doc), ""]
        params = [p for p in cmd.params if p.name not in ("help",) and not getattr(p, "hidden", False)]
        if params:
            out += ["| argument or option | type | default | what it is |", "| --- | --- | --- | --- |"]
            out += [_param_row(p) for p in params]
            out.append("")
        subs = getattr(cmd, "commands", None) or {}
        if subs:
            out += ["Commands: " + ", ".join(f"`{' '.join([name, s])}`" for s in subs), ""]
    return "\n".join(out)


# ---------------------------------------------------------------------------------------------- tables, plots
def _first_paragraph(obj) -> str:
    doc = inspect.getdoc(obj) or ""
    return " ".join(doc.split("\n\n")[0].split())


def tables_page() -> str:
    from needlecli.reports import PLOTS, TABLES

    out = ["# Tables and plots", "",
           "<!-- generated at build time from the registries (tools/docs_hooks.py) -->", "",
           "What `needle evaluate` can write: a results file's (and a fit file's) tables by name "
           "(`--tables a,b`, the config's `output.tables`) and its plots (PNG, `--no-plots` for none). Each "
           "entry's description is its own docstring; a plug-in's tables and plots join these lists "
           "(entry points `needlecli.tables`, `needlecli.plots`). A table is written as Markdown, CSV and "
           "LaTeX with its caption (see [Error tables](../guide/error-tables.md)).", "",
           "## Tables", "", "| table | what it is |", "| --- | --- |"]
    for n in TABLES.names():
        out.append(f"| `{n}` | {_md(_first_paragraph(TABLES.get(n)))} |")
    out += ["", "## Plots", "", "| plot | what it is |", "| --- | --- |"]
    for n in PLOTS.names():
        out.append(f"| `{n}` | {_md(_first_paragraph(PLOTS.get(n)))} |")
    out.append("")
    return "\n".join(out)


def check_no_raw_html(text: str) -> list[str]:
    """Angle-bracket words outside code in generated Markdown (they would vanish as HTML tags)."""
    plain = re.sub(r"`[^`]*`", "", re.sub(r"```.*?```", "", text, flags=re.S))
    return re.findall(r"<[a-z][a-z_]*>", plain)
