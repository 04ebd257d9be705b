"""One clock abstraction, so the same service code runs on wall time and sim time."""

from __future__ import annotations

import threading
import time
from typing import Protocol


class Clock(Protocol):
    def now_ns(self) -> int: ...


class WallClock:
    """Monotonic wall time (the robot's clock)."""

    def now_ns(self) -> int:
        return time.monotonic_ns()


class SimClock:
    """Simulated time, advanced by the twin or the lockstep runner. Never goes back."""

    def __init__(self, start_ns: int = 0) -> None:
        self._now = start_ns
        self._lock = threading.Lock()

    def now_ns(self) -> int:
        return self._now

    def advance_to(self, t_ns: int) -> None:
        with self._lock:
            if t_ns < self._now:
                raise ValueError(f"sim clock cannot go back from {self._now} to {t_ns}")
            self._now = t_ns
