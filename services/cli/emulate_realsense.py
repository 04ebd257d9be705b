"""``archer emulate realsense --twin SCENARIO``: the D435 and its ``camera`` service, on the twin, in real time.

librealsense's software device lives in the process that feeds it, so the emulation is one process:
the twin (:class:`services.cli.emulate.TwinPlant`, unactuated, stepped at its control rate on a
:class:`DeadlineLoop`), its RGB-D camera (:class:`sim_twin.camera.RgbdCamera`, at the ``camera``
section's depth mode; each frame stamped with the host's monotonic clock at its capture, as the
camera's hardware clock would be) feeding a :class:`drivers.realsense.emulator.SoftwareD435`, and
the :class:`services.camera.CameraService` reading it through librealsense and publishing
``sensors/depth`` and ``sensors/color`` on Zenoh (``--endpoint``) exactly as on the robot.
The camera places each frame by the ``state`` estimate as on the robot; with ``--truth-pose``
(no estimator running) by the twin's true pose instead. Frames the host cannot render at the
stream's rate come late and fewer (``renders``, ``render_ms`` in the final counters).
Prints one JSON line (namespace, endpoint, mode), serves until SIGINT/SIGTERM.
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import sys
import threading
import time

from drivers.realsense import load
from drivers.realsense.emulator import Intrinsics, SoftwareD435
from onboard.contracts import messages as m
from onboard.contracts.params import CameraParams, TwinParams, with_overrides
from onboard.contracts.topics import namespace
from services.camera import CameraService, stream_config
from services.runtime.config import ConfigError, load_params
from services.runtime.realtime import DeadlineLoop


class EmulatedCamera(CameraService):
    """The camera service on the emulated D435 (and, with ``truth_pose``, the twin's true pose)."""

    def __init__(self, *args, source: SoftwareD435, truth=None, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        self._emulated = source
        self._truth = truth

    def open_source(self, p: CameraParams) -> SoftwareD435:
        return self._emulated

    def _state_near(self, at_ns: int, max_age_ns: int) -> m.StateEstimate | None:
        if self._truth is None:
            return super()._state_near(at_ns, max_age_ns)
        return self._truth(at_ns)

    def _estimates_ready(self) -> bool:
        return self._truth is not None or super()._estimates_ready()  # the truth needs no estimator to wait for


def run(args: argparse.Namespace, make_plant) -> int:
    """``make_plant()``: the twin behind the camera (:class:`services.cli.emulate.TwinPlant`)."""
    import mujoco

    from robot_description import params as rd
    from sim_twin.camera import CameraModel, RgbdCamera

    try:
        p: CameraParams = load_params(args.config, ("camera",))["camera"]
    except ConfigError as exc:
        print(f"archer emulate: {exc}", file=sys.stderr)
        return 2
    if not args.twin:
        print("archer emulate realsense: --twin SCENARIO is needed (the frames are the twin's)", file=sys.stderr)
        return 2
    rs = load()
    plant = make_plant()
    # the camera's mount is the twin's robot's (TwinParams.variant)
    p = with_overrides(p, {"robot_variant": TwinParams().variant})
    model = CameraModel.d435(p.width, p.height, p.fps)
    camera = RgbdCamera(plant.model, model, plant.scenario.traversable, seed=args.seed)
    cfg = stream_config(p)
    cfg = type(cfg)(**{**cfg.__dict__, "color_width": p.width, "color_height": p.height, "color_fps": p.fps})  # registered pixel for pixel
    emu = SoftwareD435(rs, cfg, Intrinsics(model.fx, model.fy, model.cx, model.cy))
    torso = plant.model.body(rd.TORSO).id
    done = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: done.set())
    counts = {"renders": 0, "render_ms": 0.0}
    zero = [0.0, 0.0, 0.0, 0.0]

    def truth(at_ns: int) -> m.StateEstimate:
        with plant._lock:
            com = plant.data.subtree_com[torso].tolist()
            q = plant.data.qpos[3:7].tolist()
            v = plant.data.qvel[0:3].tolist()
        return m.StateEstimate(stamp_ns=at_ns, position=com, velocity=v, quat=q, omega=[0.0] * 3, wheel_vel=[0.0] * 3,
                               foot_pos=0.0, foot_vel=0.0, contact=False, phase="flight", pos_vel_cov=[0.0] * 36,
                               att_cov=[0.0] * 3)

    def render_loop() -> None:
        period = 1.0 / p.fps
        next_t = time.monotonic()
        while not done.is_set():
            t0 = time.monotonic_ns()
            with plant._lock:
                mujoco.mj_forward(plant.model, plant.data)
                frame = camera.render(plant.data)
            emu.push(frame.depth, frame.rgb, t0 / 1e6)
            counts["renders"] += 1
            counts["render_ms"] = (time.monotonic_ns() - t0) / 1e6
            next_t = max(next_t + period, time.monotonic())
            done.wait(max(0.0, next_t - time.monotonic()))

    loop = DeadlineLoop(plant.dt_s, lambda _d: plant.step(time.monotonic_ns() / 1e9, zero), name="realsense-twin")
    loop.start()
    renderer = threading.Thread(target=render_loop, name="realsense-render", daemon=True)
    renderer.start()
    ns = args.namespace or namespace()
    service = EmulatedCamera(ns=ns, endpoint=args.endpoint, params={"camera": p}, source=emu,
                             truth=truth if args.truth_pose else None)
    print(json.dumps({"device": "realsense", "namespace": ns, "endpoint": service.endpoint,
                      "mode": f"{p.width}x{p.height}@{p.fps}", "truth_pose": bool(args.truth_pose),
                      "pid": os.getpid()}), flush=True)

    try:
        service.run_until(done)
    finally:
        done.set()
        renderer.join(5.0)
        loop.stop(2.0)
        emu.stop()
        final = {**counts, "published": service._seq, "frames": getattr(service, "frames", 0),
                 "overruns": loop.recorder.stats().overruns}
        print(json.dumps({"final": final}), file=sys.stderr, flush=True)
    return 0 if loop.error is None else 1
