"""The flight recorder: every topic to MCAP, in small files that are each complete.

Subscribes: every key under the namespace (``ns/**``); messages of topics in the
topic table with ``log=True`` are written, raw (the bytes as they crossed the wire),
on a channel named by the Zenoh key, with the message's JSON schema (generated
from :mod:`onboard.contracts.messages`) so Foxglove shows fields by name. Binary topics keep
their layout under the ``archer-binary-v1`` encoding (as ``sim_twin.record``).
Every ``status_period_s`` it also records each live service's status
(``ns/svc/<name>/status``), which carries the control loop's timing statistics.

Files rotate every ``chunk_s`` seconds or ``chunk_bytes`` bytes. A file is written
as ``<stem>.mcap.part`` and renamed to ``<stem>.mcap`` once finished, so every
``.mcap`` in the directory is a complete, indexed MCAP file whatever happens to the
process: SIGTERM finishes the current file; after a crash or ``kill -9`` only the
last ``.part`` is unfinished, and :func:`read_recording` still salvages its chunks
closed up to ``flush_s`` before the crash.

"Lost no message" is checked from ``seq``: per topic and publisher the recorder
counts messages received, sequence gaps (messages lost upstream of it) and
restarts (a publisher that came back at seq 1), and writes the counts into each
file's ``archer.recorder`` metadata record and its status.
"""

from __future__ import annotations

import asyncio
import collections
import json
import os
import struct
import threading
import time
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any

import msgspec
import zenoh
from mcap.reader import make_reader
from mcap.records import Channel, Message, Schema
from mcap.stream_reader import StreamReader
from mcap.writer import CompressionType, Writer

from onboard.contracts import binary_messages as bm
from onboard.contracts import messages as m
from onboard.contracts.params import RecorderParams
from onboard.contracts.topics import TOPICS, Topic, all_keys, status_key, topic_for_key
from services.runtime.peers import live_services, query_status
from services.runtime.service import EVERY_TOPIC, Service
from services.scene import SceneRecording

BINARY_ENCODING = "archer-binary-v1"  # MCAP message encoding of onboard.contracts.binary_messages layouts
METADATA_NAME = "archer.recorder"
PART_SUFFIX = ".part"
MCAP_CHUNK_BYTES = 256 * 1024  # small MCAP chunks: a crash loses little of the .part file
WRITER_PERIOD_S = 0.02  # the writer thread drains the inbox this often
MCAP_TIME_LIMIT = 1 << 63  # MCAP stores times as u64; Python ints are unbounded
REORDER_WINDOW = 64  # a seq further back than this is a restarted publisher, not a late message
BACKLOG_STALL = 100_000  # queued messages (~20 s of every topic) beyond which a growing backlog is a stall
STATE_DIRECTORY_ENV = "STATE_DIRECTORY"  # set by systemd's StateDirectory=
_BINARY_STAMP_SEQ = struct.Struct("<qQ")  # binary header: magic(4) version(2) kind(2) stamp(8) seq(8)
_BINARY_STAMP_OFFSET = 8
_COMPRESSION = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4, "none": CompressionType.NONE}


class _Envelope(msgspec.Struct):
    """The two fields every JSON message carries; the rest is skipped unparsed."""

    stamp_ns: int = 0
    seq: int = 0


_envelope = msgspec.json.Decoder(_Envelope)


def envelope(topic: Topic | None, payload: bytes) -> tuple[int, int]:
    """``(stamp_ns, seq)`` of a payload, ``(0, 0)`` when it has none readable."""
    try:
        if topic is not None and topic.binary:
            stamp, seq = _BINARY_STAMP_SEQ.unpack_from(payload, _BINARY_STAMP_OFFSET)
            return stamp, seq
        env = _envelope.decode(payload)
        return env.stamp_ns, env.seq
    except (msgspec.DecodeError, msgspec.ValidationError, struct.error):
        return 0, 0


