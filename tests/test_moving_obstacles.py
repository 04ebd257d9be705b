"""Obstacles that move (issue 28): the scenarios move MuJoCo mocap bodies and the world the stack is
told about follows; the physics counts a collision whoever moved and says who; the planner sweeps a
moving obstacle over the committed horizon, keeps a path still clear of it and plans anew when not."""

from __future__ import annotations

import math

import msgspec
import mujoco
import numpy as np
import pytest

from onboard.contracts import messages as m
from onboard.contracts.params import PlannerParams, SafetyLimits
from onboard.high_level.planning import moving_obstacles as mo
from onboard.high_level.planning.graph_planner import GraphPlanner, PlanningError
from robot_description import params as rd
from sim_twin import model as tm
from sim_twin import scenarios as sc
from sim_twin.lockstep import RunConfig, run
from sim_twin.metrics import PhysicsMetrics
from sim_twin.stack import TruthEstimator

MOVING = ["kicked", "sliding", "sliding-fast", "crossing"]


def _built(name: str, seed: int = 1):
    scn = sc.make(name, seed=seed)
    spec = tm.load_spec()
    scn.build(spec)
    model = spec.compile()
    data = mujoco.MjData(model)
    scn.initialize(model, data, rd.robot_params())
    return scn, model, data


def _geom_centre(model: mujoco.MjModel, data: mujoco.MjData, k: int) -> np.ndarray:
    return data.geom_xpos[model.geom(f"{sc.OBSTACLE_PREFIX}{k}").id][:2].copy()


@pytest.mark.parametrize("name", MOVING)
def test_movers_are_mocap_bodies_and_the_world_follows_them(name: str) -> None:
    scn, model, data = _built(name)
    assert scn.movers and model.nmocap == len(scn.movers)
    start = {k: _geom_centre(model, data, k) for k in scn.movers}
    root = int(model.joint(rd.ROOT_JOINT).qposadr[0])
    moved = set()
    for tick in range(30_000):  # 30 s at 1 ms; the robot is carried along the line (crossing's trigger)
        t = tick * 1e-3
        data.qpos[root] = min(t * 0.25, 4.0)
        scn.before_step(t, model, data)
        if tick % 500 == 0:
            mujoco.mj_kinematics(model, data)
            world = scn.polytopes(int(t * 1e9))
            for k in scn.movers:
                shift = _geom_centre(model, data, k) - start[k]
                assert np.allclose(shift, scn.offsets[k], atol=1e-9)  # the physics follows the scenario
                # the world told to the stack is the obstacle where it is, with its velocity
                verts = np.array(world.polytopes[k].vertices)
                assert np.allclose(verts, np.array(scn.obstacles[k].vertices) + scn.offsets[k], atol=1e-9)
                assert tuple(world.polytopes[k].velocity) == pytest.approx(tuple(scn.velocities[k]))
                if np.hypot(*shift) > 0.05:
                    moved.add(k)
    assert moved  # something moved during the run


def test_sliding_keeps_to_its_speed_and_away_from_start_and_goal() -> None:
    for seed in range(5):
        scn, model, data = _built("sliding", seed)
        geo = [sc._centre_radius(o) for o in scn.obstacles]
        for tick in range(0, 60_000, 50):
            scn.before_step(tick * 1e-3, model, data)
            speeds = np.hypot(scn.velocities[:, 0], scn.velocities[:, 1])
            assert np.all(speeds <= sc.Sliding.SPEED + 1e-12)
            for k in scn.movers:
                cx, cy, r = geo[k]
                c = (cx + scn.offsets[k, 0], cy + scn.offsets[k, 1])
                for p in (scn.start, scn.target()):
                    assert math.dist(c, p) >= r + sc.Sliding.CLEAR - 1e-9


