"""lidar_slam: lidar SLAM from a folder of scans or a rosbag to a drift-corrected trajectory and map."""

import os as _os

# One OpenBLAS thread. kiss-icp's registration runs on every core (TBB); OpenBLAS threads woken by
# a large NumPy product (the deskew's (N,3) x (3,3)) then spin-wait and take those cores away:
# registration took 29.5 instead of 15.1 ms per HDL-64 scan on 2 cores. Our products are all
# (N,3) x (3,3), for which one thread is as fast. Only effective when NumPy is not yet imported
# (the CLI); a user's own setting wins.
_os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

__version__ = "0.1.0"
