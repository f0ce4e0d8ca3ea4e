"""Papers named by what they are (issue 26, item 2): one table (needlecli/papers.py) that the config folders,
pages, numbers files and make targets follow; the former names (seed000 ...) keep working; user-facing
text names a paper by its slug or title, never as "seed 00N" outside a mention of its former name."""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import pytest
import yaml
from typer.main import get_command
from typer.testing import CliRunner

from needlecli.cli.app import app
from needlecli.papers import PAPERS, SEED_NAME, paper, seed_names
from needlecli.reports import PLOTS, TABLES

ROOT = Path(__file__).resolve().parents[1]


def test_the_table_names_each_paper_once():
    assert len({p.slug for p in PAPERS}) == len({p.alias for p in PAPERS}) == len(PAPERS) == 4
    assert [p.alias for p in PAPERS] == ["seed000", "seed001", "seed003", "seed004"]
    for p in PAPERS:
        assert paper(p.slug) is paper(p.alias) is p
        assert not SEED_NAME.search(p.slug + p.title + p.short)
    with pytest.raises(KeyError, match="known: highgain-us2d"):
        paper("seed002")


@pytest.mark.parametrize("p", PAPERS, ids=lambda p: p.slug)
def test_folders_pages_and_numbers_follow_the_table(p):
    folder = ROOT / p.configs
    assert folder.is_dir() and not folder.is_symlink()
    old = ROOT / "configs" / p.alias  # the former folder: a link committed in git
    assert old.is_symlink() and old.resolve() == folder.resolve()
    for cfg in sorted(folder.glob("*.yaml")):  # a results file and its tables are named by the paper's slug
        assert yaml.safe_load(cfg.read_text())["name"] == f"{p.slug}_{cfg.stem}", cfg
    page = (ROOT / p.page).read_text()
    assert page.splitlines()[0] == f"# {p.title}" and f"`{p.slug}` ({p.formerly})" in page
    stub = (ROOT / "docs" / "papers" / f"{p.alias}.md").read_text()  # the former page points to the new one
    assert f"]({p.slug}.md)" in stub and f"url=../{p.slug}/" in stub
    numbers = yaml.safe_load((ROOT / "docs" / "papers" / "numbers" / f"{p.slug}.yaml").read_text())
    assert (numbers["paper"], numbers["page"], numbers["target"]) == (p.slug, p.page, f"{p.slug}-numbers")
    for run in numbers["runs"].values():
        assert run["config"].startswith(p.configs + "/") and (ROOT / run["config"]).exists()
    nav = yaml.safe_load((ROOT / "mkdocs.yml").read_text().replace("!ENV", ""))["nav"]
    papers_nav = next(item["The papers"] for item in nav if isinstance(item, dict) and "The papers" in item)
    assert f"papers/{p.slug}.md" in [next(iter(i.values())) for i in papers_nav]


def test_every_link_under_configs_is_a_former_name():
    """The only links in configs/ and datasets/ are former names, each leading to the file or folder of the
    new one (the paper folders, an example, a sweep grid, the synthetic data sets)."""
    links = sorted(p for d in ("configs", "datasets") for p in (ROOT / d).rglob("*") if p.is_symlink())
    assert len(links) == len(PAPERS) + 2 + 3
    for link in links:
        p = next(p for p in PAPERS if link.name.startswith(p.alias))
        assert link.resolve().exists() and link.resolve().name == link.name.replace(p.alias, p.slug, 1), link


def test_a_former_config_path_still_runs(tmp_path):
    old = ROOT / "configs" / "seed003" / "table1.yaml"
    r = CliRunner().invoke(app, ["simulate", str(old), "--runs", "2", "--set", "stop.depth=3", "--out",
                                 str(tmp_path / "r.h5"), "--quiet"])
    assert r.exit_code == 0, r.output
    r = CliRunner().invoke(app, ["evaluate", str(tmp_path / "r.h5"), "--tables", "seed003_table1", "--no-plots",
                                 "--out", str(tmp_path / "t")])
    assert r.exit_code == 0, r.output
    # a former table name finds the table; its files take the name that says what it holds
    assert sorted(p.name for p in (tmp_path / "t").iterdir()) == [
        f"multirate-ukf-us3d_table1_pose_curvature_error.{e}" for e in ("csv", "md", "tex")]


def test_former_table_and_plot_names_are_aliases():
    for reg in (TABLES, PLOTS):
        for old, new in reg.aliases.items():
            assert old in reg and reg.get(old) is reg.get(new) and reg.canonical(old) == new
            assert old not in reg.names() and new in reg.names()  # listed (and drawn) once, by the new name
    assert TABLES.canonical("summary") == "summary"


@pytest.mark.skipif(shutil.which("make") is None, reason="no make")
def test_former_make_targets_run_the_new_ones():
    def dry(target):
        r = subprocess.run(["make", "-n", target], cwd=ROOT, capture_output=True, text=True, check=True)
        return r.stdout

    for p in PAPERS:
        assert dry(p.alias) == dry(p.slug) and p.configs + "/" in dry(p.slug)
        assert dry(f"{p.alias}-numbers") == dry(f"{p.slug}-numbers") == \
            f"python tools/paper_numbers.py {p.slug} \n"


def test_the_rule_of_seed_names():
    assert seed_names("Seed 003's Table 1\nsee seeds 000 and 003\nmake seed003\nseed004_like\n# as seed\n# 001 does") == [
        "Seed 003's Table 1", "see seeds 000 and 003", "make seed003", "# as seed 001 does"]
    ok = ("over seeds 3, 4, 5 (runs.seed=3)", "seed 4004", "the seed text seeds/003_*.txt",
          "`multirate-ukf-us3d` (formerly seed003)", "make seed003 runs make multirate-ukf-us3d",
          "the multi-rate UKF paper's Table 1")
    assert seed_names("\n".join(ok)) == []


def _help_texts():
    """``needle ... --help`` of every command and subcommand."""
    def walk(cmd, path):
        yield path
        for name, sub in getattr(cmd, "commands", {}).items():
            yield from walk(sub, [*path, name])

    for path in walk(get_command(app), []):
        r = CliRunner().invoke(app, [*path, "--help"], terminal_width=200)
        assert r.exit_code == 0, (path, r.output)
        yield " ".join(["needle", *path, "--help"]), r.output


def _user_texts():
    for path in sorted((ROOT / "docs").rglob("*.md")):
        yield str(path.relative_to(ROOT)), path.read_text(encoding="utf-8")
    yield "README.md", (ROOT / "README.md").read_text(encoding="utf-8")
    for path in sorted((ROOT / "configs").rglob("*.yaml")):  # comments, names and descriptions
        yield str(path.relative_to(ROOT)), path.read_text(encoding="utf-8")
    yield from _help_texts()
    for reg in (TABLES, PLOTS):  # captions: a table's caption is its docstring's first paragraph
        for name in reg.builtin_names():
            yield f"{reg.what} {name}", reg.get(name).__doc__ or ""
    if shutil.which("make"):
        yield "make help", subprocess.run(["make", "help"], cwd=ROOT, capture_output=True, text=True).stdout


def test_no_user_facing_text_names_a_paper_by_its_seed_number():
    bad = [f"{where}: {line}" for where, text in _user_texts() for line in seed_names(text)]
    assert not bad, "name the paper by its slug or title (needlecli/papers.py):\n" + "\n".join(bad)
