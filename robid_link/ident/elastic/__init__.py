"""Joint elasticity: frequency responses from stepped sines and the two-mass fits."""
