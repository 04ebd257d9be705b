"""The ``estimator`` service on a real Zenoh session over loopback.

A publisher thread replays synthetic hops (:mod:`test_estimator_synthetic`) as the
hardware would: IMU and joint frames at 1 kHz, poses at 100 Hz delivered 20 ms after
capture, all stamped on the wall-monotonic clock the service uses.
"""

from __future__ import annotations

import asyncio
import dataclasses
import math
import threading
import time

import numpy as np

from onboard import messages as m
from onboard import quaternion as quat
from onboard.params import EstimatorParams
from onboard.topics import TOPICS
from services.clock import WallClock
from services.cmd_introspect import query_status
from services.estimator import EstimatorService
from services.zenoh_session import open_session
from test_estimator_synthetic import ROBOT, synthetic_hops
from helpers import wait_for

NS_KEY = "archer/estimator-test"



def _payloads(track, t0_ns: int) -> tuple[list[tuple[int, str, bytes]], dict[int, np.ndarray]]:
    """(publish time, key, payload) in order, and the true CoM by stamp."""
    mu = ROBOT.foot_mass / ROBOT.total_mass
    c0 = np.array(ROBOT.com_offset_body)
    keys = {name: TOPICS[name].key(NS_KEY) for name in ("imu", "joints", "pose")}
    out: list[tuple[int, str, bytes]] = []
    truth: dict[int, np.ndarray] = {}
    for k in range(len(track.t_ns)):
        t = t0_ns + k * 1_000_000
        q = tuple(float(v) for v in track.quat[k])
        r = np.array(quat.to_matrix(q))
        f = r.T @ (track.accel_com[k] / (1.0 - mu) + np.array([0.0, 0.0, ROBOT.gravity])) if track.contact[k] else np.zeros(3)
        out.append((t, keys["imu"], m.encode(m.ImuSample(stamp_ns=t, quat=list(q), gyro=track.omega[k].tolist(), accel=f.tolist()))))
        out.append((t, keys["joints"], m.encode(m.JointSensors(
            stamp_ns=t, wheel_pos=[0.0] * 3, wheel_vel=[0.0] * 3, wheel_torque=[0.0] * 3,
            foot_pos=float(track.foot_s[k]), foot_vel=float(track.foot_sd[k]), foot_contact=bool(track.contact[k])))))
        truth[t] = track.pos[k]
        if k % 10 == 0:
            origin = track.pos[k] - r @ (c0 + np.array([0.0, 0.0, mu * track.foot_s[k]]))
            pose = m.PoseMeasurement(stamp_ns=t, position=origin.tolist(), quat=list(q))
            out.append((t + 20_000_000, keys["pose"], m.encode(pose)))  # delivered 20 ms after capture
    out.sort(key=lambda item: item[0])
    return out, truth


def _replay(session, payloads: list[tuple[int, str, bytes]], stop: threading.Event) -> None:
    """Publish each payload at its time (wall-monotonic); sleeps, never spins."""
    for t, key, payload in payloads:
        if stop.is_set():
            return
        wait = (t - time.monotonic_ns()) / 1e9
        if wait > 0:
            time.sleep(wait)
        session.put(key, payload)


def test_service_publishes_the_estimate_at_rate(zenoh_router):
    track = synthetic_hops(2.0)
    params = dataclasses.replace(EstimatorParams(), accel_delay_s=0.0)

    async def scenario() -> None:
        service = EstimatorService(ns=NS_KEY, endpoint=zenoh_router, params={"estimator": params}, clock=WallClock())
        task = asyncio.create_task(service.run())
        client = open_session(zenoh_router, "peer")
        states: list[m.StateEstimate] = []
        sub = client.declare_subscriber(TOPICS["state"].key(NS_KEY),
                                        lambda s: states.append(m.decode(s.payload.to_bytes(), m.StateEstimate)))
        stop = threading.Event()
        try:
            await wait_for(lambda: service.state in ("running", "degraded") and service.counters.get("ticks_without_imu") > 10)
            assert states == []  # no IMU yet: nothing to stamp an estimate with, so nothing published
            imu_key = TOPICS["imu"].key(NS_KEY)
            client.put(imu_key, b"{not json")  # malformed: rejected by the runtime, counted
            client.put(imu_key, b'{"stamp_ns": 5, "quat": [1, 0, 0, 0], "gyro": [null, 0, 0], "accel": [0, 0, 9.8]}')
            t0 = time.monotonic_ns() + 300_000_000
            payloads, truth = _payloads(track, t0)
            pub = threading.Thread(target=_replay, args=(client, payloads, stop), daemon=True)
            pub.start()
            await asyncio.to_thread(pub.join, 30.0)
            await asyncio.sleep(0.05)
            client.put(imu_key, m.encode(m.ImuSample(stamp_ns=t0, quat=[1.0, 0, 0, 0], gyro=[0.0] * 3, accel=[0.0, 0.0, 9.8])))
            await asyncio.sleep(0.1)
            status = await asyncio.to_thread(query_status, client, NS_KEY, "estimator")
        finally:
            stop.set()
            sub.undeclare()
            service.stopping.set()
            await asyncio.wait_for(task, 10.0)
            client.close()

        during = [s for s in states if t0 + 500_000_000 <= s.stamp_ns <= t0 + 1_990_000_000]
        # 1 kHz nominal; the shared 2-core test machine makes the loop skip deadlines, and the
        # replay thread shares this process's GIL: the rate itself is the bench's to measure
        assert len(during) > 0.5 * 1490, len(during)
        stamps = np.array(sorted(truth))
        path = np.array([truth[t] for t in stamps])
        # valid unless the IMU went stale (a loaded machine can hold messages back > 5 ms):
        # the filter's own uncertainty stays small throughout
        assert sum(s.valid for s in during) > 0.8 * len(during)
        assert max(s.pos_vel_cov[0] for s in during) < 0.03 ** 2
        # the estimate at its stamp against the truth interpolated there
        errs = [math.dist(s.position, [np.interp(s.stamp_ns, stamps, path[:, i]) for i in range(3)]) for s in during]
        # Median, not RMS: when the whole suite shares this process's GIL the replay can
        # stall and the tail of the run drift (seen once in a full run: RMS 8 cm, the last
        # 0.3 s off by up to 0.38 m; alone it passes). Accuracy is tested deterministically
        # in test_estimator_twin.py.
        assert np.median(errs) < 0.01
        assert status is not None
        assert status.counters["rejected.imu"] == 2
        assert status.extra["est.imu_out_of_order"] == 1.0
        assert status.extra["est.touchdowns"] >= 5
        assert 0.0 < status.extra["pos_std_m"] < 0.01
        assert status.rates_hz["loop"] > 300

    asyncio.run(asyncio.wait_for(scenario(), 90))
