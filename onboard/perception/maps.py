"""Synthetic occupancy grids (rooms, corridors, random clutter) for tests and benches.

Each map is a bool array, True = occupied, rows along y, with a one-cell wall around
it, plus a start and a goal cell in the same 4-connected free region. Deterministic
for a given seed.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np


@dataclass(frozen=True)
class SyntheticMap:
    name: str
    occupied: np.ndarray  # (rows, cols) bool
    start: tuple[int, int]  # (row, col) of a free cell
    goal: tuple[int, int]  # (row, col) of a free cell, reachable from start


def _border(occ: np.ndarray) -> None:
    occ[0, :] = occ[-1, :] = True
    occ[:, 0] = occ[:, -1] = True


def rooms(size: int = 200, seed: int = 0) -> SyntheticMap:
    """A 3 x 3 grid of rooms with walls 3 cells thick and one or two doors per wall."""
    rng = np.random.default_rng(seed)
    occ = np.zeros((size, size), dtype=bool)
    _border(occ)
    n = 3
    step = size // n
    thick = 3
    for k in range(1, n):
        w = k * step
        occ[w - 1:w + thick - 1, :] = True
        occ[:, w - 1:w + thick - 1] = True
    for k in range(1, n):
        w = k * step
        for j in range(n):
            lo, hi = j * step + 6, (j + 1) * step - 14
            for _ in range(int(rng.integers(1, 3))):
                d = int(rng.integers(lo, hi))
                width = int(rng.integers(8, 14))
                occ[w - 1:w + thick - 1, d:d + width] = False  # door in a horizontal wall
                d = int(rng.integers(lo, hi))
                occ[d:d + width, w - 1:w + thick - 1] = False  # door in a vertical wall
    _border(occ)
    # A few pieces of furniture.
    for _ in range(6):
        r, c = rng.integers(10, size - 20, size=2)
        h, w = rng.integers(3, 10, size=2)
        occ[r:r + h, c:c + w] = True
    return _finish("rooms", occ, rng)


def corridors(size: int = 200, seed: int = 0) -> SyntheticMap:
    """Corridors 6-12 cells wide: a ring, cross links and a diagonal one."""
    rng = np.random.default_rng(seed)
    occ = np.ones((size, size), dtype=np.uint8)
    m = 15
    w = int(rng.integers(6, 12))
    cv2.rectangle(occ, (m, m), (size - m, size - m), 0, thickness=w)
    for _ in range(3):
        x = int(rng.integers(2 * m, size - 2 * m))
        cv2.line(occ, (x, m), (x, size - m), 0, thickness=int(rng.integers(6, 12)))
    cv2.line(occ, (m, m), (size - m, size - m), 0, thickness=int(rng.integers(6, 12)))
    out = occ.astype(bool)
    _border(out)
    return _finish("corridors", out, rng)


def clutter(size: int = 200, seed: int = 0, count: int = 60) -> SyntheticMap:
    """Random boxes and discs (a forest seen from above)."""
    rng = np.random.default_rng(seed)
    occ = np.zeros((size, size), dtype=np.uint8)
    for _ in range(count):
        x, y = (int(v) for v in rng.integers(5, size - 5, size=2))
        if rng.random() < 0.5:
            cv2.circle(occ, (x, y), int(rng.integers(2, 8)), 1, thickness=-1)
        else:
            hw, hh = (int(v) for v in rng.integers(1, 8, size=2))
            box = cv2.boxPoints(((x, y), (2 * hw, 2 * hh), float(rng.uniform(0, 180))))
            cv2.fillConvexPoly(occ, np.round(box).astype(np.int32), 1)
    out = occ.astype(bool)
    _border(out)
    return _finish("clutter", out, rng)


def _finish(name: str, occ: np.ndarray, rng: np.random.Generator) -> SyntheticMap:
    """Start and goal: far apart free cells with some clearance, in one region."""
    free = (~occ).astype(np.uint8)
    _, comp = cv2.connectedComponents(free, connectivity=4)
    sizes = np.bincount(comp[occ == 0].ravel())
    main = int(np.argmax(sizes))
    clear = cv2.distanceTransform(free, cv2.DIST_L2, 3)
    ok = (comp == main) & (clear >= 3)
    rr, cc = np.nonzero(ok)
    i = int(rng.integers(len(rr)))
    d2 = (rr - rr[i]) ** 2 + (cc - cc[i]) ** 2
    j = int(np.argmax(d2))
    return SyntheticMap(name, occ, (int(rr[i]), int(cc[i])), (int(rr[j]), int(cc[j])))


BUILDERS = {"rooms": rooms, "corridors": corridors, "clutter": clutter}
