"""Frames from a ``cv2.VideoCapture`` source: a camera index (any UVC camera; a ZED 2 in UVC mode gives
both eyes side by side, ``crop_left`` keeps the left one) or a video file (a recorded run)."""

from __future__ import annotations

import threading
from collections.abc import Callable

import numpy as np
import cv2


class CameraError(RuntimeError):
    pass


class VideoSource:
    def __init__(self, source: int | str, crop_left: bool = False) -> None:
        self.cap = cv2.VideoCapture(source)
        if not self.cap.isOpened():
            raise CameraError(f"cannot open video source {source!r}")
        self.crop_left = crop_left
        self.frames = 0
        self.abandoned = False

    @property
    def fps(self) -> float:
        return float(self.cap.get(cv2.CAP_PROP_FPS) or 0.0)

    def read(self) -> np.ndarray | None:
        """The next frame (BGR), or None at the end of a file / when the camera gives none."""
        ok, frame = self.cap.read()
        if not ok:
            return None
        self.frames += 1
        if self.crop_left:
            frame = frame[:, : frame.shape[1] // 2]
        return frame

    def close(self) -> None:
        if not self.abandoned:
            self.cap.release()

    def abandon(self) -> None:
        """Leave the capture to the thread still blocked reading it (released with the process): OpenCV's
        capture is not to be released under a read in progress."""
        self.abandoned = True

    def __enter__(self) -> VideoSource:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class LatestFrame:
    """A live source read as fast as it sends, keeping only its newest frame: a consumer slower than the
    camera (or one that stalls) gets the scene as it is now, never a backlog of buffered frames (an IP
    camera's stream queues in the socket and in FFmpeg otherwise). ``dropped`` counts frames nobody took."""

    def __init__(self, source: VideoSource, clock_ns: Callable[[], int]) -> None:
        self.source = source
        self.clock_ns = clock_ns
        self.dropped = 0
        self.ended = False
        self.error: BaseException | None = None
        self._cond = threading.Condition()
        self._frame: tuple[np.ndarray, int] | None = None
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._grab, name="camera-grabber", daemon=True)
        self._thread.start()

    def _grab(self) -> None:
        try:
            while not self._stop.is_set():
                frame = self.source.read()
                with self._cond:
                    if frame is None:
                        self.ended = True
                    else:
                        if self._frame is not None:
                            self.dropped += 1
                        self._frame = (frame, self.clock_ns())
                    self._cond.notify_all()
                if frame is None:
                    return
        except BaseException as exc:  # the consumer reports it
            self.error = exc
            with self._cond:
                self.ended = True
                self._cond.notify_all()

    def take(self, timeout_s: float) -> tuple[np.ndarray, int] | None:
        """The newest frame not taken yet and its receive time, waiting up to ``timeout_s`` for one
        (None: none came, or the source ended: see ``ended``)."""
        with self._cond:
            if self._frame is None and not self.ended:
                self._cond.wait(timeout_s)
            got, self._frame = self._frame, None
            return got

    def close(self, timeout_s: float = 2.0) -> None:
        """Stop grabbing; a read still blocked after ``timeout_s`` keeps the source (see :meth:`VideoSource.abandon`)."""
        self._stop.set()
        self._thread.join(timeout=timeout_s)
        if self._thread.is_alive():
            self.source.abandon()
