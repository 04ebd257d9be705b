"""The stack's own Zenoh router: serves the well-known local endpoint.

zenoh-python opens a session in router mode, so no separate ``zenohd`` binary is
needed. ``archer sim`` opens one itself; on the robot it runs as ``archer-router``.
"""

from __future__ import annotations

from services.runtime.service import Service


class RouterService(Service):
    name = "router"
    zenoh_mode = "router"