def test_kicks_jump_up_to_half_a_metre_never_at_the_robot() -> None:
    scn, model, data = _built("kicked", 3)
    root = int(model.joint(rd.ROOT_JOINT).qposadr[0])
    geo = [sc._centre_radius(o) for o in scn.obstacles]
    # the robot stands in the field, in the open spot nearest its middle
    spots = [(x, y) for x in np.arange(1.0, 5.0, 0.1) for y in np.arange(-1.4, 1.4, 0.1)
             if all(math.dist((x, y), (cx, cy)) > r + 0.3 for cx, cy, r in geo)]
    robot = min(spots, key=lambda p: math.dist(p, (3.0, 0.0)))
    data.qpos[root:root + 2] = robot
    prev = scn.offsets.copy()
    for tick in range(0, 40_000):
        scn.before_step(tick * 1e-3, model, data)
        step = np.hypot(*(scn.offsets - prev).T)
        assert np.all(step <= sc.Kicked.KICK_MAX / sc.Kicked.KICK_S * 1e-3 + 1e-9)  # a jump takes KICK_S
        prev = scn.offsets.copy()
        for k, (cx, cy, r) in enumerate(geo):
            if scn.offsets[k, 0] or scn.offsets[k, 1]:  # a kicked one: never kicked at the robot
                c = (cx + scn.offsets[k, 0], cy + scn.offsets[k, 1])
                assert math.dist(c, robot) >= r + sc.Kicked.KICK_CLEAR - 1e-9
    assert scn.kicks_applied >= 5
    assert scn.world_summary()["kicks"] == scn.kicks_applied


def _metrics(scn: sc.Scenario, model: mujoco.MjModel) -> PhysicsMetrics:
    return PhysicsMetrics(model, scn, TruthEstimator(model, rd.robot_params()), SafetyLimits())


def test_an_obstacle_walking_into_the_robot_is_its_collision() -> None:
    scn, model, data = _built("crossing", 0)
    metrics = _metrics(scn, model)
    root = int(model.joint(rd.ROOT_JOINT).qposadr[0])
    cx, cy, r = sc._centre_radius(scn.obstacles[0])
    robot = np.array(data.qpos[root:root + 2])
    # the walker comes at the robot, standing still on its foot, at 1 m/s from 0.5 m
    direction = (robot - (cx, cy)) / np.hypot(*(robot - (cx, cy)))
    begin = robot - direction * (r + 0.5) - (cx, cy)
    for tick in range(800):
        t = tick * 1e-3
        scn.offsets[0] = begin + direction * t
        scn.velocities[0] = direction
        scn.move_obstacles(model, data)
        mujoco.mj_step(model, data)
        metrics.update(t, int(t * 1e9), data, None, None, (0.0, 0.0, 0.0, 0.0))
    report = metrics.summary(data, _actuation(model))
    assert report["collisions"] >= 1  # shoved away and caught up with again: each time the walker's
    assert report["collisions_by_obstacle"] == report["collisions"] and report["collisions_by_robot"] == 0
    events = report["collision_events"]
    assert len(events) == report["collisions"] and all(e["by"] == "obstacle" for e in events)
    assert 0.3 < events[0]["t_s"] < 0.8 and events[0]["since_hit_s"] is None  # 0.5 m at 1 m/s, less the radii
    assert all(0.0 < e["since_hit_s"] <= 2.0 for e in events[1:])  # caught up with again: soon after the last hit


def test_the_robot_moving_into_a_still_obstacle_is_the_robots_collision() -> None:
    scn, model, data = _built("crossing", 0)
    metrics = _metrics(scn, model)
    root = int(model.joint(rd.ROOT_JOINT).qposadr[0])
    dof = int(model.joint(rd.ROOT_JOINT).dofadr[0])
    cx, cy, r = sc._centre_radius(scn.obstacles[0])
    direction = np.array([0.0, math.copysign(1.0, cy)])
    data.qpos[root:root + 2] = (cx, cy) - direction * (r + 0.35)
    data.qvel[dof:dof + 2] = direction * 1.0  # the robot flies at the walker, who stands still
    mujoco.mj_forward(model, data)
    for tick in range(600):
        t = tick * 1e-3
        scn.move_obstacles(model, data)
        mujoco.mj_step(model, data)
        metrics.update(t, int(t * 1e9), data, None, None, (0.0, 0.0, 0.0, 0.0))
    report = metrics.summary(data, _actuation(model))
    assert report["collisions"] >= 1  # it may bounce: every episode the robot's
    assert report["collisions_by_robot"] == report["collisions"] and report["collisions_by_obstacle"] == 0
    assert [e["by"] for e in report["collision_events"]] == ["robot"] * report["collisions"]
    assert all(e["since_hit_s"] is None for e in report["collision_events"])  # nothing came at it first


