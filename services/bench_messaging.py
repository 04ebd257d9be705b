"""Zenoh latency and loss for state estimates at 1 kHz between two processes.

This process serves a router on a free loopback port and subscribes; a child
process publishes ``StateEstimate`` messages from a deadline loop, stamping each
with ``CLOCK_MONOTONIC`` (shared by all processes on the machine) just before
``put``. Latency is receive-and-decode time minus that stamp; ``lost`` is what
the publisher sent minus what arrived intact.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import threading
import time

import numpy as np

from onboard import messages as msgs
from onboard.topics import TOPICS, namespace
from services.clock import WallClock
from services.realtime import DeadlineLoop
from services.runtime import TypedPublisher
from services.zenoh_session import free_endpoint, open_session

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

    def tick(_deadline: float) -> None:
        nonlocal sent
        msg.stamp_ns = 0  # stamped at put time by the publisher
        pub.put(msg)
        sent += 1
        if sent >= n_total:
            loop.stop(timeout_s=0)

    loop = DeadlineLoop(1.0 / rate_hz, tick, name="bench-publisher")
    loop.run_here()
    stats = loop.recorder.stats()
    pub.undeclare()
    session.close()
    print(json.dumps({"sent": sent, "pub_jitter_us_p99": round(stats.period_jitter_us_p99, 1)}), flush=True)


def measure(args: argparse.Namespace) -> dict:
    endpoint = free_endpoint()
    ns = namespace()
    n_expected = int(args.duration * args.rate)
    latencies = np.zeros(n_expected + 1000)
    received = 0
    rejected = 0
    lock = threading.Lock()

    def on_sample(sample) -> None:
        nonlocal received, rejected
        try:
            msg = msgs.decode(sample.payload.to_bytes(), msgs.StateEstimate)
        except msgs.MessageError:
            rejected += 1
            return
        latency_ns = time.monotonic_ns() - msg.stamp_ns
        with lock:
            if received < len(latencies):
                latencies[received] = latency_ns
            received += 1

    router = open_session(endpoint, "router")
    sub = router.declare_subscriber(TOPICS["state"].key(ns), on_sample)
    child = subprocess.Popen(
        [sys.executable, "-m", "services.bench_messaging", endpoint, ns, str(args.duration), str(args.rate)],
        stdout=subprocess.PIPE,
        text=True,
    )
    out, _ = child.communicate(timeout=args.duration + 60)
    time.sleep(DRAIN_S)
    sub.undeclare()
    router.close()
    if child.returncode != 0:
        raise RuntimeError(f"publisher process failed with code {child.returncode}")
    pub_report = json.loads(out.strip().splitlines()[-1])
    sent = pub_report["sent"]
    lat_us = latencies[: min(received, len(latencies))] / 1e3
    return {
        "messages": sent,
        "payload_bytes": len(msgs.encode(sample_estimate())),
        "latency_us_p50": round(float(np.percentile(lat_us, 50)), 1) if received else None,
        "latency_us_p99": round(float(np.percentile(lat_us, 99)), 1) if received else None,
        "latency_us_max": round(float(lat_us.max()), 1) if received else None,
        "rate_hz": round(sent / args.duration, 1),
        "lost": sent - received,
        "rejected": rejected,
        "publisher_jitter_us_p99": pub_report["pub_jitter_us_p99"],
    }


if __name__ == "__main__":  # the publisher side, started by measure()
    _publisher(sys.argv[1], sys.argv[2], float(sys.argv[3]), float(sys.argv[4]))
