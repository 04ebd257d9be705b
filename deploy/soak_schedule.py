"""The fault schedule of a chaos soak (:mod:`deploy.sil_soak`): what to inject, when, how hard.

A schedule is a TOML or JSON file with an optional ``[soak]`` table (``duration_s``,
``services``, ``scenario``) and a list of faults (``[[fault]]`` in TOML, ``"fault": [...]``
in JSON), each with ``kind``, ``at`` (seconds after the stack first armed) and its parameters:

==================  ===============================================================================
kind                parameters
==================  ===============================================================================
``kill``            ``target``: a service (kill -9 of its main process) or ``SERVICE/child`` (of
                    its loop process, ``control/child``); the supervisor restarts it
``stall``           ``target`` as for kill: SIGSTOP of the service's processes (``SERVICE/child``:
                    the loop process only) for ``duration`` seconds (STALL_MIN_S .. STALL_MAX_S),
                    then SIGCONT
``router_restart``  none: kill -9 of the router unit (the supervisor restarts it)
``cpu_hog``         ``duration``; ``cpu`` (default 0): a busy process pinned to that core
``malformed_flood`` ``topics`` (names in :data:`onboard.contracts.topics.TOPICS`), ``duration``, ``rate_hz``
                    (per topic, default FLOOD_RATE_HZ): payloads no decoder may accept
``bad_stamps``      ``topics`` (JSON topics), ``duration``, ``offset`` (seconds added to the stamp:
                    positive in the future, negative in the past), ``rate_hz`` (default: the
                    topic's nominal rate): well-formed copies of live messages, restamped
==================  ===============================================================================

The command line's shorthand adds to a file: ``--kill SERVICE@T`` and
``--fault KIND@T[:key=value,...]`` (``topics`` joined with ``+``), e.g.
``--fault stall@40:target=control/child,duration=0.2`` or
``--fault malformed_flood@70:topics=imu+pose,duration=5``.
"""

from __future__ import annotations

import json
import math
import tomllib
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

from onboard.contracts.topics import TOPICS

# noop: nothing is done; looked at for every kind's signals, it measures how often "detected"
# fires with nothing injected (the false-detection rate)
KINDS = ("kill", "stall", "router_restart", "cpu_hog", "malformed_flood", "bad_stamps", "noop")
TARGETED = ("kill", "stall")
TIMED = ("stall", "cpu_hog", "malformed_flood", "bad_stamps")  # the fault lasts ``duration``
FLOODS = ("malformed_flood", "bad_stamps")
STALL_MIN_S = 0.05
STALL_MAX_S = 2.0
FLOOD_RATE_HZ = 5000.0
CHILD = "child"  # ``SERVICE/child``: the service's loop process
ROUTER = "router"

_KEYS = {  # file key -> Fault field
    "kind": "kind", "at": "at_s", "target": "target", "duration": "duration_s", "topics": "topics",
    "rate_hz": "rate_hz", "offset": "offset_s", "cpu": "cpu",
}
_ALLOWED = {
    "kill": {"target"},
    "stall": {"target", "duration"},
    "router_restart": set(),
    "cpu_hog": {"duration", "cpu"},
    "malformed_flood": {"topics", "duration", "rate_hz"},
    "bad_stamps": {"topics", "duration", "offset", "rate_hz"},
    "noop": set(),
}


class ScheduleError(ValueError):
    """A schedule that cannot be run as written."""


@dataclass(frozen=True)
class Fault:
    kind: str
    at_s: float  # [s] after the stack first armed
    target: str = ""  # kill, stall: SERVICE or SERVICE/child
    duration_s: float = 0.0  # [s] how long a timed fault lasts
    topics: tuple[str, ...] = ()  # floods
    rate_hz: float = 0.0  # floods: per topic; 0: the kind's default
    offset_s: float = 0.0  # bad_stamps: added to each stamp
    cpu: int = 0  # cpu_hog

    @property
    def service(self) -> str:
        """The unit a fault acts on ("" for none)."""
        return ROUTER if self.kind == "router_restart" else self.target.partition("/")[0]

    @property
    def end_s(self) -> float:
        return self.at_s + self.duration_s

    def describe(self) -> dict[str, Any]:
        """The fault's own fields, as a schedule file writes them."""
        out: dict[str, Any] = {"kind": self.kind, "at": self.at_s}
        for key in sorted(_ALLOWED[self.kind]):
            value = getattr(self, _KEYS[key])
            out[key] = list(value) if isinstance(value, tuple) else value
        return out


@dataclass(frozen=True)
class Schedule:
    faults: tuple[Fault, ...]
    settings: dict[str, Any] = field(default_factory=dict)  # the [soak] table

    def merged(self, more: list[Fault]) -> Schedule:
        return Schedule(tuple(sorted((*self.faults, *more), key=lambda f: f.at_s)), self.settings)


def fault_from_dict(raw: dict[str, Any]) -> Fault:
    """One fault from a file's table; every problem is a :class:`ScheduleError` naming it."""
    raw = dict(raw)
    kind = raw.pop("kind", None)
    if kind not in KINDS:
        raise ScheduleError(f"fault kind {kind!r}: expected one of {', '.join(KINDS)}")
    if "at" not in raw:
        raise ScheduleError(f"{kind}: no 'at' (seconds after the stack first armed)")
    unknown = set(raw) - _ALLOWED[kind] - {"at"}
    if unknown:
        raise ScheduleError(f"{kind}: unknown parameters {sorted(unknown)}; it takes {sorted(_ALLOWED[kind]) or 'none'}")
    fields: dict[str, Any] = {"kind": kind}
    for key, value in raw.items():
        name = _KEYS[key]
        try:
            if name == "topics":
                value = (value,) if isinstance(value, str) else tuple(str(v) for v in value)
            elif name == "target":
                value = str(value)
            elif name == "cpu":
                value = int(value)
            else:
                value = float(value)
        except (TypeError, ValueError):
            raise ScheduleError(f"{kind}: {key} = {value!r} is not valid") from None
        fields[name] = value
    fault = Fault(**fields)
    if fault.kind in FLOODS and fault.rate_hz == 0.0:
        fault = replace(fault, rate_hz=FLOOD_RATE_HZ if fault.kind == "malformed_flood" else 0.0)
    check_fault(fault)
    return fault


