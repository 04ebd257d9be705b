"""The whole perception chain in one object: views in, convex sets out (pure, no clock).

    view = Perception(params)
    view.integrate(depth_image, robot_xy=(x, y))       # each depth image, at apex
    polys, stats = view.polytopes(robot_xy=(x, y))     # at the publication rate
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from onboard.contracts.binary_messages import CELL_FREE, CELL_OCCUPIED, DepthImage, OccupancyGrid
from onboard.contracts.params import PerceptionParams
from onboard.perception.decomposition import DecompositionStats, decompose_free_space
from onboard.perception.geometry import ConvexPolygon
from onboard.perception.obstacles import obstacles_from_mask
from onboard.perception.occupancy import OccupancyMap
from onboard.perception.pointcloud import depth_to_points
from onboard.perception.segmentation import OCCUPIED, TRAVERSABLE, UNTRAVERSABLE, Cloud, GeometricSegmenter, Segmenter
from onboard.perception.terrain import ColorTerrainSegmenter

MODES = ("free", "obstacles")
NS = 1_000_000_000


@dataclass
class ViewStats:
    """What one fused view held: valid returns and how they were labelled."""

    points: int = 0
    traversable: int = 0
    occupied: int = 0
    untraversable: int = 0
    ground_inliers: int = 0


class Perception:
    """Depth images -> fused occupancy grid -> convex free cells or convex obstacles."""

    def __init__(self, params: PerceptionParams = PerceptionParams(), segmenter: Segmenter | None = None,
                 centre: tuple[float, float] = (0.0, 0.0)) -> None:
        if params.mode not in MODES:
            raise ValueError(f"perception mode must be one of {MODES}, got {params.mode!r}")
        self.params = params
        if segmenter is None:
            segmenter = ColorTerrainSegmenter(params) if params.segmenter == "color" else GeometricSegmenter(params)
        self.segmenter: Segmenter = segmenter
        self.map = OccupancyMap(params, centre)

    def integrate(self, img: DepthImage, robot_xy: tuple[float, float] | None = None,
                  color: np.ndarray | None = None) -> ViewStats:
        """Fuse one depth image (its ``stamp_ns`` is the capture time); ``color``: the RGB image
        aligned to it (the D435's), for a segmenter that reads colour."""
        p = self.params
        if robot_xy is not None:
            if not all(math.isfinite(v) for v in robot_xy):
                raise ValueError("robot position is not finite")
            self.map.follow(*robot_xy)
        pts, valid = depth_to_points(img, p.max_range_m, p.pixel_stride)
        image = None
        if color is not None:
            if color.shape[:2] != img.depth.shape:
                raise ValueError(f"colour image {color.shape[:2]} is not aligned to the depth image {img.depth.shape}")
            image = color[::p.pixel_stride, ::p.pixel_stride]
        foot = np.array(robot_xy, dtype=float) if robot_xy is not None else None
        labels = self.segmenter.segment(Cloud(pts, valid, np.asarray(img.cam_pos, dtype=float), image, foot))
        keep = labels != 0
        flat_pts = pts[keep]
        flat_lab = labels[keep]
        cam = (float(img.cam_pos[0]), float(img.cam_pos[1]))
        self.map.integrate(flat_pts, flat_lab, cam, img.stamp_ns / NS, robot_xy)
        plane = getattr(self.segmenter, "plane", None)
        return ViewStats(
            points=int(valid.sum()),
            traversable=int((flat_lab == TRAVERSABLE).sum()),
            occupied=int((flat_lab == OCCUPIED).sum()),
            untraversable=int((flat_lab == UNTRAVERSABLE).sum()),
            ground_inliers=int(plane.inliers) if plane is not None else 0,
        )

    def grid(self, stamp_ns: int = 0, seq: int = 0) -> OccupancyGrid:
        return self.map.grid(stamp_ns, seq)

    def polytopes(
        self,
        mode: str | None = None,
        robot_xy: tuple[float, float] | None = None,
        must_cover: tuple[tuple[float, float], ...] = (),
    ) -> tuple[list[ConvexPolygon], dict[str, float]]:
        """Convex sets of the current grid (see :func:`polytopes_of_grid`)."""
        return polytopes_of_grid(self.map.grid(), self.params, mode or self.params.mode, robot_xy, must_cover)


def polytopes_of_grid(
    grid: OccupancyGrid,
    params: PerceptionParams,
    mode: str,
    robot_xy: tuple[float, float] | None = None,
    must_cover: tuple[tuple[float, float], ...] = (),
) -> tuple[list[ConvexPolygon], dict[str, float]]:
    """Convex free cells in the robot's free region (unknown counts as blocked), or
    convex obstacles around the occupied cells (unknown counts as free), with counts."""
    if mode == "free":
        polys, st = decompose_free_space(grid.cells == CELL_FREE, grid.resolution, grid.origin, params,
                                         start=robot_xy, must_cover=must_cover)
        return polys, _dec_stats(st)
    if mode == "obstacles":
        polys = obstacles_from_mask(grid.cells == CELL_OCCUPIED, grid.resolution, grid.origin, params)
        return polys, {"polygons": float(len(polys))}
    raise ValueError(f"perception mode must be one of {MODES}, got {mode!r}")


def _dec_stats(st: DecompositionStats) -> dict[str, float]:
    return {k: float(v) for k, v in vars(st).items()}


class PerceptionLoop:
    """Perception on the caller's clock (the lockstep runner): every depth image is fused
    as it arrives; a new set of convex sets is made every ``1 / rate_hz``."""

    def __init__(self, params: PerceptionParams = PerceptionParams()) -> None:
        if not params.rate_hz > 0:
            raise ValueError("perception rate must be positive")
        self.params = params
        self.view = Perception(params)
        self.period_ns = int(round(NS / params.rate_hz))
        self.next_ns = 0
        self.sets = 0
        self.last_stamp_ns = -1

    def feed(self, img: DepthImage, robot_xy: tuple[float, float] | None, color: np.ndarray | None = None) -> bool:
        """Fuse one depth image (and the RGB image aligned to it); False (and nothing fused) when it
        is older than the last."""
        if img.stamp_ns <= self.last_stamp_ns:
            return False
        self.view.integrate(img, robot_xy, color)
        self.last_stamp_ns = img.stamp_ns
        return True

    def update(
        self, now_ns: int, robot_xy: tuple[float, float] | None, goal_xy: tuple[float, float] | None = None
    ) -> list[ConvexPolygon] | None:
        """A new set when one is due and a view has been fused, else None. In ``free``
        mode the robot's free region is decomposed, keeping the robot and the goal inside."""
        if now_ns < self.next_ns or self.view.map.views == 0:
            return None
        self.next_ns = now_ns + self.period_ns
        cover = tuple(p for p in (robot_xy, goal_xy) if p is not None)
        free = self.params.mode == "free"
        polys, _ = self.view.polytopes(robot_xy=robot_xy if free else None, must_cover=cover if free else ())
        self.sets += 1
        return polys
