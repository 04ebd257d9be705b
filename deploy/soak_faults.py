"""What the chaos soak (:mod:`deploy.sil_soak`) does to a running stack, and its helper processes.

Process faults act on the units that ``archer sim --mode realtime`` supervises, found as the
sim's child processes (``archer run SERVICE``); ``SERVICE/child`` is that process's
multiprocessing child (the control loop). Load and message faults run in helper processes of
their own, started with ``python -m deploy.soak_faults hog|flood``; each dies with the soak
(``PR_SET_PDEATHSIG``) and ends by itself after its duration.

- ``hog``: a busy loop pinned to one core (``os.sched_setaffinity``).
- ``flood --mode malformed``: payloads no decoder of the stack may accept (not JSON, the
  wrong type, unknown or missing fields, wrong array lengths, non-finite numbers, an unknown
  schema version, a torn binary header), each checked against :func:`onboard.contracts.messages.decode`
  before it is sent.
- ``flood --mode stamps``: well-formed messages (a copy of the latest live one on the topic;
  a schema example where nothing is live) stamped ``offset`` seconds from now, ``seq`` 0 so
  that no sequence check takes them for the real publisher's.

Each helper is started with the stack, before it arms (a starved host takes seconds to import and open a
session), prints ``READY_LINE`` once set up (a flood: its session open), waits for ``GO_LINE`` on
stdin, then acts, and prints one JSON line of what it did when it ends (nothing, if stdin closes
first: the soak went away).
"""

from __future__ import annotations

import argparse
import json
import os
import select
import signal
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

CHILD_MARKER = b"spawn_main"  # argv of a multiprocessing child (not its resource tracker)
REAP_POLL_S = 0.001
LIVE_COPY_WAIT_S = 1.0  # a stamps flood waits this long for a live message to copy
READY_LINE = "ready"  # a helper's first line: its start-up (imports, session) is over
GO_LINE = "go"  # the soak's word on the helper's stdin: the fault begins now


# --- finding and signalling the stack's processes -------------------------------------------------


KERNEL_LISTS_CHILDREN = Path(f"/proc/{os.getpid()}/task/{os.getpid()}/children").exists()  # CONFIG_PROC_CHILDREN


def children(pid: int) -> list[tuple[int, list[bytes]]]:
    """``(pid, argv)`` of the live processes whose parent is ``pid``.

    From the kernel's list of each of its threads' children: a scan of all of ``/proc`` read the
    ``stat`` of every kernel thread too, 0.1-0.5 s each on a loaded VM, and a fault went in 4-8 s
    late. The scan stays for a kernel built without that list."""
    if not KERNEL_LISTS_CHILDREN:
        kids = [int(e.name) for e in Path("/proc").iterdir() if e.name.isdigit()]
    else:
        try:
            tasks = list(Path(f"/proc/{pid}/task").iterdir())
        except OSError:
            return []  # pid itself is gone
        found: set[int] = set()
        for task in tasks:
            try:
                found.update(int(k) for k in (task / "children").read_text().split())
            except OSError:
                continue  # a thread that ended meanwhile (its children went to another thread)
        kids = sorted(found)
    out = []
    for kid in kids:
        entry = Path(f"/proc/{kid}")
        try:
            stat = (entry / "stat").read_text()
            fields = stat.rsplit(")", 1)[1].split()
            state, ppid = fields[0], int(fields[1])
            cmd = (entry / "cmdline").read_bytes().split(b"\0")
        except (OSError, IndexError, ValueError):
            continue
        if ppid == pid and state != "Z":
            out.append((kid, cmd))
    return out


def unit_pid(sim_pid: int, service: str) -> int | None:
    """The main process of ``archer run SERVICE`` under the sim's supervisor."""
    name = service.encode()
    return next((pid for pid, cmd in children(sim_pid) if b"run" in cmd and name in cmd), None)


def loop_child_pid(main_pid: int) -> int | None:
    return next((pid for pid, cmd in children(main_pid) if any(CHILD_MARKER in part for part in cmd)), None)


def target_pid(sim_pid: int, target: str) -> int | None:
    """``SERVICE``: its main process; ``SERVICE/child``: that process's loop child."""
    service, _, child = target.partition("/")
    main = unit_pid(sim_pid, service)
    return loop_child_pid(main) if main is not None and child else main


def signal_unit(pid: int, sig: int, whole_unit: bool) -> list[int]:
    """Send ``sig`` to ``pid``, or to its whole unit: the process group the supervisor gave it
    (``pid`` leads one), else ``pid`` and its children. Returns the pids signalled."""
    if whole_unit:
        try:
            if os.getpgid(pid) == pid:
                os.killpg(pid, sig)
                return [pid]
        except ProcessLookupError:
            return []
    pids = [pid] + ([p for p, _ in children(pid)] if whole_unit else [])
    sent = []
    for p in pids:
        try:
            os.kill(p, sig)
            sent.append(p)
        except ProcessLookupError:
            pass
    return sent


