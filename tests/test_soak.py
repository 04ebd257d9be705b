"""The chaos soak: schedule parsing, the per-fault analysis on synthetic event streams, the
malformed payloads, and one short soak of the real stack (marked ``soak``)."""

from __future__ import annotations

import json
import subprocess
import sys
import time
import tomllib
from array import array
from collections import Counter
from pathlib import Path

import msgspec
import pytest

from deploy import soak_faults as sf
from deploy.sil_soak import DEFAULT_SCHEDULE, FAULT_MIN_WATCH_S, _totals, commanded_armed, fault_start_ns
from deploy.soak_analysis import (
    ARMED_HOLD_S, Injection, Streams, analyze, falls_by_window, settle_windows, twin_falls, window_losses,
)
from deploy.soak_schedule import (
    FLOOD_RATE_HZ, KINDS, Fault, ScheduleError, check_schedule, load_schedule, parse_kill, parse_schedule, parse_shorthand,
)
from onboard.contracts import messages as m
from onboard.contracts.topics import TOPICS
from services.runtime.zenoh_session import free_endpoint

NS = 1_000_000_000
MS = 1_000_000
REPO = Path(__file__).resolve().parent.parent

SCHEDULE_TOML = """
[soak]
duration_s = 120

[[fault]]
kind = "malformed_flood"
at = 50
topics = ["imu", "pose"]
duration = 5

[[fault]]
kind = "stall"
at = 20
target = "control/child"
duration = 0.2

[[fault]]
kind = "bad_stamps"
at = 60
topics = "pose"
offset = -10
duration = 2
rate_hz = 100

[[fault]]
kind = "router_restart"
at = 70

[[fault]]
kind = "cpu_hog"
at = 80
cpu = 1
duration = 10

[[fault]]
kind = "kill"
at = 100
target = "planner"
"""


# --- schedules ---------------------------------------------------------------------------------------


def test_a_toml_schedule_parses_sorted_with_defaults_and_json_says_the_same() -> None:
    schedule = parse_schedule(SCHEDULE_TOML, "toml")
    assert [f.kind for f in schedule.faults] == ["stall", "malformed_flood", "bad_stamps", "router_restart", "cpu_hog", "kill"]
    stall, flood, stamps, router, hog, kill = schedule.faults
    assert stall == Fault("stall", 20.0, target="control/child", duration_s=0.2)
    assert stall.service == "control" and stall.end_s == pytest.approx(20.2)
    assert flood.rate_hz == FLOOD_RATE_HZ and flood.topics == ("imu", "pose")
    assert stamps.topics == ("pose",) and stamps.offset_s == -10.0 and stamps.rate_hz == 100.0
    assert router.service == "router" and hog.cpu == 1 and kill.target == "planner"
    assert schedule.settings == {"duration_s": 120}
    as_json = json.dumps({"soak": schedule.settings, "fault": [f.describe() for f in schedule.faults]})
    assert parse_schedule(as_json, "json") == schedule


def test_the_shorthand_makes_the_same_faults_as_a_file() -> None:
    assert parse_shorthand("stall@20:target=control/child,duration=0.2") == Fault("stall", 20.0, target="control/child", duration_s=0.2)
    assert parse_shorthand("malformed_flood@50:topics=imu+pose,duration=5") == parse_schedule(SCHEDULE_TOML, "toml").faults[1]
    assert parse_shorthand("router_restart@70") == Fault("router_restart", 70.0)
    assert parse_kill("control/child@300") == Fault("kill", 300.0, target="control/child")


@pytest.mark.parametrize("spec, complaint", [
    ("explode@10", "fault kind 'explode'"),
    ("stall@10:target=control,duration=0.01", "a stall lasts"),
    ("stall@10:target=control,duration=3", "a stall lasts"),
    ("stall@10:target=control", "needs a duration"),
    ("kill@10:target=control/loop", "target must be SERVICE or SERVICE/child"),
    ("kill@10", "target must be"),
    ("kill@-1:target=control", "'at' must be a time >= 0"),
    ("kill@10:target=control,duration=2", "unknown parameters ['duration']"),
    ("malformed_flood@10:topics=imu+bogus,duration=1", "unknown topics ['bogus']"),
    ("malformed_flood@10:duration=1", "needs topics"),
    ("bad_stamps@10:topics=depth,offset=5,duration=1", "binary layout"),
    ("bad_stamps@10:topics=pose,duration=1", "needs an offset"),
    ("cpu_hog@10:duration=5,cpu=-1", "cpu must be >= 0"),
    ("cpu_hog@10:duration=ten", "duration = 'ten' is not valid"),
    ("stall:target=control", "expected KIND@T"),
])
def test_a_fault_that_cannot_run_as_written_is_refused_naming_why(spec: str, complaint: str) -> None:
    with pytest.raises(ScheduleError, match=complaint.replace("[", r"\[").replace("]", r"\]").replace("(", r"\(")):
        parse_shorthand(spec)


