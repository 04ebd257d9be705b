"""The thesis's own terrains (Fig. 5.17) and planning worlds at its scale (Figs. 7.5, 7.6), for
``archer reproduce`` (issue 29) and anyone who wants them: registered in
:data:`sim_twin.scenarios.SCENARIOS` like the others.
"""

from __future__ import annotations


import mujoco
import numpy as np

from sim_twin.scenario_base import Obstacle, Scenario, _box, _segment, register, straight_reference


@register
class Stairs(Scenario):
    name = "stairs"
    description = "climb three 1.5 inch (3.8 cm) stairs to a goal on the top landing (thesis Fig. 5.17 b)"
    default_duration_s = 30.0
    RISE = 0.038  # [m] 1.5 inch
    TREAD = 0.35  # [m] a few hops per stair
    STEPS = 3
    FIRST_EDGE = 0.6  # [m] from the start
    LANDING = 2.0  # [m] the top stair runs on this far

    def setup(self, obstacles: int | None) -> None:
        # each stair a box from its edge to the landing's end, one rise taller than the last: no gaps to catch a foot
        end = self.FIRST_EDGE + self.STEPS * self.TREAD + self.LANDING
        self.terrain = []
        for k in range(self.STEPS):
            edge, top = self.FIRST_EDGE + k * self.TREAD, (k + 1) * self.RISE
            self.terrain.append((f"stair{k}", dict(type=mujoco.mjtGeom.mjGEOM_BOX, size=[(end - edge) / 2, 1.5, top / 2],
                                                   pos=[(edge + end) / 2, 0.0, top / 2])))
        self.goal_xy = (self.FIRST_EDGE + (self.STEPS - 1) * self.TREAD + 0.9, 0.0)
        self.segments = straight_reference(self.start, self.goal_xy, speed=self.cruise_speed)


@register
class Board(Scenario):
    name = "board"
    description = "hop across a 2x4 lying on the floor (3.8 x 8.9 cm) to a goal beyond it (thesis Fig. 5.17 d)"
    default_duration_s = 20.0
    HEIGHT = 0.038  # [m] a 2x4's 1.5 inch
    WIDTH = 0.089  # [m] and its 3.5 inch
    AT = 0.8  # [m] its near edge from the start

    def setup(self, obstacles: int | None) -> None:
        self.terrain = [("board", dict(type=mujoco.mjtGeom.mjGEOM_BOX, size=[self.WIDTH / 2, 1.5, self.HEIGHT / 2],
                                       pos=[self.AT + self.WIDTH / 2, 0.0, self.HEIGHT / 2]))]
        self.goal_xy = (self.AT + 1.0, 0.0)
        self.segments = straight_reference(self.start, self.goal_xy, speed=self.cruise_speed)


