"""One pydantic model per stage, gathered in SlamConfig; YAML overlay load and dump."""

from __future__ import annotations

import logging
import re
from pathlib import Path
from typing import Annotated, Literal

import numpy as np
import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from lidar_slam.errors import ConfigError, InputError
from lidar_slam.io.atomic import write_text_atomic

# Value ranges, checked when a config is loaded (a negative voxel size used to run, and quietly
# change the result): lengths, angles, sigmas and thresholds are positive, counts at least 1.
Positive = Annotated[float, Field(gt=0)]
NonNegative = Annotated[float, Field(ge=0)]
Fraction = Annotated[float, Field(ge=0, le=1)]
Count = Annotated[int, Field(ge=1, le=2**31 - 1)]  # kiss-icp and gtsam take C ints
NonNegativeInt = Annotated[int, Field(ge=0, le=2**31 - 1)]
Auto = Literal["auto"]  # the value follows the data (lidar_slam.loop.adapt), fixed at scan 0
log = logging.getLogger(__name__)


def _takes_bool(annotation) -> bool:
    """Whether a field's type has room for True / False (else pydantic reads true as 1)."""
    import typing

    if annotation is bool:
        return True
    if typing.get_origin(annotation) is Literal:
        return any(isinstance(v, bool) for v in typing.get_args(annotation))
    return any(_takes_bool(a) for a in typing.get_args(annotation))


class _Section(BaseModel):
    # No NaN/inf: `voxel_size_m: .inf` passed every range check and ran.
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    @model_validator(mode="before")
    @classmethod
    def _no_bool_for_a_number(cls, data):
        """`distance_m: true` is a mistake, not 1.0 (pydantic's lax mode reads it so)."""
        if isinstance(data, dict):
            for key, value in data.items():
                field = cls.model_fields.get(key) if isinstance(key, str) else None
                if isinstance(value, bool) and field is not None \
                        and not _takes_bool(field.annotation):
                    raise ValueError(f"{key}: {str(value).lower()} is not a number")
        return data


class DataConfig(_Section):
    min_range_m: NonNegative = 0.0
    max_range_m: Positive = 100.0
    # A scan with fewer points than this after the range crop (one per half odometry voxel) is
    # not registered but skipped like an empty one (its pose predicted, a warning, counted in
    # summary.json): ICP on a handful of points settles anywhere and drags the map with it.
    min_points: NonNegativeInt = 100
    # Deskew with per-point times (constant velocity) when the scans carry them. Done once, here.
    deskew: bool = True
    # Deskew every point of every scan (slow; for comparison): by default only the points used,
    # one per odometry voxel and the keyframe clouds.
    deskew_all_points: bool = False
    # kiss-icp's 0.205 deg vertical correction for KITTI HDL-64E scans (KITTI layout only).
    kitti_vertical_correction: bool = False

    @model_validator(mode="after")
    def _range_is_not_empty(self) -> DataConfig:
        if self.max_range_m <= self.min_range_m:
            raise ValueError(f"max_range_m ({self.max_range_m}) must exceed min_range_m "
                             f"({self.min_range_m})")
        return self


