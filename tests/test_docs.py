"""The documentation site (issue 19): ``mkdocs build --strict`` (warnings are errors: a broken link, a
missing page, an API name that does not resolve) builds, with the reference pages generated from the CLI,
the schema and the registries at build time; README is a front page of at most 200 lines whose two
commands are the ones .ci/run runs, and every page it links to exists.

Math and markup (issue 26): no page shows a docstring's Sphinx markup raw; the models' and observers'
equations are typeset by KaTeX served with the site (every formula is checked by KaTeX itself where
node is installed); no page fetches anything from outside (scripts, styles, fonts, images), so the site
works offline."""

from __future__ import annotations

import html
import importlib.util
import json
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def _need_mkdocs():
    missing = [m for m in ("mkdocs", "material", "mkdocstrings", "mkdocstrings_handlers.python", "pymdownx")
               if importlib.util.find_spec(m.split(".")[0]) is None]
    if missing:
        if os.environ.get("CI"):  # CI installs .[docs] (.ci/run): there the site must build
            pytest.fail(f"CI without the docs extra: {missing} not installed (pip install -e '.[docs]')")
        pytest.skip(f"mkdocs is not installed ({', '.join(missing)}): pip install -e '.[docs]'")


@pytest.fixture(scope="module")
def site(tmp_path_factory) -> Path:
    _need_mkdocs()
    out = tmp_path_factory.mktemp("site")
    env = {**os.environ, "PYTHONPATH": str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""),
           "NO_MKDOCS_2_WARNING": "1"}
    r = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "--site-dir", str(out)], cwd=ROOT,
                       env=env, capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stdout + r.stderr
    assert "WARNING" not in r.stderr, r.stderr
    return out


def _text(path: Path) -> str:
    return re.sub(r"<[^>]+>", " ", path.read_text(encoding="utf-8"))


def test_the_site_builds_strictly_with_every_page(site):
    for page in ("index.html", "getting-started/index.html", "tutorials/first-study/index.html",
                 "papers/highgain-us2d/index.html", "papers/so3-invariant/index.html", "papers/multirate-ukf-us3d/index.html",
                 "papers/em-magnetic-pratt2022/index.html", "real-data/index.html", "benchmarks/index.html", "layout/index.html",
                 "reference/results-file/index.html", "reference/log-file/index.html", "reference/fit-file/index.html"):
        assert (site / page).exists(), page


