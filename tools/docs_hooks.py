"""mkdocs hooks (``hooks:`` in mkdocs.yml): the reference pages that are generated at every build, so
that they cannot go stale. Nothing here is written into ``docs/``; the pages exist only in the build.

* ``reference/config/*.md``: every key of the config schema, from the schema itself
  (:func:`needlecli.experiments.config.explain.reference_pages`, what ``needle explain --format md --out DIR``
  writes);
* ``reference/commands.md``: every command with its arguments and options, read from the typer app
  (click introspection of :data:`needlecli.cli.app.app`: what ``needle CMD --help`` prints);
* ``reference/tables-plots.md``: the tables and plots registries (``needle evaluate --tables``), each
  entry's description from its own docstring;
* ``reference/mapping.md``: every key of the CSV mapping of ``needle log import-csv``, from its schema
  (:func:`needlecli.experiments.config.explain.mapping_page`, what ``needle explain mapping --format md``
  prints).

Docstrings are written for Python's ``help()`` as well as for the site, with Sphinx's markup (``:class:`X```,
``:meth:``, ``:math:``, ``.. math::``). :func:`markdown_of_docstring` turns that markup into the site's:
roles into code (a link where the object has a page), math into the formulas that KaTeX typesets. It
runs on the generated pages here and, through :class:`DocstringMarkup` (a griffe extension named in
mkdocs.yml), on every docstring of the Python API pages. The docstrings in the code are not changed.

:func:`on_config` writes the version and git commit the site was built from into every page's footer.

``benchmarks.md`` is not made here: ``make bench`` writes it into ``docs/`` from what the benchmarks print
(``tools/bench_page.py``), since it holds measurements of a machine, not facts of the code.
"""

from __future__ import annotations

import html
import inspect
import re

import griffe
from mkdocs.structure.files import File


def on_config(config):
    """The footer of every page: the needlecli version and git commit the site was built from."""
    if not config.get("copyright"):
        from needlecli.provenance import version_line

        config["copyright"] = f"Built from {version_line()}"
    return config


def on_files(files, config):
    """Add the generated pages to the build."""
    pages = {}
    from needlecli.experiments.config.explain import mapping_page, reference_pages

    for name, text in reference_pages().items():
        pages[f"reference/config/{name}.md"] = _config_intro(name) + text
    pages["reference/commands.md"] = commands_page()
    pages["reference/tables-plots.md"] = tables_page()
    pages["reference/mapping.md"] = mapping_page()
    for uri, text in pages.items():
        old = files.get_file_from_path(uri)
        if old is not None:
            files.remove(old)
        files.append(File.generated(config, uri, content=markdown_of_docstring(text, resolve=_package_path)))
    return files


# ---------------------------------------------------------------------------------------------- docstring markup
#: a Sphinx role: ``:class:`X```, ``:meth:`~a.b.f```, ``:math:`x^2```, ``:py:func:`title <a.f>```
ROLE = re.compile(r":(?:py:)?(class|meth|func|mod|data|attr|obj|exc|const|math):`([^`]+)`")
MATH_DIRECTIVE = re.compile(r"^(?P<indent>[ \t]*)\.\. math::[ \t]*(?P<first>.*)$")


def markdown_of_docstring(text: str, resolve=None) -> str:
    """Sphinx markup of a docstring as the site's Markdown.

    ``.. math::`` blocks become display formulas (``$$ ... $$``, one per paragraph of the block, lines
    joined; a body with ``\\\\`` line breaks in a ``gathered`` environment), ``:math:`x``` inline ones
    (``\\( x \\)``); pymdownx.arithmatex marks both for KaTeX. Every other role becomes code: the
    last component only for ``~a.b.C``, ``()`` after a function or method (as Sphinx shows them), and
    ``title <target>`` shows the title. Where ``resolve(target)`` gives the object's full path, the code
    is an optional cross-reference (mkdocs-autorefs links it when the object has a page, and leaves the
    code as it is when not: no warning).
    """
    return ROLE.sub(lambda m: _role(m.group(1), m.group(2), resolve), _math_blocks(text))


