"""World-frame occupancy grid fused over views, with decay (thesis 3336: vertical binning).

Labelled points are binned vertically into square cells. Each view adds evidence:
``+hit`` to a cell holding at least ``min_points_per_cell`` obstacle points, or as many returns
of untraversable ground (grass beside the path) and more of them than of traversable ground (one
return was enough once, and paving misjudged at 4 m came out as specks in the way); ``-miss`` to
a cell seen as ground (a ground return in it, or a ray passing over it on its way to a return
within the carving range; one on its way to untraversable ground only up to ground known
untraversable, or an obstacle), unless it holds a return of untraversable ground: a ray passing
over flat ground says nothing of what that ground is. A cell last hit as untraversable ground is
freed by its own traversable returns only, never by a ray passing over it (at the perception's
pixel stride a distant cell of grass holds a return in one view and none in the next; the rays to
the grass beyond it then carved it free). Evidence saturates at ``+-evidence_max``; cells a view
does not see fade to unknown with a half-life, so what moved away is forgotten. The grid follows
the robot by whole cells, so it stays aligned with the world axes.

In ``free`` mode the planner may only go where the grid holds free, so the grid keeps
what it has seen (the world of a run stands still): free evidence does not fade, and a
cell seen free turns occupied at once when it is seen occupied (its free evidence is
dropped, not outweighed hit by hit). The ground the robot stands on and passed over,
out to ``stand_radius_m``, is free unless seen occupied: the camera never sees it (its
near blind zone), yet the robot must stand inside a free cell to plan from there; only
cells in sight of the robot are cleared, past none with any occupied evidence (even
faded below the threshold), so an obstacle seen on its near face keeps its inside.
"""

from __future__ import annotations

import math

import numpy as np

from onboard.contracts.binary_messages import CELL_FREE, CELL_OCCUPIED, CELL_UNKNOWN, OccupancyGrid
from onboard.contracts.params import PerceptionParams
from onboard.perception import _kernels as K
from onboard.perception.segmentation import OCCUPIED, TRAVERSABLE, UNTRAVERSABLE


