"""The ``planner`` service on a real Zenoh session over loopback."""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import time

import numpy as np
import pytest

from onboard.geometry import polygons as pg
from onboard.contracts.binary_messages import CELL_FREE, CELL_UNKNOWN, OccupancyGrid, encode_grid
from onboard.contracts import messages as m
from onboard.contracts.params import PlannerParams
from onboard.contracts.topics import TOPICS
from services.runtime.peers import query_status
from services.planner import PlannerService, load_or_build_graph, robot_footprint_radius
from services.runtime.zenoh_session import open_session
from helpers import wait_for, with_running_service

NS = "archer/planner-test"
# session, and every process a later test starts would inherit it (test_twin_cli's real-time depth run then
# made no plan at all in fresh-clone CI, and passed alone)
PARAMS = PlannerParams(nodes=900, tube=0.05)
ROBOT_RADIUS = 0.13



def _state(x: float, y: float) -> m.StateEstimate:
    return m.StateEstimate(
        stamp_ns=time.monotonic_ns(), position=[x, y, 0.5], velocity=[0.0, 0.0, 0.0], quat=[1.0, 0.0, 0.0, 0.0],
        omega=[0.0, 0.0, 0.0], wheel_vel=[0.0, 0.0, 0.0], foot_pos=0.0, foot_vel=0.0, contact=False, phase="flight",
        pos_vel_cov=[0.0] * 36, att_cov=[0.0, 0.0, 0.0],
    )


async def _stream_resting_state(client, ns: str, stop: asyncio.Event) -> None:
    """The estimator at 50 Hz, the robot resting at the origin."""
    while not stop.is_set():
        client.put(TOPICS["state"].key(ns), m.encode(_state(0.0, 0.0)))
        await asyncio.sleep(0.02)


def _box(cx: float, cy: float, h: float) -> m.Polytope:
    verts = [[cx - h, cy - h], [cx + h, cy - h], [cx + h, cy + h], [cx - h, cy + h]]
    A, b = pg.polygon_halfspaces(np.array(verts))
    return m.Polytope(A=A.tolist(), b=b.tolist(), vertices=verts)


@contextlib.asynccontextmanager
async def _running_planner(endpoint: str, ns: str, params: PlannerParams, cache_dir):
    """The planner service running, a client session, the references it publishes, and the robot resting
    at the origin streamed as its state; all of it stopped whatever the test does."""
    service = PlannerService(ns=ns, endpoint=endpoint, params={"planner": params}, robot_radius=ROBOT_RADIUS,
                             cache_dir=cache_dir)
    task = asyncio.create_task(service.run())
    client = open_session(endpoint, "peer")
    refs: list[m.ComReference] = []
    sub = client.declare_subscriber(TOPICS["reference"].key(ns), lambda s: refs.append(m.decode(s.payload.to_bytes(), m.ComReference)))
    stop_state = asyncio.Event()
    feeder = asyncio.create_task(_stream_resting_state(client, ns, stop_state))
    try:
        await wait_for(lambda: service.state == "running")
        yield service, client, refs
    finally:
        stop_state.set()
        await feeder
        sub.undeclare()
        service.stopping.set()
        await asyncio.wait_for(task, 10.0)
        client.close()