def test_a_schedule_must_fit_its_run() -> None:
    services = ["estimator", "control", "planner"]
    check_schedule(parse_schedule(SCHEDULE_TOML, "toml"), 120.0, services)
    with pytest.raises(ScheduleError, match="after the run"):
        check_schedule(parse_schedule(SCHEDULE_TOML, "toml"), 90.0, services)
    with pytest.raises(ScheduleError, match="'recorder' is not a unit of this run"):
        check_schedule(parse_schedule(SCHEDULE_TOML, "toml").merged([parse_kill("recorder@30")]), 120.0, services)
    overlapping = parse_schedule(SCHEDULE_TOML, "toml").merged([parse_shorthand("router_restart@52")])
    with pytest.raises(ScheduleError, match="starts before malformed_flood@50 ended"):
        check_schedule(overlapping, 120.0, services)
    with pytest.raises(ScheduleError, match="not valid toml"):
        parse_schedule("[[fault]\nkind=", "toml")
    with pytest.raises(ScheduleError, match="unknown top-level keys"):
        parse_schedule('{"faults": []}', "json")


def test_the_default_schedule_runs_ten_minutes_with_every_fault_twice_and_room_to_recover() -> None:
    schedule = load_schedule(DEFAULT_SCHEDULE)
    settings = schedule.settings
    assert settings["duration_s"] == 600
    check_schedule(schedule, settings["duration_s"], settings["services"].split(","))
    kinds = Counter(f.kind for f in schedule.faults)
    assert set(kinds) == set(KINDS) and min(kinds.values()) >= 2
    gaps = [b.at_s - a.end_s for a, b in zip(schedule.faults, schedule.faults[1:])]
    assert min(gaps) >= 20.0
    assert tomllib.loads(DEFAULT_SCHEDULE.read_text())["soak"]["services"] == settings["services"]


# --- helper payloads ----------------------------------------------------------------------------------


@pytest.mark.parametrize("topic", list(TOPICS))
def test_every_malformed_payload_is_refused_and_every_kind_of_flaw_is_there(topic: str) -> None:
    payloads = sf.malformed_payloads(topic)
    assert len(payloads) >= 8
    if TOPICS[topic].msg_type is None:
        return
    for payload in payloads:
        with pytest.raises(m.MessageError):
            m.decode(payload, TOPICS[topic].msg_type)
    text = b"\n".join(payloads)
    for flaw in (b"unknown_field", b'"version":99', b'"stamp_ns":"now"'):
        assert flaw in text
    # the schema example they are made from is itself well formed
    m.decode(msgspec.json.encode(sf.example(msgspec.inspect.type_info(TOPICS[topic].msg_type))), TOPICS[topic].msg_type)


def test_a_malformed_torque_flood_does_not_read_as_the_commander_disarming() -> None:
    # Read leniently (only `armed`, defaulting to False) a flood payload with a field missing or an
    # unknown one looked like a disarm: the default soak scored 0.43-0.50 s "to zero torque" on a
    # flood the twin had refused whole.
    assert all(commanded_armed(payload) is None for payload in sf.malformed_payloads("torque_cmd"))
    for armed in (True, False):
        command = m.TorqueCommand(seq=1, stamp_ns=1, wheel_torque=[0.1, 0.0, 0.0], foot_torque=0.0, armed=armed)
        assert commanded_armed(m.encode(command)) == (armed, 1)


def test_imu_floods_hold_wrong_lengths_and_non_finite_numbers() -> None:
    text = b"\n".join(sf.malformed_payloads("imu"))
    assert b"1e999" in text  # non-finite
    assert b'"gyro":[0.0,0.0,0.0,0.0]' in text.replace(b" ", b"")  # one element too many


