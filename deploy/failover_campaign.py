"""Failover campaign: kill -9 the primary control or estimator again and again while the twin hops in
real time, with a hot standby beside each (``archer sim --mode realtime --standby``), and measure what
the robot saw at each takeover.

    python -m deploy.failover_campaign --kills control=50,estimator=50 --out /tmp/failover

Each round: wait until both a primary and its standby answer (the restarted ex-primary comes back as
the standby), then SIGKILL the primary (the pid its status names; ``control/child``: its loop process)
and watch from outside, as an operator would:

- ``torque_cmd``: the gap between the last command of the old commander and the first of the new
  one (receipt times here; ``takeover_ms``), the largest component change between those two
  commands (``torque_step_nm``), and commands from two commanders at once (``overlap``: commands of
  the old one received after the first of the new one);
- ``state``: the longest gap between estimates around the kill (``takeover_ms``) and the jump of
  the estimate at the switch (the new publisher's sequence restarts: ``position_step_m``,
  ``attitude_step``: the largest quaternion component change);
- the twin's ``safety`` events (``command_stale``: the motors saw no command for longer than
  ``SafetyLimits.command_stale_s`` and were zeroed) and its ``falls`` counter (the physics).

A fall is put back (``twin.seed``), both estimators rebuilt and both control loops asked to arm, as
:mod:`deploy.sil_soak` does, so that one fall does not spoil the rest. One JSON line per kill on
stdout; percentiles and totals in ``OUT/summary.json``. A measurement for reports, not a test
(tests/test_standby.py runs one kill of each).
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import zenoh

from deploy import soak_faults as sf
from onboard.contracts import messages as m
from onboard.contracts.topics import STANDBY_SUFFIX, TOPICS
from services.runtime.peers import query_params, query_status
from services.runtime.realtime import die_with_parent
from services.runtime.zenoh_session import endpoint_in_use, free_endpoint, open_session

START_TIMEOUT_S = 180.0  # the whole stack on a loaded 2-core machine
READY_TIMEOUT_S = 120.0  # a killed primary restarted as the standby
SETTLE_S = 2.0  # after the standby is back, before the next kill (hopping again, not just started)
AFTER_KILL_S = 1.0  # the window after a kill the streams are read in
FALL_WATCH_S = 1.5  # a fall within this long of a kill is the kill's
PUT_BACK_SETTLE_S = 1.5
TWIN = "twin"
KILL_ATTEMPTS = 3


def _pct(values: list[float], q: float) -> float | None:
    if not values:
        return None
    s = sorted(values)
    return s[min(len(s) - 1, int(round(q * (len(s) - 1))))]


def figures(values: list[float]) -> dict[str, float | None]:
    return {"n": len(values), "p50": _pct(values, 0.5), "p99": _pct(values, 0.99), "max": max(values) if values else None}


class Streams:
    """What the stack publishes, with receipt times (Zenoh threads append; lists are thread-safe enough)."""

    def __init__(self, session: zenoh.Session, ns: str) -> None:
        self.torque: list[tuple[int, str, list[float], float, bool]] = []  # recv_ns, commander, wheel, foot, armed
        self.state: list[tuple[int, int, list[float], list[float]]] = []  # recv_ns, seq, position, quat
        self.stale: list[int] = []  # recv_ns of the twin's command_stale / command_refused trips
        self._subs = [
            session.declare_subscriber(TOPICS["torque_cmd"].key(ns), self._on_torque),
            session.declare_subscriber(TOPICS["state"].key(ns), self._on_state),
            session.declare_subscriber(TOPICS["safety"].key(ns), self._on_safety),
        ]

    def _on_torque(self, sample: zenoh.Sample) -> None:
        now = time.monotonic_ns()
        try:
            c = m.decode(sample.payload.to_bytes(), m.TorqueCommand)
        except m.MessageError:
            return
        self.torque.append((now, c.commander, list(c.wheel_torque), c.foot_torque, c.armed))

    def _on_state(self, sample: zenoh.Sample) -> None:
        now = time.monotonic_ns()
        try:
            s = m.decode(sample.payload.to_bytes(), m.StateEstimate)
        except m.MessageError:
            return
        self.state.append((now, s.seq, list(s.position), list(s.quat)))

    def _on_safety(self, sample: zenoh.Sample) -> None:
        try:
            ev = m.decode(sample.payload.to_bytes(), m.SafetyEvent)
        except m.MessageError:
            return
        if ev.trip in ("command_stale", "command_refused"):
            self.stale.append(time.monotonic_ns())

    def close(self) -> None:
        for sub in self._subs:
            sub.undeclare()


def control_takeover(streams: Streams, kill_ns: int, end_ns: int, old: str) -> dict[str, Any]:
    """The switch of commander after a kill, as the torque stream shows it."""
    window = [t for t in streams.torque if kill_ns - 200_000_000 <= t[0] <= end_ns]
    last_old = next((t for t in reversed(window) if t[1] == old and t[0] <= kill_ns + 100_000_000), None)
    first_new = next((t for t in window if t[1] != old and t[0] >= kill_ns - 50_000_000), None)
    out: dict[str, Any] = {"switched": first_new is not None}
    if last_old is None or first_new is None:
        return out
    out["takeover_ms"] = (first_new[0] - last_old[0]) / 1e6
    step = max(abs(a - b) for a, b in zip(last_old[2] + [last_old[3]], first_new[2] + [first_new[3]]))
    out["torque_step_nm"] = step
    out["armed_before"], out["armed_after"] = last_old[4], first_new[4]
    out["overlap"] = sum(1 for t in window if t[1] == old and t[0] > first_new[0])
    out["commanders_after"] = sorted({t[1] for t in window if t[0] > first_new[0]})
    return out


def estimator_takeover(streams: Streams, kill_ns: int, end_ns: int) -> dict[str, Any]:
    """The switch of estimate publisher after a kill: the longest gap and the jump at the restart of seq."""
    window = [s for s in streams.state if kill_ns - 200_000_000 <= s[0] <= end_ns]
    out: dict[str, Any] = {"switched": False}
    for a, b in zip(window, window[1:]):
        if b[1] < a[1]:  # a new publisher numbers from 1
            out["switched"] = True
            out["takeover_ms"] = (b[0] - a[0]) / 1e6
            out["position_step_m"] = max(abs(x - y) for x, y in zip(a[2], b[2]))
            sign = 1.0 if sum(x * y for x, y in zip(a[3], b[3])) >= 0 else -1.0
            out["attitude_step"] = max(abs(x - sign * y) for x, y in zip(a[3], b[3]))
            break
    after = [s[0] for s in window if s[0] >= kill_ns - 50_000_000]
    gaps = [(b - a) / 1e6 for a, b in zip(after, after[1:])]
    out["max_gap_ms"] = max(gaps) if gaps else None
    return out


class Campaign:
    def __init__(self, args: argparse.Namespace) -> None:
        self.args = args
        self.ns = f"archer/failover{os.getpid()}"
        self.endpoint = args.endpoint or free_endpoint()
        self.out = Path(args.out)
        self.results: list[dict[str, Any]] = []
        self.falls_seen = 0.0
        self.put_backs = 0
        self.arm_requests = 0

    def run(self) -> dict[str, Any]:
        self.out.mkdir(parents=True, exist_ok=True)
        plan = [k for name, n in self.args.kills for k in [name] * n]
        order = sorted(range(len(plan)), key=lambda i: (i % max(1, len(plan) // 2), i))  # interleave the targets
        plan = [plan[i] for i in order] if self.args.interleave else plan
        duration = self.args.max_duration
        cmd = [sys.executable, "-m", "services.cli.main", "sim", "--mode", "realtime", "--standby", "--scenario",
               self.args.scenario, "--duration", str(duration), "--keep-going", "--json", "--quiet",
               "--endpoint", self.endpoint, "--namespace", self.ns]
        parent = os.getpid()
        stdout, stderr = open(self.out / "sim.stdout", "wb"), open(self.out / "sim.stderr", "wb")
        sim = subprocess.Popen(cmd, stdout=stdout, stderr=stderr, preexec_fn=lambda: die_with_parent(parent))
        session = streams = None
        try:
            deadline = time.monotonic() + START_TIMEOUT_S
            while not endpoint_in_use(self.endpoint):
                self._check(sim, deadline)
                time.sleep(0.1)
            session = open_session(self.endpoint, "peer")
            streams = Streams(session, self.ns)
            for target in plan:
                service = target.split("/")[0]
                for _attempt in range(KILL_ATTEMPTS):  # a unit restarted meanwhile (its watchdog on a loaded machine)
                    self._wait_ready(sim, session, service)
                    settled = self._settle(sim, session)
                    result = self._kill(sim, session, streams, target)
                    if "error" not in result:
                        break
                result["settled"] = settled
                self.results.append(result)
                print(json.dumps(result), flush=True)
        finally:
            if streams is not None:
                streams.close()
            if session is not None:
                session.close()
            if sim.poll() is None:
                sim.send_signal(signal.SIGINT)
                try:
                    sim.wait(30)
                except subprocess.TimeoutExpired:
                    sim.kill()
            stdout.close()
            stderr.close()
        summary = self._summarize()
        (self.out / "summary.json").write_text(json.dumps(summary, indent=1))
        return summary

    def _check(self, sim: subprocess.Popen, deadline: float) -> None:
        if sim.poll() is not None:
            raise RuntimeError(f"the sim exited with {sim.returncode}: see {self.out / 'sim.stderr'}")
        if time.monotonic() > deadline:
            raise RuntimeError(f"timed out: see {self.out / 'sim.stderr'}")

    def _wait_ready(self, sim: subprocess.Popen, session: zenoh.Session, service: str) -> None:
        """Both a primary and a standby of ``service`` (and of the other one) answer, and the twin runs."""
        deadline = time.monotonic() + (START_TIMEOUT_S if not self.results else READY_TIMEOUT_S)
        while True:
            missing = [name for name in ("estimator", "estimator" + STANDBY_SUFFIX, "control", "control" + STANDBY_SUFFIX, TWIN)
                       if query_status(session, self.ns, name) is None]
            if not missing:
                return
            if time.monotonic() > deadline:
                raise RuntimeError(f"{missing} did not answer: see {self.out / 'sim.stderr'}")
            self._check(sim, deadline + 1)
            time.sleep(0.2)

    def _falls(self, session: zenoh.Session) -> float:
        st = query_status(session, self.ns, TWIN)
        return st.extra.get("falls", 0.0) if st is not None else 0.0

    def _armed(self, session: zenoh.Session) -> dict[str, bool]:
        out = {}
        for name in ("control", "control" + STANDBY_SUFFIX):
            st = query_status(session, self.ns, name)
            out[name] = st is not None and st.extra.get("armed", 0.0) == 1.0
        return out

    def _arm(self, session: zenoh.Session, names: list[str]) -> None:
        for name in names:
            ctl = query_params(session, self.ns, name)
            if ctl is not None:
                query_params(session, self.ns, name, {"control.arm_request": int(ctl.params["control.arm_request"]) + 1})

    def _settle(self, sim: subprocess.Popen, session: zenoh.Session) -> bool:
        """Hopping, both control loops armed, no fall for ``SETTLE_S``, before a kill: a fallen robot is
        put back, a disarmed loop asked to arm (bounded: False when it did not settle)."""
        deadline = time.monotonic() + READY_TIMEOUT_S
        calm_since = time.monotonic()
        while time.monotonic() < deadline:
            self._check(sim, deadline + 1)
            falls = self._falls(session)
            if falls > self.falls_seen:
                self.falls_seen = falls
                self._put_back(session)
                calm_since = time.monotonic()
                continue
            armed = self._armed(session)
            if not all(armed.values()):
                self._arm(session, [n for n, a in armed.items() if not a])
                self.arm_requests += 1
                calm_since = time.monotonic()
                time.sleep(0.5)
                continue
            if time.monotonic() - calm_since >= SETTLE_S:
                return True
            time.sleep(0.1)
        return False

    def _put_back(self, session: zenoh.Session) -> None:
        twin = query_params(session, self.ns, TWIN)
        if twin is None:
            return
        query_params(session, self.ns, TWIN, {"twin.seed": twin.params["twin.seed"]})
        self.put_backs += 1
        time.sleep(PUT_BACK_SETTLE_S)
        for name in ("estimator", "estimator" + STANDBY_SUFFIX):  # both filters re-converge from the next pose
            est = query_params(session, self.ns, name)
            if est is not None:
                query_params(session, self.ns, name, {"estimator.rate_hz": est.params["estimator.rate_hz"]})
        time.sleep(PUT_BACK_SETTLE_S)
        self._arm(session, ["control", "control" + STANDBY_SUFFIX])

    def _kill(self, sim: subprocess.Popen, session: zenoh.Session, streams: Streams, target: str) -> dict[str, Any]:
        service, _, part = target.partition("/")
        st = standby = None
        for _ in range(5):  # a status query may time out on a loaded machine
            st = st or query_status(session, self.ns, service)
            standby = standby or query_status(session, self.ns, service + STANDBY_SUFFIX)
            if st is not None and standby is not None:
                break
        if st is None or standby is None:
            return {"target": target, "error": f"no {'primary' if st is None else 'standby'} answered"}
        pid = st.pid if part != "child" else sf.loop_child_pid(st.pid)
        falls_before = self._falls(session)
        stale_before = len(streams.stale)
        result: dict[str, Any] = {"target": target, "pid": pid, "standby_pid": standby.pid}
        if pid is None:
            result["error"] = "no loop process found"
            return result
        kill_ns = time.monotonic_ns()
        result["old_commands_last_s"] = sum(1 for t in streams.torque[-3000:] if t[1] == st.instance and t[0] > kill_ns - 1_000_000_000)
        os.kill(pid, signal.SIGKILL)
        time.sleep(AFTER_KILL_S)
        # who answers as the primary now
        new = query_status(session, self.ns, service)
        result["new_primary_pid"] = new.pid if new is not None else None
        result["standby_took_over"] = new is not None and new.pid == standby.pid
        end_ns = kill_ns + int(AFTER_KILL_S * 1e9)
        if service == "control":
            result.update(control_takeover(streams, kill_ns, end_ns, st.instance))
        else:
            result.update(estimator_takeover(streams, kill_ns, end_ns))
        result["stale_trips"] = sum(1 for t in streams.stale[stale_before:] if kill_ns <= t <= end_ns)
        time.sleep(max(0.0, FALL_WATCH_S - AFTER_KILL_S))
        falls = self._falls(session)
        result["fell"] = falls > falls_before
        if new is not None and service == "control":
            result["promoted_step"] = new.extra.get("takeover_step")
            result["promoted_gap_ms"] = new.extra.get("takeover_gap_ms")
            result["promote_to_publish_ms"] = new.extra.get("takeover_promote_to_publish_ms")
        return result

    def _summarize(self) -> dict[str, Any]:
        out: dict[str, Any] = {"kills": len(self.results), "put_backs": self.put_backs, "arm_rounds": self.arm_requests,
                               "by_target": {}}
        for target in sorted({r["target"] for r in self.results}):
            rs = [r for r in self.results if r["target"] == target]
            summary: dict[str, Any] = {
                "kills": len(rs),
                "falls": sum(1 for r in rs if r.get("fell")),
                "not_settled": sum(1 for r in rs if not r.get("settled")),  # not hopping armed before the kill
                "took_over": sum(1 for r in rs if r.get("standby_took_over")),
                "switched": sum(1 for r in rs if r.get("switched")),
                "stale_trip_kills": sum(1 for r in rs if r.get("stale_trips")),
                "takeover_ms": figures([r["takeover_ms"] for r in rs if r.get("takeover_ms") is not None]),
            }
            if target.startswith("control"):
                summary["torque_step_nm"] = figures([r["torque_step_nm"] for r in rs if r.get("torque_step_nm") is not None])
                summary["overlap_commands"] = sum(r.get("overlap", 0) for r in rs)
                summary["two_commanders_after"] = sum(1 for r in rs if len(r.get("commanders_after", [])) > 1)
            else:
                summary["max_gap_ms"] = figures([r["max_gap_ms"] for r in rs if r.get("max_gap_ms") is not None])
                summary["position_step_m"] = figures([r["position_step_m"] for r in rs if r.get("position_step_m") is not None])
                summary["attitude_step"] = figures([r["attitude_step"] for r in rs if r.get("attitude_step") is not None])
            out["by_target"][target] = summary
        return out


def parse_kills(text: str) -> list[tuple[str, int]]:
    out = []
    for part in text.split(","):
        name, _, n = part.partition("=")
        if name.split("/")[0] not in ("control", "estimator"):
            raise argparse.ArgumentTypeError(f"kills control, control/child or estimator, not {name!r}")
        out.append((name, int(n or 1)))
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--kills", type=parse_kills, default=parse_kills("control=5,estimator=5"),
                    help="comma list TARGET=N (control, control/child: its loop process, estimator)")
    ap.add_argument("--interleave", action="store_true", help="alternate the targets instead of one after the other")
    ap.add_argument("--scenario", default="hop-in-place")
    ap.add_argument("--max-duration", type=float, default=3600.0, help="the sim's --duration (the campaign stops it when done)")
    ap.add_argument("--endpoint")
    ap.add_argument("--out", default="/tmp/failover")
    args = ap.parse_args(argv)
    summary = Campaign(args).run()
    print(json.dumps(summary))
    return 0


if __name__ == "__main__":
    sys.exit(main())
