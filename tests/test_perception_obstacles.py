"""Obstacle mode: convex obstacles that contain every occupied cell square."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from onboard.contracts.params import PerceptionParams
from onboard.perception import maps
from onboard.perception.obstacles import obstacles_from_mask

PARAMS = PerceptionParams()


def _cells_not_inside(obstacles, occ: np.ndarray, res: float, origin: tuple[float, float]) -> int:
    """Occupied cells whose square (all four corners) lies in no single obstacle."""
    rr, cc = np.nonzero(occ)
    x0 = origin[0] + cc * res
    y0 = origin[1] + rr * res
    inside = np.zeros(len(rr), dtype=bool)
    for p in obstacles:
        ok = np.ones(len(rr), dtype=bool)
        for dx in (0.0, res):
            for dy in (0.0, res):
                ok &= p.contains(np.column_stack([x0 + dx, y0 + dy]), tol=1e-9)
        inside |= ok
    return int((~inside).sum())


def _convex_consistent(p) -> None:
    slack = p.b[:, None] - p.A @ p.vertices.T
    assert slack.min() > -1e-9
    assert p.area > 0
    v = p.vertices
    e1 = np.roll(v, -1, axis=0) - v
    e2 = np.roll(v, -2, axis=0) - np.roll(v, -1, axis=0)
    assert np.all(e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0] > 0)  # strictly convex, CCW


@pytest.mark.parametrize("method", ["hull", "rect"])
@pytest.mark.parametrize("kind", ["rooms", "corridors", "clutter"])
def test_every_occupied_cell_is_inside_an_obstacle(kind, method):
    tm = maps.BUILDERS[kind](seed=2)
    params = dataclasses.replace(PARAMS, obstacle_method=method)
    res, origin = 0.05, (-5.0, -5.0)
    obstacles = obstacles_from_mask(tm.occupied, res, origin, params)
    assert obstacles
    for p in obstacles:
        _convex_consistent(p)
        if method == "rect":
            assert len(p.vertices) == 4
    assert _cells_not_inside(obstacles, tm.occupied, res, origin) == 0


def test_separate_blobs_are_separate_obstacles_and_tight():
    occ = np.zeros((30, 30), dtype=bool)
    occ[5:8, 5:10] = True  # a 5 x 3 box
    occ[20:25, 20:22] = True
    obstacles = obstacles_from_mask(occ, 0.1, (0.0, 0.0), PARAMS)
    assert len(obstacles) == 2
    boxes = sorted(p.bbox() for p in obstacles)
    assert np.allclose(boxes[0], (0.5, 0.5, 1.0, 0.8))
    assert np.allclose(boxes[1], (2.0, 2.0, 2.2, 2.5))
    assert sorted(round(p.area, 9) for p in obstacles) == [0.1, 0.15]


def test_l_shaped_wall_is_split_so_the_corner_stays_free():
    occ = np.zeros((60, 60), dtype=bool)
    occ[5:8, 5:55] = True
    occ[5:55, 5:8] = True
    obstacles = obstacles_from_mask(occ, 0.1, (0.0, 0.0), PARAMS)
    assert len(obstacles) >= 2
    assert _cells_not_inside(obstacles, occ, 0.1, (0.0, 0.0)) == 0
    inner = np.array([[3.0, 3.0]])  # deep in the L's free corner
    assert not any(p.contains(inner)[0] for p in obstacles)
    whole = obstacles_from_mask(occ, 0.1, (0.0, 0.0), dataclasses.replace(PARAMS, obstacle_split_depth=0))
    assert len(whole) == 1 and whole[0].contains(inner)[0]


def test_empty_mask_and_bad_method():
    assert obstacles_from_mask(np.zeros((10, 10), dtype=bool), 0.05, (0.0, 0.0), PARAMS) == []
    with pytest.raises(ValueError, match="obstacle_method"):
        obstacles_from_mask(np.ones((3, 3), dtype=bool), 0.05, (0.0, 0.0), dataclasses.replace(PARAMS, obstacle_method="blob"))


@settings(max_examples=30, deadline=None)
@given(st.integers(min_value=0, max_value=2**31 - 1), st.floats(min_value=0.02, max_value=0.5), st.sampled_from(["hull", "rect"]))
def test_random_masks_fully_covered(seed, density, method):
    rng = np.random.default_rng(seed)
    occ = rng.random((25, 33)) < density
    res, origin = 0.03, (0.4, -1.7)
    obstacles = obstacles_from_mask(occ, res, origin, dataclasses.replace(PARAMS, obstacle_method=method))
    assert _cells_not_inside(obstacles, occ, res, origin) == 0
    for p in obstacles:
        _convex_consistent(p)


def test_a_u_of_grass_round_the_paving_is_split_however_many_specks_lie_beyond() -> None:
    """The grass round a sidewalk seen from its start is one U-shaped blob, and far terrain at the pixel
    stride comes as hundreds of specks, each its own blob: the U is split first (the largest), so that
    no piece's hull reaches over the paving; with the specks counted against the splits it was hulled
    whole, paving and all."""
    occ = np.zeros((120, 160), dtype=bool)
    occ[10:20, 10:150] = True  # a verge
    occ[80:90, 10:150] = True  # the other
    occ[10:90, 10:20] = True  # the grass behind the start
    occ[100:120:2, 0:160:2] = True  # specks, far off, none touching another
    assert cv2_groups(occ) > PARAMS.obstacles_max
    obstacles = obstacles_from_mask(occ, 0.05, (0.0, 0.0), PARAMS)
    assert _cells_not_inside(obstacles, occ, 0.05, (0.0, 0.0)) == 0
    paving = np.array([[x, y] for x in np.arange(1.5, 7.0, 0.25) for y in (2.0, 2.5, 3.0, 3.5)])
    assert not any(p.contains(paving).any() for p in obstacles)


def cv2_groups(occ: np.ndarray) -> int:
    import cv2

    return cv2.connectedComponents(occ.astype(np.uint8), connectivity=8)[0] - 1
