"""Bezier MPC over waypoints and control points (thesis eqs. 6.12 and 7.2).

Decision variables: the waypoints ``x_0 .. x_N`` (each in R^n) and, for orders above
``2 gamma - 1``, each segment's free control points ``Z_k``. Segment ``k`` is the Bezier
curve ``C_k = M [x_k; x_{k+1}] + N Z_k`` of duration ``tau`` (Property 2.45), so every
feasible point of the QP is a dynamically feasible trajectory of the planning model,
continuous in every derivative below ``gamma``.

Constraints (all linear, all on control points, so they hold for all time):

- ``x_0`` within ``init_radius`` of the measured state (7.2b), ``x_N = r_N`` (7.2e) or free;
- trust region ``|x_k - r_k| <= trust_region`` componentwise (6.12b; a box in place of
  the thesis's 1-norm ball: same role, no auxiliary variables);
- the reachability rows ``F [x_k; x_{k+1}; Z_k] <= G`` (6.12d / 7.2d) of
  :class:`onboard.high_level.tracking.reachability.BezierReachability` (state limits tightened by the tube,
  input limits), with per-segment references for nonlinear models;
- per segment, up to ``max_planes`` halfspaces ``a . q <= b`` on every position control
  point (7.2c separating hyperplanes or the faces of the convex set ``X_k`` of 6.12),
  tightened here by the tube (dual norm). The robot radius belongs in ``b``.

Cost: ``sum_k (x_k - r_k)' Q (x_k - r_k) + (x_N - r_N)' V (x_N - r_N)`` plus per
segment ``effort * integral ||q^(gamma)||^2 dt`` and ``path * sum_j ||C_{j+1} - C_j||^2``
(a quadratic surrogate of the path-length bound 2.49).

The QP is set up once; each :meth:`BezierMpc.solve` updates values only (never the
sparsity pattern), warm starts (OSQP), solves and then *certifies* the answer: every
inequality is re-evaluated against the untightened bounds, so ``ok`` means the returned
trajectory satisfies its constraints whatever the solver's status. Inequalities are
tightened by ``margin`` so that a solver's small residual never becomes a violation.
Before the solve, each row is bounded over the box the waypoint bounds give (interval
arithmetic); a row that holds nowhere in it (a pinned end past an obstacle's face) is refused
at once, with zero iterations, since no answer to it could ever be certified.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
import scipy.sparse as sp

from onboard.geometry import bezier as bz
from onboard.contracts.messages import BezierSegment, ComReference
from onboard.high_level.tracking.mpc_backends import OSQP_INFEASIBLE, QpBackends
from onboard.high_level.tracking.reachability import BezierReachability

Backend = Literal["osqp", "piqp"]

_ATTEMPTS = 2  # a second, tighter ADMM pass when neither the iterate nor its polish certifies
_RETRY_EPS_FACTOR = 0.01


@dataclass(frozen=True)
class MpcWeights:
    """Cost weights. ``state``/``terminal``: diagonal of ``Q``/``V`` over the state."""

    state: tuple[float, ...]
    terminal: tuple[float, ...]
    effort: float = 0.0  # per integral of ||q^(gamma)||^2 [1/(unit^2 s^(1-2 gamma))]
    path: float = 0.0  # per sum of squared control-polygon legs


@dataclass(frozen=True)
class MpcSolution:
    """One solve: the trajectory and whether it may be used."""

    ok: bool  # certified: finite, inequalities hold, equalities within tolerance
    status: str  # the solver's own status string
    waypoints: np.ndarray  # (N + 1, n)
    control_points: np.ndarray  # (N, p + 1, m): position control points per segment
    tau: float  # segment duration [s]
    objective: float
    iterations: int
    max_violation: float  # largest inequality excess over the untightened bound (<= 0 is fine)
    equality_residual: float

    @property
    def duration(self) -> float:
        return self.tau * len(self.control_points)

    def evaluate(self, t: np.ndarray, derivative: int = 0) -> np.ndarray:
        """Position (or its ``derivative``) at times ``t`` [s] from the trajectory start."""
        t = np.clip(np.asarray(t, dtype=float), 0.0, self.duration)
        seg = np.minimum((t / self.tau).astype(int), len(self.control_points) - 1)
        out = np.empty(t.shape + (self.control_points.shape[-1],))
        for k in np.unique(seg):
            sel = seg == k
            C = bz.derivative_points(self.control_points[k], self.tau, derivative)
            out[sel] = bz.evaluate(C, self.tau, t[sel] - k * self.tau)
        return out

    def to_com_reference(self, t_ref_ns: int, stamp_ns: int = 0, segments: int | None = None) -> ComReference:
        """The trajectory as the message the low level tracks (positions in metres)."""
        count = len(self.control_points) if segments is None else min(segments, len(self.control_points))
        segs = [
            BezierSegment(t0=k * self.tau, duration=self.tau, control_points=self.control_points[k].tolist())
            for k in range(count)
        ]
        return ComReference(stamp_ns=stamp_ns, t_ref_ns=t_ref_ns, segments=segs, hold=not self.ok)


@dataclass(eq=False)
class BezierMpc(QpBackends):
    """The Bezier MPC QP for one reachability model, horizon and plane budget.

    ``init_radius`` (``(n,)``) is how far ``x_0`` may sit from the measured state (the
    tube, 7.2b); a zero component is an equality. ``terminal="equal"`` pins ``x_N`` to
    the reference. ``margin`` tightens every inequality (in each row's physical unit);
    ``eps`` is the solver accuracy; ``max_iter`` caps OSQP's iterations (the thesis ran 50).

    Accuracy and speed: acceleration rows have ``(p / tau)^2``-sized coefficients on the
    positions, so a physical residual of ``margin`` on them needs position accuracy of
    about ``margin * tau^2 / 6``. With ``unit_rows=True`` (default) the solver sees unit
    rows and stops early (relative tolerance); polishing then usually makes the answer
    exact, and the certificate rejects the few answers it does not (``ok=False``: the
    caller keeps its previous plan). ``unit_rows=False`` keeps physical rows with an
    absolute tolerance: every converged answer certifies, at several times the
    iterations.
    """

    reach: BezierReachability
    horizon: int
    weights: MpcWeights
    trust_region: np.ndarray | None = None
    init_radius: np.ndarray | None = None
    max_planes: int = 0
    terminal: Literal["equal", "free"] = "equal"
    backend: Backend = "osqp"
    eps: float = 1e-4  # OSQP tolerance (PIQP: eps / 100)
    margin: float = 1e-3  # [units of each row: m, m/s, m/s^2] tightening seen by the solver
    max_iter: int = 500  # bounds the solve time; an unconverged answer is used only if certified
    # [s] OSQP's own limit on each attempt (0: none). A real-time caller bounds its refinement by
    # it; lockstep runs leave it 0, so that their answers do not depend on the machine's speed.
    time_limit_s: float = 0.0
    polish: bool = True  # active-set polishing: exact answers from loose iterates (OSQP's, then ours)
    unit_rows: bool = True  # see above
    _ready: bool = field(default=False, init=False)

    def __post_init__(self) -> None:
        R, N = self.reach, self.horizon
        n = R.n
        if N < 1:
            raise ValueError("horizon must be >= 1")
        if len(self.weights.state) != n or len(self.weights.terminal) != n:
            raise ValueError(f"state and terminal weights need {n} entries")
        if min(self.weights.state) < 0 or min(self.weights.terminal) < 0 or self.weights.effort < 0 or self.weights.path < 0:
            raise ValueError("weights must be non-negative")
        self.trust = np.full(n, np.inf) if self.trust_region is None else np.broadcast_to(np.asarray(self.trust_region, float), (n,)).copy()
        self.x0_radius = np.zeros(n) if self.init_radius is None else np.broadcast_to(np.asarray(self.init_radius, float), (n,)).copy()
        if not (self.time_limit_s >= 0.0 and math.isfinite(self.time_limit_s)):
            raise ValueError(f"time_limit_s must be finite and >= 0, got {self.time_limit_s}")
        if np.any(self.trust <= self.margin) or np.any(self.x0_radius < 0):
            raise ValueError("trust region must exceed the margin, init radius non-negative")
        if np.any((self.x0_radius > 0) & (self.x0_radius <= self.margin)):
            raise ValueError("a non-zero init radius must exceed the margin")
        self.nx = (N + 1) * n
        self.nvar = self.nx + N * R.nz
        self._split_rows()
        self._build_cost()
        self._build_constraints()
        self._setup_solver()

    # --- structure ----------------------------------------------------------------

    def _seg_cols(self, k: int) -> np.ndarray:
        """Global variable index of each entry of segment k's vector ``[x_k; x_k+1; Z_k]``."""
        R, n = self.reach, self.reach.n
        return np.concatenate([np.arange(k * n, (k + 2) * n), self.nx + k * R.nz + np.arange(R.nz)]).astype(int)

    def _split_rows(self) -> None:
        """Separate rows acting on one waypoint only (imposed once per node) when G is
        constant; pair each remaining row with its negation (one two-sided row)."""
        R, n = self.reach, self.reach.n
        F = R.F_full
        if R.G_const is None:
            self._pair_seg_rows(np.arange(F.shape[0]))
            self.node_A = np.zeros((0, n))
            self.node_b = np.zeros(0)
            return
        only0 = ~np.any(F[:, n:], axis=1)
        onlyT = ~np.any(F[:, :n], axis=1) & ~np.any(F[:, 2 * n :], axis=1)
        node = np.vstack([F[only0, :n], F[onlyT, n : 2 * n]])
        rhs = np.concatenate([R.G_const[only0], R.G_const[onlyT]])
        _, idx = np.unique(np.round(np.column_stack([node, rhs]), 12), axis=0, return_index=True)
        node, rhs = node[np.sort(idx)], rhs[np.sort(idx)]
        self._pair_seg_rows(np.flatnonzero(~(only0 | onlyT)))
        # axis-aligned node rows fold into the waypoint bounds
        self.node_lo = np.full(n, -np.inf)
        self.node_hi = np.full(n, np.inf)
        keep = []
        for row, b in zip(node, rhs):
            nz = np.flatnonzero(row)
            if len(nz) == 1:
                c = row[nz[0]]
                if c > 0:
                    self.node_hi[nz[0]] = min(self.node_hi[nz[0]], b / c)
                else:
                    self.node_lo[nz[0]] = max(self.node_lo[nz[0]], b / c)
            else:
                keep.append((row, b))
        self.node_A = np.array([r for r, _ in keep]).reshape(-1, n)
        self.node_b = np.array([b for _, b in keep])

    def _pair_seg_rows(self, rows: np.ndarray) -> None:
        """``seg_rows``: the segment rows of ``F_full`` the QP imposes as upper bounds;
        ``seg_lower``: the row whose negation each one is (its lower bound), -1 for none.
        The reachability rows come in such pairs (|velocity|, |acceleration| <= limit):
        one two-sided row instead of two halves the rows ADMM iterates on."""
        F = self.reach.F_full[rows]
        scale = np.abs(F).max(axis=1, keepdims=True)
        key = np.round(F / np.where(scale > 0, scale, 1.0), 12) + 0.0  # + 0.0: no negative zeros
        index = {k.tobytes(): i for i, k in enumerate(key)}
        taken = np.zeros(len(rows), bool)
        upper, lower = [], []
        for i in range(len(rows)):
            if taken[i]:
                continue
            taken[i] = True
            j = index.get((-key[i] + 0.0).tobytes(), -1)
            if j >= 0 and not taken[j]:
                taken[j] = True
                lower.append(rows[j])
            else:
                lower.append(-1)
            upper.append(rows[i])
        self.seg_rows = np.array(upper, int)
        self.seg_lower = np.array(lower, int)

    def _seg_bounds(self, G: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Lower and upper bounds of the (scaled) segment rows from right-hand sides ``G`` ``(..., K)``."""
        paired = self.seg_lower >= 0
        lo = np.where(paired, -G[..., self.seg_lower], -np.inf)
        return lo / self.seg_scale, G[..., self.seg_rows] / self.seg_scale

    def _build_cost(self) -> None:
        R, N, W = self.reach, self.horizon, self.weights
        m, p = R.model.m, R.p
        tau = float(R.tau)
        Hg = np.linalg.matrix_power(bz.derivative_matrix(p, tau), R.model.gamma)
        effort = Hg @ bz.gram_matrix(p, tau) @ Hg.T  # C' E C = integral ||q^(gamma)||^2
        diff = np.diff(np.eye(p + 1), axis=0)
        pts = W.effort * effort + W.path * diff.T @ diff
        seg_cost = R.segment_map.T @ np.kron(pts, np.eye(m)) @ R.segment_map  # (ns, ns)
        P = sp.lil_matrix((self.nvar, self.nvar))
        Qd = np.asarray(W.state, float)
        Vd = np.asarray(W.terminal, float)
        diag = np.concatenate([np.tile(Qd, N), Vd])
        P[np.arange(self.nx), np.arange(self.nx)] = diag
        P = P.tocsc() + sp.csc_matrix((self.nvar, self.nvar))
        rows, cols, vals = [], [], []
        for k in range(N):
            c = self._seg_cols(k)
            rr, cc = np.meshgrid(c, c, indexing="ij")
            rows.append(rr.ravel())
            cols.append(cc.ravel())
            vals.append(seg_cost.ravel())
        P = P + sp.csc_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=P.shape)
        P = 2.0 * P  # the solvers minimize 0.5 y' P y + q' y
        P.data[np.abs(P.data) < 1e-14 * max(1.0, np.abs(P.data).max())] = 0.0
        P.eliminate_zeros()
        self.P = sp.csc_matrix(sp.triu(P, format="csc"))
        self.P.sort_indices()
        self._P_full = sp.csr_matrix(P)
        coo = P.tocoo()
        self._P_full_coo = (coo.row.astype(np.int64), coo.col.astype(np.int64), coo.data)
        self.q_diag = diag

    def _build_constraints(self) -> None:
        R, N = self.reach, self.horizon
        n, m, p = R.n, R.model.m, R.p
        coo_r, coo_c, coo_v = [], [], []
        row = 0

        def add(r, c, v):
            coo_r.append(np.asarray(r, int))
            coo_c.append(np.asarray(c, int))
            coo_v.append(np.asarray(v, float))

        # (a) waypoint bounds: one identity row per waypoint entry
        self.r_box = slice(row, row + self.nx)
        add(np.arange(self.nx), np.arange(self.nx), np.ones(self.nx))
        row += self.nx
        # (b) node rows
        kn = len(self.node_b)
        self.r_node = slice(row, row + kn * (N + 1))
        for k in range(N + 1):
            rr, cc = np.nonzero(self.node_A)
            add(row + k * kn + rr, k * n + cc, self.node_A[rr, cc])
        row += kn * (N + 1)
        # (c) segment reachability rows
        # Rows scaled by seg_scale (1: physical units, so that margin and solver residual
        # mean the same on every row; unit rows condition ADMM better but then need an
        # accuracy of margin / scale).
        self.seg_scale = np.abs(R.F_full[self.seg_rows]).max(axis=1) if self.unit_rows else np.ones(len(self.seg_rows))
        Fs = R.F_full[self.seg_rows] / self.seg_scale[:, None]
        ks = len(self.seg_rows)
        self.r_seg = slice(row, row + ks * N)
        rr, cc = np.nonzero(Fs)
        for k in range(N):
            add(row + k * ks + rr, self._seg_cols(k)[cc], Fs[rr, cc])
        row += ks * N
        # (d) plane rows: plane h on position control point j of segment k
        P_ = self.max_planes
        nrow_planes = N * P_ * (p + 1)
        self.r_plane = slice(row, row + nrow_planes)
        MN = R.segment_map.reshape(p + 1, m, R.ns)  # position point j, coord d -> s
        ent = [(j, d, s, MN[j, d, s]) for j in range(p + 1) for d in range(m) for s in np.flatnonzero(MN[j, d])]
        ej = np.array([e[0] for e in ent], int)
        ed = np.array([e[1] for e in ent], int)
        es = np.array([e[2] for e in ent], int)
        ecoef = np.array([e[3] for e in ent])
        self._plane_start = sum(len(v) for v in coo_v)
        pflat, pcoef = [], []  # each plane entry: index into the flat (N, P, m) normals, coefficient
        for k in range(N):
            cols = self._seg_cols(k)
            for h in range(P_):
                base = row + (k * P_ + h) * (p + 1)
                add(base + ej, cols[es], np.zeros(len(ej)))
                pflat.append((k * P_ + h) * m + ed)
                pcoef.append(ecoef)
        row += nrow_planes
        self._pflat = np.concatenate(pflat) if pflat else np.zeros(0, int)
        self._pcoef = np.concatenate(pcoef) if pcoef else np.zeros(0)
        r_all = np.concatenate(coo_r)
        c_all = np.concatenate(coo_c)
        v_all = np.concatenate(coo_v)
        # CSC with explicit zeros kept: build on entry ids, then read back the order
        ids = sp.csc_matrix((np.arange(1, len(v_all) + 1, dtype=float), (r_all, c_all)), shape=(row, self.nvar))
        ids.sort_indices()
        if ids.nnz != len(v_all):
            raise AssertionError("duplicate constraint entries")
        self._perm = ids.data.astype(int) - 1
        self._A_indices = ids.indices.copy()
        self._A_indptr = ids.indptr.copy()
        self._entry_cols = np.repeat(np.arange(self.nvar), np.diff(self._A_indptr))  # each stored entry's column
        self._coo_vals = v_all
        where = np.empty_like(self._perm)
        where[self._perm] = np.arange(len(self._perm))
        self._plane_pos = where[self._plane_start :]  # the plane entries in the matrix's data
        # the same matrix by rows (the polish gathers active rows): pattern, and where each
        # row-major entry sits in the column-major data
        by_rows = ids.tocsr()
        self._row_ptr, self._row_cols = by_rows.indptr, by_rows.indices
        self._row_data_pos = where[by_rows.data.astype(int) - 1]
        self.n_rows = row
        # static bounds
        self.row_margin = np.full(row, self.margin)
        self.row_margin[self.r_seg] = np.tile(self.margin / self.seg_scale, N)
        self.l_static = np.full(row, -np.inf)
        self.u_static = np.full(row, np.inf)
        self.u_static[self.r_node] = np.tile(self.node_b, N + 1)
        if R.G_const is not None:
            lo, hi = self._seg_bounds(R.G_const)
            self.l_static[self.r_seg], self.u_static[self.r_seg] = np.tile(lo, N), np.tile(hi, N)

    def _A_matrix(self) -> sp.csc_matrix:
        return sp.csc_matrix((self._coo_vals[self._perm], self._A_indices, self._A_indptr), shape=(self.n_rows, self.nvar))

    @property
    def _eps_rel(self) -> float:
        return self.eps if self.unit_rows else 0.0

    # --- per tick -------------------------------------------------------------------

    def _plane_values(self, planes: tuple[np.ndarray, np.ndarray] | None) -> tuple[np.ndarray, np.ndarray]:
        R, N, P_ = self.reach, self.horizon, self.max_planes
        m, p = R.model.m, R.p
        if planes is None:
            a = np.zeros((N, P_, m))
            b = np.full((N, P_), np.inf)
        else:
            a = np.asarray(planes[0], float)
            b = np.asarray(planes[1], float)
            if a.shape != (N, P_, m) or b.shape != (N, P_):
                raise ValueError(f"planes must be ({N}, {P_}, {m}) and ({N}, {P_}); pad with b = inf")
            if not np.all(np.isfinite(a)) or np.any(np.isnan(b)):
                raise ValueError("plane normals must be finite and offsets not NaN")
            dual = {1: np.inf, 2: 2, np.inf: 1}[R.limits.tube_norm]
            b = b - np.linalg.norm(a, ord=dual, axis=-1) * R.limits.tube
        vals = a.reshape(-1)[self._pflat] * self._pcoef
        rhs = np.repeat(b, p + 1, axis=1).reshape(-1)  # row order: (k, h, j)
        return vals, rhs

    def solve(
        self,
        x_init: np.ndarray,
        reference: np.ndarray,
        planes: tuple[np.ndarray, np.ndarray] | None = None,
        warm_start: np.ndarray | None = None,
        shift: int = 0,
        target: np.ndarray | None = None,
    ) -> MpcSolution:
        """Solve for measured ``x_init`` ``(n,)`` and reference waypoints ``(N + 1, n)``.

        ``planes``: ``(a, b)`` of shapes ``(N, max_planes, m)`` and ``(N, max_planes)``;
        unused planes have ``b = inf``. ``warm_start``: waypoints ``(N + 1, n)`` (for
        example the graph path). ``shift``: knots the window advanced since the last
        solve; OSQP then starts from the last solution shifted by as many knots, the new
        knots on the reference (otherwise from the last solution as it is).
        ``warm_start`` replaces the primal waypoints. ``target`` ``(N + 1, n)``: what the
        cost tracks when it differs from the reference that centres the trust region and
        the references of nonlinear models (eq. 6.12: cost to the origin, trust region
        to a feasible reference).
        """
        R, N = self.reach, self.horizon
        n = R.n
        x_init = np.asarray(x_init, float)
        ref = np.asarray(reference, float)
        if x_init.shape != (n,) or ref.shape != (N + 1, n):
            raise ValueError(f"x_init must be ({n},) and reference ({N + 1}, {n})")
        if not (np.all(np.isfinite(x_init)) and np.all(np.isfinite(ref))):
            raise ValueError("x_init and reference must be finite")
        goal = ref if target is None else np.asarray(target, float)
        if goal.shape != ref.shape or not np.all(np.isfinite(goal)):
            raise ValueError(f"target must be finite and ({N + 1}, {n})")
        q = np.zeros(self.nvar)
        q[: self.nx] = -2.0 * self.q_diag * goal.reshape(-1)
        l, u = self.l_static.copy(), self.u_static.copy()  # the true bounds
        lo = ref - self.trust
        hi = ref + self.trust
        if R.G_const is not None:
            lo = np.maximum(lo, self.node_lo)
            hi = np.minimum(hi, self.node_hi)
        else:
            G = R.G(R.references(ref[:-1]))  # (N, K): references from each reference waypoint
            lo_seg, hi_seg = self._seg_bounds(G)
            l[self.r_seg], u[self.r_seg] = lo_seg.reshape(-1), hi_seg.reshape(-1)
        lo[0], hi[0] = x_init - self.x0_radius, x_init + self.x0_radius
        if self.terminal == "equal":
            lo[N] = hi[N] = ref[N]
        l[self.r_box], u[self.r_box] = lo.reshape(-1), hi.reshape(-1)
        vals, rhs = self._plane_values(planes)
        u[self.r_plane] = rhs
        A = self._A
        a_changed = self.max_planes > 0 and not np.array_equal(A.data[self._plane_pos], vals)
        if a_changed:  # new values in the same pattern; the solver refactors only then
            A.data[self._plane_pos] = vals
        if np.any(l > u) or np.any(np.isnan(u)):
            return self._certify(None, A, l, u, "infeasible bounds", 0, np.nan)
        # the solver sees every inequality tightened by the margin
        eq = l == u
        ls = np.where(eq, l, l + self.row_margin)
        us = np.where(eq, u, u - self.row_margin)
        if np.any(ls > us):
            return self._certify(None, A, l, u, "infeasible bounds", 0, np.nan)
        if self._start_outside_node_rows(lo[0], hi[0], us):
            # e.g. a measured speed past the speed bound: no answer exists, and an iterative solver
            # would spend its whole iteration budget finding that out
            return self._certify(None, A, l, u, "infeasible: the initial state breaks the state constraints", 0, np.nan)
        if self._row_outside_box(A, l, u):
            # e.g. the path's end at the horizon (7.2e pins it) lies past an obstacle's halfspace since
            # the obstacle moved: no answer exists, and the solver would spend its whole budget, twice
            return self._certify(None, A, l, u, "infeasible: a row holds nowhere in the waypoints' bounds", 0, np.nan)
        if self.backend == "osqp":
            upd = {"q": q, "l": ls, "u": us}
            if a_changed:
                upd["Ax"] = A.data
            self._solver.update(**upd)
            self._osqp_warm_start(warm_start, shift, ref)
            first = None
            for attempt in range(_ATTEMPTS):
                if attempt:  # refine the same iterate: tighter tolerance, then polish again
                    self._solver.update_settings(eps_abs=self.eps * _RETRY_EPS_FACTOR, eps_rel=self._eps_rel * _RETRY_EPS_FACTOR)
                res = self._solver.solve(raise_error=False)  # the status is checked below
                if attempt:
                    self._solver.update_settings(eps_abs=self.eps, eps_rel=self._eps_rel)
                status, obj = str(res.info.status), float(res.info.obj_val)
                if res.info.status_polish == 1:  # OSQP's polish replaced the iterate
                    status += " (osqp polish)"
                iters = int(res.info.iter) + (first.iterations if first is not None else 0)
                if not np.all(np.isfinite(res.x)):
                    return self._certify(None, A, l, u, status, iters, obj)
                self._last = res.x.copy()
                first = self._certify(res.x, A, l, u, status, iters, obj)
                if first.ok or not self.polish or res.info.status_val in OSQP_INFEASIBLE:
                    return first
                polished = self._polisher.polish(res.x, res.y, A, ls, us, q)
                if polished is not None:
                    obj_p = float(0.5 * polished @ (self._P_full @ polished) + q @ polished)
                    sol = self._certify(polished, A, l, u, status + " (polished)", iters, obj_p)
                    if sol.ok:
                        return sol
            return first
        else:
            x_l, x_u, b, g_l, g_u = self._piqp_split(ls, us)
            kw = {"c": q, "b": b, "h_l": g_l, "h_u": g_u, "x_l": x_l, "x_u": x_u}
            if a_changed:
                kw["G"] = A[self.r_box.stop :, :].tocsc()
            self._solver.update(**kw)
            st = self._solver.solve()
            rs = self._solver.result
            y, status, iters, obj = rs.x, str(st).split(".")[-1], int(rs.info.iter), float(rs.info.primal_obj)
        return self._certify(y, A, l, u, status, iters, obj)

    def _row_outside_box(self, A: sp.csc_matrix, l: np.ndarray, u: np.ndarray) -> bool:
        """Whether some row (beyond the waypoint bounds themselves) holds for no point of the box
        the waypoint bounds ``l, u`` give (the free control points unbounded), against the true
        bounds: interval arithmetic over each row, the box widened by the equality residual the
        certificate accepts, so a row found here could never be certified whatever the solver did."""
        box = self.r_box
        slack = 10 * self.eps * (1.0 + float(np.abs(l[box]).max(initial=0.0)))
        var_lo = np.full(self.nvar, -np.inf)
        var_hi = np.full(self.nvar, np.inf)
        var_lo[: self.nx] = l[box] - slack
        var_hi[: self.nx] = u[box] + slack
        a = A.data
        lo_e, hi_e = var_lo[self._entry_cols], var_hi[self._entry_cols]
        with np.errstate(invalid="ignore"):  # 0 * inf: explicit zeros (unused planes) add nothing
            least = np.where(a > 0, a * lo_e, np.where(a < 0, a * hi_e, 0.0))
            most = np.where(a > 0, a * hi_e, np.where(a < 0, a * lo_e, 0.0))
        row_least = np.bincount(A.indices, weights=least, minlength=self.n_rows)[box.stop :]
        row_most = np.bincount(A.indices, weights=most, minlength=self.n_rows)[box.stop :]
        lo, hi = l[box.stop :], u[box.stop :]
        inequality = lo < hi  # an equality row is certified within a residual: not judged here
        return bool(np.any(inequality & ((row_least > hi) | (row_most < lo))))

    def _start_outside_node_rows(self, lo0: np.ndarray, hi0: np.ndarray, us: np.ndarray) -> bool:
        """Whether some single-waypoint row (the speed polygon) holds for no first waypoint in
        the box ``[lo0, hi0]`` the initial state allows, as the solver sees the rows (tightened)."""
        if not len(self.node_b):
            return False
        centre, half = (lo0 + hi0) / 2, (hi0 - lo0) / 2
        least = self.node_A @ centre - np.abs(self.node_A) @ half  # each row's smallest value over the box
        return bool(np.any(least > us[self.r_node][: len(self.node_b)]))

    def _certify(self, y, A, l, u, status, iters, obj) -> MpcSolution:
        """Check the answer against the true (untightened) bounds."""
        R, N = self.reach, self.horizon
        n, m, p = R.n, R.model.m, R.p
        y = None if y is None else np.asarray(y, float)
        finite = y is not None and y.shape == (self.nvar,) and bool(np.all(np.isfinite(y)))
        if not finite:
            y = np.full(self.nvar, np.nan)
        Ay = A @ y
        eq = l == u
        if finite:  # infinite bounds give -inf excess: Ay is finite
            viol = float(np.max(np.maximum(Ay - u, l - Ay)[~eq], initial=-np.inf))
            eq_res = float(np.abs(Ay[eq] - l[eq]).max(initial=0.0))
        else:
            viol = eq_res = np.inf
        scale = 1.0 + float(np.abs(l[eq]).max(initial=0.0))
        ok = finite and viol <= 0.0 and eq_res <= 10 * self.eps * scale
        X = y[: self.nx].reshape(N + 1, n)
        S = np.concatenate([np.concatenate([X[:-1], X[1:]], axis=1), y[self.nx :].reshape(N, R.nz)], axis=1)
        C = (S @ R.segment_map.T).reshape(N, p + 1, m)
        return MpcSolution(
            ok=bool(ok), status=status, waypoints=X, control_points=C, tau=float(R.tau),
            objective=obj, iterations=iters, max_violation=viol, equality_residual=eq_res,
        )  # fmt: skip