# --- analysis on synthetic streams --------------------------------------------------------------------


def _torque(streams: Streams, t0_s: float, t1_s: float, armed: bool, sent_before_ns: int = 0) -> None:
    t = int(t0_s * NS)
    while t < int(t1_s * NS):
        streams.torque_rx.append(t)  # type: ignore[attr-defined]
        streams.torque_armed.append(1 if armed else 0)  # type: ignore[attr-defined]
        streams.torque_sent.append(t - sent_before_ns)  # type: ignore[attr-defined]
        t += MS


def _every(t0_s: float, t1_s: float, period_s: float) -> list[int]:
    return [int((t0_s + k * period_s) * NS) for k in range(int((t1_s - t0_s) / period_s))]


def _nominal(until_s: float = 40.0) -> Streams:
    """Armed and hopping, the reference at 10 Hz, every token up, the twin upright."""
    s = Streams(torque_rx=array("q"), torque_armed=bytearray(), torque_sent=array("q"))
    s.reference_rx = _every(0.0, until_s, 0.1)
    s.touchdowns = _every(0.2, until_s, 0.4)
    s.liveliness = [(0, name, True) for name in ("twin", "estimator", "control", "planner", "router")]
    s.statuses = [(t, "twin", {"falls": 0.0}) for t in _every(1.0, until_s, 2.0)]
    return s


def test_a_control_kill_is_seen_by_the_twin_first_and_recovered_when_armed_and_hopping_again() -> None:
    s = _nominal()
    _torque(s, 0.0, 10.0, armed=True)  # killed at 10 s: no command until the restart at 14 s
    _torque(s, 14.0, 15.0, armed=False)  # the new control waits for an upright estimate
    _torque(s, 15.0, 15.5, armed=True)
    _torque(s, 15.5, 15.6, armed=False)  # one more glitch: armed only counts when it holds
    _torque(s, 15.6, 40.0, armed=True)
    s.safety = [(int(10.011 * NS), "command_stale"), (int(10.6 * NS), "tilt"), (int(15.0 * NS), "arm")]
    s.liveliness += [(int(10.014 * NS), "control", False), (int(14.0 * NS), "control", True)]
    s.touchdowns = [t for t in s.touchdowns if not 10 * NS < t < 16 * NS]
    s.statuses = [(t, "twin", {"falls": 0.0 if t < 11 * NS else 1.0}) for t in _every(1.0, 40.0, 2.0)]
    inj = Injection(Fault("kill", 10.0, target="control"), 10 * NS, 10 * NS, 30 * NS, pid=1234,
                    exited_ns=int(10.012 * NS), reaped_ns=int(10.013 * NS), put_back_ns=12 * NS)

    out = analyze(s, inj, t0_ns=0)

    assert out["kind"] == "kill" and out["target"] == "control" and out["injected_at_s"] == 10.0
    assert out["detected"] and out["detected_by"] == "safety:command_stale" and out["detection_ms"] == pytest.approx(11.0)
    assert out["signals_ms"] == {"safety:command_stale": 11.0, "noticed_exit:control": 13.0, "liveliness_lost:control": 14.0,
                                 "safety:tilt": 600.0}  # the routine "arm" trip is no sign of a fault
    assert out["exited_ms"] == 12.0 and out["exit_noticed_ms"] == 13.0
    assert out["armed_at_injection"] and out["zero_torque_ms"] == pytest.approx(11.0) and out["zero_torque_by"] == "twin command_stale"
    assert out["fell"] is True and out["tilt_trip_s"] == 0.6 and out["put_back_s"] == 2.0
    assert out["recovery"]["unit:control"] == 4.0
    assert out["recovery"]["armed"] == pytest.approx(5.6)  # the run that held ARMED_HOLD_S, not the glitched one
    first_touchdown = min(t for t in s.touchdowns if t >= 15.6 * NS) / NS - 10.0
    assert out["recovery"]["hopping"] == pytest.approx(first_touchdown, abs=1e-3)
    assert out["degraded"] and out["recovered"] and out["recovery_s"] == pytest.approx(first_touchdown, abs=1e-3)
    assert "lost" not in out  # no recording given