def check_fault(f: Fault) -> None:
    where = f"{f.kind}@{f.at_s:g}"
    if not (math.isfinite(f.at_s) and f.at_s >= 0):
        raise ScheduleError(f"{where}: 'at' must be a time >= 0")
    if f.kind in TARGETED:
        service, _, child = f.target.partition("/")
        if not service or (child and child != CHILD):
            raise ScheduleError(f"{where}: target must be SERVICE or SERVICE/{CHILD}, got {f.target!r}")
    if f.kind in TIMED and not (math.isfinite(f.duration_s) and f.duration_s > 0):
        raise ScheduleError(f"{where}: needs a duration > 0")
    if f.kind == "stall" and not STALL_MIN_S <= f.duration_s <= STALL_MAX_S:
        raise ScheduleError(f"{where}: a stall lasts {STALL_MIN_S:g} .. {STALL_MAX_S:g} s, got {f.duration_s:g}")
    if f.kind == "cpu_hog" and f.cpu < 0:
        raise ScheduleError(f"{where}: cpu must be >= 0")
    if f.kind in FLOODS:
        if not f.topics:
            raise ScheduleError(f"{where}: needs topics")
        unknown = [t for t in f.topics if t not in TOPICS]
        if unknown:
            raise ScheduleError(f"{where}: unknown topics {unknown}; see `archer topics`")
        if f.kind == "bad_stamps":
            binary = [t for t in f.topics if TOPICS[t].msg_type is None]
            if binary:
                raise ScheduleError(f"{where}: {binary} carry a binary layout, not a stamped JSON message")
            if not (math.isfinite(f.offset_s) and f.offset_s != 0.0):
                raise ScheduleError(f"{where}: needs an offset != 0 (seconds; negative: in the past)")
        if f.rate_hz < 0 or not math.isfinite(f.rate_hz):
            raise ScheduleError(f"{where}: rate_hz must be >= 0 (0: the default)")


def parse_schedule(text: str, fmt: str) -> Schedule:
    """A schedule from the text of a ``toml`` or ``json`` file."""
    try:
        data = tomllib.loads(text) if fmt == "toml" else json.loads(text)
    except (tomllib.TOMLDecodeError, json.JSONDecodeError) as exc:
        raise ScheduleError(f"not valid {fmt}: {exc}") from None
    if not isinstance(data, dict):
        raise ScheduleError("a schedule is a table with a 'fault' list")
    unknown = set(data) - {"soak", "fault"}
    if unknown:
        raise ScheduleError(f"unknown top-level keys {sorted(unknown)} (expected 'soak' and 'fault')")
    faults = data.get("fault", [])
    if not isinstance(faults, list) or not all(isinstance(f, dict) for f in faults):
        raise ScheduleError("'fault' must be a list of tables")
    settings = data.get("soak", {})
    if not isinstance(settings, dict):
        raise ScheduleError("'soak' must be a table")
    return Schedule((), settings).merged([fault_from_dict(f) for f in faults])


def load_schedule(path: str | Path) -> Schedule:
    path = Path(path)
    fmt = "json" if path.suffix == ".json" else "toml"
    try:
        text = path.read_text()
    except OSError as exc:
        raise ScheduleError(f"cannot read {path}: {exc}") from None
    return parse_schedule(text, fmt)


def parse_shorthand(spec: str) -> Fault:
    """``KIND@T[:key=value,...]`` (``topics`` joined with ``+``)."""
    head, _, params = spec.partition(":")
    kind, sep, at = head.partition("@")
    if not sep:
        raise ScheduleError(f"{spec!r}: expected KIND@T[:key=value,...]")
    raw: dict[str, Any] = {"kind": kind, "at": at}
    for item in filter(None, params.split(",")):
        key, sep, value = item.partition("=")
        if not sep:
            raise ScheduleError(f"{spec!r}: {item!r} is not key=value")
        raw[key] = value.split("+") if key == "topics" else value
    return fault_from_dict(raw)


def parse_kill(spec: str) -> Fault:
    """The older shorthand ``SERVICE@T``."""
    target, sep, at = spec.rpartition("@")
    if not sep:
        raise ScheduleError(f"--kill {spec!r}: expected SERVICE@T")
    return fault_from_dict({"kind": "kill", "target": target, "at": at})


def check_schedule(schedule: Schedule, duration_s: float, services: list[str]) -> None:
    """Against the run: every fault inside it, one at a time, on a service that runs."""
    units = set(services) | {ROUTER}
    previous: Fault | None = None
    for f in schedule.faults:
        where = f"{f.kind}@{f.at_s:g}"
        if f.end_s >= duration_s:
            raise ScheduleError(f"{where}: ends at {f.end_s:g} s, after the run ({duration_s:g} s)")
        if f.kind in TARGETED and f.service not in units:
            raise ScheduleError(f"{where}: {f.service!r} is not a unit of this run ({', '.join(sorted(units))})")
        if previous is not None and f.at_s < previous.end_s:
            raise ScheduleError(f"{where}: starts before {previous.kind}@{previous.at_s:g} ended; faults run one at a time")
        previous = f
