"""At most one live instance of a service per namespace, and one commander on the motors (issue 14)."""

from __future__ import annotations

import pytest

import asyncio
import os
import signal
import socket
import subprocess
import sys
import time

import zenoh

from onboard.contracts import messages as m
from onboard.contracts.commander import (FOREIGN_COMMANDER, NO_LIVE_COMMANDER, RESTART_GAP_NS, SECOND_STREAM, UNKNOWN_COMMANDER,
                                        CommanderLatch)
from onboard.contracts.params import SafetyLimits, TwinParams
from onboard.contracts.topics import TOPICS, liveliness_key
from services.runtime.service import EXIT_CONFLICT, StandInCommander
from services.runtime.zenoh_session import open_session
from services.twin import TwinService
from helpers import wait_for

START_TIMEOUT_S = 60.0


# --- the rule ---------------------------------------------------------------------------------------


def test_the_latch_obeys_only_the_live_identified_commander() -> None:
    latch = CommanderLatch()
    assert latch.refusal("a", 1, 0) == NO_LIVE_COMMANDER  # no token: nobody's commander
    latch.commander_appeared()
    assert latch.refusal("a", 1, 0) == UNKNOWN_COMMANDER  # alive, status not heard yet
    assert latch.commander_identified("a")
    assert latch.refusal("a", 1, 0) is None
    assert latch.refusal("b", 2, 0) == FOREIGN_COMMANDER and latch.refusal("", 2, 0) == FOREIGN_COMMANDER
    assert not latch.commander_identified("b")  # a second instance answering keeps nothing
    assert latch.refusal("b", 2, 0) == FOREIGN_COMMANDER
    latch.commander_gone()  # the takeover needs the first one gone
    assert latch.refusal("a", 2, 0) == NO_LIVE_COMMANDER
    latch.commander_appeared()
    assert latch.commander_identified("b") and latch.refusal("b", 1, 0) is None and latch.refusal("a", 2, 0) == FOREIGN_COMMANDER
    assert latch.latches == 2
    assert latch.refused == {NO_LIVE_COMMANDER: 2, UNKNOWN_COMMANDER: 1, FOREIGN_COMMANDER: 4, SECOND_STREAM: 0}


def test_the_live_commanders_id_copied_into_a_second_stream_is_refused() -> None:
    """The id is in every payload: a copier has it. Its commands are refused as a second stream
    (a number not after the last obeyed) while the real stream runs; a stream that stopped for
    a restart of the loop may start again from 1."""
    latch = CommanderLatch()
    latch.commander_appeared()
    latch.commander_identified("a")
    ms = 1_000_000
    assert [latch.refusal("a", seq, seq * ms) for seq in (1, 2, 3)] == [None] * 3
    assert latch.refusal("a", 3, 3 * ms) == SECOND_STREAM  # a replay of the last one
    assert latch.refusal("a", 2, 4 * ms) == SECOND_STREAM  # an older one
    assert latch.refusal("a", 4, 4 * ms) is None  # the real stream goes on
    assert latch.refusal("a", 5, 5 * ms) is None and latch.refusal("a", 5, 5 * ms) == SECOND_STREAM  # interleaved copies
    assert latch.refusal("a", 7, 6 * ms) is None  # a dropped command is a gap, not a second stream
    quiet = 6 * ms + RESTART_GAP_NS
    assert latch.refusal("a", 1, quiet - 1) == SECOND_STREAM
    assert latch.refusal("a", 1, quiet) is None and latch.refusal("a", 2, quiet + ms) is None  # the loop restarted
    assert latch.refused[SECOND_STREAM] == 4


# --- one instance per service ---------------------------------------------------------------------


