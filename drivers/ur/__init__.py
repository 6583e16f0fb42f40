"""Universal Robots over RTDE (protocol version 2): the driver, its session and codec,
the recording of the stream, the URScript the program becomes."""
