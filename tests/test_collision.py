"""Exact hull-versus-polygon tests: hand-made scenes, brute force, dense sampling, Cut-QP."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.optimize import linprog

from onboard.high_level.tracking import collision as col

from onboard.geometry import polygons as pg

SQUARE = np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]])


def _segment_distance(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> float:
    d = b - a
    dd = float(np.dot(d, d))
    t = 0.0 if dd < 1e-200 else float(np.clip(np.dot(p - a, d) / dd, 0.0, 1.0))
    return float(np.linalg.norm(p - a - t * d))


def _hulls_meet(P: np.ndarray, O: np.ndarray) -> bool:
    """conv(P) and conv(O) share a point: an LP feasibility problem (independent of the kernel)."""
    k, m = len(P), len(O)
    A_eq = np.vstack([np.hstack([P.T, -O.T]), np.hstack([np.ones(k), np.zeros(m)]), np.hstack([np.zeros(k), np.ones(m)])])
    b_eq = np.array([0.0, 0.0, 1.0, 1.0])
    res = linprog(np.zeros(k + m), A_eq=A_eq, b_eq=b_eq, bounds=[(0, None)] * (k + m), method="highs")
    return res.status == 0


def _brute_distance(P: np.ndarray, O: np.ndarray) -> float:
    if _hulls_meet(P, O):
        return 0.0
    best = math.inf
    for p in P:
        for i in range(len(O)):
            best = min(best, _segment_distance(p, O[i], O[(i + 1) % len(O)]))
    for o in O:
        for i in range(len(P)):
            for j in range(i, len(P)):
                best = min(best, _segment_distance(o, P[i], P[j]))
    return best


def _bernstein(K: int, s: np.ndarray) -> np.ndarray:
    p = K - 1
    return np.stack([math.comb(p, k) * s**k * (1 - s) ** (p - k) for k in range(K)], axis=1)


# --- polygon validation -------------------------------------------------------------


def test_validate_polygon_makes_counter_clockwise():
    cw = SQUARE[::-1]
    out = pg.validate_polygon(cw)
    x, y = out[:, 0], out[:, 1]
    assert np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y) > 0


@pytest.mark.parametrize(
    "poly, why",
    [
        ([[0, 0], [2, 0], [1, 0.2], [2, 2], [0, 2]], "not convex"),
        ([[0, 0], [1, 0], [2, 0]], "zero area"),
        ([[0, 0], [1, 0], [1, 0], [0, 1]], "repeated vertex"),
        ([[0, 0], [1, 0]], "at least 3"),
        ([[0, 0], [float("nan"), 0], [0, 1]], "non-finite"),
        ([[1, 0], [-0.809, 0.588], [0.309, -0.951], [0.309, 0.951], [-0.809, -0.588]], "winds"),
        ([[0, 0, 0], [1, 0, 0], [0, 1, 0]], "list of"),
    ],
)
def test_validate_polygon_rejects_bad_polygons(poly, why):
    with pytest.raises(pg.PolygonError, match=why):
        pg.validate_polygon(poly)


def test_polygon_from_halfspaces_round_trip():
    A, b = pg.polygon_halfspaces(pg.validate_polygon(SQUARE))
    verts = pg.polygon_from_halfspaces(A, b)
    assert len(verts) == 4
    assert {tuple(np.round(v, 9)) for v in verts} == {tuple(v) for v in SQUARE}
    with pytest.raises(pg.PolygonError, match="do not bound"):
        pg.polygon_from_halfspaces(A[:2], b[:2])
    with pytest.raises(pg.PolygonError):  # empty
        pg.polygon_from_halfspaces(np.array([[1.0, 0.0], [-1.0, 0.0]]), np.array([0.0, -1.0]))


# --- hand-made scenes with known answers ------------------------------------------------


def _cut(points: list[list[list[float]]], polys: list[np.ndarray], margin: float) -> np.ndarray:
    return col.cut_obstacles(col.hull_set(np.array(points, dtype=float)), pg.pack_polygons(polys), margin)


def test_line_past_square_at_known_distance():
    # Horizontal segments (as 4 collinear control points) at height 1 + d above the unit square.
    curves = [[[-1.0, 1.0 + d], [0.0, 1.0 + d], [1.0, 1.0 + d], [2.0, 1.0 + d]] for d in (0.05, 0.19, 0.21, 0.5)]
    blocked = _cut(curves, [SQUARE], margin=0.2)
    assert blocked.tolist() == [True, True, False, False]


def test_corner_is_rounded_not_offset():
    # A point 0.2 * (1, 1) / sqrt(2) * 1.2 away from the corner diagonally: distance 0.24 > 0.2,
    # but inside the offset square [-0.2, 1.2]^2 that a face-offset inflation would use.
    q = 1.0 + 0.24 / math.sqrt(2)
    curve = [[[q, q], [q + 0.5, q], [q + 0.5, q + 0.5], [q, q + 0.5]]]
    assert _cut(curve, [SQUARE], margin=0.2).tolist() == [False]
    assert _cut(curve, [SQUARE], margin=0.25).tolist() == [True]


def test_hull_blocks_even_when_no_control_point_is_near():
    # Control points far on both sides: the hull (and the curve) crosses the square.
    curve = [[[-3.0, 0.5], [-2.0, 0.5], [3.0, 0.5], [4.0, 0.5]]]
    assert _cut(curve, [SQUARE], margin=0.0).tolist() == [True]


def test_curve_inside_obstacle_and_point_curve():
    assert _cut([[[0.5, 0.5]] * 4], [SQUARE], 0.1).tolist() == [True]
    assert _cut([[[1.5, 0.5]] * 4], [SQUARE], 0.49).tolist() == [False]
    assert _cut([[[1.5, 0.5]] * 4], [SQUARE], 0.51).tolist() == [True]


def test_no_obstacles_and_inactive_edges():
    hulls = col.hull_set(np.zeros((3, 4, 2)))
    assert not col.cut_obstacles(hulls, pg.pack_polygons([]), 0.3).any()
    active = np.array([True, False, True])
    blocked = col.cut_obstacles(hulls, pg.pack_polygons([SQUARE - 0.5]), 0.1, active=active)
    assert blocked.tolist() == [True, False, True]
    with pytest.raises(ValueError):
        col.cut_obstacles(hulls, pg.pack_polygons([SQUARE]), float("nan"))


def test_free_cells_every_point_in_one_cell():
    left = np.array([[0.0, 0.0], [2.0, 0.0], [2.0, 2.0], [0.0, 2.0]])
    right = left + [1.5, 0.0]  # overlaps left on x in [1.5, 2]
    cells = pg.pack_polygons([left, right])
    curves = np.array([
        [[0.5, 1.0], [1.0, 1.0], [1.5, 1.0], [1.8, 1.0]],  # inside left
        [[1.7, 1.0], [2.5, 1.0], [3.0, 1.2], [3.2, 1.0]],  # inside right
        [[0.5, 1.0], [1.5, 1.0], [2.5, 1.0], [3.0, 1.0]],  # straddles: no single cell
        [[0.05, 1.0], [0.5, 1.0], [1.0, 1.0], [1.2, 1.0]],  # inside left, but 5 cm from its wall
    ])
    blocked = col.cut_free_cells(col.hull_set(curves), cells, margin=0.1)
    assert blocked.tolist() == [False, False, True, True]
    assert col.cut_free_cells(col.hull_set(curves), pg.pack_polygons([]), 0.1).all()


# --- properties against brute force and dense sampling -------------------------------------

coords = st.floats(-3.0, 3.0, allow_nan=False, allow_infinity=False)


@st.composite
def convex_polygon(draw):
    from scipy.spatial import ConvexHull

    pts = np.array(draw(st.lists(st.tuples(coords, coords), min_size=3, max_size=8)))
    try:
        hull = ConvexHull(pts)
    except Exception:
        pts = np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]])
        hull = ConvexHull(pts)
    poly = pts[hull.vertices]
    try:
        return pg.validate_polygon(poly)
    except pg.PolygonError:
        return pg.validate_polygon(SQUARE)


@settings(max_examples=200, deadline=None)
@given(
    poly=convex_polygon(),
    ctrl=st.lists(st.tuples(coords, coords), min_size=4, max_size=4),
    margin=st.floats(0.0, 1.0),
)
def test_cut_matches_exact_distance(poly, ctrl, margin):
    P = np.array(ctrl, dtype=float)
    dist = _brute_distance(P, poly)
    if abs(dist - margin) < 1e-6:
        return  # a tie: either answer is within round-off
    blocked = col.cut_obstacles(col.hull_set(P[None]), pg.pack_polygons([poly]), margin)[0]
    assert blocked == (dist <= margin), f"distance {dist}, margin {margin}"
    # two formulas for one distance: on a sliver (a vertex 1e-7 off a line, seen once) round-off reaches 1e-7,
    # so they agree to the test's own tie tolerance
    assert col.hull_polygon_distance(P, poly) == pytest.approx(dist, abs=1e-6)


@pytest.mark.parametrize("spread", [1.0, 3.0])  # new curves inside the old ones' grid; reaching past it
def test_a_grown_hull_set_is_the_set_built_whole(spread):
    rng = np.random.default_rng(3)
    old = rng.uniform(0, 2, (500, 1, 2)) + np.cumsum(rng.normal(0, 0.1, (500, 4, 2)), axis=1)
    new = rng.uniform(0, spread, (60, 1, 2)) + np.cumsum(rng.normal(0, 0.1, (60, 4, 2)), axis=1)
    new_at = np.sort(rng.choice(560, 60, replace=False))
    shuffled = rng.permutation(60)  # any order of the new curves: each goes to its own index
    grown = col.grown_hull_set(col.hull_set(old), new[shuffled], new_at[shuffled])
    is_new = np.zeros(560, dtype=bool)
    is_new[new_at] = True
    all_pts = np.empty((560, 4, 2))
    all_pts[is_new], all_pts[~is_new] = new, old
    whole = col.hull_set(all_pts)
    for name in ("points", "aabb", "center", "radius", "axes", "half_max"):
        np.testing.assert_array_equal(getattr(grown, name), getattr(whole, name), err_msg=name)
    # the cells and their order on the grid it kept (the whole set's own when it had to bin again)
    assert np.all(np.diff(grown.by_cell[5]) >= 0) and np.array_equal(grown.cell[grown.order], grown.by_cell[5])
    for kept, field in zip(grown.by_cell, (grown.points, grown.aabb, grown.center, grown.radius, grown.axes, grown.cell)):
        np.testing.assert_array_equal(kept, field[grown.order])
    if spread > 2.5:
        assert grown.grid == whole.grid and np.array_equal(grown.order, whole.order)
    else:
        assert grown.grid == col.hull_set(old).grid  # merged into the bins it had
    polys = pg.pack_polygons([SQUARE * 0.3 + c for c in rng.uniform(0, spread, (12, 2))])
    np.testing.assert_array_equal(col.cut_obstacles(grown, polys, 0.1), col.cut_obstacles(whole, polys, 0.1))
    with pytest.raises(ValueError):
        col.grown_hull_set(col.hull_set(old), new, np.zeros(60, dtype=np.int64))  # two curves at one index


def test_a_grouped_cut_is_each_group_cut_alone():
    """Curves meet only the obstacles of their own group: one pass gives what a cut per group gives."""
    rng = np.random.default_rng(11)
    pts = rng.uniform(0, 4, (3000, 1, 2)) + np.cumsum(rng.normal(0, 0.15, (3000, 4, 2)), axis=1)
    hulls = col.hull_set(pts)
    polys = [SQUARE * 0.4 + c for c in rng.uniform(0, 4, (30, 2))]
    obstacle_group = np.arange(30) % 3
    curve_group = rng.integers(0, 4, 3000)  # group 3 has no obstacles: never blocked
    active = rng.random(3000) < 0.9
    grouped = col.cut_obstacles(hulls, pg.pack_polygons(polys), 0.1, active=active,
                                curve_group=curve_group, obstacle_group=obstacle_group)
    expected = np.zeros(3000, dtype=bool)
    for g in range(3):
        alone = col.cut_obstacles(hulls, pg.pack_polygons([p for p, k in zip(polys, obstacle_group) if k == g]), 0.1,
                                  active=active & (curve_group == g))
        expected |= alone
    np.testing.assert_array_equal(grouped, expected)
    assert grouped.any() and not grouped[curve_group == 3].any() and not grouped[~active].any()
    with pytest.raises(ValueError, match="go together"):
        col.cut_obstacles(hulls, pg.pack_polygons(polys), 0.1, curve_group=curve_group)
    with pytest.raises(ValueError, match="groups must be"):
        col.cut_obstacles(hulls, pg.pack_polygons(polys), 0.1, curve_group=curve_group[:10], obstacle_group=obstacle_group)


def test_many_curves_sound_against_dense_sampling():
    rng = np.random.default_rng(7)
    E = 4000
    start = rng.uniform(0, 10, (E, 2))
    pts = start[:, None, :] + np.cumsum(rng.normal(0, 0.25, (E, 4, 2)), axis=1)
    polys = []
    for _ in range(60):
        c = rng.uniform(0, 10, 2)
        th = rng.uniform(0, math.pi)
        w, h = rng.uniform(0.1, 0.6, 2)
        R = np.array([[math.cos(th), -math.sin(th)], [math.sin(th), math.cos(th)]])
        polys.append(c + np.array([[-w, -h], [w, -h], [w, h], [-w, h]]) @ R.T)
    obstacles = pg.pack_polygons(polys)
    margin = 0.15
    blocked = col.cut_obstacles(col.hull_set(pts), obstacles, margin)
    samples = np.einsum("sk,ekd->esd", _bernstein(4, np.linspace(0, 1, 200)), pts)
    clearance = col.samples_clearance(samples, obstacles, reach=margin + 0.1)
    assert not np.any(~blocked & (clearance <= margin)), "a kept curve enters an inflated obstacle"
    assert blocked.any() and (~blocked).any()
    # Brute force on a subset: the verdict is the exact hull distance, nothing more conservative.
    for e in rng.choice(E, 300, replace=False):
        lo, hi = pts[e].min(axis=0) - 2 * margin, pts[e].max(axis=0) + 2 * margin
        near = [p for p in polys if np.all(p.max(axis=0) >= lo) and np.all(p.min(axis=0) <= hi)]
        dist = min([_brute_distance(pts[e], p) for p in near], default=math.inf)  # others are > 2 margin away
        if abs(dist - margin) > 1e-6:
            assert blocked[e] == (dist <= margin)


def test_separating_halfspaces_keep_margin():
    rng = np.random.default_rng(3)
    polys = [SQUARE, SQUARE + [3.0, 0.0], SQUARE + [0.0, 3.0]]
    obstacles = pg.pack_polygons(polys)
    pts = np.array([[[1.6, 1.6], [2.0, 1.8], [2.2, 2.0], [2.4, 1.5]]])
    margin = 0.2
    hs = col.separating_halfspaces(pts, obstacles, margin, count=3, reach=10.0)
    assert hs.shape == (1, 3, 3)
    for a0, a1, b in hs[0]:
        assert math.hypot(a0, a1) == pytest.approx(1.0)
        # The hull satisfies the halfspace (it is clear of every obstacle by more than the margin) ...
        assert np.all(pts[0] @ [a0, a1] <= b + 1e-12)
    # ... and every point satisfying all of them is > margin from the three obstacles.
    cand = rng.uniform(-1, 5, (20000, 2))
    ok = np.all(cand @ hs[0, :, :2].T <= hs[0, :, 2], axis=1)
    dist = col.samples_clearance(cand[ok][:, None, :], obstacles, reach=1.0)
    assert np.all(dist >= margin - 1e-9)
    # Unused rows when fewer obstacles are in reach.
    far = col.separating_halfspaces(pts, obstacles, margin, count=3, reach=0.1)
    assert np.isinf(far[0, :, 2]).sum() >= 1


# --- Cut-QP ------------------------------------------------------------------------------


def test_cut_qp_agrees_with_exact_planar_test():
    rng = np.random.default_rng(11)
    A, b = pg.polygon_halfspaces(pg.validate_polygon(SQUARE))
    for _ in range(25):
        P = rng.uniform(-1.5, 2.5, (4, 2))
        exact = _brute_distance(P, SQUARE)
        assert col.hull_polytope_distance_qp(P, A, b) == pytest.approx(exact, abs=1e-4)


def test_cut_qp_in_three_dimensions():
    # Unit cube; a segment of control points passing 0.5 above its top face.
    A = np.vstack([np.eye(3), -np.eye(3)])
    b = np.array([1.0, 1.0, 1.0, 0.0, 0.0, 0.0])
    P = np.array([[-1.0, 0.5, 1.5], [0.0, 0.5, 1.5], [1.0, 0.5, 1.5], [2.0, 0.5, 1.5]])
    assert col.hull_polytope_distance_qp(P, A, b) == pytest.approx(0.5, abs=1e-5)
    assert col.cut_qp(np.stack([P, P - [0, 0, 1.0]]), [(A, b)], margin=0.4).tolist() == [False, True]
