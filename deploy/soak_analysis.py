"""What each injected fault did to the stack, from what the soak observed (pure: no I/O, no clock).

Every time is ``CLOCK_MONOTONIC`` in ns, the stack's own clock (:class:`services.runtime.clock.WallClock`),
so a ``safety`` event's stamp and the soak's receipt times compare directly.

Per fault (:func:`analyze`):

- **detection**: the first sign that the stack noticed, among the signals of the fault's kind
  (:data:`SIGNALS`), each at the time the soak saw it, from injection until ``ATTRIBUTION_S``
  after the action ended (what shows later is not this fault's doing):

  - ``safety:<trip>``: a ``safety`` event (stamped by its publisher) other than the routine ones
    (:data:`ROUTINE_TRIPS`);
  - ``liveliness_lost:<service>``: the service's liveliness token went away (its session closed);
  - ``noticed_exit:<service>``: the killed process was reaped by its parent, i.e. the supervisor
    (a unit's main process) or the service (its loop child) noticed the exit;
  - ``counter:<service>.<name>``: a status counter the fault should raise rose over its value at
    injection (:func:`counter_matters`; a status poll's time, so within the poll period).

- **time to zero torque**: from injection to the twin's ``command_stale`` / ``command_refused``
  event (it stopped applying torque) or the first ``torque_cmd`` with ``armed`` false, whichever
  is first, within the same attribution bound; only when the robot was armed at injection.
- **fell**: the twin's ``falls`` count (its physics, not an estimate) rose during the fault's window;
  every fall of the run, with its time and the window it lies in (or none), is in the totals
  (:func:`falls_by_window`).
- **not injected**: a fault whose action could not be carried out (no process found, a refused
  signal) is reported as such, never as detected, and fails the run; a ``noop`` fault does
  nothing, and any signal seen in its window is a false detection (the rate is in the totals);
- **zero torque missing**: the commander (control) killed or stalled while armed and the
  motors never reached zero torque: fails the run.
- **recovery**: from injection until everything the fault disturbed is back: each service whose
  liveliness was lost declared it again (the unit is active); the commands are armed again (and
  stay armed ``ARMED_HOLD_S``) and the robot touched down after that (hopping); the reference
  flows again after a gap longer than ``REFERENCE_GAP_S``. Nothing disturbed: 0.
- **lost**: messages lost per topic in the window, from sequence gaps in the flight recording
  (:func:`window_losses`); a publisher that restarted at ``seq`` 1 is a restart, not a loss.
"""

from __future__ import annotations

import bisect
import re
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from typing import Any

from deploy.soak_schedule import Fault
from onboard.contracts.topics import TOPICS
from services.recorder import SeqStats

NS = 1_000_000_000
ROUTINE_TRIPS = frozenset({"arm", "wheel_torque", "foot_torque", "wheel_speed"})  # arming and clamps: normal hopping
ZERO_TORQUE_TRIPS = frozenset({"command_stale", "command_refused"})  # the twin stopped applying torque
FALL_TRIP = "tilt"  # the control's own (estimated) fall trip
ARMED_AT_INJECTION_S = 0.05  # an armed command sent this recently: the robot was under control
LATE_RECEIPT_S = 1.0  # [s] a command received this long after an injection may still have been sent before it
ARMED_HOLD_S = 1.0  # re-armed means armed this long without a disarmed command
REFERENCE_GAP_S = 0.5  # a reference gap this long is a disturbance (SafetyLimits.reference_stale_s)
# Signs of a fault (detection, zero torque) count up to this long after its action ended: later
# ones belong to something else (a loaded workstation makes the estimate honestly invalid now
# and then). The status poll is 0.5 s, a counter's rise shows within two polls.
ATTRIBUTION_S = 2.0
TWIN = "twin"

