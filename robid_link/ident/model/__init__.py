"""The robot model: descriptions (MDH, URDF), the rigid-body regressor, the effect
catalog and known torques."""
