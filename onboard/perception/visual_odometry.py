"""Visual odometry from the D435's apex frames (thesis 1.5, 8.2: outdoors the robot estimates its
state without motion capture; issue 27 item 4).

Frame to frame, one frame a hop (the camera service keeps the frame nearest each apex):

1. ORB keypoints in the colour image (aligned to depth), only where the depth is valid, within
   ``vo_min_depth_m``..``vo_max_depth_m`` and not on a depth edge (a keypoint on a silhouette has
   no single depth);
2. matched to the previous frame's by Hamming distance with Lowe's ratio test (``vo_ratio``);
3. the previous frame's keypoints lifted to 3D by its own depth, and ``cv2.solvePnPRansac``
   against this frame's keypoints: the camera's motion between the two frames, refined on the
   inliers by Levenberg-Marquardt (``cv2.solvePnPRefineLM``);
4. with each frame's camera attitude from the estimator (its attitude at the frame's stamp and the
   camera's mount) the camera's displacement in the world, and with each frame's lever (CoM minus
   optical centre, world) the CoM's: ``d_com = R_wc0 c1 + lever1 - lever0``, ``c1`` the second
   camera's centre in the first camera's frame.

Covariance, from the inliers: their reprojection residuals' variance ``s^2`` (``2N - 6`` degrees of
freedom) through the normal matrix of the six pose parameters, ``s^2 (J^T J)^-1`` (``J`` from
``cv2.projectPoints``), carried to ``c1`` by its Jacobian and rotated to the world, times
``vo_cov_scale``. The depth's own error enters the residuals only through parallax, so the scale is
measured, not assumed (``tests/test_visual_odometry.py`` and the report of issue 27).

A pair is refused, counted by reason (:data:`REASONS`), when the input is malformed or not finite,
the frames are not a pair in time, there are too few keypoints, matches or inliers, the inliers
crowd one corner of the image, the frames' rotation disagrees with the attitude's, the motion is
faster than the robot moves, or the covariance is too large to be worth fusing.

Pure: numpy and OpenCV, no I/O, no clocks (OpenCV's RANSAC draws from its own fixed seed, so a
pair gives the same answer every time).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from onboard.contracts.messages import VisualOdometryDelta
from onboard.contracts.params import EstimatorParams
from onboard.geometry.quaternion import to_matrix

NS = 1_000_000_000
EDGE_REL = 0.05  # a pixel whose neighbourhood spans more than this share of its depth is on an edge
SMOOTH_PX = 5  # [px] the median filter's window on the depth
RANSAC_CONFIDENCE = 0.999
REASONS = ("bad_input", "nonfinite", "bad_interval", "too_few_features", "too_few_matches", "too_few_inliers",
           "pnp_failed", "bad_geometry", "rotation_mismatch", "implausible", "uncertain")


@dataclass(frozen=True)
class VoFrame:
    """One camera frame and where the estimator says the camera was when it was captured."""

    stamp_ns: int  # capture time on the stack's clock [ns]
    rgb: np.ndarray  # (h, w, 3) uint8, aligned to ``depth``
    depth: np.ndarray  # (h, w) [m], 0: no return
    fx: float  # intrinsics [px]; pixel [i, j]'s centre at (j + 0.5, i + 0.5)
    fy: float
    cx: float
    cy: float
    cam_quat: tuple[float, float, float, float]  # optical -> world [w, x, y, z], from the estimate's attitude and the mount
    com_from_cam: tuple[float, float, float]  # CoM minus the optical centre [m, world], from the estimate's attitude


@dataclass
class _Features:
    stamp_ns: int
    pixels: np.ndarray  # (n, 2) float32, OpenCV's pixel convention (centre of pixel [0, 0] at (0, 0))
    descriptors: np.ndarray  # (n, 32) uint8
    points: np.ndarray  # (n, 3) camera frame [m]
    r_wc: np.ndarray  # optical -> world
    lever: np.ndarray  # CoM - optical centre [m, world]
    k: np.ndarray  # camera matrix in OpenCV's pixel convention
    size: tuple[int, int]  # (w, h)


class VisualOdometry:
    """Frame-to-frame visual odometry; :meth:`step` one apex frame at a time."""

    def __init__(self, p: EstimatorParams) -> None:
        if not p.vo_min_depth_m < p.vo_max_depth_m:
            raise ValueError("estimator.vo_min_depth_m must be below vo_max_depth_m")
        self.p = p
        self._orb = cv2.ORB_create(nfeatures=p.vo_features)
        self._matcher = cv2.BFMatcher(cv2.NORM_HAMMING)
        self._prev: _Features | None = None
        self.used = 0  # pairs that gave a displacement
        self.rejections: dict[str, int] = {}  # refused pairs (or frames) by reason
        self.last_reason = ""

    def step(self, frame: VoFrame) -> VisualOdometryDelta | None:
        """This frame against the previous one: the CoM's displacement between them, or None (the
        first frame, or a refusal counted in :attr:`rejections`, its reason in :attr:`last_reason`).
        A malformed frame is dropped and the previous one kept, so the next pair spans it."""
        feats = self._features(frame)
        if isinstance(feats, str):
            return self._reject(feats)
        prev, self._prev = self._prev, feats
        if prev is None:
            return None
        out = relative_motion(prev, feats, self._matcher, self.p)
        if isinstance(out, str):
            return self._reject(out)
        self.used += 1
        self.last_reason = ""
        return out

    def _reject(self, reason: str) -> None:
        self.rejections[reason] = self.rejections.get(reason, 0) + 1
        self.last_reason = reason
        return None

    def _features(self, f: VoFrame) -> _Features | str:
        p = self.p
        rgb, depth = f.rgb, f.depth
        if (not isinstance(rgb, np.ndarray) or not isinstance(depth, np.ndarray) or rgb.ndim != 3 or rgb.shape[2] != 3
                or rgb.dtype != np.uint8 or depth.ndim != 2 or depth.shape != rgb.shape[:2] or min(depth.shape) < 16):
            return "bad_input"
        intr = (f.fx, f.fy, f.cx, f.cy)
        q = np.asarray(f.cam_quat, dtype=float)
        lever = np.asarray(f.com_from_cam, dtype=float)
        if (not all(math.isfinite(v) for v in intr) or q.shape != (4,) or lever.shape != (3,)
                or not np.all(np.isfinite(q)) or not np.all(np.isfinite(lever))):
            return "nonfinite"
        n = float(np.linalg.norm(q))
        if f.fx <= 0.0 or f.fy <= 0.0 or abs(n - 1.0) > 0.1:
            return "bad_input"
        d = np.where(np.isfinite(depth), depth, 0.0).astype(np.float32)
        # the depth's own noise, filtered over a window as the SDK's spatial filter does (a median keeps
        # edges): noisy depth would shrink the PnP's translation (errors in the variables)
        d = cv2.medianBlur(d, SMOOTH_PX)
        kernel = np.ones((3, 3), np.uint8)
        span = cv2.dilate(d, kernel) - cv2.erode(d, kernel)
        usable = (d >= p.vo_min_depth_m) & (d <= p.vo_max_depth_m) & (span <= EDGE_REL * d)
        gray = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)
        keypoints, descriptors = self._orb.detectAndCompute(gray, usable.astype(np.uint8) * 255)
        if descriptors is None or len(keypoints) < p.vo_min_inliers:
            return "too_few_features"
        pix = np.array([kp.pt for kp in keypoints], dtype=np.float32)
        cols = np.clip(np.rint(pix[:, 0]).astype(int), 0, d.shape[1] - 1)
        rows = np.clip(np.rint(pix[:, 1]).astype(int), 0, d.shape[0] - 1)
        z = d[rows, cols].astype(float)
        ok = usable[rows, cols]
        # OpenCV puts pixel [0, 0]'s centre at (0, 0); the camera model at (0.5, 0.5)
        cx, cy = f.cx - 0.5, f.cy - 0.5
        pts = np.stack([(pix[:, 0] - cx) / f.fx * z, (pix[:, 1] - cy) / f.fy * z, z], axis=1)
        pts[~ok] = np.nan  # no depth at this keypoint: usable as the second frame's, not the first's
        k = np.array([[f.fx, 0.0, cx], [0.0, f.fy, cy], [0.0, 0.0, 1.0]])
        return _Features(f.stamp_ns, pix, descriptors, pts, np.array(to_matrix(q / n)), lever, k,
                         (d.shape[1], d.shape[0]))


def relative_motion(a: _Features, b: _Features, matcher: cv2.DescriptorMatcher, p: EstimatorParams) -> VisualOdometryDelta | str:
    """The CoM's displacement from frame ``a`` to frame ``b`` with its covariance, or the reason it
    is refused."""
    dt = (b.stamp_ns - a.stamp_ns) / NS
    if not 0.0 < dt <= p.vo_max_interval_s:
        return "bad_interval"
    pairs = matcher.knnMatch(a.descriptors, b.descriptors, k=2)
    ia, ib = [], []
    for pair in pairs:
        if len(pair) == 2 and pair[0].distance < p.vo_ratio * pair[1].distance:
            if np.isfinite(a.points[pair[0].queryIdx, 2]):
                ia.append(pair[0].queryIdx)
                ib.append(pair[0].trainIdx)
    if len(ia) < p.vo_min_inliers:
        return "too_few_matches"
    obj = a.points[ia]
    img = b.pixels[ib].astype(float)
    ok, rvec, tvec, inliers = cv2.solvePnPRansac(obj, img, b.k, None, iterationsCount=p.vo_ransac_iterations,
                                                 reprojectionError=p.vo_reprojection_px, confidence=RANSAC_CONFIDENCE,
                                                 flags=cv2.SOLVEPNP_SQPNP)
    if not ok or inliers is None:
        return "pnp_failed"
    if len(inliers) < p.vo_min_inliers:
        return "too_few_inliers"
    idx = inliers[:, 0]
    obj, img = obj[idx], img[idx]
    rvec, tvec = cv2.solvePnPRefineLM(obj, img, b.k, None, rvec, tvec)
    if not (np.all(np.isfinite(rvec)) and np.all(np.isfinite(tvec))):
        return "pnp_failed"
    w, h = b.size
    box = np.ptp(img[:, 0]) * np.ptp(img[:, 1])
    if box < p.vo_min_spread * w * h:
        return "bad_geometry"
    r_ba, _ = cv2.Rodrigues(rvec)  # camera a -> camera b: x_b = r_ba x_a + t
    expected = b.r_wc.T @ a.r_wc
    mismatch, _ = cv2.Rodrigues(r_ba @ expected.T)
    if float(np.linalg.norm(mismatch)) > p.vo_max_rotation_error_rad:
        return "rotation_mismatch"
    proj, jac = cv2.projectPoints(obj, rvec, tvec, b.k, None)
    res = proj.reshape(-1, 2) - img
    j = jac[:, :6]  # d(pixels) / d(rvec, tvec)
    dof = max(2 * len(idx) - 6, 1)
    s2 = float(np.sum(res * res)) / dof
    normal = j.T @ j
    if not np.isfinite(s2) or np.linalg.cond(normal) > 1e12:
        return "bad_geometry"
    cov6 = s2 * np.linalg.inv(normal)
    t = tvec.reshape(3)
    c = -r_ba.T @ t  # camera b's centre in camera a's frame
    jc = np.zeros((3, 6))
    jc[:, 3:] = -r_ba.T
    eps = 1e-6
    for i in range(3):
        dr = rvec.reshape(3).copy()
        dr[i] += eps
        ri, _ = cv2.Rodrigues(dr)
        jc[:, i] = (-ri.T @ t - c) / eps
    cov_c = jc @ cov6 @ jc.T
    disp = a.r_wc @ c + b.lever - a.lever
    cov = p.vo_cov_scale * (a.r_wc @ cov_c @ a.r_wc.T)
    cov = 0.5 * (cov + cov.T)
    if not (np.all(np.isfinite(disp)) and np.all(np.isfinite(cov))):
        return "nonfinite"
    if float(np.linalg.norm(disp)) > p.vo_max_speed_m_s * dt:
        return "implausible"
    if math.sqrt(max(float(np.max(np.linalg.eigvalsh(cov[:2, :2]))), 0.0)) > p.vo_max_std_m:
        return "uncertain"
    return VisualOdometryDelta(stamp_ns=b.stamp_ns, from_stamp_ns=a.stamp_ns, displacement=[float(v) for v in disp],
                               cov=[float(v) for v in cov.reshape(-1)], inliers=int(len(idx)))
