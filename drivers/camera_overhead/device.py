"""Frames from a ``cv2.VideoCapture`` source: a camera index (any UVC camera; a ZED 2 in UVC mode gives
both eyes side by side, ``crop_left`` keeps the left one) or a video file (a recorded run)."""

from __future__ import annotations

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
        self.cap.release()

    def __enter__(self) -> VideoSource:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
