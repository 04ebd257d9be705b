"""A socketcand server (raw mode) on loopback: an emulated CAN bus for stock clients.

socketcand (linux-can/socketcand) exposes a CAN bus over TCP with a small ASCII
protocol; python-can ships the client (``interface="socketcand"``). The drive
emulator serves its bus this way so that a stock python-can client in another
process (our driver, the ``canopen`` package, ``python -m can.viewer``) connects with
``can.Bus(interface="socketcand", channel=..., host="127.0.0.1", port=...,
tcp_tune=True)``. No UDP discovery beacon is sent (it would be a broadcast): the
emulator prints the port instead.

The server behaves as a bus: a frame one client sends reaches every other client and
the ``on_frame`` handler (the emulated devices), whose answers reach every client.
Frames are handled on the receiving connection's thread, so an answer leaves in the
same pass that read the request (no hand-over between threads).

Protocol subset (socketcand's doc/protocol.md): the server greets ``< hi >``; the
client sends ``< open CHANNEL >`` and ``< rawmode >``, each answered ``< ok >``; then
the server sends ``< frame ID SECONDS.MICROS HEXDATA >`` for every bus frame and
``< error ID SECONDS.MICROS >`` for error frames, and the client sends
``< send ID DLC B0 B1 ... >``.
"""

from __future__ import annotations

import logging
import select
import socket
import threading
import time
from collections import deque
from collections.abc import Callable

import can

from drivers.elmo.codec import Frame

log = logging.getLogger("archer.drivers.socketcand")

LOOPBACK = "127.0.0.1"
ERROR_FLAG = 0x20000000  # SocketCAN CAN_ERR_FLAG: an error frame, error class below it
EXTENDED_FLAG = 0x80000000  # SocketCAN CAN_EFF_FLAG: a 29-bit identifier
RAWMODE_SETTLE_S = 0.1  # python-can's client reads "< ok >" with one recv(): no frames glued to it
MAX_PENDING_CHARS = 4096  # an unterminated command longer than this is garbage: drop it
RECV_CHUNK = 65536

Handler = Callable[[Frame, float], list[Frame]]


def format_frame(frame: Frame, timestamp: float) -> str:
    can_id = frame.can_id
    if can_id & ERROR_FLAG:
        return f"< error {can_id & 0x1FFFFFFF:08X} {timestamp:.6f} >"
    text_id = f"{can_id & 0x1FFFFFFF:08X}" if can_id & EXTENDED_FLAG else f"{can_id:03X}"
    return f"< frame {text_id} {timestamp:.6f} {frame.data.hex().upper()} >"


def parse_send(command: str) -> Frame:
    """``< send ID DLC B0 ... >`` -> a frame; raises ValueError when malformed."""
    parts = command[1:-1].split()
    if len(parts) < 3 or parts[0] != "send":
        raise ValueError(f"not a send command: {command!r}")
    can_id = int(parts[1], 16)
    dlc = int(parts[2], 16)
    data = bytes(int(b, 16) for b in parts[3:])
    if dlc != len(data) or dlc > 8:
        raise ValueError(f"DLC {dlc} does not match {len(data)} data bytes")
    extended = len(parts[1]) > 3
    if can_id > (0x1FFFFFFF if extended else 0x7FF):
        raise ValueError(f"identifier {parts[1]} out of range")
    return Frame(can_id | (EXTENDED_FLAG if extended else 0), data)


