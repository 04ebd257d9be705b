"""The low level (thesis ch. 4 and 5; its two layers, lines 1524-1581 and 2377-2777).

``tracking`` (low-level tracking, ch. 4.1): the quaternion PD on the wheels in flight, wheel
spin-down in stance, the foot thrust, the safety supervisor and the flip manoeuvre.
``planning`` (low-level planning, ch. 5): the Zero Dynamics Policy (linear, clipped, network)
and the geometric MPC on S3, choosing the impact attitude. ``controller`` composes them into
the 1 kHz step. Assumes a state estimate and a CoM reference (contracts); guarantees torques
within the limits and the tracking tube it actually achieves, published for the planner.
"""