def test_plans_refines_reports_broken_promises_and_holds_without_a_path(zenoh_router, tmp_path):
    async def scenario() -> None:
        service = PlannerService(ns=NS, endpoint=zenoh_router, params={"planner": PARAMS}, robot_radius=ROBOT_RADIUS,
                                 cache_dir=tmp_path)
        task = asyncio.create_task(service.run())
        client = open_session(zenoh_router, "peer")
        refs: list[m.ComReference] = []
        wps: list[m.Waypoints] = []
        reports: list[m.ContractReport] = []
        subs = [
            client.declare_subscriber(TOPICS["reference"].key(NS), lambda s: refs.append(m.decode(s.payload.to_bytes(), m.ComReference))),
            client.declare_subscriber(TOPICS["waypoints"].key(NS), lambda s: wps.append(m.decode(s.payload.to_bytes(), m.Waypoints))),
            client.declare_subscriber(TOPICS["contract"].key(NS), lambda s: reports.append(m.decode(s.payload.to_bytes(), m.ContractReport))),
        ]
        stop_state = asyncio.Event()
        feeder = asyncio.create_task(_stream_resting_state(client, NS, stop_state))
        try:
            await wait_for(lambda: service.state == "running")
            await asyncio.sleep(0.3)
            # a world given whole (as the twin's ground truth): nothing to wait to see
            obstacles = m.PolytopeSet(mode="obstacles", polytopes=[_box(1.5, 0.0, 0.3)], source="ground_truth",
                                      stamp_ns=time.monotonic_ns())  # the service's clock: its latency is measured
            client.put(TOPICS["polytopes"].key(NS), m.encode(obstacles))
            client.put(TOPICS["goal"].key(NS), m.encode(m.Goal(position=[3.0, 0.0], tolerance=0.1)))
            await wait_for(lambda: any(not r.hold for r in refs) and wps)
            ref = next(r for r in refs if not r.hold)
            first = np.array(ref.segments[0].control_points[0])
            assert np.max(np.abs(first)) <= PARAMS.tube + 1e-6  # starts within the tube (box) of the state
            assert np.allclose(ref.segments[-1].control_points[-1], [3.0, 0.0], atol=1e-6)
            t = 0.0
            for seg in ref.segments:  # consecutive, gap-free segments
                assert seg.t0 == pytest.approx(t, abs=1e-9)
                t += seg.duration
            assert np.allclose(wps[-1].points[-1], [3.0, 0.0]) and len(wps[-1].sets) == len(wps[-1].points)
            # Refined at the tick rate; published when it changes, and at least every 0.1 s (timed once
            # no graph builds beside the ticks: the first one may have started before the obstacles came)
            await wait_for(lambda: service._build is None)
            n0, e0 = len(refs), service.status_extra()
            # the world's stamp to the first tick that planned on it: measured, and within the wait above
            assert 0.0 < e0["world_to_plan_ms_p50"] <= e0["world_to_plan_ms_p99"] < 60_000.0
            await asyncio.sleep(1.0)
            e1 = service.status_extra()
            ticks = (e1["refine_solves"] + e1["refine_reused"]) - (e0["refine_solves"] + e0["refine_reused"])
            assert ticks >= 0.5 * PARAMS.refine_hz and e1["refine_solves"] > e0["refine_solves"]
            assert len(refs) - n0 >= 8
            # A malformed (non-convex) polytope set is rejected, counted, and the world kept.
            bad = m.Polytope(A=[], b=[], vertices=[[0, 0], [2, 0], [1, 0.2], [2, 2], [0, 2]])
            client.put(TOPICS["polytopes"].key(NS), m.encode(m.PolytopeSet(mode="obstacles", polytopes=[bad])))
            # The low level reports a tube over the promise: a contract report, and a larger tube.
            client.put(TOPICS["tube"].key(NS), m.encode(m.TrackingTube(hops=20, impact_err_p50=0.1, impact_err_p95=0.2,
                                                                         impact_err_max=0.3, attitude_err_p95=0.05)))
            await wait_for(lambda: reports)
            rep = reports[0]
            assert rep.layer == "planner" and rep.violated and rep.violations == 1
            assert rep.promised == pytest.approx(0.05) and rep.achieved == pytest.approx(0.2)
            status = await asyncio.to_thread(query_status, client, NS, "planner")
            assert status.contract == "violated" and status.counters["contract_violations"] == 1
            assert status.extra["tube_m"] == pytest.approx(0.2 * PARAMS.tube_growth)
            assert status.counters["rejected.polytopes_geometry"] >= 1 and status.extra["path"] == 1.0
            # A goal inside an obstacle: no path, a hold reference (hop in place), and the status says so.
            client.put(TOPICS["goal"].key(NS), m.encode(m.Goal(position=[1.5, 0.0], tolerance=0.1)))
            await wait_for(lambda: service.status_extra()["path"] == 0.0 and refs[-1].hold)
            hold = refs[-1]
            assert hold.segments[0].control_points[0] == [0.0, 0.0]
            status = await asyncio.to_thread(query_status, client, NS, "planner")
            assert status.state == "degraded" and "no path" in status.last_error
            assert status.extra["no_path"] >= 1
        finally:
            stop_state.set()
            await feeder
            for sub in subs:
                sub.undeclare()
            service.stopping.set()
            await asyncio.wait_for(task, 10.0)
            client.close()

    asyncio.run(asyncio.wait_for(scenario(), 120))


