"""Scenarios: registered names, seeded worlds, obstacles as geoms and as polytopes, terrain, pushes."""

from __future__ import annotations

import math

import mujoco
import numpy as np
import pytest

from robot_description import params as rd
from sim_twin import model as tm
from sim_twin import scenarios as sc

ALL = ["hop-in-place", "setpoint", "square", "lissajous", "push", "flip", "shove", "step", "ramp", "blind-side", "forest",
       "forest-500", "maze", "kicked", "sliding", "sliding-fast", "crossing", "sidewalk", "stairs", "board", "treadmill", "maze-600"]


def _compiled(scn: sc.Scenario) -> tuple[mujoco.MjModel, mujoco.MjData]:
    spec = tm.load_spec()
    scn.build(spec)
    model = spec.compile()
    data = mujoco.MjData(model)
    scn.initialize(model, data, rd.robot_params())
    return model, data


def _ground_height(model: mujoco.MjModel, data: mujoco.MjData, x: float, y: float) -> float:
    geomid = np.zeros(1, dtype=np.int32)
    d = mujoco.mj_ray(model, data, np.array([x, y, 5.0]), np.array([0.0, 0.0, -1.0]),
                      np.array([1, 0, 0, 0, 0, 0], dtype=np.uint8), 1, -1, geomid)
    return 5.0 - d


def test_registry_has_every_scenario() -> None:
    assert list(sc.SCENARIOS) == ALL
    with pytest.raises(ValueError):
        sc.make("volcano")


@pytest.mark.parametrize("name", ALL)
def test_scenario_builds_and_starts_clear(name: str) -> None:
    scn = sc.make(name, seed=1)
    model, data = _compiled(scn)
    assert data.ncon == 0  # starts in the air, touching nothing
    ref = scn.reference(123)
    assert ref.t_ref_ns == 123 and ref.segments
    x0 = sc.sample_reference(ref.segments, 0.0)
    assert math.dist(x0, scn.start) < 1e-9
    end = sc.sample_reference(ref.segments, 1e6)
    assert math.dist(end, scn.target()) < 1e-9
    robot = rd.robot_params()
    foot_z = data.qpos[2] - robot.leg_length
    assert foot_z == pytest.approx(_ground_height(model, data, *scn.start) + sc.START_DROP, abs=1e-6)
    # obstacles: geoms named obstacle_k whose footprint is the ground-truth polygon
    poly = scn.polytopes()
    # ...and after them the keep-out ground (the sidewalk's verges), polytopes with no geom
    assert poly.source == "ground_truth" and len(poly.polytopes) == len(scn.obstacles) + len(scn.keep_out)
    solid = poly.polytopes[:len(scn.obstacles)]
    for k, p in enumerate(solid):
        a, b, verts = np.array(p.A), np.array(p.b), np.array(p.vertices)
        assert np.all(a @ verts.T <= b[:, None] + 1e-9)
        centre = verts.mean(axis=0)
        assert np.all(a @ centre < b)
        gid = model.geom(f"{sc.OBSTACLE_PREFIX}{k}").id
        assert model.geom_contype[gid] == 1
        assert _ground_height(model, data, *centre) == pytest.approx(sc.OBSTACLE_HEIGHT, abs=1e-6)
        outside = centre + 1.02 * (verts[0] - centre) + 0.01 * (verts[0] - centre) / np.linalg.norm(verts[0] - centre)
        inside_any = any(np.all(np.array(q.A) @ outside <= np.array(q.b)) for q in solid)
        assert (_ground_height(model, data, *outside) > sc.OBSTACLE_HEIGHT - 0.1) == inside_any


