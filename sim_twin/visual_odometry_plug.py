"""Visual odometry in lockstep: the twin's D435 at each apex, through the robot's own visual
odometry (:mod:`onboard.perception.visual_odometry`), into the estimator with its latency.

As the camera service does on the robot: one frame a hop, the one at the apex, at the published
size (the D435's depth mode over the SDK's decimation), placed by the estimate (its attitude and
the MJCF's camera mount), never by the truth. The same frame, depth and colour, is what a
perceiving planner fuses (:meth:`ApexVisualOdometry.on_apex` returns it), as the perception
service fuses the camera service's. The displacement reaches the estimator
``TwinParams.vo_latency_s`` after the frame's capture, stamped with the two frames' capture times.

Beside the counts (pairs used, refused by reason, fused or gated by the estimator) the report
holds what only the twin can say: each used pair's error against the true CoM displacement
(horizontal RMS) and its normalized squared error against the claimed covariance (2 dof, mean 2
when the covariance is honest). The same frames score the robot's terrain segmenter (``[perception]
segmenter``, at its ``pixel_stride``: up to ~0.1 s a frame at stride 1, so only the one the robot runs) against the twin's labels: the IoU of the
traversable class over the run's apex views, placed by the estimate.
"""

from __future__ import annotations

from collections import deque

import mujoco
import numpy as np

from onboard.contracts import messages as m
from onboard.contracts.binary_messages import ColorImage, DepthImage
from onboard.contracts.params import CameraParams, EstimatorParams, PerceptionParams, TwinParams
from onboard.geometry import quaternion as quat
from onboard.perception.visual_odometry import VisualOdometry, VoFrame
from robot_description import params as rd
from sim_twin.camera import CameraModel, RgbdCamera
from sim_twin.terrain_eval import SEGMENTERS, Score, score_frame

SEED_SALT = 27_000  # the camera's noise drawn apart from the other sensors'