SIGNALS = {
    "kill": ("safety", "liveliness", "noticed_exit", "counter"),
    "stall": ("safety", "liveliness", "noticed_exit", "counter"),
    "router_restart": ("safety", "liveliness", "noticed_exit"),
    "cpu_hog": ("safety", "counter"),
    "malformed_flood": ("safety", "counter"),
    "bad_stamps": ("safety", "counter"),
    "noop": ("safety", "liveliness", "noticed_exit", "counter"),  # every kind's: a false detection is any of them
}
COMMANDER = "control"  # the service whose loss leaves the motors without a commander
_STAMP_SIGNS = re.compile(r"future|past|order|stale|outlier|reject|reset|bad_stamp|invalid")


def counter_matters(fault: Fault, name: str) -> bool:
    """Whether a rise of status counter ``name`` is a sign of ``fault``."""
    lowered = name.lower()
    if fault.kind == "malformed_flood":
        return "reject" in lowered and any(t in lowered for t in fault.topics)
    if fault.kind == "bad_stamps":
        return any(t in lowered for t in fault.topics) and bool(_STAMP_SIGNS.search(lowered))
    if fault.kind == "cpu_hog":
        return "overrun" in lowered
    if fault.kind in ("kill", "stall", "noop"):  # a service's own watchdog-like counters
        return "stale" in lowered or "errors" == lowered
    return False


@dataclass
class Streams:
    """What the soak observed during the run (every list in time order)."""

    safety: list[tuple[int, str]] = field(default_factory=list)  # (event stamp, trip)
    torque_rx: Sequence[int] = field(default_factory=list)  # receipt of each torque_cmd ...
    torque_armed: Sequence[int] = field(default_factory=list)  # ... and its armed flag (0/1) ...
    torque_sent: Sequence[int] = field(default_factory=list)  # ... and its stamp (the commander's clock, the same host's)
    reference_rx: list[int] = field(default_factory=list)
    touchdowns: list[int] = field(default_factory=list)  # receipt of each touchdown phase event
    liveliness: list[tuple[int, str, bool]] = field(default_factory=list)  # (receipt, service, alive)
    statuses: list[tuple[int, str, dict[str, float]]] = field(default_factory=list)  # (query sent, service, counters and extras of its reply)


@dataclass
class Injection:
    """One fault as it was carried out."""

    fault: Fault
    start_ns: int  # the action began (the signal sent, the helper started)
    end_ns: int  # the action ended (SIGCONT sent, the helper gone)
    window_end_ns: int  # observation ends: the next fault or the end of the run
    pid: int | None = None  # the process acted on
    exited_ns: int | None = None  # kill: the process was gone ...
    reaped_ns: int | None = None  # ... and its parent noticed
    put_back_ns: int | None = None  # the soak put the fallen robot back
    helper: dict[str, Any] | None = None  # what a hog or flood process reported
    error: str = ""  # why the action could not be carried out

    @property
    def attribution_end_ns(self) -> int:
        """Signs of this fault are looked for up to here (``ATTRIBUTION_S`` after the action)."""
        return min(self.window_end_ns, self.end_ns + int(ATTRIBUTION_S * NS))


def settle_windows(injections: Sequence[Injection], t_end_ns: int) -> None:
    """Each fault is watched until the next one was actually carried out (not when it was due: a soak
    process starved behind the real-time stack carried out a stall 3.8 s late, after the next fault's
    time, and its window came out empty), and not past the end of the observation."""
    for inj, after in zip(injections, injections[1:]):
        inj.window_end_ns = max(inj.window_end_ns, after.start_ns)
    for inj in injections:
        inj.window_end_ns = min(inj.window_end_ns, t_end_ns)


def _ms(t_ns: int | None, ref_ns: int) -> float | None:
    return None if t_ns is None else round((t_ns - ref_ns) / 1e6, 2)


def _s(t_ns: int | None, ref_ns: int) -> float | None:
    return None if t_ns is None else round((t_ns - ref_ns) / NS, 3)


def _first_at_or_after(times: Sequence[int], t: int) -> int:
    return bisect.bisect_left(times, t)


