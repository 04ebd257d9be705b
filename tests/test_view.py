"""`archer view`: the live Foxglove bridge, checked with an independent WebSocket client.

The client is the `websockets` package speaking Foxglove's WebSocket protocol
(`foxglove.sdk.v1`); the messages are decoded with `protobuf` from the descriptors the
server advertises, so nothing of the SDK decodes what the SDK encoded.
"""

from __future__ import annotations

import asyncio
import base64
import json
import math
import socket
import struct
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field

import pytest
import websockets
import zenoh
from google.protobuf import descriptor_pb2, descriptor_pool, message_factory

from onboard.contracts import messages as m
from onboard.contracts.params import ViewParams
from onboard.contracts.topics import TOPICS, namespace
from robot_description.params import body_shapes
from services.runtime.peers import live_services
from services.runtime.zenoh_session import open_session
from helpers import with_running_service
from services.scene import BODY_FRAME, TF_CHANNEL, WORLD_FRAME, RobotDrawing, SceneMaker, scene_channel

NS = "archer/viewtest"
SUBPROTOCOL = "foxglove.sdk.v1"
START_TIMEOUT_S = 30.0
MAX_RATE_HZ = 30.0
PUBLISH_S = 3.0
ARRIVAL_JITTER_S = 0.5  # [s] a loaded 2-core machine may delay the last state this much more than the first
STATE_HZ = 1000.0
QUAT = (math.cos(0.2), math.sin(0.2) * 0.6, 0.0, math.sin(0.2) * 0.8)  # a tilt and a yaw, unit
FOOT_POS = 0.03  # [m] compression of every published state
STEP_X = 1e-4  # [m] published state k has its CoM at x = k * STEP_X: a transform names its state
OP_MESSAGE_DATA = 0x01  # Foxglove WebSocket binary opcode


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def state(k: int) -> m.StateEstimate:
    return m.StateEstimate(
        stamp_ns=time.monotonic_ns(), seq=k, position=[k * STEP_X, 0.2, 0.5], velocity=[0.0, 0.0, 0.0], quat=list(QUAT),
        omega=[0.0, 0.0, 0.0], wheel_vel=[0.0, 0.0, 0.0], foot_pos=FOOT_POS, foot_vel=0.0, contact=False, phase="flight",
        pos_vel_cov=[0.0] * 36, att_cov=[0.0, 0.0, 0.0])


def start_view(endpoint: str, port: int, *extra: str) -> subprocess.Popen:
    """``archer view`` as its own process, once its liveliness token is up."""
    proc = subprocess.Popen([sys.executable, "-m", "services.cli.main", "view", "--endpoint", endpoint, "--namespace", NS,
                             "--port", str(port), "--log-level", "WARNING", *extra], stderr=subprocess.PIPE)
    client = open_session(endpoint, "peer")
    try:
        deadline = time.monotonic() + START_TIMEOUT_S
        while "view" not in live_services(client, NS):
            if proc.poll() is not None:
                raise AssertionError(f"archer view exited {proc.returncode}: {proc.stderr.read().decode()}")
            assert time.monotonic() < deadline, "archer view never came up"
            time.sleep(0.1)
    except BaseException:
        stop(proc)
        raise
    finally:
        client.close()
    return proc


def stop(proc: subprocess.Popen) -> int:
    if proc.poll() is None:
        proc.terminate()
    try:
        proc.wait(10)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait(5)
    return proc.returncode


class Decoders:
    """Protobuf classes built from the FileDescriptorSets the server advertises."""

    def __init__(self) -> None:
        self.pool = descriptor_pool.DescriptorPool()
        self.files: set[str] = set()
        self.classes: dict[str, type] = {}

    def add(self, schema_name: str, schema_b64: str) -> type:
        if schema_name not in self.classes:
            fds = descriptor_pb2.FileDescriptorSet.FromString(base64.b64decode(schema_b64))
            for f in fds.file:
                if f.name not in self.files:  # schemas share dependencies (Vector3, Time, ...)
                    self.pool.Add(f)
                    self.files.add(f.name)
            self.classes[schema_name] = message_factory.GetMessageClass(self.pool.FindMessageTypeByName(schema_name))
        return self.classes[schema_name]


