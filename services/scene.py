"""The stack's messages as a Foxglove scene: well-known schemas (``foxglove.FrameTransform``,
``SceneUpdate``, ``Grid``, ``RawImage``) made from ``state``, ``reference``, ``waypoints``,
``polytopes``, ``grid`` and ``depth``.

One maker for the live view (:mod:`services.view`) and for recordings (the flight recorder,
``archer sim --record``), so a recording opened in Foxglove shows what the live view shows.
Channels: ``/tf`` (world -> body, world -> depth_camera), ``<ns>/view/robot`` (the robot from
its MJCF geoms, the foot at its compression), ``<ns>/view/plan`` (reference curve, waypoints,
their convex sets), ``<ns>/view/world`` (obstacles as prisms, free cells as slabs),
``<ns>/view/grid``, ``<ns>/view/depth``.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator
from typing import Any

import foxglove.messages as fm
import numpy as np

from onboard.contracts import messages as m
from onboard.contracts.binary_messages import DepthImage, OccupancyGrid
from onboard.contracts.reference import sample_reference
from onboard.contracts.params import ViewParams
from onboard.contracts.topics import TOPICS
from robot_description.params import BodyGeometry, BodyShape, body_shapes, robot_params

WORLD_FRAME = "world"
BODY_FRAME = "body"
CAMERA_FRAME = "depth_camera"
TF_CHANNEL = "/tf"  # Foxglove's customary transform topic
PLAN_Z_M = 0.005  # plan lines just above the floor, so that the floor does not hide them
FREE_CELL_HEIGHT_M = 0.01  # free convex cells drawn as slabs this thin
WAYPOINT_DIAMETER_M = 0.06
LINE_THICKNESS_PX = 3.0
OBSTACLE_RGBA = (0.85, 0.3, 0.25, 0.8)
FREE_RGBA = (0.3, 0.8, 0.4, 0.25)
REFERENCE_RGBA = (0.2, 0.5, 1.0, 1.0)
WAYPOINT_RGBA = (1.0, 0.85, 0.2, 1.0)
SET_RGBA = (1.0, 0.85, 0.2, 0.6)


def scene_channel(ns: str, what: str) -> str:
    """Name of a scene channel on the Foxglove server (not a Zenoh key: nothing publishes it there)."""
    return f"{ns}/view/{what}"


def _color(rgba: tuple[float, ...]) -> fm.Color:
    return fm.Color(r=rgba[0], g=rgba[1], b=rgba[2], a=rgba[3])


def _pose(pos: tuple[float, ...] | list[float], quat_wxyz: tuple[float, ...] | list[float] = (1.0, 0.0, 0.0, 0.0)) -> fm.Pose:
    w, x, y, z = quat_wxyz
    return fm.Pose(position=fm.Vector3(x=pos[0], y=pos[1], z=pos[2]), orientation=fm.Quaternion(x=x, y=y, z=z, w=w))


def timestamp(epoch_ns: int) -> fm.Timestamp:
    return fm.Timestamp(epoch_ns // 1_000_000_000, epoch_ns % 1_000_000_000)


def _rotate(q: list[float] | tuple[float, ...], v: tuple[float, float, float]) -> tuple[float, float, float]:
    """``v`` rotated by the unit quaternion ``q`` [w, x, y, z] (scalar arithmetic: cheap per tick)."""
    w, x, y, z = q
    vx, vy, vz = v
    # t = 2 q_vec x v; v' = v + w t + q_vec x t
    tx, ty, tz = 2.0 * (y * vz - z * vy), 2.0 * (z * vx - x * vz), 2.0 * (x * vy - y * vx)
    return (vx + w * tx + (y * tz - z * ty), vy + w * ty + (z * tx - x * tz), vz + w * tz + (x * ty - y * tx))


class RobotDrawing:
    """The robot's transform and body from a state estimate, for one robot variant."""

    def __init__(self, variant: str) -> None:
        robot = robot_params(variant)
        self.geometry: BodyGeometry = body_shapes(variant)
        self.com_offset = robot.com_offset_body
        self.foot_share = robot.foot_mass / robot.total_mass  # the CoM rises this much per metre of compression

    def body_origin(self, state: m.StateEstimate) -> tuple[float, float, float]:
        """The torso frame's origin in the world [m]: the estimate's CoM less the CoM's offset."""
        a, c = self.geometry.foot_axis, self.foot_share * state.foot_pos
        offset = (self.com_offset[0] + c * a[0], self.com_offset[1] + c * a[1], self.com_offset[2] + c * a[2])
        r = _rotate(state.quat, offset)
        p = state.position
        return (p[0] - r[0], p[1] - r[1], p[2] - r[2])

    def transform(self, state: m.StateEstimate, epoch_ns: int) -> fm.FrameTransform:
        x, y, z = self.body_origin(state)
        w, qx, qy, qz = state.quat  # ours [w, x, y, z]; Foxglove's fields by name
        return fm.FrameTransform(
            timestamp=timestamp(epoch_ns), parent_frame_id=WORLD_FRAME, child_frame_id=BODY_FRAME,
            translation=fm.Vector3(x=x, y=y, z=z), rotation=fm.Quaternion(x=qx, y=qy, z=qz, w=w))

    def scene(self, foot_pos: float, epoch_ns: int) -> fm.SceneUpdate:
        """The body in its own frame (locked to it), the foot's geoms moved up by ``foot_pos`` [m]."""
        cubes: list[fm.CubePrimitive] = []
        spheres: list[fm.SpherePrimitive] = []
        cylinders: list[fm.CylinderPrimitive] = []
        a = self.geometry.foot_axis
        for shape in self.geometry.shapes:
            pos = shape.pos
            if shape.on_foot:
                pos = (pos[0] + foot_pos * a[0], pos[1] + foot_pos * a[1], pos[2] + foot_pos * a[2])
            _add_shape(shape, pos, cubes, spheres, cylinders)
        entity = fm.SceneEntity(timestamp=timestamp(epoch_ns), frame_id=BODY_FRAME, id="robot", frame_locked=True,
                                cubes=cubes, spheres=spheres, cylinders=cylinders)
        return fm.SceneUpdate(entities=[entity])