def test_seed_changes_every_random_choice() -> None:
    a, b, c = sc.make("forest", seed=5), sc.make("forest", seed=5), sc.make("forest", seed=6)
    assert a.obstacles == b.obstacles and a.obstacles != c.obstacles
    assert len(sc.make("forest", seed=2, obstacles=4).obstacles) == 4
    with pytest.raises(ValueError, match="within 0..200"):
        sc.make("forest", seed=0, obstacles=500)
    assert len(sc.make("forest-500", seed=3).obstacles) == 500  # thesis Fig. 7.5's count, in the field that holds it
    for seed in range(20):  # the first forest obstacle blocks the straight line to the goal
        ys = [v[1] for v in sc.make("forest", seed=seed).obstacles[0].vertices]
        assert min(ys) < 0.0 < max(ys)
    assert sc.make("maze", seed=1).obstacles != sc.make("maze", seed=2).obstacles
    assert sc.make("setpoint", seed=0).goal_xy == (2.0, 0.0)
    g = sc.make("setpoint", seed=9).goal_xy
    assert math.hypot(*g) == pytest.approx(2.0) and g != (2.0, 0.0)


@pytest.mark.parametrize("factor", [2, 3])
def test_a_dense_forest_is_placed_whole_in_a_grown_field_and_reported(factor: int) -> None:
    default = sc.make("forest", seed=4)
    for seed in range(5):
        f = sc.make("forest", seed=seed, obstacles=factor * sc.Forest.DEFAULT_COUNT)
        world = f.world_summary()
        assert world["obstacles"] == len(f.obstacles) == factor * sc.Forest.DEFAULT_COUNT
        # denser than the default forest, and the goal beyond the field, reached in proportion
        assert world["obstacles_per_m2"] > default.world_summary()["obstacles_per_m2"]
        (x0, x1), (y0, y1) = world["field_m"]
        assert f.goal_xy[0] > x1 and f.default_duration_s > default.default_duration_s
        centres = [np.mean(ob.vertices, axis=0) for ob in f.obstacles]
        assert all(x0 - 0.4 <= cx <= x1 + 0.4 and y0 - 0.4 <= cy <= y1 + 0.4 for cx, cy in centres)
        for i, a in enumerate(f.obstacles):  # the minimum gap holds (circumradius bound)
            for b in f.obstacles[i + 1:]:
                gap = min(math.dist(p, q) for p in a.vertices for q in b.vertices)
                assert gap >= sc.Forest.GAP - 1e-9


def test_terrain_heights() -> None:
    step = sc.make("step")
    model, data = _compiled(step)
    assert _ground_height(model, data, step.EDGE - 0.05, 0.0) == pytest.approx(0.0, abs=1e-9)
    assert _ground_height(model, data, step.EDGE + 0.05, 0.0) == pytest.approx(0.038, abs=1e-9)
    ramp = sc.make("ramp")
    model, data = _compiled(ramp)
    top = ramp.LENGTH * math.tan(math.radians(20))
    assert _ground_height(model, data, 0.0, 0.0) == pytest.approx(top, abs=1e-9)
    mid = ramp.TOP + 0.3
    assert _ground_height(model, data, mid, 0.0) == pytest.approx(top - 0.3 * math.tan(math.radians(20)), abs=1e-6)
    assert _ground_height(model, data, ramp.goal_xy[0], 0.0) == pytest.approx(0.0, abs=1e-9)


def test_square_reference_visits_corners() -> None:
    sq = sc.make("square")
    segs = sq.reference().segments
    corners = [tuple(s.control_points[0]) for s in segs] + [tuple(segs[-1].control_points[-1])]
    assert corners[:5] == [(0.0, 0.0), (1.0, 0.0), (1.0, 1.0), (0.0, 1.0), (0.0, 0.0)]
    assert len(segs) == 8  # two laps
    assert sc.sample_reference(segs, segs[0].duration / 2) == pytest.approx((0.5, 0.0))


def test_push_delivers_its_impulse() -> None:
    push = sc.make("push", seed=3)
    model, data = _compiled(push)
    model.opt.gravity[:] = 0.0
    data.qpos[2] = 3.0
    mass = rd.robot_params().total_mass
    dt = model.opt.timestep
    while data.time < push.FIRST + push.PUSH_TIME + 0.05:
        push.before_step(data.time, model, data)
        mujoco.mj_step(model, data)
    mujoco.mj_subtreeVel(model, data)
    v = data.subtree_linvel[model.body("torso").id]
    ang = push.push_angles[0]
    assert mass * v[:2] == pytest.approx([push.IMPULSE * math.cos(ang), push.IMPULSE * math.sin(ang)], abs=2 * push.IMPULSE * dt / push.PUSH_TIME)
    assert push.pushes_applied == 1


