"""The run's top view drawn by a helper process (lidar_slam.run.painter): the same picture as
drawn in the run's own process, and still drawn when the helper is gone."""

import numpy as np

from lidar_slam.eval.evaluate import plot_run_top_view
from lidar_slam.geometry import make_pose
from lidar_slam.run.painter import TopViewPainter


def _walk() -> np.ndarray:
    t = np.linspace(0.0, 2 * np.pi, 60)
    return np.stack([make_pose(np.eye(3), [5 * np.cos(a), 3 * np.sin(a), 0.0]) for a in t])


def test_the_helper_draws_the_same_picture_as_the_run_would(tmp_path):
    poses = _walk()
    plot_run_top_view(tmp_path / "here.png", poses, None)
    painter = TopViewPainter.start()
    try:
        painter.finish(painter.draw(tmp_path / "helper.png", poses, None))
    finally:
        painter.close()
    assert (tmp_path / "helper.png").read_bytes() == (tmp_path / "here.png").read_bytes()


def test_without_its_helper_the_run_draws_the_picture_itself(tmp_path):
    poses = _walk()
    painter = TopViewPainter.start()
    painter.close()  # gone (as if it had died): drawn in this process
    painter.finish(painter.draw(tmp_path / "top.png", poses, None))
    plot_run_top_view(tmp_path / "here.png", poses, None)
    assert (tmp_path / "top.png").read_bytes() == (tmp_path / "here.png").read_bytes()
