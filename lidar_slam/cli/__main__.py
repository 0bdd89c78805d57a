"""`python -m lidar_slam.cli ...`: the same as the `lidar-slam` command."""

from lidar_slam.cli import entry

if __name__ == "__main__":
    entry()