def test_a_third_control_service_is_refused_naming_the_first(zenoh_router) -> None:
    """The second instance of control is its hot standby (issue 30: it publishes nothing until the first
    one's token goes, tests/test_standby.py); a third is refused, naming the first."""
    ns = f"archer/twice{os.getpid()}"
    argv = [sys.executable, "-m", "services.cli.main", "run", "control", "--endpoint", zenoh_router, "--namespace", ns, "--log-level", "WARNING"]
    first = subprocess.Popen(argv, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    standby = None
    session = open_session(zenoh_router, "client")

    def wait_token(name: str, proc: subprocess.Popen) -> None:
        deadline = time.monotonic() + START_TIMEOUT_S
        while not any(r.ok is not None for r in session.liveliness().get(liveliness_key(ns, name), timeout=1.0)):
            assert proc.poll() is None and time.monotonic() < deadline, f"{name} did not start"
            time.sleep(0.1)

    try:
        wait_token("control", first)
        standby = subprocess.Popen(argv, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
        wait_token("control_standby", standby)
        third = subprocess.run(argv, capture_output=True, text=True, timeout=START_TIMEOUT_S)
        assert third.returncode == EXIT_CONFLICT
        assert "control already runs" in third.stderr and "with its standby" in third.stderr
        assert f"pid {first.pid}" in third.stderr and f"host {socket.gethostname()}" in third.stderr
        assert "started 20" in third.stderr  # the first one's start time, as a date
        assert first.poll() is None and standby.poll() is None, "the refused one must not disturb the running ones"
    finally:
        session.close()
        for proc in (standby, first):
            if proc is not None and proc.poll() is None:
                proc.send_signal(signal.SIGTERM)
        for proc in (standby, first):
            if proc is not None:
                proc.wait(timeout=10)
    assert first.returncode == 0 and standby.returncode == 0


# --- forged commands never reach the motors ------------------------------------------------------


def test_the_twin_counts_and_never_applies_a_forged_commanders_torques(zenoh_router) -> None:
    ns = f"archer/forge{os.getpid()}"

    async def scenario() -> None:
        twin = TwinService(ns=ns, endpoint=zenoh_router, params={"twin": TwinParams(scenario="hop-in-place", seed=0), "safety": SafetyLimits()})
        task = asyncio.create_task(twin.run())
        client = open_session(zenoh_router, "peer")
        key = TOPICS["torque_cmd"].key(ns)
        wheel_dofs = []

        def wheel_speed() -> float:
            return max(abs(float(twin.data.qvel[d])) for d in wheel_dofs)

        seqs: dict[str, int] = {}

        def put(commander: str, torque: float) -> None:
            seqs[commander] = seqs.get(commander, 0) + 1  # each sender numbers its own stream
            client.put(key, m.encode(m.TorqueCommand(seq=seqs[commander], stamp_ns=time.monotonic_ns(), wheel_torque=[torque] * 3,
                                                     foot_torque=torque, armed=True, commander=commander)),
                       congestion_control=zenoh.CongestionControl.BLOCK)  # every one arrives: the count is exact

        sent: dict[str, int] = {}

        async def stream(seconds: float, *senders: tuple[str, float]) -> float:
            """Every sender at about 1 kHz; returns the largest wheel speed seen meanwhile."""
            fastest = 0.0
            t0 = time.monotonic()
            while time.monotonic() - t0 < seconds:
                for commander, torque in senders:
                    put(commander, torque)
                    sent[commander] = sent.get(commander, 0) + 1
                fastest = max(fastest, wheel_speed())
                await asyncio.sleep(0.001)
            return fastest

        legit = StandInCommander(client, ns)
        try:
            await wait_for(lambda: twin.state == "running")
            wheel_dofs.extend(int(twin.model.joint(j).dofadr[0]) for j in ("wheel_x", "wheel_y", "wheel_z"))
            await wait_for(lambda: twin.commander_latch is not None and twin.commander_latch.instance == legit.instance)
            # the real commander holds the wheels still while a forger asks for 1e9 N m, with
            # an instance id of its own and with none
            fastest = await stream(1.5, (legit.instance, 0.0), ("f0rged", 1e9), ("", 1e9))
            assert fastest < 0.5, f"a forged torque reached the wheels: {fastest:.1f} rad/s"
            forged = sent["f0rged"] + sent[""]
            await wait_for(lambda: twin.counters.get(f"rejected.{FOREIGN_COMMANDER}") >= forged)
            assert twin.counters.get(f"rejected.{FOREIGN_COMMANDER}") == forged  # every forged one, no real one
            assert twin.actuation.counters["applied"] > 100
            assert twin.actuation.last_applied == (0.0, 0.0, 0.0, 0.0)

            # a copier: the live commander's id and the number of its last command, asking 1e9 N m
            copied_before = twin.counters.get(f"rejected.{SECOND_STREAM}")
            copies, fastest, t0 = 0, 0.0, time.monotonic()
            while time.monotonic() - t0 < 1.0:
                put(legit.instance, 0.0)
                client.put(key, m.encode(m.TorqueCommand(seq=seqs[legit.instance], stamp_ns=time.monotonic_ns(), wheel_torque=[1e9] * 3,
                                                         foot_torque=1e9, armed=True, commander=legit.instance)),
                           congestion_control=zenoh.CongestionControl.BLOCK)
                copies += 1
                fastest = max(fastest, wheel_speed())
                await asyncio.sleep(0.001)
            assert fastest < 0.5, f"a copied commander's torque reached the wheels: {fastest:.1f} rad/s"
            await wait_for(lambda: twin.counters.get(f"rejected.{SECOND_STREAM}") - copied_before >= copies)
            assert twin.counters.get(f"rejected.{SECOND_STREAM}") - copied_before == copies  # every copy, no real one
            assert twin.actuation.last_applied == (0.0, 0.0, 0.0, 0.0)

            # the commander's token gone: nobody commands, the forger least of all
            legit.close()
            await wait_for(lambda: twin.commander_latch.instance is None)
            assert await stream(0.5, ("f0rged", 1e9)) < 0.5
            assert twin.counters.get(f"rejected.{NO_LIVE_COMMANDER}") > 100

            # a new commander takes over and is obeyed
            successor = StandInCommander(client, ns)
            try:
                await wait_for(lambda: twin.commander_latch.instance == successor.instance)
                assert await stream(0.5, (successor.instance, 0.05), ("f0rged", -1e9)) > 1.0  # 0.05 N m spins a wheel up
                assert twin.commander_latch.latches == 2
            finally:
                successor.close()
        finally:
            client.close()
            twin.request_stop()
            await asyncio.wait_for(task, 10.0)

    asyncio.run(scenario())


# real time: loops at their rate, processes and Zenoh over loopback share two loaded cores
pytestmark = pytest.mark.timing_sensitive(reason="real-time loops, processes or Zenoh over loopback on a shared host")
