"""Scripts around lidar_slam (benchmarks, forensics, dev setup): see tools/README.md.

A package so that the tests import the functions they check (`from tools import benchmark`).
"""