class OdometryConfig(_Section):
    # default: max_range_m / 100, as kiss-icp; at least 1 cm, a lidar's own range noise (0.1 mm
    # ran with every point its own voxel and ended at half the path, no failure said)
    voxel_size_m: Annotated[float, Field(ge=0.01)] | None = None
    max_points_per_voxel: Count = 20
    initial_threshold_m: Positive = 2.0
    min_motion_m: NonNegative = 0.1
    max_num_iterations: Count = 500
    # kiss-icp's iterations when it starts from the IMU's prediction (within centimetres): past
    # this it creeps along a street's weak axis on noise (bank car rows with the IMU: better or
    # the same at 30, every walk, trot and flight the same bytes; docs/bank.md). None: as above.
    imu_max_num_iterations: Count | None = 30
    convergence_criterion: Positive = 1e-4
    # Without the IMU's prediction, kiss-icp first aligns every coarse_every-th point of its
    # source from the constant-velocity guess, then its whole source from there: the iterations
    # a poor guess costs (15-28 a scan on a hand-held walk against 7-10 from the IMU's) are spent
    # on a quarter of the points. A subsample, not a coarser voxel grid: it keeps the source's
    # geometry, so both passes seek the same minimum (a 4.5 x voxel grid put a legged trot's
    # odometry in another, 0.035 -> 0.064 m). Only when the subsample keeps data.min_points
    # points (ICP on fewer settles anywhere): indoors, where kiss-icp's source is 100-300
    # points, it never does. Bank, lidar only, three draws (docs/bank.md, "A coarse pass
    # first"). None: off.
    coarse_every: Annotated[int, Field(ge=2, le=2**31 - 1)] | None = 4
    # On a scan kiss-icp starts from constant velocity (lidar only, or one the IMU does not
    # predict), when the last motion turned more than this (deg a scan: a hand-held flick, a
    # drone's yaw, a trot; a car's turn stays under it), kiss-icp also starts from the
    # last pose (no motion), and the pose whose points fit the last keyframes' clouds better
    # (the failure watch's fitness) is kept: a flick that stops leaves the constant-velocity
    # guess several degrees past the scan, where ICP settles in another minimum. Bank, lidar only,
    # three draws (docs/bank.md, "A second start"): the failed walks 0.34-0.72 / 0.12-2.07 m
    # -> 0.17-0.20 / 0.10-0.11 m. None: off.
    second_start_deg: Annotated[float, Field(gt=0)] | None = 4.0
    # kiss-icp's TBB threads (0: every core). With more than one, its correspondence search and
    # normal-equation sums run in a varying order (poses ~2e-15 apart, which a run's chaos
    # carried to 1.9 cm on a hand-held walk); the odometry rounds kiss-icp's pose to 1e-6
    # (pose_quantum_m below), so two runs, and runs on 1 or 2 threads, write the same
    # poses. kiss-icp sets TBB's process-wide limit from the first registration made in a
    # process, which also bounds gtsam's TBB: the first Odometry of a process decides for all.
    # Cost of one thread: 1.35x the wall time of a dense hand-held walk (docs/design.md,
    # Determinism). Bank with the rounding, every row in docs/bank.md: IMU ATE median / worst
    # 0.022 / 0.117 -> 0.017 / 0.107 m, lidar only 0.120 / 2.695 -> 0.132 / 2.252 m (the rounding
    # perturbs each run once; the thread count no longer changes a pose).
    max_num_threads: NonNegativeInt = 0
    # The grid kiss-icp's pose is rounded to (m, and the rotation matrix's entries). Not a
    # tuning knob: tools/bank.py run --perturb moves it by 0.1 % (each pose by under 0.5 um) to
    # measure how far a run's result is its chaos (docs/bank.md, "Spread").
    pose_quantum_m: Positive = 1e-6
    # Slow scans are refined after kiss-icp: a scan whose last motion is under refine_below_mps
    # (m/s) is registered again, from kiss-icp's pose, by point-to-plane ICP against the clouds
    # of the last refine_keyframes keyframes (matches up to refine_max_correspondence_m). Its
    # scan points: those kiss-icp adds to its map (one per half voxel), evenly thinned to at
    # most refine_max_points; or, with refine_voxel_m set, one centroid per voxel of that size.
    # The centroids of kiss-icp's 1.5 x voxel_size_m source voxel (the default until 2026-12-03)
    # made hand-held indoor walks 1.3-2 % too long (~200 points per OS1-64 scan, corners
    # averaged off the walls); 2,000 points of the half-voxel selection, 0.3-0.6 %.
    # kiss-icp's point-to-point match against its own recent points is pulled towards standing
    # still by the rings the beams draw on the ground, which a plane match slides along (sim
    # 07, braking from 4 m/s: 3.4 deg and 2 m lost in 25 scans). A refinement that moves the
    # pose by more than refine_max_correction_m or _deg is not taken. 0: off (kiss-icp alone).
    # 5 m/s: there kiss-icp's speed starts to fall short of the truth (sim 07: -6 % at 5 m/s, -25 %
    # at 3 m/s, -65 % at 2 m/s; docs/benchmarks/2026-12-02-slow-odometry.md).
    refine_below_mps: NonNegative = 5.0
    refine_keyframes: Count = 4
    refine_voxel_m: Positive | None = None
    refine_max_points: Count = 2000
    refine_max_correspondence_m: Positive = 1.0
    # The same for a scan the IMU predicted: kiss-icp then starts within centimetres and the
    # refinement only polishes, and matches further out are mostly to surfaces the target's
    # keyframes never saw (a room seen anew through its door as the sensor passes), which
    # pull the pose forward: at 1 m the indoor odometry came out 0.2-1.1 % too long. Lidar
    # only, the refinement is what recovers kiss-icp's misses (a slow car stuck near standing
    # still, a 16-beam walk) and keeps the 1 m basin (0.3 m there: indoor-handheld-vlp16 ATE
    # 0.10 -> 0.44 m). Decided on the bank (docs/bank.md, Decisions, 2026-12-05).
    refine_imu_correspondence_m: Positive = 0.3
    refine_max_correction_m: Positive = 0.5
    refine_max_correction_deg: Positive = 2.0
    # refine_evidence: each slow scan's refinement proves itself (2026-12-03): a share of the
    # scan's points is held out of its source, and the refined pose is kept only when those
    # points' point-to-plane residuals against the same target (truncated at 3 robust sigmas)
    # fall by more than refine_evidence_z standard errors of their mean change (a one-sided
    # paired test); else kiss-icp's pose stands. Checked first on one Gauss-Newton step fitted
    # on the held-out points themselves: when even that is not significant, the ICP is skipped.
    # "with_imu" (the default): asked on every slow scan the IMU predicted; lidar only every
    # slow scan is refined. Decided on the bank (docs/bank.md, Decisions, 2026-12-04): with the
    # IMU ATE median 0.033 -> 0.022 m and worst 0.123 -> 0.117 m over the 15 rows against
    # refining every slow scan; lidar only the evidence lost the median (0.120 -> 0.139 m) and
    # the loop precision.
    refine_evidence: bool | Literal["with_imu"] = "with_imu"
    refine_evidence_z: Positive = 2.0
    # Lidar only, a scan at or above refine_below_mps is refined too once the registered motion
    # has stayed that fast for refine_fast_after_s (a vehicle at speed), and kept only when its
    # held-out points prove it better (as refine_evidence). At speed kiss-icp's point-to-point
    # match drifts in pitch on sparse rings (bank car05-vlp16, lidar only: 13 deg and 31 m of
    # height in 40 s; stock kiss_icp_pipeline 15 deg), which a plane match against the last
    # keyframes holds. Not with an IMU (its gravity holds the tilt; sim 07's speed), not on a
    # hand-held flick kiss-icp read as a jump (refining those lost plaza-handheld-os0 0.21 ->
    # 0.94 m). None: off. Decided on the bank (docs/bank.md, Decisions, 2026-12-05).
    refine_fast_after_s: NonNegative | None = 1.0
    # The keyframes a scan refined at speed is matched against (None, or fewer than
    # refine_keyframes: refine_keyframes). A car
    # leaves 4 keyframes' clouds behind within metres, and their planes pin its pitch no better
    # than the scan's own; 12 reach further back along the road (bank, lidar only, three draws:
    # car05-vlp16 0.85-0.93 -> 0.31-0.32 m, car08-xt32 0.14-0.15 -> 0.055-0.062 m, car07-os0
    # 0.024-0.032 -> 0.017-0.020 m, car00-hdl64 0.12-0.15 -> 0.16-0.18 m; docs/bank.md,
    # Decisions). Slow scans, the failure watch and a reset's map keep refine_keyframes.
    refine_keyframes_at_speed: Count | None = 12
    # Failure (lidar_slam.frontend.failure): failure_scans registered scans in a row with under
    # failure_min_fitness of their points within failure_inlier_m of the last keyframes' clouds
    # (failure_wide_min_fitness while kiss-icp's adaptive threshold is above failure_sigma_m)
    # reset its local map to those keyframes and its threshold to initial_threshold_m; counted
    # in summary.json (odometry_failures). 0: off. Good runs stay above both bars (>= 0.47);
    # 5 m: a car's threshold (KITTI, sims) stays under 2 m; a hand-held walk without IMU went
    # to 15 m, whose kernel let mediocre fits smear the map and made kiss-icp crawl.
    failure_min_fitness: Fraction = 0.2
    failure_sigma_m: NonNegative = 5.0
    failure_wide_min_fitness: Fraction = 0.5
    failure_inlier_m: Positive = 0.3
    failure_scans: Count = 2


