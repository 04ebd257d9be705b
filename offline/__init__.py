"""Offline work that is not the robot's code: iLQR, the thesis's Algorithm 2 (ZDP training,
5.5) and network training. Pure like ``onboard`` (no I/O), so the robot's tests may use it, but
nothing that runs on the robot imports it; ``archer train-zdp`` writes what it learns to
``onboard/data``."""
