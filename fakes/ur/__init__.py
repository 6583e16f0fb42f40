"""A fake Universal Robots controller from UR's documents: RTDE, the dashboard server, the
script port, and a small URScript interpreter over the simulated robot."""