class KeyframeConfig(_Section):
    # "auto": the descriptor radius / 40, in 0.5 m steps, 0.5-2 m (1 m indoors, 2 m outdoors).
    distance_m: Positive | Auto = "auto"
    rotation_deg: Positive = 15.0
    cloud_voxel_m: Positive = 0.5
    # Without an IMU (every scan deskewed at constant velocity) a keyframe that falls due at a
    # flick (its scan's registered pose, or the one before's, missed the constant-velocity
    # prediction by more than this and twice the walk's median miss) is made at the first scan
    # after it within this or that median, at most steady_wait_scans late (frontend.keyframes
    # SteadyWait; docs/bank.md, Decisions, "a keyframe due at a flick waits"). 0 (either): off.
    steady_miss_deg: NonNegative = 1.0
    steady_wait_scans: int = Field(4, ge=0)


class ScanContextConfig(_Section):
    rings: Count = 20
    sectors: Count = 60
    # "auto": 1.5 x the horizontal range within which 99 % of the first scan's points lie,
    # rounded up to 10 m, 20-80 m (an 80 m descriptor puts a whole room in 3-4 rings).
    max_radius_m: Positive | Auto = "auto"
    # Height of the sensor above the ground, for keyframes whose own ground fit fails ("auto":
    # the ground fitted in the first scan, else 2 m).
    sensor_height_m: Positive | Auto = "auto"
    candidates: Count = 10
    # Scan-context distance below which a keyframe is a candidate (verified by ICP). 0.33: the
    # revisit keyframes of sims 07 / s08 that 0.3 missed, with no wrong loop accepted on the
    # four sims or the Ouster loop (docs/design.md, "Loop thresholds").
    threshold: Positive = 0.33
    # A keyframe is not a loop candidate of a newer one until the sensor has travelled
    # exclude_recent_m of path since it ("auto": 0.75 x the descriptor radius) or
    # exclude_recent_s seconds have passed.
    exclude_recent_m: NonNegative | Auto = "auto"
    exclude_recent_s: NonNegative = 60.0
    local_search_sectors: NonNegativeInt = 2
    # Level each cloud on its fitted ground plane before binning (hand-held / tilted sensors); the
    # yaw guess is then about the ground normal. Bins use the fitted sensor height when found.
    level_to_ground: bool = True
    max_tilt_deg: Positive = 30.0


