"""Four emulated ELMO drives at 1 kHz through the hardware service: late/lost frames, bus load.

Three processes, as on the robot: ``archer emulate drives`` (the drives behind a
socketcand bus on 127.0.0.1), ``archer run hardware`` (the service under test, its
own process and deadline loop) and this one, which serves the Zenoh router,
publishes an armed ``TorqueCommand`` every millisecond (a stand-in for ``control``)
and counts the ``joints`` messages that come back. Where the kernel permits, the
service's exchange thread runs SCHED_FIFO as deployed, and the emulator above it, as
the drives' own silicon would.

A frame is *late or lost* when it misses its cycle: a drive's feedback PDO that is
not in when the service's next tick starts (counted by the service), or a command
PDO that is not in when the drive's next SYNC comes (counted by the emulated drive).
Bus load is the exact bit count of every frame the service sent and received
(stuffing included) over the bus time, next to the analytic budget.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
import tempfile
import threading
import time

import msgspec

from drivers.can_budget import TrafficItem, bus_load
from drivers.elmo import codec as c
from onboard import messages as msgs
from onboard.params import HardwareParams
from onboard.topics import TOPICS, namespace, status_key
from services.clock import WallClock
from services.realtime import DeadlineLoop
from services.runtime import StandInCommander, TypedPublisher
from services.zenoh_session import free_endpoint, open_session

START_TIMEOUT_S = 30.0  # emulator + service start-up (configuration over SDO)
STATUS_TIMEOUT_S = 5.0
TORQUE_AMPLITUDE = 0.2  # [N m] a slow sine on every joint: within every limit
TORQUE_PERIOD_S = 2.0
# The drives are silicon on the robot: their emulator must not queue behind the host's
# processes, so it runs above the service's exchange thread (HardwareParams.rt_priority).
EMULATOR_RT_PRIORITY = 75


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--duration", type=float, default=60.0, help="seconds of armed 1 kHz exchange (60 for the issue's figure)")


def budget(params: HardwareParams) -> dict[str, float]:
    """Analytic load of the configured traffic on the configured bitrate."""
    n = len(params.node_ids)
    rate = params.rate_hz
    items = [
        TrafficItem("SYNC", 0, rate),
        TrafficItem("RPDO1 controlword + target torque", c.RPDO1_STRUCT.size, rate, n),
        TrafficItem("TPDO1 statusword + torque + velocity", c.TPDO1_STRUCT.size, rate, n),
        TrafficItem("TPDO2 position", c.TPDO2_STRUCT.size, rate / params.position_every, n),
        TrafficItem("host heartbeat", 1, 1.0 / params.host_heartbeat_period_s),
        TrafficItem("drive heartbeats", 1, 1.0 / params.drive_heartbeat_period_s, n),
    ]
    cyclic = bus_load(items[:3], params.can_bitrate)
    total = bus_load(items, params.can_bitrate)
    return {
        "budget_cyclic_nominal": round(cyclic.nominal, 4),
        "budget_cyclic_worst_stuffing": round(cyclic.worst, 4),
        "budget_total_nominal": round(total.nominal, 4),
        "budget_total_worst_stuffing": round(total.worst, 4),
    }


def _query_status(session, ns: str) -> dict:
    replies = session.get(status_key(ns, "hardware"), timeout=STATUS_TIMEOUT_S)
    for reply in replies:
        if reply.ok is not None:
            return msgspec.json.decode(reply.ok.payload.to_bytes())
    raise RuntimeError("the hardware service did not answer its status query")


def measure(args: argparse.Namespace) -> dict:
    params = HardwareParams()
    endpoint = free_endpoint()
    ns = namespace()
    env = dict(os.environ, ARCHER_NAMESPACE=ns)
    archer = [sys.executable, "-m", "services.cli"]
    emulator = subprocess.Popen(archer + ["emulate", "drives", "--rt-priority", str(EMULATOR_RT_PRIORITY)], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    service = None
    config = None
    router = open_session(endpoint, "router")
    commander = StandInCommander(router, ns)  # the service obeys the one live commander: this bench
    try:
        info = json.loads(emulator.stdout.readline())
        bus = info["bus"]
        with tempfile.NamedTemporaryFile("w", suffix=".toml", delete=False) as f:
            f.write(f'[hardware]\nbackend = "can"\ncan_interface = "{bus["interface"]}"\ncan_channel = "{bus["channel"]}"\n')
            f.write(f'can_host = "{bus["host"]}"\ncan_port = {bus["port"]}\n')
            config = f.name
        service = subprocess.Popen(
            archer + ["run", "hardware", "--endpoint", endpoint, "--config", config, "--log-level", "WARNING"],
            stderr=subprocess.PIPE, text=True, env=env,
        )
        joints_seen = 0

        def on_joints(_sample) -> None:
            nonlocal joints_seen
            joints_seen += 1

        sub = router.declare_subscriber(TOPICS["joints"].key(ns), on_joints)
        deadline = time.monotonic() + START_TIMEOUT_S
        while joints_seen == 0 and time.monotonic() < deadline:
            if service.poll() is not None:
                raise RuntimeError(f"hardware service exited: {service.stderr.read()[-2000:]}")
            pub = TypedPublisher(router, TOPICS["torque_cmd"], ns, WallClock())
            pub.put(msgs.TorqueCommand(wheel_torque=[0.0, 0.0, 0.0], foot_torque=0.0, armed=True, commander=commander.instance))
            pub.undeclare()
            time.sleep(0.05)
        if joints_seen == 0:
            raise RuntimeError("no joints from the hardware service")
        before = _query_status(router, ns)
        pub = TypedPublisher(router, TOPICS["torque_cmd"], ns, WallClock())
        n_total = int(args.duration * params.rate_hz)
        sent = 0
        t0 = time.monotonic()
        result: dict = {}

        def snapshot() -> None:  # while commands still flow: the end of the run is no watchdog trip
            result["elapsed"] = time.monotonic() - t0
            result["joints"] = joints_seen - joints_before
            result["after"] = _query_status(router, ns)

        query = threading.Thread(target=snapshot, daemon=True)

        def tick(_deadline: float) -> None:
            nonlocal sent
            tau = TORQUE_AMPLITUDE * math.sin(2.0 * math.pi * (time.monotonic() - t0) / TORQUE_PERIOD_S)
            pub.put(msgs.TorqueCommand(wheel_torque=[tau, -tau, tau], foot_torque=tau, armed=True, commander=commander.instance))
            sent += 1
            if sent == n_total:
                query.start()
            elif sent > n_total and not query.is_alive():
                loop.stop(timeout_s=0)

        joints_before = joints_seen
        loop = DeadlineLoop(1.0 / params.rate_hz, tick, name="bench-commands")
        loop.run_here()
        if "after" not in result:
            raise RuntimeError("the hardware service did not answer its status query")
        elapsed, joints, after = result["elapsed"], result["joints"], result["after"]
        sub.undeclare()
        pub.undeclare()
    finally:
        for proc in (service, emulator):
            if proc is not None and proc.poll() is None:
                proc.terminate()
        commander.close()
        router.close()
        if config is not None:
            os.unlink(config)
    _, err = emulator.communicate(timeout=10)
    if service is not None:
        service.wait(timeout=10)
    final = next((json.loads(line)["final"] for line in err.splitlines() if line.startswith('{"final"')), {})
    x0, x1 = before["extra"], after["extra"]

    def delta(key: str) -> float:
        return x1.get(key, 0.0) - x0.get(key, 0.0)

    ticks = delta("hw.ticks")
    n = len(params.node_ids)
    fb_missed = delta("hw.feedback_missed")
    fb_late = delta("hw.feedback_late")
    drives = final.get("drives", {})
    cmd_missed = sum(d.get("sync_without_rpdo", 0) for d in drives.values())
    syncs = final.get("syncs", 0)
    frames = n * ticks + n * syncs
    figures = {
        "load_avg_1min": round(os.getloadavg()[0], 2),  # three busy 1 kHz processes share the cores
        "duration_s": round(elapsed, 2),
        "ticks": int(ticks),
        "tick_rate_hz": round(ticks / elapsed, 1) if elapsed else 0.0,
        "feedback_frames": int(n * ticks),
        "feedback_late_or_lost": int(fb_missed),
        "feedback_late": int(fb_late),
        "command_frames_whole_run": int(n * syncs),
        "command_late_or_lost_whole_run": int(cmd_missed),
        "late_or_lost_fraction": round((fb_missed + cmd_missed) / frames, 6) if frames else None,
        "joints_messages": joints,
        "bus_load_measured": x1.get("hw.bus_load"),
        "faults": int(x1.get("hw.faults", 0)),
        "last_fault": after.get("last_error", ""),
        "loop_jitter_us_p99": x1.get("loop.period_jitter_us_p99"),
        "loop_tick_us_p99": x1.get("loop.tick_us_p99"),
        "loop_overruns": int(delta("loop.overruns")),
        "commands_sent": n_total,
        "watchdog_trips": int(delta("watchdog.trips")),
    }
    figures.update(budget(params))
    return figures
