"""What the planner reports: its counters, and its side of the tracking contract with the low
level (thesis 8.1, lines 3233-3327: each layer states the tube it assumes, and a broken promise
is reported and planned around).

:class:`PlannerStats` is what the ``planner`` service publishes in its status.
:class:`TubeContract` is mixed into :class:`~onboard.high_level.planning.graph_planner.GraphPlanner`:
it compares the tube the low level achieves with the one planned with, reports a broken promise
as a :class:`~onboard.contracts.messages.ContractReport` and grows the planner's tube (its
``set_tube``, which recuts). Reads the planner's ``params`` and ``tube``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from onboard.contracts import messages as msgs


@dataclass
class PlannerStats:
    """Counters and last timings a service reports (timings are filled by the caller)."""

    plans: int = 0
    no_path: int = 0
    cuts: int = 0
    graph_builds: int = 0
    refines: int = 0  # MPC solves
    refine_reused: int = 0  # refine calls answered with the last solution (nothing changed)
    refine_failures: int = 0
    refine_idle: int = 0  # refine calls answered with the graph path: its end reached, the robot at rest there
    refine_skipped: int = 0  # free mode: refine calls answered with the graph path, the refinement having failed at that knot
    refine_numerical_errors: int = 0  # of the failures: a solver or linear-algebra error (last one in last_refine_error)
    last_refine_error: str = ""
    edges_free: int = 0
    unseen_holds: int = 0  # references held back because their committed part crossed ground not seen free
    densify_plans: int = 0  # plans whose search failed and densified the graph (onboard.high_level.planning.densify)
    densify_rounds: int = 0  # densification rounds that added nodes
    densify_nodes: int = 0  # nodes they added
    frontier_plans: int = 0  # free mode: plans that end at a frontier, the goal being beyond the known free cells
    sweep_relaxed: int = 0  # searches with moving obstacles swept shorter, the longer sweep having left no path
    evasions: int = 0  # no path, an obstacle coming: references stepping out of its way instead of holding


class TubeContract:
    """The planner's side of the tube contract (a mixin of :class:`GraphPlanner`)."""

    def _init_contract(self) -> None:
        self.contract_violations = 0
        self._reports: list[msgs.ContractReport] = []

    def check_tube(self, tube: msgs.TrackingTube, stamp_ns: int = 0) -> msgs.ContractReport | None:
        """Compare the tube the low level achieves (p95 CoM error at impact) with the tube planned with.

        Judged once the window holds ``contract_min_hops`` impacts. A broken promise
        returns a :class:`~onboard.contracts.messages.ContractReport` (also kept for
        :meth:`drain_contract_reports`) and makes the planner plan with the achieved tube
        times ``tube_growth`` (at most ``tube_max``) from now on, which recuts. None when
        the promise holds.
        """
        prm = self.params
        promised = self.tube
        achieved = float(tube.impact_err_p95)
        if tube.hops < prm.contract_min_hops or not math.isfinite(achieved) or achieved <= promised:
            return None
        self.contract_violations += 1
        new_tube = min(achieved * prm.tube_growth, prm.tube_max)
        report = msgs.ContractReport(
            stamp_ns=stamp_ns, layer="planner", promised=promised, achieved=achieved, violated=True,
            violations=self.contract_violations,
            detail=f"tube p95 {achieved:.3f} m over {tube.hops} impacts > {promised:.3f} m planned; "
                   f"planning with {max(new_tube, promised):.3f} m")
        self._reports.append(report)
        if new_tube > promised:
            self.set_tube(new_tube)
        return report

    def drain_contract_reports(self) -> list[msgs.ContractReport]:
        """Reports of broken promises since the last call."""
        out, self._reports = self._reports, []
        return out