class VerifyConfig(_Section):
    method: Literal["point_to_plane", "gicp"] = "point_to_plane"
    voxel_m: Positive = 0.5
    submap_radius: NonNegativeInt = 2
    # Coarse stage (every yaw hypothesis): clouds at coarse_voxel_m, correspondences up to
    # coarse_correspondence_m then half of it, to pull in the few metres between revisits.
    coarse_voxel_m: Positive = 1.5
    coarse_correspondence_m: Positive = 3.0
    # Hypotheses are ranked (and the margin taken) by coarse fitness: share of coarse query
    # points within coarse_inlier_m of the match after the coarse stage.
    coarse_inlier_m: Positive = 0.5
    # The winner is re-aligned from starts pushed this far sideways (0: off); a different pose
    # found that way competes in the margin like another yaw hypothesis.
    probe_shift_m: NonNegative = 4.0
    # Fine stage at voxel_m.
    max_correspondence_m: Positive = 0.6
    # Query points used (a fixed random subset beyond this; 0 = all) in the coarse / fine stage.
    coarse_max_points: NonNegativeInt = 500
    fine_max_points: NonNegativeInt = 4000
    min_fitness: Fraction = 0.5
    # RMSE of the inliers (so at most inlier_m): a loose guard; ~0.19 m for true loops here.
    max_rmse_m: Positive = 0.25
    # ICP may turn at most this far from the yaw hypothesis it started at (the yaw guess plus a
    # multiple of 90 deg): a guess a few sectors off must still pass, a slide must not.
    max_yaw_disagreement_deg: Positive = 30.0
    try_yaw_offsets: bool = True
    # Fitness = share of query points with a match point within inlier_m after ICP.
    inlier_m: Positive = 0.3
    # The best hypothesis must beat the best *different* converged pose by this much coarse
    # fitness. Measured: wrong poses that passed every other gate had margins up to 0.024, true
    # loops down to 0.048 (Ouster rooms) and 0.058 (straight roads, which 0.12 rejected).
    min_margin: Fraction = 0.04
    max_translation_m: Positive = 10.0
    max_iterations: Count = 20
    # Level both clouds on their ground planes to build the yaw hypotheses about gravity.
    level_to_ground: bool = True
    # The information matrix keeps the shape of the point-to-plane Hessian but is scaled down
    # so that no direction is more certain than these (residuals of neighbouring points correlate).
    info_min_trans_sigma_m: Positive = 0.02
    info_min_rot_sigma_deg: Positive = 0.2


class OdometryInformationConfig(_Section):
    """How sure each keyframe-to-keyframe odometry edge is, from its own data
    (lidar_slam.frontend.edge_information: the point-to-plane Hessian of the keyframe's cloud on
    the previous one, over the measured residual)."""

    # Off: every edge gets backend.odom_rot_sigma_deg / odom_trans_sigma_m.
    enabled: bool = True
    # One residual per cell of this size (m): neighbouring residuals on one surface are not
    # independent.
    cell_m: Positive = 2.0
    max_correspondence_m: Positive = 1.0
    # The residual's RMS is taken as at least this (m): sensor noise and the clouds' 0.5 m voxel
    # centroids leave more than this on any real surface.
    min_residual_m: Positive = 0.01
    # Floors: 1-sigmas added to every edge's measured covariance, so no direction is surer.
    # The rotation floor, swept on the bank lidar only (0.05 / 0.025 deg: NEES in 1..9 on
    # 10-11 / 9-10 of 16 against 11-12 at 0.1; docs/bank.md, Decisions).
    min_trans_sigma_m: Positive = 0.005
    min_rot_sigma_deg: Positive = 0.1
    # Without an IMU every scan is deskewed at constant velocity, and through a flick the pose
    # fitted to that cloud is off where no lidar constraint sees it: when the final solve has no
    # IMU factors each keyframe's position covariance gains (this x miss (rad) x the cloud's
    # median range (m))^2 per axis, miss the largest rotation by which the odometry pose of its
    # scan or the 2 before (at the scans' stamps) missed the constant-velocity prediction
    # (frontend.edge_information.deskew_white). 0: off. Set on the bank (docs/bank.md,
    # Decisions: 0.02 / 0.03 / 0.04 / 0.06).
    deskew_white_scale: NonNegative = 0.03
    # Lidar only: where at least this many scans were refined at speed (odometry.
    # refine_keyframes_at_speed: a drive), the covariances are of the same graph with the
    # rotation floor taken from the run's own data instead of min_rot_sigma_deg: the largest
    # per-axis rms of those scans' rotation corrections (at least refinement_floor_min_deg, a
    # bound for runs whose corrections are all but zero), and a constant rotation bias per
    # metre of refinement_bias_fraction x their mean over their mean motion, per axis, as a
    # consider parameter (backend.refinement_floor). The poses are the solve's with
    # min_rot_sigma_deg. None: off. Set on the bank's car rows (docs/bank.md, Decisions).
    floor_from_refinement_scans: Count | None = 30
    refinement_bias_fraction: NonNegative = 0.1
    refinement_floor_min_deg: NonNegative = 0.02