def _add_shape(shape: BodyShape, pos: tuple[float, float, float], cubes: list, spheres: list, cylinders: list) -> None:
    """One MJCF geom as Foxglove primitives (sizes are full extents there, half-sizes in MJCF)."""
    color = _color(shape.rgba)
    if shape.kind == "sphere":
        d = 2.0 * shape.size[0]
        spheres.append(fm.SpherePrimitive(pose=_pose(pos), size=fm.Vector3(x=d, y=d, z=d), color=color))
    elif shape.kind == "box":
        sx, sy, sz = (2.0 * s for s in shape.size[:3])
        cubes.append(fm.CubePrimitive(pose=_pose(pos, shape.quat), size=fm.Vector3(x=sx, y=sy, z=sz), color=color))
    elif shape.kind in ("cylinder", "capsule"):
        radius, half = shape.size[0], shape.size[1]
        cylinders.append(fm.CylinderPrimitive(pose=_pose(pos, shape.quat), size=fm.Vector3(x=2 * radius, y=2 * radius, z=2 * half),
                                              bottom_scale=1.0, top_scale=1.0, color=color))
        if shape.kind == "capsule":  # a capsule is its cylinder with a sphere at each end
            for sign in (-1.0, 1.0):
                end = _rotate(shape.quat, (0.0, 0.0, sign * half))
                d = 2.0 * radius
                spheres.append(fm.SpherePrimitive(pose=_pose((pos[0] + end[0], pos[1] + end[1], pos[2] + end[2])),
                                                  size=fm.Vector3(x=d, y=d, z=d), color=color))
    else:
        raise ValueError(f"cannot draw a geom of type {shape.kind!r}")


def _ordered(vertices: list[list[float]]) -> list[tuple[float, float]]:
    """A convex polygon's vertices counter-clockwise (messages do not promise an order)."""
    cx = sum(v[0] for v in vertices) / len(vertices)
    cy = sum(v[1] for v in vertices) / len(vertices)
    return sorted(((v[0], v[1]) for v in vertices), key=lambda v: math.atan2(v[1] - cy, v[0] - cx))


