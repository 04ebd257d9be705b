"""High-level tracking (thesis ch. 6, lines 2782-3066): Bezier reachable polytopes of the
hopping CoM, the Bezier MPC refining a path inside them, and the collision tests between
Bezier hulls and obstacles. Assumes the low level tracks a reference within its tube;
guarantees a reference that is dynamically feasible and clear of obstacles by that tube."""
