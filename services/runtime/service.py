"""The service runtime every service shares.

A service module reads top to bottom as: what it subscribes (``setup``), what it
computes with ``onboard`` and publishes, at what rate (``main``). This base gives it:

- an asyncio lifecycle with clean SIGINT/SIGTERM shutdown that never hangs;
- typed publishers and subscribers through the topic table, with strict decoding:
  a malformed payload is rejected, counted and logged once per burst;
- latest-value slots filled from Zenoh's threads (callbacks never block);
- a liveliness token, a status queryable and a parameter queryable (get/set with
  validation);
- achieved-rate meters, counters and the last error for the status;
- a clock (wall or simulated) so the same code runs in real time and against the twin.
"""

from __future__ import annotations

import argparse
import asyncio
import bisect
import json
import logging
import os
import secrets
import signal
import socket
import sys
import threading
import time
from collections import deque
from collections.abc import Awaitable, Callable
from operator import itemgetter
from typing import Any, ClassVar, Generic, TypeVar

import msgspec
import zenoh

from onboard.contracts import messages as msgs
from onboard.contracts.binary_messages import ENCODING as BINARY_ENCODING
from onboard.contracts.commander import UNKNOWN_COMMANDER, CommanderLatch
from onboard.contracts.params import SECTIONS, as_dict, with_overrides
from onboard.contracts.topics import STANDBY_SERVICES, STANDBY_SUFFIX, TOPICS, Topic, liveliness_key, namespace, params_key, status_key
from services.runtime import sd_notify
from services.runtime.clock import Clock, WallClock
from services.runtime.zenoh_session import (Mode, default_endpoint, endpoint_in_use, open_client_session, open_session,
                                            open_tool_session)

JSON_ENCODING = "application/json"
REJECT_LOG_INTERVAL_S = 1.0  # one log line per burst of rejections per topic
SHUTDOWN_GRACE_S = 2.0  # how long main() may take to notice ``stopping``
STOP_WAIT_S = 8.0  # run_until(): teardown and the session's close after that
DONE_POLL_S = 0.1  # run_until(): how often the other thread's event is looked at
EXIT_DEADLINE_S = 2.8  # after a stop signal the process is gone by then, clean or not
ASYNC_QUEUE_DEPTH = 64  # per subscription; the oldest sample is dropped beyond it
PEER_QUERY_TIMEOUT_S = 1.0  # liveliness and status queries to another instance
COMMANDER = "control"  # the one service whose commands reach the motors
PRIMARY_POLL_S = 0.5  # a standby also asks whether the primary's token is there this often (a missed DELETE)
COMMANDER_REQUERY_S = 0.5  # a live commander that has not said who it is is asked again this often
EXIT_CONFLICT = 2  # exit code of a service that found another instance running
EXIT_SIGINT = 128 + signal.SIGINT  # the shell's convention for a run ended by Ctrl-C

M = TypeVar("M")

_RELIABILITY = {"reliable": zenoh.Reliability.RELIABLE, "best_effort": zenoh.Reliability.BEST_EFFORT}
_CONGESTION = {"drop": zenoh.CongestionControl.DROP, "block": zenoh.CongestionControl.BLOCK}
_PRIORITY = {
    "real_time": zenoh.Priority.REAL_TIME,
    "interactive_high": zenoh.Priority.INTERACTIVE_HIGH,
    "data_high": zenoh.Priority.DATA_HIGH,
    "data": zenoh.Priority.DATA,
    "data_low": zenoh.Priority.DATA_LOW,
    "background": zenoh.Priority.BACKGROUND,
}


class JsonLogFormatter(logging.Formatter):
    """One JSON object per line: easy to grep, easy for journald to forward."""

    def format(self, record: logging.LogRecord) -> str:
        entry = {
            "t": round(record.created, 6),
            "level": record.levelname.lower(),
            "logger": record.name,
            "msg": record.getMessage(),
        }
        entry.update(getattr(record, "fields", {}))
        if record.exc_info:
            entry["exc"] = self.formatException(record.exc_info)
        return json.dumps(entry)


def setup_logging(level: str = "INFO") -> None:
    root = logging.getLogger()
    if not any(isinstance(h.formatter, JsonLogFormatter) for h in root.handlers):
        handler = logging.StreamHandler(sys.stderr)
        handler.setFormatter(JsonLogFormatter())
        root.addHandler(handler)
    root.setLevel(level)


class ServiceConflict(RuntimeError):
    """Another instance of this service already runs in this namespace."""