def test_the_generated_reference_is_complete(site):
    """Every command, every config section and key, every table and plot, and the plug-in contracts are
    on the built pages: generated from the code, so a new one cannot be missing."""
    import json

    # what the code has, read in a fresh process (as the build did: no test's own registrations)
    code = ("import json, typer\nfrom needlecli.cli.app import app\n"
            "from needlecli.experiments.config.explain import reference_pages\nfrom needlecli.reports import PLOTS, TABLES\n"
            "root = typer.main.get_command(app)\n"
            "cmds = [[n, list(getattr(c, 'commands', {}) or {})] for n, c in root.commands.items()]\n"
            "print(json.dumps({'cmds': cmds, 'pages': reference_pages(), 'names': TABLES.names() + PLOTS.names()}))")
    env = {**os.environ, "PYTHONPATH": str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", "")}
    have = json.loads(subprocess.run([sys.executable, "-c", code], cwd=ROOT, env=env, capture_output=True, text=True,
                                     check=True).stdout)
    commands = _text(site / "reference/commands/index.html")
    for name, subs in have["cmds"]:
        assert f"needle {name}" in commands, name
        for sub in subs:
            assert f"needle {name} {sub}" in commands, (name, sub)
    assert "--quiet" in commands and "Example:" in commands
    for name, md in have["pages"].items():
        html = _text(site / "reference/config" / name / "index.html") if name != "index" else \
            _text(site / "reference/config/index.html")
        for key in re.findall(r"^\| `([^`]+)` \|", md, re.M):
            assert key in html, (name, key)
    tables = _text(site / "reference/tables-plots/index.html")
    for n in have["names"]:
        assert n in tables, n
    api = _text(site / "reference/api/index.html")
    for name in ("Observer", "Model", "Sensor", "Pipeline", "Controller", "Registry", "EstimationProblem",
                 "InitialEstimate", "Posterior"):
        assert re.search(rf"\b{name}\b", api), name
    assert "Parameters" in api or "Returns" in api  # docstrings rendered, not only names


def test_pictures_are_committed_and_shown(site):
    for png in (ROOT / "docs").rglob("*.png"):
        assert png.stat().st_size > 10_000, png  # a plot with data, not a stub
    assert (site / "img" / "default_error_vs_depth.png").exists()


# ---------------------------------------------------------------------------------------------- README
def test_readme_is_a_front_page_with_the_two_commands():
    text = (ROOT / "README.md").read_text(encoding="utf-8")
    assert len(text.splitlines()) <= 200
    assert "pip install -e . && needle kernels compile && needle simulate configs/default.yaml" in text
    assert "pip install -e '.[test]' && python -m pytest" in text
    ci = (ROOT / ".ci" / "run").read_text()
    assert "/^## Set up/" in ci and 'bash -c "set -e; $cmd"' in ci  # CI runs README's two commands verbatim
    setup = text.split("## Set up", 1)[1].split("\n## ", 1)[0]
    assert re.search(r"\d+ minutes", setup) and "LaTeX" in setup and "builds the documentation" in setup
    assert "needle evaluate" in text and "docs/img/default_error_vs_depth.png" in text
    for link in re.findall(r"\]\((docs/[^)#]+)", text):
        assert (ROOT / link).exists(), link
    from needlecli.papers import PAPERS

    for p in PAPERS:
        assert p.page in text, p.slug


# ---------------------------------------------------------------------------------------------- benchmarks
def test_the_benchmark_page_is_what_make_bench_wrote():
    """docs/benchmarks.md is the output of a whole ``make bench`` round (tools/bench_page.py), not a page
    written by hand: its mark, every benchmark's section and issue 14's targets with their verdicts."""
    sys.path.insert(0, str(ROOT / "tools"))
    import bench_page

    text = (ROOT / "docs" / "benchmarks.md").read_text(encoding="utf-8")
    assert text.startswith(bench_page.MARK)
    for name in bench_page.BENCHMARKS:
        assert f"\n## {name}\n" in text and (ROOT / "benchmarks" / f"{name}.py").exists(), name
    head = "## Targets" if "\n## Targets\n" in text else "## Issue 14's targets"  # (the older pages' name)
    targets = text.split(head, 1)[1].split("\n## ", 1)[0]
    rows = [line for line in targets.splitlines() if line.startswith("| ")][2:]  # below the header
    assert len(rows) >= 7 and "FilterPy" in targets
    assert {line.rsplit("|", 2)[1].strip(" *") for line in rows} <= {"MET", "NOT MET", "printed"}


# ---------------------------------------------------------------------------------------------- markup and math
RAW_MARKUP = re.compile(r":(?:class|meth|func|math|mod|data|attr):|\.\. math::")


def _pages(site: Path) -> list[Path]:
    return sorted(site.rglob("*.html"))


def test_no_page_shows_raw_docstring_markup(site):
    """Sphinx roles and ``.. math::`` of the docstrings are turned into code, links and formulas at build
    time (tools/docs_hooks.py): the API pages and the config reference generated from docstrings."""
    raw = {}
    for page in _pages(site):
        hits = RAW_MARKUP.findall(html.unescape(_text(page)))
        if hits:
            raw[str(page.relative_to(site))] = hits
    assert not raw, raw
    api = (site / "reference/api/index.html").read_text(encoding="utf-8")
    assert 'href="#needlecli.models.base.Model.f"' in api  # :meth:`f` in Model's docstring, linked
    model = (site / "reference/config/model/index.html").read_text(encoding="utf-8")
    assert '<span class="arithmatex">\\(R\' = R\\,\\hat w\\)</span>' in model  # the so3 model's :math:


def _hooks():
    _need_mkdocs()
    sys.path.insert(0, str(ROOT / "tools"))
    import docs_hooks

    return docs_hooks


def test_docstring_markup_becomes_the_sites_markdown():
    md = _hooks().markdown_of_docstring
    assert md("a :class:`~needlecli.models.Model` b") == "a `Model` b"
    assert md(":meth:`measure` and :func:`needlecli.f`") == "`measure()` and `needlecli.f()`"
    assert md(":class:`the model <needlecli.models.Model>`") == "`the model`"
    assert md(":math:`x^2 + \\kappa`") == "\\(x^2 + \\kappa\\)"
    doc = "Model.\n\n.. math::\n    x' = v,\\\\\n    y' = u\n\n    z' = 0\n\nAfter."
    assert md(doc) == ("Model.\n\n\n$$\n\\begin{gathered}x' = v,\\\\ y' = u\\end{gathered}\n$$\n\n\n$$\nz' = 0\n$$\n"
                       "\nAfter.")
    assert md("    .. math:: h' = v\n    Next.") == "\n    $$\n    h' = v\n    $$\n\n    Next."
    linked = md(":class:`~needlecli.initial.InitialEstimate`", resolve=lambda name: name)
    assert linked == ('<autoref identifier="needlecli.initial.InitialEstimate" optional><code>InitialEstimate</code>'
                      "</autoref>")


def _formulas(site: Path) -> list[list]:
    out = []
    for page in _pages(site):
        for m in re.finditer(r'<(span|div) class="arithmatex">(.*?)</\1>', page.read_text(encoding="utf-8"), re.S):
            tex = html.unescape(m.group(2)).strip()
            out.append([str(page.relative_to(site)), tex[2:-2], m.group(1) == "div"])
    return out


def test_the_equations_are_math_and_katex_is_served_with_the_site(site):
    per_page = {}
    for page, _, _ in _formulas(site):
        per_page[page] = per_page.get(page, 0) + 1
    assert per_page.get("models/index.html", 0) >= 40, per_page  # every model's states, inputs and vector field
    assert per_page.get("guide/observers/index.html", 0) >= 40, per_page
    assert per_page.get("guide/fitting/index.html", 0) >= 2, per_page
    models = _text(site / "models/index.html")
    for name in ("unicycle", "modified_unicycle", "so3", "mnm", "binm", "speed_scale", "beta_cut", "l_inv", "omega_B"):
        assert name in models, name
    for rel in ("assets/katex/katex.min.js", "assets/katex/katex.min.css", "assets/katex/LICENSE", "assets/math.js"):
        assert (site / rel).is_file(), rel
    page = (site / "models/index.html").read_text(encoding="utf-8")
    assert re.search(r'<script src="\.\./assets/katex/katex\.min\.js', page) and 'href="../assets/katex/katex.min.css"' in page
    css = (site / "assets/katex/katex.min.css").read_text(encoding="utf-8")
    fonts = re.findall(r"url\(([^)]+)\)", css)
    assert len(fonts) >= 20
    for f in fonts:  # every font KaTeX's styles name is served with the site
        assert (site / "assets/katex" / f.strip("'\"")).is_file(), f


def test_every_formula_is_valid_katex(site):
    """KaTeX itself (the copy served with the site) parses every formula of every page, so that none
    shows as a red error in a reader's browser."""
    node = shutil.which("node")
    if node is None:
        pytest.skip("node is not installed: KaTeX cannot be run outside a browser here")
    check = ("const katex = require(process.argv[1]);\n"
             "const bad = [];\n"
             "for (const [page, tex, display] of JSON.parse(require('fs').readFileSync(0, 'utf8'))) {\n"
             "  try { katex.renderToString(tex, {displayMode: display, throwOnError: true}); }\n"
             "  catch (e) { bad.push(page + ': ' + e.message); }\n"
             "}\n"
             "console.log(JSON.stringify(bad));\n")
    formulas = _formulas(site)
    assert len(formulas) > 100
    r = subprocess.run([node, "-e", check, str(site / "assets/katex/katex.min.js")], input=json.dumps(formulas),
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    assert json.loads(r.stdout) == []


FETCHING = re.compile(r"<(script|img|iframe|source|audio|video|embed)\b[^>]*\bsrc=\"(https?:)?//[^\"]*\"|"
                      r"<link\b[^>]*\bhref=\"(https?:)?//[^\"]*\"[^>]*>|url\(\s*['\"]?(https?:)?//", re.I)


def test_no_page_fetches_anything_from_outside(site):
    """The site works offline: no script, style sheet, font, image or other resource of any page or style
    sheet comes from another host (the links a reader clicks may: <a href>)."""
    outside = []
    for f in [*_pages(site), *site.rglob("*.css")]:
        text = f.read_text(encoding="utf-8", errors="replace")
        outside += [f"{f.relative_to(site)}: {m.group(0)[:120]}" for m in FETCHING.finditer(text)]
    assert not outside, outside[:10]
    assert "Built from needlecli" in _text(site / "index.html")  # the footer: version and commit


# ---------------------------------------------------------------------------------------------- pages a user meets
def test_configs_are_shown_inline_and_equal_their_files():
    """A config on a page is the YAML itself, titled with its path (GitHub shows a snippet directive
    raw), and it is the file, byte for byte."""
    shown = 0
    for page in (ROOT / "docs").rglob("*.md"):
        text = page.read_text(encoding="utf-8")
        assert "--8<--" not in text, page
        for path, body in re.findall(r'^```yaml title="([^"]+)"\n(.*?)^```', text, re.S | re.M):
            assert (ROOT / path).read_text(encoding="utf-8") == body, (page.name, path)
            shown += 1
    assert shown >= 4


def test_getting_started_describes_every_command_once():
    import typer

    from needlecli.cli.app import app

    text = (ROOT / "docs" / "getting-started.md").read_text(encoding="utf-8")
    rows = re.findall(r"^\| \[`needle ([a-z-]+(?: [a-z-]+)?)", text, re.M)
    root = typer.main.get_command(app)
    have = []
    for name, cmd in root.commands.items():
        subs = list(getattr(cmd, "commands", {}) or {})
        have += [f"{name} {s}" for s in subs] if subs else [name]
    assert sorted(rows) == sorted(have)
    paragraphs = [" ".join(p.split()) for p in re.split(r"\n\s*\n", text) if len(p) > 100]
    assert len(paragraphs) == len(set(paragraphs)), "a paragraph is repeated"


def test_user_pages_name_no_issue_numbers():
    """Issues are the project's bookkeeping, not the user's (docs/benchmarks.md is what make bench wrote)."""
    hits = []
    for page in (ROOT / "docs").rglob("*.md"):
        if page.name != "benchmarks.md":
            hits += [f"{page.relative_to(ROOT)}: {m.group(0)}"
                     for m in re.finditer(r"\bissues? \d+", page.read_text(encoding="utf-8"), re.I)]
    assert not hits, hits


def test_every_tutorial_has_a_figure_and_long_output_wraps(site):
    for page in sorted((ROOT / "docs" / "tutorials").glob("*.md")):
        figs = re.findall(r"!\[[^\]]*\]\((img/[^)]+\.png)\)", page.read_text(encoding="utf-8"))
        assert figs, f"{page.name}: no figure"
        for fig in figs:
            assert (site / "tutorials" / fig).is_file(), (page.name, fig)
    # what needle prints (console) and the files it writes (text) wrap instead of running past the block
    css = (site / "assets/site.css").read_text(encoding="utf-8")
    rule = re.search(r"\.language-console pre > code,\s*\.md-typeset \.language-text pre > code \{([^}]*)\}", css)
    assert rule and "white-space: pre-wrap" in rule.group(1)
    first = (site / "tutorials/first-study/index.html").read_text(encoding="utf-8")
    assert 'class="language-console highlight"' in first and 'href="../../assets/site.css"' in first
