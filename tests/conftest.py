"""Shared fixtures: a real Zenoh router on a free loopback port per test."""

from __future__ import annotations

from services.runtime.process_env import prepare_environment

prepare_environment()  # as the archer entry point does, before a test module loads numba

import os  # noqa: E402
import threading  # noqa: E402
import traceback  # noqa: E402
from pathlib import Path  # noqa: E402

import pytest  # noqa: E402
import zenoh  # noqa: E402
from hypothesis import settings  # noqa: E402

# The suite's property tests draw the same examples on every run (CI's verdict is the code's, not
# the draw's); HYPOTHESIS_PROFILE=explore searches afresh each run, for a developer hunting cases.
settings.register_profile("ci", derandomize=True)
settings.register_profile("explore", derandomize=False)
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "ci"))

from services.runtime.zenoh_session import free_endpoint, open_session  # noqa: E402


TIMING_RERUNS = 1  # a failure that does not repeat is the machine's, one that does is ours
TIMING_RERUN_DELAY_S = 2


# A Zenoh session left open with callback subscribers keeps their (non-daemon) callback threads, and
# the interpreter waits for them at exit: pytest reported its result and then never ended (a CI run
# hung so). Every session the tests open is recorded with the test that opened it; those still open
# when the run ends are closed then and named, so that a leak is seen and fixed, not waited on.
_sessions_opened: list[tuple[str, zenoh.Session]] = []
_opening_test = ["(collection)"]
_zenoh_open = zenoh.open
OPENER_FRAMES = 4  # of the opener's stack, named with a leak (a thread an earlier test left may be the opener)


def _recorded_open(*args, **kwargs) -> zenoh.Session:
    session = _zenoh_open(*args, **kwargs)
    frames = traceback.extract_stack(limit=OPENER_FRAMES + 1)[:-1]
    where = " < ".join(f"{Path(f.filename).name}:{f.lineno} {f.name}" for f in reversed(frames))
    _sessions_opened.append((f"{_opening_test[0]} [thread {threading.current_thread().name}: {where}]", session))
    return session


zenoh.open = _recorded_open


def pytest_runtest_setup(item) -> None:
    _opening_test[0] = item.nodeid


def pytest_sessionfinish(session, exitstatus) -> None:
    leaked = []
    for nodeid, zsession in _sessions_opened:
        if not zsession.is_closed():
            zsession.close()
            leaked.append(nodeid)
    _sessions_opened.clear()
    if leaked:
        reporter = session.config.pluginmanager.get_plugin("terminalreporter")
        line = f"Zenoh sessions left open by the tests, closed at the end: {sorted(set(leaked))}"
        if reporter is not None:
            reporter.write_line(line, yellow=True)
        else:
            print(line)


def pytest_collection_modifyitems(config, items):
    """A test marked ``timing_sensitive(reason=...)`` gets one rerun; no other test does."""
    for item in items:
        mark = item.get_closest_marker("timing_sensitive")
        if mark is None:
            continue
        if not mark.kwargs.get("reason"):
            raise pytest.UsageError(f"{item.nodeid}: timing_sensitive needs reason=...")
        item.add_marker(pytest.mark.flaky(reruns=TIMING_RERUNS, reruns_delay=TIMING_RERUN_DELAY_S))


@pytest.fixture
def zenoh_router():
    """A router session listening on a free 127.0.0.1 port; yields its endpoint."""
    endpoint = free_endpoint()
    router = open_session(endpoint, "router")
    try:
        yield endpoint
    finally:
        router.close()


@pytest.fixture
def zenoh_session(zenoh_router):
    """A peer session connected to the test router."""
    session = open_session(zenoh_router, "peer")
    try:
        yield session
    finally:
        session.close()


@pytest.fixture(autouse=True)
def no_leaked_bus():
    """Fail any test that leaves a python-can virtual bus or a socketcand client open."""
    from can.interfaces import virtual

    from drivers.socketcand import SocketcandBus

    before = {name for name, queues in virtual.channels.items() if queues}
    yield
    leaked = {name: len(q) for name, q in virtual.channels.items() if q and name not in before}
    assert not leaked, f"test leaked python-can buses: {leaked}"
    assert SocketcandBus.open_buses == 0, "test leaked a socketcand bus"
