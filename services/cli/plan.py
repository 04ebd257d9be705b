"""``archer plan --input SCENE.json``: offline planning; ``archer goal X Y``: send the robot a goal.

SCENE (one JSON object)::

    {"bounds": [[xmin, ymin], [xmax, ymax]],          # planning region [m]
     "obstacles": [[[x, y], ...], ...],                 # convex polygons [m]
     "start": [x, y], "goal": [x, y],                   # [m]
     "start_velocity": [vx, vy],                        # optional [m/s], default at rest
     "limits": {"v_max": .., "a_max": ..},              # optional [m/s] speed (octagon), [m/s^2] per axis
     "tube": .., "robot_radius": ..,                    # optional [m]; radius default from the MJCF
     "nodes": .., "seed": ..,                           # optional graph size and sampling seed
     "densify_budget_s": ..}                            # optional [s] densification after a failed search

Output (``--json``: one JSON object): ``found``, ``segments`` (``{"t0", "duration",
"control_points"}``: consecutive Bezier segments of the CoM position, times in seconds
from the start), ``clearance`` (robot radius plus tube: what the plan keeps from every
obstacle), ``limits`` (``v_max``, ``a_max``, ``segment_s``), ``plan_ms`` (cut and
search, densification included), ``graph_ms`` and ``graph_cached`` (build, or load from the graph cache),
``nodes`` (the scene's random nodes plus ``lattice_nodes``, the rest lattice, plus any nodes densification added), ``edges``, ``edges_free``, ``cost`` (path-length bound [m]), ``duration``
[s]; ``path`` (the same as ``found``) and ``densified``: when the first search found no
path, the graph was densified where it failed (``onboard.high_level.planning.densify``, at most
``densify_budget_s`` of the planner parameters, or ``"densify_budget_s"`` in the scene):
``{"rounds", "nodes_added", "edges_added", "spent_ms", "finest_grid"}`` (null when the
first search found a path), and ``no_path_reason``: null with a path, else ``"budget
spent"``, ``"node limit reached"``, ``"goal unreachable in the graph at the finest
resolution"`` or ``"densification off"`` (a budget of 0). Exit code 0 with a path, 1 without, 2 for a bad scene (non-convex or degenerate
polygon, start or goal inside an obstacle or outside the bounds, NaN, unknown key),
with the reason on stderr.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from onboard.high_level.tracking import collision as col

from onboard.geometry import polygons as pg
from onboard.high_level.planning import graph_planner as gp
from onboard.contracts import messages as msgs
from onboard.contracts.params import PlannerParams
from onboard.contracts.topics import TOPICS, namespace

SCENE_KEYS = {"bounds", "obstacles", "start", "goal", "start_velocity", "limits", "tube", "robot_radius", "nodes", "seed",
              "densify_budget_s"}
REQUIRED_KEYS = ("bounds", "obstacles", "start", "goal")
LIMIT_KEYS = {"v_max", "a_max"}
MAX_NODES = 200_000  # a bigger graph does not fit the memory of the onboard computer
GOAL_TOLERANCE = 0.1  # [m]
GOAL_WAIT_S = 2.0  # how long ``archer goal`` waits for a subscriber


class SceneError(ValueError):
    """A scene that cannot be planned in; the message says why."""


@dataclasses.dataclass(frozen=True)
class Scene:
    bounds: tuple[float, float, float, float]
    obstacles: list[np.ndarray]
    start: np.ndarray
    goal: np.ndarray
    start_velocity: np.ndarray
    params: PlannerParams
    robot_radius: float | None
    nodes: int | None


def _reject_constant(name: str) -> float:
    raise SceneError(f"scene has a non-finite number ({name})")


def _vec2(value: Any, what: str) -> np.ndarray:
    try:
        arr = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        raise SceneError(f"{what} must be [x, y], got {value!r}") from None
    if arr.shape != (2,):
        raise SceneError(f"{what} must be [x, y], got {value!r}")
    if not np.all(np.isfinite(arr)):
        raise SceneError(f"{what} is not finite")
    return arr


def _number(value: Any, what: str, positive: bool = False) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise SceneError(f"{what} must be a finite number, got {value!r}")
    if value < 0 or (positive and value == 0):
        raise SceneError(f"{what} must be {'positive' if positive else '>= 0'}, got {value!r}")
    return float(value)


def parse_scene(text: str, base: PlannerParams | None = None) -> Scene:
    """Parse and check a scene; :class:`SceneError` says what is wrong."""
    try:
        raw = json.loads(text, parse_constant=_reject_constant)
    except json.JSONDecodeError as exc:
        raise SceneError(f"scene is not valid JSON: {exc}") from None
    if not isinstance(raw, dict):
        raise SceneError("scene must be a JSON object")
    unknown = sorted(set(raw) - SCENE_KEYS)
    if unknown:
        raise SceneError(f"unknown scene keys: {', '.join(unknown)}")
    missing = [k for k in REQUIRED_KEYS if k not in raw]
    if missing:
        raise SceneError(f"scene lacks: {', '.join(missing)}")
    try:
        b = np.asarray(raw["bounds"], dtype=float)
    except (TypeError, ValueError):
        raise SceneError("bounds must be [[xmin, ymin], [xmax, ymax]]") from None
    if b.shape != (2, 2) or not np.all(np.isfinite(b)) or not np.all(b[1] > b[0]):
        raise SceneError("bounds must be [[xmin, ymin], [xmax, ymax]] with finite xmin < xmax, ymin < ymax")
    bounds = (float(b[0, 0]), float(b[0, 1]), float(b[1, 0]), float(b[1, 1]))
    if not isinstance(raw["obstacles"], list):
        raise SceneError("obstacles must be a list of polygons")
    obstacles = []
    for k, poly in enumerate(raw["obstacles"]):
        try:
            obstacles.append(pg.validate_polygon(poly))
        except pg.PolygonError as exc:
            raise SceneError(f"obstacle {k}: {exc}") from None
    start = _vec2(raw["start"], "start")
    goal = _vec2(raw["goal"], "goal")
    velocity = _vec2(raw.get("start_velocity", [0.0, 0.0]), "start_velocity")
    for name, p in (("start", start), ("goal", goal)):
        if not (bounds[0] <= p[0] <= bounds[2] and bounds[1] <= p[1] <= bounds[3]):
            raise SceneError(f"{name} {p.tolist()} is outside the bounds")
    if obstacles:
        packed = pg.pack_polygons(obstacles)
        for name, p in (("start", start), ("goal", goal)):
            if col.samples_clearance(p[None, None, :], packed, reach=1.0)[0] <= 0.0:
                k = next(k for k, poly in enumerate(obstacles)
                         if col.samples_clearance(p[None, None, :], pg.pack_polygons([poly]), reach=1.0)[0] <= 0.0)
                raise SceneError(f"{name} {p.tolist()} is inside obstacle {k}")
    params = base or PlannerParams()
    changes: dict[str, Any] = {}
    limits = raw.get("limits", {})
    if not isinstance(limits, dict) or set(limits) - LIMIT_KEYS:
        raise SceneError(f"limits must be an object with keys among {sorted(LIMIT_KEYS)}")
    for key in LIMIT_KEYS & set(limits):
        changes[key] = _number(limits[key], f"limits.{key}", positive=True)
    if "tube" in raw:
        changes["tube"] = _number(raw["tube"], "tube")
    if "densify_budget_s" in raw:
        changes["densify_budget_s"] = _number(raw["densify_budget_s"], "densify_budget_s")
    if "seed" in raw:
        if isinstance(raw["seed"], bool) or not isinstance(raw["seed"], int):
            raise SceneError("seed must be an integer")
        changes["seed"] = raw["seed"]
    nodes = None
    if "nodes" in raw:
        if isinstance(raw["nodes"], bool) or not isinstance(raw["nodes"], int) or not 2 <= raw["nodes"] <= MAX_NODES:
            raise SceneError(f"nodes must be an integer in [2, {MAX_NODES}]")
        nodes = raw["nodes"]
    radius = _number(raw["robot_radius"], "robot_radius") if "robot_radius" in raw else None
    return Scene(bounds, obstacles, start, goal, velocity, dataclasses.replace(params, **changes), radius, nodes)


def plan_scene(scene: Scene, cache_dir: Path | None) -> dict[str, Any]:
    """Plan in ``scene``; the output object of ``archer plan --json``."""
    from services.planner import load_or_build_graph, robot_footprint_radius

    radius = scene.robot_radius if scene.robot_radius is not None else (scene.params.robot_radius or robot_footprint_radius(scene.params.robot))
    planner = gp.GraphPlanner(scene.params, radius, bounds=scene.bounds, nodes=scene.nodes)
    planner.set_obstacles(scene.obstacles)
    planner.set_goal(scene.goal, GOAL_TOLERANCE)
    spec = planner.graph_spec_for(scene.start)
    t0 = time.perf_counter()
    graph, cached = load_or_build_graph(spec, cache_dir)
    graph_ms = (time.perf_counter() - t0) * 1e3
    planner.set_graph(graph)
    t0 = time.perf_counter()
    ref = planner.plan(scene.start, scene.start_velocity, 0, clock=time.perf_counter)
    plan_ms = (time.perf_counter() - t0) * 1e3
    path = planner.path
    report = planner.last_densify
    if ref is not None:
        reason = None
    elif report is None:
        reason = "densification off"
    else:
        reason = report.reason
    return {
        "found": ref is not None,
        "path": ref is not None,
        "densified": None if report is None else {
            "rounds": report.rounds, "nodes_added": report.nodes_added, "edges_added": report.edges_added,
            "spent_ms": round(report.spent_s * 1e3, 3), "finest_grid": report.finest_grid},
        "no_path_reason": reason,
        "segments": [{"t0": s.t0, "duration": s.duration, "control_points": s.control_points} for s in (ref.segments if ref else [])],
        "clearance": planner.margin,
        "limits": {"v_max": scene.params.v_max, "a_max": scene.params.a_max, "segment_s": scene.params.segment_s},
        "plan_ms": round(plan_ms, 3),
        "graph_ms": round(graph_ms, 3),
        "graph_cached": cached,
        "nodes": planner.graph.n_nodes if planner.graph is not None else graph.n_nodes,
        "lattice_nodes": graph.spec.lattice_size(),
        "edges": planner.graph.n_edges if planner.graph is not None else graph.n_edges,
        "edges_free": planner.stats.edges_free,
        "cost": path.cost if path else None,
        "duration": path.duration if path else None,
    }


def add_plan_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--input", required=True, help="scene JSON file ('-' for stdin)")
    parser.add_argument("--json", action="store_true", help="print one JSON object")
    parser.add_argument("--cache-dir", help="graph cache directory (default $ARCHER_CACHE_DIR/graphs or ~/.cache/archer/graphs)")
    parser.add_argument("--no-cache", action="store_true", help="build the graph, do not read or write the cache")


def run_plan(args: argparse.Namespace) -> int:
    from services.planner import graph_cache_dir

    try:
        text = sys.stdin.read() if args.input == "-" else Path(args.input).read_text()
    except OSError as exc:
        print(f"archer plan: cannot read {args.input}: {exc.strerror}", file=sys.stderr)
        return 2
    try:
        scene = parse_scene(text)
    except SceneError as exc:
        print(f"archer plan: bad scene: {exc}", file=sys.stderr)
        return 2
    cache = None if args.no_cache else (Path(args.cache_dir) if args.cache_dir else graph_cache_dir())
    out = plan_scene(scene, cache)
    if args.json:
        print(json.dumps(out))
    else:
        if out["found"]:
            print(f"path: {len(out['segments'])} segments, {out['duration']:.1f} s, length <= {out['cost']:.2f} m")
        else:
            print(f"no path: {out['no_path_reason']}")
        if out["densified"] is not None:
            d = out["densified"]
            print(f"densified: {d['rounds']} rounds, {d['nodes_added']} nodes, {d['edges_added']} edges "
                  f"in {d['spent_ms']:.0f} ms (finest lattice {d['finest_grid']:.3f} m)")
        print(f"clearance {out['clearance']:.3f} m, graph {out['nodes']} nodes / {out['edges']} edges "
              f"({out['edges_free']} free), plan {out['plan_ms']:.1f} ms, graph {out['graph_ms']:.0f} ms"
              f"{' (cached)' if out['graph_cached'] else ''}")
    return 0 if out["found"] else 1


# --- archer goal --------------------------------------------------------------------------


def add_goal_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("x", type=float, help="[m] world")
    parser.add_argument("y", type=float, help="[m] world")
    parser.add_argument("--tolerance", type=float, default=GOAL_TOLERANCE, help="[m]")
    parser.add_argument("--endpoint", help="Zenoh endpoint (default tcp/127.0.0.1:7447)")
    parser.add_argument("--namespace", help="key namespace (default archer/robot0)")
    parser.add_argument("--wait", type=float, default=GOAL_WAIT_S, help="[s] wait this long for a subscriber (the planner)")


def run_goal(args: argparse.Namespace) -> int:
    import zenoh

    from services.runtime.zenoh_session import default_endpoint, open_tool_session

    if not (math.isfinite(args.x) and math.isfinite(args.y)) or not (math.isfinite(args.tolerance) and args.tolerance >= 0):
        print("archer goal: X, Y and the tolerance must be finite (tolerance >= 0)", file=sys.stderr)
        return 2
    topic = TOPICS["goal"]
    ns = args.namespace or namespace()
    session = open_tool_session(args.endpoint, deadline=time.monotonic() + args.wait)
    if session is None:
        print(f"archer goal: no stack served {args.endpoint or default_endpoint()} within {args.wait} s", file=sys.stderr)
        return 1
    try:
        pub = session.declare_publisher(topic.key(ns), encoding=zenoh.Encoding("application/json"),
                                        reliability=zenoh.Reliability.RELIABLE,
                                        congestion_control=zenoh.CongestionControl.BLOCK)
        deadline = time.monotonic() + args.wait
        while not pub.matching_status.matching and time.monotonic() < deadline:
            time.sleep(0.02)
        matched = pub.matching_status.matching
        goal = msgs.Goal(stamp_ns=time.monotonic_ns(), seq=1, position=[args.x, args.y], tolerance=args.tolerance)
        pub.put(msgs.encode(goal))
        time.sleep(0.1)  # let the reliable sample leave before the session closes
        pub.undeclare()
    finally:
        session.close()
    if not matched:
        print(f"archer goal: sent to {topic.key(ns)}, but nothing subscribes (is the planner running?)", file=sys.stderr)
        return 1
    print(f"goal ({args.x}, {args.y}) sent to {topic.key(ns)}")
    return 0
