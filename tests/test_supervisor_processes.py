"""The process supervisor: systemd's notify, ordering, watchdog, restart and stop semantics,
on real processes speaking the real notify protocol."""

from __future__ import annotations

import os
import signal
import sys
import threading
import time
from pathlib import Path

import pytest

from services.runtime.realtime import make_realtime
from services.runtime.supervisor import SUPERVISOR_RT_PRIORITY, Supervisor, UnitSpec, parse_timespan, parse_unit, sim_specs, spec_from_unit
from services.runtime.zenoh_session import free_endpoint

REPO = Path(__file__).resolve().parent.parent
TIMEOUT_S = 20.0

# A unit that behaves as told: READY (after READY_DELAY), watchdog pings every 50 ms, then
# depending on the mode it crashes, exits cleanly, stalls, or leaves a child behind.
UNIT_SCRIPT = f"""
import os, subprocess, sys, time
sys.path.insert(0, {str(REPO)!r})
from services.runtime.sd_notify import Notifier
mode = sys.argv[1]
n = Notifier()
if mode == "child-ready":
    if os.fork() == 0:
        Notifier().ready()
        os._exit(0)
    os.wait()
    while True:
        time.sleep(1)
time.sleep(float(os.environ.get("READY_DELAY", "0")))
if mode == "orphan":
    child = subprocess.Popen([sys.executable, "-c", "import signal, time; signal.signal(signal.SIGTERM, signal.SIG_IGN); time.sleep(60)"])
    open(os.environ["CHILD_PID_FILE"], "w").write(str(child.pid))
n.ready()
t0 = time.monotonic()
while True:
    if time.monotonic() - t0 > 0.3:
        if mode in ("crash", "orphan"):
            sys.exit(3)
        if mode == "exit0":
            sys.exit(0)
        if mode == "stall":
            time.sleep(60)
    n.watchdog()
    time.sleep(0.05)
"""


@pytest.fixture
def unit_script(tmp_path) -> Path:
    path = tmp_path / "unit.py"
    path.write_text(UNIT_SCRIPT)
    return path


def spec(script: Path, name: str, mode: str = "run", **kw) -> UnitSpec:
    kw.setdefault("restart_s", 0.05)
    kw.setdefault("stop_timeout_s", 2.0)
    kw.setdefault("start_timeout_s", 5.0)
    return UnitSpec(name=name, argv=(sys.executable, str(script), mode), **kw)


def wait_for(predicate, timeout_s: float = TIMEOUT_S) -> None:
    deadline = time.monotonic() + timeout_s
    while not predicate():
        assert time.monotonic() < deadline, "condition not met in time"
        time.sleep(0.02)


def events(sup: Supervisor, unit: str) -> list[str]:
    return [e.what for e in sup.events if e.unit == unit]


def test_unit_files_parse_into_the_policy_the_supervisor_applies():
    parsed = parse_unit("[Unit]\nAfter=a.service\nAfter=b.service\n# comment\n[Service]\nWatchdogSec=2s\n")
    assert parsed == {"Unit": {"After": ["a.service", "b.service"]}, "Service": {"WatchdogSec": ["2s"]}}
    assert parse_timespan("500ms") == 0.5 and parse_timespan("1min 30s") == 90.0 and parse_timespan("3") == 3.0
    assert parse_timespan("infinity") is None
    with pytest.raises(ValueError):
        parse_timespan("5 parsecs")
    control = spec_from_unit("control", ["true"])
    assert control.notify and control.notify_access == "all" and control.watchdog_s == 2.0
    assert control.restart == "on-failure" and control.restart_s == 1.0 and "estimator" in control.after
    ordered = {s.name: s for s in sim_specs(["estimator", "control", "planner"], "tcp/127.0.0.1:1", "archer/x")}
    assert ordered["control"].after == ("estimator",)  # the router and hardware are not in a sim run
    assert ordered["planner"].after == ("control",)
    nice = {name: spec_from_unit(name, ["true"]).nice for name in ("router", "control", "recorder", "perception", "planner")}
    assert nice["router"] < nice["control"] == nice["recorder"] == 0 < nice["perception"] == nice["planner"]
    # the estimator and the twin run SCHED_FIFO as whole processes: above every niced unit
    assert spec_from_unit("estimator", ["true"]).fifo_priority > spec_from_unit("twin", ["true"]).fifo_priority > 0
    assert ordered["planner"].argv[-6:] == ("--endpoint", "tcp/127.0.0.1:1", "--namespace", "archer/x", "--log-level", "WARNING")


