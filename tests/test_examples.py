"""The thesis's own examples run and keep their guarantees (section 6.1, Figure 6.6)."""

from __future__ import annotations

import importlib.util
import math
import sys
from pathlib import Path

import numpy as np
import pytest

from onboard.geometry import bezier as bz

EXAMPLES = Path(__file__).resolve().parent.parent / "examples"


def _load(name: str):
    spec = importlib.util.spec_from_file_location(name, EXAMPLES / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module  # dataclasses resolve annotations through sys.modules
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope="module")
def pendulum():
    return _load("pendulum_swingup")


@pytest.fixture(scope="module")
def nonlinear():
    return _load("nonlinear_bezier_mpc")


def test_pendulum_swingup_graph_is_sound_and_tighter_torque_needs_a_longer_path(pendulum):
    loose = pendulum.swing_up(5.0, nodes=4000, tau=0.15)
    tight = pendulum.swing_up(1.0, nodes=20000, tau=0.15)
    for res in (loose, tight):
        assert res.found
        np.testing.assert_allclose(res.path[0], [0.0, 0.0])
        assert abs(abs(res.path[-1, 0]) - math.pi) < 1e-12 and res.path[-1, 1] == 0.0
        # every curve on the path, densely sampled through the pendulum equation
        torque, omega = pendulum.torque_along(res.curves, res.tau, samples=1000)
        assert np.abs(torque).max() <= res.u_max + 1e-9
        assert np.abs(omega).max() <= 10.0 + 1e-9
        ends = bz.state_values(res.curves, res.tau, 2, np.array([0.0, res.tau]))
        np.testing.assert_allclose(ends[1:, 0], ends[:-1, 1], atol=1e-9)  # continuous angle and speed
        np.testing.assert_allclose(ends[:, 0], res.path[:-1], atol=1e-9)
    assert tight.segments > 2 * loose.segments  # pumping: thesis Figure 6.6
    assert loose.max_torque > 1.0  # the loose run uses torque the tight one may not


def test_pendulum_example_cli_runs(pendulum, tmp_path):
    out = tmp_path / "fig.png"
    assert pendulum.main(["--u-max", "5", "--nodes", "3000", "--plot", str(out)]) == 0
    assert out.stat().st_size > 1000


def test_section61_bezier_mpc_keeps_the_closed_loop_inside_its_limits(nonlinear):
    x0 = np.array([2.0, 0.0])
    log = nonlinear.run_bezier_mpc(x0, duration=5.0)
    worst = log.max_abs
    assert worst["x1"] <= nonlinear.X1_MAX
    assert worst["x2"] <= nonlinear.X2_MAX
    assert worst["u"] <= nonlinear.U_MAX
    assert log.planned_max_input <= nonlinear.U_PLAN + 1e-9
    assert log.certified >= 0.8 * log.replans
    assert np.linalg.norm(log.x[-1]) < 0.1 * np.linalg.norm(x0)  # converging to the origin
    # the planned curves join up: each tracked segment starts where the state was planned
    starts = np.array([bz.evaluate(c, nonlinear.TAU, 0.0)[0] for c in log.planned])
    assert np.all(np.abs(starts) <= nonlinear.X1_MAX)


def test_section61_low_level_alone_violates_the_limits(nonlinear):
    log = nonlinear.run_low_level_only(np.array([2.0, 0.0]), duration=2.0)
    worst = log.max_abs
    assert worst["x2"] > nonlinear.X2_MAX and worst["u"] > nonlinear.U_MAX


def test_section61_mpc_alone_loses_the_state_to_the_disturbance(nonlinear):
    """No low level under the plans (thesis Fig. 6.2's middle arm): each plan's own input, bounded
    by the planning limit, applied open loop; the disturbance drives x2 off and away."""
    with np.errstate(all="ignore"):
        log = nonlinear.run_bezier_mpc(np.array([2.0, 0.0]), duration=8.0, track=False)
    worst = log.max_abs
    assert worst["x2"] > nonlinear.X2_MAX
    assert worst["u"] <= nonlinear.U_PLAN + 1e-6  # the plans' input: within the planning bound
    assert log.t[-1] < 8.0 - nonlinear.DT  # it diverged and the run ended early