def prism(vertices: list[list[float]], z0: float, z1: float, rgba: tuple[float, ...]) -> fm.TriangleListPrimitive:
    """A convex polygon extruded from ``z0`` to ``z1`` [m]: top, bottom and side walls as triangles."""
    poly = _ordered(vertices)
    n = len(poly)
    if n < 3:
        raise ValueError(f"a polygon needs at least 3 vertices, got {n}")
    points: list[fm.Point3] = []

    def tri(a: tuple[float, float, float], b: tuple[float, float, float], c: tuple[float, float, float]) -> None:
        points.extend(fm.Point3(x=p[0], y=p[1], z=p[2]) for p in (a, b, c))

    for i in range(1, n - 1):  # fans: the polygon is convex
        tri((*poly[0], z1), (*poly[i], z1), (*poly[i + 1], z1))
        tri((*poly[0], z0), (*poly[i + 1], z0), (*poly[i], z0))
    for i in range(n):
        a, b = poly[i], poly[(i + 1) % n]
        tri((*a, z0), (*b, z0), (*b, z1))
        tri((*a, z0), (*b, z1), (*a, z1))
    return fm.TriangleListPrimitive(points=points, color=_color(rgba))


def world_scene(msg: m.PolytopeSet, obstacle_height: float, epoch_ns: int) -> fm.SceneUpdate:
    """Obstacles as prisms ``obstacle_height`` tall, free cells as thin slabs (one entity per set)."""
    free = msg.mode == "free"
    top, rgba = (FREE_CELL_HEIGHT_M, FREE_RGBA) if free else (obstacle_height, OBSTACLE_RGBA)
    triangles = [prism(p.vertices, 0.0, top, rgba) for p in msg.polytopes if len(p.vertices) >= 3]
    entity = fm.SceneEntity(timestamp=timestamp(epoch_ns), frame_id=WORLD_FRAME, id=f"polytopes/{msg.mode}",
                            triangles=triangles)
    # the other mode's entity goes: perception publishes one mode at a time
    gone = fm.SceneEntityDeletion(timestamp=timestamp(epoch_ns), type=fm.SceneEntityDeletionType.MatchingId,
                                  id=f"polytopes/{'obstacles' if free else 'free'}")
    return fm.SceneUpdate(deletions=[gone], entities=[entity])


def reference_points(ref: m.ComReference, samples: int) -> list[tuple[float, float]]:
    """``samples`` points of the reference CoM path, evenly in time over its segments."""
    if not ref.segments:
        return []
    t0 = ref.segments[0].t0
    t1 = ref.segments[-1].t0 + ref.segments[-1].duration
    if ref.hold or t1 <= t0:
        x, y, _, _ = sample_reference(ref, t0)
        return [(x, y)]
    return [sample_reference(ref, t0 + (t1 - t0) * i / (samples - 1))[:2] for i in range(samples)]


def _line(points: list[tuple[float, float]], rgba: tuple[float, ...], kind: fm.LinePrimitiveLineType) -> fm.LinePrimitive:
    return fm.LinePrimitive(type=kind, thickness=LINE_THICKNESS_PX, scale_invariant=True,
                            points=[fm.Point3(x=x, y=y, z=PLAN_Z_M) for x, y in points], color=_color(rgba))


def reference_scene(ref: m.ComReference, samples: int, epoch_ns: int) -> fm.SceneUpdate:
    pts = reference_points(ref, samples)
    lines = [_line(pts, REFERENCE_RGBA, fm.LinePrimitiveLineType.LineStrip)] if len(pts) > 1 else []
    spheres = [fm.SpherePrimitive(pose=_pose((pts[0][0], pts[0][1], PLAN_Z_M)), color=_color(REFERENCE_RGBA),
                                  size=fm.Vector3(x=WAYPOINT_DIAMETER_M, y=WAYPOINT_DIAMETER_M, z=WAYPOINT_DIAMETER_M))] if len(pts) == 1 else []
    entity = fm.SceneEntity(timestamp=timestamp(epoch_ns), frame_id=WORLD_FRAME, id="reference", lines=lines, spheres=spheres)
    return fm.SceneUpdate(entities=[entity])