@register
class Treadmill(Scenario):
    """A treadmill whose belt runs at up to 1 mph, in the belt's frame: the twin has no air, so
    its physics is the same in any frame moving at a constant speed, and holding station on a
    belt at speed v is tracking a point that moves at v over a still floor. Each change of the
    belt's speed is a step of the reference's velocity (the thesis's disturbances); what the
    frame does not carry over is the belt's own acceleration during a stance."""

    name = "treadmill"
    description = "hold station on a treadmill as its belt steps up to 1 mph (0.447 m/s), in the belt's frame (thesis Fig. 5.17 a)"
    SPEEDS = (0.1, 0.2, 0.3, 0.447)  # [m/s] the belt's speeds, each held STAGE_S (1 mph last)
    STAGE_S = 6.0
    SETTLE_S = 3.0  # [s] hopping in place before the belt starts
    default_duration_s = SETTLE_S + len(SPEEDS) * STAGE_S

    def setup(self, obstacles: int | None) -> None:
        x, t = 0.0, self.SETTLE_S
        segs = [_segment(0.0, t, [list(self.start)])]
        for v in self.SPEEDS:
            segs.append(_segment(t, self.STAGE_S, [[x, 0.0], [x + v * self.STAGE_S, 0.0]]))
            x, t = x + v * self.STAGE_S, t + self.STAGE_S
        self.segments = segs
        self.goal_xy = (x, 0.0)

    def belt_speed(self, t: float) -> float:
        """[m/s] at ``t`` [s]."""
        stage = int((t - self.SETTLE_S) // self.STAGE_S)
        return 0.0 if t < self.SETTLE_S else self.SPEEDS[min(stage, len(self.SPEEDS) - 1)]


@register
class GridMaze(Scenario):
    """Thesis Fig. 7.6's scale: a maze of 600 cells (30 x 20) cut from a random spanning tree of the
    grid (every cell reachable, one way between any two), then a share of its wall pieces opened
    at random: loops, as in the thesis's figure, and paths the planner must choose between rather
    than the single corridor of a perfect maze. The walls left are merged into straight runs, one
    obstacle each (about 280; the thesis's figure has 300). The robot starts in one corner cell and the goal
    is the opposite one."""

    name = "maze-600"
    description = "thesis Fig. 7.6's scale: a 30 x 20 cell maze (600 cells), its walls ~300 obstacles, corner to corner"
    COLUMNS, ROWS = 30, 20
    CELL = 0.8  # [m] passages of 0.7 m between 0.1 m walls: the robot (0.26 m) and its tube pass
    THICK = 0.1  # [m]
    OPENED = 0.15  # share of the tree's wall pieces opened: about 280 obstacles are left (the thesis: 300)
    default_duration_s = 600.0

    def setup(self, obstacles: int | None) -> None:
        cols, rows, c = self.COLUMNS, self.ROWS, self.CELL
        # walls between horizontally adjacent cells (i, j)-(i+1, j) and vertically adjacent (i, j)-(i, j+1)
        vertical = np.ones((cols - 1, rows), dtype=bool)
        horizontal = np.ones((cols, rows - 1), dtype=bool)
        seen = np.zeros((cols, rows), dtype=bool)
        stack = [(0, 0)]
        seen[0, 0] = True
        while stack:  # randomized depth-first search: a spanning tree of the cells
            i, j = stack[-1]
            nbrs = [(a, b) for a, b in ((i + 1, j), (i - 1, j), (i, j + 1), (i, j - 1))
                    if 0 <= a < cols and 0 <= b < rows and not seen[a, b]]
            if not nbrs:
                stack.pop()
                continue
            a, b = nbrs[int(self.rng.integers(len(nbrs)))]
            if a != i:
                vertical[min(a, i), j] = False
            else:
                horizontal[i, min(b, j)] = False
            seen[a, b] = True
            stack.append((a, b))
        for walls in (vertical, horizontal):
            walls &= self.rng.random(walls.shape) >= self.OPENED
        t = self.THICK / 2
        w, h = cols * c, rows * c
        border = [_box(w / 2, -t, w / 2 + 2 * t, t), _box(w / 2, h + t, w / 2 + 2 * t, t),
                  _box(-t, h / 2, t, h / 2), _box(w + t, h / 2, t, h / 2)]
        self.obstacles = self._runs(vertical, horizontal) + border
        # the start is the twin's origin: the maze is placed with the first cell's centre there
        shift = (-c / 2, -c / 2)
        self.obstacles = [Obstacle(tuple((x + shift[0], y + shift[1]) for x, y in o.vertices)) for o in self.obstacles]
        self.goal_xy = ((cols - 1) * c, (rows - 1) * c)
        self.segments = straight_reference(self.start, self.goal_xy, speed=self.cruise_speed)

    def _runs(self, vertical: np.ndarray, horizontal: np.ndarray) -> list[Obstacle]:
        """The walls left standing, consecutive collinear pieces merged into one box each."""
        c, t = self.CELL, self.THICK / 2
        out = []
        for i, line in enumerate(vertical):  # the wall at x = (i + 1) c, along y
            out += [_box((i + 1) * c, (j + k) * c / 2, t, (k - j) * c / 2 + t) for j, k in _standing(line)]
        for j, line in enumerate(horizontal.T):  # the wall at y = (j + 1) c, along x
            out += [_box((i + k) * c / 2, (j + 1) * c, (k - i) * c / 2 + t, t) for i, k in _standing(line)]
        return out

    def world_summary(self) -> dict:
        return {**super().world_summary(), "cells": self.COLUMNS * self.ROWS, "cell_m": self.CELL}


def _standing(line: np.ndarray) -> list[tuple[int, int]]:
    """``[start, end)`` of each run of True in ``line``."""
    edges = np.flatnonzero(np.diff(np.concatenate([[False], line, [False]]).astype(np.int8)))
    return list(zip(edges[::2].tolist(), edges[1::2].tolist()))
