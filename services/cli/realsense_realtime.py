"""``archer sim --mode realtime --sensing onboard`` (issue 27): outdoors as ARCHER is built, on the
real-time twin, with no motion capture.

The twin publishes no ``pose`` and none of its own low-resolution depth
(:class:`services.twin.OnboardSensing`); the estimator keeps its odometry frame from the IMU, the
legs and the D435's visual odometry. The D435 is librealsense's own software device, as in
``archer emulate realsense``, in a process of its own (:class:`RealsenseRig`) that also runs the
``camera`` service on it, as the robot's computer would (the software device lives in the process
that feeds it):

- the twin writes its configuration (``qpos``, the bodies a scenario moves) into shared memory
  every tick (:class:`SceneSnapshot`, a sequence lock): no pipe traffic, and the rig never takes
  the twin loop's GIL;
- the camera is triggered at each ``apex`` event of the estimator, as a D435 in external-trigger
  mode would be wired to the stack's apex, so every frame it delivers is an apex frame (``capture =
  "every"``): the newest snapshot is drawn (depth and colour at the ``camera`` section's mode,
  :class:`sim_twin.camera.RgbdCamera`) and handed to the software device as soon as it is drawn,
  stamped with its capture time in librealsense's ``global_time`` domain (the host's wall clock, as
  the SDK stamps a camera's frames), which the service's clock map takes as it is: a frame drawn
  late on a loaded host keeps its capture time. Drawing every frame of a 30 Hz stream would take
  this host 1.5-8 cores of ray casting (424 x 240: 50-80 ms a frame; 848 x 480: 150-280 ms) for
  frames the service drops: it keeps the one nearest each apex;
- the ``camera`` service places each frame by the estimate and publishes ``depth``, ``color`` and
  ``visual_odometry``; with ``--perception depth`` the ``perception`` service reads the first two.

The run's JSON gets a ``depth_camera`` block: triggers, frames drawn, the drawing's wall and CPU
time, capture to the SDK, and the camera service's own counters.
"""

from __future__ import annotations

import logging
import multiprocessing
import os
import pickle
import signal
import tempfile
import threading
import time
import tomllib
from pathlib import Path
from typing import Any

import numpy as np

from services.runtime.config import load_params

# A D435 mode (depth 424 x 240 at 30 Hz, colour registered pixel for pixel), drawn without the SDK's
# decimation: the deploy profile's 848 x 480 decimated by 2, at a quarter of the rays.
SIL_CAMERA = {"width": 424, "height": 240, "fps": 30, "color": True, "color_width": 424, "color_height": 240,
              "color_fps": 30, "decimation": 1, "capture": "every", "source": "device"}
SIL_DRAWN_DECIMATION = 2  # the drawing is that decimation, noise included (sim_twin.camera.CameraModel), not the SDK's
# The emulated camera's frames reach the estimator up to 2.5 s after their capture on a loaded 2-core host
# (capture_to_sdk_ms_p99, sidewalk seed 2): a VO displacement older than the odometry it is compared with is refused.
SIL_ESTIMATOR = {"vo_history_s": 4.0}
# The outdoor profile's perception (deploy/config/archer-outdoor.toml), where the user's file says nothing.
SIL_PERCEPTION = {"segmenter": "color", "pixel_stride": 4}
log = logging.getLogger("archer.d435_rig")
RIG_NICE = 0  # deploy/systemd/archer-camera.service's Nice=: the camera service's, as on the robot
# The drawing stands in for the D435's own hardware, which takes no CPU from the robot's computer: on a
# busy host it yields to the stack's loops (at Nice 0 it drew beside them on two cores and a fresh-clone
# CI run saw the estimate lost and a fall at 8.9 s, twice)
DRAW_NICE = 10
RIG_START_TIMEOUT_S = 120.0  # [s] to import MuJoCo, librealsense and Zenoh on a loaded machine
FINISH_TIMEOUT_S = 15.0
SNAPSHOT_TRIES = 100  # reads of a snapshot the twin is writing, before the trigger is counted as missed


