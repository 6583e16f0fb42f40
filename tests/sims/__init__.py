"""Small simulators written for the tests, sharing no code with the analysis they check."""