def test_the_stairs_rise_a_stair_at_each_edge_and_the_board_stands_on_the_floor() -> None:
    from sim_twin.scenarios_thesis import Board, Stairs

    model, data = _compiled(sc.make("stairs", seed=0))
    for k in range(Stairs.STEPS):
        edge = Stairs.FIRST_EDGE + k * Stairs.TREAD
        assert _ground_height(model, data, edge - 0.02, 0.0) == pytest.approx(k * Stairs.RISE, abs=1e-6)
        assert _ground_height(model, data, edge + 0.02, 0.0) == pytest.approx((k + 1) * Stairs.RISE, abs=1e-6)
    model, data = _compiled(sc.make("board", seed=0))
    assert _ground_height(model, data, Board.AT + Board.WIDTH / 2, 0.3) == pytest.approx(Board.HEIGHT, abs=1e-6)
    assert _ground_height(model, data, Board.AT + Board.WIDTH + 0.02, 0.0) == pytest.approx(0.0, abs=1e-6)


def test_the_treadmill_reference_moves_at_the_belt_speed_of_each_stage() -> None:
    scn = sc.make("treadmill", seed=0)
    for k, speed in enumerate(scn.SPEEDS):
        t = scn.SETTLE_S + (k + 0.5) * scn.STAGE_S
        dx = sc.sample_reference(scn.segments, t + 0.5)[0] - sc.sample_reference(scn.segments, t - 0.5)[0]
        assert dx == pytest.approx(speed, rel=1e-9) and scn.belt_speed(t) == speed
    assert sc.sample_reference(scn.segments, 1.0) == scn.start and scn.belt_speed(1.0) == 0.0


@pytest.mark.parametrize("seed", range(6))
def test_the_600_cell_maze_joins_start_and_goal_with_room_for_the_robot(seed: int) -> None:
    """A walk over the cell centres, stepping only where the robot's footprint and tube clear every wall."""
    from sim_twin.scenarios_thesis import GridMaze

    scn = sc.make("maze-600", seed=seed)
    assert 220 <= len(scn.obstacles) <= 340  # the thesis's figure: 300
    clearance = 0.13 + 0.1  # the robot's radius and the planner's tube
    polys = [np.array(o.vertices) for o in scn.obstacles]

    def blocked(p: np.ndarray) -> bool:
        for v in polys:
            lo, hi = v.min(axis=0) - clearance, v.max(axis=0) + clearance
            if np.all(p >= lo) and np.all(p <= hi):
                return True
        return False

    c = GridMaze.CELL
    start, goal = (0, 0), (GridMaze.COLUMNS - 1, GridMaze.ROWS - 1)
    assert scn.goal_xy == pytest.approx((goal[0] * c, goal[1] * c))
    seen, frontier = {start}, [start]
    while frontier:
        i, j = frontier.pop()
        for a, b in ((i + 1, j), (i - 1, j), (i, j + 1), (i, j - 1)):
            if not (0 <= a < GridMaze.COLUMNS and 0 <= b < GridMaze.ROWS) or (a, b) in seen:
                continue
            if not any(blocked(np.array([(i + s * (a - i)) * c, (j + s * (b - j)) * c])) for s in np.linspace(0.0, 1.0, 9)):
                seen.add((a, b))
                frontier.append((a, b))
    assert goal in seen
    assert len(seen) > 0.9 * GridMaze.COLUMNS * GridMaze.ROWS  # nearly every cell is reachable, not just one corridor


