"""`sim_twin.record.write_mcap`: what a lockstep run records reads back as it was sent."""

from __future__ import annotations

from mcap.reader import make_reader

from onboard.contracts import messages as m
from sim_twin.record import write_mcap


def test_an_estimate_before_the_first_imu_sample_is_recorded_with_its_own_stamp(tmp_path) -> None:
    # with sensor latency drawn (--model-error) the first estimates precede any IMU sample and are
    # stamped -1; MCAP's publish time is unsigned, and the run's whole recording was lost to it
    early = m.StateEstimate(stamp_ns=-1, position=[0.0] * 3, velocity=[0.0] * 3, quat=[1.0, 0.0, 0.0, 0.0],
                            omega=[0.0] * 3, wheel_vel=[0.0] * 3, foot_pos=0.0, foot_vel=0.0, contact=True,
                            phase="stance", pos_vel_cov=[0.0] * 36, att_cov=[0.0] * 3, valid=False)
    later = m.ImuSample(stamp_ns=2_000_000, quat=[1.0, 0.0, 0.0, 0.0], gyro=[0.0] * 3, accel=[0.0, 0.0, 9.81])
    path = tmp_path / "run.mcap"
    assert write_mcap(path, [("state", 1_000_000, early), ("imu", 2_000_000, later)]) == 2
    with open(path, "rb") as f:
        records = list(make_reader(f).iter_messages())
    assert [(r[2].log_time, r[2].publish_time) for r in records] == [(1_000_000, 0), (2_000_000, 2_000_000)]
    assert m.decode(records[0][2].data, m.StateEstimate).stamp_ns == -1
