"""The service table: one row per service process (openpilot's process list is the model).

A row names the process (what ``archer run NAME`` starts), its class, and its systemd unit
(``deploy/systemd``; None for the stand-ins only ``archer sim`` runs). What a service
reads is its class's ``subscribes`` (the runtime refuses any other subscription); what
it writes is its column in the topic table (:data:`onboard.contracts.topics.TOPICS`
``publishers``: the runtime refuses any other publisher, and the Zenoh access control
is generated from it); its parameters are its class's ``params_sections``. ``archer
services`` prints the table; ``archer run``, ``archer sim``'s supervisor and the unit
tests read it.
"""

from __future__ import annotations

import importlib
import importlib.util
from dataclasses import dataclass

from onboard.contracts.topics import TOPICS
from services.runtime.service import EVERY_TOPIC, Service


@dataclass(frozen=True)
class ServiceRow:
    process: str  # `archer run <process>`
    target: str  # "module:Class"
    unit: str | None  # its unit file in deploy/systemd; None: a stand-in only `archer sim` runs
    on_robot: bool  # runs on the robot (no MuJoCo, no simulator)
    needs: tuple[tuple[str, str], ...] = ()  # (module, the package extra that installs it): optional dependencies

    def missing(self) -> list[str]:
        """One line per optional dependency this service needs and this install lacks."""
        return [f"{self.process} needs the Python module {module!r}: install the {extra!r} extra "
                f"(pip install -e '.[{extra}]' in the checkout)"
                for module, extra in self.needs if importlib.util.find_spec(module) is None]

    def service_class(self) -> type[Service]:
        module_name, _, class_name = self.target.partition(":")
        return getattr(importlib.import_module(module_name), class_name)

    def describe(self) -> dict[str, object]:
        """The row with what its class declares and what the topic table lets it publish."""
        cls = self.service_class()
        reads = ["*"] if cls.subscribes == EVERY_TOPIC else list(cls.subscribes)
        return {
            "process": self.process, "class": self.target, "unit": self.unit, "on_robot": self.on_robot,
            "params": list(cls.params_sections), "subscribes": reads,
            "publishes": [t.name for t in TOPICS.values() if cls.name in t.publishers],
        }


SERVICES: dict[str, ServiceRow] = {row.process: row for row in (
    ServiceRow("router", "services.runtime.router:RouterService", "archer-router.service", True),
    ServiceRow("hardware", "services.hardware:HardwareService", "archer-hardware.service", True),
    ServiceRow("mocap", "services.mocap:MocapService", "archer-mocap.service", True, needs=(("motioncapture", "mocap"),)),
    ServiceRow("camera", "services.camera:CameraService", "archer-camera.service", True, needs=(("pyrealsense2", "realsense"),)),
    ServiceRow("estimator", "services.estimator:EstimatorService", "archer-estimator.service", True),
    ServiceRow("control", "services.control:ControlService", "archer-control.service", True),
    ServiceRow("planner", "services.planner:PlannerService", "archer-planner.service", True),
    ServiceRow("perception", "services.perception:PerceptionService", "archer-perception.service", True),
    ServiceRow("recorder", "services.recorder:RecorderService", "archer-recorder.service", True),
    ServiceRow("view", "services.view:ViewService", "archer-view.service", True),
    ServiceRow("twin", "services.twin:TwinService", "archer-twin.service", False),
    ServiceRow("scenario_reference", "services.twin:ScenarioReferenceService", None, False),
    ServiceRow("camera_overhead", "services.camera_overhead:CameraOverheadService", "archer-camera-overhead.service", True),
)}


def missing_dependencies(processes: list[str]) -> list[str]:
    """What the optional dependencies of ``processes`` lack here, one line each (empty: nothing)."""
    return [line for name in processes if name in SERVICES for line in SERVICES[name].missing()]
