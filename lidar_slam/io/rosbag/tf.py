"""The IMU's mounting from a bag's own /tf_static (tf2_msgs/TFMessage): a ROS driver publishes
where each of its frames sits (an Ouster driver: os1_sensor -> os1_lidar turned 180 deg about z
and 36 mm up, os1_sensor -> os1_imu 6, -12, 8 mm), and every PointCloud2 and Imu message names
its frame in its header. T_lidar_imu is then the chain between the two frames, through their
common root. Both messages naming the same frame is not taken as a mounting (a default left in
two drivers' settings says nothing): the IMU is then calibrated from the data, as without
/tf_static. Only static transforms are read: a mounting does not move, and a /tf at 100 Hz is
a robot's motion, not its calibration."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import numpy as np

from lidar_slam.geometry import inverse, make_pose, matrix_from_quat
from lidar_slam.io.rosbag.bag import open_bag, topic_messages
from lidar_slam.io.rosbag.reader import BAG_ERRORS, LEAKS
from lidar_slam.io.rosbag.topics import pick_typed_topic

log = logging.getLogger(__name__)

TF_MESSAGE = "tf2_msgs/msg/TFMessage"
STATIC_TOPICS = ("/tf_static", "tf_static")
UNIT_QUATERNION_TOLERANCE = 1e-3  # |q| - 1: a quaternion written with 6 digits is within this


def _frame(name: str) -> str:
    return name.strip().lstrip("/")  # ROS1 tf names may carry a leading slash


def static_tree(bag: Any) -> tuple[dict[str, tuple[str, np.ndarray]], list[str]]:
    """{child: (parent, T_parent_child)} of the transforms on the bag's /tf_static, and what
    was left out: a transform that is not finite or whose quaternion is not a unit one, and a
    child given two different transforms (which one holds cannot be told)."""
    tree: dict[str, tuple[str, np.ndarray]] = {}
    left_out: dict[str, str] = {}
    topics = bag.topics()
    for topic in STATIC_TOPICS:
        if topics.get(topic, ("", 0))[0] != TF_MESSAGE:
            continue
        for deserialize in topic_messages(bag, topic):
            for tf in deserialize().transforms:
                t, q = tf.transform.translation, tf.transform.rotation
                child, parent = _frame(tf.child_frame_id), _frame(tf.header.frame_id)
                quat, trans = np.array([q.x, q.y, q.z, q.w]), np.array([t.x, t.y, t.z])
                if not (np.isfinite(quat).all() and np.isfinite(trans).all()
                        and abs(np.linalg.norm(quat) - 1.0) < UNIT_QUATERNION_TOLERANCE):
                    left_out[child] = f"{parent} -> {child} is not a rigid transform"
                    continue
                T = make_pose(matrix_from_quat(quat), trans)
                if child in tree and (tree[child][0] != parent
                                      or not np.allclose(tree[child][1], T, atol=1e-9)):
                    left_out[child] = f"{child} is given two different transforms"
                tree[child] = (parent, T)
    for child in left_out:
        tree.pop(child, None)
    return tree, list(left_out.values())


def _to_root(tree: dict[str, tuple[str, np.ndarray]], frame: str) -> tuple[str, np.ndarray]:
    """(root, T_root_frame) up the tree (a loop in it stops at the repeat)."""
    T, seen = np.eye(4), {frame}
    while frame in tree:
        parent, T_parent_frame = tree[frame]
        T, frame = T_parent_frame @ T, parent
        if frame in seen:
            break
        seen.add(frame)
    return frame, T


def between(tree: dict[str, tuple[str, np.ndarray]], target: str, source: str
            ) -> np.ndarray | None:
    """T_target_source (source-frame vectors into the target frame) through the tree, or None
    when the two frames are not in one tree."""
    if target == source:
        return np.eye(4)
    root_t, T_root_target = _to_root(tree, target)
    root_s, T_root_source = _to_root(tree, source)
    if root_t != root_s:
        return None
    return inverse(T_root_target) @ T_root_source


def _first_frame(bag: Any, topic: str) -> str | None:
    for deserialize in topic_messages(bag, topic):
        return _frame(deserialize().header.frame_id) or None
    return None


def imu_mounting(path: Path, cloud_topic: str, imu_topic: str | None
                 ) -> tuple[np.ndarray | None, str]:
    """T_lidar_imu from the bag's /tf_static between the frames its clouds and its Imu messages
    name (imu_topic: named, else the only sensor_msgs/Imu topic), and a phrase saying from
    where; (None, why not) when the bag does not say."""
    try:
        with open_bag(path) as bag:
            topics = bag.topics()
            picked = pick_typed_topic(path, topics, imu_topic, "sensor_msgs/msg/Imu",
                                      "--imu-topic")
            if picked is None:
                return None, "no Imu topic"
            lidar, imu = _first_frame(bag, cloud_topic), _first_frame(bag, picked)
            if lidar is None or imu is None:
                return None, "a header without a frame_id"
            if lidar == imu:  # often a default left in both drivers' settings: not a statement
                return None, f"clouds and Imu messages both say frame_id {lidar}"
            tree, left_out = static_tree(bag)
            T = between(tree, lidar, imu)
    except (*BAG_ERRORS, *LEAKS):
        return None, "unreadable /tf_static"  # the streams' own reading names the problem
    if T is None:
        why = f"no /tf_static chain from {imu} to {lidar}"
        if left_out:
            why += f" ({'; '.join(left_out)}: left out)"
            log.warning("%s: the IMU's mounting is not taken from /tf_static: %s", path, why)
        return None, why
    return T, f"/tf_static {imu} -> {lidar}"
