"""CiA 402 servo drives on a CAN bus, the daemon as motion master: the driver, its
motion master thread, recording, feed-forward offsets and the CiA 301/402 facts it uses."""
