"""``archer emulate overhead``: the lab's overhead camera as an IP camera, an MJPEG stream over HTTP on
127.0.0.1 (:class:`drivers.camera_overhead.emulator.MjpegServer`), for the ``camera_overhead`` service
(``camera_overhead.source`` = the printed ``url``) or any MJPEG client.

- ``--twin SCENARIO``: the twin's rendered overhead view of the scenario (:mod:`sim_twin.overhead_camera`)
  at ``--rate`` Hz of wall time, its obstacles moved as the scenario moves them (kicked, sliding,
  crossing); the robot drawn standing at the start (no physics: the scene only).
- ``--video FILE``: a recorded video's frames at ``--rate`` Hz, from the start again at its end.

Prints one JSON line (``url``, ``host``, ``port``, ``rate_hz``), serves until SIGINT/SIGTERM, then
writes its counters to stderr as ``{"final": ...}``.
"""

from __future__ import annotations

import argparse
import json
import sys
import threading
import time
from collections.abc import Iterator

import numpy as np

from drivers.camera_overhead.device import CameraError, VideoSource
from drivers.camera_overhead.emulator import MjpegServer, serve_frames
from services.runtime.config import ConfigError, load_params

LOOPBACK = "127.0.0.1"


def twin_frames(scenario: str, seed: int, stop: threading.Event) -> Iterator[np.ndarray]:
    """The scenario's overhead view as time goes on (its movers driven by the wall clock)."""
    import mujoco

    from robot_description import params as rd
    from sim_twin import model as tm
    from sim_twin import overhead_camera as oc
    from sim_twin import scenarios as sc

    scn = sc.make(scenario, seed)
    spec = tm.load_spec()
    scn.build(spec)
    model = spec.compile()
    data = mujoco.MjData(model)
    scn.initialize(model, data, rd.robot_params())
    renderer = oc.OverheadRenderer(oc.default_camera(), oc.default_markers(), seed=seed)
    start = (float(data.qpos[0]), float(data.qpos[1]))
    t0 = time.monotonic()
    while not stop.is_set():
        scn.before_step(time.monotonic() - t0, model, data)
        yield renderer.render(scn, start)


def video_frames(path: str, stop: threading.Event) -> Iterator[np.ndarray]:
    """A video file's frames, looped."""
    while not stop.is_set():
        shown = 0
        with VideoSource(path) as src:
            while (frame := src.read()) is not None:
                shown += 1
                yield frame
        if shown == 0:
            raise CameraError(f"{path!r} has no frames")


def run(args: argparse.Namespace, stop: threading.Event) -> int:
    if bool(args.twin) == bool(args.video):
        print("archer emulate overhead: one of --twin SCENARIO or --video FILE", file=sys.stderr)
        return 2
    try:
        params = load_params(args.config, ("camera_overhead",))["camera_overhead"]
    except ConfigError as exc:
        print(f"archer emulate: {exc}", file=sys.stderr)
        return 2
    rate_hz = args.rate if args.rate is not None else params.rate_hz
    if not 0.0 < rate_hz <= 120.0:
        print("archer emulate overhead: --rate must be in (0, 120] Hz", file=sys.stderr)
        return 2
    if args.video:
        try:
            VideoSource(args.video).close()  # said now, not after the line is printed
        except CameraError as exc:
            print(f"archer emulate overhead: {exc}", file=sys.stderr)
            return 2
    frames = twin_frames(args.twin, args.seed, stop) if args.twin else video_frames(args.video, stop)
    first = next(frames)  # the scene built before a client is told where to look
    server = MjpegServer(LOOPBACK, args.port).start()
    error: list[BaseException] = []
    try:
        server.publish(first)

        def feed() -> None:
            try:
                serve_frames(server, frames, rate_hz, stop)
            except BaseException as exc:  # noqa: BLE001 (said on stderr, exit code 1)
                error.append(exc)
            stop.set()

        feeder = threading.Thread(target=feed, name="overhead-frames", daemon=True)
        host, port = server.address
        print(json.dumps({"device": "overhead", "url": server.url, "host": host, "port": port, "rate_hz": rate_hz,
                          "source": f"twin:{args.twin}" if args.twin else args.video}), flush=True)
        feeder.start()
        while not stop.wait(0.5):
            pass
        feeder.join(timeout=5.0)
    finally:
        server.stop()
        print(json.dumps({"final": dict(server.counts), **({"error": repr(error[0])} if error else {})}), file=sys.stderr, flush=True)
    return 1 if error else 0
