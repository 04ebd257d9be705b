"""Bezier reachable polytopes: a linear test ``F [x0; xT] <= G`` for dynamic feasibility.

Thesis chapter 6 (lines 2782-3062): Lemma 6.1, Theorem 6.2, Corollary 6.3.

Planning model (eq. 6.2), relative degree ``gamma``, coordinates ``q`` in R^m, state
``x = [q, q', ..., q^(gamma-1)]`` in R^n (``n = m * gamma``, position block first)::

    q^(gamma) = f(x) + g(x) u

The curve from ``x0`` to ``xT`` over ``[0, tau]`` is the Bezier curve ``C = M X + N Z``
(:func:`onboard.geometry.bezier.boundary_solution`); applying ``u = g(x)^-1 (q^(gamma) - f(x))``
(eq. 6.4) makes it an exact trajectory of the model. :class:`BezierReachability`
builds linear inequalities on the *segment vector* ``s = [x0; xT; vec(Z)]`` that imply,
for every ``t`` in ``[0, tau]``:

- state: ``A x(t) + v <= b`` for every tracking error ``v`` in the tube, i.e.
  ``A x <= b - ||A_i[sel]||_* e`` (dual-norm tightening, eq. 6.6);
- input: ``||u(t)||_inf <= u_max``.

The input bound is Lemma 6.1 with explicit choices: around a reference state
``xbar`` (constant on each piece of a k-refinement, Corollary 6.3),
``|q^(gamma)_j - f_j(x)| <= |q^(gamma)_j - f_j(xbar)| + sum_i L[j, i] |x_i - xbar_i|``
(componentwise Lipschitz matrix ``L`` of ``f``), and
``||g^-1(x)||_inf <= ||g^-1(xbar)||_inf + sum_i LG_i rho_i`` over a deviation box
``|x_i - xbar_i| <= rho_i``. The absolute values expand into sign rows, each linear in
``(x, q^(gamma))``; the joint curve ``(x(t), q^(gamma)(t))`` is itself a Bezier curve, so
imposing every row on its control points (Property 2.44) bounds the curve for all ``t``.
For the double integrator (``f = 0``, ``g = I``) this reduces to exact box constraints on
the acceleration control points and ``G`` is constant.

Only ``G`` depends on the references; ``F`` is constant. The edge test of the graph
planner (thesis ch. 7) uses the particular curve (``Z = 0``): ``F [x0; xT] <= G`` with
``F = F_full[:, :2n]``; :class:`EdgeTable` runs it over many node pairs.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from itertools import product
from typing import Literal

import numba
import numpy as np
import scipy.optimize

from onboard.geometry import bezier as bz

ReferenceMode = Literal["drift", "start"]

_TOL = 1e-9  # relative tolerance of the redundant-row test


@dataclass(frozen=True, eq=False)
class PlanningModel:
    """Control-affine model ``q^(gamma) = f(x) + g(x) u`` (thesis eq. 6.2).

    ``drift`` maps states ``(..., n)`` to ``(..., m)``; ``gain_inv`` maps states to
    ``g(x)^-1`` of shape ``(..., m, m)``. ``None`` means ``f = 0`` / ``g = I`` (the pure
    integrator chain). ``lipschitz_drift`` ``(m, n)``: ``|f_j(x) - f_j(y)| <= sum_i
    L[j, i] |x_i - y_i|``; ``lipschitz_gain_inv`` ``(n,)``: ``||g^-1(x) - g^-1(y)||_inf <=
    sum_i LG_i |x_i - y_i|``; both must hold on the bounding box of the state set.
    """

    m: int
    gamma: int
    drift: Callable[[np.ndarray], np.ndarray] | None = None
    gain_inv: Callable[[np.ndarray], np.ndarray] | None = None
    lipschitz_drift: np.ndarray | None = None
    lipschitz_gain_inv: np.ndarray | None = None
    name: str = "model"

    def __post_init__(self) -> None:
        if self.m < 1 or self.gamma < 1:
            raise ValueError("need m >= 1 and gamma >= 1")
        L = np.zeros((self.m, self.n)) if self.lipschitz_drift is None else np.array(self.lipschitz_drift, float)
        LG = np.zeros(self.n) if self.lipschitz_gain_inv is None else np.array(self.lipschitz_gain_inv, float)
        if L.shape != (self.m, self.n) or LG.shape != (self.n,):
            raise ValueError(f"Lipschitz shapes must be ({self.m}, {self.n}) and ({self.n},)")
        if np.any(L < 0) or np.any(LG < 0) or not (np.all(np.isfinite(L)) and np.all(np.isfinite(LG))):
            raise ValueError("Lipschitz constants must be finite and non-negative")
        if self.drift is not None and self.lipschitz_drift is None:
            raise ValueError("a drift needs its Lipschitz matrix (soundness depends on it)")
        object.__setattr__(self, "lipschitz_drift", L)
        object.__setattr__(self, "lipschitz_gain_inv", LG)

    @property
    def n(self) -> int:
        return self.m * self.gamma

    @property
    def constant_dynamics(self) -> bool:
        """True for the pure integrator chain: the test's ``G`` needs no reference."""
        return self.drift is None and self.gain_inv is None

    def f(self, x: np.ndarray) -> np.ndarray:
        x = np.asarray(x, dtype=float)
        return np.zeros(x.shape[:-1] + (self.m,)) if self.drift is None else np.asarray(self.drift(x), float)

    def g_inv(self, x: np.ndarray) -> np.ndarray:
        x = np.asarray(x, dtype=float)
        if self.gain_inv is None:
            return np.broadcast_to(np.eye(self.m), x.shape[:-1] + (self.m, self.m))
        return np.asarray(self.gain_inv(x), float)

    def input(self, x: np.ndarray, q_gamma: np.ndarray) -> np.ndarray:
        """Input ``u = g(x)^-1 (q^(gamma) - f(x))`` (eq. 6.4) realizing a curve."""
        return np.einsum("...ij,...j->...i", self.g_inv(x), np.asarray(q_gamma) - self.f(x))

    def vector_field(self, x: np.ndarray, u: np.ndarray | None = None) -> np.ndarray:
        """``dx/dt`` of eq. 6.2 (``u = None``: zero input, the drift flow)."""
        acc = self.f(x)
        if u is not None:
            acc = acc + np.linalg.solve(self.g_inv(x), np.asarray(u, float)[..., None])[..., 0]
        return np.concatenate([x[..., self.m :], acc], axis=-1)


