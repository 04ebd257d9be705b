"""Compact binary layout for large arrays: depth images and occupancy grids.

Layout (little endian), documented so any client can parse it:

    header  : magic b"ARCB", version u16, kind u16, stamp_ns i64, seq u64   (24 bytes)
    depth   : width u32, height u32, fx fy cx cy f64, cam_pos f64[3], cam_quat f64[4]
              then float32 depth [m] row-major (height x width); 0 or inf = no return
    color   : as depth (width, height, intrinsics, camera pose), then uint8 RGB row-major
              (height x width x 3), registered to a depth image of the same stamp pixel for pixel
    grid    : width u32 (columns, along x), height u32 (rows, along y), resolution f64 [m],
              origin_x f64, origin_y f64 [m, world position of the lower-left corner of
              cell [0, 0]], then uint8 cells row-major: 0 free, 100 occupied, 255 unknown

Zenoh encoding for both: ``application/octet-stream;archer-binary-v1``.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

import numpy as np

from onboard.contracts.messages import MessageError

MAGIC = b"ARCB"
BINARY_VERSION = 1
ENCODING = "application/octet-stream;archer-binary-v1"
KIND_DEPTH = 1
KIND_GRID = 2
KIND_COLOR = 3

CELL_FREE = 0
CELL_OCCUPIED = 100
CELL_UNKNOWN = 255

_HEADER = struct.Struct("<4sHHqQ")
_DEPTH = struct.Struct("<II4d3d4d")
_GRID = struct.Struct("<II3d")


@dataclass
class DepthImage:
    depth: np.ndarray  # (height, width) float32 [m]
    fx: float  # focal lengths and principal point [px]
    fy: float
    cx: float
    cy: float
    cam_pos: np.ndarray  # camera optical centre in world [m]
    cam_quat: np.ndarray  # camera->world [w, x, y, z]; camera frame: x right, y down, z forward
    stamp_ns: int = 0
    seq: int = 0


@dataclass
class ColorImage:
    rgb: np.ndarray  # (height, width, 3) uint8, RGB
    fx: float  # intrinsics of the pixels [px] (those of the depth image it is aligned to)
    fy: float
    cx: float
    cy: float
    cam_pos: np.ndarray  # as DepthImage
    cam_quat: np.ndarray
    stamp_ns: int = 0
    seq: int = 0


@dataclass
class OccupancyGrid:
    cells: np.ndarray  # (rows along y, cols along x) uint8
    resolution: float  # [m]
    origin: tuple[float, float]  # lower-left corner of cell [0, 0] in world [m]
    stamp_ns: int = 0
    seq: int = 0


def _header(kind: int, stamp_ns: int, seq: int) -> bytes:
    return _HEADER.pack(MAGIC, BINARY_VERSION, kind, stamp_ns, seq)


def _parse_header(buf: bytes, kind: int) -> tuple[int, int]:
    if len(buf) < _HEADER.size:
        raise MessageError("binary message shorter than its header")
    magic, version, got_kind, stamp_ns, seq = _HEADER.unpack_from(buf, 0)
    if magic != MAGIC or version != BINARY_VERSION:
        raise MessageError("not an archer binary message of a known version")
    if got_kind != kind:
        raise MessageError(f"binary message kind {got_kind}, expected {kind}")
    return stamp_ns, seq


def encode_depth(img: DepthImage) -> bytes:
    h, w = img.depth.shape
    meta = _DEPTH.pack(w, h, img.fx, img.fy, img.cx, img.cy, *map(float, img.cam_pos), *map(float, img.cam_quat))
    return _header(KIND_DEPTH, img.stamp_ns, img.seq) + meta + np.ascontiguousarray(img.depth, dtype="<f4").tobytes()


def decode_depth(payload: bytes | bytearray | memoryview) -> DepthImage:
    buf = bytes(payload)
    stamp_ns, seq = _parse_header(buf, KIND_DEPTH)
    off = _HEADER.size
    if len(buf) < off + _DEPTH.size:
        raise MessageError("depth image truncated")
    w, h, fx, fy, cx, cy, *pose = _DEPTH.unpack_from(buf, off)
    off += _DEPTH.size
    if w == 0 or h == 0 or len(buf) - off != 4 * w * h:
        raise MessageError(f"depth image {w}x{h} does not match its {len(buf) - off} data bytes")
    meta = np.array([fx, fy, cx, cy, *pose])
    if not np.all(np.isfinite(meta)):
        raise MessageError("depth image with non-finite intrinsics or pose")
    depth = np.frombuffer(buf, dtype="<f4", offset=off).reshape(h, w)
    if np.isnan(depth).any():
        raise MessageError("depth image with NaN pixels")
    return DepthImage(depth, fx, fy, cx, cy, np.array(pose[:3]), np.array(pose[3:]), stamp_ns, seq)


def encode_color(img: ColorImage) -> bytes:
    h, w, channels = img.rgb.shape
    if channels != 3:
        raise ValueError(f"colour image with {channels} channels, expected 3 (RGB)")
    meta = _DEPTH.pack(w, h, img.fx, img.fy, img.cx, img.cy, *map(float, img.cam_pos), *map(float, img.cam_quat))
    return _header(KIND_COLOR, img.stamp_ns, img.seq) + meta + np.ascontiguousarray(img.rgb, dtype=np.uint8).tobytes()


def decode_color(payload: bytes | bytearray | memoryview) -> ColorImage:
    buf = bytes(payload)
    stamp_ns, seq = _parse_header(buf, KIND_COLOR)
    off = _HEADER.size
    if len(buf) < off + _DEPTH.size:
        raise MessageError("colour image truncated")
    w, h, fx, fy, cx, cy, *pose = _DEPTH.unpack_from(buf, off)
    off += _DEPTH.size
    if w == 0 or h == 0 or len(buf) - off != 3 * w * h:
        raise MessageError(f"colour image {w}x{h} does not match its {len(buf) - off} data bytes")
    if not np.all(np.isfinite([fx, fy, cx, cy, *pose])):
        raise MessageError("colour image with non-finite intrinsics or pose")
    rgb = np.frombuffer(buf, dtype=np.uint8, offset=off).reshape(h, w, 3)
    return ColorImage(rgb, fx, fy, cx, cy, np.array(pose[:3]), np.array(pose[3:]), stamp_ns, seq)


def encode_grid(grid: OccupancyGrid) -> bytes:
    rows, cols = grid.cells.shape
    meta = _GRID.pack(cols, rows, grid.resolution, grid.origin[0], grid.origin[1])
    return _header(KIND_GRID, grid.stamp_ns, grid.seq) + meta + np.ascontiguousarray(grid.cells, dtype=np.uint8).tobytes()


def decode_grid(payload: bytes | bytearray | memoryview) -> OccupancyGrid:
    buf = bytes(payload)
    stamp_ns, seq = _parse_header(buf, KIND_GRID)
    off = _HEADER.size
    if len(buf) < off + _GRID.size:
        raise MessageError("occupancy grid truncated")
    cols, rows, res, ox, oy = _GRID.unpack_from(buf, off)
    off += _GRID.size
    if cols == 0 or rows == 0 or len(buf) - off != cols * rows:
        raise MessageError(f"occupancy grid {rows}x{cols} does not match its {len(buf) - off} data bytes")
    if not (np.isfinite([res, ox, oy]).all() and res > 0):
        raise MessageError("occupancy grid with bad resolution or origin")
    cells = np.frombuffer(buf, dtype=np.uint8, offset=off).reshape(rows, cols)
    return OccupancyGrid(cells, res, (ox, oy), stamp_ns, seq)


# the decoder of each binary layout a topic names (``Topic.binary``): the one table every reader uses
DECODERS = {"depth": decode_depth, "grid": decode_grid, "color": decode_color}
