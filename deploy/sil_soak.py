"""Software-in-the-loop soak run: the real-time stack for minutes, with faults injected.

    .venv/bin/python -m deploy.sil_soak --duration 600 --kill planner@300 --kill control@570 --out /tmp/soak

Runs ``archer sim --mode realtime`` (the twin in place of the hardware, every service
its own process under :mod:`services.supervisor`) on a free loopback endpoint and its
own namespace, with the flight recorder. An operator thread sends a tour of goals
(re-sent every second, as an operator console would, so that a restarted planner
picks the current one up). At the given times it ``kill -9``s a service's main
process and measures:

- for ``control``: how long after the kill torque commands stop arriving, and how
  long until the twin stops applying torque (its ``safety`` event ``command_stale``,
  on the same monotonic clock as the kill; only when control was armed then);
- for ``planner``: how long until a reference flows again, and whether the robot
  kept hopping (no fall) meanwhile.

Afterwards it reads the recording (messages lost per topic from ``seq``), plots it
with ``archer plot`` and prints one JSON summary (also ``OUT/summary.json``).
This is a measurement for reports, not a test: CI does not run it.
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import threading
import time
import tomllib
from pathlib import Path
from typing import Any

import zenoh

from onboard import messages as m
from onboard.topics import TOPICS
from services.cmd_introspect import live_services, query_status
from services.recorder import file_metadata, recording_files
from services.zenoh_session import endpoint_in_use, free_endpoint, open_session

NS_DEFAULT = "archer/soak"
GOAL_RESEND_S = 1.0
STATUS_PERIOD_S = 30.0  # status queries cost the services CPU: few
RESTART_GAP_NS = 500_000_000  # a pause in torque commands this long: the old control is gone
SERVICES = "estimator,control,planner,recorder"
SIL_CONFIG = Path(__file__).resolve().parent / "config" / "sil.toml"


def _sil_config(base: Path, rec_dir: Path) -> str:
    """``base`` with the recording going to ``rec_dir`` in 30 s files, as TOML."""
    tables = tomllib.loads(base.read_text())
    tables.setdefault("recorder", {}).update(directory=str(rec_dir), chunk_s=30.0)
    return "".join(
        f"[{name}]\n" + "".join(f"{key} = {json.dumps(value)}\n" for key, value in table.items()) + "\n"
        for name, table in tables.items()
    )


def _children(pid: int) -> list[tuple[int, list[bytes]]]:
    """``(pid, argv)`` of the processes whose parent is ``pid``."""
    out = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            stat = (entry / "stat").read_text()
            ppid = int(stat.rsplit(")", 1)[1].split()[1])
            cmd = (entry / "cmdline").read_bytes().split(b"\0")
        except (OSError, IndexError, ValueError):
            continue
        if ppid == pid:
            out.append((int(entry.name), cmd))
    return out


def _pid_of(sim_pid: int, target: str) -> int | None:
    """``SERVICE``: the main process of ``archer run SERVICE`` started by our sim;
    ``SERVICE/child``: that process's child (the control loop process)."""
    service, _, child = target.partition("/")
    main_pid = next((pid for pid, cmd in _children(sim_pid) if b"run" in cmd and service.encode() in cmd), None)
    if main_pid is None or not child:
        return main_pid
    # the multiprocessing child that runs the loop, not its resource tracker
    return next((pid for pid, cmd in _children(main_pid) if any(b"spawn_main" in part for part in cmd)), None)