@dataclass
class SeqStats:
    """Counts of one topic: received, lost (sequence gaps), restarts, out of order.

    ``max_sources`` is how many publishers the topic may have at once (its
    ``publishers`` column): without a publisher identity, each message continues
    the stream it fits best, and no more streams than that are opened.
    """

    max_sources: int = 1
    received: int = 0
    lost: int = 0
    restarts: int = 0
    reordered: int = 0
    _last: dict[Any, int] = field(default_factory=dict)

    def observe(self, seq: int, source: Any = None) -> None:
        """Count one message with sequence number ``seq`` from publisher ``source`` (None: unknown)."""
        self.received += 1
        if seq <= 0:
            return  # no sequence number to check
        if source is None:
            source = self._match(seq)
        last = self._last.get(source)
        if last is not None:
            if seq > last + 1:
                self.lost += seq - last - 1
            elif seq == 1 or seq < last - REORDER_WINDOW:
                self.restarts += 1  # the publisher came back ...
                self.lost += seq - 1  # ... and these never arrived
            elif seq <= last:
                self.reordered += 1
                return
        self._last[source] = seq

    def _match(self, seq: int) -> Any:
        """The stream ``seq`` continues: exact successor, a new publisher, or the nearest lower."""
        lower, lower_last = None, 0
        for src, last in self._last.items():
            if last == seq - 1:
                return src
            if lower_last < last < seq:
                lower, lower_last = src, last
        room = len(self._last) < self.max_sources
        if room and (seq == 1 or lower is None):
            return len(self._last)  # a publisher not seen before
        if lower is not None:
            return lower
        return next(iter(self._last))  # a restart (seq 1) or a duplicate: any stream will do

    def as_dict(self) -> dict[str, int]:
        return {"received": self.received, "lost": self.lost, "restarts": self.restarts, "reordered": self.reordered}


def schema_for(topic: Topic) -> tuple[str, str, bytes, str]:
    """``(schema name, schema encoding, schema data, message encoding)`` of a topic's channel."""
    if topic.binary:
        return topic.binary, "", b"", BINARY_ENCODING
    return _json_schema(topic.msg_type)


def _json_schema(msg_type: type) -> tuple[str, str, bytes, str]:
    return msg_type.__name__, "jsonschema", json.dumps(msgspec.json.schema(msg_type)).encode(), "json"


class RotatingMcap:
    """MCAP files that rotate by age or size; each is renamed from ``.part`` when finished."""

    def __init__(self, directory: Path, params: RecorderParams, stem: str | None = None) -> None:
        if params.compression not in _COMPRESSION:
            raise ValueError(f"recorder.compression must be one of {sorted(_COMPRESSION)}")
        self.directory = directory
        self.directory.mkdir(parents=True, exist_ok=True)
        self.params = params
        self.stem = stem or f"{time.strftime('archer-%Y%m%d-%H%M%S')}-{os.getpid()}"  # a restart never reuses a name
        self.index = 0
        self.finished: list[Path] = []
        self._file: IO[bytes] | None = None
        self._writer: Writer | None = None
        self._path: Path | None = None
        self._channels: dict[str, int] = {}
        self._opened_s = 0.0
        self._bytes = 0
        self._last_flush_s = 0.0
        self.messages_written = 0

    @property
    def current(self) -> Path | None:
        return self._path

    def _open(self) -> None:
        self.index += 1
        self._path = self.directory / f"{self.stem}-{self.index:04d}.mcap{PART_SUFFIX}"
        self._file = open(self._path, "wb")
        self._writer = Writer(self._file, chunk_size=MCAP_CHUNK_BYTES, compression=_COMPRESSION[self.params.compression])
        self._writer.start(profile="", library="archer recorder")
        self._channels = {}
        self._opened_s = self._last_flush_s = time.monotonic()
        self._bytes = 0

    def write(self, key: str, schema: tuple[str, str, bytes, str], log_ns: int, publish_ns: int, seq: int, data: bytes) -> None:
        if self._writer is None:
            self._open()
        assert self._writer is not None
        channel = self._channels.get(key)
        if channel is None:
            name, encoding, schema_data, message_encoding = schema
            schema_id = self._writer.register_schema(name=name, encoding=encoding, data=schema_data) if encoding else 0
            channel = self._channels[key] = self._writer.register_channel(topic=key, message_encoding=message_encoding, schema_id=schema_id)
        self._writer.add_message(channel, log_time=log_ns, data=data, publish_time=publish_ns, sequence=seq & 0xFFFFFFFF)
        self._bytes += len(data)
        self.messages_written += 1

    def tick(self, metadata: Callable[[], dict[str, str]]) -> None:
        """Rotate when due (``metadata()`` goes into the finished file), else flush when due."""
        if self._writer is None:
            return
        now = time.monotonic()
        if now - self._opened_s >= self.params.chunk_s or self._bytes >= self.params.chunk_bytes:
            self.finish(metadata())
        elif now - self._last_flush_s >= self.params.flush_s:
            self._last_flush_s = now
            self._writer.flush()  # a closed chunk survives a crash
            assert self._file is not None
            self._file.flush()

    def finish(self, metadata: dict[str, str]) -> None:
        """Finish the current file (summary, index, footer) and give it its final name."""
        if self._writer is None:
            return
        assert self._file is not None and self._path is not None
        self._writer.add_metadata(METADATA_NAME, metadata)
        self._writer.finish()
        self._file.flush()
        os.fsync(self._file.fileno())
        self._file.close()
        final = self._path.with_name(self._path.name.removesuffix(PART_SUFFIX))
        os.replace(self._path, final)
        self.finished.append(final)
        self._writer = self._file = self._path = None
        self._prune()

    def _prune(self) -> None:
        files = sorted(self.directory.glob("*.mcap"), key=lambda p: p.stat().st_mtime)
        total = sum(p.stat().st_size for p in files)
        while files and total > self.params.keep_bytes:
            oldest = files.pop(0)
            total -= oldest.stat().st_size
            oldest.unlink()