def test_ordering_waits_for_ready(unit_script):
    first = spec(unit_script, "first", env={"READY_DELAY": "0.5"})
    second = spec(unit_script, "second", after=("first",))
    sup = Supervisor([second, first])
    sup.start()
    try:
        assert sup.wait_active(timeout_s=TIMEOUT_S)
        ready_first = next(e.t for e in sup.events if e.unit == "first" and e.what == "ready")
        start_second = next(e.t for e in sup.events if e.unit == "second" and e.what == "start")
        assert start_second >= ready_first
    finally:
        codes = sup.stop()
    assert codes == {"first": -signal.SIGTERM, "second": -signal.SIGTERM}
    assert [e.unit for e in sup.events if e.what == "stop"] == ["second", "first"]  # reverse order


def test_threads_a_real_time_thread_starts_share_its_class():
    """A loop process raises itself, then opens Zenoh: those threads deliver its inputs."""
    result: dict[str, object] = {}

    def loop_process_main() -> None:
        applied = make_realtime(priority=SUPERVISOR_RT_PRIORITY)
        result["applied"] = applied["priority"]
        worker = threading.Thread(target=lambda: result.update(policy=os.sched_getscheduler(0)))
        worker.start()
        worker.join()

    probe = threading.Thread(target=loop_process_main)
    probe.start()
    probe.join()
    if not str(result["applied"]).startswith("SCHED_FIFO"):
        pytest.skip(f"this kernel refuses SCHED_FIFO: {result['applied']}")
    assert result["policy"] == os.SCHED_FIFO


def test_units_do_not_inherit_the_supervisors_real_time_class(unit_script):
    probe = threading.Thread(target=lambda: applied.update(make_realtime(priority=SUPERVISOR_RT_PRIORITY, reset_on_fork=True)))
    applied: dict[str, str] = {}
    probe.start()
    probe.join()
    if not applied["priority"].startswith("SCHED_FIFO"):
        pytest.skip(f"this kernel refuses SCHED_FIFO: {applied['priority']}")
    sup = Supervisor([spec(unit_script, "unit")])
    sup.start()  # the supervision thread raises itself to SCHED_FIFO, then forks the unit
    try:
        assert sup.wait_active(timeout_s=TIMEOUT_S)
        assert os.sched_getscheduler(sup.pid("unit")) == os.SCHED_OTHER
    finally:
        sup.stop()


def test_nice_applies_to_the_units_process(unit_script):
    sup = Supervisor([spec(unit_script, "unit", nice=7)])
    sup.start()
    try:
        assert sup.wait_active(timeout_s=TIMEOUT_S)
        pid = sup.pid("unit")
        assert {os.getpriority(os.PRIO_PROCESS, int(tid)) for tid in os.listdir(f"/proc/{pid}/task")} == {7}
    finally:
        sup.stop()


def test_restart_on_failure_but_not_after_a_clean_exit(unit_script):
    sup = Supervisor([spec(unit_script, "crashy", "crash"), spec(unit_script, "clean", "exit0"), spec(unit_script, "steady")])
    sup.start()
    try:
        wait_for(lambda: sup.restarts("crashy") >= 2)
        wait_for(lambda: sup.state("clean") == "dead")
        assert sup.restarts("clean") == 0
        # kill -9 is a failure: restarted; a SIGTERM from outside is a clean stop: not restarted
        wait_for(lambda: sup.state("steady") == "active")
        pid = sup.pid("steady")
        os.kill(pid, signal.SIGKILL)
        wait_for(lambda: sup.restarts("steady") == 1 and sup.state("steady") == "active")
        assert sup.pid("steady") != pid
        os.kill(sup.pid("steady"), signal.SIGTERM)
        wait_for(lambda: sup.state("steady") == "dead")
        assert sup.restarts("steady") == 1
    finally:
        sup.stop()
    assert events(sup, "crashy")[:4] == ["start", "ready", "exit", "restart-scheduled"]


