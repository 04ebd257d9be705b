"""Write a run's messages to an MCAP file (JSON schemas, readable in Foxglove).

Channels are the Zenoh keys of :mod:`onboard.contracts.topics` (so a recording of a lockstep run looks like
one of the live system); JSON messages carry their msgspec-generated JSON schema; depth images keep
their binary layout (:mod:`onboard.contracts.binary_messages`) under the ``archer-binary-v1`` encoding.
"""

from __future__ import annotations

import json
from collections.abc import Callable, Iterable
from pathlib import Path

import msgspec
from mcap.writer import CompressionType, Writer

from onboard.contracts import binary_messages as bm
from onboard.contracts import messages as m
from onboard.contracts.topics import TOPICS, namespace

BINARY_ENCODING = "archer-binary-v1"


# (channel, (schema name, schema encoding, schema data, message encoding), message bytes)
ExtraRecord = tuple[str, tuple[str, str, bytes, str], bytes]


def write_mcap(path: str | Path, messages: Iterable[tuple[str, int, object]], ns: str | None = None,
               extra: Callable[[str, int, object], Iterable[ExtraRecord]] | None = None) -> int:
    """Write ``(topic name, log time ns, message)`` triples; returns the number written.

    ``extra(topic, log_ns, msg)`` gives more records to write beside each message, at its times
    (the Foxglove scene channels of ``archer sim --record``)."""
    ns = ns or namespace()
    count = 0
    with open(path, "wb") as f:
        writer = Writer(f, compression=CompressionType.ZSTD)
        writer.start(profile="", library="archer sim_twin")
        channels: dict[str, int] = {}
        for topic, log_ns, msg in messages:
            ch = channels.get(topic)
            if ch is None:
                ch = channels[topic] = _register(writer, topic, msg, ns)
            if isinstance(msg, bm.DepthImage):
                data = bm.encode_depth(msg)
                stamp = msg.stamp_ns
            else:
                data = m.encode(msg)
                # an estimate published before the first IMU sample is stamped -1 (valid at no time):
                # MCAP's publish time is unsigned, the message keeps its own stamp
                stamp = max(0, getattr(msg, "stamp_ns", log_ns))
            writer.add_message(ch, log_time=int(log_ns), data=data, publish_time=int(stamp), sequence=count)
            count += 1
            for key, (name, encoding, schema_data, message_encoding), payload in (extra(topic, log_ns, msg) if extra else ()):
                xch = channels.get(key)
                if xch is None:
                    schema = writer.register_schema(name=name, encoding=encoding, data=schema_data)
                    xch = channels[key] = writer.register_channel(topic=key, message_encoding=message_encoding, schema_id=schema)
                writer.add_message(xch, log_time=int(log_ns), data=payload, publish_time=int(stamp), sequence=0)
                count += 1
        writer.finish()
    return count


def _register(writer: Writer, topic: str, msg: object, ns: str) -> int:
    key = TOPICS[topic].key(ns) if topic in TOPICS else f"{ns}/{topic}"
    if isinstance(msg, bm.DepthImage):
        schema = writer.register_schema(name="DepthImage", encoding="", data=b"")
        return writer.register_channel(topic=key, message_encoding=BINARY_ENCODING, schema_id=schema)
    schema_json = msgspec.json.schema(type(msg))
    schema = writer.register_schema(name=type(msg).__name__, encoding="jsonschema", data=json.dumps(schema_json).encode())
    return writer.register_channel(topic=key, message_encoding="json", schema_id=schema)
