"""ROS 2 nodes: driver, tensor, calibrator, compensator, target (thin: message -> array ->
core -> message), and their shared helpers (``common``)."""