class BackendConfig(_Section):
    # Odometry edges whose own information cannot be had (an empty keyframe, odom_information
    # off), 1-sigma per keyframe edge.
    odom_rot_sigma_deg: Positive = 0.1
    odom_trans_sigma_m: Positive = 0.05
    odom_information: OdometryInformationConfig = OdometryInformationConfig()
    prior_rot_sigma_deg: Positive = 1e-3
    prior_trans_sigma_m: Positive = 1e-3
    huber_k: Positive = 1.345
    max_iterations: Count = 100
    # Newest keyframes that a loop corrects while the drive goes on (bounded cost per loop);
    # the final full solve corrects every keyframe.
    window_keyframes: Count = 100
    # The live estimate takes in new loops at every update_every_keyframes-th keyframe (a
    # revisit closed keyframe by keyframe adds a loop at each; one window solve takes them all).
    update_every_keyframes: Count = 5
    # Loop kernel of the final full solve: huber (huber_k), or gnc (graduated non-convexity,
    # truncated least squares; odometry edges are known inliers, wrong loops get weight 0).
    # The live (window) solution keeps Huber either way.
    robust: Literal["none", "huber", "gnc"] = "huber"
    # The final solve also starts from a global initialisation (gtsam InitializePose3) and keeps
    # it when it ends at a lower error than the one started at the live estimate.
    global_init: bool = True
    # The odometry edges in the final solve with the IMU (backend.imu_gnss_solve), 1-sigma per
    # keyframe, Huber-robust (huber_k): the pose graph's 5 cm above let the IMU's velocity bend a
    # hand-held walk (300-scan walks: keyframe ATE 0.061 -> 0.078 m; 0.048 with 1 cm), and a
    # scan registered wrongly in a shake is an outlier against the IMU. Rotation 0.1 deg: 0.2
    # or 0.5 leave the gyro bias too free on a drive with a good odometry (synthetic drive in
    # tests/test_backend_inertial.py: ATE 0.07 -> 0.10 m at 0.2), sim 07 the same either way.
    inertial_odom_rot_sigma_deg: Positive = 0.1
    inertial_odom_trans_sigma_m: Positive = 0.01
    # The rotation floor of the measured odometry edges (odom_information) in the solve with the
    # IMU, in place of odom_information.min_rot_sigma_deg: there the odometry variance check
    # loosens the edges wherever their residuals against the IMU say so, so a low floor costs
    # nothing where the registration is worse, and lets a good one hold the gyro bias (the bank,
    # docs/bank.md: ATE median 0.050 -> 0.033 m, car07-os0 0.106 -> 0.073 m). The lidar-only
    # pose graph has no such check and keeps the 0.1 deg.
    inertial_odom_min_rot_sigma_deg: Positive = 0.02
    # The odometry in the solve with the IMU as a drift state (the pose of the odometry's world,
    # a random walk) plus white pose noise, split per run from the odometry edges' residuals
    # (backend.imu_gnss_solve.odometry_white_fractions), instead of a chain of edges whose
    # errors all accumulate: a scan-to-map odometry's error mostly does not, and the chain let
    # the IMU bend it. Bank with the IMU, 15 rows (docs/bank.md, every row there): ATE median /
    # worst 0.022 / 0.117 m with the chain and with the drift state, final worse than 1.05x the
    # odometry on 4 rows -> 1 (car07 1.93 -> 1.02), NEES in 1..9 on 6 -> 12.
    odometry_drift_state: bool = True
    # The odometry's scale error as a consider parameter of the solve with the IMU: a 1-sigma
    # scale error of this fraction, the same on every odometry translation, is added to each
    # keyframe's covariance as the solution's own shift under it (not estimated; None: not
    # added). A scale error keeps its sign from edge to edge, so no edge's variance carries it:
    # car05-vlp16 ends 0.08 % short and its covariance ahead did not grow (NEES 8.5-9.9).
    # Estimated instead (a state with this prior), the scale moved the wrong way on sim 07
    # (ATE 0.054 -> 0.084 m): the IMU cannot tell it. 0.05 %: the IMU-aided odometry's own
    # scale error on the bank is 0.03 % median, 0.10 % RMS (docs/bank.md, Decisions).
    odometry_scale_sigma: Positive | None = 0.0005


class LoopConfig(_Section):
    enabled: bool = True
    # Candidates verified per keyframe query (best descriptor distance first). 2: a third
    # candidate closed no extra loop on sims 07 / s00 / s05 / s08, full 00 or the Ouster loop,
    # and cost 15 % of the verifications (docs/benchmarks/2026-12-02-loop-gates.md).
    max_verify: Count = 2
    # A candidate is verified only where the odometry could have put it: the odometry places
    # the two keyframes at most max_gap_m + max_drift x (path travelled between them) apart.
    # kiss-icp drifts ~1 % of the path; true loops on the sims were at most 12 m / 1.8 % apart,
    # while 97-100 % of the wrong candidates were further (docs/design.md, "Loop thresholds").
    max_gap_m: NonNegative = 20.0
    max_drift: NonNegative = 0.1
    # A verified loop is kept only when the correction it implies (its pose against the
    # odometry's) is one the odometry can have drifted: Mahalanobis distance under the
    # covariance accumulated along the odometry edges since the match keyframe (each edge's own
    # information, lidar_slam.frontend.edge_information) plus the loop's own, against the
    # chi-square(6) quantile of this tail probability (1e-6: 38.3). 0 turns the gate off. The
    # same test keeps the verification's submaps from crossing an odometry edge that the two
    # keyframes' own clouds contradict (a jump: LoopDetector.edge_consistent).
    drift_gate_p: Fraction = 1e-6
    # With an IMU, a loop is also refused when the up direction it implies for the query
    # keyframe (the match's, as the IMU saw it, turned by the loop) is further than this from
    # the one the IMU saw at the query: gravity fixes roll and pitch whatever the drift. True
    # loops of the bank: at most 1.8 deg (hand-held office), 1.3 (drone in a warehouse). 0: off.
    max_tilt_disagreement_deg: NonNegative = 3.0
    # Detection runs in a worker process (or thread; "inline": in the main flow, for
    # debugging); the result of keyframe k is applied to the graph when keyframe
    # k + collect_lag_keyframes is made (or at the end), whatever the worker's speed, so runs
    # are deterministic. The worker process only gets the CPU time the odometry leaves and
    # falls behind in dense revisits; a long lag lets it catch up later instead of the
    # odometry waiting for it (the live estimate takes loops in that much later; the final
    # poses come from the complete graph either way).
    worker: Literal["process", "thread", "inline"] = "process"
    collect_lag_keyframes: NonNegativeInt = 200
    scan_context: ScanContextConfig = ScanContextConfig()
    verify: VerifyConfig = VerifyConfig()


