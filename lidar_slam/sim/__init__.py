"""A lidar simulator: a procedural street world along a trajectory, ray cast with open3d.

Modules: sensor (lidar models: spinning multi-beam ones, and a non-repetitive one with a time per
point; poses between stamps), world (the street world), sequence (sweeps
and KITTI-layout sequences, KITTI ground truth), inertial (a smooth trajectory, and the IMU and
GNSS measured along it), jobs (`lidar-slam simulate`: one sequence per pose file, several on the
Ray fleet of `batch`), handheld (`--motion handheld`: a walk with the lidar in the hand, no pose
file), legged and drone (`--motion legged|drone`: a quadruped's trot, a multirotor's flight),
motions (one of those three through a world, written as a sequence), indoor (the built interior
a walk goes through) and floors (`--world office|warehouse`: identical rooms, a pillared hall).

Conventions (also written into every sequence's README):
- Input poses are T_world_lidar (K, 4, 4) at stamps_s (K,). The world is built along the stretch
  that is simulated. The ground is ONE height field fitted to the trajectory's heights minus the
  sensor mount height; the simulated poses keep the input x, y and heading, and take z (ground +
  mount height) and roll/pitch (ground normal) from that field. Those simulated poses are the
  ones written out.
- A scan's stamp is the START of its sweep (`--stamp end`: its END, start + period; the poses
  and the per-point times then refer to that instant). Column c of a spinning sweep is captured
  at start + c * period / n_azimuth, each point of a non-repetitive sweep at its own time (a
  sensor's `sweep(frame, seed)` says which directions fire when), from the pose interpolated at
  that instant (slerp/lerp between the simulated poses, extrapolated past the last one), so
  scans carry true motion distortion. With an IMU or GNSS,
  the poses between stamps come from imu_gnss.SmoothTrajectory instead (a cubic spline and a
  RotationSpline through the same poses), for the points and the IMU/GNSS alike. The head
  starts facing backwards (azimuth 180 deg) and turns clockwise seen from above, like a
  Velodyne.
- Points are in the sensor frame of their own capture instant (raw, not deskewed); per-point times
  are seconds relative to the stamp, in [0, period) (in [-period, 0) stamped at the end).
- With an IMU, imu.csv may be on a clock time_offset_s behind the lidar's; lidar_slam.yaml beside
  the sequence is the config overlay (imu.T_lidar_imu, imu.time_offset_s) a run needs.
- Output is a KITTI-layout folder: velodyne/NNNNNN.bin (float32 x, y, z, intensity),
  velodyne_times/NNNNNN.bin (float32 s), times.txt, calib.txt (Tr: T_cam_lidar, identity unless
  given), poses.txt with P_i = Tr @ T_seq_lidar_i @ inv(Tr), where the sequence frame is the
  lidar frame of the first written scan (so P_0 = I, as in KITTI).
"""


from lidar_slam.sim.sensor import (
    SENSORS,
    LidarModel,
    NonRepetitiveModel,
    PoseInterpolator,
    SensorModel,
    Sweep,
    get_sensor,
)
from lidar_slam.sim.sequence import (
    OVERLAY_FILE,
    STAMPS,
    KittiTruth,
    SimScan,
    SimSummary,
    load_kitti_truth,
    sequence_world,
    simulate_scan,
    simulate_sequence,
    write_calib,
)
from lidar_slam.sim.world import (
    ALBEDO,
    CLASSES,
    Centerline,
    Terrain,
    World,
    WorldParams,
    build_world,
    fit_terrain,
    make_centerline,
    place_on_terrain,
)

__all__ = ["ALBEDO", "CLASSES", "OVERLAY_FILE", "SENSORS", "STAMPS", "Centerline", "KittiTruth",
           "LidarModel", "NonRepetitiveModel", "PoseInterpolator", "SensorModel", "SimScan",
           "SimSummary", "Sweep", "Terrain", "World", "WorldParams",
           "build_world", "fit_terrain", "get_sensor", "load_kitti_truth", "make_centerline",
           "place_on_terrain", "sequence_world", "simulate_scan", "simulate_sequence",
           "write_calib"]
