"""Files: rosbag2 bags, ROS 2 parameter files, calibration files, scenarios; atomic output."""
