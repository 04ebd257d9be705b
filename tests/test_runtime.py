"""The service runtime on real Zenoh sessions over loopback."""

from __future__ import annotations

import asyncio
import subprocess
import sys
import threading
import time

import msgspec
import pytest

from onboard.contracts import messages as m
from onboard.contracts.topics import TOPICS, liveliness_key, params_key, status_key
from services.runtime.peers import live_services, query_status
from services.runtime.service import LazyLatestSlot, Service
from services.runtime.zenoh_session import endpoint_in_use, free_endpoint, open_session
from helpers import wait_for

NS = "archer/test"
TIMEOUT_S = 10.0


class RelayService(Service):
    """Relays IMU gyro z into a torque command: enough to exercise every runtime path."""

    name = "control"  # a torque commander: its row in the topic table may publish torque_cmd
    subscribes = ("imu",)
    params_sections = ("safety",)

    async def setup(self) -> None:
        self.imu_slot = self.latest("imu")
        self.imu_sampled = self.latest_sampled("imu")
        self.cmd = self.publisher("torque_cmd")
        self.subscribe("imu", self.on_imu)

    async def on_imu(self, msg: m.ImuSample) -> None:
        limit = self.params["safety"].wheel_torque_max
        self.cmd.put(m.TorqueCommand(wheel_torque=[0.0, 0.0, min(msg.gyro[2], limit)], foot_torque=0.0, armed=True))
        self.count("relayed")



def _imu(gz: float) -> m.ImuSample:
    return m.ImuSample(quat=[1.0, 0, 0, 0], gyro=[0.0, 0.0, gz], accel=[0.0, 0.0, 9.81])


def test_service_relays_rejects_and_reports(zenoh_router):
    async def scenario() -> None:
        service = RelayService(ns=NS, endpoint=zenoh_router)
        task = asyncio.create_task(service.run())
        client = open_session(zenoh_router, "peer")
        received: list[m.TorqueCommand] = []
        sub = client.declare_subscriber(TOPICS["torque_cmd"].key(NS), lambda s: received.append(m.decode(s.payload.to_bytes(), m.TorqueCommand)))
        try:
            await wait_for(lambda: service.state == "running")
            await asyncio.sleep(0.3)  # let the subscription reach the service
            imu_key = TOPICS["imu"].key(NS)
            client.put(imu_key, m.encode(_imu(0.5)))
            for bad in (b"garbage", b'{"quat":[1,0,0,0]}', m.encode(_imu(float("nan")))):
                client.put(imu_key, bad)
            client.put(imu_key, m.encode(_imu(99.0)))  # clamped by the safety parameter
            await wait_for(lambda: len(received) == 2)
            assert received[0].wheel_torque[2] == pytest.approx(0.5)
            assert received[1].wheel_torque[2] == pytest.approx(1.5)
            assert [r.seq for r in received] == [1, 2]
            # each bad payload counted once per subscription (slot and async handler)
            await wait_for(lambda: service.counters.get("rejected.imu") == 6)
            assert service.imu_slot.get()[0].gyro[2] == 99.0
            await wait_for(lambda: service.imu_sampled.get() is not None)
            assert service.imu_sampled.get()[0].gyro[2] == 99.0  # only what is read is decoded:
            assert service.counters.get("rejected.imu") == 6  # the bad payloads it skipped count nowhere

            # a second session sees the liveliness token and gets the status
            # liveliness propagates asynchronously: ask until the token is seen
            names: list[str] = []

            async def token_seen() -> bool:
                names[:] = await asyncio.to_thread(live_services, client, NS)
                return "control" in names

            for _ in range(10):
                if await token_seen():
                    break
            assert "control" in names
            status = await asyncio.to_thread(query_status, client, NS, "control")
            assert status.state == "running"
            assert status.counters["relayed"] == 2 and status.counters["rejected.imu"] == 6

            # parameters: a valid set applies, an invalid one is refused whole
            def ask(payload: bytes) -> m.ParamReply:
                replies = list(client.get(params_key(NS, "control"), payload=payload, timeout=5.0))
                return msgspec.json.decode(replies[0].ok.payload.to_bytes(), type=m.ParamReply)

            reply = await asyncio.to_thread(ask, b'{"set": {"safety.wheel_torque_max": 1.0}}')
            assert reply.error == "" and reply.params["safety.wheel_torque_max"] == 1.0
            reply = await asyncio.to_thread(ask, b'{"set": {"safety.wheel_torque_max": "lots"}}')
            assert "safety.wheel_torque_max" in reply.error and "expected `float`" in reply.error
            assert reply.params["safety.wheel_torque_max"] == 1.0
            reply = await asyncio.to_thread(ask, b'{"set": {"safety.no_such": 1}}')
            assert "no parameter" in reply.error
        finally:
            sub.undeclare()
            service.stopping.set()
            await asyncio.wait_for(task, 5.0)
            # the token is gone once the service stopped
            names = await asyncio.to_thread(live_services, client, NS)
            client.close()
        assert "control" not in names

    asyncio.run(asyncio.wait_for(scenario(), 60))