def test_a_robot_tipping_into_an_obstacle_that_comes_slowly_is_the_robots_collision() -> None:
    """What moved into whom is read at the touching point: the robot's top swings into a walker that
    closes at 0.1 m/s while the robot's CoM drifts away from it; by the CoMs alone it was the walker's."""
    scn, model, data = _built("crossing", 0)
    model.opt.gravity[:] = 0.0  # a body tipping in the air, no floor or foot in the way
    metrics = _metrics(scn, model)
    root = int(model.joint(rd.ROOT_JOINT).qposadr[0])
    dof = int(model.joint(rd.ROOT_JOINT).dofadr[0])
    cx, cy, r = sc._centre_radius(scn.obstacles[0])
    direction = np.array([0.0, math.copysign(1.0, cy)])
    data.qpos[root:root + 2] = (cx, cy) - direction * (r + 0.2)
    data.qpos[root + 2] += 0.3
    mujoco.mj_forward(model, data)
    torso = model.body(rd.TORSO).id
    omega = np.array([-direction[1] * 4.0, 0.0, 0.0])  # the top toward the walker (upright: body axes are world axes)
    com_velocity = np.append(-direction * 0.05, 0.0)  # the CoM away from it
    data.qvel[dof:dof + 3] = com_velocity - np.cross(omega, data.subtree_com[torso] - data.xpos[torso])
    data.qvel[dof + 3:dof + 6] = omega
    for tick in range(500):
        t = tick * 1e-3
        scn.offsets[0] = -direction * 0.1 * t  # from where the scenario placed it
        scn.velocities[0] = -direction * 0.1
        scn.move_obstacles(model, data)
        mujoco.mj_step(model, data)
        metrics.update(t, int(t * 1e9), data, None, None, (0.0, 0.0, 0.0, 0.0))
        if metrics.collisions:
            break
    _, (vx, vy, _) = metrics.truth.com(data)
    assert metrics.collisions == 1 and vx * direction[0] + vy * direction[1] < 0.0  # its CoM still moving away
    assert [e["by"] for e in metrics.collision_events] == ["robot"]


def _actuation(model: mujoco.MjModel):
    from sim_twin.actuation import Actuation

    return Actuation(model, rd.robot_params(), SafetyLimits())


def test_polytope_velocity_is_optional_and_checked() -> None:
    static = m.Polytope(A=[[1.0, 0.0]], b=[1.0], vertices=[[0.0, 0.0]])
    assert b"velocity" not in msgspec.json.encode(static)  # a static world's message is as it was
    old = m.decode(msgspec.json.encode(m.PolytopeSet(mode="obstacles", polytopes=[static])), m.PolytopeSet)
    assert tuple(old.polytopes[0].velocity) == (0.0, 0.0) and old.polytopes[0].covariance == []
    moving = m.Polytope(A=[[1.0, 0.0]], b=[1.0], vertices=[[0.0, 0.0]], velocity=(0.3, -0.1))
    back = m.decode(msgspec.json.encode(m.PolytopeSet(mode="obstacles", polytopes=[moving])), m.PolytopeSet)
    assert tuple(back.polytopes[0].velocity) == (0.3, -0.1)
    with pytest.raises(m.MessageError):
        m.decode(b'{"mode":"obstacles","polytopes":[{"A":[],"b":[],"vertices":[],"velocity":[1.0]}]}', m.PolytopeSet)


def _square(cx: float, cy: float, h: float) -> np.ndarray:
    return np.array([[cx - h, cy - h], [cx + h, cy - h], [cx + h, cy + h], [cx - h, cy + h]])


def test_swept_polygon_is_the_hull_of_both_places() -> None:
    sq = _square(0.0, 0.0, 0.5)
    out = mo.swept(sq, np.array([2.0, 0.0]))
    assert out.shape == (4, 2)
    assert np.allclose(np.sort(out[:, 0]), [-0.5, -0.5, 2.5, 2.5])
    tri = np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]])
    hexa = mo.swept(tri, np.array([1.0, 1.0]))
    assert hexa.tolist() == [[0.0, 0.0], [1.0, 0.0], [2.0, 1.0], [1.0, 2.0], [0.0, 1.0]]  # CCW, no inner vertex
    capped = mo.sweep_obstacles([sq], np.array([[10.0, 0.0]]), horizon_s=1.0, max_m=0.5)[0]
    assert capped[:, 0].max() == pytest.approx(1.0)  # a kick is swept its cap, not 10 m
    assert mo.sweep_obstacles([sq], np.zeros((1, 2)), 1.0, 1.0)[0] is sq


