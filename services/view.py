"""The live viewer bridge: the stack's topics to a Foxglove WebSocket server (``archer view``).

Subscribes: any topic of the topic table, while a client watches a channel it feeds (a
topic nobody watches costs nothing), each through a Zenoh ring buffer drained by the
bridge's own sender thread (no Python callback per sample: a 1 kHz topic costs this
process little between two sends, and a service publishing it never waits on us).
Fast topics (nominal rate above ``view.max_rate_hz``) keep only their latest sample;
slow and event topics keep up to ``view.event_queue`` samples; what overflows is dropped.

Computes and publishes, at most ``view.max_rate_hz`` per channel, on a Foxglove
WebSocket server (``foxglove-sdk``) at ``view.host:view.port``:

- ``/tf`` (``foxglove.FrameTransform``): world -> body from ``state`` (the torso frame:
  the estimate's CoM less the CoM's offset in the body, which moves with the foot), and
  world -> depth_camera from ``depth``;
- ``<ns>/view/robot`` (``foxglove.SceneUpdate``): the robot drawn from its MJCF geoms
  (:func:`robot_description.params.body_shapes`), the foot at its compression;
- ``<ns>/view/plan``: the ``reference`` Bezier curve sampled as a line, the ``waypoints``
  and the outlines of their convex sets;
- ``<ns>/view/world``: the ``polytopes`` as extruded polygons (obstacles as prisms,
  free cells as thin slabs); ``<ns>/view/grid`` (``foxglove.Grid``) the occupancy grid;
  ``<ns>/view/depth`` (``foxglove.RawImage``, 32FC1) the depth image;
- every JSON topic on a channel named by its Zenoh key, with its JSON schema (the
  flight recorder's), so any field can be plotted.

Foxglove's timestamps are wall-clock epoch times; the stack's stamps are monotonic, so
each is shifted by the wall - monotonic offset taken when the service starts.
"""

from __future__ import annotations

import asyncio
import threading
import time
from typing import Any

import foxglove
import foxglove.channels as fc
import zenoh

from onboard.contracts import messages as m
from onboard.contracts.params import ViewParams
from onboard.contracts.topics import TOPICS, Topic
from services.recorder import schema_for
from services.runtime.service import EVERY_TOPIC, PolledInput, Service
from services.scene import SceneMaker, channel_name

SENDER_JOIN_S = 2.0
# the scene channels each source topic feeds (services.scene.SceneMaker)
_FEEDS = {"state": ("tf", "robot"), "reference": ("plan",), "waypoints": ("plan",), "polytopes": ("world",),
          "grid": ("grid",), "depth": ("depth", "tf")}

_CHANNEL_TYPES = {"tf": fc.FrameTransformChannel, "robot": fc.SceneUpdateChannel, "plan": fc.SceneUpdateChannel,
                  "world": fc.SceneUpdateChannel, "grid": fc.GridChannel, "depth": fc.RawImageChannel}


class FoxgloveBridge:
    """A Foxglove WebSocket server and its channels; :meth:`send` shows one stack message on them.

    Not thread-safe: one thread sends. The ``view`` service feeds it from Zenoh; ``archer sim
    --view`` in lockstep feeds it straight from the runner.
    """

    def __init__(self, ns: str, params: ViewParams) -> None:
        self.params = params
        self.maker = SceneMaker(params)
        self._context = foxglove.Context()  # channels of this server only (a test may run two)
        try:
            self.server = foxglove.start_server(name=f"archer {ns}", host=params.host, port=params.port,
                                                context=self._context, message_backlog_size=params.message_backlog)
        except Exception as exc:  # the SDK's own error type; say which address, and why
            raise RuntimeError(f"view: cannot serve on {params.host}:{params.port} ({exc}); set view.port") from exc
        self.port = self.server.port
        ctx = self._context
        self._scene = {which: cls(channel_name(ns, which), context=ctx) for which, cls in _CHANNEL_TYPES.items()}
        self._json: dict[str, foxglove.Channel] = {}
        for topic in TOPICS.values():
            if not topic.binary:
                name, encoding, data, message_encoding = schema_for(topic)
                self._json[topic.name] = foxglove.Channel(
                    topic.key(ns), schema=foxglove.Schema(name=name, encoding=encoding, data=data),
                    message_encoding=message_encoding, context=ctx)

    def send(self, topic: Topic, msg: Any, epoch: int) -> None:
        """Convert and log ``msg`` (stamped ``epoch`` [ns since 1970]) on every channel it feeds that a
        client subscribes to (the rest costs nothing)."""
        scene = self._scene
        for which, out in self.maker.messages(topic.name, msg, epoch, lambda w: scene[w].has_sinks()):
            scene[which].log(out, log_time=epoch)
        channel = self._json.get(topic.name)
        if channel is not None and channel.has_sinks():
            channel.log(m.encode(msg), log_time=epoch)

    def wanted(self, topic: str) -> bool:
        """Whether a client subscribes to a channel that ``topic`` feeds (its JSON channel or a scene channel)."""
        channel = self._json.get(topic)
        if channel is not None and channel.has_sinks():
            return True
        return any(self._scene[which].has_sinks() for which in _FEEDS.get(topic, ()))

    def watched(self) -> bool:
        """A client subscribes to the robot's transform or body."""
        return self._scene["tf"].has_sinks() or self._scene["robot"].has_sinks()

    def stop(self) -> None:
        self.server.stop()


