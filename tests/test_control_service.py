"""The control service on real Zenoh over loopback: a 1 kHz loop process that arms on a
valid estimate, commands torque, publishes phase events, tube and safety trips, refuses
bad payloads, falls back to safe torque on a stale estimate and reports its timing."""

from __future__ import annotations

import pytest

import asyncio
import math
import threading
import time

import msgspec

from onboard.contracts import messages as m
from onboard.contracts.topics import TOPICS, params_key
from services.bench.control import synthetic_state
from services.runtime.peers import query_status
from services.control import ControlService
from services.runtime.zenoh_session import open_session
from helpers import wait_for

NS = "archer/test-control"



class Feeder:
    """Publishes a synthetic hop (estimate + joints) at about 1 kHz from a thread."""

    def __init__(self, session) -> None:
        self.state_key = TOPICS["state"].key(NS)
        self.joints_key = TOPICS["joints"].key(NS)
        self.session = session
        self.running = True
        self.paused = False
        self.t0 = time.monotonic()
        self.thread = threading.Thread(target=self.run, daemon=True)

    def run(self) -> None:
        while self.running:
            if not self.paused:
                st, jn = synthetic_state(time.monotonic() - self.t0, time.monotonic_ns())
                self.session.put(self.state_key, m.encode(st))
                self.session.put(self.joints_key, m.encode(jn))
            time.sleep(0.001)


def test_control_service_end_to_end(zenoh_router):
    async def scenario() -> None:
        service = ControlService(ns=NS, endpoint=zenoh_router)
        task = asyncio.create_task(service.run())
        client = open_session(zenoh_router, "peer")
        got: dict[str, list] = {"torque_cmd": [], "phase": [], "safety": [], "tube": []}
        types = {"torque_cmd": m.TorqueCommand, "phase": m.PhaseEvent, "safety": m.SafetyEvent, "tube": m.TrackingTube}
        subs = [
            client.declare_subscriber(TOPICS[name].key(NS), lambda s, n=name: got[n].append(m.decode(s.payload.to_bytes(), types[n])))
            for name in got
        ]
        feeder = Feeder(client)
        try:
            await wait_for(lambda: service.state in ("running", "degraded") and service._loop_proc is not None)
            # before any estimate: disarmed zero commands, every tick
            await wait_for(lambda: len(got["torque_cmd"]) > 50)
            assert not got["torque_cmd"][-1].armed
            assert got["torque_cmd"][-1].wheel_torque == [0.0, 0.0, 0.0]

            feeder.thread.start()
            await wait_for(lambda: any(c.armed for c in got["torque_cmd"][-20:]))
            await wait_for(lambda: {"touchdown", "liftoff", "apex"} <= {e.event for e in got["phase"]})
            assert any(e.trip == "arm" for e in got["safety"])
            n0, t0 = len(got["torque_cmd"]), time.monotonic()
            await asyncio.sleep(1.0)
            rate = (len(got["torque_cmd"]) - n0) / (time.monotonic() - t0)
            assert rate > 500.0  # nominal 1 kHz; a loaded shared machine without RT priority loses ticks
            armed = [c for c in got["torque_cmd"][-200:] if c.armed]
            assert armed and all(all(math.isfinite(v) and abs(v) <= 1.5 for v in c.wheel_torque) for c in armed)
            await wait_for(lambda: len(got["tube"]) > 0)
            assert got["tube"][-1].hops >= 1

            # a malformed and a non-finite estimate are refused and counted, never used
            key = TOPICS["state"].key(NS)
            client.put(key, b"not json")
            st, _ = synthetic_state(0.0, time.monotonic_ns())
            bad = msgspec.json.encode(st).replace(b'"foot_vel":', b'"foot_vel":1e999,"x":', 1)
            client.put(key, bad)
            await wait_for(lambda: service._loop_proc.last.get("rejected", {}).get("state", 0) >= 2)

            # the estimator dies: stale trip, then disarm after the fault bound
            feeder.paused = True
            await wait_for(lambda: any(e.trip == "estimate_lost" for e in got["safety"]))
            assert any(e.trip == "estimate_stale" for e in got["safety"])
            await asyncio.sleep(0.05)
            assert not got["torque_cmd"][-1].armed
            await wait_for(lambda: service.counters.get("trip.estimate_lost") == 1)  # logged in the parent

            # operator re-arms through the parameter queryable
            feeder.paused = False
            req = m.ParamRequest(set={"control.arm_request": 1})
            replies = await asyncio.to_thread(lambda: list(client.get(params_key(NS, "control"), payload=msgspec.json.encode(req))))
            assert replies and replies[0].ok is not None
            await wait_for(lambda: got["torque_cmd"][-1].armed)

            # status carries the loop's timing figures
            status = await asyncio.to_thread(query_status, client, NS, "control")
            assert status.extra["loop_ticks"] > 1000
            # a tick's compute: the controller step is tens of microseconds, well inside the 1 ms period
            assert 5.0 < status.extra["loop_tick_us_p50"] < 1000.0
            assert status.extra["loop_tick_us_p50"] <= status.extra["loop_tick_us_p99"] <= status.extra["loop_tick_us_max"]
            assert "loop_period_jitter_us_p99" in status.extra and "loop_overruns" in status.extra
            # and the wheels' momentum governor's state: no cap while the wheels are slow
            assert status.extra["momentum_speed_cap_m_s"] == 0.0 and status.extra["momentum_governed_hops"] == 0.0
        finally:
            proc = service._loop_proc
            feeder.running = False
            for s in subs:
                s.undeclare()
            service.request_stop()
            await asyncio.wait_for(task, 10.0)
            client.close()
        assert proc is not None and not proc.alive  # the loop process ends with the service

    asyncio.run(scenario())


# real time: loops at their rate, processes and Zenoh over loopback share two loaded cores
pytestmark = pytest.mark.timing_sensitive(reason="real-time loops, processes or Zenoh over loopback on a shared host")