def test_the_sidewalks_grass_is_kept_off_all_round_the_paving() -> None:
    """The keep-out ground rings the paving: a step off it past a kerb, or past either end, lands in it
    (with open ends a planner that found no way between the posts went round the verges across the
    grass behind the start); the paving itself is in none."""
    scn = sc.make("sidewalk", seed=1)
    zones = [(np.array(p.A), np.array(p.b)) for p in (o.polytope() for o in scn.keep_out)]

    def kept_off(x: float, y: float) -> bool:
        return any(np.all(a @ np.array([x, y]) <= b + 1e-9) for a, b in zones)

    w, x0, x1 = sc.Sidewalk.HALF_WIDTH, -1.0, sc.Sidewalk.LENGTH
    for x in np.linspace(x0 + 0.01, x1 - 0.01, 30):
        assert kept_off(x, w + 0.05) and kept_off(x, -w - 0.05) and not kept_off(x, 0.0)
    for y in np.linspace(-w, w, 10):
        assert kept_off(x0 - 0.05, y) and kept_off(x1 + 0.05, y)
        assert not kept_off(scn.start[0], y * 0.9) and not kept_off(scn.target()[0], y * 0.9)


def test_the_widest_way_past_the_obstacles_is_the_narrowest_link_of_the_best_chain() -> None:
    """Two staggered posts across a 2 m strip: beside each, on its own side, 0.55 m and 0.35 m; the way
    goes between them, over the lower and under the upper, as wide as their diagonal gap."""
    def post(x: float, y: float, half: float) -> sc.Obstacle:
        return sc.Obstacle(np.array([[x - half, y - half], [x + half, y - half], [x + half, y + half], [x - half, y + half]]))

    lower, upper = post(1.0, -0.4, 0.05), post(1.3, 0.5, 0.15)  # corners (1.05, -0.35) and (1.15, 0.35)
    assert sc.widest_way([lower, upper], -1.0, 1.0) == pytest.approx(math.hypot(0.1, 0.7))
    assert sc.widest_way([lower, post(1.3, 0.5, 0.3)], -1.0, 1.0) == pytest.approx(0.55)  # a larger upper post: 0.55 m between them too
    assert sc.widest_way([], -1.0, 1.0) == pytest.approx(2.0)
    # far apart along the strip: each post alone, its wider side
    assert sc.widest_way([post(1.0, -0.4, 0.05), post(5.0, 0.5, 0.15)], -1.0, 1.0) == pytest.approx(
        min(max(0.55, 1.35), max(1.35, 0.35)))


def test_every_sidewalk_keeps_its_promise_of_a_way() -> None:
    """The placement keeps GAP beside every obstacle on one side and between obstacles, so a way GAP
    wide is left on every seed; a run's report carries its width (a miss on a narrow layout is told
    from a miss on a wide one)."""
    widths = []
    for seed in range(60):
        scn = sc.make("sidewalk", seed=seed)
        w = scn.world_summary()["widest_way_m"]
        assert w >= sc.Sidewalk.GAP - 1e-3, seed
        assert w == pytest.approx(sc.widest_way(scn.obstacles, -sc.Sidewalk.HALF_WIDTH, sc.Sidewalk.HALF_WIDTH), abs=1e-3)
        widths.append(w)
    assert min(widths) < 0.7 < max(widths)  # the layouts differ: some tight, some open


def test_touchdowns_on_the_grass_are_counted() -> None:
    """No geom marks the grass, so no contact does: the metrics count the touchdowns whose foot lands
    in the keep-out ground. The robot hopping in place on the verge: every one; on the paving: none."""
    from sim_twin.lockstep import LockstepRunner, RunConfig

    def touchdowns(y_offset: float) -> tuple[int, int]:
        runner = LockstepRunner(RunConfig(scenario="sidewalk", seed=1, duration_s=2.0, variant="outdoor"))
        runner.data.qpos[1] += y_offset  # the free joint's y: moved before the first step
        m = runner.run().metrics
        return m["hops"], m["keep_out_touchdowns"]

    hops, on_grass = touchdowns(-1.5)
    assert hops >= 3 and on_grass >= hops
    hops, on_grass = touchdowns(0.0)
    assert hops >= 3 and on_grass == 0
