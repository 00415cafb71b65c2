"""Backends: turn odometry (and loop) measurements into a trajectory."""
