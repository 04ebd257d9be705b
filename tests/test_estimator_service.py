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
import pytest

from onboard.contracts import messages as m
from onboard.geometry import quaternion as quat
from onboard.contracts.params import EstimatorParams
from onboard.contracts.topics import TOPICS
from services.runtime.clock import WallClock
from services.runtime.peers import query_status
from services.estimator import EstimatorService
from services.runtime.zenoh_session import open_session
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
        # a valid estimate is a certain one (a stalled replay grows the covariance honestly
        # and the estimate says it is not valid then)
        assert max(s.pos_vel_cov[0] for s in during if s.valid) < 0.03 ** 2
        # the estimate at its stamp against the truth interpolated there
        errs = [math.dist(s.position, [np.interp(s.stamp_ns, stamps, path[:, i]) for i in range(3)]) for s in during]
        # Median, not RMS: when the whole suite shares this process's GIL the replay can
        # stall and the tail of the run drift (seen once in a full run: RMS 8 cm, the last
        # 0.3 s off by up to 0.38 m; alone it passes). Accuracy is tested deterministically
        # in test_estimator_twin.py.
        assert np.median(errs) < 0.01
        assert status is not None
        assert status.counters["rejected.imu"] == 2
        assert status.extra["est.imu_past"] == 1.0  # the sample stamped t0, 2 s after it: from the past, refused
        assert status.extra["est.touchdowns"] >= 5
        assert 0.0 < status.extra["pos_std_m"] < 0.01
        assert status.rates_hz["loop"] > 300

    asyncio.run(asyncio.wait_for(scenario(), 90))


def _run_with_attacker(zenoh_router, attack) -> tuple[list[m.StateEstimate], dict, object, int]:
    """Replay 2 s of synthetic hops while ``attack(client, t0, stop)`` runs on its own thread;
    returns the published estimates, the truth by stamp, the final status and t0."""
    track = synthetic_hops(2.0)
    params = dataclasses.replace(EstimatorParams(), accel_delay_s=0.0)

    async def scenario():
        service = EstimatorService(ns=NS_KEY, endpoint=zenoh_router, params={"estimator": params}, clock=WallClock())
        task = asyncio.create_task(service.run())
        client = open_session(zenoh_router, "peer")
        states: list[m.StateEstimate] = []
        sub = client.declare_subscriber(TOPICS["state"].key(NS_KEY),
                                        lambda s: states.append(m.decode(s.payload.to_bytes(), m.StateEstimate)))
        stop = threading.Event()
        try:
            await wait_for(lambda: service.state in ("running", "degraded"))
            t0 = time.monotonic_ns() + 300_000_000
            payloads, truth = _payloads(track, t0)
            threads = [threading.Thread(target=_replay, args=(client, payloads, stop), daemon=True),
                       threading.Thread(target=attack, args=(client, t0, stop), daemon=True)]
            for th in threads:
                th.start()
            await asyncio.to_thread(threads[0].join, 30.0)
            stop.set()
            await asyncio.to_thread(threads[1].join, 5.0)
            await asyncio.sleep(0.1)
            status = await asyncio.to_thread(query_status, client, NS_KEY, "estimator")
        finally:
            stop.set()
            sub.undeclare()
            service.stopping.set()
            await asyncio.wait_for(task, 10.0)
            client.close()
        return states, truth, status, t0

    return asyncio.run(asyncio.wait_for(scenario(), 90))


def _median_error(states: list[m.StateEstimate], truth: dict, t0: int) -> float:
    during = [s for s in states if t0 + 500_000_000 <= s.stamp_ns <= t0 + 1_990_000_000]
    assert len(during) > 0.5 * 1490, len(during)
    stamps = np.array(sorted(truth))
    path = np.array([truth[t] for t in stamps])
    return float(np.median([math.dist(s.position, [np.interp(s.stamp_ns, stamps, path[:, i]) for i in range(3)])
                            for s in during]))