class _Client:
    def __init__(self, server: SocketcandServer, sock: socket.socket) -> None:
        self.server = server
        self.sock = sock
        self.raw = False
        self.ready = False  # rawmode settled: frames flow at once, not queued
        self._pending: list[str] = []
        self.closed = threading.Event()
        self.bad_commands = 0
        self._write_lock = threading.Lock()

    def write(self, text: str) -> None:
        if self.closed.is_set():
            return
        try:
            with self._write_lock:
                self.sock.sendall(text.encode("ascii"))
        except OSError:
            self.close()

    def write_frames(self, text: str) -> None:
        """Bus traffic for this client: queued until raw mode has settled."""
        with self._write_lock:
            if not self.ready:
                if self.raw:
                    self._pending.append(text)
                return
        self.write(text)

    def run(self) -> None:
        try:
            self.write("< hi >")
            buffer = ""
            while not self.closed.is_set() and not self.server.stopping.is_set():
                chunk = self.sock.recv(RECV_CHUNK)
                if not chunk:
                    break
                buffer += chunk.decode("ascii", errors="replace")
                frames: list[Frame] = []
                while True:
                    start = buffer.find("<")
                    if start < 0:
                        buffer = ""
                        break
                    end = buffer.find(">", start + 1)
                    if end < 0:
                        buffer = buffer[start:] if len(buffer) - start < MAX_PENDING_CHARS else ""
                        break
                    command = buffer[start : end + 1]
                    buffer = buffer[end + 1 :]
                    frame = self._command(command)
                    if frame is not None:
                        frames.append(frame)
                if frames:
                    self.server.deliver(frames, self)
        except OSError:
            pass
        finally:
            self.close()

    def _command(self, command: str) -> Frame | None:
        words = command[1:-1].split()
        if not words:
            return None
        if words[0] == "send" and self.raw:
            try:
                return parse_send(command)
            except ValueError:
                self.bad_commands += 1
                self.write("< error bad send command >")
                return None
        if words[0] == "open":
            if len(words) == 2 and words[1] == self.server.channel:
                self.write("< ok >")
            else:
                self.write("< error could not open bus >")
            return None
        if words[0] == "rawmode":
            self.raw = True
            self.write("< ok >")
            threading.Timer(RAWMODE_SETTLE_S, self._settled).start()
            return None
        self.bad_commands += 1
        self.write("< error unknown command >")
        return None

    def _settled(self) -> None:
        with self._write_lock:
            self.ready = True
            pending, self._pending = "".join(self._pending), []
        if pending:
            self.write(pending)

    def close(self) -> None:
        if self.closed.is_set():
            return
        self.closed.set()
        try:
            self.sock.shutdown(socket.SHUT_RDWR)  # wakes the reading thread and sends the FIN now
        except OSError:
            pass
        try:
            self.sock.close()
        except OSError:
            pass


class SocketcandServer:
    """Serves ``channel`` on 127.0.0.1:``port`` (0: a free port) around ``on_frame``."""

    def __init__(self, on_frame: Handler | None = None, channel: str = "can0", port: int = 0) -> None:
        self.on_frame = on_frame
        self.channel = channel
        self.stopping = threading.Event()
        self._listener = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        self._listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        self._listener.bind((LOOPBACK, port))
        self._listener.listen(4)
        self._listener.settimeout(0.2)
        self.port = self._listener.getsockname()[1]
        self.clients: list[_Client] = []
        self.frames_from_clients = 0
        self.frames_to_clients = 0
        self._thread = threading.Thread(target=self._accept_loop, name="socketcand-accept", daemon=True)

    def bus_kwargs(self) -> dict[str, object]:
        """What a python-can client passes to ``can.Bus``."""
        return {"interface": "socketcand", "channel": self.channel, "host": LOOPBACK, "port": self.port, "tcp_tune": True}

    def start(self) -> SocketcandServer:
        self._thread.start()
        return self

    def _accept_loop(self) -> None:
        while not self.stopping.is_set():
            try:
                sock, _addr = self._listener.accept()
            except TimeoutError:
                continue
            except OSError:
                break
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            client = _Client(self, sock)
            self.clients = [c for c in self.clients if not c.closed.is_set()] + [client]
            threading.Thread(target=client.run, name="socketcand-client", daemon=True).start()

    def deliver(self, frames: list[Frame], sender: _Client) -> None:
        """Frames a client put on the bus: to the other clients and to the devices."""
        self.frames_from_clients += len(frames)
        now = time.time()
        relay = "".join(format_frame(f, now) for f in frames)
        for client in self.clients:
            if client is not sender:
                client.write_frames(relay)
        if self.on_frame is None:
            return
        answers: list[Frame] = []
        mono = time.monotonic()
        for f in frames:
            answers += self.on_frame(f, mono)
        self.broadcast(answers)

    def broadcast(self, frames: list[Frame]) -> None:
        """Frames the devices put on the bus: to every client."""
        if not frames:
            return
        now = time.time()
        text = "".join(format_frame(f, now) for f in frames)
        for client in self.clients:
            client.write_frames(text)
            self.frames_to_clients += len(frames)

    def disconnect_clients(self) -> None:
        """Drop every connection (a vanished adapter, seen from the client)."""
        for client in self.clients:
            client.close()

    def stop(self) -> None:
        self.stopping.set()
        self.disconnect_clients()
        try:
            self._listener.close()
        except OSError:
            pass
        if self._thread.is_alive():
            self._thread.join(1.0)


