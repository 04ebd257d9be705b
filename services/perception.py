"""The ``perception`` service: depth images to convex sets for the planner.

Subscribes: ``depth`` (binary DepthImage, captured at apex; every image is fused), with
``perception.segmenter = "color"`` also ``color`` (the D435's colour aligned to the depth image of
the same stamp: a depth image waits for its colour, at most ``COLOR_WAIT_S`` or until a later
colour image shows that its own is not coming),
``state`` (robot position: the grid follows the robot, its footprint counts as free,
and ``free`` mode decomposes the robot's free region), ``goal`` (kept inside a free
cell in ``free`` mode).
Computes: :class:`onboard.perception.pipeline.Perception` - point cloud, segmentation,
fused occupancy grid - then Algorithm 4 (``free``) or convex obstacles (``obstacles``)
on a snapshot of the grid, off the event loop.
Publishes: ``polytopes`` (PolytopeSet) at ``perception.rate_hz`` (4-20 Hz) once a
view has been fused, and ``grid`` (binary OccupancyGrid) with it, for inspection.
"""

from __future__ import annotations

import asyncio
import math
import time

import numpy as np

from onboard.contracts import messages as m
from onboard.contracts.binary_messages import ColorImage, DepthImage, encode_grid
from onboard.contracts.params import PerceptionParams
from onboard.geometry.quaternion import from_matrix
from onboard.perception.geometry import ConvexPolygon
from onboard.perception.pipeline import MODES, Perception, polytopes_of_grid
from services.runtime.service import Service

COLOR_KEEP = 4  # colour images kept for depth images still to come, and depth images for their colour
COLOR_WAIT_S = 1.0  # [s] a depth image waits this long for its colour at most
RATE_MIN_HZ = 4.0  # the band for the publication rate
RATE_MAX_HZ = 20.0

# warm_up's synthetic view: a small camera 0.5 m up, pitched down 30 degrees, over a floor with a wall ahead
WARM_ROWS, WARM_COLS = 48, 64
WARM_FOCAL_PX = 40.0
WARM_CAMERA_HEIGHT_M = 0.5
WARM_PITCH_RAD = math.radians(30.0)
WARM_WALL_X_M, WARM_WALL_TOP_M = 1.2, 0.4


def warm_view() -> DepthImage:
    """A floor and a wall ahead, ray-cast for a small camera (pixels: x right, y down, z forward)."""
    c, sn = math.cos(WARM_PITCH_RAD), math.sin(WARM_PITCH_RAD)
    right, forward = np.array([0.0, -1.0, 0.0]), np.array([c, 0.0, -sn])
    cam_to_world = np.column_stack([right, np.cross(forward, right), forward])
    u, v = np.meshgrid((np.arange(WARM_COLS) + 0.5 - WARM_COLS / 2) / WARM_FOCAL_PX,
                       (np.arange(WARM_ROWS) + 0.5 - WARM_ROWS / 2) / WARM_FOCAL_PX)
    rays = np.stack([u, v, np.ones_like(u)], axis=-1) @ cam_to_world.T  # optical depth 1
    with np.errstate(divide="ignore"):
        to_floor = np.where(rays[..., 2] < 0, -WARM_CAMERA_HEIGHT_M / rays[..., 2], np.inf)
        to_wall = np.where(rays[..., 0] > 0, WARM_WALL_X_M / rays[..., 0], np.inf)
    wall_z = WARM_CAMERA_HEIGHT_M + to_wall * rays[..., 2]
    depth = np.where((wall_z >= 0) & (wall_z <= WARM_WALL_TOP_M), np.minimum(to_wall, to_floor), to_floor)
    depth = np.where(np.isfinite(depth), depth, 0.0).astype(np.float32)
    return DepthImage(depth, WARM_FOCAL_PX, WARM_FOCAL_PX, WARM_COLS / 2, WARM_ROWS / 2,
                      np.array([0.0, 0.0, WARM_CAMERA_HEIGHT_M]), np.array(from_matrix(cam_to_world.tolist())))


def warm_up(params: PerceptionParams) -> None:
    """Fuse and decompose one synthetic view on a throwaway map: loads numba's kernels and what
    their first call imports. Left to the first real view, that second of CPU held the event loop
    past the watchdog (Nice=10 on two busy cores: over 5 s) and the service was restarted."""
    view = Perception(params)
    img = warm_view()
    color = np.full(img.depth.shape + (3,), 128, dtype=np.uint8) if params.segmenter == "color" else None
    robot = (0.0, 0.0)
    view.integrate(img, robot, color)
    polytopes_of_grid(view.grid(0, 0), params, params.mode, robot if params.mode == "free" else None, (robot,))


def to_message(poly: ConvexPolygon) -> m.Polytope:
    return m.Polytope(A=poly.A.tolist(), b=poly.b.tolist(), vertices=poly.vertices.tolist())


