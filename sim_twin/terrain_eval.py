"""Terrain segmentation scored against the twin's ground truth: IoU of the traversable class.

Views are taken as the robot would take them: along the scenario's reference, in order, at
apex height, heading along the way (with a random yaw, tilt and offset to the side), each
rendered by :class:`sim_twin.camera.RgbdCamera` at a D435 mode; a segmenter sees the view's
organized cloud and colour (:class:`onboard.perception.segmentation.Cloud`), and its
``TRAVERSABLE`` pixels are compared with the twin's labels over the pixels with a return.

    python -m sim_twin.terrain_eval --scenario sidewalk --seeds 20 --views 15
"""

from __future__ import annotations

import argparse
import json
import math
import time
from collections.abc import Callable
from dataclasses import dataclass

import mujoco
import numpy as np

from onboard.contracts.binary_messages import DepthImage
from onboard.contracts.params import PerceptionParams
from onboard.perception.pointcloud import depth_to_points
from onboard.perception.segmentation import TRAVERSABLE, Cloud, GeometricSegmenter, Segmenter
from onboard.perception.terrain import ColorTerrainSegmenter
from robot_description import params as rd
from sim_twin import scenarios as sc
from sim_twin.camera import TRAVERSABLE as TRUE_TRAVERSABLE
from sim_twin.camera import CameraModel, RgbdCamera, RgbdFrame
from sim_twin.model import load_spec

APEX_RISE_M = 0.12  # [m] foot above the ground at apex (a hop of the outdoor robot)
YAW_STD = 0.35  # [rad] heading off the way
TILT_STD = 0.04  # [rad] roll and pitch at apex
SIDE_STD = 0.15  # [m] offset across the way
CLEARANCE_M = 0.3  # [m] views are not taken inside or against an obstacle

SEGMENTERS: dict[str, Callable[[PerceptionParams], Segmenter]] = {
    "color": ColorTerrainSegmenter,
    "geometric": GeometricSegmenter,
}


@dataclass
class Score:
    intersection: int = 0
    union: int = 0
    views: int = 0

    @property
    def iou(self) -> float:
        return self.intersection / self.union if self.union else 1.0


def _quat(roll: float, pitch: float, yaw: float) -> list[float]:
    cr, sr, cp, sp, cy, sy = (math.cos(roll / 2), math.sin(roll / 2), math.cos(pitch / 2), math.sin(pitch / 2),
                              math.cos(yaw / 2), math.sin(yaw / 2))
    return [cr * cp * cy + sr * sp * sy, sr * cp * cy - cr * sp * sy, cr * sp * cy + sr * cp * sy, cr * cp * sy - sr * sp * cy]


def _clear(scenario: sc.Scenario, xy: tuple[float, float]) -> bool:
    for ob in scenario.obstacles:
        p = ob.polytope()
        if np.max(np.array(p.A) @ np.array(xy) - np.array(p.b)) < CLEARANCE_M:
            return False
    return True