def test_every_bands_sweep_is_the_hull_of_both_places_to_the_bit() -> None:
    """One hull order per obstacle serves every window: each band's polygon is ``swept`` of where the
    obstacle is at the window's ends, bit for bit; a window past the travel cap is the obstacle where
    it stopped; still obstacles are left out."""
    rng = np.random.default_rng(4)
    polys, vels = [], []
    for k in range(12):
        n = int(rng.integers(3, 9))
        angles = np.sort(rng.uniform(0.0, 2.0 * np.pi, n))
        polys.append(np.c_[np.cos(angles), np.sin(angles)] * rng.uniform(0.1, 0.6) + rng.uniform(-5.0, 5.0, 2))
        vels.append(rng.uniform(-0.5, 0.5, 2) if k % 4 else np.zeros(2))
    vel = np.array(vels)
    windows = np.array([[0.5 * b, 0.5 * b + 1.7] for b in range(10)])
    max_m = 1.5
    got = mo.band_polygons(polys, vel, mo.sweep_orders(polys, vel), windows, max_m)
    stopped = 0
    for (t0, t1), band in zip(windows.tolist(), got):
        want = []
        for poly, (vx, vy) in zip(polys, vel.tolist()):
            speed = math.hypot(vx, vy)
            if speed < mo.STILL:
                continue
            a, b = min(t0, max_m / speed), min(t1, max_m / speed)
            p0 = poly + np.array([vx * a, vy * a])
            stopped += b <= a
            want.append(p0 if b <= a else mo.swept(p0, np.array([vx * (b - a), vy * (b - a)])))
        assert len(band) == len(want) == 9
        for g, w in zip(band, want):
            assert g.shape == w.shape and np.array_equal(g, w)
    assert stopped > 0  # some windows lie past a fast one's cap


def _planner(**kw) -> GraphPlanner:
    prm = PlannerParams(nodes=1500, **kw)
    pl = GraphPlanner(prm, robot_radius=0.13, bounds=(-1.0, -2.0, 5.0, 2.0))
    pl.set_goal((4.0, 0.0))
    return pl


def test_static_obstacles_given_with_zero_velocity_plan_as_without() -> None:
    a, b = _planner(), _planner()
    polys = [_square(2.0, 0.0, 0.3)]
    a.set_obstacles(polys)
    b.set_obstacles(polys, [(0.0, 0.0)])
    ra, rb = a.plan((0.0, 0.0), (0.0, 0.0)), b.plan((0.0, 0.0), (0.0, 0.0))
    assert ra is not None and rb is not None
    assert np.array_equal(a.path.control_points, b.path.control_points)
    with pytest.raises(PlanningError):
        a.set_obstacles(polys, [(math.nan, 0.0)])
    with pytest.raises(PlanningError):
        a.set_obstacles(polys, [(0.0, 0.0), (1.0, 0.0)])


def _min_clearance(pl: GraphPlanner, poly: np.ndarray) -> float:
    from onboard.high_level.tracking import collision as col
    from onboard.geometry import polygons as pg

    pts = np.concatenate([c for c in pl.path.control_points])
    return float(col.samples_clearance(pts[None], pg.pack_polygons([poly]), reach=5.0)[0])


def test_a_moving_obstacle_is_planned_around_where_it_goes() -> None:
    # an obstacle beside the straight way, walking onto it at 0.4 m/s: where it will be is cut
    walker = _square(1.5, 0.8, 0.2)
    still, moving = _planner(), _planner()
    still.set_obstacles([walker])
    moving.set_obstacles([walker], [(0.0, -0.4)])
    assert still.plan((0.0, 0.0), (0.0, 0.0)) is not None and moving.plan((0.0, 0.0), (0.0, 0.0)) is not None
    ahead = walker + (0.0, -0.4 * PlannerParams().obstacle_sweep_s)
    assert _min_clearance(moving, ahead) >= moving.margin - 1e-6
    assert _min_clearance(still, ahead) < still.margin  # the static plan goes where it is going


