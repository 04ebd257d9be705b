"""Zenoh configurations for the robot, generated from the topic table.

The access-control rules derive from the ``publishers`` column of
:mod:`onboard.contracts.topics`, so they cannot drift from it: only ``control`` may put wheel
and foot commands, only ``hardware`` or ``twin`` may put sensor frames, and so on.

How it is enforced: every service connects as a Zenoh *client* to the robot's
router (peers would link directly and bypass it), authenticates with a user name
and password (``transport/auth/usrpwd``; the user name is the service name), and
the router's ACL matches subjects by user name. Default permission is deny; the
rules allow:

- everyone: to subscribe, to receive what it subscribed, to see liveliness and to
  query any service's status;
- each service: to declare its own status/params queryables, answer on them and
  hold its own liveliness token (no service can pose as another);
- each topic's publishers: to put on that topic;
- the operator: to put goals and to query ``params`` (which sets parameters, e.g.
  arming requests).

Rules use the namespace pattern ``archer/*`` so one file serves every robot.
``archer deploy acl`` prints the checked-in files; ``tests/test_acl.py`` fails if
they differ from what this module generates.
"""

from __future__ import annotations

import json
import secrets
from pathlib import Path
from typing import Any

from onboard.contracts.topics import SERVICES, STANDBY_SERVICES, STANDBY_SUFFIX, TOPICS, liveliness_key, params_key, status_key
from services.runtime.zenoh_session import link_queue_config

NS_PATTERN = "archer/*"  # every robot's namespace
ALL_KEYS = "archer/**"
OPERATOR = "operator"  # people and tools: `archer status`, `archer echo`, zenoh-cli, goals
ROUTER_PORT = 7447
TLS_PORT = 7448
CONFIG_DIR = "/etc/archer/zenoh"
USERS_FILE = f"{CONFIG_DIR}/users.txt"
TLS_DIR = "/etc/archer/tls"
PASSWORD_BYTES = 24

# What a subscriber-side peer needs to see, in both directions through the router.
_OBSERVE_IN = ["declare_subscriber", "declare_liveliness_subscriber", "liveliness_query"]
_OBSERVE_OUT = [
    "put",
    "declare_subscriber",
    "declare_queryable",
    "query",
    "reply",
    "liveliness_token",
    "declare_liveliness_subscriber",
    "liveliness_query",
]
_OWN = ["declare_queryable", "reply", "liveliness_token"]


def users() -> list[str]:
    """Every subject: the services, anyone the topic table names, and the operator."""
    names = set(SERVICES) | {OPERATOR}
    for topic in TOPICS.values():
        names.update(topic.publishers)
    return sorted(names)


def access_control() -> dict[str, Any]:
    """The ``access_control`` section (Zenoh 1.x schema: rules, subjects, policies)."""
    everyone = users()
    rules: list[dict[str, Any]] = [
        _rule("observe-in", ["ingress"], _OBSERVE_IN, [ALL_KEYS]),
        _rule("observe-out", ["egress"], _OBSERVE_OUT, [ALL_KEYS]),
        _rule("query-status", ["ingress"], ["query"], [status_key(NS_PATTERN, "*")]),
        _rule("set-params", ["ingress"], ["query"], [params_key(NS_PATTERN, "*")]),
    ]
    policies: list[dict[str, Any]] = [
        {"id": "everyone-observes", "rules": ["observe-in", "observe-out", "query-status"], "subjects": ["everyone"]},
        {"id": "operator-sets-params", "rules": ["set-params"], "subjects": [OPERATOR]},
    ]
    for name in everyone:
        own = [f"{NS_PATTERN}/svc/{name}/**", liveliness_key(NS_PATTERN, name)]
        if name in STANDBY_SERVICES:  # its hot standby, under its user
            own += [f"{NS_PATTERN}/svc/{name}{STANDBY_SUFFIX}/**", liveliness_key(NS_PATTERN, name + STANDBY_SUFFIX)]
        rules.append(_rule(f"own-{name}", ["ingress"], _OWN, own))
        policies.append({"id": f"{name}-owns-its-keys", "rules": [f"own-{name}"], "subjects": [name]})
    for topic in TOPICS.values():
        rules.append(_rule(f"publish-{topic.name}", ["ingress"], ["put"], [topic.key(NS_PATTERN)]))
        policies.append({"id": f"{topic.name}-publishers", "rules": [f"publish-{topic.name}"], "subjects": sorted(topic.publishers)})
    subjects = [{"id": "everyone", "usernames": everyone}] + [{"id": n, "usernames": [n]} for n in everyone]
    return {"enabled": True, "default_permission": "deny", "rules": rules, "subjects": subjects, "policies": policies}