class ViewService(Service):
    name = "view"
    zenoh_mode = "client"  # a person's tool: it waits for the stack and never serves its endpoint
    params_sections = ("view",)
    subscribes = EVERY_TOPIC  # it shows every topic (scene channels from some, JSON from all)

    async def setup(self) -> None:
        params: ViewParams = self.params["view"]
        self._epoch_offset_ns = time.time_ns() - time.monotonic_ns()  # stamps are monotonic, Foxglove's epoch
        self.bridge = FoxgloveBridge(self.ns, params)
        self.port = self.bridge.port
        # topic -> its subscription while a client watches a channel it feeds (None while nobody does: a
        # 1 kHz topic nobody watches then costs this process nothing, not even Zenoh's work per sample)
        self._inputs: dict[str, tuple[Topic, PolledInput | None]] = {t.name: (t, None) for t in TOPICS.values()}
        self._ticks = 0
        self._last_ticks = -1
        self._stop_sender = threading.Event()
        self._sender = threading.Thread(target=self._send_loop, name="view-sender", daemon=True)
        self._sender.start()
        self.log.info("foxglove server", extra={"fields": {"url": f"ws://{params.host}:{self.port}"}})

    def _send_loop(self) -> None:
        """Every 1 / max_rate_hz: drain each input and send what it holds (absolute deadlines)."""
        period = 1.0 / self.params["view"].max_rate_hz
        deadline = time.monotonic()
        batch: list[Any] = []
        try:
            while not self._stop_sender.is_set():
                self._follow_clients()
                for topic, inp in self._inputs.values():
                    if inp is None:
                        continue
                    batch.clear()
                    taken = inp.drain(batch)
                    if taken >= inp.capacity > 1:
                        self.count(f"dropped.{topic.name}")  # the ring was full: older ones were lost
                    for msg in batch:
                        self._send(topic, msg)
                    if batch:
                        self.count(f"taken.{topic.name}", len(batch))  # taken from Zenoh; sent where subscribed
                self._ticks += 1
                deadline += period
                delay = deadline - time.monotonic()
                if delay < 0:  # fell behind (a big scene): start afresh rather than burst
                    deadline = time.monotonic()
                    self.count("late_ticks")
                self._stop_sender.wait(max(0.0, delay))
        except Exception as exc:  # noqa: BLE001 - recorded; progress() then stops the watchdog pings
            self.fail(f"sender: {exc!r}")
            self.log.exception("view sender failed")

    def _follow_clients(self) -> None:
        """Subscribe to a topic while a client watches what it feeds; unsubscribe when nobody does."""
        max_rate, queue = self.params["view"].max_rate_hz, self.params["view"].event_queue
        for name, (topic, inp) in self._inputs.items():
            wanted = self.bridge.wanted(name)
            if wanted and inp is None:
                self._reads(name)  # the service table's rule
                # a ring of one keeps the latest of a fast topic; slow and event topics keep what arrived
                capacity = 1 if topic.rate_hz > max_rate else queue
                sub = self.session.declare_subscriber(topic.key(self.ns), zenoh.handlers.RingChannel(capacity))
                self._inputs[name] = (topic, PolledInput(sub, capacity, self._decoder(topic),
                                                         lambda exc, t=topic: self._reject(t, exc), self.rate(f"rx.{name}")))
            elif not wanted and inp is not None:
                inp.close()
                self._inputs[name] = (topic, None)

    def _send(self, topic: Topic, msg: Any) -> None:
        stamp = getattr(msg, "stamp_ns", 0)
        self.bridge.send(topic, msg, stamp + self._epoch_offset_ns if stamp > 0 else time.time_ns())

    def status_extra(self) -> dict[str, float]:
        if not hasattr(self, "bridge"):
            return {}
        return {"port": self.port, "ticks": self._ticks}

    def progress(self) -> bool:
        """The sender thread lives and ticked since the last call."""
        ticks = self._ticks
        advanced, self._last_ticks = ticks != self._last_ticks, ticks
        return self._sender.is_alive() and advanced

    async def main(self) -> None:
        while not self.stopping.is_set():
            try:
                await asyncio.wait_for(self.stopping.wait(), 1.0)
            except asyncio.TimeoutError:
                pass
            if not self._sender.is_alive():  # exit with an error: the supervisor restarts us
                raise RuntimeError(f"the view's sender thread died: {self.last_error}")

    async def teardown(self) -> None:
        if hasattr(self, "_sender"):
            self._stop_sender.set()
            self._sender.join(SENDER_JOIN_S)
            for _, inp in self._inputs.values():
                if inp is not None:
                    inp.close()
        if hasattr(self, "bridge"):
            self.bridge.stop()