def double_integrator(m: int = 2) -> PlanningModel:
    """``q'' = u`` in R^m: the CoM planning model of ARCHER (thesis ch. 7)."""
    return PlanningModel(m=m, gamma=2, name=f"double_integrator_{m}d")


def pendulum(mass: float, length: float, gravity: float = 9.81, damping: float = 0.0) -> PlanningModel:
    """Pendulum ``theta'' = -(g/l) sin(theta) - c theta' + u / (m l^2)``, theta = 0 hanging.

    State ``[theta, omega]`` [rad, rad/s], input torque [N m] (thesis Figure 6.6).
    """
    if mass <= 0 or length <= 0:
        raise ValueError("mass and length must be positive")
    g_over_l = gravity / length
    inertia = mass * length**2

    def drift(x: np.ndarray) -> np.ndarray:
        return (-g_over_l * np.sin(x[..., 0]) - damping * x[..., 1])[..., None]

    def gain_inv(x: np.ndarray) -> np.ndarray:
        return np.full(x.shape[:-1] + (1, 1), inertia)

    return PlanningModel(
        m=1,
        gamma=2,
        drift=drift,
        gain_inv=gain_inv,
        lipschitz_drift=np.array([[g_over_l, damping]]),
        name="pendulum",
    )


@dataclass(frozen=True, eq=False)
class ReachLimits:
    """State and input limits of a planning model, and the tracking tube.

    ``state_A x <= state_b`` with ``state_A`` of shape ``(k, n)`` (units of the state);
    ``u_max`` bounds ``||u||_inf`` (for the double integrator: the acceleration
    [m/s^2]). The tube: every tracking error ``v`` has ``||v[tube_components]||_tube_norm
    <= tube`` (default components: the position block ``q``). ``deviation`` (``(n,)``)
    is the box ``rho`` around each reference, needed only where ``lipschitz_gain_inv``
    is non-zero.
    """

    u_max: float
    state_A: np.ndarray
    state_b: np.ndarray
    tube: float = 0.0
    tube_norm: float = np.inf
    tube_components: tuple[int, ...] | None = None
    deviation: np.ndarray | None = None

    def __post_init__(self) -> None:
        A = np.atleast_2d(np.array(self.state_A, dtype=float))
        b = np.array(self.state_b, dtype=float).reshape(-1)
        if A.shape[0] != b.shape[0]:
            raise ValueError("state_A and state_b disagree in rows")
        if not (np.all(np.isfinite(A)) and np.all(np.isfinite(b))):
            raise ValueError("state limits must be finite (drop unbounded rows)")
        if not (self.u_max > 0 and np.isfinite(self.u_max)):
            raise ValueError("u_max must be positive and finite")
        if not (self.tube >= 0 and np.isfinite(self.tube)):
            raise ValueError("tube must be >= 0 and finite")
        if self.tube_norm not in (1, 2, np.inf):
            raise ValueError("tube_norm must be 1, 2 or inf")
        object.__setattr__(self, "state_A", A)
        object.__setattr__(self, "state_b", b)

    def tightened_b(self, m: int) -> np.ndarray:
        """``b - ||A_i[sel]||_* e``: the rows hold for every error in the tube (eq. 6.6)."""
        sel = list(range(m)) if self.tube_components is None else list(self.tube_components)
        dual = {1: np.inf, 2: 2, np.inf: 1}[self.tube_norm]
        return self.state_b - np.linalg.norm(self.state_A[:, sel], ord=dual, axis=1) * self.tube


