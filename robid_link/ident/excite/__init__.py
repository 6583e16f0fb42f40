"""What the robot moves: excitation trajectories, experiment kinds, the verification path."""