def test_a_sampled_slot_decodes_what_is_read_and_keeps_the_last_good_value():
    decoded: list[bytes] = []
    rejected: list[Exception] = []

    def decode(payload: bytes) -> m.ImuSample:
        decoded.append(payload)
        return m.decode(payload, m.ImuSample)

    slot = LazyLatestSlot(decode, rejected.append)
    assert slot.get() is None and slot.take() is None
    for gz in (1.0, 2.0, 3.0):
        slot.put_payload(m.encode(_imu(gz)), int(gz))
    assert slot.get()[0].gyro[2] == 3.0 and slot.get()[1] == 3 and len(decoded) == 1  # decoded once
    assert slot.take()[0].gyro[2] == 3.0 and slot.take() is None
    slot.put_payload(m.encode(_imu(float("nan"))), 4)
    assert slot.get()[0].gyro[2] == 3.0 and len(rejected) == 1  # refused, counted once, last good kept
    assert slot.get()[0].gyro[2] == 3.0 and len(rejected) == 1


def test_shutdown_leaves_no_thread_or_session(zenoh_router):
    before = set(threading.enumerate())

    async def scenario() -> Service:
        service = RelayService(ns=NS, endpoint=zenoh_router)
        task = asyncio.create_task(service.run())
        await wait_for(lambda: service.state == "running")
        service.request_stop()
        await asyncio.wait_for(task, 5.0)
        return service

    service = asyncio.run(scenario())
    assert service.session.is_closed()
    leaked = [t for t in set(threading.enumerate()) - before if t.is_alive()]
    assert leaked == []


class CrashingService(RelayService):
    async def main(self) -> None:
        raise RuntimeError("lost the device")


def test_run_until_serves_on_a_thread_of_its_own_until_the_other_thread_says_done(zenoh_router):
    """What a process running a service beside its own work does (the camera rig): the service runs
    until the event is set, then stops and closes; one that crashes ends the wait by itself."""
    done = threading.Event()
    service = RelayService(ns=NS, endpoint=zenoh_router)
    runner = threading.Thread(target=service.run_until, args=(done,))
    runner.start()
    try:
        deadline = time.monotonic() + TIMEOUT_S
        while service.state != "running" and time.monotonic() < deadline:
            time.sleep(0.05)
        assert service.state == "running" and runner.is_alive()
    finally:
        done.set()
        runner.join(TIMEOUT_S)
    assert not runner.is_alive() and service.session.is_closed()

    crashing = CrashingService(ns=NS, endpoint=zenoh_router)
    with pytest.raises(RuntimeError, match="lost the device"):
        crashing.run_until(threading.Event())  # nobody will set it
    assert "lost the device" in crashing.last_error


def test_sigterm_stops_a_service_process():
    """`archer run router` serves the endpoint; a client finds it; SIGTERM ends it cleanly."""
    endpoint = free_endpoint()
    proc = subprocess.Popen(
        [sys.executable, "-m", "services.cli.main", "run", "router", "--endpoint", endpoint, "--namespace", NS],
        stderr=subprocess.DEVNULL,
    )
    deadline = time.monotonic() + TIMEOUT_S
    while not endpoint_in_use(endpoint):
        assert time.monotonic() < deadline, "router never listened"
        time.sleep(0.05)
    client = open_session(endpoint, "client")
    try:
        deadline = time.monotonic() + TIMEOUT_S
        while "router" not in live_services(client, NS):
            assert time.monotonic() < deadline, "service never announced itself"
            time.sleep(0.1)
        proc.terminate()
        assert proc.wait(timeout=5.0) == 0
    finally:
        client.close()
        if proc.poll() is None:
            proc.kill()


def test_keys_come_from_the_table():
    assert liveliness_key(NS, "x") == "archer/test/alive/x"
    assert status_key(NS, "x").startswith(NS + "/")


# real time: loops at their rate, processes and Zenoh over loopback share two loaded cores
pytestmark = pytest.mark.timing_sensitive(reason="real-time loops, processes or Zenoh over loopback on a shared host")


def test_loop_statistics_say_which_ticks_they_cover_and_keep_every_ticks_maximum():
    """Percentiles over the ring of recent ticks (``window`` of them), maxima and overruns over every
    tick: a spike that has left the ring is still the maximum."""
    from services.runtime.realtime import LoopRecorder

    rec = LoopRecorder(capacity=100)
    rec.record(late_s=5e-3, compute_s=9e-4, overrun=True)  # early spike
    for _ in range(250):
        rec.record(late_s=1e-5, compute_s=1e-4, overrun=False)
    st = rec.stats()
    assert st.ticks == 251 and st.window == 100 and st.overruns == 1
    assert st.tick_us_p99 == pytest.approx(100.0) and st.period_jitter_us_p99 == pytest.approx(10.0)
    assert st.tick_us_max == pytest.approx(900.0) and st.period_jitter_us_max == pytest.approx(5000.0)
    assert rec.stats(last=10).window == 10
