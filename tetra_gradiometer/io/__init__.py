"""Formats and messages: what is read and written, with no pipeline in it.

rosbag2 bags (``bag``, ``bag_decode``, ``bag_skips``, ``recording``: the data contract's
topics as arrays), message <-> array conversions for rclpy and rosbags alike
(``conversions``), matching the four magnetometer streams by stamp (``matching``), ROS 2
parameter files (``params``), calibration files (``calibration``), scenario files
(``scenario``), ``targets.json`` (``targets``), atomic outputs (``outputs``) and progress
bars (``progress``).

Layering: ``io`` imports ``core`` only. ``bag`` and ``recording`` import ``rosbags`` (an
offline-only package); the nodes import ``conversions``, ``matching``, ``calibration`` and
``params``, which do not.
"""
