"""lidar_slam: lidar SLAM from a folder of scans or a rosbag to a drift-corrected trajectory and map."""

__version__ = "0.1.0"
