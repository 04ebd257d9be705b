"""Live parameter changes on a running control service (real Zenoh over loopback, the
loop in its own process): gains and limits are taken between two ticks with no gap in
the torque stream, bad values are refused naming the field, and what needs a new loop
process is refused while armed and applied by a restart, watchdog fed, when disarmed."""

from __future__ import annotations

import pytest

import asyncio
import contextlib
import socket
import threading
import time

import msgspec

from onboard.contracts import messages as m
from onboard.contracts.params import ControlParams, SafetyLimits
from onboard.contracts.topics import TOPICS, params_key
from services.bench.control import synthetic_state
from services.runtime.peers import query_status
from services.control import ControlService
from services.runtime.zenoh_session import open_session
from helpers import wait_for

NS = "archer/test-control-params"
# Wide estimate margins: the feeder is a thread of the test process, and its stalls on
# a loaded machine must not make the loop send safe commands, or "control never dropped"
# would test the machine rather than the parameter path.
PARAMS = {"control": ControlParams(estimate_fault_disarm_s=1.0), "safety": SafetyLimits(estimate_stale_s=0.1)}
GAP_MAX_S = 0.05  # a restart of the loop process costs seconds; a tick 1 ms
WATCHDOG_USEC = 2_000_000  # the control unit's WatchdogSec=2


class Feeder:
    """Publishes a synthetic hop in place (estimate + joints) at about 1 kHz from a thread."""

    def __init__(self, session) -> None:
        self.session = session
        self.running = True
        self.thread = threading.Thread(target=self.run, daemon=True)

    def run(self) -> None:
        state_key, joints_key = TOPICS["state"].key(NS), TOPICS["joints"].key(NS)
        t0 = time.monotonic()
        while self.running:
            st, jn = synthetic_state(time.monotonic() - t0, time.monotonic_ns())
            self.session.put(state_key, m.encode(st))
            self.session.put(joints_key, m.encode(jn))
            time.sleep(0.001)


class TorqueLog:
    """Every torque command: arrival time [s], the loop's stamp [s] (its tick), armed."""

    def __init__(self, session) -> None:
        self.commands: list[tuple[float, float, bool]] = []
        self.sub = session.declare_subscriber(TOPICS["torque_cmd"].key(NS), self._on_sample)

    def _on_sample(self, sample) -> None:
        cmd = m.decode(sample.payload.to_bytes(), m.TorqueCommand)
        self.commands.append((time.monotonic(), cmd.stamp_ns / 1e9, cmd.armed))

    def between(self, t0: float, t1: float) -> list[tuple[float, float, bool]]:
        return [c for c in list(self.commands) if t0 <= c[0] <= t1]


class WatchdogListener:
    """The service manager's notify socket: when each WATCHDOG=1 arrived."""

    def __init__(self, path: str) -> None:
        self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        self.sock.bind(path)
        self.sock.settimeout(0.05)
        self.pings: list[float] = []
        self.running = True
        self.thread = threading.Thread(target=self._collect, daemon=True)
        self.thread.start()

    def _collect(self) -> None:
        while self.running:
            try:
                data = self.sock.recv(4096)
            except TimeoutError:
                continue
            if b"WATCHDOG=1" in data.split(b"\n"):
                self.pings.append(time.monotonic())

    def close(self) -> None:
        self.running = False
        self.thread.join()
        self.sock.close()


def max_gap(commands: list[tuple[float, float, bool]], column: int) -> float:
    """The longest time between two consecutive commands: 0 arrivals, 1 the loop's ticks."""
    return max(b[column] - a[column] for a, b in zip(commands, commands[1:]))


def set_params(session, changes: dict) -> m.ParamReply:
    body = msgspec.json.encode(m.ParamRequest(set=changes))
    replies = list(session.get(params_key(NS, "control"), payload=body, timeout=5.0))
    return msgspec.json.decode(replies[0].ok.payload.to_bytes(), type=m.ParamReply)


async def ask(session, changes: dict) -> m.ParamReply:
    return await asyncio.to_thread(set_params, session, changes)



@contextlib.asynccontextmanager
async def armed_control(endpoint: str):
    """A control service armed on a fed estimate: yields it, a client session and the torque log."""
    service = ControlService(ns=NS, endpoint=endpoint, params=dict(PARAMS))
    task = asyncio.create_task(service.run())
    client = open_session(endpoint, "peer")
    torque = TorqueLog(client)
    feeder = Feeder(client)
    feeder.thread.start()
    try:
        await wait_for(lambda: getattr(service, "_loop_proc", None) is not None and service._loop_proc.last.get("armed"))
        yield service, client, torque
    finally:
        feeder.running = False
        torque.sub.undeclare()
        service.request_stop()
        await asyncio.wait_for(task, 10.0)
        client.close()

