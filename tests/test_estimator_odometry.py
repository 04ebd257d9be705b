"""No motion capture (issue 27): the estimator keeps a valid CoM from the IMU and leg kinematics in an
odometry frame anchored at the first touchdown; its position drifts, and its covariance says so."""

from __future__ import annotations

import pytest

from onboard.contracts import messages as m
from onboard.contracts.params import EstimatorParams, with_overrides
from onboard.estimation.estimator import StateEstimator
from robot_description import params as rd
from sim_twin.lockstep import RunConfig, run


def test_odometry_refuses_poses_and_waits_for_a_touchdown() -> None:
    est = StateEstimator(with_overrides(EstimatorParams(), {"position_source": "odometry"}), rd.robot_params("outdoor"))
    imu = m.ImuSample(stamp_ns=1_000_000, quat=[1.0, 0.0, 0.0, 0.0], gyro=[0.0] * 3, accel=[0.0, 0.0, 9.81])
    assert est.update_imu(imu, 1_000_000)
    pose = m.PoseMeasurement(stamp_ns=1_000_000, position=[0.0, 0.0, 0.5], quat=[1.0, 0.0, 0.0, 0.0], source="mocap")
    assert not est.update_pose(pose, 1_000_000) and est.rejections()["pose_not_used"] == 1
    assert est.status()["mode"] == "init" and not est.estimate(1_000_000).valid


@pytest.mark.parametrize("scenario, duration_s", [("hop-in-place", 10.0), ("setpoint", 12.0)])
def test_hops_without_motion_capture_and_its_drift_is_within_its_covariance(scenario: str, duration_s: float) -> None:
    got = run(RunConfig(scenario=scenario, seed=3, duration_s=duration_s, variant="outdoor", estimator="kalman",
                        sensing="onboard")).metrics
    assert got["falls"] == 0 and got["hops"] > 20, got
    c = got["estimator_counters"]
    assert c["odometry_anchored"] == 1 and c["pose_fused"] == 0 and c["imu_att_fused"] > 500 and c["leg_fused"] > 500
    assert abs(got["final_drift_z_m"]) < 0.03  # the ground's height at each touchdown bounds the vertical drift
    # the horizontal drift is what the published covariance allows, and it grows with the way
    assert got["final_drift_m"] < 3.0 * got["final_pos_std_m"] + 0.01, got
    assert got["final_pos_std_m"] > EstimatorParams().anchor_std_m
    # the attitude: no absolute heading without motion capture, the gyro's bias integrates; the tilt
    # is held by gravity (what places a camera's ground at range)
    assert 0.0 < got["final_heading_err_deg"] <= got["max_heading_err_deg"] < 3.0, got
    assert 0.0 < got["final_tilt_err_deg"] <= got["max_tilt_err_deg"] < 2.0, got
    if scenario == "setpoint":
        assert got["distance_travelled_m"] > 1.0 and got["final_goal_error_m"] < 0.3


def test_sensing_onboard_needs_the_onboard_estimator() -> None:
    with pytest.raises(ValueError, match="sensing onboard"):
        run(RunConfig(scenario="hop-in-place", duration_s=0.1, variant="outdoor", estimator="truth", sensing="onboard"))
