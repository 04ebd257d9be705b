"""The ``mocap`` service: the robot's pose from a motion capture system (issue 15).

Subscribes: nothing. Reads: OptiTrack (NatNet), Vicon, Qualisys or VRPN through the
``motioncapture`` library (``pip install '.[mocap]'``), which blocks in
``waitForNextFrame``; a reader thread waits there and hands each frame's rigid body
``mocap.rigid_body`` to :func:`pose_of`.
Computes: the pose's capture time on the stack's clock, ``receive - latency_s`` (the
library's Python bindings report no per-frame latency), and refuses bad frames,
counted as ``rejected.<reason>``: the body missing (not tracked), a value not finite,
a quaternion that is not unit.
Publishes: ``pose`` (PoseMeasurement, ``source = "mocap:<system>"``) at the system's
frame rate.

``motioncapture.connect`` blocks holding the GIL until the server answers, which would
freeze this process if no server listens: for NatNet the reader first asks the
server's command port itself (NAT_CONNECT with a timeout) and connects only after an
answer. A connection that fails is retried every ``reconnect_s``.
"""

from __future__ import annotations

import asyncio
import math
import socket
import threading
from typing import Any, ClassVar

from drivers import natnet
from onboard.contracts import messages as m
from onboard.contracts.params import MocapParams
from services.runtime.service import Service

SYSTEMS = ("optitrack", "vicon", "qualisys", "vrpn")
NATNET_COMMAND_PORT = 1510  # Motive's default


def connect_config(p: MocapParams) -> dict[str, str]:
    """The ``motioncapture.connect`` configuration for ``p``."""
    cfg = {"hostname": p.host}
    if p.port:
        cfg["port_command" if p.system == "optitrack" else "port"] = str(p.port)
    return cfg


def natnet_answers(host: str, port: int, timeout_s: float) -> bool:
    """Whether a NatNet server on ``host:port`` answers NAT_CONNECT with its server info."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.settimeout(timeout_s)
        s.sendto(natnet.pack_request(natnet.NAT_CONNECT), (host, port))
        try:
            data, _ = s.recvfrom(natnet.MAX_PACKET)
        except (socket.timeout, ConnectionRefusedError):
            return False
    return len(data) >= 2 and int.from_bytes(data[:2], "little") == natnet.NAT_SERVERINFO


def pose_of(body: Any, receive_ns: int, p: MocapParams) -> m.PoseMeasurement:
    """The PoseMeasurement of a ``motioncapture`` rigid body received at ``receive_ns``.

    ValueError (its text the rejection reason) for a value that is not finite or a
    quaternion whose norm is off by more than ``quat_norm_tolerance``.
    """
    pos = [float(v) for v in body.position]
    r = body.rotation
    quat = [float(r.w), float(r.x), float(r.y), float(r.z)]
    if len(pos) != 3 or not all(math.isfinite(v) for v in (*pos, *quat)):
        raise ValueError("not_finite")
    norm = math.sqrt(sum(q * q for q in quat))
    if abs(norm - 1.0) > p.quat_norm_tolerance:
        raise ValueError("quat_not_unit")
    return m.PoseMeasurement(
        stamp_ns=receive_ns - round(p.latency_s * 1e9),
        position=pos,
        quat=[q / norm for q in quat],  # float32 on the wire: renormalise what passed the check
        source=f"mocap:{p.system}",
    )


class MocapService(Service):
    name: ClassVar[str] = "mocap"
    params_sections: ClassVar[tuple[str, ...]] = ("mocap",)

    async def setup(self) -> None:
        p: MocapParams = self.params["mocap"]
        if p.system not in SYSTEMS:
            raise ValueError(f"mocap.system must be one of {SYSTEMS}, got {p.system!r}")
        if not (p.latency_s >= 0 and p.rate_hz > 0 and p.connect_timeout_s > 0 and p.reconnect_s > 0):
            raise ValueError("mocap: latency_s >= 0 and positive rate_hz, connect_timeout_s, reconnect_s needed")
        import motioncapture  # an optional extra: only this service needs it

        self._connect = motioncapture.connect
        self._pose_pub = self.publisher("pose")
        self._poses = self.rate("pose")
        self._stop = threading.Event()
        self._frames = 0
        self.reader_error: BaseException | None = None
        self._reader = threading.Thread(target=self._read, name="mocap-reader", daemon=True)

    def _open(self, p: MocapParams) -> Any | None:
        if p.system == "optitrack" and not natnet_answers(p.host, p.port or NATNET_COMMAND_PORT, p.connect_timeout_s):
            self.count("connect_failed")
            return None
        try:
            return self._connect(p.system, connect_config(p))
        except RuntimeError as exc:
            self.count("connect_failed")
            self.log.warning("mocap: cannot connect to %s at %s: %s", p.system, p.host, exc)
            return None

    def _read(self) -> None:
        try:
            while not self._stop.is_set():
                p: MocapParams = self.params["mocap"]
                mc = self._open(p)
                if mc is None:
                    self._stop.wait(p.reconnect_s)
                    continue
                self.count("connects")
                while not self._stop.is_set():
                    mc.waitForNextFrame()  # releases the GIL while it waits
                    self._on_frame(mc.rigidBodies, self.clock.now_ns())
        except BaseException as exc:  # reported by main(); the service goes to error
            self.reader_error = exc

    def _on_frame(self, bodies: dict[str, Any], receive_ns: int) -> None:
        p: MocapParams = self.params["mocap"]
        self._frames += 1
        body = bodies.get(p.rigid_body)
        if body is None:  # the library lists only bodies tracked in this frame
            self.count("rejected.body_missing")
            return
        try:
            pose = pose_of(body, receive_ns, p)
        except ValueError as exc:
            self.count(f"rejected.{exc}")
            return
        self._pose_pub.put(pose)
        self._poses.tick()

    async def main(self) -> None:
        self._reader.start()
        self.state = "degraded"  # until poses flow
        while not self.stopping.is_set():
            try:
                await asyncio.wait_for(self.stopping.wait(), 0.5)
            except asyncio.TimeoutError:
                pass
            if self.reader_error is not None:
                self.state = "error"
                self.fail(f"mocap reader crashed: {self.reader_error!r}")
                return
            self.state = "running" if self.rates_hz().get("pose", 0.0) > 0 else "degraded"

    async def teardown(self) -> None:
        # The reader may sit in waitForNextFrame, which nothing interrupts: it is a
        # daemon thread and ends with the process.
        self._stop.set()

    def status_extra(self) -> dict[str, float]:
        return {"frames": float(self._frames), "latency_s": self.params["mocap"].latency_s}