def detection_signals(s: Streams, inj: Injection) -> dict[str, int]:
    """Each signal of the fault's kind and the first time it showed while it is attributed to it."""
    f, lo, hi = inj.fault, inj.start_ns, inj.attribution_end_ns
    kinds = SIGNALS[f.kind]
    out: dict[str, int] = {}

    def note(name: str, t: int) -> None:
        if lo <= t < hi and (name not in out or t < out[name]):
            out[name] = t

    if "safety" in kinds:
        for stamp, trip in s.safety:
            if trip not in ROUTINE_TRIPS:
                note(f"safety:{trip}", stamp)
    if "liveliness" in kinds:
        for t, service, alive in s.liveliness:
            if not alive and (service == f.service or f.kind == "router_restart"):
                note(f"liveliness_lost:{service}", t)
    if "noticed_exit" in kinds and inj.reaped_ns is not None:
        note(f"noticed_exit:{f.service}", inj.reaped_ns)
    if "counter" in kinds:
        baseline: dict[str, dict[str, float]] = {}
        for t, service, values in s.statuses:
            if t < lo:
                baseline[service] = values
            elif t < hi:
                before = baseline.get(service, {})
                for name, value in values.items():
                    if counter_matters(f, name) and value > before.get(name, 0.0):
                        note(f"counter:{service}.{name}", t)
    return out


def armed_at(s: Streams, t: int) -> bool:
    """An armed command was sent in the ``ARMED_AT_INJECTION_S`` before ``t``.

    Not necessarily the last one: on a starved host the estimate is late for 30-80 ms at times
    (two or three times a second in soaks here), the control loop holds zero torque meanwhile, and
    the robot stays under its control.

    By the commands' own stamps: on a loaded host the soak's subscriber receives them late and in
    bursts, and a command sent just before ``t`` may arrive well after it (up to 3.5 s after, in soaks
    of the 2-core host beside the whole real-time stack)."""
    recent = int(ARMED_AT_INJECTION_S * NS)
    i = _first_at_or_after(s.torque_rx, t - recent)
    # a backlog outlasts LATE_RECEIPT_S (its commands, sent before t, still arriving): it is followed to its end
    while i < len(s.torque_rx) and (s.torque_rx[i] - t <= LATE_RECEIPT_S * NS or s.torque_sent[i] <= t):
        if s.torque_armed[i] and t - recent <= s.torque_sent[i] <= t:
            return True
        i += 1
    return False


def zero_torque(s: Streams, inj: Injection) -> tuple[int | None, str]:
    """When torque went to zero after injection (while attributed to it), and what said so."""
    lo, hi = inj.start_ns, inj.attribution_end_ns
    twin = next(((stamp, trip) for stamp, trip in s.safety if lo <= stamp < hi and trip in ZERO_TORQUE_TRIPS), None)
    # by the commands' own stamps: a backlog's commands, sent before the fault, arrive after it
    i = _first_at_or_after(s.torque_rx, lo)
    disarmed = None
    while i < len(s.torque_rx) and s.torque_sent[i] < hi:
        if not s.torque_armed[i] and s.torque_sent[i] >= lo:
            disarmed = s.torque_sent[i]
            break
        i += 1
    candidates = [(twin[0], f"twin {twin[1]}")] if twin is not None else []
    if disarmed is not None:
        candidates.append((disarmed, "torque_cmd armed=false"))
    return min(candidates) if candidates else (None, "")


def rearmed(s: Streams, after_ns: int, hi: int) -> int | None:
    """The first armed command after ``after_ns`` that starts ``ARMED_HOLD_S`` of armed ones
    (or armed ones up to ``hi``)."""
    hold = int(ARMED_HOLD_S * NS)
    i = _first_at_or_after(s.torque_rx, after_ns)
    start = None
    while i < len(s.torque_rx) and s.torque_rx[i] < hi:
        t = s.torque_rx[i]
        if s.torque_armed[i]:
            if start is None:
                start = t
            elif t - start >= hold:
                return start
        else:
            start = None
        i += 1
    return start