class SceneSnapshot:
    """The twin's configuration in shared memory, under a sequence lock: ``[seq, stamp_ns, qpos,
    mocap_pos, mocap_quat]`` as float64 (a stamp in ns is exact below 2^53, ~104 days of uptime).
    One writer (the twin's loop), one reader (the rig's drawing thread)."""

    def __init__(self, nq: int, nmocap: int, ctx: Any) -> None:
        self.nq, self.nmocap = nq, nmocap
        self.array = ctx.Array("d", 2 + nq + 7 * nmocap, lock=False)
        self._buf: np.ndarray | None = None

    def __getstate__(self) -> dict[str, Any]:  # to the rig's process: the shared array, not this side's view
        return {"nq": self.nq, "nmocap": self.nmocap, "array": self.array, "_buf": None}

    def _view(self) -> np.ndarray:
        if self._buf is None:
            self._buf = np.frombuffer(self.array, dtype=np.float64)
        return self._buf

    def write(self, stamp_ns: int, data: Any) -> None:
        buf, nq, nm = self._view(), self.nq, self.nmocap
        buf[0] += 1.0  # odd: being written
        buf[1] = stamp_ns
        buf[2:2 + nq] = data.qpos
        if nm:
            buf[2 + nq:2 + nq + 3 * nm] = data.mocap_pos.ravel()
            buf[2 + nq + 3 * nm:] = data.mocap_quat.ravel()
        buf[0] += 1.0  # even: whole

    def read_into(self, data: Any) -> int | None:
        """The newest whole snapshot into ``data`` (qpos, mocap); its stamp, or None when none was
        whole within ``SNAPSHOT_TRIES`` reads (or none was written yet)."""
        buf, nq, nm = self._view(), self.nq, self.nmocap
        for _ in range(SNAPSHOT_TRIES):
            seq = buf[0]
            if seq == 0.0:
                return None
            if seq % 2.0 == 0.0:
                copy = buf.copy()
                if buf[0] == seq:
                    data.qpos[:] = copy[2:2 + nq]
                    if nm:
                        data.mocap_pos[:] = copy[2 + nq:2 + nq + 3 * nm].reshape(nm, 3)
                        data.mocap_quat[:] = copy[2 + nq + 3 * nm:].reshape(nm, 4)
                    return int(copy[1])
            time.sleep(0)
        return None


def rig_overrides(user: dict[str, Any], variant: str) -> dict[str, Any]:
    """The user's config with what the emulated camera forces (its mode and trigger, its mount's robot),
    the estimator without a pose source (and history for the camera's latency), and the outdoor
    profile's perception, each where the user's file leaves it unset."""
    out = dict(user)
    out["camera"] = {**user.get("camera", {}), **SIL_CAMERA, "robot_variant": variant}
    out["estimator"] = {**SIL_ESTIMATOR, **user.get("estimator", {}), "position_source": "odometry"}
    out["perception"] = {**SIL_PERCEPTION, **user.get("perception", {})}
    return out