class Counters:
    """Thread-safe named counters (Zenoh callbacks run on Zenoh's threads)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._values: dict[str, int] = {}

    def add(self, name: str, n: int = 1) -> None:
        with self._lock:
            self._values[name] = self._values.get(name, 0) + n

    def get(self, name: str) -> int:
        return self._values.get(name, 0)

    def snapshot(self) -> dict[str, int]:
        with self._lock:
            return dict(self._values)


class RateMeter:
    """Achieved rate over the last window, cheap enough to tick at 1 kHz."""

    def __init__(self, clock: Clock, window_s: float = 1.0) -> None:
        self._clock = clock
        self._window_ns = int(window_s * 1e9)
        self._count = 0
        self._start_ns = clock.now_ns()
        self._rate = 0.0
        self.last_ns = 0

    def tick(self) -> None:
        now = self._clock.now_ns()
        self.last_ns = now
        self._count += 1
        elapsed = now - self._start_ns
        if elapsed >= self._window_ns:
            self._rate = self._count * 1e9 / elapsed
            self._count = 0
            self._start_ns = now

    @property
    def hz(self) -> float:
        elapsed = self._clock.now_ns() - self._start_ns
        if elapsed > 2 * self._window_ns:  # nothing ticked for a while: report the decay
            return self._count * 1e9 / elapsed
        return self._rate


class LatestSlot(Generic[M]):
    """Latest-value input: written by a Zenoh thread, read by a loop without waiting.

    A single tuple assignment is atomic under CPython, so no lock is needed.
    """

    def __init__(self) -> None:
        self._value: tuple[M, int] | None = None
        self._taken_seq = -1
        self._writes = 0

    def put(self, msg: M, recv_ns: int) -> None:
        self._writes += 1
        self._value = (msg, recv_ns)

    def get(self) -> tuple[M, int] | None:
        return self._value

    def take(self) -> tuple[M, int] | None:
        """The latest value if it was not returned by ``take`` before, else None."""
        writes = self._writes
        if writes == self._taken_seq:
            return None
        self._taken_seq = writes
        return self.get()


class LazyLatestSlot(LatestSlot[M]):
    """A :class:`LatestSlot` that keeps raw payloads and decodes on read (see
    :meth:`Service.latest_sampled`); read from one thread."""

    def __init__(self, decode: Callable[[bytes], M], reject: Callable[[Exception], None]) -> None:
        super().__init__()
        self._decode = decode
        self._reject = reject
        self._raw: tuple[bytes, int] | None = None
        self._decoded_from: tuple[bytes, int] | None = None

    def put_payload(self, payload: bytes, recv_ns: int) -> None:
        self._writes += 1
        self._raw = (payload, recv_ns)

    def get(self) -> tuple[M, int] | None:
        raw = self._raw
        if raw is not None and raw is not self._decoded_from:
            self._decoded_from = raw
            try:
                self._value = (self._decode(raw[0]), raw[1])
            except msgs.MessageError as exc:
                self._reject(exc)
        return self._value


class LazyHistory(Generic[M]):
    """The last ``maxlen`` payloads of a topic with their receipt times, decoded (and validated) only
    where a reader looks (see :meth:`Service.sampled_history`). Appended on Zenoh's thread; read
    from another: each read takes a copy in one C call under the GIL."""

    def __init__(self, maxlen: int, decode: Callable[[bytes], M], reject: Callable[[Exception], None]) -> None:
        self._raw: deque[tuple[int, bytes]] = deque(maxlen=maxlen)
        self._decode = decode
        self._reject = reject

    def put_payload(self, payload: bytes, recv_ns: int) -> None:
        self._raw.append((recv_ns, payload))

    def __len__(self) -> int:
        return len(self._raw)

    def _decoded(self, entry: tuple[int, bytes]) -> M | None:
        try:
            return self._decode(entry[1])
        except msgs.MessageError as exc:
            self._reject(exc)
            return None

    def newest(self) -> M | None:
        """The newest message that decodes (None: none yet)."""
        for entry in reversed(list(self._raw)):
            msg = self._decoded(entry)
            if msg is not None:
                return msg
        return None

    def nearest(self, at_ns: int, stamp_of: Callable[[M], int]) -> M | None:
        """The message whose stamp is nearest ``at_ns``: found by receipt time, then a walk over the
        neighbours' stamps (a message is stamped before its receipt, in order), a few decoded."""
        entries = list(self._raw)
        i = bisect.bisect_left(entries, at_ns, key=itemgetter(0))
        best: M | None = None
        for step in (1, -1):  # forward to the first stamp at or after at_ns, back to the last before it
            j = i if step == 1 else i - 1
            while 0 <= j < len(entries):
                msg = self._decoded(entries[j])
                j += step
                if msg is None:
                    continue
                if best is None or abs(stamp_of(msg) - at_ns) < abs(stamp_of(best) - at_ns):
                    best = msg
                if (stamp_of(msg) >= at_ns) if step == 1 else (stamp_of(msg) <= at_ns):
                    break
        return best


class TypedPublisher(Generic[M]):
    """Publishes one topic's messages: fills ``seq`` and, when zero, ``stamp_ns``."""

    def __init__(self, session: zenoh.Session, topic: Topic, ns: str, clock: Clock) -> None:
        self.topic = topic
        self.key = topic.key(ns)
        self._clock = clock
        self._seq = 0
        self._pub = session.declare_publisher(
            self.key,
            encoding=zenoh.Encoding(BINARY_ENCODING if topic.binary else JSON_ENCODING),
            congestion_control=_CONGESTION[topic.congestion],
            priority=_PRIORITY[topic.priority],
            express=topic.express,
            reliability=_RELIABILITY[topic.reliability],
        )

    def put(self, msg: msgspec.Struct) -> None:
        if self.topic.msg_type is None or not isinstance(msg, self.topic.msg_type):
            raise TypeError(f"{self.key} carries {self.topic.msg_type}, not {type(msg).__name__}")
        self._seq += 1
        msg.seq = self._seq
        if msg.stamp_ns == 0:
            msg.stamp_ns = self._clock.now_ns()
        self._pub.put(msgs.encode(msg))

    def put_bytes(self, payload: bytes) -> None:
        """For binary topics, whose encoder already wrote stamp and sequence."""
        if not self.topic.binary:
            raise TypeError(f"{self.key} is a JSON topic")
        self._seq += 1
        self._pub.put(payload)

    def undeclare(self) -> None:
        self._pub.undeclare()


