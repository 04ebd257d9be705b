"""``archer sim --obstacles-from overhead`` (lockstep): the planner's world from the twin's rendered
overhead view through the ``camera_overhead`` service's own pipeline (calibration on the markers,
segmentation, tracking) at the camera's rate, instead of the ground truth."""

from __future__ import annotations

from collections.abc import Callable

from onboard.contracts import messages as m
from onboard.contracts.params import CameraOverheadParams
from services.camera_overhead import ObstacleCamera
from sim_twin import overhead_camera as oc
from sim_twin import scenarios as sc

NS = 1_000_000_000


def overhead_world(p: CameraOverheadParams) -> Callable[[sc.Scenario], Callable[[int, m.StateEstimate], m.PolytopeSet | None]]:
    """The world source for :class:`sim_twin.lockstep.RunConfig`: the twin's default overhead camera and
    markers (the lens and markers of ``p`` are the lab's: the twin's are its own), ``p``'s rate and colours."""

    def for_scenario(scenario: sc.Scenario) -> Callable[[int, m.StateEstimate], m.PolytopeSet | None]:
        cam = oc.default_camera()
        renderer = oc.OverheadRenderer(cam, oc.default_markers(), seed=scenario.seed)
        camera = ObstacleCamera(p)
        camera.lens = cam.lens
        camera.markers = oc.default_markers()
        period_ns = int(NS / p.rate_hz)
        due = [0]

        def world(now_ns: int, state: m.StateEstimate) -> m.PolytopeSet | None:
            if now_ns < due[0]:
                return None
            due[0] = now_ns + period_ns
            frame = renderer.render(scenario, (state.position[0], state.position[1]))
            return camera.step(frame, now_ns / NS, now_ns)

        return world

    return for_scenario
