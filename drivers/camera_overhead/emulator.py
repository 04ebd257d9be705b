"""An IP camera's MJPEG stream, emulated: JPEG frames served over HTTP as ``multipart/x-mixed-replace``
(what most network cameras stream and ``cv2.VideoCapture`` reads through its FFmpeg backend from an
``http://`` URL), so that the ``camera_overhead`` service reads emulated frames through the same
``VideoCapture`` path as a lab's camera. In a real-time run the twin's camera process serves its
rendered overhead view here (``services/cli/overhead_realtime.py``); ``archer emulate overhead`` serves
a scenario's frames or a video file.

Every client gets the newest frame when it connects, then each frame as it is published (a slow
client skips frames rather than falling behind, as a camera's server does). Each part carries its
``Content-Length``, so a reader need not wait for the next boundary to end a frame.
"""

from __future__ import annotations

import http.server
import logging
import socketserver
import threading
import time
from collections import Counter

import cv2
import numpy as np

log = logging.getLogger("archer.camera_overhead.emulator")

BOUNDARY = "archerframe"
STREAM_PATH = "/stream.mjpg"
JPEG_QUALITY = 85
CLIENT_POLL_S = 0.5  # [s] how often a waiting client's thread checks the server is still up


class MjpegServer:
    """Serves the newest published frame to every client of ``url`` (127.0.0.1, a free port by default)."""

    def __init__(self, host: str = "127.0.0.1", port: int = 0, quality: int = JPEG_QUALITY) -> None:
        self.quality = quality
        self.counts: Counter[str] = Counter()
        self._cond = threading.Condition()
        self._jpeg: bytes | None = None
        self._seq = 0
        self._stopping = False
        server = self

        class Handler(http.server.BaseHTTPRequestHandler):
            protocol_version = "HTTP/1.0"  # the stream ends when the connection does

            def do_GET(self) -> None:  # noqa: N802 (http.server's name)
                if self.path.split("?")[0] != STREAM_PATH:
                    server.counts["not_found"] += 1
                    self.send_error(404, f"the stream is {STREAM_PATH}")
                    return
                server.counts["clients"] += 1
                self.send_response(200)
                self.send_header("Content-Type", f"multipart/x-mixed-replace; boundary={BOUNDARY}")
                self.send_header("Cache-Control", "no-cache")
                self.send_header("Connection", "close")
                self.end_headers()
                sent = server._seq - 1 if server._jpeg is not None else server._seq  # the newest frame first
                try:
                    while True:
                        jpeg, sent = server._next(sent)
                        if jpeg is None:
                            return
                        self.wfile.write(f"--{BOUNDARY}\r\nContent-Type: image/jpeg\r\nContent-Length: {len(jpeg)}\r\n\r\n"
                                         .encode("ascii") + jpeg + b"\r\n")
                        self.wfile.flush()
                        server.counts["frames_sent"] += 1
                except (BrokenPipeError, ConnectionResetError):
                    server.counts["clients_gone"] += 1

            def log_message(self, format: str, *args: object) -> None:  # noqa: A002 (http.server's name)
                log.debug(format, *args)

        class Server(socketserver.ThreadingMixIn, http.server.HTTPServer):
            daemon_threads = True
            allow_reuse_address = True

        self._httpd = Server((host, port), Handler)
        self._thread = threading.Thread(target=self._httpd.serve_forever, name="mjpeg-server", daemon=True)

    @property
    def address(self) -> tuple[str, int]:
        host, port = self._httpd.server_address[:2]
        return str(host), int(port)

    @property
    def url(self) -> str:
        host, port = self.address
        return f"http://{host}:{port}{STREAM_PATH}"

    def start(self) -> MjpegServer:
        self._thread.start()
        return self

    def publish(self, frame: np.ndarray) -> int:
        """Encode a BGR frame and serve it; its sequence number (1, 2, ...)."""
        try:
            ok, buf = cv2.imencode(".jpg", frame, [cv2.IMWRITE_JPEG_QUALITY, self.quality])
        except cv2.error:
            ok = False
        if not ok:
            raise ValueError(f"cannot encode a frame of shape {frame.shape} as JPEG")
        return self.publish_jpeg(buf.tobytes())

    def publish_jpeg(self, jpeg: bytes) -> int:
        with self._cond:
            self._jpeg = jpeg
            self._seq += 1
            self.counts["frames_published"] += 1
            self._cond.notify_all()
            return self._seq

    def _next(self, sent: int) -> tuple[bytes | None, int]:
        """The newest frame after ``sent`` once there is one (None when the server stops)."""
        with self._cond:
            while self._seq == sent and not self._stopping:
                self._cond.wait(CLIENT_POLL_S)
            if self._stopping:
                return None, sent
            return self._jpeg, self._seq

    def stop(self) -> None:
        with self._cond:
            self._stopping = True
            self._cond.notify_all()
        if self._thread.is_alive():
            self._httpd.shutdown()
        self._httpd.server_close()

    def __enter__(self) -> MjpegServer:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()


def serve_frames(server: MjpegServer, frames, rate_hz: float, stop: threading.Event) -> int:
    """Publish ``frames`` (an iterable of BGR images) at ``rate_hz`` until they end or ``stop`` is set;
    how many were published."""
    period = 1.0 / rate_hz
    next_t = time.monotonic()
    n = 0
    for frame in frames:
        if stop.wait(max(0.0, next_t - time.monotonic())):
            break
        server.publish(frame)
        n += 1
        next_t = max(next_t + period, time.monotonic())
    return n
