"""OptiTrack NatNet 3.1 over UDP unicast: the packets a Motive server sends, and a server.

Written from NaturalPoint's public description of the NatNet packet format. Every
packet is ``message id (u16) | payload size (u16) | payload``, little-endian. A client
sends NAT_CONNECT to the server's command port and gets NAT_SERVERINFO back (name,
versions, the high-resolution clock's frequency, the data port, unicast or multicast);
NAT_REQUEST_MODELDEF returns NAT_MODELDEF (rigid body names and ids); frames of data
(NAT_FRAMEOFDATA) then stream to the client.

This server streams by unicast only, never to a multicast group, to two places per
client: the address the client's NAT_CONNECT / NAT_KEEPALIVE came from (where Motive
sends unicast data; the NatNet SDK's clients read it on their command socket) and the
advertised data port on the client's host (where libmotioncapture's optitrack backend
listens in unicast mode). Nothing listening on one of them costs one dropped datagram.

Frame timestamps are in ticks of the server's high-resolution clock; this server's
clock is the host's monotonic clock in nanoseconds (``CLOCK_HZ``), so a client on the
same host can compare the exposure time with its own ``time.monotonic_ns()``.
"""

from __future__ import annotations

import socket
import struct
import threading
from collections import Counter
from dataclasses import dataclass

from drivers.udp import free_udp_port

NAT_CONNECT = 0
NAT_SERVERINFO = 1
NAT_REQUEST = 2
NAT_RESPONSE = 3
NAT_REQUEST_MODELDEF = 4
NAT_MODELDEF = 5
NAT_REQUEST_FRAMEOFDATA = 6
NAT_FRAMEOFDATA = 7
NAT_MESSAGESTRING = 8
NAT_DISCONNECT = 9
NAT_KEEPALIVE = 10
NAT_UNRECOGNIZED_REQUEST = 100

PROTOCOL_VERSION = (3, 1, 0, 0)
SERVER_VERSION = (3, 1, 0, 0)  # the Motive release that streams NatNet 3.1
CLOCK_HZ = 1_000_000_000  # high-resolution clock ticks per second: monotonic ns
APP_NAME_BYTES = 256  # fixed-size, NUL-padded application name in NAT_SERVERINFO
MAX_PACKET = 65503  # largest NatNet datagram
DATASET_RIGID_BODY = 1  # data description type in NAT_MODELDEF
RIGID_BODY_TRACKED = 0x01  # rigid body params bit: tracked in this frame

_HEADER = struct.Struct("<HH")
_RIGID_BODY = struct.Struct("<i3f4ffh")  # id, x y z, qx qy qz qw, mean marker error, params
_SUFFIX = struct.Struct("<IIdQQQh")  # timecode, subframe, timestamp [s], exposure, received, transmit, params


@dataclass(frozen=True)
class RigidBodySample:
    """One rigid body in a frame: position [m], orientation quaternion (w, x, y, z)."""

    id: int
    position: tuple[float, float, float]
    quat: tuple[float, float, float, float]
    tracked: bool = True
    error_m: float = 0.0  # mean marker error [m]


@dataclass(frozen=True)
class Frame:
    """A frame of mocap data; times on the server's clock [ns] (``CLOCK_HZ`` ticks)."""

    number: int
    bodies: tuple[RigidBodySample, ...]
    exposure_ns: int  # camera mid-exposure: when the pose was true
    received_ns: int  # camera data reached the server (exposure + camera latency)
    timestamp_s: float  # seconds since streaming began


def _packet(message_id: int, payload: bytes) -> bytes:
    if len(payload) > MAX_PACKET - _HEADER.size:
        raise ValueError(f"NatNet payload of {len(payload)} bytes is over the datagram limit")
    return _HEADER.pack(message_id, len(payload)) + payload


def _cstring(text: str) -> bytes:
    raw = text.encode("utf-8")
    if b"\0" in raw:
        raise ValueError(f"NatNet name {text!r} holds a NUL")
    return raw + b"\0"


def pack_server_info(app_name: str, data_port: int) -> bytes:
    """NAT_SERVERINFO: who we are, NatNet 3.1, clock frequency, unicast data port."""
    name = app_name.encode("utf-8")[:APP_NAME_BYTES - 1].ljust(APP_NAME_BYTES, b"\0")
    payload = (name + bytes(SERVER_VERSION) + bytes(PROTOCOL_VERSION)
               + struct.pack("<QH?4s", CLOCK_HZ, data_port, False, bytes(4)))
    return _packet(NAT_SERVERINFO, payload)


def pack_model_def(bodies: dict[int, str]) -> bytes:
    """NAT_MODELDEF: one rigid body description per id (no parent, no offset, no markers)."""
    parts = [struct.pack("<i", len(bodies))]
    for body_id, name in bodies.items():
        parts += [struct.pack("<i", DATASET_RIGID_BODY), _cstring(name),
                  struct.pack("<ii3fi", body_id, -1, 0.0, 0.0, 0.0, 0)]
    return _packet(NAT_MODELDEF, b"".join(parts))


