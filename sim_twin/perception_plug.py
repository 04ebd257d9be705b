"""``--perception depth``: the graph planner on what ``onboard.perception`` makes of the
twin's depth camera, instead of the scenario's ground-truth obstacles.

Depth images are fused as the sensors deliver them (with the robot's estimated
position), each with the colour image of its stamp where one came first (the D435's
apex frames: ``color`` then ``depth``); every ``perception.rate_hz`` the perceived
convex obstacles (or free cells, ``perception.mode = "free"``) replace the planner's
world, which makes it replan. Before
the first view the planner knows no obstacle at all; in obstacle mode it then commits the
robot nowhere (``onboard.high_level.planning.seen_space``).
"""

from __future__ import annotations

from typing import TypeVar

from onboard.contracts import messages as m
from onboard.contracts.binary_messages import ColorImage, DepthImage
from onboard.contracts.params import PerceptionParams
from onboard.perception.pipeline import PerceptionLoop
from onboard.high_level.planning.seen_space import SeenSpace
from robot_description import params as rd
from sim_twin.scenarios import Scenario
from sim_twin.stack import GraphPlannerPlug

PERCEPTIONS = ("truth", "depth")

T = TypeVar("T")


def _expect(topic: str, msg: object, kind: type[T]) -> T:
    if not isinstance(msg, kind):
        raise TypeError(f"{topic}: expected a {kind.__name__}, got {type(msg).__name__}")
    return msg


class PerceivedGraphPlannerPlug(GraphPlannerPlug):
    name = "graph+perception"

    def __init__(self, scenario: Scenario, robot: rd.RobotParams, params: object | None = None,
                 perception_params: PerceptionParams | None = None) -> None:
        super().__init__(scenario, robot, params)
        self.loop = PerceptionLoop(perception_params or PerceptionParams())
        self.mode = self.loop.params.mode
        # nothing is known before the first view: no obstacle, or no free cell
        (self.planner.set_free_cells if self.mode == "free" else self.planner.set_obstacles)([])
        if self.mode == "obstacles":  # unknown counts as free there: commit only to what was seen
            self.planner.set_seen(None, required=self.planner.params.require_seen)
        self._xy: tuple[float, float] = scenario.start
        self._goal = scenario.target()
        self.polygons = 0
        self._color: ColorImage | None = None
        self.views_with_color = 0

    def feed(self, topic: str, msg: object) -> None:
        if topic == "color":
            self._color = _expect(topic, msg, ColorImage)
        elif topic == "depth":
            depth = _expect(topic, msg, DepthImage)
            color = self._color.rgb if self._color is not None and self._color.stamp_ns == depth.stamp_ns else None
            self._color = None
            if self.loop.feed(depth, self._xy, color) and color is not None:
                self.views_with_color += 1
        else:
            super().feed(topic, msg)

    def update(self, now_ns: int, state: m.StateEstimate) -> m.ComReference | None:
        self._xy = (state.position[0], state.position[1])
        polys = self.loop.update(now_ns, self._xy, self._goal)
        if polys is not None:
            self.polygons = len(polys)
            verts = [p.vertices for p in polys]
            if self.mode == "free":
                self.planner.set_free_cells(verts)
                # not a gate (free cells are seen free): the frontier to head for when the goal is beyond them
                self.planner.set_seen(SeenSpace.from_grid(self.loop.view.grid()), required=False)
            else:
                self.planner.set_obstacles(verts)
                self.planner.set_seen(SeenSpace.from_grid(self.loop.view.grid()))
        return super().update(now_ns, state)


def make_planner(name: str, perception: str, scenario: Scenario, robot: rd.RobotParams, params: object | None = None,
                 perception_params: PerceptionParams | None = None):
    """The planner the runner asks for, on ground truth or on perception."""
    from sim_twin.stack import make_planner as make_truth_planner

    if perception == "truth":
        return make_truth_planner(name, scenario, robot, params)
    if perception != "depth":
        raise ValueError(f"unknown perception {perception!r}; known: {', '.join(PERCEPTIONS)}")
    if name not in ("auto", "graph"):
        raise ValueError("--perception depth feeds the graph planner; use --planner graph or auto")
    return PerceivedGraphPlannerPlug(scenario, robot, params, perception_params)
