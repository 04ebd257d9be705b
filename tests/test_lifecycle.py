"""Every way of stopping the real-time stack stops all of it (issue 14).

Each test runs ``archer sim --mode realtime`` (or ``archer run``) as a real process tree
on a free loopback endpoint, stops it the way a user or a crash would, and checks that no
process of the tree is left and that nobody serves the endpoint any more.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from helpers import descendants

from onboard.contracts.topics import liveliness_key
from services.runtime.service import EXIT_CONFLICT, EXIT_SIGINT
from services.runtime.zenoh_session import endpoint_in_use, free_endpoint, open_session

STACK_UP_TIMEOUT_S = 90.0  # services start one after another on a loaded 2-core machine
STOP_BOUND_S = 3.0  # SIGINT / SIGTERM: every process gone by then
ORPHAN_BOUND_S = 1.0  # kill -9 of the parent: its children gone by then (plus polling)
POLL_S = 0.02


def _ppid_and_state(pid: int) -> tuple[int, str] | None:
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return None
    fields = stat.rsplit(")", 1)[1].split()
    return int(fields[1]), fields[0]


def _alive(pid: int) -> bool:
    """Running (a zombie has exited: only a parent that never reaps keeps its entry)."""
    info = _ppid_and_state(pid)
    return info is not None and info[1] != "Z"


def _descendants(root: int) -> set[int]:
    return set(descendants(root))


def _wait_gone(pids: set[int], bound_s: float) -> tuple[float, set[int]]:
    t0 = time.monotonic()
    while time.monotonic() - t0 < bound_s + 2.0:
        left = {p for p in pids if _alive(p)}
        if not left:
            return time.monotonic() - t0, set()
        time.sleep(POLL_S)
    return time.monotonic() - t0, {p for p in pids if _alive(p)}


def _kill_all(pids: set[int]) -> None:
    for pid in pids:
        try:
            os.kill(pid, signal.SIGKILL)
        except ProcessLookupError:
            pass


def _archer(*argv: str) -> list[str]:
    return [sys.executable, "-m", "services.cli.main", *argv]


class RealtimeSim:
    """``archer sim --mode realtime`` as a process tree; every process killed at exit."""

    def __init__(self, endpoint: str, ns: str, *extra: str) -> None:
        self.endpoint, self.ns = endpoint, ns
        self.proc = subprocess.Popen(
            _archer("sim", "--mode", "realtime", "--scenario", "hop-in-place", "--duration", "60", "--keep-going", "--quiet", "--json",
                    "--endpoint", endpoint, "--namespace", ns, *extra),
            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        self.tree: set[int] = set()

    def wait_running(self) -> None:
        """Until the twin (which starts after every service) is alive; records the tree."""
        deadline = time.monotonic() + STACK_UP_TIMEOUT_S
        while not endpoint_in_use(self.endpoint):
            assert self.proc.poll() is None, self.proc.communicate()
            assert time.monotonic() < deadline, "no router came up"
            time.sleep(0.1)
        session = open_session(self.endpoint, "client")
        try:
            while not any(r.ok is not None for r in session.liveliness().get(liveliness_key(self.ns, "twin"), timeout=1.0)):
                assert self.proc.poll() is None, self.proc.communicate()
                assert time.monotonic() < deadline, "the twin did not start"
                time.sleep(0.2)
        finally:
            session.close()
        self.tree = _descendants(self.proc.pid)
        assert len(self.tree) >= 3, "router, estimator and control run as children"

    def close(self) -> None:
        _kill_all({self.proc.pid} | self.tree | _descendants(self.proc.pid))
        self.proc.communicate(timeout=10)


@pytest.fixture
def sim_factory():
    sims: list[RealtimeSim] = []

    def make(*extra: str) -> RealtimeSim:
        sim = RealtimeSim(free_endpoint(), f"archer/life{os.getpid()}x{len(sims)}", *extra)
        sims.append(sim)
        return sim

    yield make
    for sim in sims:
        sim.close()


@pytest.mark.parametrize("sig, code", [(signal.SIGINT, EXIT_SIGINT), (signal.SIGTERM, 0)])
def test_a_stop_signal_to_the_sim_stops_every_process(sim_factory, sig, code) -> None:
    sim = sim_factory()
    sim.wait_running()
    sim.proc.send_signal(sig)
    took, left = _wait_gone({sim.proc.pid} | sim.tree, STOP_BOUND_S)
    assert not left, f"still running {took:.2f} s after {sig.name}: {left}"
    assert took <= STOP_BOUND_S
    out, err = sim.proc.communicate(timeout=5)
    assert sim.proc.returncode == code, err[-2000:]
    assert f'"stopped_by": "{sig.name}"' in out.strip().splitlines()[-1]
    assert not endpoint_in_use(sim.endpoint), "a Zenoh session still serves the endpoint"


def test_kill_9_of_the_sim_takes_its_services_with_it(sim_factory) -> None:
    sim = sim_factory()
    sim.wait_running()
    sim.proc.kill()
    took, left = _wait_gone(sim.tree, ORPHAN_BOUND_S)
    assert not left, f"orphans {took:.2f} s after kill -9 of their supervisor: {left}"
    assert took <= ORPHAN_BOUND_S + 0.2  # the bound plus this test's polling
    assert not endpoint_in_use(sim.endpoint)


def test_a_sim_refuses_an_endpoint_someone_else_serves(capfd) -> None:
    endpoint = free_endpoint()
    stranger = open_session(endpoint, "router")
    try:
        proc = subprocess.run(_archer("sim", "--mode", "realtime", "--scenario", "hop-in-place", "--duration", "5",
                                      "--endpoint", endpoint, "--namespace", "archer/stranger"),
                              capture_output=True, text=True, timeout=60)
    finally:
        stranger.close()
    assert proc.returncode == 2
    assert "already served by another process" in proc.stderr and f"pid {os.getpid()}" in proc.stderr
    assert "--join" in proc.stderr


@pytest.mark.parametrize("sig, code", [(signal.SIGINT, EXIT_SIGINT), (signal.SIGTERM, 0)])
def test_archer_run_stops_on_a_signal(zenoh_router, sig, code) -> None:
    proc = subprocess.Popen(_archer("run", "estimator", "--endpoint", zenoh_router, "--namespace", f"archer/run{sig}"),
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_IGN))  # as a script's background job
    session = open_session(zenoh_router, "client")
    try:
        deadline = time.monotonic() + STACK_UP_TIMEOUT_S
        key = liveliness_key(f"archer/run{sig}", "estimator")
        while not any(r.ok is not None for r in session.liveliness().get(key, timeout=1.0)):
            assert proc.poll() is None and time.monotonic() < deadline
            time.sleep(0.1)
        t0 = time.monotonic()
        proc.send_signal(sig)
        proc.wait(timeout=10)
        assert time.monotonic() - t0 <= STOP_BOUND_S
        assert proc.returncode == code, proc.stderr.read()[-2000:]
        # its session is closed: the token is gone
        assert not any(r.ok is not None for r in session.liveliness().get(key, timeout=1.0))
    finally:
        session.close()
        if proc.poll() is None:
            proc.kill()
        proc.wait()


# real time: loops at their rate, processes and Zenoh over loopback share two loaded cores
pytestmark = pytest.mark.timing_sensitive(reason="real-time loops, processes or Zenoh over loopback on a shared host")