def _role(kind: str, body: str, resolve) -> str:
    if kind == "math":
        return "\\(" + body + "\\)"
    title = None
    m = re.fullmatch(r"(.+?)\s*<([^<>]+)>", body)
    if m:
        title, body = m.group(1), m.group(2)
    target = body.lstrip("~.!")
    if title is None:
        title = target.rsplit(".", 1)[-1] if body.startswith("~") else target
        if kind in ("meth", "func"):
            title += "()"
    path = resolve(target) if resolve is not None else None
    if not path:
        return f"`{title}`"
    return f'<autoref identifier="{html.escape(path)}" optional><code>{html.escape(title)}</code></autoref>'


def _math_blocks(text: str) -> str:
    lines = text.split("\n")
    out: list[str] = []
    i = 0
    while i < len(lines):
        m = MATH_DIRECTIVE.match(lines[i])
        if not m:
            out.append(lines[i])
            i += 1
            continue
        indent = m.group("indent")
        body = [m.group("first")] if m.group("first").strip() else []
        i += 1
        while i < len(lines) and (not lines[i].strip() or len(lines[i]) - len(lines[i].lstrip()) > len(indent)):
            body.append(lines[i].strip())
            i += 1
        formulas = [" ".join(p.split("\n")) for p in "\n".join(body).strip().split("\n\n") if p.strip()]
        for tex in formulas:
            if "\\\\" in tex:
                tex = "\\begin{gathered}" + tex + "\\end{gathered}"
            out += ["", f"{indent}$$", f"{indent}{tex}", f"{indent}$$", ""]
    return "\n".join(out)


def _package_path(target: str) -> str | None:
    """A target written as a full path of the package (``needlecli.initial.InitialEstimate``) is its own
    identifier; anything else is left unlinked on the generated pages."""
    return target if target.startswith("needlecli.") else None


class DocstringMarkup(griffe.Extension):
    """griffe extension (mkdocs.yml: ``extensions``): every docstring of the loaded package through
    :func:`markdown_of_docstring`, each role resolved in the scope of the object whose docstring it is."""

    def on_package(self, *, pkg, **kwargs) -> None:
        self._convert(pkg, set())

    on_package_loaded = on_package  # the hook's name before griffe 2

    def _convert(self, obj, seen: set) -> None:
        if obj.is_alias or obj.path in seen:
            return
        seen.add(obj.path)
        if obj.docstring is not None:
            obj.docstring.value = markdown_of_docstring(obj.docstring.value, resolve=lambda name: _resolve(obj, name))
        for member in obj.members.values():
            self._convert(member, seen)


def _resolve(obj, name: str) -> str | None:
    """The full path of ``name`` as written in ``obj``'s docstring: a full dotted path (re-exports
    followed to where the object is defined) or a name in the object's scope."""
    try:
        return obj.modules_collection[name].canonical_path
    except Exception:  # not a full path of a loaded module
        pass
    try:
        return obj.resolve(name)
    except Exception:  # griffe cannot tell: the role stays plain code
        return None


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
    def former(reg, n):  # the names a table or plot had when it was named by its paper's seed text
        old = [f"`{a}`" for a, b in reg.aliases.items() if b == n]
        return f" (formerly {', '.join(old)}, which still names it)" if old else ""

    for n in TABLES.names():
        out.append(f"| `{n}`{former(TABLES, n)} | {_md(_first_paragraph(TABLES.get(n)))} |")
    out += ["", "## Plots", "", "| plot | what it is |", "| --- | --- |"]
    for n in PLOTS.names():
        out.append(f"| `{n}`{former(PLOTS, n)} | {_md(_first_paragraph(PLOTS.get(n)))} |")
    out.append("")
    return "\n".join(out)


def check_no_raw_html(text: str) -> list[str]:
    """Angle-bracket words outside code in generated Markdown (they would vanish as HTML tags)."""
    plain = re.sub(r"`[^`]*`", "", re.sub(r"```.*?```", "", text, flags=re.S))
    return re.findall(r"<[a-z][a-z_]*>", plain)
