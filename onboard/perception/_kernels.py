"""Compiled inner loops of perception (numba, cached on disk).

Everything here is in cell units: cell ``[r, c]`` is the square ``[c, c+1] x [r, r+1]``.
A fit is a few hundred squares and a few dozen halfplanes; in numpy its cost is call
overhead, which these loops do not have.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

BOUND_SIDES = 8  # the polygon bounding each fit circumscribes the unit circle
_TIGHT_REL = 1e-9  # a vertex is on a line when closer than this, relative to the scale


@njit(cache=True)
def fit_free(su, sv, l00, l10, l11, bu, bv, cols, rows, margin, flip_factor):  # pragma: no cover - compiled
    """FITFREE around the seed ``(su, sv)`` in the metric of the ellipse ``L L^T``.

    ``L = [[l00, 0], [l10, l11]]`` (Cholesky factor), ``bu, bv``: lower-left corners of
    the blocked squares that may bound the polygon. In the frame ``y = L^-1 (x - s)``
    the ellipse is the unit circle. Returns ``(A, b, V)``: unit outward normals, offsets
    and CCW vertices of the polygon [cells]; ``V`` is empty when the fit fails.

    Soundness: each halfplane is tangent, in the ellipse metric, to a blocked square at
    the square's point nearest the seed, so the square lies wholly on its far side; a
    square is dropped only when its four corners are behind a chosen halfplane; so no
    blocked square meets the interior of the result.
    """
    S = BOUND_SIDES
    i00 = 1.0 / l00
    i11 = 1.0 / l11
    i10 = -l10 * i00 * i11
    rad = 1.0 / math.cos(math.pi / S)
    # Bounding polygon, cell units.
    ou = np.empty(S)
    ov = np.empty(S)
    for k in range(S):
        a = (k + 0.5) * 2.0 * math.pi / S
        yu = rad * math.cos(a)
        yv = rad * math.sin(a)
        ou[k] = l00 * yu + su
        ov[k] = l10 * yu + l11 * yv + sv
    umin, umax, vmin, vmax = ou.min(), ou.max(), ov.min(), ov.max()

    n_all = bu.shape[0]
    sel = np.empty(n_all, dtype=np.int64)
    n = 0
    for j in range(n_all):
        if bu[j] + 1.0 > umin and bu[j] < umax and bv[j] + 1.0 > vmin and bv[j] < vmax:
            sel[n] = j
            n += 1
    yu4 = np.empty((n, 4))
    yv4 = np.empty((n, 4))
    qu = np.empty(n)
    qv = np.empty(n)
    r = np.empty(n)
    du4 = (0.0, 1.0, 1.0, 0.0)
    dv4 = (0.0, 0.0, 1.0, 1.0)
    for i in range(n):
        cu = bu[sel[i]] - su
        cv = bv[sel[i]] - sv
        for k in range(4):
            xu = cu + du4[k]
            xv = cv + dv4[k]
            yu4[i, k] = i00 * xu
            yv4[i, k] = i10 * xu + i11 * xv
        best = np.inf
        for k in range(4):
            au, av = yu4[i, k], yv4[i, k]
            eu = yu4[i, (k + 1) % 4] - au
            ev = yv4[i, (k + 1) % 4] - av
            t = -(au * eu + av * ev) / (eu * eu + ev * ev)
            t = min(max(t, 0.0), 1.0)
            pu, pv = au + t * eu, av + t * ev
            d2 = pu * pu + pv * pv
            if d2 < best:
                best, qu[i], qv[i] = d2, pu, pv
        r[i] = math.sqrt(best)
        if r[i] <= 0.0:
            return np.empty((0, 2)), np.empty(0), np.empty((0, 2))  # seed in a blocked square

    alive = np.ones(n, dtype=np.bool_)
    for k in range(S):  # side normals at whole steps (vertices are at half steps)
        a = k * 2.0 * math.pi / S
        ca, sa = math.cos(a), math.sin(a)
        for i in range(n):
            if alive[i]:
                out = True
                for c in range(4):
                    if ca * yu4[i, c] + sa * yv4[i, c] < 1.0:
                        out = False
                        break
                if out:
                    alive[i] = False

    cut_u = np.empty(n)
    cut_v = np.empty(n)
    cut_r = np.empty(n)
    n_cut = 0

    # Sphere flipping (Katz et al.): blocked points on the hull of the flipped set are
    # the ones visible from the centre; they shape the polygon, so they go first.
    inside = np.empty(n, dtype=np.int64)
    m = 0
    rmax = 0.0
    for i in range(n):
        if alive[i] and r[i] < 1.0:
            inside[m] = i
            m += 1
            rmax = max(rmax, r[i])
    visible = np.empty(0, dtype=np.int64)
    if m > 0:
        big_r = flip_factor * rmax
        fu = np.empty(m + 1)
        fv = np.empty(m + 1)
        for t in range(m):
            i = inside[t]
            s = 2.0 * big_r / r[i] - 1.0
            fu[t] = qu[i] * s
            fv[t] = qv[i] * s
        fu[m] = 0.0
        fv[m] = 0.0
        hull = _hull(fu, fv)
        cnt = 0
        for h in hull:
            if h < m:
                cnt += 1
        visible = np.empty(cnt, dtype=np.int64)
        cnt = 0
        for h in hull:
            if h < m:
                visible[cnt] = inside[h]
                cnt += 1
    for pass_ in range(2):
        if pass_ == 0:
            order = visible[np.argsort(r[visible])]
        else:
            order = np.argsort(r)
        for i in order:
            if not alive[i]:
                continue
            nu = qu[i] / r[i]
            nv = qv[i] / r[i]
            ri = r[i]
            cut_u[n_cut] = nu
            cut_v[n_cut] = nv
            cut_r[n_cut] = ri
            n_cut += 1
            alive[i] = False
            for j in range(n):
                if alive[j]:
                    behind = True
                    for c in range(4):
                        if nu * yu4[j, c] + nv * yv4[j, c] < ri:
                            behind = False
                            break
                    if behind:
                        alive[j] = False

    # Halfplanes in cell units: bounding sides, grid edges, cuts.
    n_h = S + 4 + n_cut
    ha = np.empty((n_h, 2))
    hb = np.empty(n_h)
    for k in range(S):
        k2 = (k + 1) % S
        eu, ev = ou[k2] - ou[k], ov[k2] - ov[k]
        ln = math.hypot(eu, ev)
        ha[k, 0], ha[k, 1] = ev / ln, -eu / ln
        hb[k] = ha[k, 0] * ou[k] + ha[k, 1] * ov[k]
    ha[S, 0], ha[S, 1], hb[S] = -1.0, 0.0, 0.0
    ha[S + 1, 0], ha[S + 1, 1], hb[S + 1] = 1.0, 0.0, float(cols)
    ha[S + 2, 0], ha[S + 2, 1], hb[S + 2] = 0.0, -1.0, 0.0
    ha[S + 3, 0], ha[S + 3, 1], hb[S + 3] = 0.0, 1.0, float(rows)
    for t in range(n_cut):
        # n . y <= r  <=>  (L^-T n) . (x - s) <= r
        au = cut_u[t] * i00 + cut_v[t] * i10
        av = cut_v[t] * i11
        ln = math.hypot(au, av)
        au /= ln
        av /= ln
        ha[S + 4 + t, 0] = au
        ha[S + 4 + t, 1] = av
        hb[S + 4 + t] = cut_r[t] / ln + au * su + av * sv - margin

    # Clip the bounding polygon (Sutherland-Hodgman); at most one vertex per halfplane.
    cap = S + n_h + 2
    pu = np.empty(cap)
    pv = np.empty(cap)
    tu = np.empty(cap)
    tv = np.empty(cap)
    for k in range(S):
        pu[k] = ou[k]
        pv[k] = ov[k]
    npv = S
    for h in range(S, n_h):
        ax, ay, beta = ha[h, 0], ha[h, 1], hb[h]
        nt = 0
        xu, xv = pu[npv - 1], pv[npv - 1]
        xd = ax * xu + ay * xv - beta
        for k in range(npv):
            zu, zv = pu[k], pv[k]
            zd = ax * zu + ay * zv - beta
            if zd <= 0.0:
                if xd > 0.0:
                    f = xd / (xd - zd)
                    tu[nt] = xu + f * (zu - xu)
                    tv[nt] = xv + f * (zv - xv)
                    nt += 1
                tu[nt] = zu
                tv[nt] = zv
                nt += 1
            elif xd <= 0.0:
                f = xd / (xd - zd)
                tu[nt] = xu + f * (zu - xu)
                tv[nt] = xv + f * (zv - xv)
                nt += 1
            xu, xv, xd = zu, zv, zd
        if nt < 3:
            return np.empty((0, 2)), np.empty(0), np.empty((0, 2))
        for k in range(nt):
            pu[k] = tu[k]
            pv[k] = tv[k]
        npv = nt

    scale = 1.0 + max(abs(su), abs(sv)) + max(umax - umin, vmax - vmin)
    eps = 1e-12 * scale
    # Drop repeated vertices (a clip through an existing vertex).
    nv_ = 0
    for k in range(npv):
        if nv_ == 0 or abs(pu[k] - tu[nv_ - 1]) > eps or abs(pv[k] - tv[nv_ - 1]) > eps:
            tu[nv_] = pu[k]
            tv[nv_] = pv[k]
            nv_ += 1
    while nv_ > 1 and abs(tu[0] - tu[nv_ - 1]) <= eps and abs(tv[0] - tv[nv_ - 1]) <= eps:
        nv_ -= 1
    if nv_ < 3:
        return np.empty((0, 2)), np.empty(0), np.empty((0, 2))
    V = np.empty((nv_, 2))
    for k in range(nv_):
        V[k, 0] = tu[k]
        V[k, 1] = tv[k]
    # Keep the halfplanes that carry an edge (two vertices on the line).
    keep = np.zeros(n_h, dtype=np.bool_)
    n_keep = 0
    tight = _TIGHT_REL * scale
    for h in range(n_h):
        cnt = 0
        for k in range(nv_):
            if hb[h] - (ha[h, 0] * V[k, 0] + ha[h, 1] * V[k, 1]) <= tight:
                cnt += 1
        if cnt >= 2:
            keep[h] = True
            n_keep += 1
    A = np.empty((n_keep, 2))
    b = np.empty(n_keep)
    t = 0
    for h in range(n_h):
        if keep[h]:
            A[t, 0], A[t, 1], b[t] = ha[h, 0], ha[h, 1], hb[h]
            t += 1
    return A, b, V


@njit(cache=True)
def _hull(x, y):  # pragma: no cover - compiled
    """Indices of the convex hull vertices (monotone chain, CCW, collinear dropped)."""
    n = x.shape[0]
    order = np.argsort(x * 1.0)
    # Stable tie-break on y within equal x (insertion sort on short runs).
    for i in range(1, n):
        j = i
        while j > 0 and x[order[j - 1]] == x[order[j]] and y[order[j - 1]] > y[order[j]]:
            order[j - 1], order[j] = order[j], order[j - 1]
            j -= 1
    out = np.empty(2 * n + 1, dtype=np.int64)
    k = 0
    for t in range(n):
        i = order[t]
        while k >= 2 and _cross(x, y, out[k - 2], out[k - 1], i) <= 0.0:
            k -= 1
        out[k] = i
        k += 1
    lo = k + 1
    for t in range(n - 2, -1, -1):
        i = order[t]
        while k >= lo and _cross(x, y, out[k - 2], out[k - 1], i) <= 0.0:
            k -= 1
        out[k] = i
        k += 1
    return out[: max(k - 1, 0)]


@njit(cache=True)
def _cross(x, y, o, a, b):  # pragma: no cover - compiled
    return (x[a] - x[o]) * (y[b] - y[o]) - (y[a] - y[o]) * (x[b] - x[o])


@njit(cache=True)
def mark_interior(A, b, V, covered, owner, idx, tol):  # pragma: no cover - compiled
    """Mark cells whose centre is strictly inside ``A x < b - tol``; new ones get ``idx``."""
    rows, cols = covered.shape
    c0 = max(int(math.floor(V[:, 0].min())), 0)
    c1 = min(int(math.ceil(V[:, 0].max())), cols)
    r0 = max(int(math.floor(V[:, 1].min())), 0)
    r1 = min(int(math.ceil(V[:, 1].max())), rows)
    m = b.shape[0]
    for r in range(r0, r1):
        y = r + 0.5
        for c in range(c0, c1):
            x = c + 0.5
            ok = True
            for h in range(m):
                if A[h, 0] * x + A[h, 1] * y >= b[h] - tol:
                    ok = False
                    break
            if ok:
                if not covered[r, c]:
                    covered[r, c] = True
                    owner[r, c] = idx
    return


@njit(cache=True)
def overlaps_blocked(A, b, V, blocked, tol):  # pragma: no cover - compiled
    """Whether the polygon overlaps (thicker than ``tol``) any square of ``blocked``."""
    rows, cols = blocked.shape
    xmin, xmax = V[:, 0].min(), V[:, 0].max()
    ymin, ymax = V[:, 1].min(), V[:, 1].max()
    c0 = max(int(math.floor(xmin)) - 1, 0)
    c1 = min(int(math.ceil(xmax)) + 1, cols)
    r0 = max(int(math.floor(ymin)) - 1, 0)
    r1 = min(int(math.ceil(ymax)) + 1, rows)
    m = b.shape[0]
    for r in range(r0, r1):
        for c in range(c0, c1):
            if not blocked[r, c]:
                continue
            if c + 1.0 <= xmin + tol or c >= xmax - tol or r + 1.0 <= ymin + tol or r >= ymax - tol:
                continue
            sep = False
            for h in range(m):
                lo = A[h, 0] * c + A[h, 1] * r + min(A[h, 0], 0.0) + min(A[h, 1], 0.0)
                if lo >= b[h] - tol:
                    sep = True
                    break
            if not sep:
                return True
    return False


@njit(cache=True)
def overlap_groups(A, b, h_off, V, v_off, tol):  # pragma: no cover - compiled
    """Connected-component label per polygon of the graph "overlaps with area".

    Polygon ``i`` is rows ``h_off[i]:h_off[i+1]`` of ``A, b`` and ``v_off[i]:v_off[i+1]``
    of ``V``. Two convex polygons are apart when some face of either has the other's
    vertices all at or beyond it (within ``tol``): the separating axis test.
    """
    n = h_off.shape[0] - 1
    parent = np.arange(n)
    box = np.empty((n, 4))
    for i in range(n):
        vs = V[v_off[i]:v_off[i + 1]]
        box[i, 0], box[i, 1] = vs[:, 0].min(), vs[:, 1].min()
        box[i, 2], box[i, 3] = vs[:, 0].max(), vs[:, 1].max()
    for i in range(n):
        for j in range(i + 1, n):
            if box[j, 0] >= box[i, 2] or box[j, 2] <= box[i, 0] or box[j, 1] >= box[i, 3] or box[j, 3] <= box[i, 1]:
                continue
            ri = i
            while parent[ri] != ri:
                ri = parent[ri]
            rj = j
            while parent[rj] != rj:
                rj = parent[rj]
            if ri == rj:
                continue
            if _apart(A, b, h_off[i], h_off[i + 1], V, v_off[j], v_off[j + 1], tol):
                continue
            if _apart(A, b, h_off[j], h_off[j + 1], V, v_off[i], v_off[i + 1], tol):
                continue
            parent[rj] = ri
    out = np.empty(n, dtype=np.int64)
    for i in range(n):
        r = i
        while parent[r] != r:
            r = parent[r]
        out[i] = r
    return out


@njit(cache=True)
def _apart(A, b, h0, h1, V, v0, v1, tol):  # pragma: no cover - compiled
    for h in range(h0, h1):
        beyond = True
        for k in range(v0, v1):
            if A[h, 0] * V[k, 0] + A[h, 1] * V[k, 1] < b[h] - tol:
                beyond = False
                break
        if beyond:
            return True
    return False


@njit(cache=True)
def bfs_labels(tflat, flat, rows, cols):  # pragma: no cover - compiled
    """Multi-source BFS over 4-connected ``tflat`` cells from the labelled ones.

    Flat row-major arrays: ``tflat`` (bool) the cells to walk, ``flat`` (int64 label,
    -1 = none) filled in place. Returns ``(dist, parent)``, ``parent`` being the flat
    index of the cell each one was reached from (-1 for sources).
    """
    n = rows * cols
    dist = np.full(n, -1, dtype=np.int64)
    parent = np.full(n, -1, dtype=np.int64)
    queue = np.empty(n, dtype=np.int64)
    head = 0
    tail = 0
    for i in range(n):
        if flat[i] >= 0:
            dist[i] = 0
            queue[tail] = i
            tail += 1
    while head < tail:
        i = queue[head]
        head += 1
        r = i // cols
        c = i - r * cols
        for k in range(4):
            rr, cc = r, c
            if k == 0:
                cc = c + 1
            elif k == 1:
                cc = c - 1
            elif k == 2:
                rr = r + 1
            else:
                rr = r - 1
            if rr < 0 or rr >= rows or cc < 0 or cc >= cols:
                continue
            j = rr * cols + cc
            if tflat[j] and dist[j] < 0:
                dist[j] = dist[i] + 1
                parent[j] = i
                flat[j] = flat[i]
                queue[tail] = j
                tail += 1
    return dist, parent


@njit(cache=True)
def carve(cu, cv, eu, ev, include_end, stoppable, stop, rows, cols, seen_free):  # pragma: no cover - compiled
    """Mark the cells a 2D ray from ``(cu, cv)`` to each ``(eu[i], ev[i])`` passes over.

    Cell units. Cells strictly before the end cell are marked, the end cell too when
    ``include_end[i]`` (a ground return); a ray with ``stoppable[i]`` ends at the first cell
    ``stop`` holds. Amanatides-Woo grid traversal.
    """
    for i in range(eu.shape[0]):
        x, y = cu, cv
        dx, dy = eu[i] - x, ev[i] - y
        c, r = int(math.floor(x)), int(math.floor(y))
        ce, re = int(math.floor(eu[i])), int(math.floor(ev[i]))
        sx = 1 if dx > 0 else -1
        sy = 1 if dy > 0 else -1
        tdx = abs(1.0 / dx) if dx != 0 else np.inf
        tdy = abs(1.0 / dy) if dy != 0 else np.inf
        tx = ((c + 1 - x) if dx > 0 else (x - c)) * tdx if dx != 0 else np.inf
        ty = ((r + 1 - y) if dy > 0 else (y - r)) * tdy if dy != 0 else np.inf
        steps = abs(ce - c) + abs(re - r)
        for _ in range(steps + 1):
            at_end = c == ce and r == re
            if at_end and not include_end[i]:
                break
            if 0 <= r < rows and 0 <= c < cols:
                if stoppable[i] and stop[r, c]:
                    break
                seen_free[r, c] = True
            if at_end:
                break
            if tx < ty:
                tx += tdx
                c += sx
            else:
                ty += tdy
                r += sy
    return