EVERY_TOPIC = ("*",)  # Service.subscribes of a service that reads every topic (the flight recorder)


def check_publisher(service: str, topic_name: str) -> Topic:
    """The topic, if ``service`` is one of its publishers in the topic table; the robot's
    access control (generated from the same column) would deny anything else."""
    topic = TOPICS[topic_name]
    if service not in topic.publishers:
        raise ValueError(f"{service} may not publish {topic_name!r}: the topic table lists {list(topic.publishers)}")
    return topic


class PolledInput:
    """What :meth:`Service.polled` returns: ``drain()`` takes every queued sample, decoded."""

    def __init__(self, subscriber: Any, capacity: int, decode: Callable[[bytes], Any],
                 reject: Callable[[Exception], None], rate: Any) -> None:
        self._sub = subscriber
        self.capacity = capacity
        self._decode = decode
        self._reject = reject
        self._rate = rate

    def close(self) -> None:
        """Undeclare the subscription (a service that subscribes only while it needs a topic)."""
        try:
            self._sub.undeclare()
        except zenoh.ZError:
            pass  # already gone with a closed session

    def drain(self, into: list) -> int:
        """Append the decoded messages to ``into``, oldest first; returns how many samples were
        taken (good or not): ``capacity`` means the ring was full, and older ones may be lost."""
        taken = 0
        try_recv, decode = self._sub.try_recv, self._decode
        while (sample := try_recv()) is not None:
            taken += 1
            try:
                msg = decode(sample.payload.to_bytes())
            except msgs.MessageError as exc:
                self._reject(exc)
                continue
            self._rate.tick()
            into.append(msg)
        return taken