@dataclass
class ExitWatch:
    """When a killed process exited (its pidfd) and when its parent reaped it (the parent noticed)."""

    pid: int
    exited_ns: int | None = None
    reaped_ns: int | None = None

    def start(self, timeout_s: float) -> threading.Thread:
        try:
            fd = os.pidfd_open(self.pid)
        except OSError:
            fd = None  # gone already; the reap poll still answers
        thread = threading.Thread(target=self._run, args=(fd, timeout_s), name=f"exit-watch-{self.pid}", daemon=True)
        thread.start()
        return thread

    def _run(self, fd: int | None, timeout_s: float) -> None:
        deadline = time.monotonic() + timeout_s
        try:
            if fd is not None and select.select([fd], [], [], timeout_s)[0]:
                self.exited_ns = time.monotonic_ns()
            while time.monotonic() < deadline:
                if not _exists(self.pid):
                    self.reaped_ns = time.monotonic_ns()
                    if self.exited_ns is None:
                        self.exited_ns = self.reaped_ns
                    return
                time.sleep(REAP_POLL_S)
        finally:
            if fd is not None:
                os.close(fd)


def _exists(pid: int) -> bool:
    """The process is there, a zombie included (not yet reaped)."""
    return Path(f"/proc/{pid}").exists()


def helper_argv(mode: str, *args: str) -> list[str]:
    """``python -m deploy.soak_faults MODE ... --parent THIS_PID``: dies with this process."""
    return [sys.executable, "-m", "deploy.soak_faults", mode, *args, "--parent", str(os.getpid())]


# --- the helper processes -------------------------------------------------------------------------


def ready_then_go() -> None:
    """Say the set-up is over; return at the soak's word, exit at once if it never comes."""
    print(READY_LINE, flush=True)
    if sys.stdin.readline().strip() != GO_LINE:
        sys.exit(0)


def run_hog(cpu: int, duration_s: float) -> dict[str, Any]:
    os.sched_setaffinity(0, {cpu})
    ready_then_go()
    deadline = time.monotonic() + duration_s
    spins = 0
    while time.monotonic() < deadline:
        spins += 1
    return {"hog_cpu": cpu, "duration_s": duration_s, "spins": spins}


def example(type_info: Any) -> Any:
    """A value that decodes as ``type_info`` (a :mod:`msgspec.inspect` type): zeros, first choices."""
    import msgspec.inspect as mi

    t = type_info
    if isinstance(t, mi.StructType):
        return {f.encode_name: example(f.type) for f in t.fields if f.required}
    if isinstance(t, mi.ListType):
        return [example(t.item_type) for _ in range(t.min_length or 0)]
    if isinstance(t, mi.LiteralType):
        return t.values[0]
    if isinstance(t, mi.UnionType):
        return example(next(u for u in t.types if not isinstance(u, mi.NoneType)))
    if isinstance(t, mi.DictType):
        return {}
    if isinstance(t, mi.BoolType):
        return False
    if isinstance(t, mi.IntType):
        return 0
    if isinstance(t, mi.FloatType):
        return 0.0
    if isinstance(t, mi.StrType):
        return ""
    raise TypeError(f"no example for {t}")


def malformed_payloads(topic_name: str) -> list[bytes]:
    """Payloads of ``topic_name`` that its decoder must refuse (each is checked here)."""
    import msgspec

    from onboard.contracts import binary_messages as bm
    from onboard.contracts import messages as m
    from onboard.contracts.topics import TOPICS

    topic = TOPICS[topic_name]
    garbage = [b"", b"\xff\xfe\x00garbage", b"{", b"null", b"[1, 2, 3]", b'"a string"']
    if topic.msg_type is None:
        decode = bm.DECODERS[topic.binary]
        candidates = garbage + [b"\x00" * 24, os.urandom(64)]
    else:
        base = example(msgspec.inspect.type_info(topic.msg_type))

        def dumps(obj: dict[str, Any]) -> bytes:  # compact, as msgspec writes; inf as a number literal
            return json.dumps(obj, separators=(",", ":")).replace("Infinity", "1e999").encode()

        candidates = garbage + [
            dumps({**base, "unknown_field": 1}),
            dumps({**base, "version": 99}),
            dumps({**base, "stamp_ns": "now"}),
        ]
        for key, value in base.items():
            candidates.append(dumps({k: v for k, v in base.items() if k != key}))  # a field missing
            if isinstance(value, list):
                candidates.append(dumps({**base, key: value + [0.0]}))  # one element too many
            if isinstance(value, list) and value and isinstance(value[0], float):
                candidates.append(dumps({**base, key: [float("inf")] + value[1:]}))
            if isinstance(value, float):
                candidates.append(dumps({**base, key: float("inf")}))
        msg_type = topic.msg_type

        def decode(payload: bytes) -> Any:
            return m.decode(payload, msg_type)

    refused = []
    for payload in candidates:
        try:
            decode(payload)
        except (m.MessageError, ValueError):
            refused.append(payload)
    return refused