def test_perceived_obstacles_commit_the_robot_only_over_ground_the_grid_saw_free(zenoh_router, tmp_path):
    ns = NS + "3"

    async def scenario() -> None:
        service = PlannerService(ns=ns, endpoint=zenoh_router, params={"planner": PARAMS}, robot_radius=ROBOT_RADIUS,
                                 cache_dir=tmp_path)
        refs: list[m.ComReference] = []

        async def drive(client) -> None:
            sub = client.declare_subscriber(TOPICS["reference"].key(ns), lambda s: refs.append(m.decode(s.payload.to_bytes(), m.ComReference)))
            stop_state = asyncio.Event()
            feeder = asyncio.create_task(_stream_resting_state(client, ns, stop_state))
            try:
                # perception's obstacles (unknown counts as free there) and no grid yet: hold, facing the goal
                client.put(TOPICS["polytopes"].key(ns), m.encode(m.PolytopeSet(mode="obstacles", polytopes=[])))
                client.put(TOPICS["goal"].key(ns), m.encode(m.Goal(position=[2.0, 0.0], tolerance=0.1)))
                await wait_for(lambda: service.status_extra()["unseen_holds"] > 5 and refs)
                assert all(r.hold for r in refs)
                assert any(r.yaw is not None and abs(r.yaw) < 1.0 for r in refs)
                # the grid says the way ahead was seen free: the robot may go
                cells = np.full((80, 80), CELL_FREE, dtype=np.uint8)
                grid = OccupancyGrid(stamp_ns=time.monotonic_ns(), seq=1, resolution=0.05, origin=(-2.0, -2.0), cells=cells)
                client.put(TOPICS["grid"].key(ns), encode_grid(grid))
                await wait_for(lambda: any(not r.hold for r in refs))
                # a grid with nothing seen: held again
                n = len(refs)
                unseen = OccupancyGrid(stamp_ns=time.monotonic_ns(), seq=2, resolution=0.05, origin=(-2.0, -2.0),
                                       cells=np.full((80, 80), CELL_UNKNOWN, dtype=np.uint8))
                client.put(TOPICS["grid"].key(ns), encode_grid(unseen))
                await wait_for(lambda: len(refs) > n + 3 and refs[-1].hold)
            finally:
                stop_state.set()
                await feeder
                sub.undeclare()

        await with_running_service(service, zenoh_router, drive)

    asyncio.run(asyncio.wait_for(scenario(), 60))


