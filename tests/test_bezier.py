"""Bezier tools (thesis 2.6): each property checked against direct evaluation."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from onboard.geometry import bezier as bz

FAST = settings(max_examples=40, deadline=None)

orders = st.integers(min_value=1, max_value=9)
dims = st.integers(min_value=1, max_value=3)
taus = st.floats(min_value=0.05, max_value=5.0)
seeds = st.integers(min_value=0, max_value=2**32 - 1)


def _points(seed: int, p: int, m: int) -> np.ndarray:
    return np.random.default_rng(seed).normal(size=(p + 1, m))


def _poly_values(C: np.ndarray, tau: float, t: np.ndarray) -> np.ndarray:
    """Reference evaluation by de Casteljau's recurrence (independent of bernstein())."""
    out = []
    for s in t / tau:
        pts = C.copy()
        while len(pts) > 1:
            pts = (1 - s) * pts[:-1] + s * pts[1:]
        out.append(pts[0])
    return np.array(out)


@FAST
@given(p=orders, m=dims, tau=taus, seed=seeds)
def test_evaluate_matches_de_casteljau_and_basis_sums_to_one(p, m, tau, seed):
    C = _points(seed, p, m)
    t = np.linspace(0, tau, 13)
    np.testing.assert_allclose(bz.evaluate(C, tau, t), _poly_values(C, tau, t), atol=1e-12)
    np.testing.assert_allclose(bz.bernstein(p, t / tau).sum(axis=1), 1.0, atol=1e-12)
    np.testing.assert_allclose(bz.evaluate(C, tau, tau / 3), _poly_values(C, tau, np.array([tau / 3]))[0], atol=1e-12)


def test_evaluate_batched_over_curves():
    rng = np.random.default_rng(0)
    C = rng.normal(size=(5, 7, 4, 2))
    t = np.linspace(0, 1.3, 9)
    out = bz.evaluate(C, 1.3, t)
    assert out.shape == (5, 7, 9, 2)
    np.testing.assert_allclose(out[3, 2], _poly_values(C[3, 2], 1.3, t), atol=1e-12)


@FAST
@given(p=orders, m=dims, tau=taus, seed=seeds)
def test_derivative_matrix_matches_finite_differences_and_hodograph(p, m, tau, seed):
    C = _points(seed, p, m)
    t = np.linspace(0.1 * tau, 0.9 * tau, 7)
    h = 1e-6 * tau
    fd = (bz.evaluate(C, tau, t + h) - bz.evaluate(C, tau, t - h)) / (2 * h)
    d = bz.derivative_points(C, tau)
    assert d.shape == C.shape
    np.testing.assert_allclose(bz.evaluate(d, tau, t), fd, atol=1e-5 * (1 + np.abs(fd).max()))
    np.testing.assert_allclose(bz.evaluate(bz.hodograph(C, tau), tau, t), bz.evaluate(d, tau, t), atol=1e-9)
    H = bz.derivative_matrix(p, tau)
    np.testing.assert_allclose(H.T @ C, d)


def test_derivative_of_a_line_is_constant_and_of_constant_is_zero():
    C = np.array([[0.0, 1.0], [1.0, 3.0], [2.0, 5.0], [3.0, 7.0]])  # uniform spacing: a line
    np.testing.assert_allclose(bz.derivative_points(C, 2.0), np.tile([1.5, 3.0], (4, 1)))
    np.testing.assert_allclose(bz.derivative_points(np.ones((5, 2)), 1.0), 0.0, atol=1e-12)


@FAST
@given(p=orders, m=dims, seed=seeds, a=st.floats(0.0, 0.9), frac=st.floats(0.05, 1.0))
def test_split_matrix_reparameterizes_sub_interval(p, m, seed, a, frac):
    b = a + frac * (1.0 - a)
    if b - a < 1e-3:
        return
    C = _points(seed, p, m)
    Q = bz.split_matrix(p, a, b)
    s = np.linspace(0, 1, 11)
    np.testing.assert_allclose(bz.evaluate(Q.T @ C, 1.0, s), bz.evaluate(C, 1.0, a + s * (b - a)), atol=1e-10)


def test_split_pieces_cover_curve_and_keep_derivatives():
    C = _points(3, 5, 2)
    curve = bz.BezierCurve(C, 2.0)
    pieces = curve.split(np.array([0.0, 0.25, 0.6, 1.0]))
    assert [pc.duration for pc in pieces] == pytest.approx([0.5, 0.7, 0.8])
    t0 = 0.0
    for pc in pieces:
        tt = np.linspace(0, pc.duration, 5)
        np.testing.assert_allclose(pc(tt), curve(t0 + tt), atol=1e-12)
        np.testing.assert_allclose(pc.derivative(2)(tt), curve.derivative(2)(t0 + tt), atol=1e-9)
        t0 += pc.duration


