"""Small helpers shared by the tests (importable: pytest puts tests/ on sys.path)."""

from __future__ import annotations

import asyncio
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
