"""A service's helper process: spawned clean, talked to over a pipe.

The control loop and the geometric MPC each run in a process of their own (their own
interpreter, GIL and scheduling class). Both speak the same small protocol: the child sends
one hello first (``{"realtime": ...}``, or ``{"error": ...}`` when it could not start), then
reports (dicts), and a last one with ``"final": True`` after ``"stop"``.
"""

from __future__ import annotations

import multiprocessing as mp
import threading
import time
from typing import Any, Callable

STOP_TIMEOUT_S = 3.0  # [s] for the last report, then the child is killed
POLL_S = 0.1


class ChildProcess:
    """Starts a child (``target(cfg, conn)``) and talks to it."""

    def __init__(self, target: Callable[..., None], cfg: Any, name: str) -> None:
        ctx = mp.get_context("spawn")  # a clean interpreter: no inherited threads or sessions
        self._conn, child = ctx.Pipe()
        self.name = name
        self.proc = ctx.Process(target=target, args=(cfg, child), name=name, daemon=True)
        self.last: dict[str, Any] = {}
        self.realtime: dict[str, str] = {}
        self._send_lock = threading.Lock()  # requests may come from Zenoh's threads

    def start(self, timeout_s: float) -> None:
        self.proc.start()
        if not self._conn.poll(timeout_s):
            self.proc.kill()
            raise RuntimeError(f"{self.name} did not start")
        first = self._conn.recv()
        if "error" in first:
            self.proc.join(1.0)
            raise RuntimeError(f"{self.name} failed: {first['error']}")
        self.realtime = first.get("realtime", {})

    def poll(self) -> list[dict[str, Any]]:
        """Reports received since the last call (non-blocking)."""
        out = []
        try:
            while self._conn.poll():
                rep = self._conn.recv()
                out.append(rep)
                self.last = rep
        except (EOFError, OSError):
            pass
        return out

    def send(self, request: Any) -> None:
        """A request to the child; a child already gone is not an error here (``alive`` says it)."""
        with self._send_lock:
            try:
                self._conn.send(request)
            except (BrokenPipeError, OSError):
                pass

    def wait_final(self, timeout_s: float) -> dict[str, Any]:
        """The child's last report (after a stop or a timed run); killed if it does not end."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if self._conn.poll(POLL_S):
                try:
                    rep = self._conn.recv()
                except EOFError:
                    break
                self.last = rep
                if rep.get("final"):
                    break
        self.proc.join(STOP_TIMEOUT_S)
        if self.proc.is_alive():
            self.proc.kill()
        return self.last

    def stop(self) -> dict[str, Any]:
        self.send("stop")
        return self.wait_final(STOP_TIMEOUT_S)

    @property
    def alive(self) -> bool:
        return self.proc.is_alive()
