"""The ``hardware`` service: its watchdog, faults to topics, recovery by parameter, both backends.

Real Zenoh on loopback, the emulated drives on python-can's virtual bus or as an
``archer emulate drives`` process, the emulated Teensy on a pty.
"""

from __future__ import annotations

import asyncio
import json
import subprocess
import sys
import threading
import time
import uuid

import can
import msgspec
import pytest
import zenoh

from drivers.elmo import codec as c
from drivers.elmo.emulator import VirtualBusRunner, make_emulator
from drivers.teensy.emulator import TeensyEmulator
from onboard.contracts import messages as m
from onboard.contracts.params import HardwareParams, SafetyLimits
from onboard.contracts.topics import TOPICS, params_key, status_key
from services.bench.hardware import EMULATOR_RT_PRIORITY, budget
from services.hardware import CanBackend, CommandGate, HardwareService, gear_ratios
from services.runtime.service import StandInCommander
from services.runtime.zenoh_session import open_session

NS = "archer/hwtest"
SAFETY = SafetyLimits()
# The drives and the host in one process on a loaded 2-core CI host: a thread starved past the
# robot's 100 ms latched "heartbeat lost" / "feedback lost" (seen in CI). Those bounds have their
# own tests (test_elmo_drive.py); here they only need to hold a running bus.
BUS_SAFETY = SafetyLimits(heartbeat_timeout_s=1.0)
STALE_NS = int(SAFETY.command_stale_s * 1e9)
SLACK_S = 0.15  # scheduling on a loaded 2-core machine
TIMEOUT_S = 30.0  # an event wait returns when it happens: the bound is for a loaded machine


# --- the command gate (pure) ----------------------------------------------------------------


def cmd(*torques: float, armed: bool = True) -> m.TorqueCommand:
    return m.TorqueCommand(wheel_torque=list(torques[:3]), foot_torque=torques[3], armed=armed)


