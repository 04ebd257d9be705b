"""The flight recorder: sequence accounting, rotation, valid files after SIGTERM and kill -9."""

from __future__ import annotations

import pytest

import asyncio
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import zenoh
from mcap.reader import make_reader

from onboard.contracts import messages as m
from onboard.contracts.params import RecorderParams
from onboard.contracts.topics import TOPICS
from services.runtime.peers import live_services
from services.recorder import PART_SUFFIX, RecorderService, SeqStats, file_metadata, read_recording
from services.runtime.zenoh_session import open_session
from helpers import with_running_service

NS = "archer/rectest"
START_TIMEOUT_S = 20.0


def test_seq_stats_counts_gaps_restarts_and_interleaved_publishers():
    s = SeqStats()
    for seq in (1, 2, 3, 6, 7, 7, 1, 2):
        s.observe(seq)
    assert s.as_dict() == {"received": 8, "lost": 2, "restarts": 1, "reordered": 1}
    late = SeqStats()
    for seq in [*range(1, 501), 5, 6]:  # came back, its first four messages missed
        late.observe(seq)
    assert late.as_dict() == {"received": 502, "lost": 4, "restarts": 1, "reordered": 0}
    # two publishers on one topic (e.g. `phase`: estimator and control), no identity given
    both = SeqStats(max_sources=2)
    for seq in (1, 1, 2, 2, 3, 4, 3, 5):
        both.observe(seq)
    assert both.lost == 0 and both.received == 8
    ident = SeqStats(max_sources=2)
    for seq, src in ((5, "a"), (9, "b"), (6, "a"), (12, "b")):
        ident.observe(seq, src)
    assert ident.lost == 2  # b skipped 10 and 11; a's first seq is not a loss


def _state(seq: int, stamp_ns: int | None = None) -> bytes:
    msg = m.StateEstimate(
        stamp_ns=time.monotonic_ns() if stamp_ns is None else stamp_ns, seq=seq, position=[0.0, 0.0, 0.4], velocity=[0.0, 0.0, 0.0],
        quat=[1.0, 0.0, 0.0, 0.0], omega=[0.0, 0.0, 0.0], wheel_vel=[0.0, 0.0, 0.0], foot_pos=0.0,
        foot_vel=0.0, contact=False, phase="flight", pos_vel_cov=[0.0] * 36, att_cov=[0.0, 0.0, 0.0],
    )
    return m.encode(msg)


def _publish(session: zenoh.Session, seqs: list[int], period_s: float, bad_stamp_at: int = 0) -> None:
    pub = session.declare_publisher(TOPICS["state"].key(NS), reliability=zenoh.Reliability.RELIABLE, congestion_control=zenoh.CongestionControl.BLOCK)
    time.sleep(0.3)  # a fresh session learns of the recorder's subscription asynchronously
    for seq in seqs:
        pub.put(_state(seq, -5 if seq == bad_stamp_at else None))
        time.sleep(period_s)
    pub.undeclare()


