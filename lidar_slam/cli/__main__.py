"""`python -m lidar_slam.cli ...`: the same as the `lidar-slam` command."""

from lidar_slam.cli import app

if __name__ == "__main__":
    app()
