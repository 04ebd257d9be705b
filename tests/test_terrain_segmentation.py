"""Terrain segmentation from colour and depth (onboard/perception/terrain.py) against the twin's
ground-truth labels: the paving is told from the grass, the obstacles from the ground."""

from __future__ import annotations

import numpy as np
import pytest

from onboard.contracts.params import PerceptionParams
from onboard.perception.segmentation import TRAVERSABLE, Cloud, GeometricSegmenter
from onboard.perception.terrain import ColorTerrainSegmenter, kmeans, nearest
from sim_twin.camera import CameraModel
from sim_twin.terrain_eval import SEGMENTERS, score_seed


def scores(scenario: str, seeds: range, views: int) -> dict[str, float]:
    cam = CameraModel.d435(424, 240, 30)
    inter = {n: 0 for n in SEGMENTERS}
    union = {n: 0 for n in SEGMENTERS}
    for seed in seeds:
        params = PerceptionParams(seed=seed, pixel_stride=4)
        for name, s in score_seed(scenario, seed, views, {n: mk(params) for n, mk in SEGMENTERS.items()}, cam).items():
            assert s.views == views
            inter[name] += s.intersection
            union[name] += s.union
    return {n: inter[n] / union[n] for n in SEGMENTERS}


def test_sidewalk_paving_is_told_from_the_grass_that_geometry_calls_ground() -> None:
    iou = scores("sidewalk", range(3), 4)
    assert iou["color"] > 0.85 and iou["color"] > iou["geometric"] + 0.15, iou


def test_forest_floor_stays_traversable_with_colour() -> None:
    iou = scores("forest", range(2), 4)
    assert iou["color"] > 0.85 and iou["geometric"] > 0.85, iou


def test_without_colour_it_is_the_geometric_segmenter_and_a_wrong_image_is_refused() -> None:
    rng = np.random.default_rng(0)
    h, w = 30, 40
    xs, ys = np.meshgrid(np.linspace(1, 3, w), np.linspace(-1, 1, h))
    pts = np.stack([xs, ys, rng.normal(0, 0.005, (h, w))], axis=-1)
    pts[10:20, 10:20, 2] = 0.5  # a box on the floor
    valid = np.ones((h, w), dtype=bool)
    cloud = Cloud(pts, valid, np.array([0.0, 0.0, 0.8]))
    params = PerceptionParams(ground_min_points=10)
    assert np.array_equal(ColorTerrainSegmenter(params).segment(cloud), GeometricSegmenter(params).segment(cloud))
    with pytest.raises(ValueError, match="does not match"):
        ColorTerrainSegmenter(params).segment(Cloud(pts, valid, np.zeros(3), np.zeros((h, w + 1, 3), np.uint8)))
    with pytest.raises(ValueError, match="odd"):
        ColorTerrainSegmenter(PerceptionParams(terrain_blur_px=4))


def test_kmeans_finds_separated_clusters() -> None:
    rng = np.random.default_rng(1)
    truth = np.array([[0.0, 0.0, 0.0], [10.0, 0.0, 0.0], [0.0, 10.0, 5.0]])
    x = np.concatenate([c + rng.normal(0, 0.5, (200, 3)) for c in truth])
    centres = kmeans(x, 3, np.random.default_rng(2))
    assert np.allclose(np.sort(centres, axis=0), np.sort(truth, axis=0), atol=0.2)
    assert len(set(nearest(x, centres)[::200].tolist())) == 3


PAVING, GRASS = (168, 163, 153), (77, 133, 46)  # the sidewalk scenario's colours (sim_twin/scenarios.py)


def _flat_view(near_colour: tuple[int, int, int], far_colour: tuple[int, int, int], seed: int) -> Cloud:
    """Flat ground from 0.3 to 3 m ahead of the foot, one colour within the seed range and another beyond."""
    rng = np.random.default_rng(seed)
    h, w = 40, 40
    xs, ys = np.meshgrid(np.linspace(3.0, 0.3, h), np.linspace(-1.0, 1.0, w), indexing="ij")
    pts = np.stack([xs, ys, rng.normal(0.0, 0.003, (h, w))], axis=-1)
    image = np.where((xs <= PerceptionParams().terrain_seed_range_m)[..., None], near_colour, far_colour)
    image = np.clip(image + rng.normal(0.0, 4.0, image.shape), 0, 255).astype(np.uint8)
    return Cloud(pts, np.ones((h, w), dtype=bool), np.array([0.0, 0.0, 0.6]), image, np.array([0.0, 0.0]))


def test_a_view_across_a_boundary_does_not_change_what_the_robot_stands_on() -> None:
    """At a walkway's end facing the grass, the nearest ground in view is grass: once the paving was seen
    under the foot view after view, that seed is refused (counted), and the grass is not traversable.
    A first view across a boundary has nothing to agree with: the memory follows it."""
    params = PerceptionParams(ground_min_points=10, seed=3)
    seg = ColorTerrainSegmenter(params)
    for k in range(params.terrain_seed_confirm):
        seg.segment(_flat_view(PAVING, PAVING, k))
    paving = seg.seed_color.copy()
    view = _flat_view(GRASS, PAVING, 99)
    labels = seg.segment(view)
    near = view.points[..., 0] <= params.terrain_seed_range_m
    assert seg.seed_jumps == 1 and np.array_equal(seg.seed_color, paving)
    assert (labels[near] != TRAVERSABLE).mean() > 0.9 and (labels[~near] == TRAVERSABLE).mean() > 0.9  # the blur edge aside
    fresh = ColorTerrainSegmenter(params)
    labels = fresh.segment(_flat_view(GRASS, PAVING, 99))
    assert fresh.seed_jumps == 0 and (labels[near] == TRAVERSABLE).mean() > 0.9  # what it has: the grass
