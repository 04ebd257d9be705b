"""Seen before stepped on: the part of a plan the robot is committed to lies on seen-free ground.

In obstacle mode perception turns what the camera saw occupied into convex obstacles, and
what it has not seen counts as free, so the planner may route optimistically through
unknown space. The robot is only *committed* to the first ``PlannerParams.commit_s`` of
a reference (what it executes before the planner can change its mind); along that part,
every cell whose centre lies within ``radius`` (the robot's footprint) of a sample of the
reference must be free in the occupancy grid (the clearance the tube needs from what was
seen occupied is the planner's cut's to keep). The robot's own region, its footprint grown
by its tube around where it is now, counts as seen: the robot hops there, and beside its
body lies the camera's blind zone (cells there are never seen, from anywhere).

    space = SeenSpace.from_grid(grid)
    k = space.first_unseen(samples_xy, radius, here_xy, own_radius)   # None: all seen free
    pts = space.frontier()                                            # where seen free meets unknown

In free mode the planner plans only inside seen-free cells; when the goal lies beyond
them it heads for the frontier (Yamauchi's frontier-based exploration): the free cells
that border cells never seen, where going on shows the camera more.
"""

from __future__ import annotations

import math

import cv2
import numpy as np

from onboard.contracts.binary_messages import CELL_FREE, CELL_UNKNOWN, OccupancyGrid
from onboard.perception import _kernels as K


