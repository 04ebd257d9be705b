"""The high level (thesis ch. 6 and 7): ``tracking`` turns waypoints and convex sets into a
dynamically feasible Bezier CoM trajectory; ``planning`` finds those waypoints through free
space. It learns of the low level only through the contracts (the tube it was promised)."""
