"""lidar_slam: lidar SLAM from a folder of scans or a rosbag to a drift-corrected trajectory and
map.

Importing it has no side effects; a run's process tuning is lidar_slam.runtime.tune_process().
"""

__version__ = "0.1.0"
