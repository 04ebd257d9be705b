"""Depth to points, segmentation, occupancy fusion with decay, and the whole chain on
analytically ray-cast scenes (ground plane, tree trunks, boxes)."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from onboard.contracts.binary_messages import CELL_FREE, CELL_OCCUPIED, CELL_UNKNOWN, DepthImage, decode_grid, encode_grid
from onboard.contracts.params import PerceptionParams
from onboard.perception.occupancy import OccupancyMap
from onboard.perception.pipeline import Perception
from onboard.perception.pointcloud import depth_to_points
from onboard.perception.segmentation import (
    IGNORE,
    OCCUPIED,
    TRAVERSABLE,
    UNTRAVERSABLE,
    Cloud,
    GeometricSegmenter,
    MaskSegmenter,
    fit_ground_plane,
)
from onboard.geometry.quaternion import from_matrix

PARAMS = PerceptionParams()
W, H, HFOV_DEG = 64, 48, 87.0  # the twin's camera
# Optical frame (x right, y down, z forward) -> a level camera looking along world +x.
LEVEL = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


def _camera_rotation(yaw: float, pitch_down: float) -> np.ndarray:
    cp, sp = math.cos(pitch_down), math.sin(pitch_down)
    cy, sy = math.cos(yaw), math.sin(yaw)
    pitch = np.array([[cp, 0.0, sp], [0.0, 1.0, 0.0], [-sp, 0.0, cp]])
    yaw_m = np.array([[cy, -sy, 0.0], [sy, cy, 0.0], [0.0, 0.0, 1.0]])
    return yaw_m @ pitch @ LEVEL


def render(pos, yaw=0.0, pitch_down=math.radians(20), cylinders=(), boxes=(), ground_z=0.0, ground_slope=0.0,
           stamp_ns=0, max_range=6.0) -> DepthImage:
    """Ray-cast a depth image: ground ``z = ground_z + slope x``, vertical cylinders
    ``(x, y, radius, height)`` and boxes ``(x0, y0, x1, y1, z0, z1)``."""
    R = _camera_rotation(yaw, pitch_down)
    p = np.asarray(pos, dtype=float)
    f = 0.5 * W / math.tan(math.radians(HFOV_DEG) / 2)
    u, v = np.meshgrid(np.arange(W) + 0.5, np.arange(H) + 0.5)
    d = np.stack([(u - W / 2) / f, (v - H / 2) / f, np.ones_like(u)], axis=-1) @ R.T  # optical z = 1
    with np.errstate(divide="ignore", invalid="ignore"):
        denom = d[..., 2] - ground_slope * d[..., 0]
        t = np.where(denom < 0, (ground_z + ground_slope * p[0] - p[2]) / denom, np.inf)
        for cx, cy, r, ht in cylinders:
            ox, oy = p[0] - cx, p[1] - cy
            a = d[..., 0] ** 2 + d[..., 1] ** 2
            b = 2 * (ox * d[..., 0] + oy * d[..., 1])
            c = ox * ox + oy * oy - r * r
            disc = b * b - 4 * a * c
            tc = (-b - np.sqrt(disc)) / (2 * a)
            z = p[2] + tc * d[..., 2]
            ok = (disc >= 0) & (tc > 0) & (z >= ground_z) & (z <= ht)
            t = np.where(ok & (tc < t), tc, t)
        for x0, y0, x1, y1, z0, z1 in boxes:
            lo, hi = np.array([x0, y0, z0]), np.array([x1, y1, z1])
            t1, t2 = (lo - p) / d, (hi - p) / d
            tmin = np.nanmax(np.minimum(t1, t2), axis=-1)
            tmax = np.nanmin(np.maximum(t1, t2), axis=-1)
            ok = (tmax >= tmin) & (tmin > 0)
            t = np.where(ok & (tmin < t), tmin, t)
    depth = np.where(np.isfinite(t) & (t <= max_range), t, 0.0).astype(np.float32)
    return DepthImage(depth, f, f, W / 2, H / 2, p.copy(), np.array(from_matrix(R)), stamp_ns, 0)


def test_depth_to_points_pinhole_and_pose():
    depth = np.zeros((4, 6), dtype=np.float32)
    depth[1, 4] = 2.0
    depth[3, 0] = 7.0  # beyond max range
    img = DepthImage(depth, fx=3.0, fy=2.0, cx=3.0, cy=2.0, cam_pos=np.array([1.0, 2.0, 0.5]),
                     cam_quat=np.array(from_matrix(LEVEL)))
    pts, valid = depth_to_points(img, max_range=6.0)
    assert valid.sum() == 1 and valid[1, 4]
    # Pixel centre (4.5, 1.5): optical ray ((4.5-3)/3, (1.5-2)/2, 1) * 2 = (1.0, -0.5, 2).
    # Level camera: optical z -> world x, optical x -> world -y, optical y -> world -z.
    assert np.allclose(pts[1, 4], [1.0 + 2.0, 2.0 - 1.0, 0.5 + 0.5])
    with pytest.raises(ValueError):
        depth_to_points(dataclasses.replace(img, cam_quat=np.zeros(4)))


def test_ground_plane_found_on_a_slope_and_obstacles_above_it():
    slope = math.tan(math.radians(10))
    img = render((0, 0, 0.6), cylinders=[(2.0, 0.0, 0.2, 2.0)], ground_slope=slope)
    pts, valid = depth_to_points(img, PARAMS.max_range_m)
    seg = GeometricSegmenter(PARAMS)
    labels = seg.segment(Cloud(pts, valid, img.cam_pos))
    expected = np.array([-slope, 0.0, 1.0]) / math.hypot(slope, 1.0)
    assert np.dot(seg.plane.normal, expected) > math.cos(math.radians(1.0))
    on_trunk = valid & (np.hypot(pts[..., 0] - 2.0, pts[..., 1]) < 0.25) & (pts[..., 2] > slope * pts[..., 0] + 0.1)
    assert on_trunk.sum() > 20
    assert np.all(labels[on_trunk] == OCCUPIED)
    ground = valid & ~on_trunk & (np.abs(pts[..., 2] - slope * pts[..., 0]) < 0.01)
    assert (labels[ground] == TRAVERSABLE).mean() > 0.97


def test_overhang_ignored_low_box_occupied():
    img = render((0, 0, 0.5), boxes=[(1.5, -0.3, 1.8, 0.3, 0.0, 0.15), (2.5, -2.0, 3.0, 2.0, 1.3, 1.5)], pitch_down=math.radians(5))
    pts, valid = depth_to_points(img, PARAMS.max_range_m)
    labels = GeometricSegmenter(PARAMS).segment(Cloud(pts, valid, img.cam_pos))
    low = valid & (pts[..., 0] > 1.49) & (pts[..., 0] < 1.81) & (pts[..., 2] > 0.05) & (np.abs(pts[..., 1]) < 0.3)
    high = valid & (pts[..., 2] > 1.25)
    assert low.sum() > 5 and high.sum() > 5
    assert np.all(labels[low] == OCCUPIED)
    assert np.all(labels[high] == IGNORE)


def test_ransac_rejects_too_few_points_and_steep_planes():
    rng = np.random.default_rng(0)
    wall = np.column_stack([np.full(200, 2.0), rng.uniform(-1, 1, 200), rng.uniform(0, 1, 200)])
    assert fit_ground_plane(wall, PARAMS, rng) is None
    assert fit_ground_plane(wall[:5], PARAMS, rng) is None


def test_learned_segmenter_plugs_in():
    img = render((0, 0, 0.5))
    pts, valid = depth_to_points(img, PARAMS.max_range_m)
    # A stand-in for a learned model: "sidewalk" is the strip |y| < 0.5.
    seg = MaskSegmenter(lambda cloud: np.abs(cloud.points[..., 1]) < 0.5, PARAMS)
    labels = seg.segment(Cloud(pts, valid, img.cam_pos))
    assert np.all(labels[valid & (np.abs(pts[..., 1]) < 0.5)] == TRAVERSABLE)
    assert np.all(labels[valid & (np.abs(pts[..., 1]) > 0.5)] == UNTRAVERSABLE)  # the floor outside the mask
    with pytest.raises(ValueError, match="mask"):
        MaskSegmenter(lambda cloud: np.ones((2, 2), dtype=bool)).segment(Cloud(pts, valid, img.cam_pos))
    # The perception chain takes it like the geometric default.
    view = Perception(PARAMS, segmenter=seg)
    view.integrate(img, robot_xy=(0.0, 0.0))
    grid = view.grid()
    res, (ox, oy) = grid.resolution, grid.origin
    y = oy + (np.arange(grid.cells.shape[0]) + 0.5) * res
    occupied_rows = np.nonzero((grid.cells == CELL_OCCUPIED).any(axis=1))[0]
    assert len(occupied_rows) > 0
    assert np.all(np.abs(y[occupied_rows]) > 0.5 - res)
    assert (grid.cells[np.abs(y) < 0.45] == CELL_FREE).sum() > 100


def test_occupancy_fuses_views_decays_and_follows():
    p = PARAMS
    occ_map = OccupancyMap(p)
    # A column of two obstacle returns at (1, 1), a ground return, a lone obstacle return.
    pts = np.array([[1.0, 1.0, 0.3], [1.01, 1.01, 0.5], [1.5, 0.0, 0.0], [2.0, -1.0, 0.2]])
    labels = np.array([OCCUPIED, OCCUPIED, TRAVERSABLE, OCCUPIED], dtype=np.int8)
    occ_map.integrate(pts, labels, (0.0, 0.0), stamp_s=0.0)
    g = occ_map.grid()
    res, (ox, oy) = g.resolution, g.origin
    cell = lambda x, y: (int((y - oy) / res), int((x - ox) / res))  # noqa: E731
    assert g.cells[cell(1.0, 1.0)] == CELL_OCCUPIED
    assert g.cells[cell(1.5, 0.0)] == CELL_FREE
    assert g.cells[cell(0.75, 0.0)] == CELL_FREE  # carved along the ray to the ground return
    assert g.cells[cell(-1.0, 0.0)] == CELL_UNKNOWN
    assert g.cells[cell(2.0, -1.0)] != CELL_OCCUPIED  # one return is noise, not an obstacle
    # Seen again, then an empty view later: unseen cells fade (one half-life halves the
    # evidence); after many half-lives they are unknown.
    occ_map.integrate(pts, labels, (0.0, 0.0), stamp_s=0.1)
    occ_map.integrate(np.zeros((0, 3)), np.zeros(0, dtype=np.int8), (0.0, 0.0), stamp_s=0.1 + p.decay_half_life_s)
    assert occ_map.evidence[cell(1.0, 1.0)] == pytest.approx(0.5 * 2 * p.hit_evidence)
    assert occ_map.grid().cells[cell(1.0, 1.0)] == CELL_OCCUPIED
    occ_map.integrate(np.zeros((0, 3)), np.zeros(0, dtype=np.int8), (0.0, 0.0), stamp_s=5 * p.decay_half_life_s)
    assert occ_map.grid().cells[cell(1.0, 1.0)] == CELL_UNKNOWN
    # Repeated evidence saturates, and a single contrary view does not flip a confident cell.
    for k in range(5):
        occ_map.integrate(pts[:2], labels[:2], (0.0, 0.0), stamp_s=100.0 + k)
    occ_map.integrate(np.array([[1.0, 1.0, 0.0]]), np.array([TRAVERSABLE], dtype=np.int8), (0.0, 0.0), stamp_s=106.0)
    assert occ_map.grid().cells[cell(1.0, 1.0)] == CELL_OCCUPIED
    # Following the robot shifts by whole cells and keeps world positions.
    assert not occ_map.follow(0.5, 0.0)
    assert occ_map.follow(3.0, 0.0)
    g2 = occ_map.grid()
    assert (g2.origin[0] - ox) / res == pytest.approx(round((g2.origin[0] - ox) / res))
    r2, c2 = int((1.0 - g2.origin[1]) / res), int((1.0 - g2.origin[0]) / res)
    assert g2.cells[r2, c2] == CELL_OCCUPIED
    assert decode_grid(encode_grid(g2)).cells.tobytes() == g2.cells.tobytes()


def test_footprint_is_free_and_bad_stamp_rejected():
    occ_map = OccupancyMap(PARAMS)
    occ_map.integrate(np.zeros((0, 3)), np.zeros(0, dtype=np.int8), (0.0, 0.0), 0.0, footprint_xy=(0.3, -0.2))
    g = occ_map.grid()
    assert g.cells[int((-0.2 - g.origin[1]) / g.resolution), int((0.3 - g.origin[0]) / g.resolution)] == CELL_FREE
    with pytest.raises(ValueError):
        occ_map.integrate(np.zeros((0, 3)), np.zeros(0, dtype=np.int8), (0.0, 0.0), math.nan)


TREES = [(2.0, 0.4, 0.15, 2.0), (3.0, -0.8, 0.2, 2.0), (1.6, -1.2, 0.12, 2.0), (3.5, 1.2, 0.25, 2.0)]


def _look_around(view: Perception, trees, robot=(0.0, 0.0)) -> None:
    for k, yaw in enumerate((0.0, 0.7, -0.7)):
        view.integrate(render((robot[0], robot[1], 0.5), yaw=yaw, cylinders=trees, stamp_ns=(k + 1) * 200_000_000), robot_xy=robot)


@pytest.mark.parametrize("mode", ["obstacles", "free"])
def test_scene_to_polytopes_against_ground_truth(mode):
    view = Perception(PARAMS)
    _look_around(view, TREES)
    polys, stats = view.polytopes(mode, robot_xy=(0.0, 0.0), must_cover=((0.0, 0.0),))
    assert polys
    # Ground truth: the trunks' discs.
    if mode == "obstacles":
        # Every trunk's visible face is inside an obstacle, and every obstacle is near a trunk.
        for tx, ty, r, _ in TREES:
            face = np.array([[tx - r * math.cos(a), ty - r * math.sin(a)] for a in np.linspace(-0.5, 0.5, 5)]) * 0.999 + 0.001 * np.array([tx, ty])
            assert all(any(p.contains(q[None], 1e-6)[0] for p in polys) for q in face), (tx, ty)
        for p in polys:
            centre = p.vertices.mean(axis=0)
            assert min(math.hypot(centre[0] - tx, centre[1] - ty) - r for tx, ty, r, _ in TREES) < 0.1
    else:
        # No free polygon enters a trunk, seen side or not (lattice of points in each), beyond
        # the grid's own resolution: a cell that a ray crosses beside a trunk is free although
        # the trunk's disc clips its corner (a polygon may reach that corner; the planner's
        # margin is more than a cell).
        cell_diagonal = PARAMS.resolution_m * math.sqrt(2.0)
        for p in polys:
            xmin, ymin, xmax, ymax = p.bbox()
            gx, gy = np.meshgrid(np.arange(xmin, xmax, 0.005), np.arange(ymin, ymax, 0.005))
            pts = np.column_stack([gx.ravel(), gy.ravel()])
            pts = pts[p.contains(pts)]
            for tx, ty, r, _ in TREES:
                assert np.all(np.hypot(pts[:, 0] - tx, pts[:, 1] - ty) >= r - cell_diagonal)
        assert any(p.contains(np.array([[0.0, 0.0]]))[0] for p in polys)
        assert stats["groups"] == 1


def test_integrate_rejects_non_finite_robot_position():
    view = Perception(PARAMS)
    with pytest.raises(ValueError):
        view.integrate(render((0, 0, 0.5)), robot_xy=(math.nan, 0.0))
    with pytest.raises(ValueError, match="mode"):
        Perception(dataclasses.replace(PARAMS, mode="everything"))


def test_ground_plane_is_kept_while_it_explains_the_view_and_follows_a_new_slope():
    seg = GeometricSegmenter(PARAMS)
    flat = render((0, 0, 0.5), cylinders=TREES)
    pts, valid = depth_to_points(flat, PARAMS.max_range_m)
    seg.segment(Cloud(pts, valid, flat.cam_pos))
    first = seg.plane
    img = render((0, 0, 0.55), yaw=0.3, cylinders=TREES)
    pts, valid = depth_to_points(img, PARAMS.max_range_m)
    seg.segment(Cloud(pts, valid, img.cam_pos))
    assert seg.kept == 1 and np.array_equal(seg.plane.normal, first.normal)
    slope = math.tan(math.radians(12))
    img = render((0, 0, 0.5), ground_slope=slope)  # the robot now faces a ramp
    pts, valid = depth_to_points(img, PARAMS.max_range_m)
    seg.segment(Cloud(pts, valid, img.cam_pos))
    assert math.degrees(math.acos(seg.plane.normal[2])) == pytest.approx(12.0, abs=0.5)
