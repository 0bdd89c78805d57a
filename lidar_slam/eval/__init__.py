"""Measurement: KITTI drift, ATE, RPE (metrics, pure NumPy), and scoring a trajectory file
against ground truth with plots (evaluate)."""