@dataclass
class Received:
    channels: dict[str, dict] = field(default_factory=dict)  # topic -> advertised channel
    messages: dict[str, list] = field(default_factory=dict)  # topic -> [(receive time, log time [ns], decoded)]


async def connect(port: int, timeout_s: float = START_TIMEOUT_S):
    """A client connection once the server listens (it starts with its service)."""
    deadline = time.monotonic() + timeout_s
    while True:
        try:
            return await websockets.connect(f"ws://127.0.0.1:{port}", subprotocols=[SUBPROTOCOL], max_size=None)
        except OSError:
            if time.monotonic() > deadline:
                raise
            await asyncio.sleep(0.2)


async def watch(port: int, topics: list[str], duration_s: float, ready: threading.Event, received: Received) -> None:
    """Connect, subscribe to ``topics`` once advertised, and decode what arrives for ``duration_s``."""
    decoders = Decoders()
    async with await connect(port) as ws:
        assert ws.subprotocol == SUBPROTOCOL
        subs: dict[int, str] = {}
        end = None
        while end is None or time.monotonic() < end:
            try:
                frame = await asyncio.wait_for(ws.recv(), 0.2)
            except asyncio.TimeoutError:
                continue
            except websockets.ConnectionClosed:
                return  # the server is gone (the run it showed ended)
            if isinstance(frame, str):
                msg = json.loads(frame)
                if msg.get("op") == "advertise":
                    for ch in msg["channels"]:
                        received.channels[ch["topic"]] = ch
                    wanted = [received.channels[t] for t in topics if t in received.channels]
                    if end is None and len(wanted) == len(topics):
                        for i, ch in enumerate(wanted, start=1):
                            subs[i] = ch["topic"]
                        await ws.send(json.dumps({"op": "subscribe", "subscriptions": [
                            {"id": i, "channelId": ch["id"]} for i, ch in enumerate(wanted, start=1)]}))
                        end = time.monotonic() + duration_s
                        await asyncio.sleep(0.3)  # the subscription is in place before the publisher starts
                        ready.set()
                continue
            opcode, sub_id, log_ns = struct.unpack_from("<BIQ", frame, 0)
            if opcode != OP_MESSAGE_DATA or sub_id not in subs:
                continue
            topic = subs[sub_id]
            ch = received.channels[topic]
            payload = frame[13:]
            if ch["encoding"] == "protobuf":
                decoded = decoders.add(ch["schemaName"], ch["schema"]).FromString(payload)
            else:
                decoded = json.loads(payload)
            received.messages.setdefault(topic, []).append((time.monotonic(), log_ns, decoded))


def publish_states(endpoint: str, ready: threading.Event, published: list[int], published_ns: list[int],
                   polytopes: m.PolytopeSet) -> None:
    session = open_session(endpoint, "peer")
    try:
        pub = session.declare_publisher(TOPICS["state"].key(NS), express=True)
        world = session.declare_publisher(TOPICS["polytopes"].key(NS), reliability=zenoh.Reliability.RELIABLE)
        assert ready.wait(START_TIMEOUT_S), "the client never subscribed"
        t0 = time.monotonic()
        k = 0
        while time.monotonic() - t0 < PUBLISH_S:  # absolute deadlines: 1 kHz on average
            k += 1
            if k % 100 == 1:  # at 10 Hz, as perception does (the view subscribes once a client watches)
                world.put(m.encode(polytopes))
            pub.put(m.encode(state(k)))
            published.append(k)
            published_ns.append(time.monotonic_ns())
            delay = t0 + k / STATE_HZ - time.monotonic()
            if delay > 0:
                time.sleep(delay)
    finally:
        session.close()