def run_flood(endpoint: str, ns: str, topics: list[str], mode: str, rate_hz: float, offset_s: float,
              duration_s: float) -> dict[str, Any]:
    import msgspec

    from onboard.contracts import messages as m
    from onboard.contracts.topics import TOPICS
    from services.runtime.zenoh_session import open_session

    session = open_session(endpoint, "client")
    sent = {t: 0 for t in topics}
    copied = {t: False for t in topics}
    try:
        pubs = {t: session.declare_publisher(TOPICS[t].key(ns)) for t in topics}
        rates = {t: rate_hz or TOPICS[t].rate_hz or 10.0 for t in topics}
        if mode == "malformed":
            payloads = {t: malformed_payloads(t) for t in topics}
            ready_then_go()

            def make(t: str, k: int) -> bytes:
                return payloads[t][k % len(payloads[t])]
        else:
            # the live message to copy is the one last seen at the word (the helper is set up
            # long before, maybe before the stack publishes), and at least LIVE_COPY_WAIT_S after
            # its subscription
            latest: dict[str, Any] = {}
            subs = [session.declare_subscriber(TOPICS[t].key(ns), lambda s, t=t: latest.__setitem__(t, s.payload.to_bytes()))
                    for t in topics]
            subscribed = time.monotonic()
            ready_then_go()
            time.sleep(max(0.0, subscribed + LIVE_COPY_WAIT_S - time.monotonic()))
            for s in subs:
                s.undeclare()
            templates = {}
            for t in topics:
                msg_type = TOPICS[t].msg_type
                try:
                    templates[t] = m.decode(latest[t], msg_type)
                    copied[t] = True
                except (KeyError, m.MessageError):
                    templates[t] = msgspec.convert(example(msgspec.inspect.type_info(msg_type)), msg_type)
            offset_ns = int(offset_s * 1e9)

            def make(t: str, k: int) -> bytes:
                return m.encode(msgspec.structs.replace(templates[t], stamp_ns=time.monotonic_ns() + offset_ns, seq=0))
        t0 = time.monotonic()
        while (elapsed := time.monotonic() - t0) < duration_s:
            for t in topics:
                due = int(elapsed * rates[t])
                # a starved helper does not catch up past its duration: it ends on time, having sent fewer
                while sent[t] < due and time.monotonic() - t0 < duration_s:
                    pubs[t].put(make(t, sent[t]))
                    sent[t] += 1
            time.sleep(0.0005)
        wall = time.monotonic() - t0
    finally:
        session.close()
    return {"mode": mode, "sent": sent, "rate_hz": {t: round(n / wall, 1) for t, n in sent.items()},
            "copied_live_message": copied if mode == "stamps" else None, "duration_s": round(wall, 3)}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description="a chaos soak's helper process")
    sub = ap.add_subparsers(dest="mode", required=True)
    hog = sub.add_parser("hog", help="keep one core busy")
    hog.add_argument("--cpu", type=int, required=True)
    flood = sub.add_parser("flood", help="publish malformed or badly stamped messages")
    flood.add_argument("--endpoint", required=True)
    flood.add_argument("--namespace", required=True)
    flood.add_argument("--topics", required=True, help="comma list of topic names")
    flood.add_argument("--kind", choices=("malformed", "stamps"), required=True)
    flood.add_argument("--rate", type=float, default=0.0, help="[Hz] per topic (0: the topic's own)")
    flood.add_argument("--offset", type=float, default=0.0, help="[s] stamps: added to now")
    for p in (hog, flood):
        p.add_argument("--duration", type=float, required=True)
        p.add_argument("--parent", type=int, required=True, help="die with this process")
    args = ap.parse_args(argv)
    from services.runtime.realtime import die_with_parent

    die_with_parent(args.parent)
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(0))  # ended early: close the Zenoh session on the way out
    if args.mode == "hog":
        result = run_hog(args.cpu, args.duration)
    else:
        result = run_flood(args.endpoint, args.namespace, args.topics.split(","), args.kind, args.rate, args.offset, args.duration)
    print(json.dumps(result), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
