"""The registry of reproduction items: each a figure or table of the thesis, what it claims, and
how this project measures it.

An item's ``build(ctx)`` runs what it needs (campaigns through :mod:`.engine`, benches, the
examples), draws its figure into ``ctx.out`` and returns an :class:`ItemResult`: one row per
claim (the thesis's number with its line, ours, a verdict) and a note saying why where ours
differs. Verdicts are computed from the measurements against the claim, never written by hand.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from typing import Any

REPRODUCED, DIFFERS, PARTLY = "reproduced", "differs", "partly"
MEASURED = "measured"  # a row where the thesis gives no number: ours is reported, and no verdict is drawn from it


@dataclass
class Row:
    quantity: str
    thesis: str  # the thesis's number or claim, with its line
    ours: str  # measured here
    verdict: str  # REPRODUCED, DIFFERS, or MEASURED


@dataclass
class ItemResult:
    rows: list[Row]
    figures: list[str] = field(default_factory=list)  # PNG files under the output folder
    notes: list[str] = field(default_factory=list)  # how it was measured; why it differs
    runs: int = 0  # lockstep runs behind the rows
    wall_s: float = 0.0
    commit: str = ""  # the code that measured it

    @property
    def verdict(self) -> str:
        verdicts = {r.verdict for r in self.rows if r.verdict != MEASURED}
        if verdicts == {REPRODUCED}:
            return REPRODUCED
        return DIFFERS if REPRODUCED not in verdicts else PARTLY

    def to_json(self) -> dict[str, Any]:
        return {**asdict(self), "verdict": self.verdict}

    @staticmethod
    def from_json(data: dict[str, Any]) -> ItemResult:
        return ItemResult(rows=[Row(**r) for r in data["rows"]], figures=data["figures"], notes=data["notes"],
                          runs=data["runs"], wall_s=data["wall_s"], commit=data.get("commit", ""))


@dataclass(frozen=True)
class Item:
    name: str
    title: str
    where: str  # section, figure or table, and the thesis's lines
    claim: str  # what the thesis shows, in a sentence
    build: Callable[[Any], ItemResult]
    quick: bool = False  # part of --quick (CI's subset)


ITEMS: dict[str, Item] = {}


def item(name: str, title: str, where: str, claim: str, quick: bool = False) -> Callable[[Callable[[Any], ItemResult]], Callable[[Any], ItemResult]]:
    """Registers ``build`` as the item ``name``."""

    def register(build: Callable[[Any], ItemResult]) -> Callable[[Any], ItemResult]:
        if name in ITEMS:
            raise ValueError(f"reproduction item {name!r} registered twice")
        ITEMS[name] = Item(name, title, where, claim, build, quick)
        return build

    return register


def verdict(ok: bool) -> str:
    return REPRODUCED if ok else DIFFERS


def thesis_line(where: str) -> int:
    """The first thesis line an item cites: items are listed in the thesis's own order."""
    import re

    found = re.search(r"lines? (\d+)", where)
    if found is None:
        raise ValueError(f"an item's place in the thesis must cite a line: {where!r}")
    return int(found.group(1))