def test_a_window_the_twin_never_answered_in_takes_its_falls_from_the_first_answer_after_it() -> None:
    s = _nominal()
    # answers every 2 s from 1 s, none at 11 s; a fall shows from 15 s
    s.statuses = [(t, "twin", {"falls": 0.0 if t < 14 * NS else 1.0}) for t in _every(1.0, 40.0, 2.0) if t != 11 * NS]
    assert twin_falls(s, 10 * NS, 12 * NS) == (0.0, 0.0)  # 13 s answered first: nothing fell by then
    assert twin_falls(s, int(13.5 * NS), int(14.5 * NS)) == (0.0, 1.0)  # 15 s answered first, a fall: laid on this window
    assert twin_falls(s, 3 * NS, 6 * NS) == (0.0, 0.0)  # answered inside: the answers after it are not read
    s.statuses = [(t, "twin", {"falls": 0.0}) for t in _every(1.0, 8.0, 2.0)]
    assert twin_falls(s, 10 * NS, 12 * NS) == (0.0, None)  # the twin never answered again: unknown, not "no fall"


def test_a_fault_nobody_noticed_is_reported_undetected_and_undisturbed() -> None:
    s = _nominal()
    _torque(s, 0.0, 40.0, armed=True)
    s.statuses += [(int(9.9 * NS), "recorder", {"counters.errors": 0.0}), (int(10.5 * NS), "recorder", {"counters.errors": 0.0})]
    s.statuses.sort(key=lambda r: r[0])
    out = analyze(s, Injection(Fault("stall", 10.0, target="recorder", duration_s=0.1), 10 * NS, int(10.1 * NS), 30 * NS), t0_ns=0)
    assert not out["detected"] and out["detection_ms"] is None and out["signals_ms"] == {}
    assert out["armed_at_injection"] and out["zero_torque_ms"] is None
    assert out["fell"] is False and not out["degraded"] and out["recovered"] and out["recovery_s"] == 0.0


def test_a_fault_not_carried_out_is_never_detected_and_fails_the_run() -> None:
    """No process to kill: whatever shows in its window (here a routine stale estimate) is not its
    detection; the run's verdict fails on it."""
    s = _nominal()
    _torque(s, 0.0, 40.0, armed=True)
    s.safety = [(int(10.2 * NS), "estimate_stale")]
    inj = Injection(Fault("kill", 10.0, target="estimator"), 10 * NS, 10 * NS, 30 * NS, error="no process for 'estimator' found")
    out = analyze(s, inj, t0_ns=0)
    assert not out["injected"] and not out["detected"] and out["detected_by"] is None
    assert out["signals_without_injection_ms"] == {"safety:estimate_stale": 200.0}
    totals = _totals([out], [])
    assert totals["not_injected"] == ["kill@10"] and totals["detected"] == 0 and not totals["passed"]


def test_noop_faults_measure_false_detections() -> None:
    s = _nominal()
    _torque(s, 0.0, 40.0, armed=True)
    s.safety = [(int(25.5 * NS), "estimate_stale")]  # something in the second noop's window
    quiet = analyze(s, Injection(Fault("noop", 10.0), 10 * NS, 10 * NS, 20 * NS), t0_ns=0)
    noisy = analyze(s, Injection(Fault("noop", 25.0), 25 * NS, 25 * NS, 35 * NS), t0_ns=0)
    assert not quiet["detected"] and noisy["detected"] and noisy["detected_by"] == "safety:estimate_stale"
    totals = _totals([quiet, noisy], [])
    assert totals["faults"] == 0 and totals["noop_faults"] == 2
    assert totals["false_detections"] == ["noop@25"] and totals["false_detection_rate"] == 0.5


def test_every_fall_is_counted_by_the_physics_with_its_window_and_a_lost_commander_must_cut_torque() -> None:
    s = _nominal()
    _torque(s, 0.0, 40.0, armed=True)  # the torque never stops: a stall of control that nobody cut
    s.statuses = [(t, "twin", {"falls": 0.0 if t < 12 * NS else 1.0 if t < 34 * NS else 2.0}) for t in _every(1.0, 40.0, 2.0)]
    stall = Injection(Fault("stall", 10.0, target="control", duration_s=0.2), 10 * NS, int(10.2 * NS), 20 * NS, pid=7)
    falls = falls_by_window(s, [stall], t0_ns=0)
    assert falls == [{"t_s": 13.0, "fault": "stall@10"}, {"t_s": 35.0, "fault": None}]  # the second outside any fault
    out = analyze(s, stall, t0_ns=0)
    assert out["armed_at_injection"] and out["zero_torque_ms"] is None and out["zero_torque_missing"]
    totals = _totals([out], falls)
    assert totals["falls"] == 2 and totals["falls_outside_faults"] == 1 and totals["zero_torque_missing"] == ["stall@10"]
    assert not totals["passed"]