def test_a_goal_the_planner_cannot_take_is_refused_once_and_the_last_plan_kept(zenoh_router, tmp_path):
    """A goal far outside any graph the planner can build (1000, 1000) is refused when it arrives,
    once, with its reason in the status; the planner does not fail on every tick over it, and the
    robot keeps the goal and the plan it had."""
    ns = NS + "-far"

    async def scenario() -> None:
        async with _running_planner(zenoh_router, ns, PARAMS, tmp_path) as (service, client, refs):
            client.put(TOPICS["polytopes"].key(ns), m.encode(m.PolytopeSet(mode="obstacles", polytopes=[], source="ground_truth")))
            client.put(TOPICS["goal"].key(ns), m.encode(m.Goal(position=[2.0, 0.0], tolerance=0.1)))
            await wait_for(lambda: any(not r.hold for r in refs))
            errors_before = service.counters.get("errors")
            client.put(TOPICS["goal"].key(ns), m.encode(m.Goal(position=[1000.0, 1000.0], tolerance=0.1)))
            await wait_for(lambda: service.counters.get("rejected.goal_unreachable") == 1)
            n0 = len(refs)
            await asyncio.sleep(1.0)  # about refine_hz ticks with the refused goal gone by
            status = await asyncio.to_thread(query_status, client, ns, "planner")
            assert status.counters["rejected.goal_unreachable"] == 1  # refused once, not per tick
            assert service.counters.get("errors") == errors_before
            assert "goal refused" in status.last_error and "1000.0" in status.last_error
            assert np.array_equal(service.planner.goal, [2.0, 0.0]) and status.extra["path"] == 1.0
            kept = refs[n0:]
            assert kept and not any(r.hold for r in kept)
            assert np.allclose(kept[-1].segments[-1].control_points[-1], [2.0, 0.0], atol=1e-6)

    asyncio.run(asyncio.wait_for(scenario(), 120))


def _wall(x0: float, y0: float, x1: float, y1: float) -> m.Polytope:
    verts = [[x0, y0], [x1, y0], [x1, y1], [x0, y1]]
    A, b = pg.polygon_halfspaces(np.array(verts))
    return m.Polytope(A=A.tolist(), b=b.tolist(), vertices=verts)


def test_with_no_path_and_an_obstacle_coming_the_robot_steps_out_of_its_way(zenoh_router, tmp_path):
    """The goal walled in (no path) and a box sliding at the resting robot: the planner publishes the step
    out of its way (not a hold where it stands) and keeps it; a real-time run crashed its tick here."""
    async def scenario() -> None:
        async with _running_planner(zenoh_router, NS + "evade", PARAMS, tmp_path) as (service, client, refs):
            await asyncio.sleep(0.3)
            room = [_wall(1.4, -0.7, 1.5, 0.7), _wall(2.5, -0.7, 2.6, 0.7), _wall(1.4, -0.8, 2.6, -0.7), _wall(1.4, 0.7, 2.6, 0.8)]
            mover = _box(0.0, 0.45, 0.1)
            mover.velocity = (0.0, -0.3)
            world = m.PolytopeSet(mode="obstacles", polytopes=[*room, mover], source="ground_truth", stamp_ns=time.monotonic_ns())
            client.put(TOPICS["polytopes"].key(NS + "evade"), m.encode(world))
            client.put(TOPICS["goal"].key(NS + "evade"), m.encode(m.Goal(position=[2.0, 0.0], tolerance=0.1)))
            await wait_for(lambda: service.counters.get("evasions") >= 1 or service.counters.get("errors") > 0, timeout_s=30.0)
            assert service.counters.get("errors") == 0, service.last_error
            await wait_for(lambda: any(not r.hold for r in refs))
            step = next(r for r in refs if not r.hold)
            end = np.array(step.segments[-1].control_points[-1])
            assert np.linalg.norm(end) > 0.1 and end[1] < 0.45 - 0.1 - ROBOT_RADIUS  # away from where the box comes
            await asyncio.sleep(0.5)
            assert service.counters.get("errors") == 0, service.last_error
            assert np.allclose(refs[-1].segments[-1].control_points[-1], end)  # kept, not replaced by a hold

    asyncio.run(asyncio.wait_for(scenario(), 90))