class Operator:
    """Sends the current goal every second; collects safety events and references."""

    def __init__(self, session: zenoh.Session, ns: str, goals: list[tuple[float, float]], period_s: float) -> None:
        self.session, self.ns, self.goals, self.period_s = session, ns, goals, period_s
        self.safety: list[m.SafetyEvent] = []
        self.reference_rx_ns: list[int] = []
        self.torque_rx_ns: list[int] = []
        self._stop = threading.Event()
        self._subs = [
            session.declare_subscriber(TOPICS["safety"].key(ns), lambda s: self.safety.append(m.decode(s.payload.to_bytes(), m.SafetyEvent))),
            session.declare_subscriber(TOPICS["reference"].key(ns), lambda s: self.reference_rx_ns.append(time.monotonic_ns())),
            session.declare_subscriber(TOPICS["torque_cmd"].key(ns), lambda s: self.torque_rx_ns.append(time.monotonic_ns())),
        ]
        self._pub = session.declare_publisher(TOPICS["goal"].key(ns), reliability=zenoh.Reliability.RELIABLE)
        self._thread = threading.Thread(target=self._run, daemon=True)
        self.t0 = time.monotonic()

    def start(self) -> None:
        self.t0 = time.monotonic()
        self._thread.start()

    def current_goal(self) -> tuple[float, float]:
        k = int((time.monotonic() - self.t0) / self.period_s)
        return self.goals[k % len(self.goals)]

    def _run(self) -> None:
        seq = 0
        while not self._stop.wait(GOAL_RESEND_S):
            seq += 1
            x, y = self.current_goal()
            self._pub.put(m.encode(m.Goal(stamp_ns=time.monotonic_ns(), seq=seq, position=[x, y], tolerance=0.15)))

    def stop(self) -> None:
        self._stop.set()
        self._thread.join()
        for s in self._subs:
            s.undeclare()
        self._pub.undeclare()


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--duration", type=float, default=600.0, help="[s] wall time")
    ap.add_argument("--scenario", default="hop-in-place", help="twin scenario (hop-in-place: no goal of its own)")
    ap.add_argument("--goals", default="1.5,0;1.5,1.5;0,1.5;0,0", help="tour of goals 'x,y;x,y;...' [m]")
    ap.add_argument("--goal-period", type=float, default=75.0, help="[s] per goal")
    ap.add_argument("--kill", action="append", default=[], metavar="SERVICE@T", help="kill -9 SERVICE (SERVICE/child: its child process) T seconds after the twin started")
    ap.add_argument("--services", default=SERVICES)
    ap.add_argument("--out", default="soak", help="output directory")
    ap.add_argument("--namespace", default=NS_DEFAULT)
    ap.add_argument("--config", default=str(SIL_CONFIG), help="the SIL profile the run starts from")
    args = ap.parse_args(argv)

    out = Path(args.out).resolve()
    out.mkdir(parents=True, exist_ok=True)
    rec_dir = out / "rec"
    config = out / "sil.toml"
    config.write_text(_sil_config(Path(args.config), rec_dir))
    endpoint = free_endpoint()
    goals = [tuple(float(v) for v in g.split(",")) for g in args.goals.split(";")]
    kills = sorted((float(k.split("@")[1]), k.split("@")[0]) for k in args.kill)

    cmd = [sys.executable, "-m", "services.cli", "sim", "--mode", "realtime", "--scenario", args.scenario, "--planner", "graph",
           "--services", args.services, "--duration", str(args.duration), "--keep-going", "--json", "--quiet",
           "--config", str(config), "--endpoint", endpoint, "--namespace", args.namespace]
    stdout, stderr = open(out / "sim.stdout", "wb"), open(out / "sim.stderr", "wb")
    sim = subprocess.Popen(cmd, stdout=stdout, stderr=stderr)
    while not endpoint_in_use(endpoint):
        if sim.poll() is not None:
            raise SystemExit(f"sim exited early: see {out / 'sim.stderr'}")
        time.sleep(0.1)
    session = open_session(endpoint, "client")
    while "twin" not in live_services(session, args.namespace):  # the physics starts with the twin
        if sim.poll() is not None:
            raise SystemExit(f"sim exited early: see {out / 'sim.stderr'}")
        time.sleep(0.2)
    operator = Operator(session, args.namespace, goals, args.goal_period)
    operator.start()
    t0 = time.monotonic()
    statuses = open(out / "status.jsonl", "w")
    injected: list[dict[str, Any]] = []
    next_status = 0.0
    try:
        while sim.poll() is None:
            el = time.monotonic() - t0
            if kills and el >= kills[0][0]:
                _, service = kills.pop(0)
                pid = _pid_of(sim.pid, service)
                t_kill = time.monotonic_ns()
                if pid is not None:
                    os.kill(pid, signal.SIGKILL)
                injected.append({"service": service, "at_s": round(el, 1), "pid": pid, "t_kill_ns": t_kill, "goal": operator.current_goal()})
            if el >= next_status:
                next_status = el + STATUS_PERIOD_S
                snap: dict[str, Any] = {"t": round(el, 1)}
                for name in live_services(session, args.namespace):
                    st = query_status(session, args.namespace, name)
                    if st is not None:
                        snap[name] = {"state": st.state, "extra": st.extra, "counters": st.counters}
                statuses.write(json.dumps(snap) + "\n")
                statuses.flush()
            time.sleep(0.05)
    finally:
        operator.stop()
        session.close()
        statuses.close()
        if sim.poll() is None:
            sim.send_signal(signal.SIGTERM)
        sim.wait()
        stdout.close()
        stderr.close()

    lines = (out / "sim.stdout").read_text().strip().splitlines()
    metrics = json.loads(lines[-1]) if lines else {}
    for inj in injected:
        after = [e for e in operator.safety if e.stamp_ns >= inj["t_kill_ns"]]
        if inj["service"].startswith("control"):
            # the last command before the restarted control's first (a gap of a second at least)
            rx = [t for t in operator.torque_rx_ns if t >= inj["t_kill_ns"]]
            last = next((a for a, b in zip(rx, rx[1:]) if b - a > RESTART_GAP_NS), rx[-1] if rx else None)
            if last is not None:
                inj["commands_stopped_after_kill_ms"] = round((last - inj["t_kill_ns"]) / 1e6, 2)
            stale = [e for e in after if e.trip == "command_stale"]
            if stale:
                inj["zero_torque_after_kill_ms"] = round((stale[0].stamp_ns - inj["t_kill_ns"]) / 1e6, 2)
                inj["last_command_age_ms"] = round(stale[0].value * 1e3, 2)
        refs = [t for t in operator.reference_rx_ns if t > inj["t_kill_ns"]]
        gaps = [b - a for a, b in zip([inj["t_kill_ns"]] + refs, refs)]
        if gaps:
            inj["longest_reference_gap_after_kill_s"] = round(max(gaps[:2000]) / 1e9, 3)
    files = recording_files([rec_dir], include_partial=False) if rec_dir.is_dir() else []
    lost = file_metadata(files[-1]) if files else {}
    plot = subprocess.run([sys.executable, "-m", "services.cli", "plot", str(rec_dir), "--out", str(out / "plots")], capture_output=True, text=True) if files else None
    summary = {"metrics": metrics, "injected": injected, "recorder": lost, "recording_files": len(files),
               "plot": (json.loads(plot.stdout.strip().splitlines()[-1]) if plot.returncode == 0 else plot.stderr[-2000:]) if plot else None}
    (out / "summary.json").write_text(json.dumps(summary, indent=2))
    print(json.dumps(summary))
    return 0


if __name__ == "__main__":
    sys.exit(main())
