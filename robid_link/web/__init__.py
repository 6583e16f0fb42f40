"""The operator's web page: ``robid web`` (read-only, from the state dir) and the daemon's own
page (``web: {listen: …}``, with actions)."""