def test_stale_state_is_not_planned_from(zenoh_router, tmp_path):
    async def scenario() -> None:
        service = PlannerService(ns=NS + "2", endpoint=zenoh_router, params={"planner": PARAMS},
                                 robot_radius=ROBOT_RADIUS, cache_dir=tmp_path)
        task = asyncio.create_task(service.run())
        client = open_session(zenoh_router, "peer")
        refs: list[bytes] = []
        sub = client.declare_subscriber(TOPICS["reference"].key(NS + "2"), lambda s: refs.append(s.payload.to_bytes()))
        try:
            await wait_for(lambda: service.state == "running")
            await asyncio.sleep(0.3)
            old = _state(0.0, 0.0)
            old.stamp_ns -= int(2e9)
            client.put(TOPICS["state"].key(NS + "2"), m.encode(old))
            client.put(TOPICS["goal"].key(NS + "2"), m.encode(m.Goal(position=[2.0, 0.0])))
            await wait_for(lambda: service.counters.get("stale_state") > 5)
            assert refs == []
        finally:
            sub.undeclare()
            service.stopping.set()
            await asyncio.wait_for(task, 10.0)
            client.close()

    asyncio.run(asyncio.wait_for(scenario(), 60))


def test_graph_cache_round_trip_and_corrupt_file(tmp_path):
    from onboard.high_level.planning import bezier_graph as bg

    spec = bg.spec_from_params(PARAMS, (0.0, 0.0, 3.0, 3.0), nodes=300)
    g1, cached1 = load_or_build_graph(spec, tmp_path)
    g2, cached2 = load_or_build_graph(spec, tmp_path)
    assert not cached1 and cached2 and np.array_equal(g1.control_points, g2.control_points)
    (tmp_path / f"{spec.key()}.npz").write_bytes(b"not a zip")
    g3, cached3 = load_or_build_graph(spec, tmp_path)
    assert not cached3 and np.array_equal(g3.dst, g1.dst)
    assert load_or_build_graph(dataclasses.replace(spec, seed=9), tmp_path)[1] is False
    # A cache that cannot be written (a read-only home under systemd): the graph all the same.
    blocker = tmp_path / "file"
    blocker.write_text("not a directory")
    g4, cached4 = load_or_build_graph(spec, blocker / "graphs")
    assert not cached4 and np.array_equal(g4.dst, g1.dst)


def test_footprint_radius_comes_from_the_mjcf():
    # The housing is a 0.13 m cylinder about the spine (robot_description/models/archer.xml).
    assert robot_footprint_radius() == pytest.approx(0.13)


# real time: loops at their rate, processes and Zenoh over loopback share two loaded cores
pytestmark = pytest.mark.timing_sensitive(reason="real-time loops, processes or Zenoh over loopback on a shared host")


def test_a_graph_is_installed_while_the_obstacles_extent_keeps_changing(zenoh_router, tmp_path):
    """The automatic region follows the obstacles' extent, which an overhead camera's silhouettes move a
    little every frame: the build in flight is kept (not replaced by one for each new extent, none of which
    ever finished), installed when it holds the robot and the goal, and the robot gets a plan."""
    quantum = 0.05  # [m] every message below changes the region
    prm = dataclasses.replace(PARAMS, bounds_quantum=quantum)

    async def scenario() -> None:
        async with _running_planner(zenoh_router, NS, prm, tmp_path) as (service, client, refs):
            client.put(TOPICS["goal"].key(NS), m.encode(m.Goal(position=[2.0, 0.0], tolerance=0.1)))
            far = 1.5
            deadline = time.monotonic() + 60.0
            while service.planner.graph is None and time.monotonic() < deadline:
                far += quantum  # a far obstacle's silhouette, a little further each frame
                world = m.PolytopeSet(mode="obstacles", polytopes=[_box(1.0, -0.8, 0.2), _box(1.0, far, 0.2)],
                                      source="ground_truth")
                client.put(TOPICS["polytopes"].key(NS), m.encode(world))
                await asyncio.sleep(0.05)
            assert service.planner.graph is not None, f"no graph installed while the extent moved {far - 1.5:.1f} m"
            assert service.counters.get("graph_builds") + service.counters.get("graph_cache_hits") >= 1
            await wait_for(lambda: any(not r.hold for r in refs))  # and the robot has a plan

    asyncio.run(asyncio.wait_for(scenario(), 150))