def score_seed(scenario_name: str, seed: int, views: int, segmenters: dict[str, Segmenter],
               cam: CameraModel) -> dict[str, Score]:
    """Each segmenter's score over ``views`` views of one seeded world, in the order of the way."""
    scenario = sc.make(scenario_name, seed=seed)
    spec = load_spec("outdoor")
    scenario.build(spec)
    model = spec.compile()
    data = mujoco.MjData(model)
    robot = rd.robot_params("outdoor")
    scenario.initialize(model, data, robot)
    camera = RgbdCamera(model, cam, scenario.traversable, seed=seed)
    rng = np.random.default_rng(seed + 10_000)
    ref = scenario.reference().segments
    t_end = ref[-1].t0 + ref[-1].duration
    scores = {name: Score() for name in segmenters}
    adr = int(model.joint(rd.ROOT_JOINT).qposadr[0])
    taken = 0
    for t in np.linspace(0.0, t_end, views * 4):
        if taken >= views:
            break
        x, y = sc.sample_reference(ref, float(t))
        x2, y2 = sc.sample_reference(ref, float(t) + 0.5)
        heading = math.atan2(y2 - y, x2 - x) if math.hypot(x2 - x, y2 - y) > 1e-6 else 0.0
        side = float(rng.normal(0.0, SIDE_STD))
        xy = (x - side * math.sin(heading), y + side * math.cos(heading))
        if not _clear(scenario, xy):
            continue
        data.qpos[adr:adr + 3] = [xy[0], xy[1], scenario.start_ground + robot.leg_length + APEX_RISE_M]
        data.qpos[adr + 3:adr + 7] = _quat(*rng.normal(0.0, TILT_STD, 2), heading + float(rng.normal(0.0, YAW_STD)))
        mujoco.mj_forward(model, data)
        frame = camera.render(data)
        img = DepthImage(frame.depth, cam.fx, cam.fy, cam.cx, cam.cy, frame.cam_pos, frame.cam_quat)
        taken += 1
        for name, seg in segmenters.items():
            score_frame(seg, img, frame, xy, scores[name])
    return scores


def score_frame(seg: Segmenter, img: DepthImage, frame: RgbdFrame, robot_xy: tuple[float, float], score: Score) -> None:
    """Add one view to ``score``: ``seg`` on the depth image ``img`` (placed where the robot believes
    the camera is) and the frame's colour, against the frame's true labels, over the pixels with a
    return (the segmenter's own stride)."""
    sp: PerceptionParams = seg.params  # type: ignore[attr-defined]
    k = sp.pixel_stride
    pts, valid = depth_to_points(img, sp.max_range_m, k)
    labels = seg.segment(Cloud(pts, valid, np.asarray(img.cam_pos, dtype=float), frame.rgb[::k, ::k], np.array(robot_xy, dtype=float)))
    s = (labels == TRAVERSABLE) & valid
    t_ = (frame.labels[::k, ::k] == TRUE_TRAVERSABLE) & valid
    score.intersection += int((s & t_).sum())
    score.union += int((s | t_).sum())
    score.views += 1


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenario", default="sidewalk", choices=sorted(sc.SCENARIOS))
    ap.add_argument("--seeds", type=int, default=10)
    ap.add_argument("--first-seed", type=int, default=0)
    ap.add_argument("--views", type=int, default=15, help="views per seed")
    ap.add_argument("--width", type=int, default=424, help="the frames' size, after the decimation")
    ap.add_argument("--height", type=int, default=240)
    ap.add_argument("--decimation", type=int, default=2, help="the SDK's decimation the frames come out of (1: a native mode)")
    ap.add_argument("--stride", type=int, default=4, help="perception.pixel_stride: every n-th pixel (as on the robot)")
    args = ap.parse_args(argv)
    cam = CameraModel.d435(args.width * args.decimation, args.height * args.decimation, 30, args.decimation)
    totals = {name: Score() for name in SEGMENTERS}
    per_seed: dict[str, list[float]] = {name: [] for name in SEGMENTERS}
    t0 = time.perf_counter()
    for seed in range(args.first_seed, args.first_seed + args.seeds):
        params = PerceptionParams(seed=seed, pixel_stride=args.stride)
        got = score_seed(args.scenario, seed, args.views, {n: make(params) for n, make in SEGMENTERS.items()}, cam)
        for name, s in got.items():
            totals[name].intersection += s.intersection
            totals[name].union += s.union
            totals[name].views += s.views
            per_seed[name].append(s.iou)
    out = {"scenario": args.scenario, "seeds": args.seeds, "views_per_seed": args.views,
           "resolution": [args.width, args.height], "wall_s": round(time.perf_counter() - t0, 1)}
    for name, s in totals.items():
        out[name] = {"iou": round(s.iou, 4), "views": s.views, "iou_per_seed_min": round(min(per_seed[name]), 4),
                     "iou_per_seed_median": round(float(np.median(per_seed[name])), 4)}
    print(json.dumps(out))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
