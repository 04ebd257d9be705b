"""Hot standby of control and the estimator (issue 30.1): a second instance runs on the same inputs,
publishes nothing, and takes over the moment the first one's liveliness token goes; the twin's
one-commander latch re-forms on it, and the restarted ex-primary comes back as the new standby."""

from __future__ import annotations

import asyncio
import os
import signal
import subprocess
import sys
import time

import pytest

from deploy import soak_faults as sf
from onboard.contracts import messages as m
from onboard.contracts.params import SafetyLimits, TwinParams
from onboard.contracts.topics import liveliness_key
from services.control import command_step
from services.runtime.peers import query_status
from services.runtime.supervisor import process_of, sim_specs
from services.runtime.zenoh_session import open_session
from services.twin import TwinService
from helpers import wait_for

START_TIMEOUT_S = 90.0  # a control service builds its controller; two at once on a loaded 2-core machine
TAKEOVER_TIMEOUT_S = 30.0  # generous: what the figure is comes from deploy/failover_campaign.py


def run_argv(service: str, endpoint: str, ns: str) -> list[str]:
    return [sys.executable, "-m", "services.cli.main", "run", service, "--endpoint", endpoint, "--namespace", ns,
            "--log-level", "WARNING"]


def wait_status(session, ns: str, name: str, procs: list[subprocess.Popen], pred=lambda st: True,
                timeout_s: float = START_TIMEOUT_S) -> m.ServiceStatus:
    """The status of ``name`` once it answers and satisfies ``pred`` (bounded; fails if a process died)."""
    deadline = time.monotonic() + timeout_s
    while True:
        st = query_status(session, ns, name)
        if st is not None and pred(st):
            return st
        for p in procs:
            assert p.poll() is None or p.returncode == -signal.SIGKILL, f"a service exited with {p.returncode}: {p.stderr.read() if p.stderr else ''}"
        assert time.monotonic() < deadline, f"{name} did not answer as expected in {timeout_s:g} s"
        time.sleep(0.05)


def stop_all(procs: list[subprocess.Popen]) -> None:
    for p in procs:
        if p.poll() is None:
            p.send_signal(signal.SIGTERM)
    for p in procs:
        try:
            p.wait(timeout=10)
        except subprocess.TimeoutExpired:
            p.kill()
            p.wait()


def test_command_step_is_the_largest_component_change() -> None:
    a = m.TorqueCommand(wheel_torque=[0.1, -0.2, 0.0], foot_torque=1.0, armed=True)
    b = m.TorqueCommand(wheel_torque=[0.1, 0.3, 0.0], foot_torque=0.9, armed=True)
    assert command_step(a, b) == pytest.approx(0.5) and command_step(a, a) == 0.0
    s = m.AttitudeSetpoint(quat_des=[1.0, 0, 0, 0], omega_des=[0, 0, 0], torque_ff=[0, 0, 0], foot_torque=0.0, armed=True)
    assert command_step(a, s) == float("inf")  # two kinds of command: never a small step


def test_a_standby_unit_runs_a_second_instance_of_its_service_after_the_first() -> None:
    assert process_of("control_standby") == "control" and process_of("estimator_standby") == "estimator"
    assert process_of("planner_standby") == "planner_standby"  # no standby for the planner
    specs = {s.name: s for s in sim_specs(["estimator", "control", "estimator_standby", "control_standby"], "tcp/127.0.0.1:1", "archer/x")}
    assert specs["control_standby"].argv[3:5] == ("run", "control") and "control" in specs["control_standby"].after
    assert specs["estimator_standby"].argv[3:5] == ("run", "estimator") and "estimator" in specs["estimator_standby"].after


