"""The mocap path on the twin: estimator RMSE with poses through NatNet vs. straight from the twin.

Lockstep, three runs of one scenario and seed with the low level flying on the truth
(so every run sees the same trajectory; the estimator is only scored):

- ``direct``: the twin's pose sensor (capture time stamped, delivered ``--pose-latency``
  later) feeds the estimator;
- ``natnet``: each of those poses becomes a NatNet frame, sent by :mod:`drivers.natnet`
  (in a child process: ``motioncapture.connect`` holds the GIL) over UDP on 127.0.0.1 to
  ``motioncapture``'s optitrack client, and :func:`services.mocap.pose_of` stamps what it
  decodes with receive time (the simulated delivery time) minus ``mocap.latency_s``;
- ``natnet_uncompensated``: the same with ``latency_s = 0`` (stamp = receive time).
"""

from __future__ import annotations

import argparse
import dataclasses
import multiprocessing as mp
from typing import Any

from drivers import natnet
from onboard.contracts.params import EstimatorParams, MocapParams, TwinParams
from services.bench.estimator import MeasuredEstimator
from services.mocap import pose_of
from sim_twin import lockstep as ls

NS = 1_000_000_000
BODY_ID = 1


def _serve(conn: Any, name: str) -> None:
    """Child process: a NatNet server that publishes each frame the parent sends."""
    server = natnet.NatNetServer({BODY_ID: name}).start()
    conn.send(server.command_port)
    try:
        while (item := conn.recv()) is not None:
            frame, transmit_ns = item
            server.publish(frame, transmit_ns)
    finally:
        server.stop()


class NatNetPoses:
    """Feeds the estimator the twin's poses as they come out of NatNet and ``motioncapture``."""

    def __init__(self, inner: Any, params: MocapParams, tick_ns: int) -> None:
        import motioncapture

        self.inner = inner
        self.name = inner.name
        self.params = params
        self.tick_ns = tick_ns
        self.now_ns = 0
        self.frames = 0
        self._conn, child = mp.Pipe()
        self._proc = mp.get_context("spawn").Process(target=_serve, args=(child, params.rigid_body), daemon=True)
        self._proc.start()
        port = self._conn.recv()
        self.mc = motioncapture.connect("optitrack", {"hostname": "127.0.0.1", "port_command": str(port)})

    def close(self) -> None:
        self._conn.send(None)
        self._proc.join(5.0)

    def feed(self, topic: str, msg: Any, now_ns: int) -> None:
        if topic == "pose":
            receive_ns = self.now_ns + self.tick_ns  # the tick being delivered
            self.frames += 1
            body = natnet.RigidBodySample(BODY_ID, tuple(msg.position), tuple(msg.quat))
            self._conn.send((natnet.Frame(self.frames, (body,), msg.stamp_ns, receive_ns, msg.stamp_ns / NS), receive_ns))
            self.mc.waitForNextFrame()
            msg = pose_of(self.mc.rigidBodies[self.params.rigid_body], receive_ns, self.params)
        self.inner.feed(topic, msg, now_ns)

    def estimate(self, now_ns: int, data: Any) -> Any:
        self.now_ns = now_ns
        return self.inner.estimate(now_ns, data)

    def counters(self) -> dict[str, int]:
        return self.inner.counters()

    @property
    def est(self) -> Any:
        return self.inner.est


def run_path(path: str, scenario: str, seed: int, duration_s: float, pose_latency_s: float) -> dict[str, Any]:
    twin = dataclasses.replace(TwinParams(), pose_latency_s=pose_latency_s, pose_dropout=0.0)
    cfg = ls.RunConfig(scenario=scenario, seed=seed, duration_s=duration_s, estimator="kalman",
                       twin=twin, estimator_params=EstimatorParams())
    runner = ls.LockstepRunner(cfg)
    source = runner.estimator
    if path != "direct":
        latency = pose_latency_s if path == "natnet" else 0.0
        source = NatNetPoses(runner.estimator, MocapParams(latency_s=latency), runner.tick_ns)
    measured = MeasuredEstimator(source, runner.truth, 0.5, closed_loop=False, seed=seed)
    runner.estimator = measured
    try:
        metrics = runner.run().metrics
    finally:
        if isinstance(source, NatNetPoses):
            source.close()
    fig = measured.figures()
    out = {k: fig[k] for k in ("rmse_pos_m", "rmse_vel_m_s", "rmse_att_deg", "valid_fraction")}
    out["hops"] = metrics["hops"]
    if isinstance(source, NatNetPoses):
        out["natnet_frames"] = source.frames
    return out


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--scenario", default="hop-in-place")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--duration", type=float, default=5.0, help="simulated seconds")
    parser.add_argument("--pose-latency", type=float, default=0.020, help="pose capture to receive [s]")


def measure(args: argparse.Namespace) -> dict[str, Any]:
    runs = {path: run_path(path, args.scenario, args.seed, args.duration, args.pose_latency)
            for path in ("direct", "natnet", "natnet_uncompensated")}
    direct = runs["direct"]
    ratio = {k: round(runs["natnet"][k] / direct[k], 3) for k in ("rmse_pos_m", "rmse_vel_m_s", "rmse_att_deg")}
    return {"scenario": args.scenario, "pose_latency_s": args.pose_latency, **runs, "natnet_over_direct": ratio}
