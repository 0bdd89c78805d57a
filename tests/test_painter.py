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


def test_a_helper_ended_from_its_pools_own_thread_does_not_join_that_thread():
    """A run that stops by an exception leaves its painter to a finalizer, which a garbage
    collection may run in the pool's manager thread (seen in CI: "cannot join current thread"
    printed as a traceback under the run's one-line error). Here a thread stands for it."""
    import threading

    from lidar_slam.loop.worker import kill_pool

    painter = TopViewPainter.start()
    pool = painter._pool
    manager = pool._executor_manager_thread
    errors = []

    def as_the_manager():
        pool._executor_manager_thread = threading.current_thread()
        try:
            kill_pool(pool)
        except Exception as exc:  # noqa: BLE001 (the test's finding)
            errors.append(exc)

    worker = threading.Thread(target=as_the_manager)
    worker.start()
    worker.join()
    painter._finalizer.detach()
    manager.join(timeout=30)
    assert errors == [] and not manager.is_alive()
