"""Zenoh latency and loss for state estimates at 1 kHz between two processes.

This process serves a router on a free loopback port and subscribes; a child
process publishes ``StateEstimate`` messages from a deadline loop, stamping each
with ``CLOCK_MONOTONIC`` (shared by all processes on the machine) just before
``put``. Every figure is measured, none is the configured rate: ``rate_hz`` is
the rate at which messages arrived at the subscriber (over the span from the first
arrival to the last), ``publisher_rate_hz`` the rate the publisher achieved between
its first and last ``put``; ``received`` counts distinct sequence numbers that
arrived intact, ``lost`` is what the publisher sent minus that, and latency is
receive-and-decode time minus the send stamp.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import threading
import time

import numpy as np

from onboard.contracts import messages as msgs
from onboard.contracts.topics import TOPICS, namespace
from services.runtime.clock import WallClock
from services.runtime.realtime import DeadlineLoop
from services.runtime.service import TypedPublisher
from services.runtime.zenoh_session import free_endpoint, open_session

WARMUP_S = 1.0  # let the peers link before the first counted message
DRAIN_S = 0.5  # wait for the last messages in flight


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--duration", type=float, default=10.0, help="seconds of publishing (>= 10 for the issue's figure)")
    parser.add_argument("--rate", type=float, default=1000.0, help="messages per second")


def sample_estimate() -> msgs.StateEstimate:
    """A state estimate of realistic size (full covariance, all fields set)."""
    return msgs.StateEstimate(
        position=[0.1234567, -2.3456789, 0.4567891],
        velocity=[0.3456789, -0.0123456, -1.2345678],
        quat=[0.9987654, 0.0123456, -0.0456789, 0.0012345],
        omega=[0.0123456, -0.2345678, 0.0345678],
        wheel_vel=[123.456789, -45.678912, 7.8912345],
        foot_pos=0.0123456,
        foot_vel=-0.2345678,
        contact=False,
        phase="flight",
        pos_vel_cov=[1.234567e-5 * (i + 1) for i in range(36)],
        att_cov=[1.0e-6, 1.1e-6, 2.0e-6],
    )


def _publisher(endpoint: str, ns: str, duration_s: float, rate_hz: float) -> None:
    session = open_session(endpoint, "peer")
    pub = TypedPublisher(session, TOPICS["state"], ns, WallClock())
    msg = sample_estimate()
    time.sleep(WARMUP_S)
    n_total = int(duration_s * rate_hz)
    sent = 0
    first_put_ns = last_put_ns = 0

    def tick(_deadline: float) -> None:
        nonlocal sent, first_put_ns, last_put_ns
        msg.stamp_ns = 0  # stamped at put time by the publisher
        pub.put(msg)
        last_put_ns = msg.stamp_ns
        if sent == 0:
            first_put_ns = last_put_ns
        sent += 1
        if sent >= n_total:
            loop.stop(timeout_s=0)

    loop = DeadlineLoop(1.0 / rate_hz, tick, name="bench-publisher")
    loop.run_here()
    stats = loop.recorder.stats()
    pub.undeclare()
    session.close()
    print(json.dumps({"sent": sent, "put_span_ns": last_put_ns - first_put_ns,
                      "pub_jitter_us_p99": round(stats.period_jitter_us_p99, 1)}), flush=True)


def rate_over_span(count: int, span_ns: int) -> float | None:
    """Events per second from ``count`` events whose first and last are ``span_ns`` apart."""
    if count < 2 or span_ns <= 0:
        return None
    return (count - 1) * 1e9 / span_ns


def arrival_figures(seq: np.ndarray, stamp_ns: np.ndarray, arrival_ns: np.ndarray, sent: int) -> dict:
    """Figures from what the subscriber saw, one entry per intact arrival (in arrival order)."""
    unique = np.unique(seq)
    received = int(len(unique))
    out_of_order = int(np.count_nonzero(np.diff(seq) < 0)) if len(seq) > 1 else 0
    lat_us = (arrival_ns - stamp_ns) / 1e3
    rate = rate_over_span(len(arrival_ns), int(arrival_ns[-1] - arrival_ns[0])) if len(arrival_ns) else None

    def pct(q: float) -> float | None:
        return round(float(np.percentile(lat_us, q)), 1) if len(lat_us) else None

    return {
        "sent": sent,
        "received": received,
        "lost": sent - received,
        "duplicates": int(len(seq)) - received,
        "out_of_order": out_of_order,
        "rate_hz": round(rate, 1) if rate is not None else None,
        "latency_us_p50": pct(50),
        "latency_us_p99": pct(99),
        "latency_us_max": round(float(lat_us.max()), 1) if len(lat_us) else None,
    }


def measure(args: argparse.Namespace) -> dict:
    endpoint = free_endpoint()
    ns = namespace()
    arrivals: list[tuple[int, int, int]] = []  # (seq, stamp_ns, arrival_ns) per intact message
    rejected = 0
    lock = threading.Lock()

    def on_sample(sample) -> None:
        nonlocal rejected
        try:
            msg = msgs.decode(sample.payload.to_bytes(), msgs.StateEstimate)
        except msgs.MessageError:
            rejected += 1
            return
        arrived_ns = time.monotonic_ns()
        with lock:
            arrivals.append((msg.seq, msg.stamp_ns, arrived_ns))

    router = open_session(endpoint, "router")
    child = None
    try:
        sub = router.declare_subscriber(TOPICS["state"].key(ns), on_sample)
        child = subprocess.Popen(
            [sys.executable, "-m", "services.bench.messaging", endpoint, ns, str(args.duration), str(args.rate)],
            stdout=subprocess.PIPE,
            text=True,
        )
        out, _ = child.communicate(timeout=args.duration + 60)
        time.sleep(DRAIN_S)
        sub.undeclare()
    finally:
        if child is not None and child.poll() is None:
            child.kill()
            child.wait()
        router.close()
    if child.returncode != 0:
        raise RuntimeError(f"publisher process failed with code {child.returncode}")
    pub_report = json.loads(out.strip().splitlines()[-1])
    with lock:
        seen = np.array(arrivals, dtype=np.int64).reshape(-1, 3)
    figures = arrival_figures(seen[:, 0], seen[:, 1], seen[:, 2], pub_report["sent"])
    publisher_rate = rate_over_span(pub_report["sent"], pub_report["put_span_ns"])
    figures.update({
        "rate_hz_requested": args.rate,
        "publisher_rate_hz": round(publisher_rate, 1) if publisher_rate is not None else None,
        "payload_bytes": len(msgs.encode(sample_estimate())),
        "rejected": rejected,
        "publisher_jitter_us_p99": pub_report["pub_jitter_us_p99"],
    })
    return figures


if __name__ == "__main__":  # the publisher side, started by measure()
    _publisher(sys.argv[1], sys.argv[2], float(sys.argv[3]), float(sys.argv[4]))