class RealsenseRig:
    """The emulated D435 and its ``camera`` service for a real-time run (module docstring): the config
    file every service reads (:func:`rig_overrides`), and the rig's process, started by the twin
    once its model is built (:meth:`start`), fed by :meth:`write` on the twin's tick."""

    def __init__(self, config: str | None, toml: Any, variant: str, endpoint: str, ns: str) -> None:
        from drivers.realsense import load

        try:
            load()
        except ImportError as exc:  # said before anything starts
            raise ValueError(f"--sensing onboard in real time emulates the D435 through librealsense: "
                             f"pip install '.[realsense]' ({exc})") from None
        user = tomllib.loads(Path(config).read_text()) if config else {}
        fd, self.config_path = tempfile.mkstemp(prefix="archer-onboard-", suffix=".toml")
        with os.fdopen(fd, "w") as f:
            f.write(toml(rig_overrides(user, variant)))
        try:
            load_params(self.config_path)  # what the services will read is valid before they start
        except BaseException:
            os.unlink(self.config_path)
            raise
        self.endpoint, self.ns = endpoint, ns
        self.snapshot: SceneSnapshot | None = None
        self._proc: Any = None
        self._conn: Any = None
        self._ready = False
        self.failure: str | None = None
        self._report: dict[str, Any] | None = None

    def start(self, model: Any, traversable: Any, seed: int) -> None:
        """Spawn the rig's process on the twin's compiled model (its model error and world included).
        Returns at once; :meth:`poll` says when it is up or why it failed."""
        ctx = multiprocessing.get_context("spawn")  # no fork of a process with Zenoh's and MuJoCo's threads
        self.snapshot = SceneSnapshot(model.nq, model.nmocap, ctx)
        self._conn, child = ctx.Pipe()
        self._proc = ctx.Process(target=_rig_main, name="archer-d435-rig", daemon=True,
                                 args=(child, pickle.dumps(model), list(traversable), seed, self.snapshot,
                                       self.config_path, self.endpoint, self.ns, os.getpid()))
        self._proc.start()
        child.close()
        self._started = time.monotonic()

    @property
    def ready(self) -> bool:
        """The rig's camera service is up (its start-up, which competes with the stack's loops for the
        cores, is over)."""
        return self._ready

    def write(self, stamp_ns: int, data: Any) -> None:
        if self.snapshot is not None:
            self.snapshot.write(stamp_ns, data)

    def poll(self) -> str | None:
        """Why the rig failed (it could not start, or it died), else None."""
        if self._proc is None or self.failure is not None:
            return self.failure
        try:
            while self._conn.poll():
                msg = self._conn.recv()
                if "error" in msg:
                    self.failure = f"the D435 rig failed: {msg['error']}"
                    return self.failure
                if msg.get("ready"):
                    self._ready = True
        except (EOFError, OSError):
            self._proc.join(1.0)
            self.failure = f"the D435 rig's process ended (exit code {self._proc.exitcode})"
        if not self._ready and self.failure is None and time.monotonic() - self._started > RIG_START_TIMEOUT_S:
            self.failure = "the D435 rig did not start"
        return self.failure

    def finish(self) -> dict[str, Any]:
        """Stop the rig's process; its report (counters of the drawing and the camera service)."""
        if self._report is not None:
            return self._report
        self._report = {"failure": self.failure} if self.failure else {}
        if self._proc is None:
            return self._report
        try:
            self._conn.send(None)
            deadline = time.monotonic() + FINISH_TIMEOUT_S
            while time.monotonic() < deadline and self._conn.poll(max(0.0, deadline - time.monotonic())):
                msg = self._conn.recv()
                if "final" in msg:
                    self._report.update(msg["final"])
                    break
        except (EOFError, OSError):
            pass
        self._conn.close()
        self._proc.join(FINISH_TIMEOUT_S)
        if self._proc.is_alive():
            self._proc.kill()
            self._proc.join()
        return self._report

    def close(self) -> None:
        self.finish()
        if os.path.exists(self.config_path):
            os.unlink(self.config_path)


def _percentile(values: list[float], q: float) -> float | None:
    return round(float(np.percentile(values, q)), 2) if values else None