def test_a_flood_is_detected_by_the_rejection_counter_of_its_topic_only() -> None:
    s = _nominal()
    _torque(s, 0.0, 40.0, armed=True)
    s.statuses += [
        (int(9.5 * NS), "estimator", {"counters.rejected.imu": 3.0, "counters.rejected.joints": 0.0, "loop_overruns": 5.0}),
        (int(10.2 * NS), "estimator", {"counters.rejected.imu": 3.0, "counters.rejected.joints": 1.0, "loop_overruns": 9.0}),
        (int(10.7 * NS), "estimator", {"counters.rejected.imu": 2503.0, "counters.rejected.joints": 1.0, "loop_overruns": 9.0}),
        (int(10.8 * NS), "control", {"rejected_imu": 0.0}),
    ]
    s.statuses.sort(key=lambda r: r[0])
    flood = Fault("malformed_flood", 10.0, topics=("imu",), duration_s=1.0, rate_hz=5000.0)
    out = analyze(s, Injection(flood, 10 * NS, 11 * NS, 30 * NS, helper={"sent": {"imu": 5000}}), t0_ns=0)
    assert out["detected_by"] == "counter:estimator.counters.rejected.imu" and out["detection_ms"] == pytest.approx(700.0)
    assert list(out["signals_ms"]) == ["counter:estimator.counters.rejected.imu"]  # not joints, not overruns
    assert out["helper"] == {"sent": {"imu": 5000}} and out["recovery_s"] == 0.0
    # a CPU hog's sign is the overrun counter instead
    hog = analyze(s, Injection(Fault("cpu_hog", 10.0, duration_s=1.0), 10 * NS, 11 * NS, 30 * NS), t0_ns=0)
    assert hog["detected_by"] == "counter:estimator.loop_overruns" and hog["detection_ms"] == pytest.approx(200.0)


def test_a_planner_kill_is_recovered_when_the_reference_flows_again() -> None:
    s = _nominal()
    _torque(s, 0.0, 40.0, armed=True)
    s.reference_rx = [t for t in s.reference_rx if not 10 * NS < t < 16 * NS]
    s.liveliness += [(int(10.02 * NS), "planner", False), (int(15.0 * NS), "planner", True)]
    out = analyze(s, Injection(Fault("kill", 10.0, target="planner"), 10 * NS, 10 * NS, 30 * NS), t0_ns=0)
    assert out["detected_by"] == "liveliness_lost:planner"
    assert out["zero_torque_ms"] is None and out["fell"] is False
    assert out["recovery"] == {"unit:planner": 5.0, "reference": pytest.approx(6.0, abs=0.11)}
    assert out["recovery_s"] == out["recovery"]["reference"]
    # never back inside the window: not recovered
    s.reference_rx = [t for t in s.reference_rx if t < 10 * NS]
    late = analyze(s, Injection(Fault("kill", 10.0, target="planner"), 10 * NS, 10 * NS, 30 * NS), t0_ns=0)
    assert late["recovery"]["reference"] is None and not late["recovered"] and late["recovery_s"] is None


def test_disarmed_commands_count_as_zero_torque_only_when_the_robot_was_armed() -> None:
    s = _nominal()
    _torque(s, 0.0, 10.3, armed=True)
    _torque(s, 10.3, 10.5, armed=False)
    _torque(s, 10.5, 40.0, armed=True)
    out = analyze(s, Injection(Fault("bad_stamps", 10.0, topics=("imu",), duration_s=1.0, offset_s=-10.0), 10 * NS, 11 * NS, 30 * NS), t0_ns=0)
    assert out["zero_torque_ms"] == pytest.approx(300.0) and out["zero_torque_by"] == "torque_cmd armed=false"
    assert out["recovery"]["armed"] == pytest.approx(0.5) and out["recovered"]
    assert ARMED_HOLD_S < 20.0  # the window held it
    disarmed = _nominal()
    _torque(disarmed, 0.0, 40.0, armed=False)
    out = analyze(disarmed, Injection(Fault("kill", 10.0, target="control"), 10 * NS, 10 * NS, 30 * NS), t0_ns=0)
    assert not out["armed_at_injection"] and out["zero_torque_ms"] is None


