"""The graph planner in the lockstep twin: it plans around the forest and hears the low level's tube."""

from __future__ import annotations

from sim_twin.lockstep import LockstepRunner, RunConfig
from sim_twin.stack import GraphPlannerPlug


def test_forest_start_is_planned_and_the_contract_is_checked():
    runner = LockstepRunner(RunConfig(scenario="forest", seed=1, duration_s=6.0))
    plug = runner.planner
    assert isinstance(plug, GraphPlannerPlug)
    result = runner.run()
    m = result.metrics
    assert m["planner"] == "graph" and m["planner_plans"] >= 1 and m["planner_no_path"] == 0
    assert m["collisions"] == 0 and m["falls"] == 0
    planner = plug.planner
    # refinement ran every planner tick: solved when the knot or the world changed, else reused
    st = planner.stats
    assert planner.path is not None and st.refines > 10 and st.refines + st.refine_reused > 100
    # The tube reached the planner: every broken promise it saw is in the run's count, and
    # each made it plan with a larger tube.
    assert m["contract_violations"] == planner.contract_violations
    assert planner.tube >= planner.params.tube
    if planner.contract_violations:
        assert planner.tube > planner.params.tube
