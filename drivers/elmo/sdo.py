"""SDO client (CiA 301): read and write one object of one node, expedited or segmented.

Blocking, for configuration before the cyclic exchange starts (never inside a
tick). Frames that arrive meanwhile and are not the awaited response (heartbeats,
EMCY, PDOs) go to ``on_other`` so that nothing is lost while waiting; ``idle`` runs
between waits (the master keeps its heartbeat going through a long configuration).
"""

from __future__ import annotations

import struct
import time
from collections.abc import Callable

from drivers.elmo import codec as c
from drivers.elmo.transport import CanTransport


class SdoError(Exception):
    """The server aborted the transfer, or it timed out."""

    def __init__(self, node_id: int, index: int, subindex: int, code: int, detail: str = "") -> None:
        self.node_id, self.index, self.subindex, self.code = node_id, index, subindex, code
        text = detail or c.abort_text(code)
        super().__init__(f"SDO node {node_id} 0x{index:04X}:{subindex:02X}: 0x{code:08X} {text}")


class SdoClient:
    def __init__(
        self,
        transport: CanTransport,
        node_id: int,
        timeout_s: float,
        on_other: Callable[[c.Frame], None] | None = None,
        idle: Callable[[], None] | None = None,
    ) -> None:
        self.transport = transport
        self.node_id = c.check_node_id(node_id)
        self.timeout_s = timeout_s
        self.on_other = on_other
        self.idle = idle
        self._rx_id = c.SDO_TX_BASE + node_id
        self._tx_id = c.SDO_RX_BASE + node_id
        self.transfers = 0
        self.segments = 0

    def _response(self, index: int, subindex: int) -> c.SdoMessage:
        deadline = time.monotonic() + self.timeout_s
        while True:
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                self.transport.send(c.make_sdo_abort(self._tx_id, index, subindex, c.SdoAbort.TIMEOUT))
                raise SdoError(self.node_id, index, subindex, c.SdoAbort.TIMEOUT, "no response (timeout)")
            if self.idle is not None:
                self.idle()
            frame = self.transport.recv(min(remaining, 0.005))
            if frame is None:
                if self.transport.broken:
                    raise SdoError(self.node_id, index, subindex, c.SdoAbort.GENERAL, self.transport.fault)
                continue
            if frame.can_id != self._rx_id:
                if self.on_other is not None:
                    self.on_other(frame)
                continue
            try:
                msg = c.parse_sdo(frame.data, client_to_server=False)
            except ValueError as exc:
                self.transport.send(c.make_sdo_abort(self._tx_id, index, subindex, c.SdoAbort.INVALID_COMMAND))
                raise SdoError(self.node_id, index, subindex, c.SdoAbort.INVALID_COMMAND, str(exc)) from None
            if msg.cs == c.CS_ABORT:
                raise SdoError(self.node_id, index, subindex, msg.abort_code)
            return msg

    def _fail(self, index: int, subindex: int, code: int, detail: str) -> SdoError:
        self.transport.send(c.make_sdo_abort(self._tx_id, index, subindex, code))
        return SdoError(self.node_id, index, subindex, code, detail)

    def upload(self, index: int, subindex: int) -> bytes:
        """Read ``index:subindex``; expedited or segmented as the server chooses."""
        self.transport.send(c.make_sdo_upload_request(self.node_id, index, subindex))
        msg = self._response(index, subindex)
        if msg.cs != c.SCS_INITIATE_UPLOAD or (msg.index, msg.subindex) != (index, subindex):
            raise self._fail(index, subindex, c.SdoAbort.INVALID_COMMAND, f"unexpected response cs={msg.cs}")
        self.transfers += 1
        if msg.expedited:
            return msg.payload
        data = bytearray()
        toggle = 0
        while True:
            self.transport.send(c.make_sdo_upload_segment_request(self.node_id, toggle))
            seg = self._response(index, subindex)
            if seg.cs != c.SCS_UPLOAD_SEGMENT:
                raise self._fail(index, subindex, c.SdoAbort.INVALID_COMMAND, f"unexpected segment cs={seg.cs}")
            if seg.toggle != toggle:
                raise self._fail(index, subindex, c.SdoAbort.TOGGLE_BIT, "toggle bit not alternated")
            self.segments += 1
            data += seg.payload
            if seg.last:
                break
            toggle ^= 1
        if msg.size is not None and len(data) != msg.size:
            raise SdoError(self.node_id, index, subindex, c.SdoAbort.LENGTH_MISMATCH, f"got {len(data)} bytes, announced {msg.size}")
        return bytes(data)

    def download(self, index: int, subindex: int, data: bytes) -> None:
        """Write ``data`` to ``index:subindex``; segmented beyond 4 bytes."""
        self.transport.send(c.make_sdo_download_request(self.node_id, index, subindex, data))
        msg = self._response(index, subindex)
        if msg.cs != c.SCS_INITIATE_DOWNLOAD or (msg.index, msg.subindex) != (index, subindex):
            raise self._fail(index, subindex, c.SdoAbort.INVALID_COMMAND, f"unexpected response cs={msg.cs}")
        self.transfers += 1
        if len(data) <= c.EXPEDITED_MAX:
            return
        toggle = 0
        for start in range(0, len(data), c.SEGMENT_BYTES):
            chunk = data[start : start + c.SEGMENT_BYTES]
            last = start + c.SEGMENT_BYTES >= len(data)
            self.transport.send(c.make_sdo_download_segment(self.node_id, toggle, chunk, last))
            seg = self._response(index, subindex)
            if seg.cs != c.SCS_DOWNLOAD_SEGMENT:
                raise self._fail(index, subindex, c.SdoAbort.INVALID_COMMAND, f"unexpected segment response cs={seg.cs}")
            if seg.toggle != toggle:
                raise self._fail(index, subindex, c.SdoAbort.TOGGLE_BIT, "toggle bit not alternated")
            self.segments += 1
            toggle ^= 1

    # typed helpers

    def read_u8(self, index: int, subindex: int = 0) -> int:
        return self._read(index, subindex, "<B")

    def read_u16(self, index: int, subindex: int = 0) -> int:
        return self._read(index, subindex, "<H")

    def read_u32(self, index: int, subindex: int = 0) -> int:
        return self._read(index, subindex, "<I")

    def read_i8(self, index: int, subindex: int = 0) -> int:
        return self._read(index, subindex, "<b")

    def read_string(self, index: int, subindex: int = 0) -> str:
        return self.upload(index, subindex).decode("ascii", errors="replace")

    def _read(self, index: int, subindex: int, fmt: str) -> int:
        data = self.upload(index, subindex)
        size = struct.calcsize(fmt)
        if len(data) != size:
            raise SdoError(self.node_id, index, subindex, c.SdoAbort.LENGTH_MISMATCH, f"{len(data)} bytes, expected {size}")
        return struct.unpack(fmt, data)[0]

    def write(self, index: int, subindex: int, fmt: str, value: int) -> None:
        self.download(index, subindex, struct.pack(fmt, value))
