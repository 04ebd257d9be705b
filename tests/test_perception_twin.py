"""The twin's ray-cast depth camera over the ``forest`` scenario, through the perception
chain, checked against the scenario's ground-truth obstacles."""

from __future__ import annotations

import math

import mujoco
import numpy as np
import pytest

from onboard.contracts.params import PerceptionParams, TwinParams
from onboard.perception.geometry import ConvexPolygon, polygon_from_points
from onboard.perception.pipeline import Perception
from onboard.perception.pointcloud import depth_to_points
from robot_description import params as rd
from sim_twin import model as tm
from sim_twin import scenarios as sc
from sim_twin.sensors import SensorSuite

APEX_M = 0.3  # foot this high: the robot sees at apex
SURFACE_TOL_M = 0.02  # a depth return this close to a true obstacle's boundary is on it
NEAR_M = 0.05  # one cell: how far a perceived obstacle may stick out of the true one
FAR_FALSE_M = 0.3  # a perceived obstacle farther than this from every true one is a false positive
RECALL_RANGE_M = 4.0


def _distance_to(poly: ConvexPolygon, pts: np.ndarray) -> np.ndarray:
    """Euclidean distance [m] from each point to a convex polygon (0 inside)."""
    v = poly.vertices
    a, b = v, np.roll(v, -1, axis=0)
    d = b - a
    t = np.clip(np.einsum("pkj,kj->pk", pts[:, None, :] - a[None], d) / np.einsum("kj,kj->k", d, d), 0.0, 1.0)
    proj = a[None] + t[..., None] * d[None]
    dist = np.linalg.norm(pts[:, None, :] - proj, axis=2).min(axis=1)
    inside = np.all(pts @ poly.A.T <= poly.b, axis=1)
    return np.where(inside, 0.0, dist)


def _views(seed: int):
    """Depth images from apex poses along the way to the goal, looking ahead and aside."""
    scen = sc.make("forest", seed=seed)
    spec = tm.load_spec()
    scen.build(spec)
    model = spec.compile()
    data = mujoco.MjData(model)
    robot = rd.robot_params()
    scen.initialize(model, data, robot)
    sensors = SensorSuite(model, TwinParams(), seed=seed)  # with the twin's depth noise
    adr = int(model.joint(rd.ROOT_JOINT).qposadr[0])
    truth = [polygon_from_points(np.array(p.vertices)) for p in scen.polytopes().polytopes]
    images = []
    k = 0
    for x in (0.0, 1.0, 2.0):
        if any(t.contains(np.array([[x, 0.0]]), 0.3)[0] for t in truth):
            continue  # the robot would stand in a tree
        for yaw in (0.0, 0.6, -0.6):
            data.qpos[adr:adr + 3] = [x, 0.0, robot.leg_length + APEX_M]
            data.qpos[adr + 3:adr + 7] = [math.cos(yaw / 2), 0.0, 0.0, math.sin(yaw / 2)]
            mujoco.mj_forward(model, data)
            k += 1
            images.append(((x, 0.0), sensors.depth_image(data, k * 200_000_000)))
    return truth, images


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_forest_obstacles_match_ground_truth(seed):
    truth, images = _views(seed)
    params = PerceptionParams()
    view = Perception(params)
    for xy, img in images:
        view.integrate(img, robot_xy=xy)
    obstacles, _ = view.polytopes("obstacles")
    assert obstacles

    # Precision: every perceived obstacle sits on a true one (no phantom in the open).
    for ob in obstacles:
        d = min(float(_distance_to(t, ob.vertices).max()) for t in truth)
        assert d <= FAR_FALSE_M, f"phantom obstacle at {ob.vertices.mean(axis=0)}"
    # How far perceived obstacles stick out of the true ones: a cell (5 cm, the corner of
    # a cell holding a surface return) plus depth noise (5 mm x range^2 in the twin).
    outward = [min(float(_distance_to(t, ob.vertices).max()) for t in truth) for ob in obstacles]
    assert np.median(outward) <= 2 * NEAR_M, outward

    # Recall: the returns that hit a true obstacle within range lie in a perceived obstacle.
    on_truth = []
    for _, img in images:
        pts, valid = depth_to_points(img, RECALL_RANGE_M)
        p = pts[valid][:, :2]
        p = p[np.linalg.norm(pts[valid] - img.cam_pos, axis=1) <= RECALL_RANGE_M]
        for t in truth:
            on_truth.append(p[_distance_to(t, p) <= SURFACE_TOL_M])
    hits = np.concatenate(on_truth)
    assert len(hits) > 100
    covered = np.zeros(len(hits), dtype=bool)
    for ob in obstacles:
        covered |= _distance_to(ob, hits) <= NEAR_M
    assert covered.mean() >= 0.95, covered.mean()


@pytest.mark.parametrize("seed", [0, 1])
def test_forest_free_cells_stay_out_of_the_trees(seed):
    truth, images = _views(seed)
    view = Perception(PerceptionParams())
    robot = images[-1][0]
    for xy, img in images:
        view.integrate(img, robot_xy=xy)
    free, stats = view.polytopes("free", robot_xy=robot, must_cover=(robot,))
    assert free and stats["groups"] == 1
    assert any(f.contains(np.array([robot]))[0] for f in free)
    # Depth noise and 5 cm cells: a free cell may graze a trunk by less than one cell,
    # which the planner's robot-radius margin absorbs; never more.
    for f in free:
        xmin, ymin, xmax, ymax = f.bbox()
        gx, gy = np.meshgrid(np.arange(xmin, xmax, 0.01), np.arange(ymin, ymax, 0.01))
        pts = np.column_stack([gx.ravel(), gy.ravel()])
        pts = pts[f.contains(pts)]
        for t in truth:
            depth_in = (t.b[None, :] - pts @ t.A.T).min(axis=1)
            assert depth_in.max(initial=0.0) <= NEAR_M, f"free cell {depth_in.max():.3f} m inside a tree"