def test_a_websocket_client_sees_the_published_state_as_transform_and_scene_within_the_rate_cap(zenoh_router):
    port = free_port()
    proc = start_view(zenoh_router, port)
    tf_topic, robot_topic, world_topic = TF_CHANNEL, scene_channel(NS, "robot"), scene_channel(NS, "world")
    state_topic = TOPICS["state"].key(NS)
    received = Received()
    published: list[int] = []
    published_ns: list[int] = []  # when each was put
    ready = threading.Event()
    obstacles = m.PolytopeSet(mode="obstacles", polytopes=[
        m.Polytope(A=[[1.0, 0.0], [-1.0, 0.0], [0.0, 1.0], [0.0, -1.0]], b=[1.5, -1.0, 0.5, 0.5],
                   vertices=[[1.0, -0.5], [1.5, 0.5], [1.5, -0.5], [1.0, 0.5]])])  # unordered on purpose
    publisher = threading.Thread(target=publish_states, args=(zenoh_router, ready, published, published_ns, obstacles), daemon=True)
    try:
        publisher.start()
        asyncio.run(asyncio.wait_for(
            watch(port, [tf_topic, robot_topic, world_topic, state_topic], PUBLISH_S + 0.5, ready, received), 60))
        publisher.join(10)
        assert stop(proc) == 0
    finally:
        stop(proc)
        ready.set()
        publisher.join(10)

    assert received.channels[tf_topic]["schemaName"] == "foxglove.FrameTransform"
    assert received.channels[robot_topic]["schemaName"] == "foxglove.SceneUpdate"
    assert received.channels[state_topic]["schemaEncoding"] == "jsonschema"
    assert "foot_pos" in received.channels[state_topic]["schema"]
    assert len(published) > 0.8 * STATE_HZ * PUBLISH_S

    # each transform is the torso frame of one published state: CoM less its offset, quat as sent
    drawing = RobotDrawing("indoor")
    origin0 = drawing.body_origin(state(0))
    tfs = [msg for _, _, msg in received.messages[tf_topic]]
    assert len(tfs) > 10
    seen = set()
    published_set = set(published)
    for tf in tfs:
        assert (tf.parent_frame_id, tf.child_frame_id) == (WORLD_FRAME, BODY_FRAME)
        k = round((tf.translation.x - origin0[0]) / STEP_X)
        assert k in published_set
        expected = drawing.body_origin(state(k))
        assert (tf.translation.x, tf.translation.y, tf.translation.z) == pytest.approx(expected, abs=1e-9)
        assert (tf.rotation.w, tf.rotation.x, tf.rotation.y, tf.rotation.z) == pytest.approx(QUAT, abs=1e-12)
        seen.add(k)
    assert len(seen) == len(tfs)  # never the same state twice: only new estimates are sent

    # the cap: at most one transform a tick of MAX_RATE_HZ while state arrives at 1 kHz. Counted over
    # the span the states were published in, widened by how much later the last one may reach the
    # view than the first: the transforms' stamps (the states') and the client's receive times both
    # bunch when this test process is busy. Uncapped, it would be ~STATE_HZ * span_s
    span_s = (published_ns[-1] - published_ns[0]) * 1e-9
    assert len(tfs) <= MAX_RATE_HZ * (span_s + ARRIVAL_JITTER_S) + 1, (len(tfs), span_s)
    assert len(tfs) >= 5.0 * span_s, (len(tfs), span_s)

    # the body: frame-locked to the torso frame, the foot sphere raised by the compression
    update = received.messages[robot_topic][-1][2]
    entity = update.entities[0]
    assert entity.frame_id == BODY_FRAME and entity.frame_locked and entity.id == "robot"
    foot = next(s for s in body_shapes("indoor").shapes if s.name == "foot")
    foot_spheres = [s for s in entity.spheres if s.size.x == pytest.approx(2 * foot.size[0])]
    assert len(foot_spheres) == 1 and foot_spheres[0].pose.position.z == pytest.approx(foot.pos[2] + FOOT_POS)
    assert len(entity.cylinders) >= 4  # housing, three wheels (and the spool)

    # the obstacle: one prism 0.5 m tall over the 0.5 x 1 m rectangle
    world = received.messages[world_topic][-1][2]
    prism = world.entities[0].triangles[0]
    xs, ys, zs = ([getattr(p, a) for p in prism.points] for a in "xyz")
    assert (min(xs), max(xs), min(ys), max(ys), min(zs), max(zs)) == pytest.approx((1.0, 1.5, -0.5, 0.5, 0.0, 0.5))
    assert len(prism.points) == 3 * (2 * 2 + 2 * 4)  # two fans of 2 triangles, 4 walls of 2

    # the JSON channel: the estimate itself, any field plottable
    last_json = received.messages[state_topic][-1][2]
    assert last_json["foot_pos"] == FOOT_POS and last_json["quat"] == pytest.approx(list(QUAT))