def default_directory(params: RecorderParams) -> Path:
    if params.directory:
        return Path(params.directory)
    state = os.environ.get(STATE_DIRECTORY_ENV, "").split(":")[0]
    return Path(state) / "recordings" if state else Path("recordings")


class RecorderService(Service):
    name = "recorder"
    params_sections = ("recorder", "view")  # [view]: how the scene channels draw the robot, and their rate
    subscribes = EVERY_TOPIC

    async def setup(self) -> None:
        params: RecorderParams = self.params["recorder"]
        self.files = RotatingMcap(default_directory(params), params)
        self._scene = SceneRecording(self.ns, self.params["view"]) if params.scene else None
        self._epoch_offset_ns = time.time_ns() - time.monotonic_ns()  # stamps are monotonic, Foxglove's epoch
        self.seq_stats = {t.name: SeqStats(max(1, len(t.publishers))) for t in TOPICS.values()}
        self._inbox: collections.deque[tuple[str, Topic, int, bytes, Any]] = collections.deque()
        self._stop_writer = threading.Event()
        self._last_backlog = 0
        self._status_schema = _json_schema(m.ServiceStatus)
        self._schemas = {t.name: schema_for(t) for t in TOPICS.values()}
        rate = self.rate("rx")
        ns = self.ns

        def on_sample(sample: zenoh.Sample) -> None:  # Zenoh thread: queue and return
            key = str(sample.key_expr)
            topic = topic_for_key(ns, key)
            if topic is None or not topic.log:
                return
            info = sample.source_info  # identifies the publisher when it sets one
            source = str(info.source_id) if info is not None else None
            self._inbox.append((key, topic, time.time_ns(), sample.payload.to_bytes(), source))
            rate.tick()

        self._declared.append(self.session.declare_subscriber(all_keys(self.ns), on_sample))
        self._writer = threading.Thread(target=self._write_loop, name="recorder-writer", daemon=True)
        self._writer.start()
        self.log.info("recording", extra={"fields": {"directory": str(self.files.directory)}})

    def _write_loop(self) -> None:
        """Drain the inbox into the current file; rotate; finish on stop (or on a failure)."""
        try:
            while not self._stop_writer.is_set():
                time.sleep(WRITER_PERIOD_S)
                self._drain()
                self.files.tick(self.metadata)
            self._drain()
        except Exception as exc:  # noqa: BLE001 - logged, then main() fails the service
            self.fail(f"writer: {exc!r}")
            self.log.exception("recorder writer failed")
        finally:
            self.files.finish(self.metadata())

    def _drain(self) -> None:
        inbox = self._inbox
        while inbox:
            key, topic, log_ns, payload, source = inbox.popleft()
            stamp, seq = envelope(topic, payload)
            if topic is _STATUS_TOPIC:
                self.files.write(key, self._status_schema, log_ns, stamp or log_ns, 0, payload)
                continue
            self.seq_stats[topic.name].observe(seq, source)
            epoch = stamp + self._epoch_offset_ns  # the scene's own times: the message's stamp on the wall clock
            if not 0 < stamp < MCAP_TIME_LIMIT:  # MCAP times are unsigned; keep the message anyway
                self.count(f"bad_stamp.{topic.name}")
                stamp = epoch = log_ns
            self.files.write(key, self._schemas[topic.name], log_ns, stamp, seq, payload)
            if self._scene is not None and self._scene.due(topic.name, topic.rate_hz, stamp):
                self._write_scene(topic, payload, log_ns, stamp, epoch)

    def _write_scene(self, topic: Topic, payload: bytes, log_ns: int, stamp: int, epoch: int) -> None:
        """The scene records of one message (Foxglove's schemas), beside its raw record."""
        try:
            if topic.binary:
                msg: Any = bm.DECODERS[topic.binary](payload)
            else:
                msg = m.decode(payload, topic.msg_type)
        except m.MessageError:
            self.count(f"scene_rejected.{topic.name}")  # the raw record keeps it as it came
            return
        for channel, schema, data in self._scene.records(topic.name, msg, epoch):
            self.files.write(channel, schema, log_ns, stamp, 0, data)  # seq 0: the raw record carries the sequence

    def record_status(self, status: m.ServiceStatus) -> None:
        """Queue one service's status as a message on ``ns/svc/<name>/status``."""
        key = status_key(self.ns, status.service)
        self._inbox.append((key, _STATUS_TOPIC, time.time_ns(), m.encode(status), None))

    def totals(self) -> dict[str, int]:
        out = {"received": 0, "lost": 0, "restarts": 0, "reordered": 0}
        for stats in self.seq_stats.values():
            for k, v in stats.as_dict().items():
                out[k] += v
        return out

    def metadata(self) -> dict[str, str]:
        """Per-topic counts since the recorder started (MCAP metadata values are strings)."""
        data = {name: json.dumps(stats.as_dict()) for name, stats in self.seq_stats.items() if stats.received}
        data["total"] = json.dumps(self.totals())
        return data

    def status_extra(self) -> dict[str, float]:
        if not hasattr(self, "files"):
            return {}  # asked before setup() ran (the status queryable comes first)
        totals = self.totals()
        return {
            "received": totals["received"],
            "lost": totals["lost"],
            "restarts": totals["restarts"],
            "written": self.files.messages_written,
            "files": len(self.files.finished),
            "backlog": len(self._inbox),
        }

    async def main(self) -> None:
        period = self.params["recorder"].status_period_s

        def poll() -> None:
            for name in live_services(self.session, self.ns):
                status = self.status() if name == self.name else query_status(self.session, self.ns, name)
                if status is not None:
                    self.record_status(status)

        while not self.stopping.is_set():
            try:
                await asyncio.wait_for(self.stopping.wait(), period)
            except asyncio.TimeoutError:
                await asyncio.to_thread(poll)
            if not self._writer.is_alive():  # exit with an error: the supervisor restarts us
                raise RuntimeError("the recorder's writer thread died")

    def progress(self) -> bool:
        """The writer thread lives and keeps up (what arrives gets written)."""
        backlog = len(self._inbox)
        alive_and_draining = self._writer.is_alive() and (backlog < BACKLOG_STALL or backlog < self._last_backlog)
        self._last_backlog = backlog
        return alive_and_draining

    async def teardown(self) -> None:
        self._stop_writer.set()
        await asyncio.to_thread(self._writer.join)
        self.log.info("recording finished", extra={"fields": {"files": len(self.files.finished), **self.totals()}})