class MapConfig(_Section):
    # map.ply is the keyframe clouds (one point per keyframes.cloud_voxel_m voxel) merged at
    # this voxel: it can thin them, not make the map denser than they are
    voxel_size_m: Positive = 0.2
    max_range_m: Positive = 60.0


class LocalizeConfig(_Section):
    """`lidar-slam localize`: tracking gates against the fixed map, and relocalisation."""

    # Tracking: point-to-plane ICP of the scan (one point per source_voxel_m) against the map's
    # clouds (one point per map_voxel_m), correspondences up to max_correspondence_m (first up
    # to coarse_correspondence_m while the motion is not yet measured).
    map_voxel_m: Positive = 0.5
    # The target: the clouds of the keyframe nearest to the prediction, of submap_behind
    # keyframes before it and submap_ahead after it (what the map run had mapped when it passed).
    submap_behind: NonNegativeInt = 3
    submap_ahead: NonNegativeInt = 1
    source_voxel_m: Positive = 1.0
    max_correspondence_m: Positive = 1.0
    coarse_correspondence_m: Positive = 3.0
    # ICP stops when it converges; the cap binds on a pull-in from far off (a 28 deg miss of the
    # prediction indoors was 15 deg short after 20 iterations, converged after 50).
    max_iterations: Count = 50
    # A tracked frame is kept when the share of its registration points above the ground
    # (structure, not road: the road matches anywhere along it) that lie within inlier_m of a
    # map point reaches min_fitness...
    inlier_m: Positive = 0.5
    min_fitness: Fraction = 0.5
    structure_min_height_m: NonNegative = 0.5
    # ...and the registration moved the motion model's prediction by at most this much, or by
    # correction_margin x the largest miss of that prediction along the map run's own poses
    # where that is more (a 2 Hz hand-held indoor set misses by up to 0.5 m / 29 deg; a car at
    # 10 Hz by 0.06 m / 0.8 deg). Where the map run's motion is not predictable within the
    # gates, every frame is first pulled in with coarse_correspondence_m.
    max_correction_m: Positive = 1.0
    max_correction_deg: Positive = 5.0
    correction_margin: Positive = 1.5
    # After this many frames without a good registration, stop predicting and only relocalise.
    max_predicted_frames: NonNegativeInt = 3
    # Scan Context candidates verified (loop.verify gates) per relocalisation attempt.
    max_verify: Count = 3


class CheckpointConfig(_Section):
    # A checkpoint (for `run --resume`) every this many keyframes; 0 = none.
    every_keyframes: NonNegativeInt = 100


class ImuConfig(_Section):
    """The IMU (imu.csv beside the scans or a sensor_msgs/Imu topic; lidar_slam.io.imu_gnss)."""

    enabled: bool = True
    # The IMU's pose in the lidar frame: 6 numbers x, y, z (m), roll, pitch, yaw (deg; extrinsic
    # x-y-z, i.e. R = Rz(yaw) Ry(pitch) Rx(roll)), or 16 numbers, the 4x4 matrix row by row; or
    # "auto": its rotation found from the data (lidar_slam.imu_calibration; the translation 0).
    # Not set: the input's own calibration (a dataset's, an Ouster's metadata), else "auto".
    T_lidar_imu: list[float] | Auto = [0.0, 0.0, 0.0, 0.0, 0.0, 0.0]
    # Added to every IMU stamp to put it on the clock of the scan stamps (s); or "auto": found
    # from the data. Not set: 0 for an input whose own streams share a clock (a dataset, a
    # pcap), else "auto".
    time_offset_s: float | Auto = 0.0
    # The rotation of T_lidar_imu is refined in the back-end's final solve, with a prior of this
    # sigma (deg, per axis) about it; None: used as given. lidar_slam.imu_calibration sets it when
    # it found the rotation from the data (its few tenths of a degree cost the final solve up to
    # 40 % of ATE: docs/benchmarks/2026-12-04b-imu-calibration.md).
    T_lidar_imu_sigma_deg: Positive | None = None
    # Continuous-time noise of a BMI088-class MEMS unit (BST-BMI088-DS001): gyro 0.014
    # deg/s/sqrt(Hz) = 2.4e-4 rad/s/sqrt(Hz) (the datasheet's typical value as Bosch's forum
    # quotes it); accelerometer 175 ug/sqrt(Hz) = 1.7e-3 m/s^2/sqrt(Hz), UNVERIFIED (only
    # third-party code quotes it; the datasheet's table was not found). No bias random walk in
    # the datasheet: these are the usual order for such units (calibrate, e.g. Allan variance).
    gyro_noise_density: Positive = 2.4e-4  # rad/s/sqrt(Hz)
    accel_noise_density: Positive = 1.7e-3  # m/s^2/sqrt(Hz)
    gyro_bias_random_walk: Positive = 2.0e-5  # rad/s^2/sqrt(Hz)
    accel_bias_random_walk: Positive = 3.0e-4  # m/s^3/sqrt(Hz)

    @model_validator(mode="after")
    def _extrinsic_is_rigid(self) -> ImuConfig:
        # Six finite numbers are always a rigid transform: not built here.
        if self.T_lidar_imu == "auto":
            return self
        if len(self.T_lidar_imu) == 6:
            if not np.all(np.isfinite(self.T_lidar_imu)):
                raise ValueError("T_lidar_imu must be finite (x y z m, roll pitch yaw deg)")
            if np.abs(self.T_lidar_imu[3:]).max() > 360.0:  # 1e300 deg: an internal error
                raise ValueError("T_lidar_imu's roll, pitch and yaw are degrees within "
                                 "-360..360 (x y z m, roll pitch yaw deg)")
            return self
        self.T_lidar_imu_matrix()
        return self

    def T_lidar_imu_matrix(self) -> np.ndarray:  # noqa: N802 (frame-named, as the project)
        """T_lidar_imu as a 4x4 float64 array (maps IMU-frame points into the lidar frame);
        "auto" is resolved by the run driver (lidar_slam.imu_calibration) before any use."""
        if self.T_lidar_imu == "auto":
            raise ValueError("imu.T_lidar_imu is 'auto': found from the data by the run driver "
                             "(lidar_slam.imu_calibration.resolve) before it is used")
        values = np.asarray(self.T_lidar_imu, dtype=np.float64)
        if len(values) == 6:  # extrinsic x-y-z: R = Rz(yaw) Ry(pitch) Rx(roll)
            from lidar_slam.geometry import matrix_from_rotvec  # NumPy: no scipy.spatial (28 MB)

            roll, pitch, yaw = np.radians(values[3:])
            T = np.eye(4)
            T[:3, :3] = (matrix_from_rotvec([0.0, 0.0, yaw]) @ matrix_from_rotvec([0.0, pitch, 0.0])
                         @ matrix_from_rotvec([roll, 0.0, 0.0]))
            T[:3, 3] = values[:3]
            return T
        if len(values) != 16:
            raise ValueError(f"T_lidar_imu must have 6 numbers (x y z m, roll pitch yaw deg) "
                             f"or 16 (a 4x4 matrix row by row), not {len(values)}")
        T = values.reshape(4, 4)
        R = T[:3, :3]
        if (not np.allclose(T[3], [0, 0, 0, 1]) or not np.allclose(R.T @ R, np.eye(3), atol=1e-6)
                or np.linalg.det(R) <= 0):
            raise ValueError("T_lidar_imu is not a rigid transform (its rotation must be "
                             "orthonormal with determinant +1, its last row 0 0 0 1)")
        T = T.copy()
        if np.linalg.norm(R @ R.T - np.eye(3)) > 1e-12:
            # Printed to a few decimals, a rotation is orthonormal to ~1e-9: the IMU front-end
            # takes a prediction off by more than 1e-11 for a diverged one (Sophus aborts at
            # 1e-10). The nearest rotation (SVD), which leaves an exact one as it is.
            U, _, Vt = np.linalg.svd(R)
            T[:3, :3] = U @ Vt
        return T


