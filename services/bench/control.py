"""The control loop at 1 kHz in its own process, with the other core busy: tick and jitter.

Runs the real loop (:class:`services.control.LoopProcess`: the low level built from the
MJCF, its own Zenoh session, a deadline loop with real-time priority and CPU pinning
when allowed) for ``--duration`` seconds. This process serves a Zenoh router on a
free loopback port and feeds the loop like the estimator and the planner would: a
``StateEstimate`` and a ``JointSensors`` frame every millisecond following a synthetic
hop cycle (ballistic flights, 70 ms stances, 5 cm off the reference so that the
policy and the attitude PD work every flight tick) and a ``ComReference`` at 100 Hz.
``--load`` processes spin a core each meanwhile (default 1: "the other core busy").

Figures from the loop's own recorder: ``tick_us_*`` is the compute time of a tick
(read inputs, controller step, publish), ``period_jitter_us_*`` the lateness of each
wake-up against its absolute deadline, ``overruns`` the ticks that ended after the
next deadline. The percentiles cover the last ``percentile_ticks`` ticks (the loop's ring:
every tick of a run up to 65 s), the maxima and overruns every tick of the run (``ticks``).
``armed_fraction`` shows that the full controller path ran.
"""

from __future__ import annotations

import argparse
import math
import multiprocessing as mp
import os
import time

from onboard.contracts import messages as msgs
from onboard.contracts.params import ControlParams, SafetyLimits
from onboard.contracts.topics import TOPICS, namespace
from services.runtime.clock import WallClock
from services.control import LoopConfig, LoopProcess
from services.runtime.realtime import DeadlineLoop
from services.runtime.service import TypedPublisher
from services.runtime.zenoh_session import free_endpoint, open_session

G = 9.81
HOP_VZ = 1.4  # [m/s] lift-off speed of the synthetic hop
STANCE_S = 0.07  # [s]
TOUCHDOWN_Z = 0.39  # [m] CoM height at touchdown
OFFSET = 0.05  # [m] the robot sits this far from the reference
REFERENCE_EVERY = 10  # feeder ticks between references (100 Hz)
WARMUP_S = 1.0  # let the peers link before the loop's figures count


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--duration", type=float, default=60.0, help="seconds of the loop at 1 kHz")
    parser.add_argument("--load", type=int, default=1, help="busy processes spinning meanwhile (0: idle machine)")


def _spin(cpu: int | None) -> None:
    if cpu is not None:
        try:
            os.sched_setaffinity(0, {cpu})
        except OSError:
            pass
    while True:
        pass


def synthetic_state(t_s: float, stamp_ns: int) -> tuple[msgs.StateEstimate, msgs.JointSensors]:
    """A hop cycle in place (flight ballistic, stance as a half sine of the spring)."""
    flight = 2.0 * HOP_VZ / G
    period = flight + STANCE_S
    ph = t_s % period
    if ph < flight:
        z = TOUCHDOWN_Z + HOP_VZ * ph - 0.5 * G * ph * ph
        vz = HOP_VZ - G * ph
        contact, foot, foot_vel = False, 0.01, 0.0
    else:
        s = (ph - flight) / STANCE_S
        z = TOUCHDOWN_Z - 0.03 * math.sin(math.pi * s)
        vz = -0.03 * math.pi / STANCE_S * math.cos(math.pi * s)
        contact, foot, foot_vel = True, 0.01 + 0.03 * math.sin(math.pi * s), 0.03 * math.pi / STANCE_S * math.cos(math.pi * s)
    roll = 0.02 * math.sin(2 * math.pi * t_s / period)
    q = [math.cos(roll / 2), math.sin(roll / 2), 0.0, 0.0]
    st = msgs.StateEstimate(
        stamp_ns=stamp_ns, position=[OFFSET, 0.0, z], velocity=[0.0, 0.0, vz], quat=q,
        omega=[0.1 * math.cos(2 * math.pi * t_s / period), 0.0, 0.0], wheel_vel=[10.0, -5.0, 1.0],
        foot_pos=foot, foot_vel=foot_vel, contact=contact, phase="stance" if contact else "flight",
        pos_vel_cov=[0.0] * 36, att_cov=[1e-6, 1e-6, 1e-6],
    )
    jn = msgs.JointSensors(
        stamp_ns=stamp_ns, wheel_pos=[0.0, 0.0, 0.0], wheel_vel=[10.0, -5.0, 1.0], wheel_torque=[0.0, 0.0, 0.0],
        foot_pos=foot, foot_vel=foot_vel, foot_contact=contact, foot_motor_pos=0.5,
    )
    return st, jn


def measure(args: argparse.Namespace) -> dict:
    if args.duration <= 0:
        raise ValueError("--duration must be positive")
    ns = namespace()
    endpoint = free_endpoint()
    router = open_session(endpoint, "router")
    clock = WallClock()
    pubs = {name: TypedPublisher(router, TOPICS[name], ns, clock) for name in ("state", "joints", "reference")}
    ncpu = os.cpu_count() or 1
    loop_cpu = ncpu - 1 if ncpu > 1 else -1
    ctx = mp.get_context("spawn")
    burners = [ctx.Process(target=_spin, args=((k % max(1, ncpu - 1)) if ncpu > 1 else None,), daemon=True)
               for k in range(args.load)]
    reference = msgs.ComReference(t_ref_ns=0, hold=True, segments=[
        msgs.BezierSegment(t0=0.0, duration=1.0, control_points=[[0.0, 0.0]])])
    fed = 0
    t0 = time.monotonic()

    def feed(_deadline: float) -> None:
        nonlocal fed
        now = clock.now_ns()
        st, jn = synthetic_state(time.monotonic() - t0, now)
        pubs["state"].put(st)
        pubs["joints"].put(jn)
        if fed % REFERENCE_EVERY == 0:
            reference.stamp_ns = now
            pubs["reference"].put(reference)
        fed += 1

    feeder = DeadlineLoop(1e-3, feed, name="bench-feeder")
    cfg = LoopConfig(ns=ns, endpoint=endpoint, zenoh_config=None, control=ControlParams(cpu=loop_cpu),
                     safety=SafetyLimits(), duration_s=args.duration)
    loop = LoopProcess(cfg)
    try:
        feeder.start()
        time.sleep(WARMUP_S)
        for b in burners:
            b.start()
        loop.start()
        final = loop.wait_final(args.duration + 30.0)
    finally:
        feeder.stop()
        for b in burners:
            b.kill()
        for p in pubs.values():
            p.undeclare()
        router.close()
    if "loop" not in final:
        raise RuntimeError(f"the control loop gave no statistics: {final}")
    stats = final["loop"]
    ticks = stats["ticks"]
    return {
        "tick_us_p50": stats["tick_us_p50"],
        "tick_us_p99": stats["tick_us_p99"],
        "tick_us_max": stats["tick_us_max"],
        "period_jitter_us_p50": stats["period_jitter_us_p50"],
        "period_jitter_us_p99": stats["period_jitter_us_p99"],
        "period_jitter_us_max": stats["period_jitter_us_max"],
        "overruns": stats["overruns"],
        "ticks": ticks,
        "percentile_ticks": stats["window"],
        "armed_fraction": round(1.0 - final["safe_ticks"] / ticks, 4) if ticks else 0.0,
        "hops_seen": final["hops"],
        "busy_processes": args.load,
        "cpus": ncpu,
        "realtime": ", ".join(f"{k}={v}" for k, v in loop.realtime.items()) or "not requested",
    }
