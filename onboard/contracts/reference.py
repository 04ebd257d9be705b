"""How a CoM reference is read: the one meaning of a :class:`ComReference` at a time.

The high level publishes a piecewise Bezier CoM reference; the low level (every tick), the
geometric MPC and the planner's own commit checks all read it here, so the planner and the
trackers cannot disagree about what was promised. Pure scalar floats: it runs every tick
(compiled with the tick, ``setup.py``).
"""

from __future__ import annotations

from onboard.contracts.messages import ComReference


def _bernstein_point(pts: list[list[float]], s: float) -> tuple[float, float]:
    """de Casteljau in scalar floats: ``onboard.geometry.bezier`` works on numpy batches, which
    costs tens of microseconds for one point; this runs every tick."""
    xs = [p[0] for p in pts]
    ys = [p[1] for p in pts]
    u = 1.0 - s
    for k in range(len(xs) - 1, 0, -1):
        for i in range(k):
            xs[i] = u * xs[i] + s * xs[i + 1]
            ys[i] = u * ys[i] + s * ys[i + 1]
    return xs[0], ys[0]


def _sample_unrolled(pts: list[list[float]], n: int, tau: float, s: float) -> tuple[float, float, float, float]:
    """Cubic and linear segments (the scenarios' references) with de Casteljau unrolled: the
    same operations in the same order as :func:`_bernstein_point` on the points and on the
    hodograph, so the same bits, at a fraction of the loops' cost (this runs every tick)."""
    u = 1.0 - s
    k = n / tau
    if n == 1:
        (x0, y0), (x1, y1) = pts[0][:2], pts[1][:2]
        return u * x0 + s * x1, u * y0 + s * y1, k * (x1 - x0), k * (y1 - y0)
    (x0, y0), (x1, y1), (x2, y2), (x3, y3) = pts[0][:2], pts[1][:2], pts[2][:2], pts[3][:2]
    hx0, hx1, hx2 = k * (x1 - x0), k * (x2 - x1), k * (x3 - x2)
    hy0, hy1, hy2 = k * (y1 - y0), k * (y2 - y1), k * (y3 - y2)
    x0, x1, x2 = u * x0 + s * x1, u * x1 + s * x2, u * x2 + s * x3
    y0, y1, y2 = u * y0 + s * y1, u * y1 + s * y2, u * y2 + s * y3
    x0, x1 = u * x0 + s * x1, u * x1 + s * x2
    y0, y1 = u * y0 + s * y1, u * y1 + s * y2
    hx0, hx1 = u * hx0 + s * hx1, u * hx1 + s * hx2
    hy0, hy1 = u * hy0 + s * hy1, u * hy1 + s * hy2
    return u * x0 + s * x1, u * y0 + s * y1, u * hx0 + s * hx1, u * hy0 + s * hy1


def sample_reference(ref: ComReference, t_s: float) -> tuple[float, float, float, float]:
    """Reference CoM ``(x, y, vx, vy)`` at ``t_s`` [s] after ``ref.t_ref_ns``.

    Before the first segment: its start at rest; after the last: its end at rest.
    """
    segs = ref.segments
    first, last = segs[0], segs[-1]
    if t_s < first.t0:
        p = first.control_points[0]
        return p[0], p[1], 0.0, 0.0
    if t_s >= last.t0 + last.duration:
        p = last.control_points[-1]
        return p[0], p[1], 0.0, 0.0
    seg = first
    for sg in segs:
        if sg.t0 <= t_s < sg.t0 + sg.duration:
            seg = sg
            break
    pts = seg.control_points
    tau = seg.duration
    s = min(max((t_s - seg.t0) / tau, 0.0), 1.0)
    n = len(pts) - 1
    if n == 3 or n == 1:
        return _sample_unrolled(pts, n, tau, s)
    x, y = _bernstein_point(pts, s)
    if n == 0:
        return x, y, 0.0, 0.0
    # the hodograph: n / tau * (P_{j+1} - P_j), a curve of degree n - 1
    k = n / tau
    hod = [[k * (b[0] - a[0]), k * (b[1] - a[1])] for a, b in zip(pts[:-1], pts[1:])]
    vx, vy = _bernstein_point(hod, s)
    return x, y, vx, vy