class ApexVisualOdometry:
    """The twin's camera at each apex -> visual odometry -> the estimator, late by the latency."""

    def __init__(self, model: mujoco.MjModel, traversable: tuple[str, ...] | list[str], variant: str,
                 est: EstimatorParams, twin: TwinParams, seed: int, camera: CameraParams | None = None,
                 perception: PerceptionParams | None = None) -> None:
        cp = camera or CameraParams()
        self.cam = CameraModel.d435(cp.width, cp.height, cp.fps, cp.decimation)
        self.camera = RgbdCamera(model, self.cam, list(traversable), seed=seed + SEED_SALT, noise=twin.noise)
        self.mount = rd.camera_mount(variant)
        self.vo = VisualOdometry(est)
        self.latency_ns = int(round(twin.vo_latency_s * 1e9))
        self._queue: deque[tuple[int, m.VisualOdometryDelta]] = deque()
        self._truth: dict[int, tuple[np.ndarray, np.ndarray]] = {}  # true and estimated CoM at each frame's stamp
        self.frames = 0
        self.delivered = 0
        self.fused = 0
        self._errors: list[tuple[float, float]] = []
        self._nees: list[float] = []
        self._est_errors: list[tuple[float, float]] = []
        pp = perception or PerceptionParams()
        self.segmenter_name = pp.segmenter
        self.segmenter = SEGMENTERS[pp.segmenter](pp)
        self.segmentation = Score()

    def on_apex(self, now_ns: int, data: mujoco.MjData, state: m.StateEstimate,
                true_com: list[float]) -> tuple[DepthImage, ColorImage] | None:
        """Render the frame at this apex, place it by the estimate, and run the VO on it; the frame
        (None: no estimate could place it)."""
        if not state.attitude_valid:
            return None  # nothing can place the frame (the camera service refuses it too)
        frame = self.camera.render(data)
        self.frames += 1
        q = quat.normalize(state.quat)
        cam_quat = quat.normalize(quat.mul(q, self.mount.quat))
        lever = quat.rotate(q, [-v for v in self.mount.pos_from_com])
        vf = VoFrame(now_ns, frame.rgb, frame.depth, self.cam.fx, self.cam.fy, self.cam.cx, self.cam.cy,
                     (cam_quat[0], cam_quat[1], cam_quat[2], cam_quat[3]), (lever[0], lever[1], lever[2]))
        cam_pos = [p - v for p, v in zip(state.position, lever)]  # the optical centre where the estimate puts it
        intrinsics = (self.cam.fx, self.cam.fy, self.cam.cx, self.cam.cy)
        img = DepthImage(frame.depth, *intrinsics, np.array(cam_pos), np.array(cam_quat), now_ns, self.frames)
        rgb = ColorImage(frame.rgb, *intrinsics, img.cam_pos, img.cam_quat, now_ns, self.frames)
        score_frame(self.segmenter, img, frame, (state.position[0], state.position[1]), self.segmentation)
        self._truth[now_ns] = (np.array(true_com[:2], dtype=float), np.array(state.position[:2], dtype=float))
        delta = self.vo.step(vf)
        if delta is not None:
            self._track(now_ns, delta)
        return img, rgb

    def _track(self, now_ns: int, delta: m.VisualOdometryDelta) -> None:
        """Queue the displacement for the estimator; its error against the truth's."""
        self._queue.append((now_ns + self.latency_ns, delta))
        first = self._truth.get(delta.from_stamp_ns)
        if first is not None:
            true_d = self._truth[now_ns][0] - first[0]
            err = np.array(delta.displacement[:2]) - true_d
            cov = np.array(delta.cov).reshape(3, 3)[:2, :2]
            self._errors.append((float(err[0]), float(err[1])))
            self._nees.append(float(err @ np.linalg.solve(cov, err)))
            est = self._truth[now_ns][1] - first[1] - true_d  # the estimate's own over the same pair
            self._est_errors.append((float(est[0]), float(est[1])))
        for stamp in [s for s in self._truth if s < delta.from_stamp_ns]:
            del self._truth[stamp]

    def due(self, now_ns: int) -> list[m.VisualOdometryDelta]:
        """The displacements whose latency has passed by ``now_ns``, oldest first."""
        out = []
        while self._queue and self._queue[0][0] <= now_ns:
            out.append(self._queue.popleft()[1])
        self.delivered += len(out)
        return out

    def report(self, counters: dict[str, int]) -> dict:
        """Counts, the estimator's verdicts, and the pairs' errors against the truth."""
        errs = np.array(self._errors).reshape(-1, 2)
        est = np.array(self._est_errors).reshape(-1, 2)
        return {
            "frames": self.frames,
            "used": self.vo.used,
            "rejected": dict(sorted(self.vo.rejections.items())),
            "delivered": self.delivered,
            "fused": counters.get("vo_fused", 0),
            "gated": counters.get("vo_outliers", 0),
            "error_xy_rms_m": _rms(errs),  # the VO's displacement against the truth's, per pair
            "error_xy_mean_m": [round(float(v), 5) for v in errs.mean(axis=0)] if len(errs) else None,
            "estimate_error_xy_mean_m": [round(float(v), 5) for v in est.mean(axis=0)] if len(est) else None,
            # the estimate's displacement over the same pairs (odometry alone when the VO is not fused)
            "estimate_error_xy_rms_m": _rms(est),
            "estimate_error_axis_std_m": round(float(np.std(est)), 5) if len(est) > 1 else None,
            "nees_xy_mean": round(float(np.mean(self._nees)), 3) if self._nees else None,
        }

    def segmentation_report(self) -> dict:
        """The segmenter's IoU of the traversable class over the run's apex views (and the pixel
        counts, so that runs can be pooled)."""
        s = self.segmentation
        return {"segmenter": self.segmenter_name, "iou": round(s.iou, 4), "views": s.views, "intersection": s.intersection,
                "union": s.union}


def _rms(e: np.ndarray) -> float | None:
    """Root mean square of the rows' norms, or None without rows."""
    return round(float(np.sqrt(np.mean(np.sum(e * e, axis=1)))), 5) if len(e) else None
