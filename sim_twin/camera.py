"""The twin's RGB-D camera: depth and colour of a D435 by ray casting, with per-pixel ground truth.

One ray per pixel from the MJCF site ``depth_camera`` (``mujoco.mj_multiRay`` against world
geoms, group 0, as :class:`sim_twin.sensors.SensorSuite`'s depth), at the D435's intrinsics
(:mod:`robot_description.d435`). Per pixel:

- depth: the z-distance with the D435's error (RMS growing with range squared,
  :func:`robot_description.d435.depth_rms_m`, at the focal length the stereo matching ran at),
  quantised to its depth unit (1 mm); no return below ``MIN_RANGE_M`` or beyond the maximum
  range (0). A mode drawn after the SDK's decimation filter (:attr:`CameraModel.decimation`) has
  the filter's noise: the median the SDK picks (element ``d*d // 2`` of each ``d x d`` block,
  sorted) of that many native pixels' errors. One ray per output pixel: the block's pixels are
  taken to see the same surface (at a silhouette the SDK's median picks one side or the other);
- colour: the hit geom's material colour (its material's rgba, else its own), a texture (a
  seeded value per 4 cm cell of the hit point, so grass, pavement and bark are not flat
  colours), lit by a sun (Lambert, with ambient light) and exposed as an auto-exposure would
  (the frame's mean brought to a target, jittered per frame), with read noise; sky where
  nothing is hit;
- label: ground truth, ``TRAVERSABLE`` where the hit geom is one the scenario calls
  traversable (:attr:`sim_twin.scenarios.Scenario.traversable`), ``NOT_TRAVERSABLE``
  elsewhere, ``NO_RETURN`` where the depth has none.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import mujoco
import numpy as np

from robot_description import d435
from robot_description.params import DEPTH_CAMERA_SITE, SITE_FROM_OPTICAL

NOT_TRAVERSABLE = 0
TRAVERSABLE = 1
NO_RETURN = 255
MIN_RANGE_M = 0.2  # [m] the D435's minimum depth at 848x480 is ~0.2 m (datasheet "min-Z")
MAX_RANGE_M = 6.0  # [m] beyond, no return (outdoor stereo on ground texture)
SKY_RGB = (0.62, 0.75, 0.95)
SUN_DIR = (0.35, 0.2, 0.915)  # towards the sun, world (unit): high, slightly behind +x
AMBIENT = 0.35  # share of light that is not the sun's direct light
TEXTURE_CELL_M = 0.04
TEXTURE_AMPLITUDE = 0.18  # albedo varies by this fraction, cell to cell
EXPOSURE_TARGET = 0.45  # mean of the exposed image, full scale 1
EXPOSURE_JITTER = 0.08  # per-frame relative error of the auto exposure
READ_NOISE = 2.0 / 255.0  # std of the colour noise, full scale 1
_GROUPS = np.array([1, 0, 0, 0, 0, 0], dtype=np.uint8)  # world geoms only


@dataclass(frozen=True)
class CameraModel:
    width: int
    height: int
    fx: float  # [px]
    fy: float
    cx: float
    cy: float
    depth_rms_per_m2: float  # depth RMS error of one native (undecimated) pixel = this * z^2 [1/m]
    decimation: int = 1  # the SDK's decimation filter between the sensor and this size (1: a native mode)

    @staticmethod
    def d435(width: int = 848, height: int = 480, fps: int = 30, decimation: int = 1) -> "CameraModel":
        """The D435's depth stream in one of its modes (square pixels at the datasheet's horizontal field of
        view), drawn after the SDK's decimation by ``decimation`` (the size and focal length divided by it,
        the noise the filter's median leaves of the mode's)."""
        d435.check_mode("depth", width, height, fps)
        if not 1 <= decimation <= d435.MAX_DECIMATION or width % decimation or height % decimation:
            raise ValueError(f"decimation {decimation} does not divide the {width}x{height} mode within 1..{d435.MAX_DECIMATION}")
        fx, _ = d435.nominal_focal_px(width, height, d435.DEPTH_HFOV_DEG, d435.DEPTH_VFOV_DEG)
        w, h, f = width // decimation, height // decimation, fx / decimation
        return CameraModel(w, h, f, f, 0.5 * w, 0.5 * h, float(d435.depth_rms_m(1.0, fx)), decimation)


@dataclass
class RgbdFrame:
    depth: np.ndarray  # (h, w) float32 [m], 0 = no return
    rgb: np.ndarray  # (h, w, 3) uint8
    labels: np.ndarray  # (h, w) uint8: TRAVERSABLE, NOT_TRAVERSABLE, NO_RETURN
    cam_pos: np.ndarray  # optical centre, world [m]
    cam_quat: np.ndarray  # optical -> world [w, x, y, z]


def _cell_hash(cells: np.ndarray, salt: np.ndarray) -> np.ndarray:
    """A value in [-1, 1) per integer cell ``(..., 3)`` and salt: a fixed texture, the same every frame."""
    h = (cells[..., 0] * 73856093) ^ (cells[..., 1] * 19349663) ^ (cells[..., 2] * 83492791) ^ (salt * 2654435761)
    h = (h ^ (h >> 13)) * 1274126177
    h = h ^ (h >> 16)
    return (h & 0xFFFF).astype(np.float64) / 32768.0 - 1.0


class RgbdCamera:
    """Renders :class:`RgbdFrame` from the physics; noise from its own seeded generator."""

    def __init__(self, model: mujoco.MjModel, cam: CameraModel, traversable: Sequence[str], seed: int = 0,
                 noise: bool = True) -> None:
        self.model = model
        self.cam = cam
        self.noise = noise
        self.rng = np.random.default_rng(seed)
        u, v = np.meshgrid(np.arange(cam.width) + 0.5, np.arange(cam.height) + 0.5)
        rays = np.stack([(u - cam.cx) / cam.fx, (v - cam.cy) / cam.fy, np.ones_like(u)], axis=-1).reshape(-1, 3)
        self._ray_z = 1.0 / np.linalg.norm(rays, axis=1)
        self._rays = rays * self._ray_z[:, None]
        self._site = int(model.site(DEPTH_CAMERA_SITE).id)
        n = cam.width * cam.height
        self._geom = np.zeros(n, dtype=np.int32)
        self._dist = np.zeros(n)
        self._normal = np.zeros(3 * n)
        # per geom: albedo (material rgba, else geom rgba) and whether it is traversable ground
        albedo = model.geom_rgba[:, :3].copy()
        has_mat = model.geom_matid >= 0
        albedo[has_mat] = model.mat_rgba[model.geom_matid[has_mat], :3]
        self._albedo = albedo
        names = [model.geom(i).name for i in range(model.ngeom)]
        self._traversable = np.array([any(nm == t or (t.endswith("_") and nm.startswith(t)) for t in traversable)
                                      for nm in names], dtype=bool)
        self._sun = np.array(SUN_DIR) / np.linalg.norm(SUN_DIR)

    def _depth_error(self, n: int) -> np.ndarray:
        """Standardized depth errors of ``n`` output pixels: one native pixel's, or the decimation's median."""
        d = self.cam.decimation
        if d == 1:
            return self.rng.standard_normal(n)
        block = self.rng.standard_normal((n, d * d))
        return np.partition(block, d * d // 2, axis=1)[:, d * d // 2]

    def render(self, data: mujoco.MjData) -> RgbdFrame:
        """One frame from the camera site's pose in ``data`` (last forward pass)."""
        cam, n = self.cam, self.cam.width * self.cam.height
        pos = data.site_xpos[self._site].copy()
        rot = data.site_xmat[self._site].reshape(3, 3) @ np.array(SITE_FROM_OPTICAL)
        vec = self._rays @ rot.T
        mujoco.mj_multiRay(self.model, data, pos, vec.reshape(-1), _GROUPS, True, -1, self._geom, self._dist,
                           self._normal, n, MAX_RANGE_M / float(self._ray_z.min()))
        dist, geom = self._dist, self._geom
        z = dist * self._ray_z
        hit = (dist >= 0.0) & (geom >= 0)
        if self.noise:
            z = z + cam.depth_rms_per_m2 * z * z * self._depth_error(n)
        ret = hit & (z >= MIN_RANGE_M) & (z <= MAX_RANGE_M)
        depth = np.where(ret, np.rint(z / d435.DEPTH_UNITS_M) * d435.DEPTH_UNITS_M, 0.0)
        g = np.where(hit, geom, 0)
        # colour: albedo x texture x light, then auto exposure and read noise
        points = pos + vec * np.where(hit, dist, 0.0)[:, None]
        cells = np.floor(points / TEXTURE_CELL_M).astype(np.int64)
        texture = 1.0 + TEXTURE_AMPLITUDE * _cell_hash(cells, g.astype(np.int64))
        normals = self._normal.reshape(-1, 3)
        light = AMBIENT + (1.0 - AMBIENT) * np.clip(normals @ self._sun, 0.0, 1.0)
        radiance = self._albedo[g] * (texture * light)[:, None]
        radiance[~hit] = SKY_RGB
        gain = EXPOSURE_TARGET / max(float(radiance.mean()), 1e-6)
        if self.noise:
            gain *= 1.0 + EXPOSURE_JITTER * float(self.rng.standard_normal())
            radiance = radiance * gain + READ_NOISE * self.rng.standard_normal(radiance.shape)
        else:
            radiance = radiance * gain
        rgb = np.clip(np.rint(radiance * 255.0), 0, 255).astype(np.uint8)
        labels = np.where(self._traversable[g], TRAVERSABLE, NOT_TRAVERSABLE).astype(np.uint8)
        labels[~ret] = NO_RETURN
        quat = np.zeros(4)
        mujoco.mju_mat2Quat(quat, rot.reshape(-1))
        shape = (cam.height, cam.width)
        return RgbdFrame(depth.astype(np.float32).reshape(shape), rgb.reshape(*shape, 3), labels.reshape(shape), pos, quat)
