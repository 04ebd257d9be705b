"""High-level planning (thesis ch. 7, lines 3067-3220): the kinodynamic Bezier graph (build,
cut against obstacles, search), its densification, the record of space seen, and the planner
that composes them with the MPC refinement. Assumes convex obstacles or free cells from
perception and the high-level tracking layer; guarantees waypoints and convex sets {X_k} that
the MPC can refine."""
