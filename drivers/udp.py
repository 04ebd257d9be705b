"""UDP helpers shared by the UDP devices and their emulators (ARCHER firmware, NatNet)."""

from __future__ import annotations

import socket

LOOPBACK = "127.0.0.1"


def free_udp_port(host: str = LOOPBACK) -> int:
    """A UDP port on ``host`` that is free right now (for emulators and tests)."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind((host, 0))
        return s.getsockname()[1]
