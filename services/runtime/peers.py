"""Ask a namespace which services are alive and what their status says (Zenoh queries).

The recorder, the soak and ``archer status`` all ask; the answer is each service's
liveliness token and its status queryable (:mod:`services.runtime.service`).
"""

from __future__ import annotations

import zenoh

from onboard import messages as msgs
from onboard.topics import liveliness_key, status_key

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
