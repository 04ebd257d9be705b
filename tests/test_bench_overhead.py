"""``archer bench overhead`` times the planner's plan apart from the graph builds the service runs beside
its ticks, times every frame, and refuses sizes it cannot measure."""

from __future__ import annotations

import argparse
import dataclasses

import pytest

from onboard.high_level.planning.graph_planner import GraphPlanner
from services.bench import overhead


def test_builds_are_timed_apart_from_the_plans(monkeypatch):
    """A region that changes every frame (a new sampling seed each time) makes the bench build a graph at
    every frame: each build is timed as one, and none inside the plan's figure."""
    calls = iter(range(1, 1000))
    real_spec_for = GraphPlanner.graph_spec_for
    monkeypatch.setattr(GraphPlanner, "graph_spec_for",
                        lambda self, *a, **k: dataclasses.replace(real_spec_for(self, *a, **k), seed=next(calls)))
    out = overhead.measure(argparse.Namespace(obstacles=4, frames=3, refines=1, seed=0))
    assert out["frames"] == 3 and out["tracked_median"] >= 1 and out["graph_builds"] == 3
    assert out["plan_ms"]["p99"] < out["build_ms"]["p50"]  # the plans do not hold the builds
    for stage in ("camera", "plan", "refine", "frame_to_plan", "build"):
        spread = out[f"{stage}_ms"]
        assert 0.0 < spread["p50"] <= spread["p99"]
    assert out["plan_thesis_hz"] == 50.0 and out["plan_rate_p99_hz"] > 0.0
    without = overhead.measure(argparse.Namespace(obstacles=4, frames=2, refines=0, seed=0))
    assert "refine_ms" not in without and "refine_rate_p99_hz" not in without and "plan_ms" in without


@pytest.mark.parametrize("obstacles, frames, refines", [(0, 2, 1), (4, 0, 1), (4, 2, -1)])
def test_sizes_it_cannot_measure_are_refused(obstacles, frames, refines):
    with pytest.raises(SystemExit, match="needs --obstacles >= 1"):
        overhead.measure(argparse.Namespace(obstacles=obstacles, frames=frames, refines=refines, seed=0))