def test_archer_view_started_before_the_stack_waits_as_a_client_and_never_takes_its_endpoint():
    """A person starts the viewer first: it waits (saying so) without serving the stack's endpoint,
    so the stack still starts on it, and the viewer joins it when it comes."""
    from services.runtime.zenoh_session import endpoint_in_use, free_endpoint

    endpoint, port = free_endpoint(), free_port()
    proc = subprocess.Popen([sys.executable, "-m", "services.cli.main", "view", "--endpoint", endpoint, "--namespace", NS,
                             "--port", str(port), "--log-level", "WARNING"], stderr=subprocess.PIPE, text=True)
    router = None
    try:
        waiting = proc.stderr.readline()  # the one line it says while it waits
        assert "waiting for the stack at " + endpoint in waiting, waiting
        time.sleep(1.0)
        assert proc.poll() is None and not endpoint_in_use(endpoint)
        router = open_session(endpoint, "router")  # the stack comes up on its endpoint
        deadline = time.monotonic() + START_TIMEOUT_S
        while "view" not in live_services(router, NS):
            assert proc.poll() is None, proc.stderr.read()
            assert time.monotonic() < deadline, "the viewer never joined the stack"
            time.sleep(0.1)
    finally:
        assert stop(proc) == 0
        if router is not None:
            router.close()


def test_archer_view_refuses_a_bad_port_by_name():
    out = subprocess.run([sys.executable, "-m", "services.cli.main", "view", "--port", "70000"], capture_output=True, text=True,
                         timeout=60)
    assert out.returncode == 2 and "view.port" in out.stderr


