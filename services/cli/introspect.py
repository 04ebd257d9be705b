"""``archer topics``, ``archer services``, ``archer echo`` and ``archer status``: the tables, and a running stack."""

from __future__ import annotations

import argparse
import json
import queue
import sys
import time

import msgspec

from onboard.contracts import messages as msgs
from onboard.contracts.binary_messages import decode_color, decode_depth, decode_grid
from onboard.contracts.topics import TOPICS, Topic, namespace, topic_for_key
from services.runtime.peers import live_services, query_status
from services.runtime.zenoh_session import default_endpoint, open_tool_session



def _add_connection(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--endpoint", help="Zenoh endpoint (default tcp/127.0.0.1:7447)")
    parser.add_argument("--namespace", help="key namespace (default archer/robot0)")


def add_topics_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--namespace", help="key namespace (default archer/robot0)")
    parser.add_argument("--json", action="store_true")


def run_topics(args: argparse.Namespace) -> int:
    ns = args.namespace or namespace()
    rows = [
        {
            "name": t.name,
            "key": t.key(ns),
            "type": t.msg_type.__name__ if t.msg_type else f"binary:{t.binary}",
            "rate_hz": t.rate_hz,
            "publishers": list(t.publishers),
            "reliability": t.reliability,
            "congestion": t.congestion,
            "priority": t.priority,
            "log": t.log,
        }
        for t in TOPICS.values()
    ]
    if args.json:
        print(json.dumps(rows))
        return 0
    print(f"{'name':<13}{'key':<34}{'type':<17}{'rate':>6}  {'publishers':<24}{'qos'}")
    for r in rows:
        qos = f"{r['reliability']}/{r['congestion']}/{r['priority']}"
        rate = f"{r['rate_hz']:g}" if r["rate_hz"] else "event"
        print(f"{r['name']:<13}{r['key']:<34}{r['type']:<17}{rate:>6}  {','.join(r['publishers']):<24}{qos}")
    return 0


def add_services_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--json", action="store_true")


def run_services(args: argparse.Namespace) -> int:
    from services.table import SERVICES

    rows = [row.describe() for row in SERVICES.values()]
    if args.json:
        print(json.dumps(rows))
        return 0
    for r in rows:
        where = "robot" if r["on_robot"] else "sim"
        print(f"{r['process']:<19}{where:<6}{r['unit'] or '-':<27}{r['class']}")
        print(f"{'':<19}params {', '.join(r['params']) or '-'}; reads {', '.join(r['subscribes']) or '-'}; "
              f"writes {', '.join(r['publishes']) or '-'}")
    return 0


def add_echo_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("key", help="topic name (e.g. state) or key suffix (state/estimate)")
    parser.add_argument("--count", type=int, default=0, help="stop after N messages (0: run until Ctrl-C)")
    parser.add_argument("--timeout", type=float, default=0.0, help="stop after S seconds (0: never)")
    _add_connection(parser)


def _resolve(ns: str, key: str) -> Topic:
    if key in TOPICS:
        return TOPICS[key]
    topic = topic_for_key(ns, key) or topic_for_key(ns, f"{ns}/{key}")
    if topic is None:
        raise SystemExit(f"archer echo: unknown topic {key!r}; see `archer topics`")
    return topic


def _render(topic: Topic, payload: bytes) -> str:
    if topic.binary == "depth":
        img = decode_depth(payload)
        return json.dumps({"stamp_ns": img.stamp_ns, "seq": img.seq, "shape": list(img.depth.shape), "fx": img.fx})
    if topic.binary == "color":
        rgb = decode_color(payload)
        return json.dumps({"stamp_ns": rgb.stamp_ns, "seq": rgb.seq, "shape": list(rgb.rgb.shape), "fx": rgb.fx})
    if topic.binary == "grid":
        grid = decode_grid(payload)
        return json.dumps({"stamp_ns": grid.stamp_ns, "seq": grid.seq, "shape": list(grid.cells.shape), "resolution": grid.resolution})
    return msgspec.json.encode(msgs.decode(payload, topic.msg_type)).decode()


def run_echo(args: argparse.Namespace) -> int:
    ns = args.namespace or namespace()
    topic = _resolve(ns, args.key)
    inbox: queue.SimpleQueue[bytes] = queue.SimpleQueue()
    deadline = time.monotonic() + args.timeout if args.timeout > 0 else float("inf")
    session = open_tool_session(args.endpoint, deadline=deadline)
    if session is None:
        print(f"archer echo: no stack served {args.endpoint or default_endpoint()} within {args.timeout} s", file=sys.stderr)
        return 1
    try:
        sub = session.declare_subscriber(topic.key(ns), lambda s: inbox.put(s.payload.to_bytes()))
        shown, rejected = 0, 0
        while (args.count == 0 or shown < args.count) and time.monotonic() < deadline:
            try:
                payload = inbox.get(timeout=0.1)
            except queue.Empty:
                continue
            try:
                print(_render(topic, payload), flush=True)
                shown += 1
            except msgs.MessageError as exc:
                rejected += 1
                print(f"rejected: {exc}", file=sys.stderr)
        sub.undeclare()
    finally:
        session.close()
    return 0 if shown or args.count == 0 else 1


def add_status_arguments(parser: argparse.ArgumentParser) -> None:
    _add_connection(parser)
    parser.add_argument("--json", action="store_true")


def run_status(args: argparse.Namespace) -> int:
    ns = args.namespace or namespace()
    session = open_tool_session(args.endpoint)
    assert session is not None  # no deadline: it waits for the stack
    try:
        statuses = {name: query_status(session, ns, name) for name in live_services(session, ns)}
    finally:
        session.close()
    if args.json:
        print(json.dumps({n: (msgspec.to_builtins(s) if s else None) for n, s in statuses.items()}))
        return 0
    if not statuses:
        print(f"no live services under {ns}")
        return 1
    for name, st in statuses.items():
        if st is None:
            print(f"{name:<12} alive, no status reply")
            continue
        rates = ", ".join(f"{k}={v:g}" for k, v in st.rates_hz.items())
        print(f"{name:<12} {st.state:<9} up {st.uptime_s:8.1f}s  contract={st.contract}  {rates}")
        if st.counters:
            print(f"{'':<12} counters: {st.counters}")
        if st.last_error:
            print(f"{'':<12} last error: {st.last_error}")
    return 0
