"""The live viewer bridge: the stack's topics to a Foxglove WebSocket server (``archer view``).

Subscribes: every topic of the topic table, each through a Zenoh ring buffer drained by
the bridge's own sender thread (no Python callback per sample: a 1 kHz topic costs this
process nothing between two sends, and a service publishing it never waits on us).
Fast topics (nominal rate above ``view.max_rate_hz``) keep only their latest sample;
slow and event topics keep up to ``view.event_queue`` samples; what overflows is dropped.

Computes and publishes, at most ``view.max_rate_hz`` per channel, on a Foxglove
WebSocket server (``foxglove-sdk``) at ``view.host:view.port``:

- ``/tf`` (``foxglove.FrameTransform``): world -> body from ``state`` (the torso frame:
  the estimate's CoM less the CoM's offset in the body, which moves with the foot), and
  world -> depth_camera from ``depth``;
- ``<ns>/view/robot`` (``foxglove.SceneUpdate``): the robot drawn from its MJCF geoms
  (:func:`robot_description.params.body_shapes`), the foot at its compression;
- ``<ns>/view/plan``: the ``reference`` Bezier curve sampled as a line, the ``waypoints``
  and the outlines of their convex sets;
- ``<ns>/view/world``: the ``polytopes`` as extruded polygons (obstacles as prisms,
  free cells as thin slabs); ``<ns>/view/grid`` (``foxglove.Grid``) the occupancy grid;
  ``<ns>/view/depth`` (``foxglove.RawImage``, 32FC1) the depth image;
- every JSON topic on a channel named by its Zenoh key, with its JSON schema (the
  flight recorder's), so any field can be plotted.

Foxglove's timestamps are wall-clock epoch times; the stack's stamps are monotonic, so
each is shifted by the wall - monotonic offset taken when the service starts.
"""

from __future__ import annotations

import asyncio
import math
import threading
import time
from typing import Any

import foxglove
import foxglove.channels as fc
import foxglove.messages as fm
import numpy as np

from onboard import messages as m
from onboard.binary_messages import DepthImage, OccupancyGrid
from onboard.low_level import sample_reference
from onboard.params import ViewParams
from onboard.topics import TOPICS, Topic
from robot_description.params import BodyGeometry, BodyShape, body_shapes, robot_params
from services.recorder import schema_for
from services.runtime.service import EVERY_TOPIC, Service

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
SENDER_JOIN_S = 2.0


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


class FoxgloveBridge:
    """A Foxglove WebSocket server and its channels; :meth:`send` shows one stack message on them.

    Not thread-safe: one thread sends. The ``view`` service feeds it from Zenoh; ``archer sim
    --view`` in lockstep feeds it straight from the runner.
    """

    def __init__(self, ns: str, params: ViewParams) -> None:
        self.params = params
        self.drawing = RobotDrawing(params.variant)
        self._context = foxglove.Context()  # channels of this server only (a test may run two)
        try:
            self.server = foxglove.start_server(name=f"archer {ns}", host=params.host, port=params.port,
                                                context=self._context, message_backlog_size=params.message_backlog)
        except Exception as exc:  # the SDK's own error type; say which address, and why
            raise RuntimeError(f"view: cannot serve on {params.host}:{params.port} ({exc}); set view.port") from exc
        self.port = self.server.port
        ctx = self._context
        self._tf = fc.FrameTransformChannel(TF_CHANNEL, context=ctx)
        self._robot = fc.SceneUpdateChannel(scene_channel(ns, "robot"), context=ctx)
        self._plan = fc.SceneUpdateChannel(scene_channel(ns, "plan"), context=ctx)
        self._world = fc.SceneUpdateChannel(scene_channel(ns, "world"), context=ctx)
        self._grid = fc.GridChannel(scene_channel(ns, "grid"), context=ctx)
        self._depth = fc.RawImageChannel(scene_channel(ns, "depth"), context=ctx)
        self._json: dict[str, foxglove.Channel] = {}
        for topic in TOPICS.values():
            if not topic.binary:
                name, encoding, data, message_encoding = schema_for(topic)
                self._json[topic.name] = foxglove.Channel(
                    topic.key(ns), schema=foxglove.Schema(name=name, encoding=encoding, data=data),
                    message_encoding=message_encoding, context=ctx)

    def send(self, topic: Topic, msg: Any, epoch: int) -> None:
        """Convert and log ``msg`` (stamped ``epoch`` [ns since 1970]) on every channel it feeds that a
        client subscribes to (the rest costs nothing)."""
        params = self.params
        name = topic.name
        if name == "state":
            if self._tf.has_sinks():
                self._tf.log(self.drawing.transform(msg, epoch), log_time=epoch)
            if self._robot.has_sinks():
                self._robot.log(self.drawing.scene(msg.foot_pos, epoch), log_time=epoch)
        elif name == "reference" and self._plan.has_sinks():
            self._plan.log(reference_scene(msg, params.reference_samples, epoch), log_time=epoch)
        elif name == "waypoints" and self._plan.has_sinks():
            self._plan.log(waypoints_scene(msg, epoch), log_time=epoch)
        elif name == "polytopes" and self._world.has_sinks():
            self._world.log(world_scene(msg, params.obstacle_height_m, epoch), log_time=epoch)
        elif name == "grid" and self._grid.has_sinks():
            self._grid.log(grid_message(msg, epoch), log_time=epoch)
        elif name == "depth" and (self._depth.has_sinks() or self._tf.has_sinks()):
            image, tf = depth_messages(msg, epoch)
            if self._depth.has_sinks():
                self._depth.log(image, log_time=epoch)
            if self._tf.has_sinks():
                self._tf.log(tf, log_time=epoch)
        channel = self._json.get(name)
        if channel is not None and channel.has_sinks():
            channel.log(m.encode(msg), log_time=epoch)

    def watched(self) -> bool:
        """A client subscribes to the robot's transform or body."""
        return self._tf.has_sinks() or self._robot.has_sinks()

    def stop(self) -> None:
        self.server.stop()


