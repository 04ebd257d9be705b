"""The D435's frames as numbers: z16 <-> metres, its clock on the stack's, the frame nearest an apex.

(Its modes, fields of view and depth error are the datasheet's: :mod:`robot_description.d435`.)

Nothing here imports librealsense: the device (:mod:`drivers.realsense.device`) hands over
arrays and timestamps, and these functions and classes are tested alone.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass
from typing import Generic, TypeVar

import numpy as np


def z16_to_metres(z16: np.ndarray, depth_scale: float) -> np.ndarray:
    """Depth [m] (float32) of z16 counts; 0 stays 0 (no return)."""
    return z16.astype(np.float32) * np.float32(depth_scale)


def metres_to_z16(depth_m: np.ndarray, depth_scale: float) -> np.ndarray:
    """z16 counts of depth [m]: rounded; 0, negative, non-finite or beyond the z16 range -> 0 (no return)."""
    counts = np.rint(np.nan_to_num(depth_m, nan=0.0, posinf=0.0, neginf=0.0) / depth_scale)
    return np.where((counts > 0) & (counts <= np.iinfo(np.uint16).max), counts, 0).astype(np.uint16)


GLOBAL_TIME = "global_time"  # librealsense's timestamp domain: the camera's clock on the host's wall clock


class ClockMap:
    """A sensor's clock mapped onto the stack's monotonic clock.

    The offset is the smallest ``receive - sensor`` over the last ``window`` frames (the
    least-delayed frame bounds the transport delay from below; a sliding window follows the
    two clocks' drift), less ``min_latency_ns``, the delay no frame beats (exposure to the
    host, measured once). A frame's capture time is then ``sensor + offset``.

    A frame in librealsense's ``global_time`` domain from a camera (``live``) carries its capture
    time on the host's wall clock already (the SDK's own regression of the camera's clock against
    the host's): that time, moved onto the stack's clock, is taken as it is, whatever the delivery
    delay was (a camera triggered at an apex and delivered late, a loaded host), unless it is older
    than ``global_max_age_ns`` at receipt: then the frame came too late to use (:meth:`stamp`
    returns None, counted in ``stale``). A global time in the future (the wall clock stepped), and
    every frame of a recording played back (its global times are the day it was recorded), go
    through the offset as any other.

    A live camera's frames are placed by the offset only once the map has seen one come no sooner than
    half its sensor spacing after the one before (``settled``): that frame waited for its capture, not
    in a queue. Frames read from a queue at the stream's start (a camera that streamed before the
    reader came, a reader held up) all carry a delay of their own; placing them by the least of those
    put a frame captured 0.9 s before an apex at the apex. Until then :meth:`stamp` returns None,
    counted in ``queued``. A recording played back (not ``live``) is placed from its first frame.
    """

    def __init__(self, window: int, min_latency_ns: int, global_max_age_ns: int = 0, live: bool = True) -> None:
        if window < 1 or min_latency_ns < 0 or global_max_age_ns < 0:
            raise ValueError("ClockMap needs window >= 1, min_latency_ns >= 0 and global_max_age_ns >= 0")
        self._gaps: deque[int] = deque(maxlen=window)
        self._min_latency_ns = min_latency_ns
        self._global_max_age_ns = global_max_age_ns
        self._live = live
        self._last_sensor_ns: int | None = None
        self._last_receive_ns = 0
        self.settled = not live
        self.global_stamps = 0  # frames stamped by their global time
        self.stale = 0  # frames delivered later than the bound
        self.queued = 0  # frames read before the map settled

    def stamp(self, sensor_ns: int, receive_ns: int, domain: str = "", wall_minus_stack_ns: int = 0) -> int | None:
        """The capture time on the stack's clock of a frame stamped ``sensor_ns`` in ``domain``, received
        at ``receive_ns`` (None: a camera's frame delivered too late, or read before the map settled);
        ``wall_minus_stack_ns``: the host's wall clock less the stack's, at receipt.

        A sensor clock that goes back (a camera reset, a recording played again) restarts the map.
        """
        if domain == GLOBAL_TIME and self._live:
            capture_ns = sensor_ns - wall_minus_stack_ns
            if capture_ns < receive_ns - self._global_max_age_ns:
                self.stale += 1
                return None
            if capture_ns <= receive_ns:
                self.global_stamps += 1
                return capture_ns
        if self._last_sensor_ns is not None and sensor_ns < self._last_sensor_ns:
            self._gaps.clear()
            self._last_sensor_ns = None
            self.settled = not self._live
        if not self.settled and self._last_sensor_ns is not None:
            self.settled = 2 * (receive_ns - self._last_receive_ns) >= sensor_ns - self._last_sensor_ns
        self._last_sensor_ns, self._last_receive_ns = sensor_ns, receive_ns
        self._gaps.append(receive_ns - sensor_ns)
        if not self.settled:
            self.queued += 1
            return None
        return sensor_ns + min(self._gaps) - self._min_latency_ns


F = TypeVar("F")


@dataclass
class Picked(Generic[F]):
    frame: F
    stamp_ns: int  # the frame's capture time on the stack's clock
    apex_ns: int  # the apex it stands for
    offset_ns: int  # stamp - apex


class ApexPicker(Generic[F]):
    """The frame captured nearest each apex.

    Frames (stamped on the stack's clock) go in as they arrive; apex events as the estimator
    sends them. An apex is answered once a frame captured at or after it has arrived (the
    nearest is then that one or the one before), with the nearer of the two if it lies within
    ``tolerance_ns``; otherwise the apex is counted as missed (``missed``). A newer apex
    replaces one still waiting.
    """

    def __init__(self, tolerance_ns: int, keep: int) -> None:
        if tolerance_ns <= 0 or keep < 2:
            raise ValueError("ApexPicker needs tolerance_ns > 0 and keep >= 2")
        self._frames: deque[tuple[int, F]] = deque(maxlen=keep)
        self._apex_ns: int | None = None
        self.tolerance_ns = tolerance_ns
        self.missed = 0

    def add_frame(self, stamp_ns: int, frame: F) -> Picked[F] | None:
        self._frames.append((stamp_ns, frame))
        return self._try()

    def add_apex(self, apex_ns: int) -> Picked[F] | None:
        if self._apex_ns is not None:
            self.missed += 1  # no frame came after the previous apex before this one
        self._apex_ns = apex_ns
        return self._try()

    def _try(self) -> Picked[F] | None:
        apex = self._apex_ns
        if apex is None or not self._frames or self._frames[-1][0] < apex:
            return None
        self._apex_ns = None
        stamp, frame = min(self._frames, key=lambda sf: abs(sf[0] - apex))
        if abs(stamp - apex) > self.tolerance_ns:
            self.missed += 1
            return None
        return Picked(frame, stamp, apex, stamp - apex)
