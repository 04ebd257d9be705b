"""The robot's algorithms, pure and synchronous, in folders that are the thesis's layers.

Bottom to top (each imports only the ones before it; ``tests/test_layers.py`` holds the rule):

- ``contracts``: what passes between layers (ch. 3.5, 8.1): messages, binary layouts, the
  topic table, parameters and limits, the commander rule, the tracking tube, how a reference
  is read;
- ``geometry``: quaternions, Bezier curves, polygons, shared by several layers;
- ``estimation``: the Kalman estimator, attitude and CoM filters, phase detection (5.5, 2751);
- ``perception``: depth and grids to convex sets (7.1, 8.2);
- ``low_level``: ``tracking`` (ch. 4: quaternion PD, spin-down, foot, supervisor, flip), then
  ``planning`` (ch. 5: ZDP, geometric MPC), composed by ``low_level.controller`` at 1 kHz;
- ``high_level``: ``tracking`` (ch. 6: reachable polytopes, Bezier MPC, collision tests),
  then ``planning`` (ch. 7: the Bezier graph, densification, seen space, the planner).

No I/O, threads, clocks, global random state or files written anywhere in here; offline work
(training) lives in the top-level ``offline`` package, which the robot never imports.
"""