def waypoints_scene(msg: m.Waypoints, epoch_ns: int) -> fm.SceneUpdate:
    d = WAYPOINT_DIAMETER_M
    pts = [(p[0], p[1]) for p in msg.points]
    lines = [_line(pts, WAYPOINT_RGBA, fm.LinePrimitiveLineType.LineStrip)] if len(pts) > 1 else []
    lines += [_line(_ordered(s.vertices), SET_RGBA, fm.LinePrimitiveLineType.LineLoop) for s in msg.sets if len(s.vertices) >= 3]
    spheres = [fm.SpherePrimitive(pose=_pose((x, y, PLAN_Z_M)), size=fm.Vector3(x=d, y=d, z=d), color=_color(WAYPOINT_RGBA))
               for x, y in pts]
    entity = fm.SceneEntity(timestamp=timestamp(epoch_ns), frame_id=WORLD_FRAME, id="waypoints", lines=lines, spheres=spheres)
    return fm.SceneUpdate(entities=[entity])


def grid_message(grid: OccupancyGrid, epoch_ns: int) -> fm.Grid:
    """The occupancy grid as a Foxglove grid: one uint8 field, rows along +y from the origin, as ours."""
    rows, cols = grid.cells.shape
    return fm.Grid(timestamp=timestamp(epoch_ns), frame_id=WORLD_FRAME, pose=_pose((grid.origin[0], grid.origin[1], 0.0)),
                   column_count=cols, cell_size=fm.Vector2(x=grid.resolution, y=grid.resolution), row_stride=cols, cell_stride=1,
                   fields=[fm.PackedElementField(name="occupancy", offset=0, type=fm.PackedElementFieldNumericType.Uint8)],
                   data=np.ascontiguousarray(grid.cells, dtype=np.uint8).tobytes())


def depth_messages(img: DepthImage, epoch_ns: int) -> tuple[fm.RawImage, fm.FrameTransform]:
    """The depth image (32FC1, metres) and the camera's pose (optical frame: x right, y down, z forward)."""
    h, w = img.depth.shape
    w_, x, y, z = (float(v) for v in img.cam_quat)
    image = fm.RawImage(timestamp=timestamp(epoch_ns), frame_id=CAMERA_FRAME, width=w, height=h, encoding="32FC1", step=4 * w,
                        data=np.ascontiguousarray(img.depth, dtype="<f4").tobytes())
    pos = [float(v) for v in img.cam_pos]
    tf = fm.FrameTransform(timestamp=timestamp(epoch_ns), parent_frame_id=WORLD_FRAME, child_frame_id=CAMERA_FRAME,
                           translation=fm.Vector3(x=pos[0], y=pos[1], z=pos[2]), rotation=fm.Quaternion(x=x, y=y, z=z, w=w_))
    return image, tf


SCENE_CHANNELS = ("tf", "robot", "plan", "world", "grid", "depth")  # what scene_channel() names
SCENE_SOURCES = ("state", "reference", "waypoints", "polytopes", "grid", "depth")  # the topics a scene is made from


def channel_name(ns: str, which: str) -> str:
    """The channel of one of :data:`SCENE_CHANNELS`."""
    return TF_CHANNEL if which == "tf" else scene_channel(ns, which)


class SceneMaker:
    """The scene messages of one stack message, for one robot variant and the ``[view]`` drawing settings."""

    def __init__(self, params: ViewParams) -> None:
        self.params = params
        self.drawing = RobotDrawing(params.variant)

    def messages(self, topic: str, msg: Any, epoch: int, wanted: Callable[[str], bool] = lambda which: True) -> Iterator[tuple[str, Any]]:
        """``(scene channel, Foxglove message)`` pairs of ``msg`` (of topic ``topic``, stamped ``epoch``
        [ns since 1970]); only for channels ``wanted`` (nothing is built for the rest)."""
        params = self.params
        if topic == "state":
            if not msg.valid:  # before the first pose, or lost: its position means nothing, so the last valid one stays shown
                return
            if wanted("tf"):
                yield "tf", self.drawing.transform(msg, epoch)
            if wanted("robot"):
                yield "robot", self.drawing.scene(msg.foot_pos, epoch)
        elif topic == "reference" and wanted("plan"):
            yield "plan", reference_scene(msg, params.reference_samples, epoch)
        elif topic == "waypoints" and wanted("plan"):
            yield "plan", waypoints_scene(msg, epoch)
        elif topic == "polytopes" and wanted("world"):
            yield "world", world_scene(msg, params.obstacle_height_m, epoch)
        elif topic == "grid" and wanted("grid"):
            yield "grid", grid_message(msg, epoch)
        elif topic == "depth" and (wanted("depth") or wanted("tf")):
            image, tf = depth_messages(msg, epoch)
            if wanted("depth"):
                yield "depth", image
            if wanted("tf"):
                yield "tf", tf