def test_a_path_still_clear_is_kept_and_one_crossed_is_replanned() -> None:
    pl = _planner()
    far = _square(2.0, 1.7, 0.15)
    pl.set_obstacles([far], [(0.1, 0.0)])
    assert pl.plan((0.0, 0.0), (0.0, 0.0), 0) is not None
    plans = pl.stats.plans
    pl.set_obstacles([far + (0.05, 0.0)], [(0.1, 0.0)])  # moved, still far from the path
    assert not pl.needs_replan(np.array([0.0, 0.0]), 100_000_000, 0.3)
    on_path = pl.path.control_points[0][-1]  # moved onto the path
    pl.set_obstacles([_square(on_path[0], on_path[1], 0.15)], [(0.0, -0.1)])
    assert pl.needs_replan(np.array([0.0, 0.0]), 200_000_000, 0.3)
    assert pl.stats.plans == plans


def test_standing_in_a_sweep_it_still_finds_a_way_out() -> None:
    pl = _planner()
    # coming straight at the robot at 0.3 m/s from 0.4 m: the full sweep reaches where it stands
    pl.set_obstacles([_square(0.6, 0.0, 0.2)], [(-0.3, 0.0)])
    ref = pl.plan((0.0, 0.0), (0.0, 0.0), 0)
    assert ref is not None and pl.stats.sweep_relaxed >= 1


@pytest.mark.parametrize("name", ["crossing"])
def test_lockstep_planner_sees_the_world_move(name: str) -> None:
    res = run(RunConfig(scenario=name, seed=0, duration_s=4.0, estimator="truth", planner="graph", record=True))
    worlds = [msg for topic, _, msg in res.messages if topic == "polytopes"]
    assert len(worlds) >= 30  # the world topic's rate over 4 s (plus the one at the start)
    met = res.metrics
    assert met["collisions"] == met["collisions_by_robot"] + met["collisions_by_obstacle"]
    assert "planner_replans_per_s" in met and "time_to_goal_s" in met


def test_curve_bands_are_the_boxes_distances_in_bands() -> None:
    rng = np.random.default_rng(5)
    lo = rng.uniform(-3.0, 3.0, (2000, 2))
    aabb = np.hstack([lo, lo + rng.uniform(0.0, 1.0, (2000, 2))])
    origin = np.array([0.3, -0.2])
    dx = np.maximum(np.maximum(aabb[:, 0] - origin[0], origin[0] - aabb[:, 2]), 0.0)
    dy = np.maximum(np.maximum(aabb[:, 1] - origin[1], origin[1] - aabb[:, 3]), 0.0)
    expected = np.floor(np.hypot(dx, dy) / 0.4).astype(np.int64)
    bands = mo.curve_bands(aabb, origin, 0.4)
    np.testing.assert_array_equal(bands, expected)
    inside = (aabb[:, 0] <= origin[0]) & (origin[0] <= aabb[:, 2]) & (aabb[:, 1] <= origin[1]) & (origin[1] <= aabb[:, 3])
    assert inside.any() and np.all(bands[inside] == 0)  # a box holding the origin is in the first band


def test_among_moving_obstacles_a_replan_starts_where_the_robot_is() -> None:
    # a replan there dodges an obstacle: from the robot's state, not from where its old path would be
    from onboard.high_level.planning.bezier_graph import path_states

    pl = _planner()
    pl.set_obstacles([_square(2.0, 1.7, 0.15)], [(0.0, 0.0)])  # velocities given, none moving yet
    assert pl.plan((0.0, 0.0), (0.0, 0.0), 0) is not None
    stamp = 1_500_000_000
    on_path = path_states(pl.path.control_points, pl.path.tau, np.array([stamp * 1e-9]))[0]
    near = on_path[:2] + (0.0, 0.5 * pl.tube)
    assert pl.plan(near, (0.0, 0.0), stamp) is not None
    start = path_states(pl.path.control_points, pl.path.tau, np.array([0.0]))[0]
    assert np.allclose(start, [near[0], near[1], 0.0, 0.0])