def test_armed_at_injection_goes_by_the_commands_stamps_not_their_late_receipt() -> None:
    """On a loaded host the soak receives the commands 200 ms late: the robot was still under control
    when the fault came; a commander that had gone quiet 200 ms before it was not."""
    late = _nominal()
    _torque(late, 0.2, 40.0, armed=True, sent_before_ns=200 * MS)
    kill = Fault("kill", 10.0, target="control")
    assert analyze(late, Injection(kill, 10 * NS, 10 * NS, 30 * NS), t0_ns=0)["armed_at_injection"]
    quiet = _nominal()
    _torque(quiet, 0.0, 9.8, armed=True)
    assert not analyze(quiet, Injection(kill, 10 * NS, 10 * NS, 30 * NS), t0_ns=0)["armed_at_injection"]


def test_armed_at_injection_follows_a_backlog_longer_than_a_second_and_holds_through_a_late_estimate() -> None:
    """Soaks here received the commands up to 3.5 s late; and the control holds zero torque while
    its estimate is late (30-80 ms, a few times a second on a starved host), still in control."""
    kill = Fault("kill", 10.0, target="control")
    backlog = _nominal()
    _torque(backlog, 2.5, 40.0, armed=True, sent_before_ns=2500 * MS)
    assert analyze(backlog, Injection(kill, 10 * NS, 10 * NS, 30 * NS), t0_ns=0)["armed_at_injection"]
    blip = _nominal()
    _torque(blip, 0.0, 9.97, armed=True)
    _torque(blip, 9.97, 10.03, armed=False)
    _torque(blip, 10.03, 40.0, armed=True)
    out = analyze(blip, Injection(kill, 10 * NS, 10 * NS, 30 * NS), t0_ns=0)
    assert out["armed_at_injection"] and out["zero_torque_by"] == "torque_cmd armed=false"
    held = _nominal()  # zero torque for longer than the bound before the fault: not under control
    _torque(held, 0.0, 9.9, armed=True)
    _torque(held, 9.9, 40.0, armed=False)
    assert not analyze(held, Injection(kill, 10 * NS, 10 * NS, 30 * NS), t0_ns=0)["armed_at_injection"]


def test_a_fault_carried_out_late_is_watched_until_the_next_one_was_carried_out() -> None:
    """A CI soak's stall due at 4 s went in at 7.83 s, past the flood's 7.5 s, which went in at 8.08 s:
    the stall's window ran to the flood's due time and came out empty (undetected, zero torque missing)."""
    s = _nominal()
    _torque(s, 0.0, 7.85, armed=True)  # the control loop stopped at 7.85 s ...
    s.safety = [(int(7.86 * NS), "command_stale")]  # ... and the twin cut the torque
    stall = Injection(Fault("stall", 4.0, target="control/child", duration_s=0.2), int(7.85 * NS), int(8.05 * NS), int(7.5 * NS))
    flood = Injection(Fault("malformed_flood", 7.5, topics=("imu",), duration_s=1.5), int(8.08 * NS), int(9.6 * NS), int(11 * NS))
    settle_windows([stall, flood], t_end_ns=int(10.5 * NS))
    assert (stall.window_end_ns, flood.window_end_ns) == (flood.start_ns, int(10.5 * NS))
    out = analyze(s, stall, t0_ns=0)
    assert out["detected"] and out["detected_by"] == "safety:command_stale" and out["zero_torque_ms"] == pytest.approx(10.0)
    # and the next fault waits for it: due 7.5 s, carried out FAULT_MIN_WATCH_S after the late stall's action
    assert fault_start_ns(0, 7.5, stall.end_ns) == stall.end_ns + int(FAULT_MIN_WATCH_S * NS) > int(7.5 * NS)
    assert fault_start_ns(0, 7.5, int(4.2 * NS)) == int(7.5 * NS) and fault_start_ns(0, 4.0, None) == 4 * NS
    on_time = Injection(Fault("stall", 4.0, target="control/child", duration_s=0.2), 4 * NS, int(4.2 * NS), int(7.5 * NS))
    settle_windows([on_time, flood], t_end_ns=int(10.5 * NS))
    assert on_time.window_end_ns == int(7.5 * NS) + 580 * MS  # the next one's actual start, later than due