# A pseudo-topic for service statuses: recorded, never published by anyone.
_STATUS_TOPIC = Topic("status", "svc", m.ServiceStatus, 0, (), log=True)


# --- reading ------------------------------------------------------------------------


@dataclass
class Recorded:
    key: str  # Zenoh key (the MCAP channel)
    schema: str  # message type name ("StateEstimate"), or the binary kind
    log_ns: int  # wall-clock receive time [ns]
    publish_ns: int  # the message's own stamp [ns]
    data: bytes


def recording_files(paths: Iterable[str | Path], include_partial: bool = True) -> list[Path]:
    """Expand directories into their ``.mcap`` (and ``.mcap.part``) files, sorted by name."""
    out: list[Path] = []
    for p in map(Path, paths):
        if p.is_dir():
            out.extend(sorted(p.glob("*.mcap")))
            if include_partial:
                out.extend(sorted(p.glob(f"*.mcap{PART_SUFFIX}")))
        else:
            out.append(p)
    return sorted(out, key=lambda p: p.name)


def read_recording(paths: Iterable[str | Path]) -> Iterator[Recorded]:
    """Every message of the files, in file order; an unfinished file yields what survived."""
    for path in recording_files(paths):
        if path.name.endswith(PART_SUFFIX):
            yield from _salvage(path)
            continue
        with open(path, "rb") as f:
            reader = make_reader(f)
            for schema, channel, message in reader.iter_messages():
                yield Recorded(channel.topic, schema.name if schema else "", message.log_time, message.publish_time, message.data)


def _salvage(path: Path) -> Iterator[Recorded]:
    """Stream the records of a truncated file until the damage."""
    schemas: dict[int, Schema] = {}
    channels: dict[int, Channel] = {}
    with open(path, "rb") as f:
        try:
            for record in StreamReader(f, skip_magic=False, validate_crcs=True).records:
                if isinstance(record, Schema):
                    schemas[record.id] = record
                elif isinstance(record, Channel):
                    channels[record.id] = record
                elif isinstance(record, Message) and record.channel_id in channels:
                    ch = channels[record.channel_id]
                    schema = schemas.get(ch.schema_id)
                    yield Recorded(ch.topic, schema.name if schema else "", record.log_time, record.publish_time, record.data)
        except Exception:  # noqa: BLE001 - whatever the torn tail looks like, stop there
            return


def file_metadata(path: str | Path) -> dict[str, Any]:
    """The recorder's counts stored in a finished file."""
    with open(path, "rb") as f:
        for meta in make_reader(f).iter_metadata():
            if meta.name == METADATA_NAME:
                return {k: json.loads(v) for k, v in meta.metadata.items()}
    return {}