class Service:
    """Base class of every service; see the module docstring."""

    name: ClassVar[str] = "service"
    params_sections: ClassVar[tuple[str, ...]] = ()
    subscribes: ClassVar[tuple[str, ...]] = ()  # the topics it reads (EVERY_TOPIC: all); a subscription to another is refused
    zenoh_mode: ClassVar[Mode] = "peer"

    def __init__(
        self,
        *,
        ns: str | None = None,
        endpoint: str | None = None,
        session: zenoh.Session | None = None,
        clock: Clock | None = None,
        params: dict[str, Any] | None = None,
        config_file: str | None = None,
    ) -> None:
        self.ns = ns or namespace()
        self.endpoint = endpoint or default_endpoint()
        self.clock: Clock = clock or WallClock()
        self.log = logging.getLogger(f"archer.{self.name}")
        self.counters = Counters()
        self.stopping = asyncio.Event()
        self.state = "starting"
        self.last_error = ""
        self.contract_state = "unknown"
        self.params: dict[str, Any] = {s: SECTIONS[s]() for s in self.params_sections}
        for section, obj in (params or {}).items():
            self.params[section] = obj
        self._params_lock = threading.Lock()
        self._own_session = session is None
        self._zenoh_config_file = config_file
        self.session: zenoh.Session = session  # type: ignore[assignment]  # opened in run()
        self._rates: dict[str, RateMeter] = {}
        self._declared: list[Any] = []
        self._tasks: list[asyncio.Task] = []
        self._last_reject_log: dict[str, float] = {}
        self._aio_loop: asyncio.AbstractEventLoop | None = None
        self._started_ns = 0
        self.instance = secrets.token_hex(8)  # this run of the service; its commands carry it
        self.started_unix_s = time.time()
        self._latch: CommanderLatch | None = None  # built by the first commands() slot
        self._set_up = False  # setup() was entered: teardown() has something to release
        self._serving_endpoint = self.zenoh_mode == "router"  # a router binds the endpoint: nobody else can
        self.role = "primary"  # or "standby" (standby_capable services that found a primary running)
        self.promoted = threading.Event()  # a standby took over (set on the event loop)
        self.promoted_mono_ns = 0  # when it did (time.monotonic_ns)
        self._identity: list[Any] = []  # status and params queryables and the token, under the name in use
        self.primary_status: msgs.ServiceStatus | None = None  # a standby: the primary's status when it started

    # --- what subclasses override -------------------------------------------------

    async def setup(self) -> None:
        """Declare subscriptions and publishers."""

    async def main(self) -> None:
        """Run until ``self.stopping`` is set."""
        await self.stopping.wait()

    async def teardown(self) -> None:
        """Release what ``setup`` acquired beyond Zenoh entities (those go automatically)."""

    def status_extra(self) -> dict[str, float]:
        return {}

    def progress(self) -> bool:
        """Whether the service made progress since the last call (gates WATCHDOG=1).

        The check runs on the event loop, so a blocked loop already stops the
        pings. Override when the work happens elsewhere: a DeadlineLoop thread
        returns whether its tick count advanced and it has no error.
        """
        return True

    @property
    def standby_capable(self) -> bool:
        """A second instance runs as the hot standby (one at most) instead of exiting: same inputs,
        nothing published, and it takes over when the first one's token goes (STANDBY_SERVICES)."""
        return self.name in STANDBY_SERVICES

    def fence_pid(self) -> int:
        """A standby: the pid of the primary it found, when that runs on this host (0: none), for a fence
        (kill -9) of a primary that hangs with its token declared (the token outlives a hung process by
        the link's lease, seconds: the robot would fall meanwhile)."""
        st = self.primary_status
        return st.pid if self.role == "standby" and st is not None and st.host == socket.gethostname() else 0

    def on_promoted(self) -> None:
        """Called on the event loop the moment a standby took over (token and status declared under
        the service's own name): start publishing now. Must not block."""

    def accept_params(self, updated: dict[str, Any]) -> None:
        """Raise ValueError to refuse validated new sections the service cannot take in
        its current state (called on a Zenoh thread, under the parameter lock)."""

    def on_params_changed(self, section: str) -> None:
        """Called (on a Zenoh thread) after a validated parameter change, under the
        parameter lock: changes apply one at a time, in the order they were accepted."""

    # --- messaging ----------------------------------------------------------------

    def publisher(self, topic_name: str) -> TypedPublisher:
        pub = TypedPublisher(self.session, check_publisher(self.name, topic_name), self.ns, self.clock)
        self._declared.append(pub)
        return pub

    def _decoder(self, topic: Topic) -> Callable[[bytes], Any]:
        if topic.binary:
            from onboard.contracts import binary_messages as bm

            return bm.DECODERS[topic.binary]
        msg_type = topic.msg_type
        return lambda payload: msgs.decode(payload, msg_type)

    def _reject(self, topic: Topic, exc: Exception, counter: str | None = None) -> None:
        counter = counter or f"rejected.{topic.name}"
        self.counters.add(counter)
        now = time.monotonic()
        if now - self._last_reject_log.get(counter, 0.0) >= REJECT_LOG_INTERVAL_S:
            self._last_reject_log[counter] = now
            total = self.counters.get(counter)
            self.log.warning("rejected message", extra={"fields": {"topic": topic.name, "error": str(exc), "counter": counter, "rejected_total": total}})

    def _reads(self, topic_name: str) -> Topic:
        if self.subscribes != EVERY_TOPIC and topic_name not in self.subscribes:
            raise ValueError(f"{self.name} subscribes to {topic_name!r}, which its declared reads {list(self.subscribes)} "
                             "do not list (Service.subscribes, shown by `archer services`)")
        return TOPICS[topic_name]

    def on_message(self, topic_name: str, deliver: Callable[[Any], None]) -> None:
        """Call ``deliver(msg)`` on a Zenoh thread for every message that decodes.

        ``deliver`` must not block (append to a deque, fill a slot, hand over to a
        loop). Rejected payloads are counted and logged here, never delivered.
        """
        topic = self._reads(topic_name)
        decode = self._decoder(topic)
        rate = self.rate(f"rx.{topic_name}")

        def on_sample(sample: zenoh.Sample) -> None:
            try:
                msg = decode(sample.payload.to_bytes())
            except msgs.MessageError as exc:
                self._reject(topic, exc)
                return
            rate.tick()
            deliver(msg)

        self._declared.append(self.session.declare_subscriber(topic.key(self.ns), on_sample))

    def polled(self, topic_name: str, capacity: int) -> PolledInput:
        """A subscription whose samples wait in Zenoh's own ring buffer (``capacity``, the oldest
        dropped beyond) until the caller's thread drains them: no Python callback thread.

        For a hard-rate loop's inputs: a callback thread per sample competes with the loop for
        the GIL, which is not priority-aware, so a flood on an input topic (5 kHz of malformed
        payloads) delayed the SCHED_FIFO estimator loop by tens of milliseconds. Drained on the
        loop's thread, each sample costs the loop its decode and nothing else. Rejections are
        counted and logged as for any subscription.
        """
        topic = self._reads(topic_name)
        sub = self.session.declare_subscriber(topic.key(self.ns), zenoh.handlers.RingChannel(capacity))
        self._declared.append(sub)
        return PolledInput(sub, capacity, self._decoder(topic), lambda exc: self._reject(topic, exc),
                           self.rate(f"rx.{topic_name}"))

    def latest(self, topic_name: str) -> LatestSlot:
        """A latest-value slot kept current by a Zenoh subscription."""
        slot: LatestSlot = LatestSlot()
        self.on_message(topic_name, lambda msg: slot.put(msg, self.clock.now_ns()))
        return slot

    def latest_sampled(self, topic_name: str) -> LazyLatestSlot:
        """A latest-value slot that decodes (and validates) only what its reader takes.

        For a fast topic read now and then (the twin's metrics read the 1 kHz estimate
        every tenth tick): every payload is kept, only the one read is decoded. A
        payload that fails to decode is counted and logged as usual, and the read
        returns the last good value.
        """
        topic = self._reads(topic_name)
        rate = self.rate(f"rx.{topic_name}")
        slot = LazyLatestSlot(self._decoder(topic), lambda exc: self._reject(topic, exc))

        def on_sample(sample: zenoh.Sample) -> None:
            rate.tick()
            slot.put_payload(sample.payload.to_bytes(), self.clock.now_ns())

        self._declared.append(self.session.declare_subscriber(topic.key(self.ns), on_sample))
        return slot

    def sampled_history(self, topic_name: str, maxlen: int) -> LazyHistory:
        """The last ``maxlen`` payloads of a topic, decoded (and validated) only where the reader looks.

        For a fast topic searched now and then (the camera service places a few frames a second by
        the 1 kHz estimate): decoding and validating every message cost the camera's process more
        than its work. A payload that fails to decode when read is counted and logged as usual.
        """
        topic = self._reads(topic_name)
        rate = self.rate(f"rx.{topic_name}")
        history: LazyHistory = LazyHistory(maxlen, self._decoder(topic), lambda exc: self._reject(topic, exc))

        def on_sample(sample: zenoh.Sample) -> None:
            rate.tick()
            history.put_payload(sample.payload.to_bytes(), self.clock.now_ns())

        self._declared.append(self.session.declare_subscriber(topic.key(self.ns), on_sample))
        return history

    def subscribe(self, topic_name: str, callback: Callable[[Any], Awaitable[None]]) -> None:
        """Deliver each decoded message to ``callback`` on the asyncio loop."""
        queue: asyncio.Queue = asyncio.Queue(ASYNC_QUEUE_DEPTH)
        loop = self._aio_loop
        assert loop is not None, "subscribe() belongs in setup()"

        def offer(msg: Any) -> None:  # on the loop thread
            if queue.full():
                queue.get_nowait()
                self.counters.add(f"dropped.{topic_name}")
            queue.put_nowait(msg)

        async def consume() -> None:
            while True:
                msg = await queue.get()
                try:
                    await callback(msg)
                except Exception as exc:  # a bad message must not kill the service
                    self.fail(f"{topic_name} handler: {exc!r}")
                    self.log.exception("handler failed", extra={"fields": {"topic": topic_name}})

        self._tasks.append(loop.create_task(consume(), name=f"{self.name}.{topic_name}"))
        self.on_message(topic_name, lambda msg: loop.call_soon_threadsafe(offer, msg))

    def commands(self, topic_name: str) -> LatestSlot:
        """A latest-value slot of motor commands that only the live commander fills.

        The one-commander rule of :mod:`onboard.contracts.commander`: the commander's liveliness
        token and its status (its instance id) are watched here; a command from any
        other instance, or while no commander is alive, never reaches the slot (so a
        flood of forged commands cannot even displace the real ones), and is counted
        (``rejected.<reason>``) and logged once per burst.
        """
        topic = TOPICS[topic_name]
        latch = self._commander_latch()
        slot: LatestSlot = LatestSlot()
        last_query = [0.0]

        def deliver(msg: Any) -> None:  # Zenoh thread
            now = self.clock.now_ns()
            reason = latch.refusal(msg.commander, msg.seq, now)
            if reason is None:
                slot.put(msg, now)
                return
            if reason == UNKNOWN_COMMANDER and time.monotonic() - last_query[0] > COMMANDER_REQUERY_S:
                last_query[0] = time.monotonic()
                self._ask_commander(latch)
            self._reject(topic, ValueError(f"{reason}: {msg.commander!r}"), counter=f"rejected.{reason}")

        self.on_message(topic_name, deliver)
        return slot

    @property
    def commander_latch(self) -> CommanderLatch | None:
        """Whose commands this service obeys (None: it takes no commands)."""
        return self._latch

    def _commander_latch(self) -> CommanderLatch:
        if self._latch is not None:
            return self._latch
        latch = self._latch = CommanderLatch()

        def on_liveliness(sample: zenoh.Sample) -> None:  # Zenoh thread
            if sample.kind == zenoh.SampleKind.PUT:
                latch.commander_appeared()
                self._ask_commander(latch)
            else:
                was = latch.instance
                latch.commander_gone()
                self.log.warning("commander gone", extra={"fields": {"instance": was}})

        key = liveliness_key(self.ns, COMMANDER)
        self._declared.append(self.session.liveliness().declare_subscriber(key, on_liveliness, history=True))
        return latch

    def _ask_commander(self, latch: CommanderLatch) -> None:
        """Ask the live commander's status who it is (the reply arrives on a Zenoh thread)."""

        def on_reply(reply: zenoh.Reply) -> None:
            if reply.ok is None:
                return
            try:
                st = msgs.decode(reply.ok.payload.to_bytes(), msgs.ServiceStatus)
            except msgs.MessageError:
                self.count("rejected.commander_status")
                return
            before = latch.instance
            if latch.commander_identified(st.instance) and before is None:
                self.log.info("commander latched", extra={"fields": {"instance": st.instance, "host": st.host, "pid": st.pid}})
            elif latch.instance != st.instance:
                self.count("commander_conflicts")
                self.log.error("a second commander answered; keeping the first",
                               extra={"fields": {"kept": latch.instance, "refused": st.instance, "host": st.host, "pid": st.pid}})

        self.session.get(status_key(self.ns, COMMANDER), on_reply, timeout=PEER_QUERY_TIMEOUT_S)

    # --- health -----------------------------------------------------------------------

    def rate(self, name: str) -> RateMeter:
        meter = self._rates.get(name)
        if meter is None:
            meter = self._rates[name] = RateMeter(self.clock)
        return meter

    def rates_hz(self) -> dict[str, float]:
        """Every rate meter's current figure [Hz] (cheap: no status extras)."""
        return {name: m.hz for name, m in self._rates.items()}

    def count(self, name: str, n: int = 1) -> None:
        self.counters.add(name, n)

    def fail(self, message: str) -> None:
        self.last_error = message
        self.counters.add("errors")

    def status(self) -> msgs.ServiceStatus:
        now = self.clock.now_ns()
        return msgs.ServiceStatus(
            stamp_ns=now,
            service=self.name,
            state=self.state,
            uptime_s=(now - self._started_ns) / 1e9,
            rates_hz={name: round(hz, 2) for name, hz in self.rates_hz().items()},
            counters=self.counters.snapshot(),
            last_error=self.last_error,
            contract=self.contract_state,
            # before setup() has run, a service's own figures do not exist yet
            # a hot standby says so from the start (services that may have one: 0 for the primary)
            extra={**({} if self.state == "starting" else {k: float(v) for k, v in self.status_extra().items()}),
                   **({"standby": float(self.role == "standby")} if self.standby_capable else {})},
            instance=self.instance,
            host=socket.gethostname(),
            pid=os.getpid(),
            started_unix_s=self.started_unix_s,
        )

    def _on_status_query(self, query: zenoh.Query) -> None:
        query.reply(query.key_expr, msgs.encode(self.status()), encoding=zenoh.Encoding(JSON_ENCODING))

    def _on_params_query(self, query: zenoh.Query) -> None:
        error = ""
        payload = query.payload.to_bytes() if query.payload is not None else b""
        if payload:
            try:
                request = msgspec.json.decode(payload, type=msgs.ParamRequest)
                self.set_params(request.set)
            except (msgspec.DecodeError, msgspec.ValidationError, ValueError) as exc:
                error = str(exc)
                self.count("rejected.params")
        reply = msgs.ParamReply(params=self.flat_params(), error=error)
        query.reply(query.key_expr, msgspec.json.encode(reply), encoding=zenoh.Encoding(JSON_ENCODING))

    def flat_params(self) -> dict[str, Any]:
        out: dict[str, Any] = {}
        for section, obj in self.params.items():
            for key, value in as_dict(obj).items():
                if isinstance(value, (int, float, bool, str)):
                    out[f"{section}.{key}"] = value
        return out

    def set_params(self, changes: dict[str, Any]) -> None:
        """Apply ``{"section.name": value}``, all or nothing, validated."""
        by_section: dict[str, dict[str, Any]] = {}
        for dotted, value in changes.items():
            section, _, name = dotted.partition(".")
            if section not in self.params or not name:
                raise ValueError(f"{self.name} has no parameter {dotted!r}")
            by_section.setdefault(section, {})[name] = value
        with self._params_lock:
            updated = {s: with_overrides(self.params[s], ch) for s, ch in by_section.items()}
            self.accept_params(updated)
            self.params.update(updated)
            for section in updated:
                self.log.info("parameters changed", extra={"fields": {"section": section, "changes": by_section[section]}})
                self.on_params_changed(section)

    # --- lifecycle ----------------------------------------------------------------------

    def _open_session(self) -> zenoh.Session | None:
        mode = self.zenoh_mode
        if mode == "client":  # a person's tool: waits for the stack, never serves its endpoint (None: stopped first)
            return open_tool_session(self.endpoint, self._zenoh_config_file, stopped=self.stopping.is_set)
        if mode == "peer" and not self._zenoh_config_file and not endpoint_in_use(self.endpoint):
            # No router yet: this service serves the well-known endpoint itself.
            try:
                session = open_session(self.endpoint, "router")
                self._serving_endpoint = True
                return session
            except zenoh.ZError:
                pass  # another process won the race; join it as a peer
        return open_session(self.endpoint, mode, self._zenoh_config_file)

    async def run(self) -> None:
        self._aio_loop = asyncio.get_running_loop()
        self._started_ns = self.clock.now_ns()
        if self.session is None:
            self.session = await asyncio.to_thread(self._open_session)
            if self.session is None:
                return  # stopped while waiting for the stack
        try:
            if await asyncio.to_thread(self._refuse_if_running):
                self.role = "standby"
            self._declare_identity(self.name if self.role == "primary" else self.name + STANDBY_SUFFIX)
            self._set_up = True
            await self.setup()
            if self.role == "standby":
                self._watch_primary()
            self.state = "running"
            self._tasks.append(asyncio.create_task(sd_notify.keep_alive(self), name=f"{self.name}.sd_notify"))
            self.log.info("started", extra={"fields": {"ns": self.ns, "endpoint": self.endpoint}})
            main = asyncio.create_task(self.main(), name=f"{self.name}.main")
            stop = asyncio.create_task(self.stopping.wait())
            done, _ = await asyncio.wait({main, stop}, return_when=asyncio.FIRST_COMPLETED)
            if main in done:
                main.result()  # re-raise a crash of main()
            else:
                try:
                    await asyncio.wait_for(main, SHUTDOWN_GRACE_S)
                except asyncio.TimeoutError:
                    self.log.warning("main() ignored stop; cancelled")
            stop.cancel()
        except Exception as exc:
            self.state = "error"
            self.fail(repr(exc))
            raise
        finally:
            self.state = "stopping"
            await self._close()

    def _declare_identity(self, as_name: str) -> None:
        """Status and parameter queryables and the liveliness token under ``as_name``; answerable
        before announced: whoever sees the token asks the status who we are."""
        self._identity = [
            self.session.declare_queryable(status_key(self.ns, as_name), self._on_status_query),
            self.session.declare_queryable(params_key(self.ns, as_name), self._on_params_query),
            self.session.liveliness().declare_token(liveliness_key(self.ns, as_name)),
        ]
        self._declared.extend(self._identity)

    def withdraw(self) -> None:
        """Undeclare this instance's token and queryables now (a primary whose work stopped: its
        standby takes over at once, and no late status reply of ours can name us commander)."""
        for entity in reversed(self._identity):
            try:
                entity.undeclare()
            except zenoh.ZError:
                pass
            if entity in self._declared:
                self._declared.remove(entity)
        self._identity = []

    def _watch_primary(self) -> None:
        """A standby: take over when the primary's token goes (or is gone already)."""

        def on_liveliness(sample: zenoh.Sample) -> None:  # Zenoh thread
            if sample.kind == zenoh.SampleKind.DELETE:
                self.call_in_loop(self._promote)

        key = liveliness_key(self.ns, self.name)
        self._declared.append(self.session.liveliness().declare_subscriber(key, on_liveliness, history=False))

        async def poll() -> None:
            # gone between the probe and the subscription (no DELETE will come), or a DELETE missed: asked again
            # twice in a row: a query that timed out on a loaded machine looks the same as no token
            empty = 0
            while self.role == "standby" and not self.stopping.is_set():
                replies = await asyncio.to_thread(lambda: list(self.session.liveliness().get(key, timeout=PEER_QUERY_TIMEOUT_S)))
                empty = 0 if any(r.ok is not None for r in replies) else empty + 1
                if empty >= 2:
                    self.log.warning("primary's token found gone by asking (no DELETE seen)")
                    self._promote()
                    return
                await asyncio.sleep(PRIMARY_POLL_S)

        self._tasks.append(asyncio.create_task(poll(), name=f"{self.name}.watch_primary"))

    def _promote(self) -> None:
        """On the event loop: the primary's token is gone; declare ours under the service's name and
        start publishing (the one-commander latch re-forms on us: onboard/contracts/commander.py)."""
        if self.role != "standby" or self.stopping.is_set():
            return
        self.withdraw()  # the standby token and queryables
        self.role = "primary"
        self._declare_identity(self.name)
        self.promoted_mono_ns = time.monotonic_ns()
        self.promoted.set()
        self.on_promoted()
        self.log.warning("took over from the primary", extra={"fields": {"instance": self.instance}})

    def _refuse_if_running(self) -> bool:
        """Raise :class:`ServiceConflict` when this service's token is already declared:
        two estimators, or two commanders on one set of motors, must never run. A service that
        may stand by (``standby_capable``) returns True instead (it runs as the standby) unless a
        standby runs already.

        Asked through a client session of its own: this service's peer session may not
        have learnt the router's tokens yet. A service that serves the endpoint itself
        (no router was there) is alone by construction."""
        if self._serving_endpoint:
            return False
        probe = open_client_session(self.endpoint, self._zenoh_config_file)
        try:
            key = liveliness_key(self.ns, self.name)
            if not any(r.ok is not None for r in probe.liveliness().get(key, timeout=PEER_QUERY_TIMEOUT_S)):
                return False
            other = "no status reply"
            for reply in probe.get(status_key(self.ns, self.name), timeout=PEER_QUERY_TIMEOUT_S):
                if reply.ok is None:
                    continue
                try:
                    st = msgs.decode(reply.ok.payload.to_bytes(), msgs.ServiceStatus)
                except msgs.MessageError:
                    continue
                self.primary_status = st
                started = time.strftime("%Y-%m-%d %H:%M:%S", time.localtime(st.started_unix_s))
                other = f"host {st.host}, pid {st.pid}, started {started}, instance {st.instance}"
            standby_key = liveliness_key(self.ns, self.name + STANDBY_SUFFIX)
            if self.standby_capable and not any(r.ok is not None for r in probe.liveliness().get(standby_key, timeout=PEER_QUERY_TIMEOUT_S)):
                return True
        finally:
            probe.close()
        also = " with its standby" if self.standby_capable else ""
        raise ServiceConflict(f"{self.name} already runs under {self.ns} ({other}){also}; stop it first")

    async def _close(self) -> None:
        for task in self._tasks:
            task.cancel()
        await asyncio.gather(*self._tasks, return_exceptions=True)
        self._tasks.clear()
        try:
            if self._set_up:
                await self.teardown()
        finally:
            for entity in reversed(self._declared):
                try:
                    entity.undeclare()
                except zenoh.ZError:
                    pass  # already gone with a closed session
            self._declared.clear()
            if self._own_session and self.session is not None:
                await asyncio.to_thread(self.session.close)
            self.log.info("stopped")

    def run_until(self, done: threading.Event) -> None:
        """Run the service on an event loop of this thread's own until ``done`` is set by another
        thread, or the service ends by itself (a crash: raised here, and in ``last_error``)."""

        async def serve() -> None:
            task = asyncio.create_task(self.run())
            while not done.is_set() and not task.done():
                await asyncio.sleep(DONE_POLL_S)
            self.stopping.set()
            await asyncio.wait_for(task, SHUTDOWN_GRACE_S + STOP_WAIT_S)

        asyncio.run(serve())

    def call_in_loop(self, fn: Callable[..., Any], *args: Any) -> None:
        """Run ``fn(*args)`` on the service's event loop; safe from any thread."""
        if self._aio_loop is not None:
            self._aio_loop.call_soon_threadsafe(fn, *args)

    def request_stop(self) -> None:
        """Thread-safe stop request."""
        self.call_in_loop(self.stopping.set)