class OccupancyMap:
    """Evidence per cell; positive = occupied. Rows along world y, columns along x."""

    def __init__(self, params: PerceptionParams = PerceptionParams(), centre: tuple[float, float] = (0.0, 0.0)) -> None:
        if params.grid_cells < 2 or not params.resolution_m > 0:
            raise ValueError("grid needs at least 2 cells and a positive resolution")
        self.params = params
        self.res = params.resolution_m
        n = params.grid_cells
        self.evidence = np.zeros((n, n), dtype=np.float32)
        self.terrain = np.zeros((n, n), dtype=bool)  # last hit as untraversable ground (see the module docstring)
        half = 0.5 * n * self.res
        self.origin = (self._snap(centre[0] - half), self._snap(centre[1] - half))
        self.last_stamp_s: float | None = None
        self.views = 0
        self.keep_free = params.mode == "free"  # see the module docstring

    def _snap(self, x: float) -> float:
        return math.floor(x / self.res) * self.res

    @property
    def shape(self) -> tuple[int, int]:
        return self.evidence.shape  # type: ignore[return-value]

    def centre(self) -> tuple[float, float]:
        half = 0.5 * self.params.grid_cells * self.res
        return self.origin[0] + half, self.origin[1] + half

    def follow(self, x: float, y: float) -> bool:
        """Shift the grid by whole cells to centre it on ``(x, y)`` [m] when the robot is
        ``recenter_distance_m`` off centre; new cells are unknown. True if it moved."""
        cx, cy = self.centre()
        if max(abs(x - cx), abs(y - cy)) < self.params.recenter_distance_m:
            return False
        n = self.params.grid_cells
        dc = int(round((x - cx) / self.res))
        dr = int(round((y - cy) / self.res))
        src_r = slice(max(dr, 0), n + min(dr, 0))
        dst_r = slice(max(-dr, 0), n + min(-dr, 0))
        src_c = slice(max(dc, 0), n + min(dc, 0))
        dst_c = slice(max(-dc, 0), n + min(-dc, 0))

        def shifted(layer: np.ndarray) -> np.ndarray:
            out = np.zeros_like(layer)
            if abs(dr) < n and abs(dc) < n:
                out[dst_r, dst_c] = layer[src_r, src_c]
            return out

        self.evidence, self.terrain = shifted(self.evidence), shifted(self.terrain)
        self.origin = (self.origin[0] + dc * self.res, self.origin[1] + dr * self.res)
        return True

    def integrate(
        self,
        points: np.ndarray,
        labels: np.ndarray,
        sensor_xy: tuple[float, float],
        stamp_s: float,
        footprint_xy: tuple[float, float] | None = None,
    ) -> None:
        """Fuse one view: ``points`` ``(N, 3)`` world [m] with ``labels`` ``(N,)``.

        ``sensor_xy`` [m] is where the rays start (the camera, projected); ``stamp_s``
        [s] the capture time (decay uses the time since the previous view);
        ``footprint_xy`` [m], the robot's position, is cleared to free.
        """
        p = self.params
        if not math.isfinite(stamp_s):
            raise ValueError("view stamp is not finite")
        rows, cols = self.shape
        ox, oy = self.origin
        u = (points[:, 0] - ox) / self.res
        v = (points[:, 1] - oy) / self.res
        fin = np.isfinite(u) & np.isfinite(v)
        inside = fin & (u >= 0) & (u < cols) & (v >= 0) & (v < rows)
        c = np.where(inside, u, 0).astype(np.intp)
        r = np.where(inside, v, 0).astype(np.intp)

        def per_cell(label: int) -> np.ndarray:
            at = inside & (labels == label)
            return np.bincount(r[at] * cols + c[at], minlength=rows * cols).reshape(rows, cols)

        counts, on_ground, off_ground = per_cell(OCCUPIED), per_cell(TRAVERSABLE), per_cell(UNTRAVERSABLE)
        # Vertical binning: a real obstacle puts a column of returns into its cell, a
        # noisy ground return only one, so a cell needs a few obstacle points per view.
        off_hit = (off_ground >= p.min_points_per_cell) & (off_ground > on_ground)
        occ = (counts >= p.min_points_per_cell) | off_hit
        self.terrain[off_hit] = True
        self.terrain[on_ground > off_ground] = False
        ground = on_ground > 0
        # Rays over the ground to every return within the carving range. One to untraversable ground
        # stops at the first cell known untraversable or occupied: beyond a kerb it passes over cells
        # the kerb hides, and those, never seen, came out free.
        su, sv = (sensor_xy[0] - ox) / self.res, (sensor_xy[1] - oy) / self.res
        ray = fin & (labels != 0)
        ray &= np.hypot(u - su, v - sv) * self.res <= p.carve_range_m
        if math.isfinite(su) and math.isfinite(sv) and np.any(ray):
            stop = self.terrain | occ | (self.evidence >= p.occupied_threshold)
            K.carve(float(su), float(sv), u[ray].astype(float), v[ray].astype(float), labels[ray] == TRAVERSABLE,
                    labels[ray] == UNTRAVERSABLE, stop, rows, cols, ground)
        seen = occ | ground
        e = self.evidence
        if self.last_stamp_s is not None and p.decay_half_life_s > 0:
            dt = max(stamp_s - self.last_stamp_s, 0.0)
            fade = ~seen & (e > 0) if self.keep_free else ~seen
            e[fade] *= np.float32(0.5 ** (dt / p.decay_half_life_s))
        self.last_stamp_s = stamp_s if self.last_stamp_s is None else max(stamp_s, self.last_stamp_s)
        if self.keep_free:
            e[occ] = np.maximum(e[occ], 0.0)
        e[occ] += p.hit_evidence
        free_now = ground & ~occ & (off_ground == 0) & ~(self.terrain & (on_ground == 0))
        e[free_now] -= p.miss_evidence
        np.clip(e, -p.evidence_max, p.evidence_max, out=e)
        if footprint_xy is not None:
            if self.keep_free:
                self.clear_in_sight(footprint_xy, p.stand_radius_m)
            self.clear_disc(footprint_xy, p.footprint_radius_m)
        self.views += 1

    def clear_in_sight(self, xy: tuple[float, float], radius: float) -> None:
        """Set to free the cells whose centre is within ``radius`` [m] of ``xy`` [m] and in sight
        of it: neither the cell nor one the straight line to it crosses holds any occupied
        evidence (even faded below the threshold). An obstacle seen only on its near face
        keeps its unseen inside: the line to it crosses that face."""
        found = self._disc(xy, radius)
        if found is None:
            return
        cu, cv, k, (r0, r1, c0, c1), uu, vv, disc = found
        rows, cols = self.shape
        tu, tv = uu[disc], vv[disc]
        # samples every half cell along each line: none can step over a cell unseen
        t = np.linspace(0.0, 1.0, int(math.ceil(2 * k)) + 2)
        su = np.clip((cu + np.outer(tu - cu, t)).astype(np.intp), 0, cols - 1)
        sv = np.clip((cv + np.outer(tv - cv, t)).astype(np.intp), 0, rows - 1)
        clear = ~np.any(self.evidence[sv, su] > 0.0, axis=1)
        cleared = tv[clear].astype(np.intp), tu[clear].astype(np.intp)
        self.evidence[cleared] = -self.params.evidence_max
        self.terrain[cleared] = False

    def clear_disc(self, xy: tuple[float, float], radius: float) -> None:
        """Set the cells whose centre is within ``radius`` [m] of ``xy`` [m] to free."""
        found = self._disc(xy, radius)
        if found is not None:
            _, _, _, (r0, r1, c0, c1), _, _, disc = found
            self.evidence[r0:r1, c0:c1][disc] = -self.params.evidence_max
            self.terrain[r0:r1, c0:c1][disc] = False

    def _disc(self, xy: tuple[float, float], radius: float) -> tuple | None:
        """The cells whose centre is within ``radius`` [m] of ``xy`` [m]: ``(cu, cv, k, (r0, r1,
        c0, c1), uu, vv, disc)`` with ``xy`` and ``radius`` in cell units, the window, its cell
        centres and the mask over it; None when ``xy`` is not finite or the window is off the grid."""
        rows, cols = self.shape
        cu = (xy[0] - self.origin[0]) / self.res
        cv = (xy[1] - self.origin[1]) / self.res
        if not (math.isfinite(cu) and math.isfinite(cv)):
            return None
        k = radius / self.res
        c0, c1 = max(int(cu - k) - 1, 0), min(int(cu + k) + 2, cols)
        r0, r1 = max(int(cv - k) - 1, 0), min(int(cv + k) + 2, rows)
        if c0 >= c1 or r0 >= r1:
            return None
        uu, vv = np.meshgrid(np.arange(c0, c1) + 0.5, np.arange(r0, r1) + 0.5)
        return cu, cv, k, (r0, r1, c0, c1), uu, vv, (uu - cu) ** 2 + (vv - cv) ** 2 <= k * k

    def occupied(self) -> np.ndarray:
        return self.evidence >= self.params.occupied_threshold

    def free(self) -> np.ndarray:
        return self.evidence <= -self.params.free_threshold

    def grid(self, stamp_ns: int = 0, seq: int = 0) -> OccupancyGrid:
        """The binary message: 0 free, 100 occupied, 255 unknown."""
        cells = np.full(self.shape, CELL_UNKNOWN, dtype=np.uint8)
        cells[self.free()] = CELL_FREE
        cells[self.occupied()] = CELL_OCCUPIED
        return OccupancyGrid(cells, self.res, self.origin, stamp_ns, seq)
