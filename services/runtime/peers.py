"""Ask a namespace which services are alive and what their status says (Zenoh queries).

The recorder, the soak and ``archer status`` all ask; the answer is each service's
liveliness token and its status queryable (:mod:`services.runtime.service`).
"""

from __future__ import annotations

from typing import Any

import msgspec
import zenoh

from onboard.contracts import messages as msgs
from onboard.contracts.topics import liveliness_key, params_key, status_key

QUERY_TIMEOUT_S = 2.0


def live_services(session: zenoh.Session, ns: str) -> list[str]:
    prefix = liveliness_key(ns, "")
    names = []
    for reply in session.liveliness().get(liveliness_key(ns, "*"), timeout=QUERY_TIMEOUT_S):
        if reply.ok is not None:
            names.append(str(reply.ok.key_expr).removeprefix(prefix))
    return sorted(set(names))


def query_status(session: zenoh.Session, ns: str, service: str) -> msgs.ServiceStatus | None:
    for reply in session.get(status_key(ns, service), timeout=QUERY_TIMEOUT_S):
        if reply.ok is not None:
            return msgs.decode(reply.ok.payload.to_bytes(), msgs.ServiceStatus)
    return None


def query_params(session: zenoh.Session, ns: str, service: str, changes: dict[str, Any] | None = None) -> msgs.ParamReply | None:
    """A service's parameters, after setting ``changes`` (``{"section.name": value}``) if given;
    None when it does not answer. A refused change comes back in the reply's ``error``."""
    body = msgspec.json.encode(msgs.ParamRequest(set=changes)) if changes else None
    for reply in session.get(params_key(ns, service), payload=body, timeout=QUERY_TIMEOUT_S):
        if reply.ok is not None:
            return msgspec.json.decode(reply.ok.payload.to_bytes(), type=msgs.ParamReply)
    return None


def request_once(session: zenoh.Session, ns: str, service: str, field: str) -> str:
    """Send an operator command counter (``"section.name_request"``): its value plus one.
    Empty on success, else why not."""
    now = query_params(session, ns, service)
    if now is None:
        return f"{service} does not answer"
    if field not in now.params:
        return f"{service} has no parameter {field}"
    reply = query_params(session, ns, service, {field: int(now.params[field]) + 1})
    if reply is None:
        return f"{service} does not answer"
    return reply.error