class StandInCommander:
    """What a torque consumer needs to obey a publisher that is not the control service
    (a bench, a test): the commander's liveliness token and a status naming an instance
    id, which the publisher's commands carry (``commander=stand_in.instance``)."""

    def __init__(self, session: zenoh.Session, ns: str) -> None:
        self.instance = secrets.token_hex(8)
        self._seq = 0
        self._started_ns = time.monotonic_ns()
        self._entities = [  # answerable before announced, as a service
            session.declare_queryable(status_key(ns, COMMANDER), self._on_status_query),
            session.liveliness().declare_token(liveliness_key(ns, COMMANDER)),
        ]

    def _on_status_query(self, query: zenoh.Query) -> None:
        status = msgs.ServiceStatus(service=COMMANDER, state="running", uptime_s=(time.monotonic_ns() - self._started_ns) / 1e9,
                                    rates_hz={}, counters={}, instance=self.instance, host=socket.gethostname(), pid=os.getpid())
        query.reply(query.key_expr, msgs.encode(status), encoding=zenoh.Encoding(JSON_ENCODING))

    def next_seq(self) -> int:
        """The number of this commander's next command: a consumer obeys one stream, each number
        after the last (:mod:`onboard.contracts.commander`)."""
        self._seq += 1
        return self._seq

    def close(self) -> None:
        for entity in self._entities:
            entity.undeclare()


