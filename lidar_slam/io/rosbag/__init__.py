"""ROS bags: sensor_msgs/PointCloud2 topics as Scans, Imu and NavSatFix topics as IMU samples and
GNSS fixes; the only package that imports rosbags, one module per job:

- source.py: RosbagSource, the scans of one PointCloud2 topic (and the bag's IMU / GNSS);
- topics.py: which topic to read (the one named, else the only one of its type);
- pointcloud2.py: decoding a PointCloud2 message (points, per-point times, intensity);
- imu_gnss.py: the Imu and NavSatFix topics as ImuSamples and GnssFixes;
- bag.py: opening a bag (rosbags' AnyReader, or one of the readers below), errors as InputError;
- mcap.py, recovery.py: sequential readers (ros1-profile MCAP; recordings cut short);
- reader.py: the BagReader interface and the errors caught around rosbags.

Containers: a ROS1 `.bag`, a ROS2 bag folder (metadata.yaml with .db3 or .mcap storage), and a
standalone `.mcap` of profile "ros2" (all through rosbags' AnyReader) or "ros1" (which rosbags'
MCAP reader rejects, so `McapScan` (mcap.py) walks the records and deserializes with a rosbags
typestore built from the file's ros1msg schemas).

A recording cut short (a crashed recorder: no mcap footer, no ROS1 index, a .db3 shorter than
its header says), which rosbags refuses, is read up to its last complete message by the
sequential readers here (`McapScan`, `Ros1BagScan`, `Db3Scan`), with one warning.

Time convention of the Scans produced here:
- `Scan.stamp_s` is the PointCloud2 header stamp in seconds (not the bag's receive time).
- `Scan.point_times` are seconds relative to `stamp_s`, converted by
  `lidar_slam.io.point_times.relative_seconds` (the conversion every reader shares): a relative
  field (Ouster `t`, Livox `offset_time`, Velodyne `time`) is an offset from the header stamp as
  it stands, so an Ouster cloud stamped at the sweep start gets times in [0, ~0.1] and a Velodyne
  cloud stamped at the sweep end gets times in [~-0.1, 0]; an absolute field (within 10 s of the
  header stamp, in s, us or ns) has the header stamp subtracted.
"""


from lidar_slam.io.rosbag.bag import open_bag
from lidar_slam.io.rosbag.imu_gnss import read_gnss_topic, read_imu_topic
from lidar_slam.io.rosbag.pointcloud2 import (
    POINTCLOUD2,
    DecodedCloud,
    PointCloud2Error,
    decode_pointcloud2,
    header_stamp_ns,
)
from lidar_slam.io.rosbag.source import RosbagSource

__all__ = ["POINTCLOUD2", "DecodedCloud", "PointCloud2Error", "RosbagSource", "decode_pointcloud2",
           "header_stamp_ns", "open_bag", "read_gnss_topic", "read_imu_topic"]
