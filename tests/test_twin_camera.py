"""The twin's RGB-D camera: D435 intrinsics, depth error growing with range squared, colour from
the hit geom's material, and per-pixel ground truth of what is traversable."""

from __future__ import annotations

import math

import mujoco
import numpy as np
import pytest

from robot_description import d435
from robot_description import params as rd
from sim_twin import scenarios as sc
from sim_twin.camera import NO_RETURN, NOT_TRAVERSABLE, TRAVERSABLE, CameraModel, RgbdCamera
from sim_twin.model import load_spec


def world(name: str, seed: int = 0):
    scenario = sc.make(name, seed=seed)
    spec = load_spec("outdoor")
    scenario.build(spec)
    model = spec.compile()
    data = mujoco.MjData(model)
    scenario.initialize(model, data, rd.robot_params("outdoor"))
    return scenario, model, data


def test_d435_model_has_the_datasheet_intrinsics() -> None:
    cam = CameraModel.d435(848, 480, 90)
    assert abs(math.degrees(2 * math.atan(cam.width / 2 / cam.fx)) - d435.DEPTH_HFOV_DEG) < 1e-9
    assert cam.depth_rms_per_m2 * 4.0 == float(d435.depth_rms_m(2.0, cam.fx))


# (decimation, error std and mean over the native pixel's RMS): a native mode's error, and the SDK's 2x2
# decimation's, which keeps element 2 of the 4 sorted (its order statistic: std 0.60, mean +0.30 of N(0, 1))
DEPTH_ERRORS = [(1, 1.0, 0.0), (2, 0.60, 0.30)]


@pytest.mark.parametrize("decimation, std_share, mean_share", DEPTH_ERRORS)
def test_flat_floor_depth_error_grows_with_range_squared_and_is_all_traversable(decimation, std_share, mean_share) -> None:
    _, model, data = world("hop-in-place")
    cam = CameraModel.d435(424 * decimation, 240 * decimation, 30, decimation)
    assert (cam.width, cam.height) == (424, 240)
    truth = RgbdCamera(model, cam, sc.Scenario.traversable, noise=False).render(data)
    noisy = [RgbdCamera(model, cam, sc.Scenario.traversable, seed=s).render(data) for s in range(8)]
    ret = truth.labels != NO_RETURN
    assert ret.mean() > 0.5 and (truth.labels[ret] == TRAVERSABLE).all()  # nothing but floor in view
    assert (truth.rgb[ret].astype(int) - truth.rgb[ret].mean(axis=0)).std() > 3  # textured, not flat
    err = np.stack([f.depth - truth.depth for f in noisy])
    both = np.all(np.stack([f.depth for f in noisy]) > 0, axis=0) & ret
    z = truth.depth[both]
    for lo, hi in ((1.0, 1.5), (2.5, 3.5)):
        sel = (z >= lo) & (z < hi)
        zc = z[sel].mean()
        e = err[:, both][:, sel]
        native = cam.depth_rms_per_m2 * zc * zc
        assert 0.8 * std_share * native < float(e.std()) < 1.25 * std_share * native, (lo, float(e.std()), native)
        assert abs(float(e.mean()) - mean_share * native) < 0.1 * native, (lo, float(e.mean()), native)


def test_a_decimated_mode_is_the_native_mode_at_a_coarser_size() -> None:
    native, decimated = CameraModel.d435(848, 480, 30), CameraModel.d435(848, 480, 30, 2)
    assert (decimated.width, decimated.height, decimated.decimation) == (424, 240, 2)
    assert decimated.fx == native.fx / 2 and decimated.depth_rms_per_m2 == native.depth_rms_per_m2
    with pytest.raises(ValueError, match="decimation"):
        CameraModel.d435(848, 480, 30, 3)  # 848 is not a multiple of 3


def test_sidewalk_labels_the_paving_traversable_and_the_grass_and_posts_not() -> None:
    scenario, model, data = world("sidewalk", seed=2)
    cam = CameraModel.d435(424, 240, 30)
    f = RgbdCamera(model, cam, scenario.traversable, noise=False).render(data)
    floor = model.geom("floor").id
    paving = model.geom(sc.TERRAIN_PREFIX + "sidewalk").id
    geom = np.full(cam.width * cam.height, -1, dtype=np.int32)
    dist = np.zeros(cam.width * cam.height)
    rays = RgbdCamera(model, cam, scenario.traversable)._rays
    rot = data.site_xmat[model.site("depth_camera").id].reshape(3, 3) @ np.array(rd.SITE_FROM_OPTICAL)
    mujoco.mj_multiRay(model, data, data.site_xpos[model.site("depth_camera").id].copy(), (rays @ rot.T).reshape(-1),
                       np.array([1, 0, 0, 0, 0, 0], dtype=np.uint8), True, -1, geom, dist, None, len(geom), 100.0)
    geom = geom.reshape(cam.height, cam.width)
    ret = f.labels != NO_RETURN
    assert ((f.labels == TRAVERSABLE) == (ret & (geom == paving))).all()
    assert (f.labels[ret & (geom == floor)] == NOT_TRAVERSABLE).all()
    grass, paved = f.rgb[ret & (geom == floor)].mean(axis=0), f.rgb[ret & (geom == paving)].mean(axis=0)
    assert grass[1] > grass[0] + 20 and grass[1] > grass[2] + 20  # green
    assert abs(paved[0] - paved[1]) < 15 and paved.mean() > grass.mean()  # grey and brighter
    assert f.depth[ret].min() >= 0.2 and f.depth.max() <= 6.0
