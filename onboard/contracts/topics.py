"""The one table of topics.

Every Zenoh key the stack uses is declared here, under a namespace
(``archer/<robot>`` by default). Code never spells a key literal elsewhere: it asks
this module for ``TOPICS[name].key(ns)`` or one of the service key helpers.

Liveness derives from the table (as openpilot's services table): a topic is
``alive`` when a message arrived within ``ALIVE_PERIODS`` nominal periods, and
``freq_ok`` when its achieved rate is at least ``FREQ_OK_FRACTION`` of nominal.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from typing import Literal

from onboard.contracts import messages as m

DEFAULT_ROBOT = "robot0"
NAMESPACE_ENV = "ARCHER_NAMESPACE"
ALIVE_PERIODS = 10.0
FREQ_OK_FRACTION = 0.9

Reliability = Literal["reliable", "best_effort"]
Congestion = Literal["drop", "block"]
Priority = Literal["real_time", "interactive_high", "data_high", "data", "data_low", "background"]


@dataclass(frozen=True)
class Topic:
    name: str
    suffix: str  # key below the namespace
    msg_type: type | None  # msgspec struct, or None for a binary layout
    rate_hz: float  # nominal rate; 0 for event-driven topics
    publishers: tuple[str, ...]  # services allowed to publish (access control follows it)
    reliability: Reliability = "best_effort"
    congestion: Congestion = "drop"
    priority: Priority = "data"
    express: bool = False  # send at once, do not batch
    log: bool = True  # recorded by the flight recorder
    binary: str = ""  # binary kind ("depth", "grid", "color") when msg_type is None

    def key(self, ns: str) -> str:
        return f"{ns}/{self.suffix}"

    def alive(self, age_s: float) -> bool:
        if self.rate_hz <= 0:
            return True
        return age_s < ALIVE_PERIODS / self.rate_hz

    def freq_ok(self, achieved_hz: float) -> bool:
        if self.rate_hz <= 0:
            return True
        return achieved_hz >= FREQ_OK_FRACTION * self.rate_hz


_SENSOR_PUBLISHERS = ("hardware", "twin")

_TABLE = [
    # sensors: hardware service on the robot, the twin in simulation; pose also from motion capture
    Topic("imu", "sensors/imu", m.ImuSample, 1000, _SENSOR_PUBLISHERS, priority="real_time", express=True),
    Topic("joints", "sensors/joints", m.JointSensors, 1000, _SENSOR_PUBLISHERS, priority="real_time", express=True),
    Topic("pose", "sensors/pose", m.PoseMeasurement, 100, (*_SENSOR_PUBLISHERS, "mocap"), priority="interactive_high", express=True),
    Topic("depth", "sensors/depth", None, 5, (*_SENSOR_PUBLISHERS, "camera"), priority="data_low", binary="depth"),
    Topic("color", "sensors/color", None, 5, ("camera", "twin"), priority="data_low", binary="color"),
    # estimation
    Topic("state", "state/estimate", m.StateEstimate, 1000, ("estimator",), priority="real_time", express=True),
    Topic("phase", "state/phase", m.PhaseEvent, 0, ("estimator", "control"), reliability="reliable", priority="interactive_high"),
    # low level
    Topic("torque_cmd", "control/torque", m.TorqueCommand, 1000, ("control",), priority="real_time", express=True),
    Topic("attitude_cmd", "control/attitude", m.AttitudeSetpoint, 1000, ("control",), priority="real_time", express=True),
    Topic("mid_level", "control/mid_level", m.MidLevelSetpoint, 100, ("control",), priority="real_time", express=True),
    Topic("tube", "control/tube", m.TrackingTube, 2, ("control",), reliability="reliable"),
    Topic("safety", "control/safety", m.SafetyEvent, 0, ("control", "hardware", "twin"), reliability="reliable", congestion="block", priority="interactive_high"),
    # high level
    Topic("goal", "plan/goal", m.Goal, 0, ("operator", "twin"), reliability="reliable", congestion="block"),
    Topic("reference", "plan/reference", m.ComReference, 100, ("planner",), reliability="reliable", priority="interactive_high"),
    Topic("waypoints", "plan/waypoints", m.Waypoints, 10, ("planner",), reliability="reliable"),
    Topic("contract", "plan/contract", m.ContractReport, 0, ("planner", "control"), reliability="reliable", congestion="block"),
    # world model
    Topic("polytopes", "world/polytopes", m.PolytopeSet, 10, ("perception", "twin", "camera_overhead"), reliability="reliable"),
    Topic("grid", "world/grid", None, 5, ("perception",), priority="data_low", binary="grid"),
    # visual odometry: the CoM's displacement between two apex frames (estimator.visual_odometry), one a hop
    Topic("visual_odometry", "sensors/visual_odometry", m.VisualOdometryDelta, 0, ("camera",), reliability="reliable",
          priority="interactive_high"),
]

TOPICS: dict[str, Topic] = {t.name: t for t in _TABLE}
assert len(TOPICS) == len(_TABLE), "duplicate topic name"
assert len({t.suffix for t in _TABLE}) == len(_TABLE), "duplicate topic key"

SERVICES = ("hardware", "twin", "mocap", "camera", "estimator", "control", "planner", "perception", "recorder", "view",
            "camera_overhead")
# services whose second instance runs as a hot standby (services/runtime/service.py), under the same
# user: it announces itself as <name>_standby until the first one's token goes
STANDBY_SERVICES = ("estimator", "control")
STANDBY_SUFFIX = "_standby"


def namespace(robot: str | None = None) -> str:
    """The key namespace: ``$ARCHER_NAMESPACE`` or ``archer/<robot>``."""
    if robot is None:
        env = os.environ.get(NAMESPACE_ENV)
        if env:
            return env.strip("/")
        robot = DEFAULT_ROBOT
    return f"archer/{robot}"


def liveliness_key(ns: str, service: str) -> str:
    return f"{ns}/alive/{service}"


def status_key(ns: str, service: str) -> str:
    return f"{ns}/svc/{service}/status"


def params_key(ns: str, service: str) -> str:
    return f"{ns}/svc/{service}/params"


def all_keys(ns: str) -> str:
    return f"{ns}/**"


def topic_for_key(ns: str, key: str) -> Topic | None:
    prefix = ns + "/"
    if not key.startswith(prefix):
        return None
    suffix = key[len(prefix):]
    for t in _TABLE:
        if t.suffix == suffix:
            return t
    return None