def test_a_foreign_pose_stream_never_captures_the_estimate(zenoh_router):
    """Poses 100 m away at 100 Hz, stamped fresh, beside the real ones: each is refused by the
    gate and counted in the status counters; the real poses keep being fused (the old
    estimator re-initialized on the foreign stream after 20 refusals)."""
    sent = []

    def foreign(client, t0: int, stop: threading.Event) -> None:
        key = TOPICS["pose"].key(NS_KEY)
        time.sleep(max(0.0, (t0 + 200_000_000 - time.monotonic_ns()) / 1e9))
        while not stop.is_set() and time.monotonic_ns() < t0 + 1_900_000_000:
            now = time.monotonic_ns()
            client.put(key, m.encode(m.PoseMeasurement(stamp_ns=now, position=[100.0, 0.0, 0.5], quat=[1.0, 0, 0, 0])))
            sent.append(now)
            time.sleep(0.01)

    states, truth, status, t0 = _run_with_attacker(zenoh_router, foreign)
    assert len(sent) > 100
    assert _median_error(states, truth, t0) < 0.01
    stamps = np.array(sorted(truth))
    xs = np.array([truth[t][0] for t in stamps])
    during = [s for s in states if t0 + 500_000_000 <= s.stamp_ns <= t0 + 1_990_000_000]
    errors = [abs(s.position[0] - np.interp(s.stamp_ns, stamps, xs)) for s in during]
    assert max(errors) < 1.0  # never pulled towards the foreign poses, 100 m away
    # every estimate that says it is valid is close (a stalled replay makes some drift, invalid:
    # seen once in a clean-clone run, 12 cm while the replay thread stalled)
    assert max(e for e, s in zip(errors, during) if s.valid) < 0.05
    # most say they are valid (a replay thread stalled by a loaded machine makes some honestly
    # invalid), and none of those is far off: the foreign stream never captured it
    assert sum(s.valid for s in during) >= 0.5 * len(during)
    # after the replay the IMU is gone: the predictions drift, and say so
    assert not states[-1].valid
    refused = status.counters.get("est.pose_outliers", 0) + status.counters.get("est.pose_future", 0)
    assert refused >= 0.95 * len(sent), (refused, len(sent), status.counters)
    assert status.counters.get("est.pose_outliers", 0) > 0.5 * len(sent)
    assert status.extra["est.pose_fused"] >= 150  # the real poses: 200 sent, the last few still pending


def test_imu_samples_stamped_an_hour_away_are_refused_and_counted(zenoh_router):
    """IMU samples stamped 1 h in the past (before the first real one) or 1 h in the future
    (amid the real ones), and poses 1 h ahead, are refused against their arrival time and
    counted; the estimate goes on undisturbed (the old estimator took the future IMU sample
    and refused every real one after it as out of order)."""
    hour = 3600 * 1_000_000_000
    sent = {"future": 0, "past": 0, "pose": 0}

    def wrong_clock(client, t0: int, stop: threading.Event) -> None:
        imu_key, pose_key = TOPICS["imu"].key(NS_KEY), TOPICS["pose"].key(NS_KEY)

        def imu(stamp: int) -> bytes:
            return m.encode(m.ImuSample(stamp_ns=stamp, quat=[1.0, 0, 0, 0], gyro=[3.0, 0.0, 0.0], accel=[0.0, 50.0, 9.8]))

        # before the first real sample: an hour-old one would start the filter an hour back
        for _ in range(20):
            client.put(imu_key, imu(max(time.monotonic_ns() - hour, 1)))  # the clock may be younger than an hour
            sent["past"] += 1
            time.sleep(0.005)
        time.sleep(max(0.0, (t0 + 400_000_000 - time.monotonic_ns()) / 1e9))
        for k in range(20):
            if stop.is_set():
                return
            now = time.monotonic_ns()
            client.put(imu_key, imu(now + hour))
            sent["future"] += 1
            if k % 5 == 0:
                client.put(pose_key, m.encode(m.PoseMeasurement(stamp_ns=now + hour, position=[5.0, 0.0, 0.5],
                                                                 quat=[1.0, 0, 0, 0])))
                sent["pose"] += 1
            time.sleep(0.04)

    states, truth, status, t0 = _run_with_attacker(zenoh_router, wrong_clock)
    assert sent["future"] == sent["past"] == 20
    assert status.counters.get("est.imu_future") == sent["future"], status.counters
    assert status.counters.get("est.imu_past") == sent["past"], status.counters
    assert status.counters.get("est.pose_future") == sent["pose"], status.counters
    assert _median_error(states, truth, t0) < 0.01
    assert all(s.stamp_ns < t0 + 3 * 1_000_000_000 for s in states)  # never stamped an hour ahead


@pytest.mark.parametrize("field, value", [("rt_priority", 10), ("cpu", 1), ("rate_hz", 500.0)])
def test_loop_scheduling_and_rate_are_refused_live_and_named(field, value):
    params = EstimatorParams()
    service = EstimatorService(ns=NS_KEY, endpoint="tcp/127.0.0.1:1", params={"estimator": params}, clock=WallClock())
    with pytest.raises(ValueError, match=f"estimator.{field}.*restart"):
        service.set_params({f"estimator.{field}": value})
    assert service.params["estimator"] is params


# real time: loops at their rate, processes and Zenoh over loopback share two loaded cores
pytestmark = pytest.mark.timing_sensitive(reason="real-time loops, processes or Zenoh over loopback on a shared host")
