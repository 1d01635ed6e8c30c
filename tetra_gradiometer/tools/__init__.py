"""Offline tools on rosbag2 files and the paper reproduction (one command per module)."""
