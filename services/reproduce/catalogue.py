"""Every reproduction item, in the thesis's order: importing the item modules registers them."""

from __future__ import annotations

from services.reproduce import hopping, planning, timing  # noqa: F401  (each registers its items)
from services.reproduce.items import ITEMS, Item, thesis_line


def load_all() -> dict[str, Item]:
    order = sorted(ITEMS.values(), key=lambda i: thesis_line(i.where))
    return {i.name: i for i in order}
