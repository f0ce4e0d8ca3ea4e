"""Bring the printed output that the tutorial pages show up to date with what their commands print now.

``tests/test_tutorials.py`` runs every ``console`` block of the tutorial pages (and of Getting started)
and compares what each ``$ needle ...`` prints with the lines the page shows, numbers within 1 %. When a
change moves numbers on purpose, this tool reruns the commands the same way (a fresh folder with the
repository's configs) and, with ``--write``, replaces each shown line whose words are the same but whose
numbers moved by the printed line (``…`` kept where the page has it). A line whose words changed (a new
column, a new line) is not guessed at: it is listed, with the printed lines around it, for an edit by
hand. A figure the page shows (``img/NAME.png``) that its commands make under the same name is copied
into the page's ``img/``. Prose numbers are not touched: read the page again after a run.

Usage: ``python tools/tutorial_pages.py [--write] [docs/tutorials/first-study.md ...]``
(default: every page the test checks, but own-observer.md and own-data.md, which need their own set-up).
"""

from __future__ import annotations

import argparse
import os
import re
import shutil
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))

from test_tutorials import BLOCK, OWN_RUNNER, PAGES, _number, commands, same_line  # noqa: E402


def shape(line: str) -> list[str]:
    """The words of a line with every number replaced by ``#`` (what must not change for a number update)."""
    out = []
    for w in line.split():
        n = _number(w)
        out.append("#" + w.strip("0123456789.eE+-") if n is not None else w)
    return out


def same_shape(expected: str, actual: str) -> bool:
    e, a = shape(expected), shape(actual)
    return len(e) == len(a) and all(x == y or x == "…" for x, y in zip(e, a))


def updated(expected: list[str], actual: list[str], what: str, skipping: bool = False) -> tuple[list[str], list[str]]:
    """``(new expected lines, problems)``: the page's lines with moved numbers taken from ``actual``,
    following the matcher of tests/test_tutorials.py (``...`` skips, other lines follow directly)."""
    out, problems, i = [], [], 0
    for exp in expected:
        if exp.strip() == "..." or not exp.strip():
            skipping = skipping or exp.strip() == "..."
            out.append(exp)
            continue
        while i < len(actual) and not actual[i].strip():
            i += 1
        cands = range(i, len(actual)) if skipping else range(i, min(i + 1, len(actual)))
        j = next((k for k in cands if same_line(exp, actual[k])), None)
        if j is None:
            j = next((k for k in cands if same_shape(exp, actual[k])), None)
        if j is None:
            near = "\n".join(f"    {ln}" for ln in actual[max(i - 2, 0): i + 6])
            problems.append(f"{what}: the page's line\n    {exp}\nis not printed any more; printed from there:\n{near}")
            out.append(exp)
            continue
        if same_line(exp, actual[j]):
            out.append(exp)
        elif "…" not in exp:  # numbers moved: the printed line
            out.append(actual[j])
        else:  # the printed words, with the page's … where it had them
            out.append(" ".join("…" if x == "…" else y for x, y in zip(exp.split(), actual[j].split())))
        i, skipping = j + 1, False
    return out, problems


def run_page(page: Path, write: bool) -> list[str]:
    from typer.testing import CliRunner

    from needlecli.cli.app import app

    text = page.read_text(encoding="utf-8")
    problems: list[str] = []
    pieces: list[str] = []
    last = 0
    with tempfile.TemporaryDirectory() as tmp:
        shutil.copytree(ROOT / "configs", Path(tmp) / "configs")
        here = os.getcwd()
        os.chdir(tmp)
        try:
            runner = CliRunner()
            for m in BLOCK.finditer(text):
                if m.group(1) != "console":  # a file the commands wrote, shown from wherever the page starts
                    shown_ = Path(m.group(2))
                    if not shown_.exists():
                        problems.append(f"{page.name}: {shown_} is not written by the commands before it")
                        continue
                    lines, probs = updated(m.group(3).splitlines(), shown_.read_text(encoding="utf-8").splitlines(),
                                           f"{page.name}: {shown_}", skipping=True)
                    problems += probs
                    pieces += [text[last: m.start(3)], "\n".join(lines) + "\n"]
                    last = m.end(3)
                    continue
                body = m.group(3)
                lines_ = body.splitlines()
                first = next((k for k, ln in enumerate(lines_) if ln.startswith("$ ")), len(lines_))
                rebuilt: list[str] = lines_[:first]  # (lines before the first command, as they are)
                cmds = [ln for ln in lines_ if ln.startswith("$ ")]
                for cmd, (argv, expected) in zip(cmds, commands(body)):
                    r = runner.invoke(app, argv[1:])
                    if r.exit_code != 0:
                        problems.append(f"{page.name}: {' '.join(argv)} exited {r.exit_code}:\n{r.output}")
                        rebuilt += [cmd, *expected]
                        continue
                    lines, probs = updated(expected, r.stdout.splitlines(), f"{page.name}: {' '.join(argv)}")
                    problems += probs
                    rebuilt += [cmd, *lines]
                pieces.append(text[last: m.start(3)])
                pieces.append("\n".join(rebuilt) + "\n")
                last = m.end(3)
            for name in dict.fromkeys(re.findall(r"\]\(img/([^)]+\.png)\)", text)):  # the page's figures, made again
                made = sorted(Path(tmp).rglob(name))
                if made and write:
                    shutil.copyfile(made[0], page.parent / "img" / name)
                    print(f"figure: {(page.parent / 'img' / name).relative_to(ROOT)}", file=sys.stderr)
                elif not made:
                    problems.append(f"{page.name}: figure img/{name} is not made under that name by the page's "
                                    "commands: copy it by hand")
        finally:
            os.chdir(here)
    pieces.append(text[last:])
    new = "".join(pieces)
    if write and new != text:
        page.write_text(new, encoding="utf-8")
        print(f"updated: {page.relative_to(ROOT)}", file=sys.stderr)
    elif new != text:
        print(f"would update: {page.relative_to(ROOT)}", file=sys.stderr)
    return problems


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("pages", nargs="*", type=Path)
    ap.add_argument("--write", action="store_true", help="rewrite the pages (default: say what would change)")
    args = ap.parse_args()
    os.environ.setdefault("COLUMNS", "80")
    pages = [p.resolve() for p in args.pages] or [p for p in PAGES if p.name not in OWN_RUNNER]
    problems = [p for page in pages for p in run_page(page, args.write)]
    for p in problems:
        print(p, file=sys.stderr)
    return 1 if problems else 0


if __name__ == "__main__":
    raise SystemExit(main())
