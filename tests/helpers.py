"""Small helpers shared by the tests (importable: pytest puts tests/ on sys.path)."""

from __future__ import annotations

import asyncio
import json
import subprocess
import sys
import time

DEFAULT_TIMEOUT_S = 30.0  # generous: the CI machine may be loaded
POLL_S = 0.01


async def wait_for(predicate, timeout_s: float = DEFAULT_TIMEOUT_S) -> None:
    """Await until ``predicate()`` is true; fail the test after ``timeout_s``."""
    deadline = time.monotonic() + timeout_s
    while not predicate():
        if time.monotonic() > deadline:
            raise AssertionError("condition not met in time")
        await asyncio.sleep(POLL_S)


async def with_running_service(service, endpoint: str, body) -> None:
    """Run ``service``; once it runs and its subscriptions reach the router, ``await
    body(session)`` with a peer session of the test's; then stop the service, whatever happens."""
    from services.runtime.zenoh_session import open_session

    task = asyncio.create_task(service.run())
    session = open_session(endpoint, "peer")
    try:
        await wait_for(lambda: service.state == "running")
        await asyncio.sleep(0.3)  # the subscriptions reach the router
        await body(session)
    finally:
        service.stopping.set()
        await asyncio.wait_for(task, 10.0)
        session.close()


EMULATE = [sys.executable, "-m", "services.cli.main", "emulate"]


def start_emulator(*args: str) -> tuple[subprocess.Popen, dict]:
    """``archer emulate ARGS`` as a process, and the one JSON line saying how to connect."""
    proc = subprocess.Popen(EMULATE + list(args), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    line = proc.stdout.readline()
    if not line:
        proc.wait(10)
        raise AssertionError(proc.stderr.read())
    return proc, json.loads(line)


def stop_emulator(proc: subprocess.Popen) -> dict:
    """SIGTERM (unless it already ended), a clean exit, and its final counters."""
    if proc.poll() is None:
        proc.terminate()
    out, err = proc.communicate(timeout=10)
    assert proc.returncode == 0, err
    assert out == ""  # exactly one line on stdout
    return next(json.loads(line)["final"] for line in err.splitlines() if line.startswith('{"final"'))