def _valid_messages(path: Path) -> list[int]:
    """Seq numbers of a finished file, read through its index (fails on an invalid file)."""
    with open(path, "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        assert summary is not None and summary.statistics is not None
        seqs = [msg.sequence for _, _, msg in reader.iter_messages()]
        assert summary.statistics.message_count == len(seqs)
        return seqs


def test_recorder_rotates_into_finished_files_with_schemas(tmp_path, zenoh_router):
    params = RecorderParams(directory=str(tmp_path), chunk_s=0.4, flush_s=0.1, status_period_s=0.2)
    seqs = [s for s in range(1, 301) if s not in (100, 101, 102)]  # three lost upstream

    async def scenario() -> RecorderService:
        rec = RecorderService(ns=NS, endpoint=zenoh_router, params={"recorder": params})

        async def publish(session: zenoh.Session) -> None:
            await asyncio.to_thread(_publish, session, seqs, 0.005, 200)  # one stamp MCAP cannot store
            await asyncio.sleep(0.3)

        await with_running_service(rec, zenoh_router, publish)
        return rec

    rec = asyncio.run(asyncio.wait_for(scenario(), 60))
    files = sorted(tmp_path.glob("*.mcap"))
    assert len(files) >= 3 and not list(tmp_path.glob(f"*{PART_SUFFIX}"))
    recorded = [s for f in files for s in _valid_messages(f) if s]  # statuses carry seq 0
    assert recorded == seqs
    assert rec.seq_stats["state"].as_dict() == {"received": len(seqs), "lost": 3, "restarts": 0, "reordered": 0}
    assert rec.counters.get("bad_stamp.state") == 1 and rec.counters.get("errors") == 0
    assert file_metadata(files[-1])["state"]["lost"] == 3
    # every file stands alone in Foxglove: its own schemas for what it holds (the first
    # file may hold only the recorder's status when it rotated before the first sample)
    with open(next(f for f in files if any(_valid_messages(f))), "rb") as f:
        summary = make_reader(f).get_summary()
    schema = next(s for s in summary.schemas.values() if s.name == "StateEstimate")
    assert schema.encoding == "jsonschema" and "position" in json.dumps(json.loads(schema.data))
    # the raw topics as JSON, the scene made from them with Foxglove's protobuf schemas (tests/test_view.py)
    assert {c.message_encoding for c in summary.channels.values()} == {"json", "protobuf"}
    statuses = [r for r in read_recording([tmp_path]) if r.schema == "ServiceStatus"]
    assert statuses and m.decode(statuses[0].data, m.ServiceStatus).service == "recorder"


def _start_recorder(tmp_path: Path, endpoint: str, **overrides) -> subprocess.Popen:
    config = tmp_path / "archer.toml"
    lines = [f'directory = "{tmp_path / "rec"}"'] + [f"{k} = {v}" for k, v in overrides.items()]
    config.write_text("[recorder]\n" + "\n".join(lines) + "\n")
    proc = subprocess.Popen(
        [sys.executable, "-m", "services.cli.main", "run", "recorder", "--endpoint", endpoint, "--namespace", NS, "--config", str(config)],
        stderr=subprocess.DEVNULL,
    )
    client = open_session(endpoint, "peer")
    try:
        deadline = time.monotonic() + START_TIMEOUT_S
        while "recorder" not in live_services(client, NS):
            assert proc.poll() is None, "recorder exited"
            assert time.monotonic() < deadline, "recorder never came up"
            time.sleep(0.1)
    finally:
        client.close()
    time.sleep(0.3)
    return proc


def test_sigterm_finishes_the_current_file(tmp_path, zenoh_router):
    proc = _start_recorder(tmp_path, zenoh_router, chunk_s=600.0)
    session = open_session(zenoh_router, "peer")
    try:
        _publish(session, list(range(1, 201)), 0.002)
        time.sleep(0.5)
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(timeout=10) == 0
    finally:
        if proc.poll() is None:
            proc.kill()
        session.close()
    rec = tmp_path / "rec"
    files = list(rec.glob("*.mcap"))
    assert len(files) == 1 and not list(rec.glob(f"*{PART_SUFFIX}"))
    assert [s for s in _valid_messages(files[0]) if s] == list(range(1, 201))


def test_kill_9_leaves_every_finished_file_valid_and_the_last_salvageable(tmp_path, zenoh_router):
    proc = _start_recorder(tmp_path, zenoh_router, chunk_s=0.5, flush_s=0.1)
    session = open_session(zenoh_router, "peer")
    published = list(range(1, 601))
    try:
        _publish(session, published, 0.004)  # ~2.4 s: several rotations
        time.sleep(0.3)  # past a flush
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait(timeout=5)
    finally:
        if proc.poll() is None:
            proc.kill()
        session.close()
    rec = tmp_path / "rec"
    finished = sorted(rec.glob("*.mcap"))
    partial = list(rec.glob(f"*{PART_SUFFIX}"))
    assert len(finished) >= 3 and len(partial) <= 1
    in_finished = [s for f in finished for s in _valid_messages(f) if s]
    assert in_finished == published[: len(in_finished)]  # contiguous from the start
    salvaged = [int(json.loads(r.data)["seq"]) for r in read_recording(partial) if r.schema == "StateEstimate"]
    assert in_finished + salvaged == published  # the torn file's flushed chunks hold the rest


def test_an_unfinished_file_yields_what_was_flushed(tmp_path):
    from services.recorder import RotatingMcap, schema_for

    files = RotatingMcap(tmp_path, RecorderParams(chunk_s=600.0, flush_s=0.0))
    key, schema = TOPICS["state"].key(NS), schema_for(TOPICS["state"])
    for seq in range(1, 51):
        files.write(key, schema, seq, seq, seq, _state(seq))
    files.tick(dict)  # flush_s = 0: the chunk closes and reaches the file
    for seq in range(51, 61):
        files.write(key, schema, seq, seq, seq, _state(seq))  # still in memory at the "crash"
    torn = tmp_path / "torn.mcap.part"
    torn.write_bytes(files.current.read_bytes()[:-3])  # torn mid-record, as a crash leaves it
    salvaged = [json.loads(r.data)["seq"] for r in read_recording([torn])]
    assert salvaged == list(range(1, 51))
    files.finish({})
    assert [json.loads(r.data)["seq"] for r in read_recording(files.finished)] == list(range(1, 61))


def test_status_before_setup_answers():
    """The status queryable exists before setup(): an early `archer status` must get a reply."""
    status = RecorderService(ns=NS).status()
    assert status.state == "starting" and status.extra == {}


# real time: loops at their rate, processes and Zenoh over loopback share two loaded cores
pytestmark = pytest.mark.timing_sensitive(reason="real-time loops, processes or Zenoh over loopback on a shared host")