def fence(pid: int, service: str) -> bool:
    """kill -9 ``pid`` if it still is an ``archer run <service>`` process (not a reused pid); True
    when it was. A hot standby's fence of a hung primary."""
    try:
        argv = open(f"/proc/{pid}/cmdline", "rb").read().split(b"\0")
    except OSError:
        return False
    if b"run" not in argv or service.encode() not in argv:
        return False
    try:
        os.kill(pid, signal.SIGKILL)
    except OSError:
        return False
    return True


def add_service_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--config", help="TOML file overriding parameters by section")
    parser.add_argument("--endpoint", help="Zenoh endpoint (default tcp/127.0.0.1:7447 or $ARCHER_ZENOH_ENDPOINT)")
    parser.add_argument("--zenoh-config", help="Zenoh JSON5 config file (see deploy/zenoh/)")
    parser.add_argument("--namespace", help="key namespace (default archer/robot0 or $ARCHER_NAMESPACE)")
    parser.add_argument("--log-level", default="INFO")


def exit_by_deadline(code: int, deadline_s: float = EXIT_DEADLINE_S) -> None:
    """Make sure this process is gone ``deadline_s`` from now, with ``code``, whatever
    its clean-up is stuck on (a Zenoh close, a child that does not answer)."""

    def force() -> None:
        logging.getLogger("archer").error("clean shutdown overran; exiting", extra={"fields": {"deadline_s": deadline_s}})
        os._exit(code)

    timer = threading.Timer(deadline_s, force)
    timer.daemon = True
    timer.start()


def stop_signal_exit_code(sig: int) -> int:
    """0 for SIGTERM (a requested stop), 130 for SIGINT (the shell's Ctrl-C convention)."""
    return EXIT_SIGINT if sig == signal.SIGINT else 0


def run_service(service: Service) -> int:
    """Run ``service`` until SIGINT/SIGTERM; returns the process exit code: 0 after SIGTERM,
    130 after SIGINT, 2 when another instance runs, 1 on a crash."""
    exit_code = 0

    def on_signal(sig: int) -> None:
        nonlocal exit_code
        if service.stopping.is_set():
            return
        exit_code = stop_signal_exit_code(sig)
        exit_by_deadline(exit_code)
        service.stopping.set()

    async def runner() -> None:
        loop = asyncio.get_running_loop()
        for sig in (signal.SIGINT, signal.SIGTERM):
            # also where the caller left SIGINT ignored (a background job of a script)
            loop.add_signal_handler(sig, on_signal, sig)
        await service.run()

    try:
        asyncio.run(runner())
    except ServiceConflict as exc:
        print(f"archer run: {exc}", file=sys.stderr)
        return EXIT_CONFLICT
    except Exception:
        service.log.exception("service crashed")
        return 1
    return exit_code
