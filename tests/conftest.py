"""Shared fixtures: a real Zenoh router on a free loopback port per test."""

from __future__ import annotations

import pytest

from services.zenoh_session import free_endpoint, open_session


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