def test_a_status_is_stamped_when_asked_so_a_trip_from_before_a_fault_is_its_baseline(zenoh_router, tmp_path: Path) -> None:
    """A reply that arrives after the fault to a query sent before it holds the counters of then."""
    from deploy.sil_soak import StatusPoller
    from onboard.contracts.topics import status_key
    from services.runtime.zenoh_session import open_session

    ns = "archer/soakpoll"
    answer_after_s = 0.3
    server, client = open_session(zenoh_router, "peer"), open_session(zenoh_router, "peer")
    answered: list[int] = []

    def reply(query) -> None:
        time.sleep(answer_after_s)  # a starved service, or a starved asker
        answered.append(time.monotonic_ns())
        status = m.ServiceStatus(service="control", state="running", uptime_s=1.0, rates_hz={}, counters={"trip.estimate_stale": 1})
        query.reply(query.key_expr, m.encode(status))

    queryable = server.declare_queryable(status_key(ns, "control"), reply)
    try:
        streams = Streams(torque_rx=array("q"), torque_armed=bytearray(), torque_sent=array("q"))
        observer = type("ObserverLike", (), {"streams": streams, "live": {"control"}})()
        deadline = time.monotonic() + 10.0
        poller = StatusPoller(client, ns, observer, tmp_path / "status.jsonl")  # type: ignore[arg-type]
        while not streams.statuses and time.monotonic() < deadline:  # the queryable reaches the client
            asked = time.monotonic_ns()
            poller.poll(["control"])
        poller.stop()
        (stamp, service, values), = streams.statuses
        assert service == "control" and values["counters.trip.estimate_stale"] == 1.0
        assert asked <= stamp < answered[-1] - int(answer_after_s * 0.9 * 1e9)
    finally:
        queryable.undeclare()
        server.close()
        client.close()


def test_losses_per_window_come_from_sequence_gaps_and_a_restart_is_no_loss() -> None:
    msgs: list[tuple[int, str, int]] = []
    for k in range(1, 301):  # imu at 100 Hz; seq 151..155 lost (inside window 0), 201..210 lost (spans window 1's start)
        if not (151 <= k <= 155 or 201 <= k <= 210):
            msgs.append((k * 10 * MS, "imu", k))
    for k in range(1, 101):  # torque_cmd at 50 Hz: the commander restarts at 1.52 s
        msgs.append((k * 20 * MS + 1, "torque_cmd", k if k <= 75 else k - 75))
    for k, pub_seq in enumerate([1, 1, 2, 2, 3, 3]):  # safety from control and the twin, interleaved
        msgs.append((k * 400 * MS + 2, "safety", pub_seq))
    msgs.append((1500 * MS + 3, "imu", 0))  # a flood's message: no sequence to check
    msgs.sort()
    windows = [(1400 * MS, 1800 * MS), (2055 * MS, 2500 * MS), (2800 * MS, 2900 * MS)]
    w0, w1, w2 = window_losses(msgs, windows)
    assert w0["imu"] == {"received": 36, "lost": 5, "restarts": 0}
    assert w0["torque_cmd"]["lost"] == 0 and w0["torque_cmd"]["restarts"] == 1
    assert w0["safety"]["lost"] == 0
    assert w1["imu"]["lost"] == 10 and w1["torque_cmd"]["restarts"] == 0
    assert w2["imu"] == {"received": 10, "lost": 0, "restarts": 0}


# --- a real soak ---------------------------------------------------------------------------------------


# The real-time stack asks more of two cores than they have: in a soak here the twin, the
# estimator and the control loop process took 0.79, 0.58 and 0.66 of a core (Zenoh's threads
# about a third of each), and the twin ran at 0.6-0.7 of real time. Its estimate then degrades
# (attitude-only trips), and the 17 s run with a 2 kHz flood that this test was failed 3 of 6 runs
# here (a disarm before the stall, a fall after the flood) and both tries of a CI run. So the run is
# short and the flood at the IMU's own rate; what a starved host stretches (how soon the torque is
# cut, how many samples the recorder misses) has the bounds a starved host gave, and the figures
# of a robot-class host are `archer soak`'s to report.
SOAK_S = 12.0
STALL_AT_S, FLOOD_AT_S = 4.0, 7.5
FLOOD_HZ, FLOOD_S = 1000, 1.5
ZERO_TORQUE_MAX_MS = 300.0  # 9-11 ms in 5 of 6 runs here; 226 ms once, the twin's own loop starved
RECORDER_KILLED_IMU_LOST = 500  # a recorder killed loses its restart's worth of the 1 kHz IMU, 1000+


