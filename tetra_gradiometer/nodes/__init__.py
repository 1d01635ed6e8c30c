"""ROS 2 nodes: driver, tensor, calibrator, compensator (thin: message -> array -> core ->
message), and their shared helpers (``common``)."""