def _rig_main(conn: Any, model_bytes: bytes, traversable: list[str], seed: int, snapshot: SceneSnapshot,
              config_path: str, endpoint: str, ns: str, parent_pid: int) -> None:
    """The rig's process: the twin's scene drawn at each apex into librealsense's software device, and
    the camera service reading it. Ends on ``None`` or when the twin's end of the pipe goes."""
    import faulthandler

    from services.runtime.realtime import die_with_parent

    faulthandler.enable()  # a crash in librealsense or MuJoCo says where, on the run's stderr
    die_with_parent(parent_pid, signal.SIGTERM)
    if os.sched_getscheduler(0) != os.SCHED_OTHER:  # spawned by the twin's real-time process
        os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
    os.setpriority(os.PRIO_PROCESS, 0, RIG_NICE)  # not the twin's -10, which starved the planner (nice 10)
    try:
        import mujoco

        from drivers.realsense import load
        from drivers.realsense.emulator import Intrinsics, SoftwareD435
        from services.camera import stream_config
        from services.cli.emulate_realsense import EmulatedCamera
        from sim_twin.camera import CameraModel, RgbdCamera

        rs = load()
        model = pickle.loads(model_bytes)
        data = mujoco.MjData(model)
        params = load_params(config_path, ("camera", "estimator"))
        p = params["camera"]
        lens = CameraModel.d435(p.width * SIL_DRAWN_DECIMATION, p.height * SIL_DRAWN_DECIMATION, p.fps, SIL_DRAWN_DECIMATION)
        camera = RgbdCamera(model, lens, traversable, seed=seed)
        emu = SoftwareD435(rs, stream_config(p), Intrinsics(lens.fx, lens.fy, lens.cx, lens.cy), global_time=True)
    except BaseException as exc:  # noqa: BLE001 (the twin reports it and the run fails)
        conn.send({"error": repr(exc)})
        return

    done = threading.Event()
    triggered = threading.Event()
    counts = {"triggers": 0, "drawn": 0, "no_snapshot": 0}
    draw_ms: list[float] = []
    draw_cpu_ms: list[float] = []  # the drawing thread's own CPU: what the frame costs, apart from waiting for a core
    capture_to_sdk_ms: list[float] = []

    def on_apex(_stamp_ns: int) -> None:
        counts["triggers"] += 1
        triggered.set()

    def draw_loop() -> None:
        try:
            os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), DRAW_NICE)  # this thread only (Linux)
        except OSError as exc:
            log.warning("d435 rig: the drawing keeps the rig's priority: %s", exc)
        while not done.is_set():
            if not triggered.wait(0.1):
                continue
            triggered.clear()
            stamp_ns = snapshot.read_into(data)
            if stamp_ns is None:
                counts["no_snapshot"] += 1
                continue
            tic, cpu = time.perf_counter(), time.thread_time()
            mujoco.mj_kinematics(model, data)
            frame = camera.render(data)
            draw_ms.append((time.perf_counter() - tic) * 1e3)
            draw_cpu_ms.append((time.thread_time() - cpu) * 1e3)
            now_ns = time.monotonic_ns()
            capture_to_sdk_ms.append((now_ns - stamp_ns) / 1e6)
            emu.push(frame.depth, frame.rgb, (stamp_ns + time.time_ns() - now_ns) / 1e6)  # global time: wall clock [ms]
            counts["drawn"] += 1

    def watch_pipe() -> None:
        try:
            while conn.recv() is not None:
                pass
        except (EOFError, OSError):
            pass
        done.set()

    class TriggeredCamera(EmulatedCamera):
        async def setup(self) -> None:
            await super().setup()
            conn.send({"ready": True})  # its session open and its pipeline started: the start-up's cost is paid

        def _on_phase(self, event: Any) -> None:
            super()._on_phase(event)
            if event.event == "apex":
                on_apex(event.stamp_ns)

    service = TriggeredCamera(ns=ns, endpoint=endpoint, params={"camera": p, "estimator": params["estimator"]},
                              source=emu)
    drawer = threading.Thread(target=draw_loop, name="d435-draw", daemon=True)
    watcher = threading.Thread(target=watch_pipe, name="d435-pipe", daemon=True)

    drawer.start()
    watcher.start()
    try:
        service.run_until(done)
        if not done.is_set():  # the service ended by itself: a crash it caught
            conn.send({"error": f"the camera service stopped: {service.last_error or service.state}"})
    except BaseException as exc:  # noqa: BLE001 (reported to the twin)
        try:
            conn.send({"error": repr(exc)})
        except OSError:
            pass
    finally:
        done.set()
        drawer.join(5.0)
        emu.stop()
        final = {**counts, "mode": f"{p.width}x{p.height}@{p.fps}",
                 "draw_ms_p50": _percentile(draw_ms, 50), "draw_ms_p99": _percentile(draw_ms, 99),
                 "draw_cpu_ms_p50": _percentile(draw_cpu_ms, 50), "process_cpu_s": round(time.process_time(), 2),
                 "capture_to_sdk_ms_p50": _percentile(capture_to_sdk_ms, 50),
                 "capture_to_sdk_ms_p99": _percentile(capture_to_sdk_ms, 99),
                 "camera_counters": service.counters.snapshot(), "camera_status": service.status_extra()}
        try:
            conn.send({"final": final})
        except OSError:
            pass