class GnssConfig(_Section):
    """The GNSS receiver (gnss.csv beside the scans or a sensor_msgs/NavSatFix topic)."""

    enabled: bool = True
    # The antenna's position in the lidar frame (m): the fixes are of the antenna, not the lidar.
    lever_arm_m: list[float] = [0.0, 0.0, 0.0]
    # Added to every GNSS stamp to put it on the clock of the scan stamps (s).
    time_offset_s: float = 0.0

    @model_validator(mode="after")
    def _lever_arm_is_a_vector(self) -> GnssConfig:
        if len(self.lever_arm_m) != 3:
            raise ValueError(f"lever_arm_m must have 3 numbers (x y z m), not "
                             f"{len(self.lever_arm_m)}")
        return self


class SlamConfig(_Section):
    data: DataConfig = DataConfig()
    odometry: OdometryConfig = OdometryConfig()
    keyframes: KeyframeConfig = KeyframeConfig()
    loop: LoopConfig = LoopConfig()
    backend: BackendConfig = BackendConfig()
    map: MapConfig = MapConfig()
    checkpoint: CheckpointConfig = CheckpointConfig()
    localize: LocalizeConfig = LocalizeConfig()
    imu: ImuConfig = ImuConfig()
    gnss: GnssConfig = GnssConfig()

    def voxel_size_m(self) -> float:
        """Effective odometry voxel size in metres."""
        if self.odometry.voxel_size_m is not None:
            return self.odometry.voxel_size_m
        return self.data.max_range_m / 100.0


def _merge(base: dict, overlay: dict) -> dict:
    out = dict(base)
    for key, value in overlay.items():
        if isinstance(value, dict) and isinstance(out.get(key), dict):
            out[key] = _merge(out[key], value)
        else:
            out[key] = value
    return out


def load_config(path: str | Path | None = None, overrides: dict | None = None) -> SlamConfig:
    """Defaults, overlaid by a YAML file, overlaid by a dict of overrides."""
    data = _read_overlay(Path(path)) if path is not None else {}
    data = _merge(data, overrides or {})
    try:
        return SlamConfig.model_validate(data)
    except ValidationError as exc:
        errors = exc.errors()
        err = errors[0]
        loc = _key_path(err["loc"])
        where = ".".join(str(x) for x in loc) or "(top level)"
        shown = repr(err["input"])
        got = _did_you_mean(err["loc"]) if err["type"] == "extra_forbidden" else \
            f" (got {shown if len(shown) <= 60 else shown[:57] + '...'})"
        # A value of a union (a number or "auto"): what each of its kinds wanted, in one line.
        said = list(dict.fromkeys(_plain(e["msg"]) for e in errors if _key_path(e["loc"]) == loc))
        message = " ".join(f"{where}: {'; or '.join(said)}{got}".split())
        if err["type"] == "value_error":  # a section's own check: it names its key
            text = err["msg"].removeprefix("Value error, ")
            message = text if not loc else f"{where}.{text}"
        raise ConfigError(f"{path or 'config'}: {message}") from None