def box_limits(
    model: PlanningModel,
    u_max: float,
    lower: np.ndarray,
    upper: np.ndarray,
    tube: float = 0.0,
    tube_norm: float = np.inf,
    deviation: np.ndarray | None = None,
) -> ReachLimits:
    """Box state limits ``lower <= x <= upper`` (infinite entries are left out)."""
    lower = np.broadcast_to(np.asarray(lower, float), (model.n,))
    upper = np.broadcast_to(np.asarray(upper, float), (model.n,))
    if np.any(lower >= upper):
        raise ValueError("need lower < upper")
    eye = np.eye(model.n)
    A = np.vstack([eye, -eye])
    b = np.concatenate([upper, -lower])
    keep = np.isfinite(b)
    return ReachLimits(u_max=u_max, state_A=A[keep], state_b=b[keep], tube=tube, tube_norm=tube_norm, deviation=deviation)


@dataclass(frozen=True)
class _RowTemplate:
    """One family of rows ``w . [x; q^(gamma)] <= rhs`` imposed on every checked point."""

    w: np.ndarray  # (n + m,)
    base: float  # constant part of rhs
    g_coef: float  # times u_max / gmax(xbar)
    f_sign: float  # times f_j(xbar)
    f_index: int
    xbar_coef: np.ndarray  # (n,), times xbar

    @property
    def constant(self) -> bool:
        return self.g_coef == 0.0 and self.f_sign == 0.0 and not np.any(self.xbar_coef)


