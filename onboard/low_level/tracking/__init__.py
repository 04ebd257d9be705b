"""Low-level tracking (thesis ch. 4.1, lines 1524-1581, 2201-2216, 2719-2734): the quaternion PD
on the reaction wheels, wheel spin-down on the ground, the foot's thrust, the safety
supervisor, and the flip (Fig. 5.13). Assumes a desired attitude and a state estimate;
guarantees bounded torques that track it, or a counted, logged safe stop."""