def _key_path(loc: tuple) -> tuple:
    """The config keys of a pydantic error location, without the tags pydantic adds for the
    kinds of a union ('constrained-float', 'bool', "literal['auto']")."""
    out, model = [], SlamConfig
    for part in loc:
        is_model = isinstance(model, type) and issubclass(model, BaseModel)
        if not is_model:
            if isinstance(part, int):  # an item of a list
                out.append(part)
                continue
            break  # a union's tag
        out.append(part)  # a key of the section, or one it does not have
        if part not in model.model_fields:
            break
        model = model.model_fields[part].annotation
    return tuple(out)


def _plain(msg: str) -> str:
    """pydantic's 'a valid dictionary or instance of KeyframeConfig' as a user reads it."""
    return re.sub(r"a valid dictionary or instance of \w+", "a mapping of settings", msg)


def _section_keys(model: type[BaseModel], prefix: str = "") -> dict[str, list[str]]:
    """Every key of model and of the sections nested in it, by name: its dotted paths."""
    keys: dict[str, list[str]] = {}
    for name, field in model.model_fields.items():
        keys.setdefault(name, []).append(prefix + name)
        sub = field.annotation
        if isinstance(sub, type) and issubclass(sub, BaseModel):
            for key, paths in _section_keys(sub, f"{prefix}{name}.").items():
                keys.setdefault(key, []).extend(paths)
    return keys


def _did_you_mean(loc: tuple) -> str:
    """For a key the config does not have: the closest key of its section (difflib), or the
    section that has a key of that name; "" when neither."""
    import difflib

    model: type[BaseModel] = SlamConfig
    for part in loc[:-1]:
        field = model.model_fields.get(str(part))
        sub = field.annotation if field is not None else None
        if not (isinstance(sub, type) and issubclass(sub, BaseModel)):
            return ""
        model = sub
    key = str(loc[-1])
    close = difflib.get_close_matches(key, list(model.model_fields), n=1, cutoff=0.6)
    if close:
        return f" (did you mean {'.'.join([*map(str, loc[:-1]), close[0]])}?)"
    elsewhere = _section_keys(SlamConfig).get(key)
    return f" (did you mean {' or '.join(elsewhere[:3])}?)" if elsewhere else ""


class _DuplicateKey(ValueError):
    pass


class _UniqueKeyLoader(yaml.SafeLoader):
    """PyYAML's safe loader, but a key given twice in one mapping is an error: the last one
    would win silently (two `imu:` sections: the first one's settings lost)."""

    def construct_mapping(self, node, deep=False):
        seen: dict = {}
        for key_node, _ in node.value:
            key = self.construct_object(key_node, deep=deep)
            try:
                first = seen.setdefault(key, key_node.start_mark.line + 1)
            except TypeError:  # an unhashable key: the base class says so
                break
            if first != key_node.start_mark.line + 1:
                raise _DuplicateKey(f"line {key_node.start_mark.line + 1}: key {key!r} given "
                                    f"twice (first on line {first})")
        return super().construct_mapping(node, deep=deep)


def _read_overlay(p: Path) -> dict:
    """The mapping of sections in a YAML file; an empty file (or only comments) is the defaults,
    said in a warning (a config that was meant to say something and says nothing)."""
    if not p.is_file():
        raise InputError(p, "config file does not exist")
    try:
        data = yaml.load(p.read_text(encoding="utf-8"), Loader=_UniqueKeyLoader)  # noqa: S506
    except UnicodeDecodeError as exc:
        raise InputError(p, f"not a text file (byte {exc.start} is not UTF-8)") from None
    except OSError as exc:
        raise InputError(p, f"cannot read the config file ({exc.strerror or exc})") from None
    except _DuplicateKey as exc:
        raise InputError(p, str(exc)) from None
    except yaml.YAMLError as exc:
        first = " ".join(str(exc).splitlines()[0].split())
        mark = getattr(exc, "problem_mark", None)
        where = f"line {mark.line + 1}: " if mark is not None else ""
        raise InputError(p, f"{where}not valid YAML ({first})") from None
    except (ValueError, RecursionError) as exc:  # e.g. a date that does not exist: 2023-02-30
        raise InputError(p, f"not valid YAML ({' '.join(str(exc).split())[:120]})") from None
    if data is None:
        log.warning("%s: config file is empty; using the defaults", p)
        return {}
    if not isinstance(data, dict):
        raise InputError(p, f"config must be a mapping of sections, not a "
                            f"{type(data).__name__}")
    return data


def dump_config(config: SlamConfig, path: str | Path) -> None:
    """Write the effective config as YAML."""
    write_text_atomic(path, yaml.safe_dump(config.model_dump(), sort_keys=False))


def overlay_config(base: SlamConfig, path: str | Path) -> SlamConfig:
    """base overlaid by the YAML file at path (only the keys the file sets)."""
    overlay = load_config(path).model_dump(exclude_unset=True)
    try:
        return SlamConfig.model_validate(_merge(base.model_dump(), overlay))
    except ValidationError as exc:  # load_config validated the file alone; this cannot fail
        raise ConfigError(f"{path}: {exc.errors()[0]['msg']}") from exc