SceneRecord = tuple[str, tuple[str, str, bytes, str], bytes]  # channel, (schema name, encoding, data, message encoding), message


class SceneRecording:
    """Scene channels for a recording: :class:`SceneMaker`'s messages, protobuf-encoded with their schemas.

    Topics faster than ``view.max_rate_hz`` are thinned to that rate by their own stamps (a
    viewer needs no more; the raw channels beside them keep every message).
    """

    def __init__(self, ns: str, params: ViewParams) -> None:
        self.ns = ns
        self.maker = SceneMaker(params)
        self.max_rate_hz = params.max_rate_hz
        self.period_ns = int(1e9 / params.max_rate_hz)
        self._last_ns: dict[str, int] = {}
        self._schemas: dict[type, tuple[str, str, bytes, str]] = {}

    def due(self, topic: str, rate_hz: float, stamp_ns: int) -> bool:
        """Whether a message of ``topic`` stamped ``stamp_ns`` gets scene records (call before decoding it)."""
        if topic not in SCENE_SOURCES:
            return False
        if rate_hz <= self.max_rate_hz:
            return True
        last = self._last_ns.get(topic)
        if last is not None and 0 <= stamp_ns - last < self.period_ns:
            return False
        self._last_ns[topic] = stamp_ns
        return True

    def records(self, topic: str, msg: Any, epoch: int) -> list[SceneRecord]:
        out = []
        for which, fmsg in self.maker.messages(topic, msg, epoch):
            schema = self._schemas.get(type(fmsg))
            if schema is None:
                s = type(fmsg).get_schema()
                schema = self._schemas[type(fmsg)] = (s.name, s.encoding, bytes(s.data), "protobuf")
            out.append((channel_name(self.ns, which), schema, fmsg.encode()))
        return out


def layout(ns: str) -> str:
    """A Foxglove layout (JSON, built with the SDK's ``foxglove.layouts``) for these channels: the 3D
    scene following the robot, the depth image, and the CoM height and foot compression plotted."""
    import foxglove.layouts as fl

    scene_topics: dict[str, Any] = {channel_name(ns, w): fl.BaseRendererSceneUpdateTopicSettings(visible=True)
                                    for w in ("robot", "plan", "world")}
    scene_topics[channel_name(ns, "grid")] = fl.BaseRendererGridTopicSettings(visible=True)
    state = f'"{TOPICS["state"].key(ns)}"'  # a topic name with slashes is quoted in a message path
    three_d = fl.ThreeDeePanel(title="ARCHER", config=fl.ThreeDeeConfig(
        follow_tf=BODY_FRAME, fixed_frame=WORLD_FRAME, follow_mode="follow-position", topics=scene_topics))
    depth = fl.ImagePanel(title="depth", config=fl.ImageConfig(image_mode=fl.ImageModeConfig(image_topic=channel_name(ns, "depth"))))
    plot = fl.PlotPanel(title="CoM height, foot compression", config=fl.PlotConfig(paths=[
        fl.PlotSeries(value=f"{state}.position[2]", label="CoM z [m]"),
        fl.PlotSeries(value=f"{state}.foot_pos", label="foot compression [m]")]))
    return fl.Layout(content=fl.SplitContainer(direction="row", items=[
        fl.SplitItem(proportion=2, content=three_d),
        fl.SplitItem(proportion=1, content=fl.SplitContainer(direction="column", items=[
            fl.SplitItem(proportion=1, content=depth), fl.SplitItem(proportion=1, content=plot)]))])).to_json()