def _rule(rule_id: str, flows: list[str], messages: list[str], keys: list[str]) -> dict[str, Any]:
    return {"id": rule_id, "permission": "allow", "flows": flows, "messages": messages, "key_exprs": keys}


def router_config(
    listen: list[str] | None = None,
    users_file: str = USERS_FILE,
    tls: bool = False,
    tls_dir: str = TLS_DIR,
) -> dict[str, Any]:
    """The robot's router: loopback for the local services, the LAN for offboard ones."""
    if listen is None:
        # All interfaces (127.0.0.1 included) on the well-known port; with TLS the
        # LAN gets its own port and plain TCP stays on loopback.
        listen = [f"tcp/127.0.0.1:{ROUTER_PORT}", f"tls/0.0.0.0:{TLS_PORT}"] if tls else [f"tcp/0.0.0.0:{ROUTER_PORT}"]
    config: dict[str, Any] = {
        "mode": "router",
        "listen": {"endpoints": listen},
        "connect": {"endpoints": []},
        "scouting": {"multicast": {"enabled": False}, "gossip": {"enabled": True}},
        "transport": {"auth": {"usrpwd": {"dictionary_file": users_file}}, "link": {"tx": {"queue": link_queue_config()}}},
        "access_control": access_control(),
    }
    if tls:
        # Mutual TLS on the LAN endpoint: a workstation needs a certificate signed
        # by the robot's CA as well as a password.
        config["transport"]["link"] |= {
            "tls": {
                "root_ca_certificate": f"{tls_dir}/ca.pem",
                "listen_private_key": f"{tls_dir}/router-key.pem",
                "listen_certificate": f"{tls_dir}/router.pem",
                "enable_mtls": True,
            }
        }
    return config


def client_config(user: str, password: str, connect: list[str] | None = None) -> dict[str, Any]:
    """A service's (or the operator's) session: a client of the router, authenticated."""
    return {
        "mode": "client",
        "connect": {"endpoints": connect or [f"tcp/127.0.0.1:{ROUTER_PORT}"]},
        "listen": {"endpoints": []},
        "scouting": {"multicast": {"enabled": False}},
        "transport": {"auth": {"usrpwd": {"user": user, "password": password}}, "link": {"tx": {"queue": link_queue_config()}}},
    }


def tls_client_config(user: str, password: str, connect: list[str], tls_dir: str = TLS_DIR) -> dict[str, Any]:
    """An offboard client over mutual TLS: ``ca.pem`` and its own ``<user>.pem``/``<user>-key.pem``
    (an X.509 v3 certificate signed by the robot's CA), plus the password as on the robot."""
    config = client_config(user, password, connect)
    config["transport"]["link"] |= {
        "tls": {
            "root_ca_certificate": f"{tls_dir}/ca.pem",
            "connect_private_key": f"{tls_dir}/{user}-key.pem",
            "connect_certificate": f"{tls_dir}/{user}.pem",
            "enable_mtls": True,
        }
    }
    return config


def new_passwords(names: list[str] | None = None) -> dict[str, str]:
    return {name: secrets.token_urlsafe(PASSWORD_BYTES) for name in (names or users())}


def users_file_text(passwords: dict[str, str]) -> str:
    """The router's ``dictionary_file``: one ``user:password`` per line."""
    return "".join(f"{user}:{password}\n" for user, password in sorted(passwords.items()))


def render(config: dict[str, Any], comment: str) -> str:
    """JSON5 text: a comment header, then plain JSON (a subset of JSON5)."""
    header = "".join(f"// {line}".rstrip() + "\n" for line in comment.strip().splitlines())
    return header + json.dumps(config, indent=2) + "\n"


_GENERATED = "Generated by `archer deploy acl` from onboard/contracts/topics.py; do not edit by hand."

def checked_in_files() -> dict[str, str]:
    """File name in ``deploy/zenoh/`` -> text, for every generated config."""
    return {
        "robot-router.json5": render(
            router_config(),
            f"""The robot's router with access control (robot LAN).
Local services connect as clients on 127.0.0.1:{ROUTER_PORT}; an offboard workstation
connects to the robot's LAN address on port {ROUTER_PORT}. Everyone authenticates with
a user name and password from {USERS_FILE} (written by `archer deploy install`).
{_GENERATED}""",
        ),
        "robot-router-tls.json5": render(
            router_config(tls=True),
            f"""As robot-router.json5, but the LAN endpoint is mutual TLS on port {TLS_PORT}
(certificates in {TLS_DIR}: ca.pem, router.pem, router-key.pem). Optional.
{_GENERATED}""",
        ),
    }


def write_checked_in(directory: Path) -> list[Path]:
    written = []
    for name, text in checked_in_files().items():
        path = directory / name
        path.write_text(text)
        written.append(path)
    return written
