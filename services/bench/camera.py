"""``archer bench camera``: the camera chain at a D435 mode, from the frame's sensor timestamp to the
polytopes: librealsense (software device, filters, alignment), the stamp on the stack's clock,
the point cloud, terrain segmentation from colour and depth, the occupancy grid and convex obstacles.

The twin renders the frames first (:class:`sim_twin.camera.RgbdCamera`, the forest or the
sidewalk, views along the way); a feeder thread then pushes them into the software device at the
stream's rate, each stamped with the host's monotonic clock at the push (its capture). The
chain takes every frame it can (``--every``, a bound on the load) or one frame in
``--every`` (one a hop, as the camera service does at the apex); a frame still queued when the
next comes is dropped by librealsense, counted. Latency: polytopes out minus the sensor stamp.
CPU: the process's CPU time over the wall time of the run (both cores count).
"""

from __future__ import annotations

import argparse
import threading
import time

import numpy as np

from drivers.realsense import load
from drivers.realsense.device import D435, StreamConfig
from drivers.realsense.emulator import Intrinsics, SoftwareD435
from drivers.realsense.frames import ClockMap
from onboard.contracts.binary_messages import DepthImage
from onboard.contracts.params import PerceptionParams
from onboard.perception.pipeline import Perception
from onboard.perception.terrain import ColorTerrainSegmenter

NS = 1_000_000_000


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--scenario", default="sidewalk", help="the world the frames are rendered from")
    parser.add_argument("--width", type=int, default=848)
    parser.add_argument("--height", type=int, default=480)
    parser.add_argument("--fps", type=int, default=30)
    parser.add_argument("--decimation", type=int, default=2, help="the SDK's decimation filter (1: off)")
    parser.add_argument("--stride", type=int, default=4, help="perception.pixel_stride on the decimated image")
    parser.add_argument("--every", type=int, default=1, help="process one frame in N (10: one a hop at ~3 hops/s)")
    parser.add_argument("--frames", type=int, default=150, help="frames pushed")
    parser.add_argument("--views", type=int, default=10, help="distinct views rendered (cycled)")
    parser.add_argument("--seed", type=int, default=1)


def _render(args: argparse.Namespace) -> tuple[list, object]:
    from sim_twin.camera import CameraModel
    from sim_twin.terrain_eval import score_seed  # noqa: F401  (the same view sampling)
    import sim_twin.terrain_eval as te

    cam = CameraModel.d435(args.width, args.height, args.fps)
    frames: list = []
    original = te.RgbdCamera.render

    def keep(self, data):  # record what the evaluation's view sampler renders
        f = original(self, data)
        frames.append(f)
        return f

    te.RgbdCamera.render = keep  # type: ignore[method-assign]
    try:
        te.score_seed(args.scenario, args.seed, args.views, {}, cam)
    finally:
        te.RgbdCamera.render = original  # type: ignore[method-assign]
    return frames, cam


def measure(args: argparse.Namespace) -> dict:
    rs = load()
    frames, cam = _render(args)
    cfg = StreamConfig(width=args.width, height=args.height, fps=args.fps, decimation=args.decimation, spatial=True)
    emu = SoftwareD435(rs, cfg, Intrinsics(cam.fx, cam.fy, cam.cx, cam.cy))
    device = D435(rs, cfg, emu)
    params = PerceptionParams(pixel_stride=args.stride, mode="obstacles")
    view = Perception(params, segmenter=ColorTerrainSegmenter(params))
    clock = ClockMap(window=300, min_latency_ns=0)
    # warm up (numba compiles the grid's kernels on first use, as the service does at start)
    emu.push(frames[0].depth, frames[0].rgb, time.monotonic_ns() / 1e6)
    warm = device.process(device.wait(5000))
    xy0 = (float(frames[0].cam_pos[0]), float(frames[0].cam_pos[1]))
    view.integrate(DepthImage(warm.depth, warm.fx, warm.fy, warm.cx, warm.cy, frames[0].cam_pos, frames[0].cam_quat, 1),
                   xy0, warm.color)
    view.polytopes(robot_xy=xy0)
    stop = threading.Event()
    pushed = [0]

    def feed() -> None:
        period = 1.0 / args.fps
        next_t = time.monotonic()
        for k in range(args.frames):
            f = frames[k % len(frames)]
            emu.push(f.depth, f.rgb, time.monotonic_ns() / 1e6)  # the sensor's clock: the host's, at capture
            pushed[0] += 1
            next_t += period
            time.sleep(max(0.0, next_t - time.monotonic()))
        stop.set()

    latency_ms, chain_ms, sdk_ms = [], [], []
    feeder = threading.Thread(target=feed, daemon=True)
    wall0, cpu0 = time.monotonic(), time.process_time()
    feeder.start()
    got = 0
    while not (stop.is_set() and got >= pushed[0]):
        raw = device.wait(500)
        if raw is None:
            if stop.is_set():
                break
            continue
        got += 1
        if got % args.every:
            continue
        t0 = time.monotonic_ns()
        stamp = clock.stamp(raw.sensor_ns, t0)
        if stamp is None:  # the map's first frame: timed all the same, placed at its receipt
            stamp = t0
        frame = device.process(raw)
        sdk_ms.append((time.monotonic_ns() - t0) / 1e6)
        # the views' own poses are not carried through the device: every frame is placed at the first's
        img = DepthImage(frame.depth, frame.fx, frame.fy, frame.cx, frame.cy, frames[0].cam_pos, frames[0].cam_quat, stamp)
        view.integrate(img, xy0, frame.color)
        view.polytopes(robot_xy=xy0)
        done = time.monotonic_ns()
        latency_ms.append((done - raw.sensor_ns) / 1e6)
        chain_ms.append((done - t0) / 1e6)
    wall, cpu = time.monotonic() - wall0, time.process_time() - cpu0
    emu.stop()
    lat, chain = np.array(latency_ms), np.array(chain_ms)
    return {
        "mode": f"{args.width}x{args.height}@{args.fps}", "decimation": args.decimation, "pixel_stride": args.stride,
        "every": args.every, "frames_pushed": pushed[0], "frames_read": got, "frames_processed": len(lat),
        "latency_ms_p50": round(float(np.percentile(lat, 50)), 1), "latency_ms_p99": round(float(np.percentile(lat, 99)), 1),
        "sdk_ms_p50": round(float(np.percentile(sdk_ms, 50)), 1),  # filters, alignment, units (librealsense)
        "chain_ms_p50": round(float(np.percentile(chain, 50)), 1), "chain_ms_p99": round(float(np.percentile(chain, 99)), 1),
        "cpu_percent_of_one_core": round(100.0 * cpu / wall, 1), "wall_s": round(wall, 1),
    }