def pack_frame(frame: Frame, transmit_ns: int) -> bytes:
    """NAT_FRAMEOFDATA (NatNet 3.1) with the frame's rigid bodies and no other data."""
    parts = [struct.pack("<iii", frame.number, 0, 0)]  # frame number, marker sets, unlabeled markers
    parts.append(struct.pack("<i", len(frame.bodies)))
    for b in frame.bodies:
        w, x, y, z = b.quat
        parts.append(_RIGID_BODY.pack(b.id, *b.position, x, y, z, w, b.error_m, RIGID_BODY_TRACKED if b.tracked else 0))
    parts.append(struct.pack("<iiii", 0, 0, 0, 0))  # skeletons, labeled markers, force plates, devices
    parts.append(_SUFFIX.pack(0, 0, frame.timestamp_s, frame.exposure_ns, frame.received_ns, transmit_ns, 0))
    parts.append(struct.pack("<i", 0))  # end of data tag
    return _packet(NAT_FRAMEOFDATA, b"".join(parts))


def pack_request(message_id: int, payload: bytes = b"") -> bytes:
    """A client's request (NAT_CONNECT, NAT_KEEPALIVE, ...)."""
    return _packet(message_id, payload)


def unpack_request(data: bytes) -> tuple[int, bytes]:
    """``(message id, payload)`` of a client request; ValueError when it is malformed."""
    if len(data) < _HEADER.size:
        raise ValueError("truncated")
    message_id, size = _HEADER.unpack_from(data)
    if size != len(data) - _HEADER.size:
        raise ValueError("size_mismatch")
    return message_id, data[_HEADER.size:]


class NatNetServer:
    """A Motive-like NatNet server on ``host``: command port, model definitions, unicast frames.

    ``bodies`` maps rigid body id to name. ``publish(frame)`` sends one frame to every
    connected client. Requests that are malformed or come from a host other than
    ``host`` are dropped and counted in ``counts`` (``rejected.<reason>``).
    """

    def __init__(self, bodies: dict[int, str], host: str = "127.0.0.1", command_port: int = 0,
                 data_port: int = 0, app_name: str = "ARCHER twin", max_clients: int = 8) -> None:
        if not bodies:
            raise ValueError("a NatNet server needs at least one rigid body")
        self.bodies = dict(bodies)
        self.host = host
        self.app_name = app_name
        self.max_clients = max_clients
        self.counts: Counter[str] = Counter()
        self.error: BaseException | None = None
        self._sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self._sock.bind((host, command_port))
        self._sock.settimeout(0.1)  # the receive loop looks at the stop flag this often
        self.command_port = self._sock.getsockname()[1]
        self.data_port = data_port or free_udp_port(host)
        self._clients: dict[tuple[str, int], None] = {}  # command addresses, in connection order
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._serve, name="natnet-command", daemon=True)

    def start(self) -> "NatNetServer":
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(1.0)
        self._sock.close()

    @property
    def clients(self) -> list[tuple[str, int]]:
        with self._lock:
            return list(self._clients)

    def publish(self, frame: Frame, now_ns: int) -> int:
        """Send ``frame`` (transmit time ``now_ns``) to every client; the datagrams sent."""
        packet = pack_frame(frame, now_ns)
        with self._lock:
            targets = list(self._clients) + [(h, self.data_port) for h in dict.fromkeys(h for h, _ in self._clients)]
        sent = 0
        for addr in targets:
            try:
                self._sock.sendto(packet, addr)
                sent += 1
            except OSError:
                self.counts["send_failed"] += 1
        self.counts["frames"] += 1
        return sent

    def _serve(self) -> None:
        try:
            while not self._stop.is_set():
                try:
                    data, addr = self._sock.recvfrom(MAX_PACKET)
                except socket.timeout:
                    continue
                self._handle(data, addr)
        except BaseException as exc:  # reported by the owner; the server stops answering
            if not self._stop.is_set():
                self.error = exc

    def _handle(self, data: bytes, addr: tuple[str, int]) -> None:
        if addr[0] != self.host:
            self.counts["rejected.address"] += 1
            return
        try:
            message_id, _ = unpack_request(data)
        except ValueError as exc:
            self.counts[f"rejected.{exc}"] += 1
            return
        if message_id in (NAT_CONNECT, NAT_KEEPALIVE, NAT_REQUEST_MODELDEF) and not self._register(addr):
            return
        if message_id == NAT_CONNECT:
            self._sock.sendto(pack_server_info(self.app_name, self.data_port), addr)
            self.counts["connects"] += 1
        elif message_id == NAT_REQUEST_MODELDEF:
            self._sock.sendto(pack_model_def(self.bodies), addr)
            self.counts["modeldefs"] += 1
        elif message_id == NAT_KEEPALIVE:
            self.counts["keepalives"] += 1
        elif message_id == NAT_DISCONNECT:
            with self._lock:
                self._clients.pop(addr, None)
            self.counts["disconnects"] += 1
        else:  # string commands (NAT_REQUEST) and frame polling are not served
            self._sock.sendto(_packet(NAT_UNRECOGNIZED_REQUEST, b""), addr)
            self.counts["rejected.unsupported"] += 1

    def _register(self, addr: tuple[str, int]) -> bool:
        with self._lock:
            if addr in self._clients:
                return True
            if len(self._clients) >= self.max_clients:
                self.counts["rejected.too_many_clients"] += 1
                return False
            self._clients[addr] = None
            return True
