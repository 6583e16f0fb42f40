"""Example files shipped with robid_link (read them with importlib.resources)."""
