"""The wheels' momentum governor (onboard.low_level.planning.momentum): the cap it sets from the
wheels' speeds at touchdown, what it does to the policy's target, and in lockstep a datasheet robot
that ran its wheels into their limit and fell without it (issue 26).
"""

from __future__ import annotations

import math

import pytest

from onboard.contracts.params import ControlParams
from onboard.low_level.planning.momentum import MomentumGovernor
from sim_twin.lockstep import RunConfig, run

FREE = 0.375  # [m/s] the indoor robot's nominal sustained speed
LO, HI, MIN, LEAD, LOOKAHEAD, RISE = 150.0, 350.0, 0.05, 0.25, 3.0, 0.02


def _governor(lo: float = LO) -> MomentumGovernor:
    return MomentumGovernor(FREE, lo, HI, MIN, LEAD, LOOKAHEAD, RISE)


def test_no_cap_while_the_wheels_are_slow_and_steady() -> None:
    g = _governor()
    for _ in range(5):
        g.on_touchdown(120.0, -140.0, 10.0)
    assert g.cap == math.inf and g.governed_hops == 0
    assert g.counters()["speed_cap_m_s"] == 0.0  # none
    assert g.target(-0.8, 0.1, 0.4, 0.3) == (-0.8, 0.1, 0.4, 0.3)


def test_the_cap_falls_linearly_between_the_bounds_and_clips_the_target() -> None:
    g = _governor()
    g.on_touchdown(0.0, -250.0, 0.0)  # the first touchdown: no growth to measure, its own speed
    assert g.wheel_speed == 250.0
    g.on_touchdown(0.0, -250.0, 0.0)  # steady: halfway between the bounds
    cap = FREE + 0.5 * (MIN - FREE)
    assert g.cap == pytest.approx(cap)
    ex, ey, vx, vy = g.target(-0.3, 0.4, 0.6, 0.0)
    assert math.hypot(ex, ey) == pytest.approx(cap * LEAD)
    assert ex / ey == pytest.approx(-0.3 / 0.4)  # direction kept
    assert (vx, vy) == (pytest.approx(cap), 0.0)
    assert g.target(-0.01, 0.0, 0.05, 0.0) == (-0.01, 0.0, 0.05, 0.0)  # inside the cap: unchanged
    g.on_touchdown(0.0, 500.0, 0.0)  # past the upper bound
    assert g.cap == pytest.approx(MIN)
    assert g.counters() == {"speed_cap_m_s": pytest.approx(MIN), "wheel_speed_rad_s": pytest.approx(500.0 + LOOKAHEAD * 250.0),
                            "governed_hops": 3.0}  # every touchdown above the low bound


def test_a_fast_growing_wheel_is_capped_before_it_is_fast() -> None:
    """115 -> 210 rad/s in one hop (the datasheet square's seed 37) counts as 495: the lowest cap."""
    g = _governor()
    g.on_touchdown(0.0, 115.0, 0.0)
    g.on_touchdown(0.0, 115.0, 0.0)
    assert g.cap == math.inf
    g.on_touchdown(0.0, 210.0, 0.0)
    assert g.wheel_speed == pytest.approx(210.0 + LOOKAHEAD * 95.0)
    assert g.cap == pytest.approx(MIN)
    g.on_touchdown(0.0, -200.0, 0.0)  # slower: no projection, whatever the sign
    assert g.wheel_speed == pytest.approx(200.0)


def test_the_cap_falls_at_once_and_rises_a_step_a_hop() -> None:
    g = _governor()
    g.on_touchdown(400.0, 0.0, 0.0)
    assert g.cap == pytest.approx(MIN)
    for hop in range(1, 6):
        g.on_touchdown(100.0, 0.0, 0.0)  # slow again
        assert g.cap == pytest.approx(MIN + hop * RISE)
    for _ in range(50):
        g.on_touchdown(100.0, 0.0, 0.0)
    assert g.cap == math.inf  # risen past the nominal speed: no cap
    g.on_touchdown(400.0, 0.0, 0.0)
    g.reset()  # a new arming
    assert g.cap == math.inf


def test_a_zero_low_bound_turns_it_off() -> None:
    g = _governor(lo=0.0)
    g.on_touchdown(590.0, 0.0, 0.0)
    assert g.cap == math.inf and g.governed_hops == 0


def test_a_datasheet_robot_that_spun_its_wheels_into_their_limit_reaches_its_goal() -> None:
    """The datasheet profile's setpoint seed 34 (torso pitch inertia +40 %, a heavier foot, weaker
    motors): without the governor its wheel gains ~60 rad/s a hop to the motors' limit and it falls;
    with it, it slows, keeps its wheels well under the limit and reaches the goal."""
    cfg = dict(scenario="setpoint", estimator="kalman", seed=34, model_error="datasheet")
    on = run(RunConfig(**cfg))
    off = run(RunConfig(**cfg, control_params=ControlParams(momentum_wheel_share_lo=0.0)))
    assert off.metrics["max_wheel_speed_rad_s"] > 500.0
    assert off.metrics["falls"] >= 1
    assert on.metrics["falls"] == 0 and on.metrics["goal_reached"]
    assert on.metrics["max_wheel_speed_rad_s"] < 450.0


def test_a_flips_momentum_is_not_governed_until_the_wheels_have_shed_it() -> None:
    g = _governor()
    g.on_touchdown(1800.0, 0.0, 0.0, ordinary=False)  # the flip's landing
    g.on_touchdown(900.0, 0.0, 0.0)  # the stances shed it: still the flip's
    assert g.cap == math.inf and g.governed_hops == 0
    g.on_touchdown(100.0, 0.0, 0.0)  # shed
    g.on_touchdown(400.0, 0.0, 0.0)  # the hopping's own again
    assert g.cap == pytest.approx(MIN)