class ViewService(Service):
    name = "view"
    params_sections = ("view",)
    subscribes = EVERY_TOPIC  # it shows every topic (scene channels from some, JSON from all)

    async def setup(self) -> None:
        params: ViewParams = self.params["view"]
        self._epoch_offset_ns = time.time_ns() - time.monotonic_ns()  # stamps are monotonic, Foxglove's epoch
        self.bridge = FoxgloveBridge(self.ns, params)
        self.port = self.bridge.port
        self._inputs: list[tuple[Topic, Any]] = []
        for topic in TOPICS.values():
            fast = topic.rate_hz > params.max_rate_hz
            # a ring of one keeps the latest of a fast topic; slow and event topics keep what arrived
            self._inputs.append((topic, self.polled(topic.name, 1 if fast else params.event_queue)))
        self._ticks = 0
        self._last_ticks = -1
        self._stop_sender = threading.Event()
        self._sender = threading.Thread(target=self._send_loop, name="view-sender", daemon=True)
        self._sender.start()
        self.log.info("foxglove server", extra={"fields": {"url": f"ws://{params.host}:{self.port}"}})

    def _send_loop(self) -> None:
        """Every 1 / max_rate_hz: drain each input and send what it holds (absolute deadlines)."""
        period = 1.0 / self.params["view"].max_rate_hz
        deadline = time.monotonic()
        batch: list[Any] = []
        try:
            while not self._stop_sender.is_set():
                for topic, inp in self._inputs:
                    batch.clear()
                    taken = inp.drain(batch)
                    if taken >= inp.capacity > 1:
                        self.count(f"dropped.{topic.name}")  # the ring was full: older ones were lost
                    for msg in batch:
                        self._send(topic, msg)
                    if batch:
                        self.count(f"taken.{topic.name}", len(batch))  # taken from Zenoh; sent where subscribed
                self._ticks += 1
                deadline += period
                delay = deadline - time.monotonic()
                if delay < 0:  # fell behind (a big scene): start afresh rather than burst
                    deadline = time.monotonic()
                    self.count("late_ticks")
                self._stop_sender.wait(max(0.0, delay))
        except Exception as exc:  # noqa: BLE001 - recorded; progress() then stops the watchdog pings
            self.fail(f"sender: {exc!r}")
            self.log.exception("view sender failed")

    def _send(self, topic: Topic, msg: Any) -> None:
        stamp = getattr(msg, "stamp_ns", 0)
        self.bridge.send(topic, msg, stamp + self._epoch_offset_ns if stamp > 0 else time.time_ns())

    def status_extra(self) -> dict[str, float]:
        if not hasattr(self, "bridge"):
            return {}
        return {"port": self.port, "ticks": self._ticks}

    def progress(self) -> bool:
        """The sender thread lives and ticked since the last call."""
        ticks = self._ticks
        advanced, self._last_ticks = ticks != self._last_ticks, ticks
        return self._sender.is_alive() and advanced

    async def main(self) -> None:
        while not self.stopping.is_set():
            try:
                await asyncio.wait_for(self.stopping.wait(), 1.0)
            except asyncio.TimeoutError:
                pass
            if not self._sender.is_alive():  # exit with an error: the supervisor restarts us
                raise RuntimeError(f"the view's sender thread died: {self.last_error}")

    async def teardown(self) -> None:
        if hasattr(self, "_sender"):
            self._stop_sender.set()
            self._sender.join(SENDER_JOIN_S)
        if hasattr(self, "bridge"):
            self.bridge.stop()
