"""Zenoh sessions with a loopback default.

Every session has multicast scouting off and binds or dials nothing beyond what its
config names. The stack serves one well-known local endpoint
(``tcp/127.0.0.1:7447``, or ``$ARCHER_ZENOH_ENDPOINT``) from a session in router
mode that it opens itself; services and any stock client connect to it. Config files
for other deployments live in ``deploy/zenoh/`` and are passed with ``config_file``.
"""

from __future__ import annotations

import json
import math
import os
import socket
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Literal

import zenoh

from onboard.contracts.params import MessagingParams

ENDPOINT_ENV = "ARCHER_ZENOH_ENDPOINT"
CONFIG_ENV = "ARCHER_ZENOH_CONFIG"
LOOPBACK = "127.0.0.1"
CONFIG_DIR = Path(__file__).resolve().parents[2] / "deploy" / "zenoh"
TCP_LISTEN = "0A"  # socket state in /proc/net/tcp

Mode = Literal["router", "peer", "client"]


def default_endpoint() -> str:
    return os.environ.get(ENDPOINT_ENV) or MessagingParams().endpoint


def free_endpoint() -> str:
    """A TCP endpoint on loopback with a port free right now (for tests and benches)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind((LOOPBACK, 0))
        return f"tcp/{LOOPBACK}:{s.getsockname()[1]}"


QUEUED_PRIORITIES = ("real_time", "interactive_high")  # the 1 kHz and 100 Hz topics (onboard.contracts.topics)


def link_queue_config(params: MessagingParams = MessagingParams()) -> dict:
    """``transport/link/tx/queue`` sizes for every session of the stack (see ``link_queue_batches``)."""
    return {"size": {name: params.link_queue_batches for name in QUEUED_PRIORITIES}}


def loopback_config(mode: Mode, endpoint: str) -> zenoh.Config:
    """Config for ``mode`` around ``endpoint``: a router listens on it, others dial it.

    Peers listen on an ephemeral loopback port so that peers can link directly
    (gossip through the router) without passing every sample through it.
    """
    conf = zenoh.Config()
    conf.insert_json5("mode", json.dumps(mode))
    conf.insert_json5("scouting/multicast/enabled", "false")
    for name, batches in link_queue_config()["size"].items():
        conf.insert_json5(f"transport/link/tx/queue/size/{name}", str(batches))
    if mode == "router":
        conf.insert_json5("listen/endpoints", json.dumps([endpoint]))
        conf.insert_json5("connect/endpoints", "[]")
    else:
        conf.insert_json5("connect/endpoints", json.dumps([endpoint]))
        listen = [f"tcp/{LOOPBACK}:0"] if mode == "peer" else []
        conf.insert_json5("listen/endpoints", json.dumps(listen))
    return conf


def open_session(
    endpoint: str | None = None,
    mode: Mode = "peer",
    config_file: str | os.PathLike | None = None,
) -> zenoh.Session:
    """Open a session. ``config_file`` (or ``$ARCHER_ZENOH_CONFIG``) overrides the default."""
    config_file = config_file or os.environ.get(CONFIG_ENV)
    if config_file:
        return zenoh.open(zenoh.Config.from_file(str(config_file)))
    return zenoh.open(loopback_config(mode, endpoint or default_endpoint()))


def open_client_session(endpoint: str | None = None, config_file: str | os.PathLike | None = None) -> zenoh.Session:
    """A client session on the same router as ``open_session(endpoint, ..., config_file)``.

    A client's ``open`` returns once its router link is up and it routes every query
    through that router, so a liveliness query right after it sees every token; a
    fresh peer's first queries can still go nowhere (measured: 3 of 5 saw nothing).
    """
    config_file = config_file or os.environ.get(CONFIG_ENV)
    if not config_file:
        return zenoh.open(loopback_config("client", endpoint or default_endpoint()))
    conf = zenoh.Config.from_file(str(config_file))
    conf.insert_json5("mode", json.dumps("client"))
    conf.insert_json5("listen/endpoints", "[]")
    return zenoh.open(conf)


STACK_POLL_S = 0.2  # how often a person's tool looks for the stack while it waits


def open_tool_session(endpoint: str | None = None, config_file: str | os.PathLike | None = None,
                      deadline: float = math.inf, stopped: Callable[[], bool] = lambda: False) -> zenoh.Session | None:
    """A client session for a person's tool (viewer, ``archer status``, ``echo``, ``goal``): it waits
    for the stack to serve ``endpoint`` (saying so once on stderr) and never serves it itself,
    so a stack started afterwards finds its endpoint free. None when ``deadline`` (monotonic [s])
    passes or ``stopped()`` says so first. With a config file the file says where to connect."""
    endpoint = endpoint or default_endpoint()
    config_file = config_file or os.environ.get(CONFIG_ENV)
    said = False
    while not config_file and not endpoint_in_use(endpoint):
        if time.monotonic() >= deadline or stopped():
            return None
        if not said:
            print(f"archer: waiting for the stack at {endpoint} (start it with archer sim or archer run; Ctrl-C to stop)",
                  file=sys.stderr, flush=True)
            said = True
        time.sleep(STACK_POLL_S)
    return open_client_session(endpoint, config_file)


def endpoint_in_use(endpoint: str) -> bool:
    """True when something accepts TCP connections on ``endpoint`` (a running router)."""
    host, port = endpoint.removeprefix("tcp/").rsplit(":", 1)
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.settimeout(0.2)
        return s.connect_ex((host, int(port))) == 0


def endpoint_holder(endpoint: str) -> str:
    """Who listens on ``endpoint``, as ``pid N: command line`` where /proc tells (else "")."""
    port = int(endpoint.rsplit(":", 1)[1])
    inodes = set()
    for table in ("/proc/net/tcp", "/proc/net/tcp6"):
        try:
            rows = Path(table).read_text().splitlines()[1:]
        except OSError:
            continue
        for row in rows:
            fields = row.split()
            if fields[3] == TCP_LISTEN and int(fields[1].rsplit(":", 1)[1], 16) == port:
                inodes.add(f"socket:[{fields[9]}]")
    for proc in Path("/proc").iterdir():
        if not proc.name.isdigit():
            continue
        try:
            if any(os.readlink(fd) in inodes for fd in (proc / "fd").iterdir()):
                argv = (proc / "cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace").strip()
                return f"pid {proc.name}: {argv}"
        except OSError:
            continue
    return ""
