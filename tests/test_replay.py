"""Replay, in the style of openpilot's process replay: a recorded lockstep run's inputs go
through the onboard estimator and low level again, and what they compute must be what the
run recorded. A restructuring that changes a number fails here.

The recording, ``tests/data/replay/setpoint_seed0.mcap``, is a lockstep run of the twin
(3 hops towards a setpoint, the Kalman estimator, the low level, default parameters):

    archer sim --scenario setpoint --seed 0 --duration 1.0 --record tests/data/replay/setpoint_seed0.mcap

A deliberate change of behaviour re-records it with that command (and says so in its commit).
Messages are read in the order the run wrote them: within a tick, the sensors the estimator
was fed, then the estimate and the command it produced.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import msgspec
import numpy as np
import pytest
from mcap.reader import make_reader

from onboard.contracts import messages as msgs
from onboard.estimation.estimator import StateEstimator
from onboard.contracts.params import ControlParams, EstimatorParams, SafetyLimits
from onboard.contracts.topics import topic_for_key
from robot_description.controller import build_controller
from robot_description.params import robot_params

RECORDING = Path(__file__).resolve().parent / "data" / "replay" / "setpoint_seed0.mcap"
NS = "archer/robot0"
SENSORS = ("imu", "joints", "pose")
# the same code on the same inputs: equal but for the last bits a BLAS may round differently
RTOL, ATOL = 1e-9, 1e-12


@dataclass
class Tick:
    now_ns: int
    sensors: list[tuple[str, object]] = field(default_factory=list)
    state: msgs.StateEstimate | None = None
    command: msgs.TorqueCommand | None = None
    reference: msgs.ComReference | None = None


def recorded_ticks() -> list[Tick]:
    ticks: dict[int, Tick] = {}
    with open(RECORDING, "rb") as fh:
        for _, channel, message in make_reader(fh).iter_messages(log_time_order=False):
            topic = topic_for_key(NS, channel.topic)
            if topic is None or topic.msg_type is None:
                continue  # depth images: no onboard object here reads them
            msg = msgs.decode(message.data, topic.msg_type)
            tick = ticks.setdefault(message.log_time, Tick(message.log_time))
            if topic.name in SENSORS:
                tick.sensors.append((topic.name, msg))
            elif topic.name == "state":
                tick.state = msg
            elif topic.name == "torque_cmd":
                tick.command = msg
            elif topic.name == "reference":
                tick.reference = msg
    return [ticks[t] for t in sorted(ticks) if ticks[t].state is not None]


def assert_same(computed: msgspec.Struct, recorded: msgspec.Struct, what: str) -> None:
    got, want = msgspec.structs.asdict(computed), msgspec.structs.asdict(recorded)
    for name in ("seq", "version"):  # set by a publisher, not computed
        got.pop(name, None), want.pop(name, None)
    assert got.keys() == want.keys()
    for name, value in want.items():
        if isinstance(value, (bool, str)) or value is None:
            assert got[name] == value, f"{what}: {name}"
        else:
            np.testing.assert_allclose(np.asarray(got[name], dtype=float), np.asarray(value, dtype=float),
                                       rtol=RTOL, atol=ATOL, err_msg=f"{what}: {name}")


@pytest.fixture(scope="module")
def ticks() -> list[Tick]:
    out = recorded_ticks()
    assert len(out) == 1000 and sum(len(t.sensors) for t in out) > 2000
    return out


def test_the_estimator_reproduces_the_recorded_estimates(ticks):
    est = StateEstimator(EstimatorParams(), robot_params("indoor"))
    update = {"imu": est.update_imu, "joints": est.update_joints, "pose": est.update_pose}
    for tick in ticks:
        for topic, msg in tick.sensors:
            update[topic](msg, tick.now_ns)
        assert_same(est.estimate(tick.now_ns), tick.state, f"estimate at {tick.now_ns} ns")
    assert est.counters["touchdowns"] >= 2  # the replay went through stances, not just a flight


def test_the_low_level_reproduces_the_recorded_commands(ticks):
    ctrl = build_controller("indoor", ControlParams(), SafetyLimits())
    ctrl.request_arm()
    reference, joints = None, None
    armed = 0
    for tick in ticks:
        joints = next((msg for topic, msg in reversed(tick.sensors) if topic == "joints"), joints)
        reference = tick.reference or reference
        command = ctrl.step(tick.now_ns, tick.state, reference, joints)
        assert_same(command, tick.command, f"command at {tick.now_ns} ns")
        armed += command.armed
    assert armed > 0.9 * len(ticks)