class SeenSpace:
    """The cells an occupancy grid holds as free (rows along world y, columns along x)."""

    def __init__(self, free: np.ndarray, resolution: float, origin: tuple[float, float],
                 unknown: np.ndarray | None = None) -> None:
        free = np.asarray(free, dtype=bool)
        if free.ndim != 2 or not (math.isfinite(resolution) and resolution > 0):
            raise ValueError("seen space needs a 2-D mask and a positive resolution")
        if not all(math.isfinite(v) for v in origin):
            raise ValueError("seen space origin is not finite")
        # without an unknown mask every cell not free counts as unknown (nothing seen occupied)
        unknown = ~free if unknown is None else np.asarray(unknown, dtype=bool)
        if unknown.shape != free.shape:
            raise ValueError("seen space: unknown mask and free mask differ in shape")
        self.free = free
        self.unknown = unknown
        self.resolution = float(resolution)
        self.origin = (float(origin[0]), float(origin[1]))
        self._frontier: tuple[tuple, np.ndarray] | None = None  # ((width, here), frontier) last asked for

    @classmethod
    def from_grid(cls, grid: OccupancyGrid) -> SeenSpace:
        return cls(grid.cells == CELL_FREE, grid.resolution, grid.origin, grid.cells == CELL_UNKNOWN)

    def frontier(self, width: float = 0.0, here: tuple[float, float] | np.ndarray | None = None) -> np.ndarray:
        """Centres ``(K, 2)`` [m] of the free cells 8-adjacent to unknown ground at least
        ``width`` [m] wide (a morphological opening by a disc of that diameter) or to the
        grid's edge (beyond it nothing is known). A cell next to one seen occupied only is not
        a frontier: going there shows nothing new; nor is one next to a sliver of unknown
        narrower than the robot, such as the strip at a wall's foot whose cells flicker between
        a noisy hit and a miss: nothing the robot could go to fits in it, and standing by it
        would never make it known. With ``here`` [m], only the free cells 4-connected to its
        cell count (none when it is not free): a free cell seen behind a wall is next to the
        unknown, but not a way on."""
        key = (float(width), None if here is None else (float(here[0]), float(here[1])))
        cached = self._frontier
        if cached is None or cached[0] != key:
            rows, cols = self.free.shape
            # the disc's diameter in cells, odd: an even kernel's anchor is off centre and its
            # opening would shift the unknown by a cell (one side's frontier lost, the other's doubled)
            d = 2 * int(round((width / self.resolution - 1.0) / 2.0)) + 1 if width > 0 else 1
            k = d
            unk = np.ones((rows + 2 * k + 2, cols + 2 * k + 2), dtype=np.uint8)  # the grid's outside is unknown
            unk[k + 1:k + 1 + rows, k + 1:k + 1 + cols] = self.unknown
            if d > 1:
                disc = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (d, d))
                unk = cv2.morphologyEx(unk, cv2.MORPH_OPEN, disc)
            unk = unk[k:k + rows + 2, k:k + cols + 2] > 0
            near = np.zeros((rows, cols), dtype=bool)
            for dr in (0, 1, 2):
                for dc in (0, 1, 2):
                    near |= unk[dr:dr + rows, dc:dc + cols]
            mine = self.free
            if here is not None:
                hr = int(math.floor((key[1][1] - self.origin[1]) / self.resolution))
                hc = int(math.floor((key[1][0] - self.origin[0]) / self.resolution))
                if not (0 <= hr < rows and 0 <= hc < cols and self.free[hr, hc]):
                    mine = np.zeros_like(self.free)
                else:
                    _, comp = cv2.connectedComponents(self.free.astype(np.uint8), connectivity=4)
                    mine = comp == comp[hr, hc]
            r, c = np.nonzero(mine & near)
            pts = np.column_stack([self.origin[0] + (c + 0.5) * self.resolution,
                                   self.origin[1] + (r + 0.5) * self.resolution])
            cached = self._frontier = (key, pts)
        return cached[1]

    def first_unseen(self, points: np.ndarray, radius: float, here: np.ndarray | tuple[float, float],
                     own_radius: float) -> int | None:
        """Index of the first of ``points`` ``(N, 2)`` [m] whose disc of ``radius`` [m] covers
        a cell not seen free (outside the grid is not seen), or None when all are on seen ground.
        Cells within ``own_radius`` of ``here`` count as seen: the robot hops there."""
        pts = np.asarray(points, dtype=float).reshape(-1, 2)
        if not np.all(np.isfinite(pts)):
            raise ValueError("points must be finite")
        res = self.resolution
        reach = int(math.ceil(radius / res)) + 1
        offsets = np.arange(-reach, reach + 1)
        rows_n, cols_n = self.free.shape
        hx, hy = float(here[0]), float(here[1])
        for k, (x, y) in enumerate(pts):
            col0 = int(math.floor((x - self.origin[0]) / res))
            row0 = int(math.floor((y - self.origin[1]) / res))
            cols = col0 + offsets
            rows = row0 + offsets
            cx = self.origin[0] + (cols + 0.5) * res  # cell centres
            cy = self.origin[1] + (rows + 0.5) * res
            near = (cy[:, None] - y) ** 2 + (cx[None, :] - x) ** 2 <= radius * radius
            own = (cy[:, None] - hy) ** 2 + (cx[None, :] - hx) ** 2 <= own_radius * own_radius
            need = near & ~own
            if not need.any():
                continue
            r_idx, c_idx = np.nonzero(need)
            r_cells, c_cells = rows[r_idx], cols[c_idx]
            inside = (r_cells >= 0) & (r_cells < rows_n) & (c_cells >= 0) & (c_cells < cols_n)
            if not inside.all() or not self.free[r_cells, c_cells].all():
                return k
        return None

    def distance_through_free(self, sources: np.ndarray, points: np.ndarray) -> np.ndarray:
        """Per point ``(N, 2)`` [m], the length [m] of the shortest 4-connected walk over free
        cells from its cell to the cell of any of ``sources`` ``(K, 2)`` [m] (steps of one cell:
        at most sqrt(2) times the straight line); inf off the free cells or where none leads.
        Unlike the straight line it never passes through a wall."""
        pts = np.asarray(points, dtype=float).reshape(-1, 2)
        src = np.asarray(sources, dtype=float).reshape(-1, 2)
        rows, cols = self.free.shape
        out = np.full(len(pts), np.inf)
        if len(src) == 0 or len(pts) == 0:
            return out
        label = np.full(rows * cols, -1, dtype=np.int64)
        sr, sc = self._cells(src)
        inside = (sr >= 0) & (sr < rows) & (sc >= 0) & (sc < cols)
        label[sr[inside] * cols + sc[inside]] = 0
        dist, _ = K.bfs_labels(self.free.ravel(), label, rows, cols)
        pr, pc = self._cells(pts)
        ok = (pr >= 0) & (pr < rows) & (pc >= 0) & (pc < cols)
        steps = np.full(len(pts), -1, dtype=np.int64)
        steps[ok] = dist[pr[ok] * cols + pc[ok]]
        out[steps >= 0] = steps[steps >= 0] * self.resolution
        return out

    def _cells(self, pts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(rows, cols) of the cells holding ``pts`` [m] (may lie outside the grid)."""
        return (np.floor((pts[:, 1] - self.origin[1]) / self.resolution).astype(np.int64),
                np.floor((pts[:, 0] - self.origin[0]) / self.resolution).astype(np.int64))