class SocketcandBus(can.BusABC):
    """A python-can bus on a socketcand server that sends a batch of frames in one write.

    python-can's own socketcand client writes (and re-arms TCP_QUICKACK) once per
    frame; on loopback each write costs tens of microseconds of kernel time, five
    times per tick. This client speaks the same protocol and adds :meth:`send_many`,
    which the CAN transport uses for its one batch per tick. Everything else is a
    plain python-can bus.
    """

    open_buses = 0  # instances not shut down yet (tests fail on a leak)

    def __init__(self, channel: str, host: str = LOOPBACK, port: int = 29536, timeout_s: float = 5.0, **kwargs: object) -> None:
        self._sock = socket.create_connection((host, port), timeout=timeout_s)
        self._sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self._buffer = b""
        self._pending: deque[can.Message] = deque()
        self.channel_info = f"socketcand {channel}@{host}:{port}"
        try:
            self._expect("< hi >", timeout_s)
            self._sock.sendall(f"< open {channel} >".encode("ascii"))
            self._expect("< ok >", timeout_s)
            self._sock.sendall(b"< rawmode >")
            self._expect("< ok >", timeout_s)
        except (OSError, can.CanError):
            self._sock.close()
            raise
        self._sock.settimeout(None)  # blocking; reads only after select() says ready
        super().__init__(channel=channel, **kwargs)
        self._open = True
        SocketcandBus.open_buses += 1

    def _expect(self, text: str, timeout_s: float) -> None:
        """Read one ``< ... >`` reply; frames glued after it stay in the buffer."""
        end = time.monotonic() + timeout_s
        while b">" not in self._buffer:
            if time.monotonic() > end:
                raise can.CanError(f"socketcand: no {text!r} from the server")
            chunk = self._sock.recv(RECV_CHUNK)
            if not chunk:
                raise can.CanError("socketcand: server closed the connection")
            self._buffer += chunk
        cut = self._buffer.index(b">") + 1
        reply, self._buffer = self._buffer[:cut].decode("ascii").strip(), self._buffer[cut:]
        if reply != text:
            raise can.CanError(f"socketcand: expected {text!r}, got {reply!r}")

    def fileno(self) -> int:
        return self._sock.fileno()

    @staticmethod
    def _format(msg: can.Message) -> str:
        can_id = f"{msg.arbitration_id:08X}" if msg.is_extended_id else f"{msg.arbitration_id:03X}"
        data = " ".join(f"{b:02X}" for b in msg.data)
        return f"< send {can_id} {len(msg.data):X} {data} >"

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        self.send_many([msg])

    def send_many(self, msgs: list[can.Message]) -> None:
        """All ``msgs`` in one write (one TCP segment on loopback)."""
        try:
            self._sock.sendall("".join(self._format(m) for m in msgs).encode("ascii"))
        except OSError as exc:
            raise can.CanOperationError(f"socketcand send failed: {exc}") from exc

    def _parse(self) -> None:
        buf = self._buffer
        start = 0
        while True:
            open_at = buf.find(b"<", start)
            if open_at < 0:
                buf = b""
                break
            close_at = buf.find(b">", open_at)
            if close_at < 0:
                buf = buf[open_at:] if len(buf) - open_at < MAX_PENDING_CHARS else b""
                break
            words = buf[open_at + 1 : close_at].split()
            start = close_at + 1
            if len(words) >= 3 and words[0] in (b"frame", b"error"):
                can_id = int(words[1], 16)
                stamp = float(words[2])
                if words[0] == b"error":
                    self._pending.append(can.Message(timestamp=stamp, arbitration_id=can_id, is_error_frame=True, is_extended_id=True, data=bytes(8), is_rx=True, channel=self.channel_info))
                else:
                    data = bytes.fromhex(words[3].decode("ascii")) if len(words) > 3 else b""
                    self._pending.append(
                        can.Message(timestamp=stamp, arbitration_id=can_id, is_extended_id=len(words[1]) > 3, data=data, is_rx=True, channel=self.channel_info)
                    )
        self._buffer = buf

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        if not self._pending:
            try:
                ready, _, _ = select.select([self._sock], [], [], timeout)
                chunk = self._sock.recv(RECV_CHUNK) if ready else None
            except OSError as exc:
                raise can.CanOperationError(f"socketcand receive failed: {exc}") from exc
            if chunk == b"":
                raise can.CanOperationError("socketcand: server closed the connection")
            if chunk:
                self._buffer += chunk
                self._parse()
        if self._pending:
            return self._pending.popleft(), False
        return None, False

    def shutdown(self) -> None:
        super().shutdown()
        self._sock.close()
        if self._open:
            self._open = False
            SocketcandBus.open_buses -= 1
