"""The papers needlecli reproduces, named by what they are: the one table every name of a paper is read from.

Each paper has a **slug** named by its method and its imaging (and its first author and year where the
text we were given states them): the folder of its configs (``configs/<slug>/``), its page
(``docs/papers/<slug>.md``), its ``make`` target, its numbers file. Its **alias** (``seed003``) is the name it
had before: the name of the text it was implemented from (``seeds/003_*.txt``). The alias keeps working
where a user or a script may have typed it: ``configs/seed003`` is a link to ``configs/multirate-ukf-us3d``
(committed in git), ``make seed003`` runs ``make multirate-ukf-us3d``, ``docs/papers/seed003.md`` points to
the new page, and ``tools/paper_numbers.py seed003`` takes it. Everywhere else a paper is named by its
title, its short name or its slug; "seed" means a random seed (and "seed text", the text a paper was
implemented from).

The titles say only what the seed texts give (three of the four begin at the abstract: no title, authors
or venue); ``docs/papers/<slug>.md`` quotes what each text says about itself.
"""

from __future__ import annotations

import re
from dataclasses import dataclass


@dataclass(frozen=True)
class Paper:
    """One paper: its names and what it is.

    Attributes
    ----------
    slug : str
        Method and imaging (and author and year where known): ``multirate-ukf-us3d``.
    alias : str
        Its former name, the seed text's number: ``seed003``.
    short : str
        How prose names it (``the multi-rate UKF paper``; "The" at a sentence's start).
    title : str
        The title line: method, imaging; authors and year where the seed text gives them.
    method, imaging : str
        What it estimates with, and from what.
    authors, year : str
        Empty where the seed text does not give them.
    """

    slug: str
    alias: str
    short: str
    title: str
    method: str
    imaging: str
    authors: str = ""
    year: str = ""

    @property
    def configs(self) -> str:
        """Its config folder, relative to the checkout (``configs/multirate-ukf-us3d``)."""
        return f"configs/{self.slug}"

    @property
    def page(self) -> str:
        """Its documentation page, relative to the checkout (``docs/papers/multirate-ukf-us3d.md``)."""
        return f"docs/papers/{self.slug}.md"

    @property
    def formerly(self) -> str:
        """The mention of its alias that user-facing text may make: ``formerly seed003``."""
        return f"formerly {self.alias}"


#: every paper, in the order of the seed texts
PAPERS: tuple[Paper, ...] = (
    Paper("highgain-us2d", "seed000", "the high-gain observer paper",
          "A nonlinear high-gain observer of the needle tip's pitch and roll from 2D transverse ultrasound",
          method="nonlinear high-gain observer on a 3D unicycle", imaging="2D transverse ultrasound"),
    Paper("so3-invariant", "seed001", "the SO(3) observer paper",
          "An almost globally convergent observer of the needle tip's orientation on SO(3) from one measured "
          "unit vector (fluoroscopy or an electromagnetic tracker)",
          method="invariant observer on SO(3)", imaging="the tangent from bi-plane fluoroscopy or an EM tracker"),
    Paper("multirate-ukf-us3d", "seed003", "the multi-rate UKF paper",
          "Multi-rate unscented Kalman filtering for pose and curvature estimation in 3D ultrasound-guided "
          "needle steering",
          method="multi-rate unscented Kalman filter on a modified unicycle", imaging="3D B-mode ultrasound"),
    Paper("em-magnetic-pratt2022", "seed004", "the magnetic needle EM paper",
          "EM identification of magnetic and bicycle needle models from camera images (Pratt and Petruska, "
          "Robotics 2022)",
          method="expectation-maximisation with an iterated extended Kalman smoother",
          imaging="overhead camera and Helmholtz coils", authors="R. L. Pratt, A. J. Petruska", year="2022"),
)

_BY_NAME = {name: p for p in PAPERS for name in (p.slug, p.alias)}
#: how user-facing text may not name a paper: ``seed 003``, ``Seed 003's``, ``seed003``, ``seeds 000 and 003``
#: (a random seed is ``seed 3``, ``seed=3``, ``runs.seed``: never three digits from 000)
SEED_NAME = re.compile(r"\b[Ss]eeds?[ _-]?00[0-9]\b")


def paper(name: str) -> Paper:
    """The paper of a slug or an alias (``multirate-ukf-us3d`` or ``seed003``).

    Raises
    ------
    KeyError
        An unknown name (the message lists the known slugs and aliases).
    """
    try:
        return _BY_NAME[name]
    except KeyError:
        known = ", ".join(f"{p.slug} ({p.alias})" for p in PAPERS)
        raise KeyError(f"unknown paper {name!r}; known: {known}") from None


def seed_names(text: str) -> list[str]:
    """Where ``text`` names a paper by its seed number other than as its alias: each such line, stripped.

    A line may name an alias only as :attr:`Paper.formerly` (``formerly seed003``) or with the paper's slug
    on the same line (``make seed003`` beside ``make multirate-ukf-us3d``: an old name that keeps working).
    """
    bad = []
    text = re.sub(r"\b([Ss]eeds?)\n[ \t]*(?:#[ \t]*)?(00[0-9])", r"\1 \2", text)  # "seed" and its number on two lines
    for line in text.splitlines():
        rest = line
        for p in PAPERS:
            if p.slug in rest:
                rest = re.sub(rf"\b{p.alias}\b", "", rest)
            rest = rest.replace(p.formerly, "")
        if SEED_NAME.search(rest):
            bad.append(line.strip())
    return bad


__all__ = ["PAPERS", "Paper", "SEED_NAME", "paper", "seed_names"]