@FAST
@given(p=orders, m=dims, seed=seeds, extra=st.integers(1, 6))
def test_elevation_keeps_curve(p, m, seed, extra):
    C = _points(seed, p, m)
    s = np.linspace(0, 1, 9)
    E = bz.elevate(C, p + extra)
    assert E.shape == (p + extra + 1, m)
    np.testing.assert_allclose(bz.evaluate(E, 1.0, s), bz.evaluate(C, 1.0, s), atol=1e-12)
    np.testing.assert_allclose(bz.elevation_matrix(p, p + extra).sum(axis=0), 1.0)  # convex combinations


@FAST
@given(gamma=st.integers(1, 3), extra=st.integers(0, 4), m=dims, tau=taus, seed=seeds)
def test_boundary_solution_meets_boundary_values_for_any_order(gamma, extra, m, tau, seed):
    p = 2 * gamma - 1 + extra
    rng = np.random.default_rng(seed)
    x0, xT = rng.normal(size=(2, m * gamma))
    M, N = bz.boundary_solution(p, gamma, tau)
    assert N.shape == (p + 1, extra)
    D = bz.boundary_matrix(p, gamma, tau)
    assert np.linalg.matrix_rank(D) == 2 * gamma  # full column rank (Property 2.45)
    X = bz.boundary_values(x0, xT, gamma)
    Z = rng.normal(size=(extra, m))
    for C in (M @ X, M @ X + N @ Z):
        ends = bz.state_values(C, tau, gamma, np.array([0.0, tau]))
        np.testing.assert_allclose(ends[0], x0, atol=1e-7 * (1 + np.abs(x0).max()))
        np.testing.assert_allclose(ends[1], xT, atol=1e-7 * (1 + np.abs(xT).max()))
        np.testing.assert_allclose(D.T @ C, X, atol=1e-7 * (1 + np.abs(X).max()))


def test_effort_weighting_minimizes_integral_of_highest_derivative():
    gamma, p, tau = 2, 6, 1.0
    rng = np.random.default_rng(7)
    x0, xT = rng.normal(size=(2, 4))
    X = bz.boundary_values(x0, xT, gamma)
    M, N = bz.boundary_solution(p, gamma, tau, "effort")
    Mn, _ = bz.boundary_solution(p, gamma, tau, "min_norm")

    def effort(C):
        t = np.linspace(0, tau, 4001)
        acc = bz.evaluate(bz.derivative_points(C, tau, 2), tau, t)
        return np.trapezoid((acc**2).sum(axis=1), t)

    best = effort(M @ X)
    assert best <= effort(Mn @ X) + 1e-9
    for _ in range(20):
        assert best <= effort(M @ X + N @ rng.normal(size=(N.shape[1], 2))) + 1e-9
    # translation invariance: shifting both positions shifts the curve
    shift = np.array([3.0, -2.0, 0.0, 0.0])
    np.testing.assert_allclose(M @ bz.boundary_values(x0 + shift, xT + shift, gamma), M @ X + shift[:2], atol=1e-9)


def test_boundary_rejects_too_low_order():
    with pytest.raises(ValueError):
        bz.boundary_matrix(2, 2, 1.0)


def test_connect_is_the_unique_cubic_for_the_double_integrator():
    x0 = np.array([0.0, 0.0, 1.0, 0.0])
    xT = np.array([1.0, 0.0, 1.0, 0.0])
    C = bz.connect(x0, xT, 1.0, gamma=2)
    np.testing.assert_allclose(C, [[0, 0], [1 / 3, 0], [2 / 3, 0], [1, 0]], atol=1e-12)
    batch = bz.connect(np.tile(x0, (4, 1)), np.tile(xT, (4, 1)), 1.0, gamma=2)
    assert batch.shape == (4, 4, 2)


@FAST
@given(p=orders, m=dims, seed=seeds)
def test_path_length_bound_dominates_arc_length(p, m, seed):
    C = _points(seed, p, m)
    s = np.linspace(0, 1, 5001)
    pts = bz.evaluate(C, 1.0, s)
    arc = np.linalg.norm(np.diff(pts, axis=0), axis=1).sum()
    assert arc <= bz.path_length_bound(C) + 1e-9
    assert bz.BezierCurve(C, 1.0).path_length_bound() == pytest.approx(float(bz.path_length_bound(C)))


def test_gram_matrix_integrates_basis_products():
    p, tau = 4, 0.5
    t = np.linspace(0, tau, 20001)
    Z = bz.bernstein(p, t / tau)
    G = np.trapezoid(Z[:, :, None] * Z[:, None, :], t, axis=0)
    np.testing.assert_allclose(bz.gram_matrix(p, tau), G, atol=1e-8)


def test_curve_rejects_bad_input():
    with pytest.raises(ValueError):
        bz.BezierCurve(np.array([[0.0, np.nan]]), 1.0)
    with pytest.raises(ValueError):
        bz.BezierCurve(np.zeros((3, 2)), 0.0)
    with pytest.raises(ValueError):
        bz.split_matrix(3, 0.5, 0.5)
