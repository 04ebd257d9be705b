"""Intel RealSense D435 through librealsense (``pyrealsense2``, ``pip install '.[realsense]'``).

- :mod:`drivers.realsense.frames` (codec): the D435's modes, z16 <-> metres, the sensor's
  clock mapped onto the stack's, the frame nearest an apex;
- :mod:`drivers.realsense.device` (device): a pipeline on a camera or a recording, depth and
  colour aligned, the SDK's post-processing filters, intrinsics and depth scale from the device;
- :mod:`drivers.realsense.emulator` (emulator): a ``rs.software_device`` fed with images (the
  twin's), optionally recorded by ``rs.recorder``.

The transport is librealsense's own (USB, or a file); :func:`load` imports it.
"""

from __future__ import annotations

import ctypes
from types import ModuleType


def load() -> ModuleType:
    """``pyrealsense2``, with ``libusb-1.0`` from the ``libusb-package`` wheel loaded first.

    The PyPI wheel links ``libusb-1.0.so.0`` but does not ship it; a machine without the
    system library gets it from ``libusb-package`` (loaded globally, so the wheel's
    dynamic link resolves to it).
    """
    try:
        import pyrealsense2 as rs  # a system libusb, if the machine has one
        return rs
    except ImportError as first:
        try:
            import libusb_package
        except ImportError:
            raise first from None
        path = libusb_package.get_library_path()
        if path is None:
            raise first from None
        ctypes.CDLL(str(path), mode=ctypes.RTLD_GLOBAL)
        import pyrealsense2 as rs
        return rs
