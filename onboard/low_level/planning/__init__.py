"""Low-level planning (thesis ch. 5): the Zero Dynamics Policy (5.5, lines 2377-2777) mapping the
CoM's state and its reference to the impact attitude, as a linear, clipped or network policy,
and the geometric MPC on S3 (5.3, lines 2061-2248). Assumes the low-level tracking layer
reaches the attitude it is given; guarantees an attitude set point whose hop stays within the
tube the high level was promised."""
