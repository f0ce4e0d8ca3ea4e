"""Every number a paper states, beside needlecli's over three seeds: each paper's page holds the table and the
list of what does not reproduce exactly as the generator makes them from the committed numbers and values
files (make seed00x-numbers), the list inside the page's "What does not reproduce"; the verdicts follow the
rules the legend states."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml

from needlecli.errors import ConfigError, DataError
from needlecli.papers import PAPERS as ALL_PAPERS
from needlecli.reports import papers

ROOT = Path(__file__).resolve().parents[1]
PAPERS = tuple(p.slug for p in ALL_PAPERS)


def _files(paper):
    d = ROOT / "docs" / "papers" / "numbers"
    return d / f"{paper}.yaml", d / f"{paper}_values.yaml"


@pytest.mark.parametrize("paper", PAPERS)
def test_each_page_holds_the_generated_numbers(paper):
    num_path, val_path = _files(paper)
    numbers = papers.load_numbers(num_path)
    values = yaml.safe_load(val_path.read_text(encoding="utf-8"))
    page = (ROOT / numbers["page"]).read_text(encoding="utf-8")
    rel = (str(num_path.relative_to(ROOT)), str(val_path.relative_to(ROOT)))
    assert papers.write_blocks(page, numbers, values, *rel) == page, f"run make {numbers['target']} --render"
    kw = {"target": numbers["target"], "numbers": rel[0], "values": rel[1]}
    # every number of the paper is a row; each computed one has a value per seed
    table = papers.block(page, papers.TABLE_BEGIN.format(**kw))
    assert table.count("\n| ") == len(numbers["numbers"]) + 1
    for n in numbers["numbers"]:
        if n.get("value") is not None:
            assert len(values["values"][n["id"]]["values"]) == len(numbers["seeds"]) >= 3, n["id"]
    # the list of what does not reproduce sits in the section of that name and names every such row
    wnr = page[page.index("## What does not reproduce"):]
    listed = papers.block(wnr, papers.LIST_BEGIN.format(**kw))
    assert listed is not None
    for n, vd, _ in papers.rows(numbers, values):
        if vd.word in ("not reproduced", "not computed"):
            assert f"**{n['quantity']}**" in listed, n["id"]


def _n(**kw):
    return {"id": "x", "quantity": "q", "source": "s", **kw}


def test_verdicts_follow_the_legend():
    v = papers.verdict
    assert papers.rounding(0.3) == pytest.approx(0.05) and papers.rounding(1.36e-2) == pytest.approx(5e-5)
    assert papers.rounding(80.0) == pytest.approx(5.0) and papers.rounding(2e-14) == pytest.approx(5e-15)
    # a value: its rounding, then the page's tolerance
    assert v(_n(paper=0.3, kind="mean"), [0.27, 0.33], 0.25).word == "inside"
    assert v(_n(paper=0.3, kind="mean"), [0.24, 0.24], 0.25).word == "near"
    assert v(_n(paper=0.3, kind="mean", why="w"), [0.2, 0.2], 0.25).word == "not reproduced"
    assert v(_n(paper=5.3, sd=3.2, kind="mean"), [8.4], 0.25).word == "inside"
    assert v(_n(paper=80.0, kind="about"), [73.0], 0.25).word == "inside"  # "about": 10 %
    assert v(_n(paper=80.0, kind="about"), [65.0], 0.25).word == "near"
    # bounds: on their side, or near past them
    assert v(_n(paper=0.05, kind="at_most"), [0.01, 0.049], 0.25).word == "inside"
    assert v(_n(paper=0.05, kind="at_most"), [0.06], 0.25).word == "near"
    assert v(_n(paper=0.05, kind="at_most", why="because"), [0.08], 0.25).text == "**not reproduced**: because"
    assert v(_n(paper=2.0, kind="at_least"), [1.9], 0.25).word == "near"
    assert v(_n(paper=[1.0, 2.0], kind="range"), [1.5], 0.25).word == "inside"
    assert v(_n(paper=None, kind="ours", stated="mine"), [3.0], 0.25).word == "needlecli's own"
    assert v(_n(paper=1.0, kind="value", why="an experiment"), None, 0.25).word == "not computed"
    with pytest.raises(DataError, match="why is missing"):
        v(_n(paper=0.05, kind="at_most"), [0.08], 0.25)
    assert (papers.fmt(0.000123), papers.fmt(1.234e-5), papers.fmt(1e-14), papers.fmt(-2.5)) == ("0.000123", "1.23e-5", "1e-14", "-2.5")


def test_the_numbers_files_are_checked(tmp_path):
    good = yaml.safe_load(_files("highgain-us2d")[0].read_text())
    for edit, words in ((lambda d: d["numbers"][0].pop("kind"), "required key is missing"),
                        (lambda d: d["numbers"][0].update(kind="median"), "one of mean"),
                        (lambda d: d["numbers"][4].pop("why"), "needs its why"),
                        (lambda d: d["numbers"][0]["value"].update(run="nowhere"), "no run 'nowhere'"),
                        (lambda d: d.update(seeds=[1, 2]), "at least three seeds")):
        d = yaml.safe_load(yaml.safe_dump(good))
        edit(d)
        p = tmp_path / "n.yaml"
        p.write_text(yaml.safe_dump(d))
        with pytest.raises(ConfigError, match=words):
            papers.load_numbers(p)


def test_a_cell_is_one_row_of_a_table():
    import pandas as pd

    t = {"tab": pd.DataFrame({"Observer": ["a", "b"], "Error": ["e_x [mm]", "e_x [mm]"], "Mean": [1.0, 2.0],
                              "tr(Q_h) †": [3.0, 4.0]})}
    assert papers.cell(t, {"table": "tab", "row": {"Observer": "b"}, "column": "Mean", "scale": 10}) == 20.0
    assert papers.cell(t, {"table": "tab", "row": {"Observer": "a"}, "column": "tr(Q_h)"}) == 3.0  # the mark ignored
    assert papers.cell(t, {"table": "tab", "row": {"Observer": "a"}, "columns": ["Mean", "tr(Q_h)"]}) == 2.0
    with pytest.raises(DataError, match="2 rows match"):
        papers.cell(t, {"table": "tab", "row": {"Error": "e_x [mm]"}, "column": "Mean"})
