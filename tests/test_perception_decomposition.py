"""Algorithm 4: convex free cells are sound against cell squares, cover and connect."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from onboard.contracts.params import PerceptionParams
from onboard.perception import maps
from onboard.perception import decomposition
from onboard.perception.decomposition import clear_of_blocked, decompose_free_space, target_region
from onboard.perception.geometry import (
    cell_centres,
    chain_exists,
    covered_mask,
    overlap_components,
    overlapping_cells,
    polygon_from_points,
    polygons_overlap,
)

RES = 0.05
ORIGIN = (-5.0, -5.0)
PARAMS = PerceptionParams()
SAMPLES_PER_CELL = 7  # dense sampling for the independent soundness check


def _centre(cell: tuple[int, int]) -> tuple[float, float]:
    x, y = cell_centres(np.array([cell[0]]), np.array([cell[1]]), RES, ORIGIN)[0]
    return float(x), float(y)


def _sampled_blocked_hits(poly, blocked: np.ndarray, res: float, origin: tuple[float, float]) -> int:
    """Points strictly inside ``poly`` on a fine lattice that fall in a blocked cell.

    Independent of the separating-axis test: it only evaluates ``A x < b``.
    """
    xmin, ymin, xmax, ymax = poly.bbox()
    step = res / SAMPLES_PER_CELL
    xs = np.arange(xmin + step / 2, xmax, step)
    ys = np.arange(ymin + step / 2, ymax, step)
    gx, gy = np.meshgrid(xs, ys)
    pts = np.column_stack([gx.ravel(), gy.ravel()])
    inside = np.all(pts @ poly.A.T < poly.b - 1e-9, axis=1)
    pts = pts[inside]
    c = np.floor((pts[:, 0] - origin[0]) / res).astype(int)
    r = np.floor((pts[:, 1] - origin[1]) / res).astype(int)
    rows, cols = blocked.shape
    out = (r < 0) | (r >= rows) | (c < 0) | (c >= cols)
    assert not out.any(), "a polygon leaves the grid"
    return int(blocked[r, c].sum())


def _check_h_form(poly) -> None:
    """Vertices satisfy A x <= b, each face carries an edge, normals are unit."""
    slack = poly.b[:, None] - poly.A @ poly.vertices.T
    assert slack.min() > -1e-9
    assert np.all((np.abs(slack) < 1e-7).sum(axis=1) >= 2)
    assert np.allclose(np.linalg.norm(poly.A, axis=1), 1.0)
    assert poly.area > 0


MAPS = [(kind, seed) for kind in ("rooms", "corridors", "clutter") for seed in range(3)]


@pytest.mark.parametrize("kind,seed", MAPS)
def test_test_maps_sound_covering_and_connected(kind, seed):
    tm = maps.BUILDERS[kind](seed=seed)
    free = ~tm.occupied
    start, goal = _centre(tm.start), _centre(tm.goal)
    polys, stats = decompose_free_space(free, RES, ORIGIN, PARAMS, start=start)
    assert polys
    for p in polys:
        _check_h_form(p)
        assert len(overlapping_cells(p, tm.occupied, RES, ORIGIN)) == 0
        assert _sampled_blocked_hits(p, tm.occupied, RES, ORIGIN) == 0
    target = target_region(free, RES, ORIGIN, start)
    coverage = covered_mask(polys, free.shape, RES, ORIGIN)[target].mean()
    assert coverage >= 0.9, f"{kind} {seed}: coverage {coverage:.3f}"
    # The reachable free space is one 4-connected region: one group of overlapping polygons.
    assert len(set(overlap_components(polys).tolist())) == 1
    assert stats.dropped_for_overlap == 0
    # Asked to cover start and goal, the polygons chain one to the other.
    polys2, _ = decompose_free_space(free, RES, ORIGIN, PARAMS, start=start, must_cover=(start, goal))
    assert chain_exists(polys2, np.array(start), np.array(goal))


def test_disconnected_free_space_gives_no_chain_and_start_region_only():
    occ = np.zeros((60, 80), dtype=bool)
    occ[0, :] = occ[-1, :] = occ[:, 0] = occ[:, -1] = True
    occ[:, 38:42] = True  # a wall with no door
    free = ~occ
    left, right = (10 * RES + ORIGIN[0], 30 * RES + ORIGIN[1]), (60 * RES + ORIGIN[0], 30 * RES + ORIGIN[1])
    polys, _ = decompose_free_space(free, RES, ORIGIN, PARAMS, start=left, must_cover=(left, right))
    assert polys
    assert not chain_exists(polys, np.array(left), np.array(right))
    assert all(p.vertices[:, 0].max() <= ORIGIN[0] + 38 * RES + 1e-9 for p in polys)
    both, _ = decompose_free_space(free, RES, ORIGIN, PARAMS)
    assert len(set(overlap_components(both).tolist())) == 2
    # Open a door: now one chain.
    occ[28:34, 38:42] = False
    polys, _ = decompose_free_space(~occ, RES, ORIGIN, PARAMS, start=left, must_cover=(left, right))
    assert chain_exists(polys, np.array(left), np.array(right))


def test_open_room_is_one_polygon_covering_everything():
    free = np.ones((40, 50), dtype=bool)
    polys, stats = decompose_free_space(free, 0.1, (0.0, 0.0), PARAMS)
    cov = covered_mask(polys, free.shape, 0.1, (0.0, 0.0))
    assert cov.all()
    for p in polys:
        _check_h_form(p)
        # Nothing outside the grid: the grid's edge is the limit of what is known.
        assert p.vertices.min() >= -1e-9 and p.vertices[:, 0].max() <= 5.0 + 1e-9 and p.vertices[:, 1].max() <= 4.0 + 1e-9


def test_one_cell_wide_corridor_is_covered_and_chained():
    occ = np.ones((30, 60), dtype=bool)
    occ[15, 5:55] = False  # 1 cell wide, 50 long
    occ[5:16, 54] = False  # turns a corner, also 1 wide
    free = ~occ
    a = (5.5 * RES, 15.5 * RES)
    b = (54.5 * RES, 5.5 * RES)
    polys, _ = decompose_free_space(free, RES, (0.0, 0.0), PARAMS, start=a, must_cover=(a, b))
    for p in polys:
        assert len(overlapping_cells(p, occ, RES, (0.0, 0.0))) == 0
    assert covered_mask(polys, free.shape, RES, (0.0, 0.0))[free].mean() >= 0.9
    assert chain_exists(polys, np.array(a), np.array(b))


def test_diagonal_obstacles_are_avoided_as_squares_not_centres():
    # A checkerboard corner: free cells touching blocked ones only at corners.
    occ = np.zeros((20, 20), dtype=bool)
    occ[0, :] = occ[-1, :] = occ[:, 0] = occ[:, -1] = True
    occ[9, 9] = occ[10, 10] = occ[8, 12] = occ[12, 8] = True
    polys, _ = decompose_free_space(~occ, 1.0, (0.0, 0.0), PARAMS)
    for p in polys:
        assert len(overlapping_cells(p, occ, 1.0, (0.0, 0.0))) == 0
        assert _sampled_blocked_hits(p, occ, 1.0, (0.0, 0.0)) == 0


def test_overlap_test_is_exact_on_hand_made_cases():
    from onboard.perception.geometry import polygon_from_points

    occ = np.zeros((3, 3), dtype=bool)
    occ[1, 1] = True  # the square [1, 2] x [1, 2]
    touching = polygon_from_points(np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 3.0], [0.0, 3.0]]))
    corner = polygon_from_points(np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]]))
    diagonal = polygon_from_points(np.array([[0.0, 2.05], [2.05, 0.0], [2.0, 0.0], [0.0, 2.0]]))  # clips (1,1)
    short = polygon_from_points(np.array([[0.0, 1.95], [1.95, 0.0], [2.0, 0.0], [0.0, 2.0]]))  # reaches its corner
    sliver = polygon_from_points(np.array([[0.0, 0.0], [1.0 + 1e-3, 0.0], [1.0 + 1e-3, 3.0], [0.0, 3.0]]))
    assert len(overlapping_cells(touching, occ, 1.0, (0.0, 0.0))) == 0
    assert len(overlapping_cells(corner, occ, 1.0, (0.0, 0.0))) == 0
    assert overlapping_cells(diagonal, occ, 1.0, (0.0, 0.0)).tolist() == [[1, 1]]
    assert len(overlapping_cells(short, occ, 1.0, (0.0, 0.0))) == 0
    assert overlapping_cells(sliver, occ, 1.0, (0.0, 0.0)).tolist() == [[1, 1]]
    assert polygons_overlap(touching, sliver)
    assert not polygons_overlap(corner, polygon_from_points(np.array([[1.0, 0.0], [2.0, 0.0], [1.0, 1.0]])))


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.integers(min_value=0, max_value=2**31 - 1), st.floats(min_value=0.05, max_value=0.35))
def test_random_grids_are_sound(seed, density):
    rng = np.random.default_rng(seed)
    occ = rng.random((24, 31)) < density
    occ = occ | np.roll(occ, 1, axis=1) & (rng.random(occ.shape) < 0.5)  # some 2-cell blobs
    free = ~occ
    res, origin = 0.07, (1.3, -2.1)
    polys, stats = decompose_free_space(free, res, origin, PARAMS)
    assert stats.dropped_for_overlap == 0
    for p in polys:
        _check_h_form(p)
        assert len(overlapping_cells(p, occ, res, origin)) == 0
        assert _sampled_blocked_hits(p, occ, res, origin) == 0


def test_deterministic_for_a_seed():
    tm = maps.clutter(seed=4)
    a, _ = decompose_free_space(~tm.occupied, RES, ORIGIN, PARAMS)
    b, _ = decompose_free_space(~tm.occupied, RES, ORIGIN, PARAMS)
    assert len(a) == len(b)
    assert all(np.array_equal(p.vertices, q.vertices) for p, q in zip(a, b))


def test_start_outside_free_space_gives_nothing():
    tm = maps.rooms(seed=0)
    assert decompose_free_space(~tm.occupied, RES, ORIGIN, PARAMS, start=(ORIGIN[0] + 0.01, ORIGIN[1] + 0.01))[0] == []
    assert decompose_free_space(~tm.occupied, RES, ORIGIN, PARAMS, start=(100.0, 100.0))[0] == []


def _box(x0: float, y0: float, x1: float, y1: float):
    return polygon_from_points(np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1]]))


def test_polygons_overlapping_a_blocked_square_are_dropped_and_counted():
    blocked = np.zeros((4, 4), dtype=bool)
    blocked[1, 1] = True  # the square [1, 2] x [1, 2] in cell units
    over = _box(0.0, 0.0, 1.5, 1.5)  # a quarter of the blocked square
    touching = _box(2.0, 1.0, 3.0, 2.0)  # shares the blocked square's edge only
    clear = _box(2.5, 2.5, 3.5, 3.5)
    kept, dropped = clear_of_blocked([over, touching, clear], blocked)
    assert kept == [touching, clear] and dropped == 1
    assert clear_of_blocked([], blocked) == ([], 0)


def test_dropped_polygons_are_counted_and_cover_nothing(monkeypatch):
    """The fits never overlap a blocked square on these maps, so a drop is forced: what a
    dropped polygon covered must leave the reported coverage."""
    tm = maps.BUILDERS["rooms"](seed=0)
    free = ~tm.occupied
    start = _centre(tm.start)
    _, honest = decompose_free_space(free, RES, ORIGIN, PARAMS, start=start)

    def drop_every_other(cell_polys, blocked):
        return cell_polys[::2], len(cell_polys) - len(cell_polys[::2])

    monkeypatch.setattr(decomposition, "clear_of_blocked", drop_every_other)
    polys, stats = decompose_free_space(free, RES, ORIGIN, PARAMS, start=start)
    assert stats.dropped_for_overlap == honest.polygons // 2 and stats.polygons == len(polys)
    target = target_region(free, RES, ORIGIN, start)
    assert stats.coverage == pytest.approx(covered_mask(polys, free.shape, RES, ORIGIN)[target].mean(), abs=0.01)
    assert stats.coverage < honest.coverage - 0.05