@pytest.mark.soak
def test_a_short_soak_detects_a_stall_and_a_flood_and_leaves_no_process(tmp_path: Path) -> None:
    out = tmp_path / "soak"
    argv = [sys.executable, "-m", "deploy.sil_soak", "--duration", str(SOAK_S), "--services", "estimator,control,recorder",
            "--fault", f"stall@{STALL_AT_S}:target=control/child,duration=0.2",
            "--fault", f"malformed_flood@{FLOOD_AT_S}:topics=imu,duration={FLOOD_S},rate_hz={FLOOD_HZ}",
            "--no-plot", "--out", str(out), "--namespace", f"archer/soaktest{free_endpoint().rsplit(':', 1)[1]}"]
    proc = subprocess.run(argv, cwd=REPO, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stdout[-4000:] + proc.stderr[-2000:]  # the faults and totals say which failed
    lines = [json.loads(line) for line in proc.stdout.strip().splitlines()]
    stall, flood, totals = lines
    summary = json.loads((out / "summary.json").read_text())
    assert summary["faults"] == [stall, flood] and summary["totals"] == totals["totals"]

    assert stall["kind"] == "stall" and stall["detected"] and stall["armed_at_injection"], json.dumps(stall)
    # the twin's watchdog or control's stale estimate, as a safety event or (first seen) the twin's trip counter
    assert stall["detected_by"].startswith(("safety:", "counter:twin.counters.trip.")), stall
    assert 0.19 <= stall["action_s"] <= 0.5
    assert stall["zero_torque_ms"] is not None and 0.0 < stall["zero_torque_ms"] <= ZERO_TORQUE_MAX_MS, stall
    assert stall["fell"] is False and stall["recovered"] and 0.0 < stall["recovery_s"] < 5.0, stall

    # the rejection counter rises (a status poll's time); a safety trip may come first (estimates late under the flood)
    rejections = [ms for name, ms in flood["signals_ms"].items() if name.startswith("counter:") and "rejected" in name and "imu" in name]
    assert flood["detected"] and rejections and 0.0 <= min(rejections) <= 3000.0, flood
    assert flood["detection_ms"] <= min(rejections)
    # the helper itself is starved at times on a shared host (1440-1497 of 1500 sent here)
    assert flood["helper"]["sent"]["imu"] >= FLOOD_HZ * FLOOD_S / 2 and flood["fell"] is False
    for fault in (stall, flood):
        # the recorder was not killed in either fault: a starved one misses some samples (0-28 of the
        # IMU per fault here; the estimate's stream, published beside the flood, up to 2390)
        assert set(fault["lost"]) >= {"imu", "joints", "torque_cmd", "state"}, fault["lost"]
        assert fault["lost"]["imu"] < RECORDER_KILLED_IMU_LOST, fault["lost"]
    assert totals["totals"]["detected"] == 2 and totals["totals"]["falls"] == 0
    # the twin ran the whole soak (after arming): at 0.6-0.9 of real time on a loaded 2-core host
    assert summary["metrics"]["mode"] == "realtime" and summary["metrics"]["sim_time_s"] > SOAK_S * 0.5
    # the recorder took the twin's 1 kHz IMU through the soak, from its start after the twin's (seconds
    # on a loaded host): 0.49-1.04 of the simulated milliseconds in 7 runs here
    assert summary["recorder"]["imu"]["received"] > 0.25 * TOPICS["imu"].rate_hz * summary["metrics"]["sim_time_s"]
    # nothing of the run is left: every process carrying its endpoint is gone
    assert sf_processes(summary["run"]["endpoint"]) == []


def sf_processes(endpoint: str) -> list[int]:
    from deploy.sil_soak import _processes_with

    return _processes_with(endpoint.encode())


# real time: loops at their rate, processes and Zenoh over loopback share two loaded cores
pytestmark = pytest.mark.timing_sensitive(reason="real-time loops, processes or Zenoh over loopback on a shared host")
