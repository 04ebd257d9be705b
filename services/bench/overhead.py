"""``archer bench overhead``: the indoor experiment's loop at the thesis's rates (issue 28): 20 obstacles
sliding, the twin's overhead frames through the camera pipeline (segment, track: the ``camera_overhead``
service's step), the planner's cut and search on the new world, and its MPC refinement.

Per stage, in this process on this machine, p50 / p99 [ms] and the rate that p99 allows against the
thesis's (perception 4 Hz, cut + search 50 Hz, MPC 200 Hz): ``camera_ms`` (frame to obstacles, the
frame's rendering not counted), ``plan_ms`` (obstacles to a new plan: set_obstacles, cut, search, and
densification where the search failed), ``build_ms`` (a graph for a region the obstacles widened:
built apart from the timed plan, as the planner service builds it beside its ticks),
``refine_ms`` (one SQP iteration), ``frame_to_plan_ms`` (camera then plan, the Zenoh hop between the
two services not counted: ``archer bench messaging`` measures it), ``cpu_*`` the same in this process's
CPU time (what a loaded shared machine does not distort).
"""

from __future__ import annotations

import argparse
import time

import mujoco
import numpy as np

from onboard.contracts.params import CameraOverheadParams, PlannerParams
from onboard.high_level.planning import bezier_graph as bg
from onboard.high_level.planning.graph_planner import GraphPlanner
from robot_description import params as rd
from services.camera_overhead import ObstacleCamera
from sim_twin import model as tm
from sim_twin import overhead_camera as oc
from sim_twin import scenarios as sc

THESIS_HZ = {"camera": 4.0, "plan": 50.0, "refine": 200.0}
WARMUP = 2  # frames (with their refinements) before the timed ones


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--obstacles", type=int, default=20)
    parser.add_argument("--frames", type=int, default=40, help="camera frames (at 4 Hz of the scene's time)")
    parser.add_argument("--refines", type=int, default=12, help="refinements between two frames (0: the refinement is not timed)")
    parser.add_argument("--seed", type=int, default=0)


def _spread(ms: list[float]) -> dict:
    return {"p50": round(float(np.percentile(ms, 50)), 2), "p99": round(float(np.percentile(ms, 99)), 2)}


def measure(args: argparse.Namespace) -> dict:
    if args.obstacles < 1 or args.frames < 1 or args.refines < 0:
        raise SystemExit(f"archer bench overhead: needs --obstacles >= 1, --frames >= 1, --refines >= 0 "
                         f"(got {args.obstacles}, {args.frames}, {args.refines})")
    scn = sc.make("sliding", seed=args.seed, obstacles=args.obstacles)
    spec = tm.load_spec()
    scn.build(spec)
    model = spec.compile()
    data = mujoco.MjData(model)
    cam = oc.default_camera()
    renderer = oc.OverheadRenderer(cam, oc.default_markers(), seed=args.seed)
    p = CameraOverheadParams(obstacle_height_m=sc.OBSTACLE_HEIGHT)
    camera = ObstacleCamera(p)
    camera.lens = cam.lens
    camera.markers = oc.default_markers()
    robot = rd.robot_params()
    prm = rd.planner_params_for(PlannerParams(replan_hz=THESIS_HZ["plan"], refine_hz=THESIS_HZ["refine"]), robot)
    planner = GraphPlanner(prm, robot_radius=robot.footprint_radius)
    planner.set_goal(scn.target())
    times: dict[str, list[float]] = {k: [] for k in ("camera", "plan", "refine", "frame_to_plan", "cpu_camera", "cpu_plan", "cpu_refine",
                                                     "build")}
    seen = []
    pos = np.array(scn.start, dtype=float)
    vel = np.zeros(2)
    planner.plan(pos, vel, 0)  # the graph is built once, before the loop (the service caches it)
    for i in range(-WARMUP, args.frames):  # the first frames compile the kernels: not timed
        t = max(i, 0) / THESIS_HZ["camera"]
        stamp = int(t * 1e9)
        scn.before_step(t, model, data)
        frame = renderer.render(scn, tuple(pos))
        w0, c0 = time.perf_counter(), time.process_time()
        msg = camera.step(frame, t, stamp)
        w1, c1 = time.perf_counter(), time.process_time()
        planner.set_obstacles([np.array(q.vertices) for q in msg.polytopes], [q.velocity for q in msg.polytopes])
        build_s = build_cpu_s = 0.0
        spec = planner.graph_spec_for(pos)
        if planner.graph is None or planner.graph.spec != spec:  # the service builds it beside its ticks: not the plan's
            b0, bc0 = time.perf_counter(), time.process_time()
            planner.set_graph(bg.build_graph(spec))
            build_s, build_cpu_s = time.perf_counter() - b0, time.process_time() - bc0
            if i >= 0:
                times["build"].append(build_s * 1e3)
        ref = planner.plan(pos, vel, stamp, build=False)
        w2, c2 = time.perf_counter(), time.process_time()
        if i >= 0:
            seen.append(len(msg.polytopes))
            times["camera"].append((w1 - w0) * 1e3)
            times["plan"].append((w2 - w1 - build_s) * 1e3)
            times["frame_to_plan"].append((w2 - w0 - build_s) * 1e3)
            times["cpu_camera"].append((c1 - c0) * 1e3)
            times["cpu_plan"].append((c2 - c1 - build_cpu_s) * 1e3)
        for k in range(args.refines):
            s = stamp + int(k * 1e9 / THESIS_HZ["refine"])
            w0, c0 = time.perf_counter(), time.process_time()
            planner.refine(pos, vel, s)
            if i >= 0:
                times["refine"].append((time.perf_counter() - w0) * 1e3)
                times["cpu_refine"].append((time.process_time() - c0) * 1e3)
        if ref is not None and not ref.hold:  # the robot moves along its plan, a frame on
            seg = ref.segments[0]
            pts = np.array(seg.control_points)
            pos = pts[-1] if seg.duration <= 0.25 else pos + (pts[-1] - pts[0]) * 0.25 / seg.duration
    out: dict = {"obstacles": args.obstacles, "tracked_median": int(np.median(seen)), "frames": args.frames}
    for key, ms in times.items():
        if ms:  # --refines 0 times no refinement
            out[f"{key}_ms"] = _spread(ms)
    for key, hz in THESIS_HZ.items():
        if times[f"cpu_{key}"]:
            p99 = float(np.percentile(times[f"cpu_{key}"], 99))
            out[f"{key}_rate_p99_hz"] = round(1e3 / p99, 1) if p99 > 0 else None
            out[f"{key}_thesis_hz"] = hz
    out["plans_no_path"] = planner.stats.no_path
    out["graph_builds"] = len(times["build"])
    return out
