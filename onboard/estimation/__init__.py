"""State estimation (thesis 5.5, line 2751): a Kalman filter with projectile dynamics in flight
and a pinned foot in stance, an error-state attitude filter, and touchdown / liftoff / apex
detection. Assumes time-stamped IMU, joint and pose samples (contracts); guarantees a state
estimate with its covariance and a ``valid`` flag the low level can trust or refuse."""