class PerceptionService(Service):
    name = "perception"
    params_sections = ("perception",)
    subscribes = ("depth", "state", "goal", "color")

    async def setup(self) -> None:
        self.view = self._new_view()
        await asyncio.to_thread(warm_up, self.params["perception"])  # before ready: the start timeout bounds it
        self._rebuild = False
        self.state_slot = self.latest_sampled("state")  # 1 kHz, read a few times a second: only that is decoded
        self.goal = self.latest("goal")
        self.polytopes_pub = self.publisher("polytopes")
        self.grid_pub = self.publisher("grid")
        self.last_depth_stamp = -1
        self.grid_seq = 0
        self.compute_ms = 0.0
        self.polygons = 0
        self._parked: dict[int, tuple[DepthImage, float]] = {}  # depth images waiting for their colour, by stamp
        # Fusing a view runs in a worker thread, so that the loop keeps answering (status, the
        # watchdog's pings) while a starved host takes seconds over it: Nice=10 beside the twin
        # and the control loops on two cores missed the 5 s watchdog and was restarted. The lock
        # keeps views fused one at a time, in order, and the map still while it is copied.
        self._map_lock = asyncio.Lock()
        self._colors: dict[int, ColorImage] = {}  # colour images by stamp, not yet paired
        self.subscribe("depth", self.on_depth)
        if self.params["perception"].segmenter == "color":
            self.subscribe("color", self.on_color)

    def _new_view(self) -> Perception:
        p = self.params["perception"]
        if not RATE_MIN_HZ <= p.rate_hz <= RATE_MAX_HZ:
            raise ValueError(f"perception.rate_hz must be within [{RATE_MIN_HZ}, {RATE_MAX_HZ}], got {p.rate_hz}")
        if p.mode not in MODES:
            raise ValueError(f"perception.mode must be one of {MODES}, got {p.mode!r}")
        return Perception(p)

    def on_params_changed(self, section: str) -> None:
        self._rebuild = True  # grid size or thresholds may have changed: start a fresh map

    def status_extra(self) -> dict[str, float]:
        return {"compute_ms": self.compute_ms, "polygons": float(self.polygons), "views": float(self.view.map.views)}

    def _robot_xy(self) -> tuple[float, float] | None:
        got = self.state_slot.get()
        if got is None:
            return None
        state: m.StateEstimate = got[0]
        x, y = state.position[0], state.position[1]
        if not (state.valid and math.isfinite(x) and math.isfinite(y)):
            return None
        return (x, y)

    async def on_color(self, rgb: ColorImage) -> None:
        parked = self._parked.pop(rgb.stamp_ns, None)
        if parked is not None:
            await self._flush_before(rgb.stamp_ns)
            await self._fuse(parked[0], rgb)
            return
        self._colors[rgb.stamp_ns] = rgb
        while len(self._colors) > COLOR_KEEP:
            del self._colors[min(self._colors)]

    async def on_depth(self, img: DepthImage) -> None:
        if self.params["perception"].segmenter != "color":
            await self._fuse(img, None)
            return
        rgb = self._colors.pop(img.stamp_ns, None)
        if rgb is not None:
            await self._flush_before(img.stamp_ns)
            await self._fuse(img, rgb)
            return
        self._parked[img.stamp_ns] = (img, time.monotonic())
        while len(self._parked) > COLOR_KEEP:
            await self._flush_before(min(self._parked) + 1)

    async def _flush_before(self, stamp_ns: int, older_than_s: float = 0.0) -> None:
        """Fuse without colour the parked depth images stamped before ``stamp_ns`` (their colour is
        not coming: the camera sends colour in order) or waiting longer than ``older_than_s``."""
        now = time.monotonic()
        due = [stamp for stamp, (_, since) in self._parked.items()
               if stamp < stamp_ns or (older_than_s > 0.0 and now - since > older_than_s)]
        images = [self._parked.pop(stamp)[0] for stamp in sorted(due)]  # taken before any await
        for img in images:
            self.count("depth_without_color")
            await self._fuse(img, None)

    async def _fuse(self, img: DepthImage, rgb: ColorImage | None) -> None:
        async with self._map_lock:
            if img.stamp_ns <= self.last_depth_stamp:
                self.count("rejected.depth_out_of_order")
                return
            robot = self._robot_xy()
            try:
                await asyncio.to_thread(self.view.integrate, img, robot, rgb.rgb if rgb is not None else None)
            except ValueError as exc:
                self.count("rejected.depth")
                self.fail(f"depth image: {exc}")
                return
            self.last_depth_stamp = img.stamp_ns
        self.count("views")
        if rgb is not None:
            self.count("views_with_color")

    async def main(self) -> None:
        period = 1.0 / self.params["perception"].rate_hz
        next_t = time.monotonic()
        while not self.stopping.is_set():
            if self._rebuild:
                self._rebuild = False
                try:
                    async with self._map_lock:
                        self.view = self._new_view()
                    period = 1.0 / self.params["perception"].rate_hz
                except ValueError as exc:
                    self.fail(str(exc))
            if self._parked:
                await self._flush_before(0, COLOR_WAIT_S)
            if self.view.map.views > 0:
                await self._publish()
            next_t += period
            delay = next_t - time.monotonic()
            if delay < 0:
                self.count("overruns")
                next_t = time.monotonic()
                delay = 0.0
            try:
                await asyncio.wait_for(self.stopping.wait(), delay)
            except asyncio.TimeoutError:
                pass

    async def _publish(self) -> None:
        p = self.params["perception"]
        now = self.clock.now_ns()
        self.grid_seq += 1
        async with self._map_lock:
            grid = self.view.grid(now, self.grid_seq)  # a copy: the next view waits only for this, not the polytopes
        robot = self._robot_xy()
        cover: tuple[tuple[float, float], ...] = ()
        if robot is not None:
            goal = self.goal.get()
            cover = (robot,) if goal is None else (robot, (goal[0].position[0], goal[0].position[1]))
        t0 = time.perf_counter()
        polys, _ = await asyncio.to_thread(polytopes_of_grid, grid, p, p.mode, robot if p.mode == "free" else None, cover)
        self.compute_ms = (time.perf_counter() - t0) * 1e3
        self.polygons = len(polys)
        self.polytopes_pub.put(m.PolytopeSet(stamp_ns=now, mode=p.mode, polytopes=[to_message(q) for q in polys]))
        self.grid_pub.put_bytes(encode_grid(grid))
        self.rate("polytopes").tick()