@dataclass(frozen=True, eq=False)
class BezierReachability:
    """Linear feasibility test for Bezier segments of duration ``tau`` [s] (Theorem 6.2).

    ``order`` defaults to ``2 * gamma - 1`` (the unique connecting curve). ``refinement``
    is Corollary 6.3: an int ``k`` (equal pieces) or break times in [0, 1]; each piece gets
    its own reference state. ``check_order`` (>= order) elevates each piece before the
    control points are checked (Property 2.48: less conservative, more rows).
    ``reference`` chooses the references of nonlinear models: ``"drift"`` simulates the
    zero-input flow from the start state to each piece's midpoint, ``"start"`` uses the
    start state for every piece.

    After construction:

    - ``F_full`` ``(K, ns)`` acts on the segment vector ``s = [x0; xT; vec(Z)]``;
      ``F = F_full[:, :2n]``, ``F0``, ``FT`` its two halves (particular curve ``Z = 0``);
    - :meth:`G` gives the right-hand side for references ``xbar`` of shape ``(..., k, n)``
      (constant for the integrator chain: :attr:`G_const`);
    - ``segment_map`` ``((p+1) m, ns)``: ``vec(C) = segment_map @ s``.
    """

    model: PlanningModel
    limits: ReachLimits
    tau: float
    order: int | None = None
    refinement: int | np.ndarray = 1
    check_order: int | None = None
    weighting: bz.Weighting = "effort"
    reference: ReferenceMode = "drift"
    F_full: np.ndarray = field(init=False)
    segment_map: np.ndarray = field(init=False)

    def __post_init__(self) -> None:
        md, lim = self.model, self.limits
        if not (self.tau > 0 and np.isfinite(self.tau)):
            raise ValueError("tau must be positive")
        if lim.state_A.shape[1] != md.n:
            raise ValueError(f"state limits act on {lim.state_A.shape[1]} states, model has {md.n}")
        p = 2 * md.gamma - 1 if self.order is None else int(self.order)
        r = p if self.check_order is None else int(self.check_order)
        if r < p:
            raise ValueError("check_order must be >= order")
        LG = md.lipschitz_gain_inv
        rho = np.full(md.n, np.inf) if lim.deviation is None else np.asarray(lim.deviation, float)
        if rho.shape != (md.n,) or np.any(rho < 0) or np.any(LG[~np.isfinite(rho)] > 0):
            raise ValueError("a state-dependent g^-1 needs a finite deviation box where its Lipschitz constant is non-zero")
        self._set("p", p)
        self._set("breaks", bz.refinement_breaks(self.refinement))
        self._set("n_pieces", len(self.breaks) - 1)
        self._set("g_margin", float(np.dot(LG[LG > 0], rho[LG > 0])))
        self._set("state_box", _bounding_box(lim.state_A, lim.state_b))

        M, N = bz.boundary_solution(p, md.gamma, float(self.tau), self.weighting)
        MN = np.hstack([M, N])  # (p+1, 2 gamma + nz_points)
        m = md.m
        self._set("nz", N.shape[1] * m)
        self._set("segment_map", np.kron(MN, np.eye(m)))
        ns = 2 * md.n + self.nz

        # Checked points: per piece, per elevated control point, the joint vector
        # [x; q^(gamma)] (n + m) as a linear map of s.
        R = bz.elevation_matrix(p, r)
        H = [np.linalg.matrix_power(bz.derivative_matrix(p, float(self.tau)), k) for k in range(md.gamma + 1)]
        joint = np.empty((self.n_pieces, r + 1, md.n + m, ns))
        for i, (a, b) in enumerate(zip(self.breaks[:-1], self.breaks[1:])):
            S = (bz.split_matrix(p, float(a), float(b)) @ R).T  # piece points = S @ C
            for k in range(md.gamma + 1):
                E = S @ H[k].T @ MN  # (r+1, 2 gamma + nz_points)
                joint[i, :, k * m : (k + 1) * m, :] = np.kron(E[:, None, :], np.eye(m))
        templates = _row_templates(md, lim, rho)
        rows, meta = [], []
        for ti, tpl in enumerate(templates):
            fam = np.einsum("c,ijcs->ijs", tpl.w, joint)  # (pieces, points, ns)
            groups = [fam.reshape(-1, ns)] if tpl.constant else list(fam)
            pieces = [None] if tpl.constant else list(range(self.n_pieces))
            for grp, piece in zip(groups, pieces):
                for row in _prune_convex(grp):
                    rows.append(row)
                    meta.append((ti, -1 if piece is None else piece))
        F_full = np.array(rows).reshape(-1, ns)
        tpl_idx = np.array([t for t, _ in meta], dtype=int)
        self._set("F_full", F_full)
        self._set("row_piece", np.array([pc for _, pc in meta], dtype=int))
        self._set("_base", np.array([templates[t].base for t in tpl_idx]))
        self._set("_g_coef", np.array([templates[t].g_coef for t in tpl_idx]))
        self._set("_f_sign", np.array([templates[t].f_sign for t in tpl_idx]))
        self._set("_f_index", np.array([templates[t].f_index for t in tpl_idx], dtype=int))
        self._set("_xbar_coef", np.array([templates[t].xbar_coef for t in tpl_idx]).reshape(-1, md.n))
        self._set("G_const", self.G(np.zeros((self.n_pieces, md.n))) if md.constant_dynamics else None)
        if lim.state_A.shape[0]:
            feas = scipy.optimize.linprog(
                np.zeros(md.n), A_ub=lim.state_A, b_ub=lim.tightened_b(m), bounds=[(None, None)] * md.n, method="highs"
            )
            if feas.status == 2:
                raise ValueError("limits leave no feasible state once tightened by the tube")

    def _set(self, name: str, value: object) -> None:
        if isinstance(value, np.ndarray):
            value.setflags(write=False)
        object.__setattr__(self, name, value)

    # --- shapes -------------------------------------------------------------------

    @property
    def n(self) -> int:
        return self.model.n

    @property
    def ns(self) -> int:
        """Size of the segment vector ``[x0; xT; vec(Z)]``."""
        return 2 * self.model.n + self.nz

    @property
    def F(self) -> np.ndarray:
        return self.F_full[:, : 2 * self.n]

    @property
    def F0(self) -> np.ndarray:
        return self.F_full[:, : self.n]

    @property
    def FT(self) -> np.ndarray:
        return self.F_full[:, self.n : 2 * self.n]

    # --- right-hand side --------------------------------------------------------------

    def G(self, xbar: np.ndarray) -> np.ndarray:
        """Right-hand side for references ``xbar`` ``(..., k, n)`` -> ``(..., K)``."""
        md = self.model
        xbar = np.asarray(xbar, dtype=float)
        if xbar.shape[-2:] != (self.n_pieces, md.n):
            raise ValueError(f"references must be (..., {self.n_pieces}, {md.n}), got {xbar.shape}")
        piece = np.maximum(self.row_piece, 0)  # constant rows ignore their reference
        x_rows = xbar[..., piece, :]  # (..., K, n)
        g_inv = md.g_inv(xbar)
        gmax = np.abs(g_inv).sum(axis=-1).max(axis=-1) + self.g_margin  # induced inf-norm
        f = md.f(xbar)
        with np.errstate(invalid="ignore"):  # NaN references (escaping drift) fail every row
            G = (
                self._base
                + self._g_coef * (self.limits.u_max / gmax[..., piece])
                + self._f_sign * f[..., piece, self._f_index]
                + np.einsum("kn,...kn->...k", self._xbar_coef, x_rows)
            )
        return G

    def references(self, x: np.ndarray, direction: Literal["forward", "backward"] = "forward") -> np.ndarray:
        """Reference states ``(..., k, n)`` for segments starting (forward) or ending (backward) at ``x``.

        ``"drift"``: the zero-input flow from ``x`` to each piece's midpoint (thesis:
        "forward simulate the drift dynamics"), clipped to the state set's bounding box
        where the Lipschitz constants hold. The integrator chain needs none (zeros).
        """
        x = np.asarray(x, dtype=float)
        k = self.n_pieces
        if self.model.constant_dynamics:
            return np.zeros(x.shape[:-1] + (k, self.n))
        if self.reference == "start":
            return np.repeat(x[..., None, :], k, axis=-2)
        mids = 0.5 * (self.breaks[:-1] + self.breaks[1:])
        if direction == "backward":
            mids = 1.0 - mids[::-1]
        sign = 1.0 if direction == "forward" else -1.0
        refs = _drift_flow(self.model, x, sign * self.tau * mids)
        if direction == "backward":
            refs = refs[..., ::-1, :]
        return np.clip(refs, self.state_box[0], self.state_box[1])

    # --- tests --------------------------------------------------------------------

    def test(self, x0: np.ndarray, xT: np.ndarray, xbar: np.ndarray | None = None) -> np.ndarray:
        """``F [x0; xT] <= G`` for stacked pairs ``(..., n)`` -> bool ``(...)``.

        ``xbar`` defaults to the forward references of ``x0``.
        """
        x0 = np.asarray(x0, dtype=float)
        xT = np.asarray(xT, dtype=float)
        G = self.G_const if self.G_const is not None and xbar is None else self.G(self.references(x0) if xbar is None else xbar)
        lhs = x0 @ self.F0.T + xT @ self.FT.T
        return np.all(lhs <= G, axis=-1)

    def forward_polytope(self, x0: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Forward reachable polytope ``{xT : A xT <= b}`` of ``x0`` (``b``: ``(..., K)``)."""
        x0 = np.asarray(x0, dtype=float)
        G = self.G_const if self.G_const is not None else self.G(self.references(x0, "forward"))
        return self.FT, G - x0 @ self.F0.T

    def backward_polytope(self, xT: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Backward reachable polytope ``{x0 : A x0 <= b}`` of ``xT``.

        For nonlinear models the references come from the backward drift flow of ``xT``.
        """
        xT = np.asarray(xT, dtype=float)
        G = self.G_const if self.G_const is not None else self.G(self.references(xT, "backward"))
        return self.F0, G - xT @ self.FT.T

    def edge_table(self, nodes: np.ndarray) -> EdgeTable:
        """Precompute the per-node halves of the edge test for ``nodes`` ``(N, n)``."""
        nodes = np.asarray(nodes, dtype=float)
        _, b = self.forward_polytope(nodes)
        return EdgeTable(start_bound=np.ascontiguousarray(b), end_value=np.ascontiguousarray(nodes @ self.FT.T))

    # --- curves ---------------------------------------------------------------------

    def curve(self, x0: np.ndarray, xT: np.ndarray, z: np.ndarray | None = None) -> np.ndarray:
        """Control points ``(..., p + 1, m)`` of the segment ``[x0; xT; z]`` (``z = 0``: particular)."""
        x0 = np.asarray(x0, dtype=float)
        xT = np.asarray(xT, dtype=float)
        s = np.concatenate([x0, xT], axis=-1)
        if self.nz:
            zz = np.zeros(s.shape[:-1] + (self.nz,)) if z is None else np.broadcast_to(z, s.shape[:-1] + (self.nz,))
            s = np.concatenate([s, zz], axis=-1)
        return (s @ self.segment_map.T).reshape(s.shape[:-1] + (self.p + 1, self.model.m))

    def reach_radius(self) -> np.ndarray:
        """Largest ``|qT_d - q0_d|`` over every accepted pair (per axis ``d``), by LP.

        Only for the integrator chain, whose test is translation invariant: a broad
        phase may drop pairs farther apart than this.
        """
        if self.G_const is None:
            raise ValueError("reach_radius needs a translation-invariant (integrator) model")
        n, m = self.n, self.model.m
        radius = np.zeros(m)
        A_ub = self.F_full
        fixed = [(0.0, 0.0)] * m  # q0 = 0: the test depends on qT - q0 only
        bounds = fixed + [(None, None)] * (2 * n - m + self.nz)
        for d in range(m):
            c = np.zeros(self.ns)
            c[n + d] = -1.0
            res = scipy.optimize.linprog(c, A_ub=A_ub, b_ub=self.G_const, bounds=bounds, method="highs")
            if res.status == 3:
                radius[d] = np.inf
            elif res.status == 0:
                radius[d] = -res.fun
        return radius

    def violation(self, C: np.ndarray, samples: int = 200) -> np.ndarray:
        """Largest constraint violation of curves ``C`` ``(..., p + 1, m)`` over dense samples.

        Positive means violated: state rows tightened by the tube, and ``||u||_inf - u_max``
        with ``u`` from eq. 6.4. Used by tests and to verify solver output.
        """
        md, lim = self.model, self.limits
        t = np.linspace(0.0, self.tau, samples)
        x = bz.state_values(C, self.tau, md.gamma, t)
        qg = bz.evaluate(bz.derivative_points(C, self.tau, md.gamma), self.tau, t)
        state = x @ lim.state_A.T - lim.tightened_b(md.m)
        u = np.abs(md.input(x, qg)).max(axis=-1) - lim.u_max
        worst = np.maximum(state.max(axis=(-1, -2)) if state.shape[-1] else -np.inf, u.max(axis=-1))
        return worst


@dataclass(frozen=True)
class EdgeTable:
    """Per-node halves of the edge test: pair ``(i, j)`` is an edge iff
    ``end_value[j] <= start_bound[i]`` row-wise (``F0 x_i + FT x_j <= G(x_i)``)."""

    start_bound: np.ndarray  # (N, K)
    end_value: np.ndarray  # (N, K)

    def test_pairs(self, i: np.ndarray, j: np.ndarray) -> np.ndarray:
        """Edge test for index pairs (compiled loop with early exit) -> bool ``(E,)``."""
        i = np.ascontiguousarray(i, dtype=np.int64)
        j = np.ascontiguousarray(j, dtype=np.int64)
        if i.shape != j.shape or i.ndim != 1:
            raise ValueError("i and j must be 1-D and of equal length")
        n_nodes = self.start_bound.shape[0]
        if len(i) and (i.min() < 0 or j.min() < 0 or i.max() >= n_nodes or j.max() >= n_nodes):
            raise IndexError("node index out of range")
        out = np.empty(len(i), dtype=np.bool_)
        _pairs_kernel(self.start_bound, self.end_value, i, j, out)
        return out

    def successors(self, i: int) -> np.ndarray:
        """Indices ``j`` (including ``i`` when it passes) reachable from node ``i``."""
        return np.flatnonzero(np.all(self.end_value <= self.start_bound[i], axis=1))


@numba.njit(cache=True, nogil=True)
def _pairs_kernel(start_bound, end_value, i, j, out):  # pragma: no cover - compiled
    K = start_bound.shape[1]
    for e in range(i.shape[0]):
        ok = True
        si = i[e]
        ej = j[e]
        for r in range(K):
            if end_value[ej, r] > start_bound[si, r]:
                ok = False
                break
        out[e] = ok


def _row_templates(md: PlanningModel, lim: ReachLimits, rho: np.ndarray) -> list[_RowTemplate]:
    n, m = md.n, md.m
    tpls: list[_RowTemplate] = []
    zero_x = np.zeros(n)
    b_tight = lim.tightened_b(m)
    for a, b in zip(lim.state_A, b_tight):
        tpls.append(_RowTemplate(np.concatenate([a, np.zeros(m)]), float(b), 0.0, 0.0, 0, zero_x))
    L = md.lipschitz_drift
    varying_f = md.drift is not None
    for j in range(m):
        support = np.flatnonzero(L[j] > 0)
        for s in (1.0, -1.0):
            for sig in product((1.0, -1.0), repeat=len(support)):
                xc = np.zeros(n)
                xc[support] = np.asarray(sig) * L[j, support]
                w = np.concatenate([xc, np.zeros(m)])
                w[n + j] = s
                tpls.append(_RowTemplate(w, 0.0, 1.0, s if varying_f else 0.0, j, xc))
    for i in np.flatnonzero(md.lipschitz_gain_inv > 0):
        for s in (1.0, -1.0):
            e = np.zeros(n)
            e[i] = s
            tpls.append(_RowTemplate(np.concatenate([e, np.zeros(m)]), float(rho[i]), 0.0, 0.0, 0, e))
    return tpls


def _prune_convex(rows: np.ndarray) -> list[np.ndarray]:
    """Drop rows that are convex combinations of the remaining ones (same right-hand side).

    Sequential, so duplicates keep one copy. Redundant rows cost solver time only.
    """
    kept = [r for r in rows if np.any(r)] or [rows[0]]
    idx = 0
    while idx < len(kept) and len(kept) > 1:
        others = np.array(kept[:idx] + kept[idx + 1 :])
        target = kept[idx]
        scale = max(1.0, float(np.abs(target).max()))
        A = np.vstack([others.T, np.ones(len(others))])
        _, res = scipy.optimize.nnls(A, np.concatenate([target, [1.0]]))
        if res <= _TOL * scale:
            kept.pop(idx)
        else:
            idx += 1
    return kept


def _bounding_box(A: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    n = A.shape[1]
    lo, hi = np.full(n, -np.inf), np.full(n, np.inf)
    if A.shape[0] == 0:
        return lo, hi
    for i in range(n):
        for sign, out in ((1.0, lo), (-1.0, hi)):
            c = np.zeros(n)
            c[i] = sign
            res = scipy.optimize.linprog(c, A_ub=A, b_ub=b, bounds=[(None, None)] * n, method="highs")
            if res.status == 0:
                out[i] = sign * res.fun
            elif res.status == 2:
                raise ValueError("state limits are infeasible")
    return lo, hi


def _drift_flow(model: PlanningModel, x: np.ndarray, times: np.ndarray, max_step: float = 0.01) -> np.ndarray:
    """Zero-input flow of ``x`` ``(..., n)`` sampled at sorted ``times`` (same sign) -> ``(..., len, n)``.

    Fixed-step RK4; non-finite results (escaping drift) propagate as NaN, which fails
    every test row (sound: no edge).
    """
    out = np.empty(x.shape[:-1] + (len(times), model.n))
    cur = x.copy()
    t_cur = 0.0
    with np.errstate(over="ignore", invalid="ignore"):
        for idx, t_next in enumerate(times):
            span = t_next - t_cur
            steps = max(1, int(np.ceil(abs(span) / max_step)))
            h = span / steps
            for _ in range(steps):
                k1 = model.vector_field(cur)
                k2 = model.vector_field(cur + 0.5 * h * k1)
                k3 = model.vector_field(cur + 0.5 * h * k2)
                k4 = model.vector_field(cur + h * k3)
                cur = cur + (h / 6.0) * (k1 + 2 * k2 + 2 * k3 + k4)
            out[..., idx, :] = cur
            t_cur = t_next
    return out
