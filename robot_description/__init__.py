"""The robot description: the MJCF models (the one source of ARCHER's physical parameters)
and what is read from them without MuJoCo, so that the robot's services need no simulator."""
