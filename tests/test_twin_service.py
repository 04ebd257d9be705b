"""The real-time twin service on a real Zenoh router over loopback."""

from __future__ import annotations

import asyncio
import time

import msgspec
import pytest

from onboard.contracts import messages as m
from onboard.contracts.binary_messages import decode_depth
from onboard.contracts.params import SafetyLimits, TwinParams
from onboard.contracts.topics import TOPICS
from services.runtime.peers import query_status
from services.runtime.service import StandInCommander
from services.runtime.zenoh_session import open_session
from services.twin import ScenarioReferenceService, TwinService
from helpers import wait_for

NS = "archer/twintest"
TIMEOUT_S = 10.0



def test_twin_publishes_sensors_applies_commands_and_zeroes_stale_ones(zenoh_router) -> None:
    async def scenario() -> None:
        twin = TwinService(ns=NS, endpoint=zenoh_router,
                           params={"twin": TwinParams(scenario="forest", seed=2, depth_rate_hz=5.0), "safety": SafetyLimits()})
        planner = ScenarioReferenceService(ns=NS, endpoint=zenoh_router, params={"twin": TwinParams(scenario="forest", seed=2)})
        tasks = [asyncio.create_task(twin.run()), asyncio.create_task(planner.run())]
        client = open_session(zenoh_router, "peer")
        got: dict[str, list] = {name: [] for name in ("imu", "joints", "pose", "depth", "safety", "goal", "polytopes", "reference")}
        subs = []
        for name in got:
            topic = TOPICS[name]

            def on_sample(sample, name=name, topic=topic) -> None:
                payload = sample.payload.to_bytes()
                got[name].append(decode_depth(payload) if topic.binary else m.decode(payload, topic.msg_type))

            subs.append(client.declare_subscriber(topic.key(NS), on_sample))
        cmd_key = TOPICS["torque_cmd"].key(NS)
        commander = StandInCommander(client, NS)
        try:
            await wait_for(lambda: twin.state == "running" and len(got["imu"]) > 50)
            t0 = time.monotonic()
            while time.monotonic() - t0 < 0.4:  # commands at about 500 Hz: wheel x spins up
                client.put(cmd_key, m.encode(m.TorqueCommand(seq=commander.next_seq(), stamp_ns=time.monotonic_ns(), wheel_torque=[0.05, 0.0, 0.0],
                                                             foot_torque=0.0, armed=True, commander=commander.instance)))
                await asyncio.sleep(0.002)
            spin = twin.data.qvel[twin.model.joint("wheel_x").dofadr[0]]
            assert spin > 0.5  # 0.05 N m on the wheel's 1.1e-3 kg m^2: 45 rad/s^2 while commands are fresh
            await asyncio.sleep(0.3)  # silence: the twin's watchdog zeroes the torque
            assert twin.actuation.last_applied == (0.0, 0.0, 0.0, 0.0)
            await wait_for(lambda: len(got["safety"]) >= 1 and len(got["goal"]) >= 1 and len(got["reference"]) >= 1)
            assert got["safety"][0].trip == "command_stale" and not got["safety"][0].armed

            status = await asyncio.to_thread(query_status, client, NS, "twin")
            assert status.extra["commands.applied"] > 100
            assert status.extra["commands.stale"] > 100
            assert 0.0 < status.extra["realtime_factor"] <= 1.05  # paced: never ahead of wall time
            assert status.extra["sim_time_s"] > 0.5 and status.extra["loop.ticks"] == pytest.approx(status.extra["sim_time_s"] * 1000, abs=50)
        finally:
            for s in subs:
                s.undeclare()
            commander.close()
            client.close()
            twin.request_stop()
            planner.request_stop()
            await asyncio.wait_for(asyncio.gather(*tasks), TIMEOUT_S)

        # every sensor arrived, stamped with its capture time and in order
        wall = twin.sim_ns / 1e9
        assert len(got["imu"]) > 0.5 * 1000 * wall
        assert len(got["pose"]) > 0.5 * 100 * wall
        assert len(got["depth"]) >= 2 and got["depth"][0].depth.shape == (48, 64)
        stamps = [s.stamp_ns for s in got["imu"]]
        assert stamps == sorted(stamps)
        assert got["goal"][0].position == pytest.approx([6.0, 0.0])
        assert len(got["polytopes"][0].polytopes) == len(twin.scenario.obstacles)
        assert got["reference"][0].segments[0].control_points[0] == pytest.approx([0.0, 0.0])
        summary = twin.summary()
        assert summary["sim_time_s"] > 0.5 and summary["falls"] == 0

    asyncio.run(scenario())


def test_setting_the_seed_puts_a_fallen_robot_back_and_other_twin_parameters_are_refused(zenoh_router) -> None:
    from onboard.contracts.topics import params_key
    from robot_description import params as rd

    async def scenario() -> None:
        twin = TwinService(ns=NS, endpoint=zenoh_router, params={"twin": TwinParams(noise=False), "safety": SafetyLimits()})
        task = asyncio.create_task(twin.run())
        client = open_session(zenoh_router, "peer")
        cmd_key = TOPICS["torque_cmd"].key(NS)

        def set_params(changes: dict) -> m.ParamReply:
            body = msgspec.json.encode(m.ParamRequest(set=changes))
            reply = next(r.ok for r in client.get(params_key(NS, "twin"), payload=body, timeout=5.0) if r.ok is not None)
            return msgspec.json.decode(reply.payload.to_bytes(), type=m.ParamReply)

        try:
            await wait_for(lambda: twin.state == "running" and twin.sim_ns > 0)
            deadline = time.monotonic() + 10.0
            while not twin.metrics.fell:  # full torque on one wheel: the body spins the other way and falls
                assert time.monotonic() < deadline, "the robot did not fall"
                client.put(cmd_key, m.encode(m.TorqueCommand(stamp_ns=time.monotonic_ns(), wheel_torque=[1.5, 0.0, 0.0],
                                                             foot_torque=0.0, armed=True)))
                await asyncio.sleep(0.002)
            assert twin.metrics.falls == 1

            refused = await asyncio.to_thread(set_params, {"twin.variant": "sim15nm"})
            assert "fixed while the twin runs" in refused.error and refused.params["twin.variant"] == "indoor"
            await asyncio.sleep(0.2)
            assert twin.metrics.fell and twin.counters.get("put_back") == 0

            reply = await asyncio.to_thread(set_params, {"twin.seed": 3})
            assert reply.error == "" and reply.params["twin.seed"] == 3
            await wait_for(lambda: twin.counters.get("put_back") == 1, timeout_s=5.0)
            await asyncio.sleep(0.05)  # a few ticks of no command: at rest over the start
            root = twin.model.joint(rd.ROOT_JOINT).qposadr[0]
            qpos = twin.data.qpos[root:root + 7]
            assert abs(qpos[0]) < 0.01 and abs(qpos[1]) < 0.01 and qpos[3] > 0.999  # upright over the start
            assert twin.metrics.falls == 1 and twin.sensors is not None  # the fall stays counted
            status = await asyncio.to_thread(query_status, client, NS, "twin")
            assert status.counters["put_back"] == 1 and status.extra["falls"] == 1.0
        finally:
            client.close()
            twin.request_stop()
            await asyncio.wait_for(task, TIMEOUT_S)

    asyncio.run(scenario())


# real time: loops at their rate, processes and Zenoh over loopback share two loaded cores
pytestmark = pytest.mark.timing_sensitive(reason="real-time loops, processes or Zenoh over loopback on a shared host")