def test_watchdog_kills_a_stalled_unit_and_restarts_it(unit_script):
    sup = Supervisor([spec(unit_script, "stally", "stall", watchdog_s=0.3)])
    sup.start()
    try:
        wait_for(lambda: sup.restarts("stally") >= 1)
    finally:
        sup.stop()
    what = events(sup, "stally")
    assert what[:5] == ["start", "ready", "watchdog", "exit", "restart-scheduled"]
    assert sup.summary()["stally"]["exit_codes"][0] == -signal.SIGABRT
    assert sup.summary()["stally"]["watchdog_pings"] >= 3  # it did ping while it progressed


def test_notify_access_decides_whether_a_child_may_report_ready(unit_script):
    allowed = spec(unit_script, "allowed", "child-ready", notify_access="all")
    refused = spec(unit_script, "refused", "child-ready", notify_access="main", start_timeout_s=1.0, restart="no")
    sup = Supervisor([allowed, refused])
    sup.start()
    try:
        wait_for(lambda: sup.state("allowed") == "active")
        wait_for(lambda: sup.state("refused") == "failed")
    finally:
        sup.stop()
    assert "start-timeout" in events(sup, "refused")


def test_what_a_dead_main_process_left_behind_is_killed_before_the_restart(unit_script, tmp_path):
    pid_file = tmp_path / "child.pid"
    sup = Supervisor([spec(unit_script, "parent", "orphan", env={"CHILD_PID_FILE": str(pid_file)}, stop_timeout_s=0.5)])
    sup.start()
    try:
        wait_for(lambda: pid_file.exists() and pid_file.read_text())
        child = int(pid_file.read_text())
        wait_for(lambda: sup.restarts("parent") >= 1)
        # the child ignored SIGTERM: SIGKILL after TimeoutStopSec, before the restart
        with pytest.raises(ProcessLookupError):
            os.kill(child, 0)
        exit_t = next(e.t for e in sup.events if e.what == "exit")
        restart_t = next(e.t for e in sup.events if e.what == "restart-scheduled")
        assert restart_t - exit_t >= 0.5
    finally:
        sup.stop()


def test_start_limit_gives_up(unit_script):
    sup = Supervisor([spec(unit_script, "hopeless", "crash", start_limit_burst=3, start_limit_interval_s=30.0)])
    sup.start()
    try:
        wait_for(lambda: sup.state("hopeless") == "failed")
    finally:
        sup.stop()
    assert sup.restarts("hopeless") == 2 and events(sup, "hopeless")[-1] == "start-limit-hit"


def test_a_real_service_notifies_through_the_runtime_and_is_restarted_after_kill_9():
    """`archer run router` under the router unit's own policy: READY, pings, kill -9, back."""
    endpoint = free_endpoint()
    (router,) = sim_specs(["router"], endpoint, "archer/suptest")
    sup = Supervisor([UnitSpec(**{**router.__dict__, "restart_s": 0.1})])
    sup.start()
    try:
        assert sup.wait_active(timeout_s=TIMEOUT_S), sup.summary()
        wait_for(lambda: sup.summary()["router"]["watchdog_pings"] >= 1)  # WatchdogSec=5s: every 2 s
        assert sup.summary()["router"]["status"].startswith("running")
        pid = sup.pid("router")
        os.kill(pid, signal.SIGKILL)
        wait_for(lambda: sup.restarts("router") == 1 and sup.state("router") == "active")
        assert sup.pid("router") != pid
    finally:
        codes = sup.stop()
    assert codes["router"] == 0  # SIGTERM: a clean shutdown


# real time: loops at their rate, processes and Zenoh over loopback share two loaded cores
pytestmark = pytest.mark.timing_sensitive(reason="real-time loops, processes or Zenoh over loopback on a shared host")