def reference_back(s: Streams, lo: int, hi: int) -> tuple[bool, int | None]:
    """``(disturbed, back)``: whether the reference stopped for ``REFERENCE_GAP_S`` or more in
    ``[lo, hi)`` while it had been flowing, and the first one after the last such gap."""
    gap = int(REFERENCE_GAP_S * NS)
    i = _first_at_or_after(s.reference_rx, lo)
    if i == 0 or lo - s.reference_rx[i - 1] > gap:
        return False, None  # not flowing at injection (no planner, or down already)
    previous, disturbed, back = s.reference_rx[i - 1], False, None
    while i < len(s.reference_rx) and s.reference_rx[i] < hi:
        t = s.reference_rx[i]
        if t - previous > gap:
            disturbed, back = True, t
        previous = t
        i += 1
    if hi - previous > gap and previous < hi:  # stopped and never came back in the window
        return True, None
    return disturbed, back


def liveliness_back(s: Streams, lo: int, hi: int) -> dict[str, int | None]:
    """Each service whose token went away in ``[lo, hi)``: when it came back (None: never)."""
    out: dict[str, int | None] = {}
    for t, service, alive in s.liveliness:
        if not lo <= t < hi:
            continue
        if not alive:
            out[service] = None
        elif service in out:
            out[service] = t
    return out


def twin_falls(s: Streams, lo: int, hi: int) -> tuple[float | None, float | None]:
    """The twin's ``falls`` count before ``lo`` and its highest in ``[lo, hi)``.

    A fault that starves the machine (a flood) can leave the window without one answered status
    poll; the count is cumulative, so the first answer after the window stands in for it: a fall
    just after the window is then laid on this fault, never a fall inside it lost."""
    before = after = None
    for t, service, values in s.statuses:
        if service != TWIN or "falls" not in values:
            continue
        if t < lo:
            before = values["falls"]
        elif t < hi:
            after = max(after or 0.0, values["falls"])
        elif after is None:
            after = values["falls"]
            break
        else:
            break
    return before, after


def fall_times(s: Streams) -> list[int]:
    """When each fall of the run showed: the twin status reply whose ``falls`` count rose (its
    physics, at the status poll's resolution)."""
    out, last = [], 0.0
    for t, service, values in s.statuses:
        if service == TWIN and "falls" in values:
            out.extend([t] * int(max(0.0, values["falls"] - last)))
            last = max(last, values["falls"])
    return out


def falls_by_window(s: Streams, injections: Sequence[Injection], t0_ns: int) -> list[dict[str, Any]]:
    """Every fall with its time [s after the stack first armed] and the fault window it lies in (None: outside any)."""
    out = []
    for t in fall_times(s):
        inside = next((inj for inj in injections if inj.start_ns <= t < inj.window_end_ns), None)
        out.append({"t_s": _s(t, t0_ns), "fault": None if inside is None else f"{inside.fault.kind}@{inside.fault.at_s:g}"})
    return out


