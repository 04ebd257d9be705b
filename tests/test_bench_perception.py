"""``archer bench perception`` reports the polygons the decomposition dropped beside ``overlap_cells``."""

from __future__ import annotations

import argparse

from onboard.perception import decomposition
from services.bench.perception import measure

SMALL = argparse.Namespace(maps="rooms,clutter", seeds=1, repeat=1, size=100)


def test_drops_are_reported_where_overlap_cells_stays_zero(monkeypatch):
    honest = measure(SMALL)
    assert honest["polygons_dropped_for_overlap"] == 0 and honest["overlap_cells"] == 0

    def drop_the_first(cell_polys, blocked):  # as if one fit per map had crossed a blocked square
        return cell_polys[1:], min(1, len(cell_polys))

    monkeypatch.setattr(decomposition, "clear_of_blocked", drop_the_first)
    fig = measure(SMALL)
    assert fig["polygons_dropped_for_overlap"] == 2  # one per map
    assert fig["overlap_cells"] == 0  # blind to it: the dropped polygon is not returned