def test_a_gain_change_while_armed_is_taken_between_ticks_and_a_bad_limit_is_refused(zenoh_router):
    async def scenario() -> None:
        async with armed_control(zenoh_router) as (service, client, torque):
            proc = service._loop_proc
            pid = proc.proc.pid
            await asyncio.sleep(1.0)

            t_change = time.monotonic()
            reply = await ask(client, {"control.kp_tilt": 40.5})
            assert reply.error == "" and reply.params["control.kp_tilt"] == 40.5
            await asyncio.sleep(1.5)
            across = torque.between(t_change - 1.0, time.monotonic())
            before = torque.between(t_change - 2.0, t_change - 1.0)
            figures = (f"torque command gaps, max [ms]: loop stamps {1e3 * max_gap(across, 1):.1f} across the change, "
                       f"{1e3 * max_gap(before, 1):.1f} in the second before; arrivals {1e3 * max_gap(across, 0):.1f} "
                       f"and {1e3 * max_gap(before, 0):.1f}; {len(across)} commands, "
                       f"{sum(not armed for _, _, armed in across)} not armed")
            print(figures)
            assert service._loop_proc is proc and proc.alive and proc.proc.pid == pid, figures  # no restart
            assert max_gap(across, 1) < GAP_MAX_S, figures  # the loop ticked on through the change
            assert len(across) > 1500, figures  # control never dropped
            # Zero-torque ticks only while this test's own estimate feeder (a thread of this
            # process) stalls: seen once, 183 of 2502 after a 283 ms stall of this process in a
            # clean-clone CI run. The loop stays armed throughout (asserted below from its status).
            assert sum(not armed for _, _, armed in across) < 0.25 * len(across), figures
            # the controller in the loop process runs with the new gain (read back from it)
            await wait_for(lambda: proc.last["control"].kp_tilt == 40.5, timeout_s=5.0)
            status = await asyncio.to_thread(query_status, client, NS, "control")
            assert status.extra["params_seq_applied"] == status.extra["params_seq_sent"] == 1.0
            assert status.extra["armed"] == 1.0

            # a limit far beyond the motor is refused, naming the field; nothing changes
            reply = await ask(client, {"safety.wheel_torque_max": 1000})
            assert "safety.wheel_torque_max" in reply.error and "<= 15.0" in reply.error
            assert reply.params["safety.wheel_torque_max"] == 1.5
            reply = await ask(client, {"control.kp_tilt": 41.0, "safety.wheel_torque_max": 1000})  # all or nothing
            assert reply.error and reply.params["control.kp_tilt"] == 40.5
            await asyncio.sleep(2 * 0.5)  # two loop reports
            assert proc.last["safety"].wheel_torque_max == 1.5 and proc.last["control"].kp_tilt == 40.5
            assert proc.last["params_seq"] == 1 and proc.last["armed"]

    asyncio.run(scenario())


def test_a_restart_parameter_is_refused_while_armed_and_applied_when_disarmed_with_the_watchdog_fed(
        zenoh_router, tmp_path, monkeypatch):
    manager = WatchdogListener(str(tmp_path / "notify"))
    monkeypatch.setenv("NOTIFY_SOCKET", str(tmp_path / "notify"))
    monkeypatch.setenv("WATCHDOG_USEC", str(WATCHDOG_USEC))
    monkeypatch.delenv("WATCHDOG_PID", raising=False)

    async def scenario() -> None:
        async with armed_control(zenoh_router) as (service, client, torque):
            first = service._loop_proc

            reply = await ask(client, {"control.rate_hz": 500.0})
            assert "control.rate_hz" in reply.error and "refused while armed" in reply.error
            assert reply.params["control.rate_hz"] == 1000.0 and service._loop_proc is first

            reply = await ask(client, {"control.disarm_request": 1})
            assert reply.error == ""
            await wait_for(lambda: not first.last["armed"] and not first.last["arm_requested"])
            t_accept = time.monotonic()
            reply = await ask(client, {"control.rate_hz": 500.0})
            assert reply.error == "" and reply.params["control.rate_hz"] == 500.0
            await wait_for(lambda: service._loop_proc is not first and "armed" in service._loop_proc.last)
            second = service._loop_proc
            assert second.proc.pid != first.proc.pid and not first.alive
            assert second.last["control"].rate_hz == 500.0
            # valid estimates and auto_arm, yet the new loop stays disarmed: nobody asked it to arm
            await asyncio.sleep(1.0)
            assert not second.last["armed"] and second.last["disarm_reason"] == "parameter_restart"
            running_again = time.monotonic()
            await asyncio.sleep(1.5)
            pings = list(manager.pings)
            gaps = [b - a for a, b in zip(pings, pings[1:]) if b > t_accept and a < running_again]
            print(f"watchdog pings across the restart: max interval {max(gaps):.2f} s")
            assert max(gaps) < WATCHDOG_USEC / 1e6

            reply = await ask(client, {"control.arm_request": 1})
            assert reply.error == ""
            await wait_for(lambda: second.last["armed"])
            t0 = time.monotonic()
            await asyncio.sleep(1.0)
            rate = len(torque.between(t0, time.monotonic())) / (time.monotonic() - t0)
            assert 250.0 < rate < 600.0, rate  # the new loop runs at 500 Hz

    try:
        asyncio.run(scenario())
    finally:
        manager.close()


# real time: loops at their rate, processes and Zenoh over loopback share two loaded cores
pytestmark = pytest.mark.timing_sensitive(reason="real-time loops, processes or Zenoh over loopback on a shared host")