def test_gate_zero_until_a_command_then_fresh_commands_pass() -> None:
    gate = CommandGate(SAFETY)
    assert gate.gate(None, 0, 10**9, [0.0] * 3) == ((0.0,) * 4, False, False)
    torques, armed, tripped = gate.gate(cmd(0.1, -0.2, 0.3, 4.0), 10**9, 10**9 + STALE_NS // 2, [0.0] * 3)
    assert armed and not tripped and torques == pytest.approx((0.1, -0.2, 0.3, 4.0))


def test_gate_stale_command_trips_once_and_zeroes() -> None:
    gate = CommandGate(SAFETY)
    t = 10**9
    gate.gate(cmd(0.5, 0.5, 0.5, 0.5), t, t, [0.0] * 3)
    assert gate.gate(cmd(0.5, 0.5, 0.5, 0.5), t, t + STALE_NS, [0.0] * 3)[1]  # at the bound: still fresh
    torques, armed, tripped = gate.gate(cmd(0.5, 0.5, 0.5, 0.5), t, t + STALE_NS + 1, [0.0] * 3)
    assert torques == (0.0,) * 4 and not armed and tripped
    assert gate.gate(cmd(0.5, 0.5, 0.5, 0.5), t, t + 2 * STALE_NS, [0.0] * 3)[2] is False  # reported once
    assert gate.trips == 1
    assert gate.gate(cmd(0.5, 0.5, 0.5, 0.5), t + 3 * STALE_NS, t + 3 * STALE_NS, [0.0] * 3)[1]  # fresh again


def test_gate_clamps_to_the_safety_limits_and_respects_wheel_speed() -> None:
    gate = CommandGate(SAFETY)
    t = 10**9
    torques, armed, _ = gate.gate(cmd(9.0, -9.0, 0.2, -99.0), t, t, [0.0] * 3)
    assert torques == (SAFETY.wheel_torque_max, -SAFETY.wheel_torque_max, 0.2, -SAFETY.foot_torque_max)
    assert gate.clamped == 3
    fast = SAFETY.wheel_speed_max + 1.0
    torques, _, _ = gate.gate(cmd(0.5, -0.5, -0.5, 0.0), t, t, [fast, fast, -fast])
    assert torques[:3] == (0.0, -0.5, 0.0)  # braking is allowed, driving further is not
    assert gate.speed_limited == 2
    assert gate.gate(cmd(0.5, 0.5, 0.5, 0.5, armed=False), t, t, [0.0] * 3)[:2] == ((0.0,) * 4, False)


# --- the service with the emulated drives ------------------------------------------------------


class Commander:
    """Publishes armed torque commands at about 1 kHz from a thread (a stand-in for control)."""

    def __init__(self, session, torques=(0.3, -0.3, 0.2, 1.0)) -> None:
        self.identity = StandInCommander(session, NS)
        self.pub = session.declare_publisher(TOPICS["torque_cmd"].key(NS))
        self.torques = torques
        self.armed = True
        self.running = threading.Event()
        self._stop = threading.Event()
        self.seq = 0
        self.last_put = 0.0
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            if self.running.is_set():
                self.seq += 1
                t = self.torques
                self.pub.put(m.encode(m.TorqueCommand(seq=self.seq, stamp_ns=time.monotonic_ns(), wheel_torque=list(t[:3]), foot_torque=t[3], armed=self.armed,
                                                      commander=self.identity.instance)))
                self.last_put = time.monotonic()
            time.sleep(0.001)

    def close(self) -> None:
        self._stop.set()
        self._thread.join(1.0)
        self.pub.undeclare()
        self.identity.close()


async def wait_for(predicate, timeout_s: float = TIMEOUT_S) -> float:
    t0 = time.monotonic()
    while not predicate():
        if time.monotonic() - t0 > timeout_s:
            raise AssertionError("condition not met in time")
        await asyncio.sleep(0.002)
    return time.monotonic() - t0


def query(session, key: str, payload: bytes | None = None) -> dict:
    for reply in session.get(key, payload=payload, timeout=5.0):
        if reply.ok is not None:
            return msgspec.json.decode(reply.ok.payload.to_bytes())
    raise AssertionError(f"no reply from {key}")


def test_service_drives_the_emulated_drives_and_trips_its_watchdog_and_reports_faults(zenoh_router) -> None:
    channel = f"hw-{uuid.uuid4().hex}"
    params = HardwareParams()
    emu_bus = can.Bus(interface="virtual", channel=channel)
    host_bus = can.Bus(interface="virtual", channel=channel)
    emulator = make_emulator(params)
    runner = VirtualBusRunner(emulator, emu_bus).start()
    backend = CanBackend(params, BUS_SAFETY, gear_ratios(), bus=host_bus)
    service = HardwareService(ns=NS, endpoint=zenoh_router, backend=backend)
    client = open_session(zenoh_router, "peer")
    joints: list[m.JointSensors] = []
    events: list[m.SafetyEvent] = []
    subs = [
        client.declare_subscriber(TOPICS["joints"].key(NS), lambda s: joints.append(m.decode(s.payload.to_bytes(), m.JointSensors))),
        client.declare_subscriber(TOPICS["safety"].key(NS), lambda s: events.append(m.decode(s.payload.to_bytes(), m.SafetyEvent))),
    ]
    commander = Commander(client)

    def applied() -> list[float]:
        return [d.applied_torque for d in emulator.drives]

    def driving() -> bool:
        """Every drive enabled and driving: the foot at its command, each wheel at its command or,
        held at its speed limit, at zero (0.3 N m takes the emulated wheel there in under a second)."""
        if not all(d.state == c.DriveState.OPERATION_ENABLED for d in emulator.drives):
            return False
        *wheels, foot = applied()
        return foot != 0.0 and all(t == 0.0 or t == pytest.approx(want, abs=0.002) for t, want in zip(wheels, commander.torques))

    async def scenario() -> None:
        task = asyncio.create_task(service.run())
        try:
            await wait_for(lambda: service.state == "running")
            commander.running.set()
            await wait_for(lambda: all(t != 0.0 for t in applied()))
            assert applied() == pytest.approx([0.3, -0.3, 0.2, 1.0 / 3.0], abs=0.002)
            await wait_for(lambda: len(joints) > 50)
            j = joints[-1]
            assert j.wheel_torque == pytest.approx([0.3, -0.3, 0.2], abs=0.004) and j.foot_sensed is False
            assert j.stamp_ns > 0 and joints[-1].seq > joints[0].seq

            # a forged commander at 1 kHz, armed, asking for 1e9 N m: counted, never applied
            forged = m.TorqueCommand(wheel_torque=[1e9] * 3, foot_torque=1e9, armed=True, commander="f0rged")
            t0, sent = time.monotonic(), 0
            while time.monotonic() - t0 < 0.5:
                forged.stamp_ns = time.monotonic_ns()
                client.put(TOPICS["torque_cmd"].key(NS), m.encode(forged), congestion_control=zenoh.CongestionControl.BLOCK)
                sent += 1
                # the real commander's torques, or less where a wheel reached its speed limit
                assert all(abs(a) <= legit + 0.002 for a, legit in zip(applied(), (0.3, 0.3, 0.2, 1.0 / 3.0)))
                await asyncio.sleep(0.001)
            await wait_for(lambda: service.counters.get("rejected.foreign_commander") >= sent)
            assert service.counters.get("rejected.foreign_commander") == sent  # every one of them

            # stale commands: the service's own watchdog zeroes the motors within its bound
            commander.running.clear()
            last = commander.last_put
            await wait_for(lambda: applied() == [0.0] * 4, SAFETY.command_stale_s + SLACK_S)
            assert time.monotonic() - last <= SAFETY.command_stale_s + SLACK_S
            await wait_for(lambda: any(e.trip == "command_stale" for e in events))
            # disabled, not faulted: the trip's event can reach the test before the drives have taken the disable
            await wait_for(lambda: all(d.state == c.DriveState.READY_TO_SWITCH_ON for d in emulator.drives))
            commander.running.set()  # fresh armed commands re-enable: staleness is not a fault
            await wait_for(driving)

            # a drive fault: latched, reported on the safety topic and in the status, all motors off
            emulator.emcy_fault(2, 0x2340, c.ErrorRegister.CURRENT)
            await wait_for(lambda: any(e.trip.startswith("hardware_fault: node 2 EMCY 0x2340") for e in events))
            await wait_for(lambda: applied() == [0.0] * 4, 0.5)
            status = await asyncio.to_thread(query, client, status_key(NS, "hardware"))
            assert "node 2" in status["last_error"] and status["extra"]["hw.faults"] >= 1
            assert status["extra"]["watchdog.trips"] >= 1 and status["extra"]["hw.ticks"] > 50
            await asyncio.sleep(0.2)
            assert applied() == [0.0] * 4  # fresh armed commands do not clear a latched fault

            # recovery on command: the operator sets hardware.recover_request
            reply = await asyncio.to_thread(query, client, params_key(NS, "hardware"), msgspec.json.encode({"set": {"hardware.recover_request": 1}}))
            assert reply["error"] == ""
            await wait_for(driving)
            assert not backend.faults
        finally:
            commander.running.clear()
            service.request_stop()
            await asyncio.wait_for(task, 10)

    try:
        asyncio.run(scenario())
    finally:
        commander.close()
        for s in subs:
            s.undeclare()
        client.close()
        runner.stop()
        emu_bus.shutdown()
        host_bus.shutdown()
    assert runner.error is None
    assert all(d.nmt == c.NmtState.PRE_OPERATIONAL for d in emulator.drives)  # stopped cleanly


def test_service_with_the_teensy_publishes_imu_and_reports_a_vanished_port(zenoh_router, tmp_path) -> None:
    emulator = TeensyEmulator(HardwareParams(), gear_ratios(), link_dir=str(tmp_path)).start()
    params = HardwareParams(backend="teensy", serial_port=emulator.port)
    service = HardwareService(ns=NS, endpoint=zenoh_router, params={"hardware": params, "safety": SAFETY})
    client = open_session(zenoh_router, "peer")
    imu: list[m.ImuSample] = []
    events: list[m.SafetyEvent] = []
    subs = [
        client.declare_subscriber(TOPICS["imu"].key(NS), lambda s: imu.append(m.decode(s.payload.to_bytes(), m.ImuSample))),
        client.declare_subscriber(TOPICS["safety"].key(NS), lambda s: events.append(m.decode(s.payload.to_bytes(), m.SafetyEvent))),
    ]
    commander = Commander(client, torques=(0.4, 0.0, -0.4, 2.0))

    async def scenario() -> None:
        task = asyncio.create_task(service.run())
        try:
            await wait_for(lambda: service.state == "running")
            commander.running.set()
            await wait_for(lambda: emulator.applied == pytest.approx([0.4, 0.0, -0.4, 2.0]))
            await wait_for(lambda: len(imu) > 20)
            assert imu[-1].accel[2] == pytest.approx(9.81) and imu[-1].quat == [1.0, 0.0, 0.0, 0.0]
            emulator.unplug()
            await wait_for(lambda: any("vanished" in e.trip for e in events))
            await wait_for(lambda: emulator.applied == [0.0] * 4, 0.1 + SLACK_S)  # the Teensy's own watchdog
        finally:
            commander.running.clear()
            service.request_stop()
            await asyncio.wait_for(task, 10)

    try:
        asyncio.run(scenario())
    finally:
        commander.close()
        for s in subs:
            s.undeclare()
        client.close()
        emulator.stop()


def test_four_drives_at_1khz_through_the_service_short_run(zenoh_router) -> None:
    """The CI-sized version of ``archer bench hardware`` (60 s): processes as on the robot."""
    # the emulated drives above the service's loop, as in the bench: silicon never waits for the host
    emulate = ["emulate", "drives", "--rt-priority", str(EMULATOR_RT_PRIORITY)]
    proc = subprocess.Popen([sys.executable, "-m", "services.cli.main", *emulate], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    info = json.loads(proc.stdout.readline())
    bus = info["bus"]
    params = HardwareParams(can_interface=bus["interface"], can_channel=bus["channel"], can_host=bus["host"], can_port=bus["port"])
    service = HardwareService(ns=NS, endpoint=zenoh_router, params={"hardware": params, "safety": SAFETY})
    client = open_session(zenoh_router, "peer")
    commander = Commander(client)

    async def scenario() -> dict:
        task = asyncio.create_task(service.run())
        try:
            await wait_for(lambda: service.state == "running", 20.0)
            commander.running.set()
            await asyncio.sleep(0.3)
            group = service.backend.group
            before, nodes_before = service.backend.summary(), dict(group.stats.per_node_missed)
            await asyncio.sleep(2.0)
            after, nodes_after = service.backend.summary(), dict(group.stats.per_node_missed)
            delta = {k: after[k] - before.get(k, 0) for k in after}
            delta["per_node_missed"] = {n: nodes_after[n] - nodes_before.get(n, 0) for n in nodes_after}
            return delta
        finally:
            commander.running.clear()
            service.request_stop()
            await asyncio.wait_for(task, 10)

    try:
        delta = asyncio.run(scenario())
    finally:
        commander.close()
        client.close()
        proc.terminate()
        proc.communicate(timeout=10)
    expected = delta["feedback_ok"] + delta["feedback_missed"]
    assert delta["ticks"] > 1000  # at least half the nominal rate on a loaded machine
    assert abs(expected - 4 * delta["ticks"]) <= 8  # snapshots taken while the loop runs
    # every drive answers every SYNC on the virtual bus, however loaded the machine: nothing lost
    assert abs(delta["feedback_received"] - 4 * delta["ticks"]) <= 8, delta
    # Late feedback is scheduling. With the emulator a plain process, two busy loops beside the
    # test made 81 % of the answers late and CI's host 22.6 % twice; above the service's loop (as
    # the bench runs it) it is 0.2-13 % quiet (14 runs) and 3.4-5.9 % beside two busy loops (5 runs).
    # How late stays the host's figure, reported by `archer bench hardware`. What is ours is a
    # drive answering the wrong SYNC: it misses every tick, so each drive is in time on at least
    # half of them (and a drive late for longer than its heartbeat timeout latches a fault).
    assert len(delta["per_node_missed"]) == 4
    for node, missed in delta["per_node_missed"].items():
        assert missed / delta["ticks"] < 0.5, (node, delta)
    assert delta["faults_latched"] == 0
    # the load of this window's frames (not since the bus opened: start-up included) per tick, at
    # the nominal rate: a loaded host ticks fewer times a second (0.826 of the budget's time base
    # once here), which is the loop's figure, not the traffic's. 0.906-0.907 measured in 16 runs,
    # between the nominal and the worst-stuffing budget
    load = delta["bus_bits"] / delta["ticks"] * params.rate_hz / params.can_bitrate
    cyclic = budget(params)
    assert cyclic["budget_total_nominal"] < load < cyclic["budget_total_worst_stuffing"], load


# real time: loops at their rate, processes and Zenoh over loopback share two loaded cores
pytestmark = pytest.mark.timing_sensitive(reason="real-time loops, processes or Zenoh over loopback on a shared host")