def analyze(s: Streams, inj: Injection, t0_ns: int, losses: dict[str, dict[str, int]] | None = None) -> dict[str, Any]:
    """The summary of one fault (see the module docstring); times relative to ``t0_ns`` (the twin's start)."""
    f, lo, hi = inj.fault, inj.start_ns, inj.window_end_ns
    out: dict[str, Any] = dict(f.describe())
    out["injected_at_s"] = _s(lo, t0_ns)
    out["action_s"] = _s(inj.end_ns, lo)
    if inj.pid is not None:
        out["pid"] = inj.pid
    if inj.exited_ns is not None or inj.reaped_ns is not None:
        out["exited_ms"] = _ms(inj.exited_ns, lo)
        out["exit_noticed_ms"] = _ms(inj.reaped_ns, lo)
    if inj.helper is not None:
        out["helper"] = inj.helper
    if inj.error:
        out["error"] = inj.error

    signals = detection_signals(s, inj)
    first = min(signals.items(), key=lambda kv: kv[1]) if signals else None
    out["injected"] = not inj.error and f.kind != "noop"
    if inj.error:  # nothing was done: whatever showed is not this fault's detection
        out["signals_without_injection_ms"] = {name: _ms(t, lo) for name, t in sorted(signals.items(), key=lambda kv: kv[1])}
        signals, first = {}, None
    out["detected"] = first is not None
    out["detection_ms"] = _ms(first[1], lo) if first else None
    out["detected_by"] = first[0] if first else None
    out["signals_ms"] = {name: _ms(t, lo) for name, t in sorted(signals.items(), key=lambda kv: kv[1])}

    was_armed = armed_at(s, lo)
    out["armed_at_injection"] = was_armed
    zero_ns, zero_by = zero_torque(s, inj) if was_armed else (None, "")
    out["zero_torque_ms"] = _ms(zero_ns, lo)
    out["zero_torque_by"] = zero_by or None
    commander_lost = out["injected"] and f.kind in ("kill", "stall") and f.service == COMMANDER
    out["zero_torque_missing"] = bool(commander_lost and was_armed and zero_ns is None)

    before, after = twin_falls(s, lo, hi)
    out["fell"] = None if before is None or after is None else after > before
    tilt = next((stamp for stamp, trip in s.safety if lo <= stamp < hi and trip == FALL_TRIP), None)
    out["tilt_trip_s"] = _s(tilt, lo)
    out["put_back_s"] = _s(inj.put_back_ns, lo)

    components: dict[str, int | None] = {}
    for service, back in liveliness_back(s, lo, hi).items():
        components[f"unit:{service}"] = back
    if zero_ns is not None:
        armed_ns = rearmed(s, zero_ns, hi)
        components["armed"] = armed_ns
        components["hopping"] = None if armed_ns is None else next(
            (t for t in s.touchdowns[_first_at_or_after(s.touchdowns, armed_ns):] if t < hi), None)
    ref_disturbed, ref_back = reference_back(s, lo, hi)
    if ref_disturbed:
        components["reference"] = ref_back
    out["degraded"] = bool(components)
    out["recovered"] = all(t is not None for t in components.values())
    out["recovery_s"] = (_s(max(components.values()), lo) if components else 0.0) if out["recovered"] else None  # type: ignore[type-var]
    out["recovery"] = {name: _s(t, lo) for name, t in components.items()}
    if losses is not None:
        out["lost"] = {topic: c["lost"] for topic, c in losses.items() if c["received"] or c["lost"]}
        restarts = {topic: c["restarts"] for topic, c in losses.items() if c["restarts"]}
        if restarts:
            out["publisher_restarts"] = restarts
    return out


def window_losses(messages: Iterable[tuple[int, str, int]], windows: list[tuple[int, int]]) -> list[dict[str, dict[str, int]]]:
    """Per window ``[lo, hi)``: per topic, messages received, lost (sequence gaps) and publisher
    restarts, from ``(receipt ns, topic name, seq)`` in receipt order. A gap that spans a window's
    start counts in that window (the messages went missing then)."""
    stats = {t.name: SeqStats(max(1, len(t.publishers))) for t in TOPICS.values()}
    marks: list[dict[str, dict[str, int]] | None] = [None] * len(windows)
    result: list[dict[str, dict[str, int]]] = [{} for _ in windows]
    order = sorted(range(len(windows)), key=lambda k: windows[k][0])

    def snapshot() -> dict[str, dict[str, int]]:
        return {name: st.as_dict() for name, st in stats.items()}

    def close(k: int) -> None:
        start, now = marks[k], snapshot()
        assert start is not None
        result[k] = {name: {key: now[name][key] - start[name][key] for key in ("received", "lost", "restarts")} for name in now}

    pending = list(order)
    open_windows: list[int] = []
    for t, topic, seq in messages:
        while pending and windows[pending[0]][0] <= t:
            k = pending.pop(0)
            marks[k] = snapshot()
            open_windows.append(k)
        for k in [k for k in open_windows if windows[k][1] <= t]:
            close(k)
            open_windows.remove(k)
        if topic in stats:
            stats[topic].observe(seq)
    for k in pending:
        marks[k] = snapshot()
        open_windows.append(k)
    for k in open_windows:
        close(k)
    return result