def test_archer_sim_view_shows_the_twin_hopping():
    """`archer sim --mode realtime --view`: the bridge runs as a supervised unit beside the twin; its
    transforms are the estimates it bridges (paired by log time) and the robot is seen hopping upright."""
    from services.runtime.zenoh_session import free_endpoint

    port, endpoint, duration = free_port(), free_endpoint(), 8.0
    proc = subprocess.Popen([sys.executable, "-m", "services.cli.main", "sim", "--mode", "realtime", "--scenario", "hop-in-place",
                             "--duration", str(duration), "--services", "estimator,control", "--view", "--view-port", str(port),
                             "--endpoint", endpoint, "--namespace", NS, "--json", "--quiet"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    tf_topic, state_topic = TF_CHANNEL, TOPICS["state"].key(NS)
    received = Received()
    try:
        asyncio.run(asyncio.wait_for(watch(port, [tf_topic, state_topic], duration, threading.Event(), received), 120))
        out, err = proc.communicate(timeout=120)
    finally:
        stop(proc)
    assert proc.returncode == 0, err
    metrics = json.loads(out.strip().splitlines()[-1])
    assert "view" in metrics["services_started"] and metrics["falls"] == 0, metrics
    assert metrics["service_restarts"]["view"] == 0

    drawing = RobotDrawing("indoor")
    estimates = {log_ns: msg for _, log_ns, msg in received.messages[state_topic]}
    pairs = [(tf, estimates[log_ns]) for _, log_ns, tf in received.messages[tf_topic]
             if tf.child_frame_id == BODY_FRAME and log_ns in estimates]
    assert len(pairs) > 30  # seconds of the run at up to 30 Hz
    heights = []
    for tf, est in pairs:
        s = m.decode(json.dumps(est).encode(), m.StateEstimate)
        assert (tf.translation.x, tf.translation.y, tf.translation.z) == pytest.approx(drawing.body_origin(s), abs=1e-9)
        assert (tf.rotation.w, tf.rotation.x, tf.rotation.y, tf.rotation.z) == pytest.approx(s.quat, abs=1e-12)
        assert 2 * (tf.rotation.w ** 2 + tf.rotation.z ** 2) - 1 > math.cos(math.radians(20))  # upright within 20 deg
        heights.append(tf.translation.z)
    assert 0.2 < min(heights) and max(heights) - min(heights) > 0.02  # on its foot, and hopping


def test_archer_sim_view_in_lockstep_is_paced_and_shows_the_run():
    """Lockstep with --view: it waits for a viewer, then runs at wall-clock pace, thinned to the cap."""
    port, duration = free_port(), 3.0
    proc = subprocess.Popen([sys.executable, "-m", "services.cli.main", "sim", "--scenario", "hop-in-place", "--duration", str(duration),
                             "--view", "--view-port", str(port), "--namespace", NS, "--json", "--quiet"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    received = Received()
    try:
        asyncio.run(asyncio.wait_for(watch(port, [TF_CHANNEL, scene_channel(NS, "robot")], duration + 1.0, threading.Event(),
                                           received), 120))
        out, err = proc.communicate(timeout=120)
    finally:
        stop(proc)
    assert proc.returncode == 0, err
    metrics = json.loads(out.strip().splitlines()[-1])
    assert metrics["falls"] == 0 and metrics["realtime_factor"] <= 1.05  # paced for watching
    tfs = [(log_ns, tf) for _, log_ns, tf in received.messages[TF_CHANNEL] if tf.child_frame_id == BODY_FRAME]
    rate = (len(tfs) - 1) / ((tfs[-1][0] - tfs[0][0]) * 1e-9)
    assert 10.0 < rate <= 1.1 * MAX_RATE_HZ, rate
    heights = [tf.translation.z for _, tf in tfs]  # an estimate before the first pose is not valid and not drawn
    assert 0.2 < min(heights) and max(heights) - min(heights) > 0.02
    assert received.messages[scene_channel(NS, "robot")]


def _scene_and_states(paths) -> tuple[dict[str, str], list[tuple[int, object]], dict[int, m.StateEstimate], list]:
    """From recordings: channel -> schema name, body transforms (publish time, decoded), raw states by
    publish time, and the robot's scene updates; decoded with protobuf from the files' own schemas."""
    from mcap.reader import make_reader

    decoders = Decoders()
    schemas: dict[str, str] = {}
    tfs, states, robots = [], {}, []
    for path in paths:
        with open(path, "rb") as f:
            for schema, channel, message in make_reader(f).iter_messages():
                schemas[channel.topic] = schema.name if schema else ""
                if channel.message_encoding == "protobuf":
                    decoded = decoders.add(schema.name, base64.b64encode(schema.data).decode()).FromString(message.data)
                    if channel.topic == TF_CHANNEL and decoded.child_frame_id == BODY_FRAME:
                        tfs.append((message.publish_time, decoded))
                    elif channel.topic.endswith("/view/robot"):
                        robots.append(decoded)
                elif channel.topic.endswith(TOPICS["state"].suffix):
                    states[message.publish_time] = m.decode(message.data, m.StateEstimate)
    return schemas, tfs, states, robots


def _check_transforms(tfs, states) -> None:
    drawing = RobotDrawing("indoor")
    assert tfs
    for publish_ns, tf in tfs:
        if publish_ns == 0:
            continue  # an estimate before any sensor data has no stamp of its own to pair by
        s = states[publish_ns]  # the state it was made from, by its stamp
        assert (tf.translation.x, tf.translation.y, tf.translation.z) == pytest.approx(drawing.body_origin(s), abs=1e-9)
        assert (tf.rotation.w, tf.rotation.x, tf.rotation.y, tf.rotation.z) == pytest.approx(s.quat, abs=1e-12)


def test_the_recorder_writes_the_scene_with_foxglove_schemas_beside_the_raw_topics(tmp_path, zenoh_router):
    from onboard.contracts.params import RecorderParams
    from services.recorder import RecorderService

    params = RecorderParams(directory=str(tmp_path), chunk_s=600.0, flush_s=0.1, status_period_s=60.0)
    n, period_s = 600, 0.002  # 1.2 s of estimates at 500 Hz

    async def scenario() -> RecorderService:
        rec = RecorderService(ns=NS, endpoint=zenoh_router, params={"recorder": params, "view": ViewParams()})

        async def publish_states(session: zenoh.Session) -> None:
            def publish() -> None:
                pub = session.declare_publisher(TOPICS["state"].key(NS), reliability=zenoh.Reliability.RELIABLE,
                                                congestion_control=zenoh.CongestionControl.BLOCK)
                time.sleep(0.3)
                for k in range(1, n + 1):
                    pub.put(m.encode(state(k)))
                    time.sleep(period_s)

            await asyncio.to_thread(publish)
            await asyncio.sleep(0.3)

        await with_running_service(rec, zenoh_router, publish_states)
        return rec


    asyncio.run(asyncio.wait_for(scenario(), 60))
    schemas, tfs, states, robots = _scene_and_states(sorted(tmp_path.glob("*.mcap")))
    assert schemas[TF_CHANNEL] == "foxglove.FrameTransform" and schemas[scene_channel(NS, "robot")] == "foxglove.SceneUpdate"
    assert len(states) == n  # every raw estimate kept ...
    span_s = (max(states) - min(states)) / 1e9
    assert 0.5 * MAX_RATE_HZ * span_s < len(tfs) <= MAX_RATE_HZ * span_s + 2  # ... the scene thinned to the cap
    _check_transforms(tfs, states)
    assert robots and robots[-1].entities[0].frame_id == BODY_FRAME


def test_a_lockstep_recording_carries_the_scene(tmp_path):
    from services.cli.main import main

    rec = tmp_path / "run.mcap"
    assert main(["sim", "--scenario", "hop-in-place", "--duration", "1.0", "--record", str(rec), "--quiet"]) == 0
    schemas, tfs, states, robots = _scene_and_states([rec])
    assert schemas[TF_CHANNEL] == "foxglove.FrameTransform"
    assert schemas[scene_channel(namespace(), "world")] == "foxglove.SceneUpdate"
    assert 25 <= len(tfs) <= 31  # 1 s of sim time at 30 Hz
    _check_transforms(tfs, states)
    assert len(robots) == len(tfs)


def test_the_shipped_foxglove_layout_is_the_generated_one():
    """deploy/foxglove/archer-layout.json: made by services.scene.layout for the default robot; it shows every scene channel."""
    from pathlib import Path

    from onboard.contracts.topics import DEFAULT_ROBOT
    from services.scene import SCENE_CHANNELS, channel_name, layout

    ns = namespace(DEFAULT_ROBOT)
    shipped = Path(__file__).resolve().parent.parent / "deploy" / "foxglove" / "archer-layout.json"
    assert json.loads(shipped.read_text()) == json.loads(layout(ns))
    text = shipped.read_text()
    assert all(channel_name(ns, w) in text for w in SCENE_CHANNELS if w != "tf")  # the transforms need no entry


def test_an_estimate_that_is_not_valid_is_not_drawn():
    """Before the first pose (or after losing it) the estimate's position means nothing: no transform
    or body is made from it, so a viewer keeps the last valid pose instead of a robot on the floor."""
    maker = SceneMaker(ViewParams())
    valid = state(1)
    assert [which for which, _ in maker.messages("state", valid, 1)] == ["tf", "robot"]
    invalid = state(1)
    invalid.valid = False
    assert list(maker.messages("state", invalid, 1)) == []


# real time: loops at their rate, processes and Zenoh over loopback share two loaded cores
pytestmark = pytest.mark.timing_sensitive(reason="real-time loops, processes or Zenoh over loopback on a shared host")