@pytest.mark.timing_sensitive(reason="two control services and the twin in real time on a loaded 2-core machine")
@pytest.mark.parametrize("target", ["service", "loop"])
def test_the_standby_takes_over_a_killed_commander_and_the_twin_obeys_it(zenoh_router, target) -> None:
    """kill -9 of the primary (or of its loop process: its parent withdraws its token at once): the
    standby declares ``control``, its status names its instance, the twin's latch re-forms on it and its
    commands reach the motors; the restarted ex-primary runs as the new standby."""
    ns = f"archer/standby{os.getpid()}{target}"
    argv = run_argv("control", zenoh_router, ns)

    async def scenario() -> None:
        twin = TwinService(ns=ns, endpoint=zenoh_router, params={"twin": TwinParams(scenario="hop-in-place", seed=0),
                                                                  "safety": SafetyLimits()})
        task = asyncio.create_task(twin.run())
        procs: list[subprocess.Popen] = []
        session = open_session(zenoh_router, "client")
        try:
            await wait_for(lambda: twin.state == "running", START_TIMEOUT_S)
            procs.append(subprocess.Popen(argv, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True))
            first = await asyncio.to_thread(wait_status, session, ns, "control", procs, lambda st: st.state != "starting")
            procs.append(subprocess.Popen(argv, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True))
            second = await asyncio.to_thread(wait_status, session, ns, "control_standby", procs,
                                             lambda st: st.extra.get("shadow_compared", 0) > 0)
            assert second.extra["standby"] == 1.0 and first.extra["standby"] == 0.0
            assert second.pid == procs[1].pid and first.pid == procs[0].pid
            latch = twin.commander_latch
            await wait_for(lambda: latch is not None and latch.instance == first.instance, TAKEOVER_TIMEOUT_S)
            slot = twin.torque_slot
            await wait_for(lambda: slot.get() is not None and slot.get()[0].commander == first.instance, TAKEOVER_TIMEOUT_S)
            # the standby publishes nothing while the primary lives: every command the twin took is the first's
            assert latch.refused["foreign_commander"] == 0 and latch.refused["commander_second_stream"] == 0

            victim = first.pid if target == "service" else sf.loop_child_pid(first.pid)
            assert victim is not None
            os.kill(victim, signal.SIGKILL)
            await wait_for(lambda: latch.instance == second.instance, TAKEOVER_TIMEOUT_S)
            await wait_for(lambda: slot.get()[0].commander == second.instance, TAKEOVER_TIMEOUT_S)
            new = await asyncio.to_thread(wait_status, session, ns, "control", procs[1:],
                                          lambda st: st.instance == second.instance and "takeover_gap_ms" in st.extra)
            assert new.pid == procs[1].pid and new.extra["standby"] == 0.0
            assert latch.latches == 2 and latch.refused["foreign_commander"] == 0
            # the ex-primary, started again (as systemd or the supervisor would), is the new standby
            if procs[0].poll() is None:  # its loop was killed: the service fails by itself
                await asyncio.to_thread(procs[0].wait, 30)
            assert procs[0].returncode != 0
            procs.append(subprocess.Popen(argv, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True))
            back = await asyncio.to_thread(wait_status, session, ns, "control_standby", procs[1:],
                                           lambda st: st.pid == procs[2].pid and st.state != "starting")
            assert back.extra.get("standby", 0.0) == 1.0
            assert latch.instance == second.instance  # the motors stay with the one that took over
        finally:
            session.close()
            await asyncio.to_thread(stop_all, procs)
            twin.request_stop()
            await asyncio.wait_for(task, 10)

    asyncio.run(scenario())


@pytest.mark.timing_sensitive(reason="two estimator services in real time on a loaded 2-core machine")
def test_the_estimator_standby_takes_over_a_killed_primary(zenoh_router) -> None:
    ns = f"archer/estsb{os.getpid()}"
    argv = run_argv("estimator", zenoh_router, ns)
    procs: list[subprocess.Popen] = []
    session = open_session(zenoh_router, "client")
    try:
        procs.append(subprocess.Popen(argv, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True))
        first = wait_status(session, ns, "estimator", procs, lambda st: st.state != "starting")
        procs.append(subprocess.Popen(argv, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True))
        second = wait_status(session, ns, "estimator_standby", procs, lambda st: st.state != "starting")
        assert second.extra.get("standby") == 1.0 and first.extra.get("standby") == 0.0
        os.kill(first.pid, signal.SIGKILL)
        new = wait_status(session, ns, "estimator", procs, lambda st: st.pid == procs[1].pid, TAKEOVER_TIMEOUT_S)
        assert new.instance == second.instance and new.extra.get("standby") == 0.0
        assert any(r.ok is not None for r in session.liveliness().get(liveliness_key(ns, "estimator"), timeout=1.0))
        assert not any(r.ok is not None for r in session.liveliness().get(liveliness_key(ns, "estimator_standby"), timeout=1.0))
    finally:
        session.close()
        stop_all(procs)
