"""The stateful BEVO engine that ``bevo_node`` and ``bevo run`` (bevo_ros.pipeline) share.

Feed it IMU and image messages in any interleaving; it keeps the one ordering rule that makes
online and offline results identical: an image is processed once every IMU sample with a stamp
<= the image stamp has been fused (a later IMU sample arrives), or when ``flush()`` is called
(the node's configurable wait; the end of a bag). An image's ``tag`` (anything the caller needs
back, e.g. the node's header stamp and arrival time) comes back on its :class:`OdometryStep`;
what the engine drops or rejects is counted (:class:`Counters`) and reported as
:class:`EngineEvent` s the caller reads with :meth:`BevoOdometry.take_events`.
"""
from __future__ import annotations

import bisect
import copy
import math
from collections import deque
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from .compiled import EngineKernels
from .dukf import DUKF, steady_state_variance
from .frame_clock import FrameClock
from .geometry import BevSpec, CameraModel, mounting_for_extrinsics
from .gyro_bias import GyroBiasFilter
from .motion import pitch_change_shift, pitch_scale_sensitivity, registration_shift_floats, roll_yaw_sensitivity
from .phase_correlation import DpcConfig, InvalidBevError, MaskWeight
from .trajectory import PlanarTrajectory, check_pose
from .rate_integration import GYRO_SAMPLING, interval_rate
from .road_tilt import RoadTiltFilter
from .standstill import CHECK_BELOW as STANDSTILL_CHECK_BELOW, StandstillDetector
from .start_tilt import StartHold, TiltMeasurement, mean_offset
from .travel_direction import MIN_PAIRS as TILT_MIN_PAIRS, direction_of_pairs, mounting_pitch_from_travel
from .validation import ImplausibleImuError, ImuLimits, imu_problem
from .vehicle_dynamics import GRAVITY, compensate_floats, suspension_attitude
from .vehicle_filter import VehicleFilter, VehicleNoise, forget_accel_bias, forget_speed, initial_vehicle_state

MODES = ("fused", "paper")
ACCEL_CORRELATION_TIME = 0.25  # s, how long a car's unexplained forward acceleration stays the same
# s: how long an error of the motion filter's acceleration lasts (a frame-rate estimate smoothed over
# about ten frames), counted once per such time when the DUKF subtracts it (fused item 17). Measured
# on the real-IMU clips (5 s / 16 s drift): 0.25 s 2.03 / 1.51 %, 1 s 1.99 / 1.49 %, 4 s 1.98 / 1.50 %.
ACCEL_ESTIMATE_CORRELATION_TIME = 1.0
# The pitch-change correction counts the DUKF's pitch change between two frames as the car's own
# only while the filter's accelerometer updates moved its pitch by less than this rate times the
# frame interval: a filter still converging from its start (or, with a 10 Hz IMU, pulled hard by an
# acceleration it cannot tell from tilt) changes its pitch without the car (0.1 deg, the gate over
# a 10 Hz pair, reads as 14 cm on KITTI). A rate, so that a faster camera does not spread a start
# over pairs that each pass.
ACCEL_PULL_RATE_GATE = math.radians(1.0)  # rad/s
# Nor in a turn while the DUKF's roll is unconverged: a roll error e makes the gyro's yaw rate wz
# move the gravity pitch by -wz e (Euler kinematics), a pitch change of neither the car nor the
# road. The correction is off over a pair whose yaw rate times sqrt(the DUKF's roll variance less
# its steady state) exceeds this rate. Found on real drive 0018 cold at frame 102: a braking
# start left the DUKF 2.5 deg off, a 32 deg/s corner rotated that into roll and back into a 1 deg/s
# pitch drift, which the correction took off the forward motion (+0.1..+0.2 m of 0.37 m per pair,
# scale -19.3 -> -8.9 % over those 5 s with this gate). Real-IMU clips: 94 5 s cuts 2.65 -> 2.59 % (max 16.5 ->
# 8.1), 59 16 s clips 1.68 -> 1.65 % (per frame 3.96 -> 3.85 cm), with traffic 2.47 -> 2.43 %; the
# 10 Hz presets' mean and the KITTI sample unchanged. 1 deg/s changed nothing, 0.3 deg/s took the presets
# 6.09 / 2.06 -> 6.21 / 2.23 %.
TURN_ROLL_RATE_GATE = math.radians(0.5)  # rad/s
# s: how long the suspension's input (_fuse_imu) leaves out the DUKF's accelerometer updates that
# its excess variance marks as unconverged (an acceleration read as tilt). Kept out for good, they
# also held out the corrections: the DUKF's accelerometer variance grows with that input, so a
# biased input kept the DUKF from converging (`make demo`'s 10 s held-out start at 100 Hz: 3.3 ->
# 6.1 cm per frame, 2.6 -> 4.8 % drift). With 2 s, against the DUKF's pitch as it is: the 59
# real-IMU 16 s clips 1.73 -> 1.68 % drift, 4.06 -> 3.96 cm per frame (BEV road pitch error 0.115 ->
# 0.108 deg), their 94 5 s cuts 2.92 -> 2.65 %, the KITTI sample 5.36 -> 5.24 cm and 1.88 -> 1.73 %,
# the 10 Hz presets 6.16 / 2.08 -> 6.09 / 2.06 %, the demo's start 3.32 -> 3.39 cm, traffic clips
# 2.46 -> 2.49 % (5 s: the sample 1.67 %, the demo 3.49 cm).
KEPT_OUT_MEMORY = 2.0
# s: the inertial speed input (VehicleNoise.imu_accel_density, fused item 16) removes gravity from
# the forward accelerometer at the DUKF's pitch less its accelerometer updates of about this long:
# the gyro's pitch since the (re)start, brought to the DUKF's level only this slowly. The DUKF's
# own pitch carries every acceleration it misreads as tilt and its convergence from the start,
# each an error g x pull in the acceleration that changes within seconds, which the motion
# filter's bias state beta (a slow walk) cannot follow; the gyro's pitch is off by a constant (the
# start's error) that beta takes. The memory bounds a gyro bias's ramp (0.11 deg/s: 3.3 deg, a
# constant again). Measured 2026-12-04 with density 1.0 (and the per-frame sum of the samples that
# _inertial_accel replaced), the DUKF's pitch -> this: the 94 real-IMU 5 s cuts 2.54 -> 2.40 %
# drift (3.65 -> 3.54 cm per frame), the 59 16 s clips 1.73 -> 1.67 %, the 10 Hz presets 4.84 /
# 1.72 -> 4.76 / 1.66 %, the KITTI sample 4.50 -> 4.45 cm (1.27 -> 1.28 %). 10 s: 16 s clips
# 1.70 %, presets 1.68 %; without the memory (the gyro's pitch for good) 1.65 / 1.64 %, but
# unbounded under a gyro bias.
INERTIAL_PULL_MEMORY = 30.0
# m: a frame's measurement error the translation's peak prior allows for besides the filter's
# prediction (the correlation's per-frame error on real roads is ~5 cm: twice that).
PEAK_PRIOR_MEASUREMENT_STD = 0.1
# m: a forward prediction wider than this says nothing about which peak is the road's. 0.5 m turned
# away the prediction after a cold start's first pair behind a car (that pair's variance holds the
# spread of its two peaks, the road's and the car's: 0.56 m std at 4.7 m/s on real drive 0027 with
# traffic, 0.064 m without), and the second pair took the car's peak at ~0: the 26 real-IMU traffic
# clips' pairs 2-5 read 10.9 / 10.7 / 10.1 / 8.8 cm RMS, 5.6 / 5.1 / 5.0 / 5.5 cm with 1 m (no other
# clip set changed).
PEAK_PRIOR_MAX_STD = 1.0
# The correlation peaks at least this share of the highest compete for the prior (a second motion,
# such as the car ahead); the road's own side peaks stay below ~0.3 of its main one.
PEAK_RATIO = 0.5
# The direction of travel (fused mode, ``direction_lock``): the correlation's peak is taken among
# forward (or, after a stop, reverse) shifts to this tolerance (m: the noise of a reading at rest),
# and a direction is taken once the motion filter's speed passes DIRECTION_SPEED (m/s) after a stop.
DIRECTION_TOLERANCE = 0.1
DIRECTION_SPEED = 1.0
# m: the images' small flow (core/standstill, run when the correlation reads a near stop) says the
# car moved at least this much more than the correlation's peak: that peak is something moving
# with the car (the car ahead at our speed), and the filter's near-zero speed is wrong.
MOVING_MARGIN = 0.05

# Fused mode, at a standstill the images confirm: the gyro's pitch and roll rates are their biases
# (as the yaw's is; a zero-rotation update). Their estimate is the rest intervals' mean rate, older
# rest time counting as at most REST_BIAS_MEMORY seconds (a MEMS bias walks: the next stop's mean
# takes over), shrunk towards zero as if REST_BIAS_PRIOR seconds at zero came first (a short stop
# moves it little). Only rest REST_BIAS_SETTLE seconds after the stop began counts: a car rocks back
# on its suspension as it stops (real drive 0018 @ 2240, test_a_stop_rocking_on_its_suspension_gives_
# no_gyro_bias: 0.3 s of that read as the bias ran the DUKF's pitch off, the BEVs moved, the
# standstill was lost and the stop crept 9.9 m). A rest interval reading more than REST_BIAS_MAX
# (rad/s) is no bias but motion the images missed, and is left out. The DUKF then predicts with the
# rates less the estimate: before this, the 10 Hz traffic_light preset's DUKF pitch ran 3 deg off
# over its 15 s stop (MEMS bias 0.1-0.2 deg/s), read as tilt after the pull-away. With the bias state
# between stops (filter.gyro_bias_std > 0, fused item 18, core/gyro_bias) a stop's mean instead weighs
# against its estimate by their variances, the stop counting as its span against REST_BIAS_PRIOR
# seconds of the prior, the memory the bias's walk.
REST_BIAS_MEMORY = 30.0  # s
REST_BIAS_PRIOR = 2.0  # s
REST_BIAS_SETTLE = 1.0  # s
REST_BIAS_MAX = math.radians(1.0)  # rad/s
Z_VARIANCE = 1e6  # z is held constant: say so with a huge variance rather than a false certainty
_PLANAR = np.ix_([0, 1, 5], [0, 1, 5])  # (x, y, yaw) in a 6x6 ROS covariance


class InvalidInputError(ValueError):
    """An input the engine refuses before using it (the caller drops it, counted); any other
    exception out of the engine is a bug, not bad input."""


# m/s: an outside speed beyond this is no car's (add_speed refuses it; 540 km/h)
MAX_SPEED = 150.0
# A frame's forward motion past this share of the BEV's forward extent (``BevSpec.extent``)
# nears the correlation's reach: two consecutive BEVs share only the rest of the road, and from ~42 %
# a cold start locks onto a wrong peak (46 m/s at 10 Hz with the default 10 m BEV read 69 % short, its
# covariance not saying so; README, Limitations: "Top speed"). Counted (``beyond_reach``) and said in
# /diagnostics: 40 m/s at 10 Hz with the default BEV.
REACH_SHARE = 0.4
# passes of the start's camera tilt (filter.tilt_from_images) that take the suspension's pitch over the held
# pairs out, each at the previous one's tilt (_settle_tilt): rendered presets, params 1 deg off, KITTI camera
START_TILT_PASSES = 1
# what a caller may set on an engine after building it (tools, the node's live parameters): the start tilt's
# pass (_start_body_pitch) takes them from the engine, not its constructor's arguments
_LIVE_SETTINGS = ("pitch_change_correction", "direction_lock", "min_frame_interval", "imu_time_offset",
                  "suspension_gradients", "max_speed_age", "turn_compensation", "max_imu_gap", "initial_attitude_std",
                  "road_tilt_time_constant", "dpc", "imu_limits", "max_pending_images", "gyro_sampling")
# A start's first this many held frame pairs all standing still (core/start_tilt): their frames are run as they
# came (at the configured tilt: a standing car's frames move nothing whatever the tilt) and the hold goes on
# from the next; a car waiting longer than tilt_hold_frames at its start still has its tilt measured
STANDING_RELEASE_PAIRS = 20
START_TILT_BODY_DEADBAND = math.radians(0.05)  # rad: the suspension model's pitch at a steady speed (_start_body_pitch)


class OutOfOrderError(InvalidInputError):
    """A message's stamp is not after the previous one of its kind."""

    def __init__(self, kind: str, stamp: float, last: float):
        super().__init__(f"{kind} stamp {stamp:.9f} is not after the previous {kind} stamp {last:.9f}")
        self.kind, self.stamp, self.last = kind, stamp, last

    @property
    def jump(self) -> float:
        return self.last - self.stamp


@dataclass
class OdometryStep:
    """The result for one image (ROS order for 6x6 covariances: x, y, z, roll, pitch, yaw)."""

    stamp: float
    motion: np.ndarray  # (3,) dx, dy, dyaw since the previous frame, base frame of that frame
    dt: float  # seconds since the previous frame (0 for the first)
    position: np.ndarray  # (3,) x, y, z in odom
    rpy: np.ndarray  # (3,) roll, pitch, yaw in odom (roll/pitch gravity-referenced from the DUKF)
    pose_covariance: np.ndarray  # (6, 6)
    twist_linear: np.ndarray  # (3,) base-frame velocity, m/s
    twist_angular: np.ndarray  # (3,) base-frame rates, rad/s
    twist_covariance: np.ndarray  # (6, 6)
    pitch_roll_road: np.ndarray  # (2,) attitude relative to the road used for the BEV
    bev: np.ndarray  # (S, S) float32 in [0, 1]
    bev_mask: np.ndarray  # (S, S) float32
    peak_quality: float  # correlation peak quality in [0, 1]; nan for the first frame
    first: bool = False
    correlation: np.ndarray | None = None  # (S, S) translation correlation (the heat-map), None first
    measured_motion: np.ndarray | None = None  # (3,) the correlation's own (dx, dy, dyaw); None first
    accepted: tuple[bool, bool] = (True, True)  # fused mode: (translation, rotation) measurement used
    speed: float = float("nan")  # fused mode: the motion filter's forward speed, m/s
    # fused mode: VehicleFilter.step's arguments this frame and the resets before it (training replays them)
    filter_inputs: dict | None = None
    tag: Any = None  # the caller's tag given to add_image with this image
    pitch_shift: float = 0.0  # fused: forward shift (m) taken off the correlation by the pitch-change correction
    standstill: bool = False  # fused: the images say the vehicle stood still since the previous frame
    direction_of_travel: str = "forward"  # fused: after this frame (BevoOdometry.direction_of_travel)


@dataclass(frozen=True)
class EngineEvent:
    """One thing the engine counted (``kind`` is the :class:`Counters` field it incremented):
    a dropped image (``dropped_*``, with the image's ``tag``), an IMU gap (``imu_gaps``, at the
    IMU stamp) or a frame whose measurement the motion filter rejected (``rejected_*``)."""

    kind: str
    stamp: float
    tag: Any = None


@dataclass
class Counters:
    imu: int = 0
    images: int = 0
    frames_out: int = 0
    imu_gaps: int = 0
    dropped_no_imu: int = 0
    dropped_pending_overflow: int = 0
    dropped_invalid_bev: int = 0  # the attitude put the BEV's ground patch out of the image
    resets: int = 0
    rejected_textureless: int = 0  # fused: a frame whose correlation carries no information
    rejected_translation: int = 0  # fused: the translation failed the Mahalanobis gate
    rejected_rotation: int = 0  # fused: the image rotation disagreed with the gyro beyond the gate
    rejected_speed: int = 0  # fused: the outside speed (add_speed) over a frame failed the Mahalanobis gate
    standstill: int = 0  # fused: frames at rest (zero motion, the gyro's biases observed)
    rest_bias_skipped: int = 0  # fused: rest intervals whose pitch/roll rates were too large for a gyro bias
    gated_peak: int = 0  # fused: the highest peak was off the prediction or the direction of travel, the road's taken
    pitch_correction_off: int = 0  # fused: pairs the pitch-change correction left alone (its DUKF pull or turn gate)
    skipped_frame_rate: int = 0  # frames closer than min_frame_interval to the last processed one: not processed
    beyond_reach: int = 0  # frames whose forward motion passed REACH_SHARE of the BEV's forward extent
    dropped_held_invalid: int = 0  # inputs held for the start's tilt that the engine refused when run (camera changed)


def _peak_height(reg) -> float:
    """The translation correlation's peak at the registration's shift: the highest of the 3x3 cells
    around its nearest (the sub-pixel fit may move the shift past half a cell; batch of one)."""
    corr = reg.translation_corr[0]
    S = corr.shape[-1]
    r, c = (int(round(float(v))) for v in reg.shift[0] + S // 2)
    return float(corr.roll((1 - r, 1 - c), dims=(0, 1))[:3, :3].max())


class BevoOdometry:
    """DUKF on every IMU sample, BEV + DPC on every image, SE(2) composition into a 6-DoF pose.

    Args:
        camera: intrinsics, extrinsics (base = IMU frame), camera height.
        spec: the BEV grid.
        dukf: the filter (holds the learned O and Q).
        dpc: phase-correlation settings.
        road_tilt_time_constant: seconds; 0 disables road-tilt separation (gravity-referenced BEV).
        mounting_attitude: static (pitch, roll) of the base relative to the road at rest, rad; added to
            the road-relative attitude when the road-tilt low-pass is on (it removes every
            constant); with it off the gravity-referenced attitude already holds the mounting.
        mounting_extrinsics: the camera's ``T_base_cam (4, 4)`` that ``mounting_attitude`` was
            calibrated with (the configured ``camera.base_T_camera``), or None. With a camera whose
            extrinsics differ (from ``/tf_static``, another day's calibration), the mounting used
            keeps the camera's tilt to the road that the calibration measured
            (:func:`~bevo_ros.core.geometry.mounting_for_extrinsics`); ``mounting_attitude`` is the
            one in use. None: the mounting is the base's, whatever the camera.
        max_imu_gap: longer IMU gaps re-initialise the filter from the accelerometer.
        turn_compensation: remove ``speed x turn rate`` from the accelerometer before the DUKF
            update, with the speed of the latest visual odometry step (see
            :func:`~bevo_ros.core.dukf.remove_turn_acceleration`).
        device: torch device for the vision part.
        max_pending_images: images waiting for IMU beyond this are dropped (counted).
        mode: ``"fused"`` (default): the accelerometer minus the car's own acceleration, the
            suspension's lean kept in the road-relative attitude, yaw from the gyro (its bias
            observed by the images), and a vehicle motion filter with Mahalanobis gates between
            the correlation and the pose (see :mod:`~bevo_ros.core.vehicle_filter`), whose
            prediction also picks the road's correlation peak over another motion in view (the
            car ahead: :meth:`_shift_prior`).
            ``"paper"``: the paper's pipeline (accelerometer = gravity, correlation composed as is).
        vehicle_noise: the motion filter's noise (fused mode).
        suspension_gradients: (pitch, roll) body lean per m/s^2 of forward / lateral
            acceleration, rad/(m/s^2) (fused mode; :func:`~bevo_ros.core.vehicle_dynamics.suspension_attitude`).
        initial_attitude_std: the DUKF's start (fused mode): the mounting attitude with this
            standard deviation (rad), then the first accelerometer sample as a measurement, so an
            accelerometer read in a bend is not locked in.
        pitch_change_correction: fused mode: each frame's forward motion loses the shift that the
            engine's own change of the BEV pitch between its two frames (road-tilt low-pass,
            suspension model) puts into it (:meth:`_pitch_change_shift`).
        min_frame_interval: frames stamped less than this (s) after the last processed one are
            skipped (``counters.skipped_frame_rate``): a camera faster than the 10 Hz the per-frame
            constants were learned at, thinned; 0 processes every frame.
        imu_time_offset: added to every IMU stamp (s): the IMU's samples on the images' clock.
        frame_clock_window: fused mode: the motion filter's frame interval is the mean period over
            this many frames times the whole periods a stamped interval spans, so stamp jitter
            is no speed change (:class:`~bevo_ros.core.frame_clock.FrameClock`); 0: as stamped.
        kernels: ``"eager"`` (default), ``"compiled"`` or ``"auto"``: the vision kernels through
            ``torch.compile`` (:mod:`~bevo_ros.core.compiled`; numbers equal to float32 rounding,
            not bit for bit; the first frames pay the compilation).
        gyro_sampling: fused mode: what a gyro sample is, ``"interval_mean"`` (the mean rate since
            the previous sample: KITTI's OXTS, delta-angle IMUs) or ``"instantaneous"`` (the rate
            at its stamp); it sets how the rates are integrated (:mod:`~bevo_ros.core.rate_integration`).
            Paper mode takes each sample as its interval's rate, as the paper does.
        standstill_max_speed: fused mode: a frame whose correlation reads less than
            :data:`~bevo_ros.core.standstill.CHECK_BELOW` forward is checked for standstill on the
            raw images (:mod:`~bevo_ros.core.standstill`); below this speed (m/s) over the frame
            interval the vehicle is at rest: zero motion, the gyro's biases observed. 0 disables it.
        direction_lock: fused mode: the direction of travel is forward from the start and changes
            only at a standstill the images confirm: the correlation's peak is taken among shifts
            of that direction (:data:`DIRECTION_TOLERANCE`). A car ahead pulling away moves in the
            BEV as the road would if the car reversed; followed, its peak took a creeping car to
            -9 m/s. After a confirmed stop either direction; the first one the motion filter's speed
            passes :data:`DIRECTION_SPEED` in is kept. Reversing without a confirmed stop (the
            images too dark or plain to confirm one, or the standstill check off) is then not
            followed: turn it off where a vehicle reverses so. A signed vehicle speed
            (:meth:`add_speed`) sets the direction itself; an unsigned one takes the direction the
            engine keeps (freed only by a confirmed stop, lock or not): reversing with one needs a
            confirmed stop whatever this setting.
        gyro_bias_std, gyro_bias_walk: fused mode: the pitch and roll gyro's bias prior std (rad/s)
            and random walk (rad/s/sqrt(s)) of the bias state beside the DUKF
            (:mod:`~bevo_ros.core.gyro_bias`); 0: the stops' estimate alone (the engine before it).
        tilt_from_images: with the road-tilt low-pass on, the mounting pitch is measured at the start
            from this many frame pairs' direction of travel (:mod:`~bevo_ros.core.start_tilt`): every
            input is held until then, then run in its order at the measured tilt
            (:attr:`tilt_measurement`); 0: the configured ``mounting_attitude`` as is. Measured once
            per engine: a :meth:`reset` keeps it (before it, a reset forgets the held inputs too).
        tilt_hold_frames: images held at most for it; then the pairs there are decide (at least
            :data:`~bevo_ros.core.travel_direction.MIN_PAIRS`, else the configured tilt is kept).
    """

    imu_limits = ImuLimits()  # plausibility limits of add_imu (build_odometry sets the configured ones)

    def __init__(
        self,
        camera: CameraModel,
        spec: BevSpec,
        dukf: DUKF,
        dpc: DpcConfig | None = None,
        road_tilt_time_constant: float = 1.0,
        mounting_attitude: tuple[float, float] = (0.0, 0.0),
        mounting_extrinsics=None,
        max_imu_gap: float = 0.5,
        turn_compensation: bool = False,
        device: str | torch.device = "cpu",
        max_pending_images: int = 20,
        mode: str = "fused",
        vehicle_noise: VehicleNoise | None = None,
        suspension_gradients: tuple[float, float] = (0.0, 0.0),
        initial_attitude_std: float = math.radians(3.0),
        pitch_change_correction: bool = True,
        frame_clock_window: int = 20,
        kernels: str = "eager",
        gyro_sampling: str = "interval_mean",
        standstill_max_speed: float = 0.1,
        direction_lock: bool = True,
        gyro_bias_std: float = 0.002,
        gyro_bias_walk: float = 2e-4,
        min_frame_interval: float = 0.0,
        imu_time_offset: float = 0.0,
        tilt_from_images: int = 0,
        tilt_hold_frames: int = 150,
    ) -> None:
        # the settings, for the start tilt's first pass (_start_body_pitch): an engine like this one
        self._settings = {k: v for k, v in locals().items() if k not in ("self", "__class__")}
        if mode not in MODES:
            raise ValueError(f"mode must be one of {MODES}, got {mode!r}")
        if gyro_sampling not in GYRO_SAMPLING:
            raise ValueError(f"gyro_sampling must be one of {GYRO_SAMPLING}, got {gyro_sampling!r}")
        self.gyro_sampling = gyro_sampling
        self.mode = mode
        self.kernels = EngineKernels(kernels)  # the vision functions, eager or compiled
        self.vehicle = VehicleFilter(vehicle_noise)
        self.suspension_gradients = (float(suspension_gradients[0]), float(suspension_gradients[1]))
        self.initial_attitude_std = float(initial_attitude_std)
        GyroBiasFilter(gyro_bias_std, gyro_bias_walk, self.initial_attitude_std)  # refuse bad values now
        self.gyro_bias_std, self.gyro_bias_walk = float(gyro_bias_std), float(gyro_bias_walk)
        self.pitch_change_correction = bool(pitch_change_correction)
        self.direction_lock = bool(direction_lock)
        if not (math.isfinite(min_frame_interval) and min_frame_interval >= 0 and math.isfinite(imu_time_offset)):
            raise ValueError(f"min_frame_interval must be >= 0 and imu_time_offset finite, got {min_frame_interval!r}, "
                             f"{imu_time_offset!r}")
        self.min_frame_interval = float(min_frame_interval)  # fast_camera_note says when to set it
        self.imu_time_offset = float(imu_time_offset)
        if tilt_from_images != 0 and not TILT_MIN_PAIRS <= tilt_from_images < tilt_hold_frames:
            raise ValueError(f"tilt_from_images must be 0 or {TILT_MIN_PAIRS} up to tilt_hold_frames - 1 "
                             f"({tilt_hold_frames - 1}), got {tilt_from_images!r}")
        self.tilt_from_images, self.tilt_hold_frames = int(tilt_from_images), int(tilt_hold_frames)
        self.tilt_measurement: TiltMeasurement | None = None  # the start's, once taken
        self._frame_clock = FrameClock(frame_clock_window)
        self.max_speed_age = 0.5  # s: an external speed older than this is not used
        self.device = torch.device(device)
        self.dtype = torch.float32
        self.spec = spec
        self._mounting_calibration = ((float(mounting_attitude[0]), float(mounting_attitude[1])), mounting_extrinsics)
        self.mounting_attitude = self._mounting_calibration[0]
        self._standstill = StandstillDetector(camera, self.mounting_attitude, standstill_max_speed)
        self.set_camera(camera)
        self.dukf = dukf
        self.dpc = dpc or DpcConfig()
        self.road_tilt_time_constant = road_tilt_time_constant
        self.max_imu_gap = max_imu_gap
        self.turn_compensation = turn_compensation
        self.max_pending_images = max_pending_images
        self.counters = Counters()
        # what was counted, for a caller that reports it (the node); bounded for callers that never read it
        self._events: deque[EngineEvent] = deque(maxlen=1000)
        self._body_pitch: list[tuple[float, float]] | None = None  # the start tilt's pass: (stamp, suspension pitch)
        self._trajectory = PlanarTrajectory()  # the pose in odom; set_pose's stamps reach back over its frames
        self.reset()
        self.counters.resets = 0  # count explicit resets only

    # ------------------------------------------------------------------ state
    def reset(self) -> None:
        """Forget everything but the settings (changed settings take effect here): the trajectory
        restarts at identity."""
        # DUKF belief as plain floats, (pitch, roll) and (P00, P01, P11): the per-message path
        # runs DUKF.step_scalar (microseconds); training runs the same math on tensors.
        self._state: tuple[tuple[float, float], tuple[float, float, float]] | None = None
        self._noise = self.dukf.noise_floats()
        self._last_imu: float | None = None
        self._imu_dt = 0.01  # the latest IMU period (s), for the steady-state attitude variance
        self._last_image: float | None = None
        self._road_tilt = RoadTiltFilter(self.road_tilt_time_constant)
        self._mounting = self.mounting_attitude if self._road_tilt.enabled else (0.0, 0.0)
        # (stamp, road-relative (pitch, roll), DUKF belief, gyro yaw integral, DUKF start count,
        # accelerometer pitch pull integrals (reaching the BEV, kept out of it)) per IMU sample: an
        # image is projected with the attitude of the last IMU sample at or before its stamp,
        # however late it arrives.
        self._history: deque[tuple[float, tuple[float, float], tuple, float, int, tuple[float, float]]] = deque(
            maxlen=4000)
        self._pending: list[tuple[float, np.ndarray, Any]] = []  # (stamp, image, tag) waiting for IMU
        self._prev = None  # prepared BEV of the previous frame
        self._weight_cache: tuple = (None, None)  # (dpc, MaskWeight) of the latest BEV mask (_mask_weight)
        self._envelope_cache = None  # ((prev, curr) weight spectra, their overlap envelope)
        self._prev_stamp: float | None = None
        self._speed = 0.0  # forward speed of the latest VO step, m/s
        self._trajectory.reset()  # x, y, yaw in odom and their covariance; z held constant (set_pose moves it)
        self._vstate = initial_vehicle_state()  # fused: [v, a, gyro yaw bias, accel bias], speed unknown
        self._yaw_cum = 0.0  # fused: gyro yaw about the vertical integrated since the start, rad
        self._yaw_rate = None  # its latest rate
        self._prev_yaw_cum = 0.0
        self._imu_restarts = 0  # DUKF (re)starts: the attitude jumps there (kept with each history entry)
        self._start_share = (0.0, 0.0)  # d (pitch, roll) mean / d start of the DUKF since its (re)start
        self._prev_pitch = None  # fused, previous frame: (BEV pitch, DUKF pitch, DUKF start count, pull integrals)
        self._pull_cum = 0.0  # fused: the DUKF's accelerometer updates' pitch changes that reach the BEV, summed, rad
        self._pull_kept_out = 0.0  # fused: the share kept out of the BEV's attitude (_fuse_imu), summed, rad
        self._pitch_kept_out_recent = 0.0  # fused: the same over the last KEPT_OUT_MEMORY (since a restart), rad
        self._frame_clock.reset()
        self._ext_speed = None  # (stamp, VehicleState) from add_speed
        self._speed_log: deque[tuple[float, float, float]] = deque(maxlen=4000)  # add_speed's (stamp, m/s, var)
        self._speed_unsigned = False  # the latest add_speed was a magnitude: its sign is the direction of travel
        self._acc_fx = None  # low-passed forward acceleration from the accelerometer, m/s^2
        self._gyro_prev = None  # fused: the previous IMU sample's rates
        self._gyro_prev2 = None  # fused: the sample before that, (rates, yaw rate about the vertical); its interval is the previous _imu_dt
        # fused: (stamp, integral of the forward acceleration, DUKF start count) per IMU sample, read at
        # the frames' stamps (_inertial_accel) as the gyro's yaw is
        self._inertial_log: deque[tuple[float, float, int]] = deque(maxlen=4000)
        self._inertial_cum = 0.0  # that integral, m/s
        self._pitch_pull_inertial = 0.0  # fused: the DUKF's pitch pulls over INERTIAL_PULL_MEMORY, rad
        self._beta_forgotten = False  # fused: forget_accel_bias since the last frame
        self._accel_has_inertial = False  # fused: the motion filter's last step had the inertial input
        self._direction = 1  # fused: direction of travel, +1 forward, -1 reverse, 0 either (after a stop)
        # fused: the raw gyro's (stamp, x, y) rates, for the rest intervals' mean (REST_BIAS_MEMORY)
        self._gyro_xy: deque[tuple[float, float, float]] = deque(maxlen=4000)
        # fused: the gyro's x (roll) and y (pitch) rate biases, from the stops and between them
        self._gyro_bias = GyroBiasFilter(self.gyro_bias_std, self.gyro_bias_walk, self.initial_attitude_std)
        self._xy_bias_time = REST_BIAS_PRIOR  # the rest time behind them, s (at most REST_BIAS_MEMORY)
        self._rest_since: float | None = None  # fused: the start of the current standstill, s
        self._standstill.reset()
        # the start's camera tilt (start_tilt): the inputs wait in it until the tilt is measured
        # (again after a start that did not measure it: it stood still, or a flush came first)
        measured = self.tilt_measurement is not None and self.tilt_measurement.measured
        if getattr(self, "_hold", None) is not None:
            self._hold.close()  # its pairs no longer wanted
        self.held_until = None  # the latest image held for the start's tilt, once released (None: none)
        self._standing_released = 0  # the start's frames run while it stood still, before the tilt (_release_standing)
        self._standing_imu: list[tuple[str, tuple]] = []  # the IMU inputs released with them (the latest 4000)
        self._hold = (StartHold(self.tilt_from_images, self.tilt_hold_frames)
                      if self.tilt_from_images and not measured and self._road_tilt.enabled else None)
        self.counters.resets += 1

    def set_pose(self, x: float, y: float, yaw: float, z: float = 0.0, covariance=None,
                 stamp: float | None = None) -> str:
        """Put the vehicle at ``(x, y, z, yaw)`` in the odometry frame (m, rad) at ``stamp`` (s; None:
        at the latest frame, or the first one to come), as robot_localization's set_pose: the frames
        after the stamp compose their motions onto it (``core.trajectory``; a stamp after the latest
        frame waits for the frame that reaches it). ``covariance``: ``(3, 3)`` of ``(x, y, yaw)``
        (None: zeros, an exact pose). Only the trajectory moves: the attitude (measured, not set), the
        filters and their biases stay, unlike :meth:`reset`. Returns how it was set
        (:meth:`PlanarTrajectory.set_pose`); raises InvalidInputError for values that are not finite or
        a covariance that is none."""
        try:
            pose, z, cov = check_pose(x, y, yaw, z, covariance)
        except ValueError as exc:
            raise InvalidInputError(str(exc)) from None
        if stamp is not None and not math.isfinite(stamp):
            raise InvalidInputError(f"pose stamp must be finite, got {stamp!r}")
        return self._trajectory.set_pose(pose, z, cov, stamp)

    def set_camera(self, camera: CameraModel) -> None:
        """Replace the camera model (e.g. from the first CameraInfo); keeps the trajectory."""
        self.camera = camera.to(self.device, self.dtype)
        mounting, calibrated_with = self._mounting_calibration
        if calibrated_with is not None:
            started_from = self.mounting_attitude
            self.mounting_attitude = mounting_for_extrinsics(mounting, calibrated_with, camera.T_base_cam)
            self._standstill.attitude = self.mounting_attitude
            if hasattr(self, "_road_tilt"):  # after __init__: reset() sets it from the attitude otherwise
                old = self._mounting
                self._mounting = self.mounting_attitude if self._road_tilt.enabled else (0.0, 0.0)
                dp, dr = self._mounting[0] - old[0], self._mounting[1] - old[1]
                sp = sr = kept = 0.0
                if self._state is not None and self._prev is None:  # before the first frame
                    sp, sr, kept = self._move_dukf_start(self.mounting_attitude[0] - started_from[0],
                                                         self.mounting_attitude[1] - started_from[1])
                if dp or dr or sp or sr or kept:
                    # The attitudes waiting for frames (a node's IMU before /tf_static) move with the mounting,
                    # and the current DUKF start's states and kept-out pulls with the start's move.
                    epoch = self._imu_restarts

                    def moved(entry: tuple) -> tuple:
                        t, road, state, yaw, e, pull = entry
                        if e == epoch:
                            state, pull = ((state[0][0] + sp, state[0][1] + sr), state[1]), (pull[0], pull[1] - kept)
                        return t, (road[0] + dp, road[1] + dr), state, yaw, e, pull

                    self._history = deque(map(moved, self._history), maxlen=self._history.maxlen)
                    if self._prev_pitch is not None:  # and so does the last frame's: the camera's tilt did not change
                        self._prev_pitch = (self._prev_pitch[0] + dp, *self._prev_pitch[1:])
        self._scale_per_pitch = pitch_scale_sensitivity(self.spec, float(camera.T_base_cam[0, 3]), camera.mount_height)
        self._shift_per_pitch_change = pitch_change_shift(self.spec, float(camera.T_base_cam[0, 3]), camera.mount_height)
        self._yaw_per_roll = roll_yaw_sensitivity(camera.mount_height)
        self._standstill.set_camera(self.camera)

    def _move_dukf_start(self, dp: float, dr: float) -> tuple[float, float, float]:
        """Before the first frame: the DUKF started from a mounting attitude that is now ``(dp, dr)``
        off (a node's IMU fused before the first image named the camera, whose extrinsics re-derive
        the mounting; 1 deg: 1.3 % of a synthetic drive's length before this, 0.001 % after): its state
        becomes what a start from the new mounting would have given (nothing moves for ``(0, 0)``). Its mean moves by the start's
        share of the change (``_start_share``: a Kalman filter's mean depends on its start by the
        product of its updates' ``1 - K``); the rest of the pitch change is the accelerometer pull it
        would not have made, which :meth:`_fuse_imu` keeps out of the BEV (the start's excess
        variance: all of it, early on), so the BEV's pitch input moves by the whole change and its
        roll input by the mean's. The road-tilt low-pass moves with the inputs (the BEV's attitude
        does not jump); ``set_camera`` moves the current start's history entries by the returned
        ``(pitch, roll, kept-out pull)`` changes (the pitch changes the correction reads stay the car's)."""
        (p, r), cov = self._state
        sp, sr = dp * self._start_share[0], dr * self._start_share[1]
        kept = dp - sp  # the pull a start from the new mounting would not have made (kept out of the BEV)
        self._state = ((p + sp, r + sr), cov)
        self._pull_kept_out -= kept
        self._pitch_kept_out_recent -= kept
        self._pitch_pull_inertial -= kept  # the gyro's pitch (the inertial input's gravity) starts at the new mounting
        self._road_tilt.shift(dp, sr)  # the inputs: the pitch less its kept-out pull moves by dp, the roll by sr
        return sp, sr, kept

    @property
    def pitch_roll(self) -> np.ndarray | None:
        """Current gravity-referenced (pitch, roll) from the DUKF, radians."""
        return None if self._state is None else np.array(self._state[0])

    @property
    def gyro_bias(self) -> tuple[float, float, float]:
        """Fused mode: the gyro biases the engine takes off (rad/s, base x, y, z): x and y from the
        rest intervals' mean rates and, with ``gyro_bias_std``, the DUKF's accelerometer between
        stops (core/gyro_bias), z the motion filter's yaw-rate bias. Zeros in paper mode."""
        return (*self._gyro_bias.xy, float(self._vstate.b) if self.mode == "fused" else 0.0)

    @property
    def pose(self) -> tuple[float, float, float]:
        """The latest frame's ``(x, y, yaw)`` in the odometry frame (m, rad), a pose set included."""
        return self._trajectory.pose

    @property
    def frame_period(self) -> float | None:
        """The camera's mean frame period (s) by the frame clock (fused mode), None before it has one."""
        return self._frame_clock.period

    @property
    def direction_of_travel(self) -> str:
        """Fused mode with ``direction_lock``: ``"forward"`` or ``"reverse"`` (the translation's
        peak is taken in that direction) or ``"either"`` (after a confirmed stop, until the speed
        passes DIRECTION_SPEED); ``"any"`` without the lock (and in paper mode)."""
        if self.mode != "fused" or not self.direction_lock:
            return "any"
        return {1: "forward", -1: "reverse", 0: "either"}[self._direction]

    @property
    def road_pitch_roll(self) -> np.ndarray | None:
        """The latest IMU sample's road-relative (pitch, roll) the BEV would use, radians, less the
        mounting attitude (the rig's static tilt on the road)."""
        if not self._history:
            return None
        road = self._history[-1][1]
        return np.array([road[0] - self._mounting[0], road[1] - self._mounting[1]])

    @property
    def pending_images(self) -> int:
        return len(self._pending)

    @property
    def pending_tags(self) -> list:
        """The tags of the images waiting for IMU, oldest stamp first."""
        return [tag for _, _, tag in self._pending]

    def take_events(self) -> list[EngineEvent]:
        """The events counted since the last call (at most the latest 1000), oldest first."""
        events = list(self._events)
        self._events.clear()
        return events

    @property
    def reach(self) -> float:
        """m: the forward motion a frame past which the frame counts as ``beyond_reach``
        (:data:`REACH_SHARE` of the BEV's forward extent)."""
        return REACH_SHARE * self.spec.extent

    def _count(self, kind: str, stamp: float, tag: Any = None) -> None:
        setattr(self.counters, kind, getattr(self.counters, kind) + 1)
        self._events.append(EngineEvent(kind, stamp, tag))

    # ------------------------------------------------------------------ inputs
    def add_imu(self, stamp: float, gyro, accel) -> list[OdometryStep]:
        """Fuse one IMU sample; returns the images it released (processed in stamp order).

        Raises ImplausibleImuError (a ValueError; ``reason`` ``imu_nonfinite``, ``imu_accel_range``
        or ``imu_gyro_range``) for NaN/inf or readings outside ``self.imu_limits``, ValueError for a
        zero acceleration (InvalidInputError) and OutOfOrderError for stamps not after the last.
        """
        g = [float(v) for v in np.asarray(gyro, dtype=np.float64).reshape(3)]
        a = [float(v) for v in np.asarray(accel, dtype=np.float64).reshape(3)]
        given = stamp
        stamp = stamp + self.imu_time_offset  # on the images' clock
        if not (math.isfinite(stamp) and all(math.isfinite(v) for v in g + a)):
            raise ImplausibleImuError("imu_nonfinite", f"IMU sample at {stamp} has NaN/inf (gyro {g}, accel {a})")
        if (problem := imu_problem(g, a, self.imu_limits)) is not None:
            raise ImplausibleImuError(*problem)
        if math.hypot(*a) < 1e-6:
            raise InvalidInputError("IMU linear acceleration is zero: no gravity, no attitude")
        last = self._last_imu if self._hold is None else self._hold.last.get("imu")
        if last is not None and stamp <= last:
            raise OutOfOrderError("IMU", stamp, last)
        if self._hold is not None:  # checked now, fused once the tilt is measured (_settle_tilt)
            self._hold.last["imu"] = stamp
            self._hold.inputs.append(("imu", (given, g, a)))
            # the pairs are measured in worker threads: the next input after the last one needed releases
            return self._hold_progress()
        self.counters.imu += 1
        if self.mode == "fused":
            # Images waiting for this sample are projected with the attitude interpolated to their
            # stamps (_attitude_at), so this sample is fused first. Releasing them before it, as
            # paper mode does, gave a frame that arrives before the IMU sample after it (the order a
            # node and a bag deliver them in: KITTI frames on the camera clock, 10 Hz OXTS) the
            # attitude and the gyro yaw of the sample before it: a 10 Hz drive's per-frame gyro
            # yaw read 0 and then twice the turn. Frames before the first sample have no attitude:
            # dropped and counted, as before.
            out = self._release(lambda s: s < stamp) if self._state is None else []
            self._fuse_imu(stamp, g, a)
            return out + self._release(lambda s: s <= stamp)
        out = self._release(lambda s: s < stamp)
        if self.turn_compensation:  # remove_turn_acceleration, in floats
            a[1] -= self._speed * g[2]
        if self._state is None or stamp - self._last_imu > self.max_imu_gap:
            if self._state is not None:
                self._count("imu_gaps", stamp)
            init = self.dukf.init_state(accel=torch.tensor([a], dtype=torch.float64))
            c = init.cov[0].tolist()
            self._state = (tuple(init.mean[0].tolist()), (c[0][0], c[0][1], c[1][1]))
        else:
            self._imu_dt = stamp - self._last_imu
            self._state = self.dukf.step_scalar(*self._state, g, a, self._imu_dt, self._noise)
        self._last_imu = stamp
        pitch, roll = self._road_tilt.update(stamp, *self._state[0])
        road = (pitch + self._mounting[0], roll + self._mounting[1])
        self._history.append((stamp, road, self._state, 0.0, 0, (0.0, 0.0)))
        out += self._release(lambda s: s <= stamp)
        return out

    def add_speed(self, stamp: float, speed: float, variance: float = 0.01, signed: bool = True) -> None:
        """Fused mode: a forward speed that does not come from the images (wheel odometry, CAN),
        m/s with its variance. While fresh (``max_speed_age``) the DUKF
        removes the whole vehicle acceleration with it, forward dv/dt included (see :meth:`_fuse_imu`),
        and the motion filter measures each frame's speed with its mean over the frame interval
        (:meth:`_external_speed`) before the images do: the scale then comes from it, no longer from
        the BEV's pitch. Feed it in stamp order with the IMU and images.

        ``signed``: negative reversing, and beyond ``DIRECTION_SPEED`` it sets the direction of travel
        itself (no stop the images confirm needed). Unsigned (a GNSS speed over ground, a wheel's
        magnitude): its size only, the sign that of the direction of travel the engine keeps (set
        by the motion filter's speed once past ``DIRECTION_SPEED`` after a stop the images confirm;
        right after one, the correlation's reading once clear of zero, :meth:`_fused_motion`)."""
        if not (math.isfinite(stamp) and math.isfinite(speed) and math.isfinite(variance) and variance > 0):
            raise ValueError(f"speed sample must be finite with a variance > 0, got {speed!r}, {variance!r}")
        if abs(speed) > MAX_SPEED:  # a corrupt message: 1e300 m/s overflowed the compensation to inf
            raise ValueError(f"speed {speed!r} m/s is beyond any car's ({MAX_SPEED:g} m/s)")
        last = (self._ext_speed[0] if self._ext_speed is not None else None) if self._hold is None else self._hold.last.get("speed")
        if last is not None and stamp <= last:  # refused before it changes anything
            raise OutOfOrderError("speed", stamp, last)
        if self._hold is not None:
            self._hold.last["speed"] = stamp
            self._hold.inputs.append(("speed", (stamp, speed, variance, signed)))
            return
        if not signed:  # the speed crosses zero where the sign changes: no jump in the DUKF's dv/dt
            speed = math.copysign(speed, self._direction or (1.0 if self._vstate.v >= 0 else -1.0))
        if self._ext_speed is None:
            state = self.vehicle.step(initial_vehicle_state(), 1.0, 0.0, forward=speed, forward_var=variance).state
        else:
            last, state = self._ext_speed
            dt = stamp - last
            state = self.vehicle.step(state, dt, 0.0, forward=speed * dt, forward_var=variance * dt * dt).state
        self._speed_unsigned = not signed
        self._ext_speed = (stamp, state)
        self._speed_log.append((stamp, float(speed), float(variance)))

    def _external_speed(self, t0: float, t1: float, magnitude: bool = False) -> tuple[float, float] | None:
        """add_speed's mean speed over the frame interval ``[t0, t1]`` (linear between its samples,
        held for ``max_speed_age`` past the ends) and the mean of their variances (a wheel's error,
        its scale, is the same for the interval's samples); None where no sample lies within
        ``max_speed_age`` of some part of the interval. What has arrived by the frame's processing
        (the IMU sample after its stamp): a speed stamped before ``t1`` arriving later is not used.
        ``magnitude``: the mean of their sizes (an unsigned speed whose sign is yet to be given)."""
        age = self.max_speed_age
        near = []  # newest first, back to the interval's start: a few samples, not the whole log
        for e in reversed(self._speed_log):
            if e[0] < t0 - age:
                break
            if e[0] <= t1 + age:
                near.append(e)
        near.reverse()
        if not near or near[0][0] > t0 + age or near[-1][0] < t1 - age or t1 <= t0:
            return None
        ts = np.array([e[0] for e in near])
        if len(ts) > 1 and float(np.diff(np.clip(ts, t0, t1)).max()) > 2 * age:
            return None
        knots = np.concatenate([[t0], ts[(ts > t0) & (ts < t1)], [t1]])
        values = np.interp(knots, ts, np.array([abs(e[1]) if magnitude else e[1] for e in near]))
        mean = float(np.sum(0.5 * (values[1:] + values[:-1]) * np.diff(knots)) / (t1 - t0))
        return mean, float(np.mean([e[2] for e in near]))

    def _fuse_imu(self, stamp: float, g: list[float], a: list[float]) -> None:
        """Fused mode, one IMU sample: compensated DUKF, suspension-aware road tilt, gyro yaw."""
        vs = self._vstate
        self._gyro_xy.append((stamp, g[0], g[1]))
        bx, by = self._gyro_bias.xy
        g = [g[0] - bx, g[1] - by, g[2]]
        elapsed = 0.0 if self._prev_stamp is None else max(stamp - self._prev_stamp, 0.0)
        speed, speed_var = vs.speed_at(elapsed)
        # The forward acceleration from the accelerometer's forward reading at the latest filtered
        # pitch, low-passed over ACCEL_CORRELATION_TIME with this sample's own interval (restarted
        # after a gap): the suspension model's input (below) whatever the speed source, and the size
        # of the uncompensated dv/dt with the visual speed alone. The pitch is the DUKF's less the
        # share of its recent accelerometer updates (KEPT_OUT_MEMORY) that its variance above the
        # steady state marks as unconverged (as kept out of the BEV below): after a cold start in
        # an acceleration those read the acceleration as tilt (real drive 0027 @ 480, 1 m/s^2: the
        # DUKF's pitch 4 deg off within 2 s, the forward acceleration half the true one); the
        # gyro's pitch changes stay in.
        tc = ACCEL_CORRELATION_TIME
        if self._state is not None:
            forward = a[0] + GRAVITY * math.sin(self._state[0][0] - self._pitch_kept_out_recent)
            step = stamp - self._last_imu
            if self._acc_fx is None or step > self.max_imu_gap:
                self._acc_fx = forward
            else:
                self._acc_fx += min(1.0, max(step, 1e-4) / tc) * (forward - self._acc_fx)
        ext = self._ext_speed
        if ext is not None and 0.0 <= stamp - ext[0] <= self.max_speed_age:
            # A speed that does not come from the images (wheel odometry): v and dv/dt both removed.
            es = ext[1]
            esp, esv = es.speed_at(stamp - ext[0])
            f, extra = compensate_floats(a, g, esp, es.a, esv, es.var(1))
        else:
            # An error in the forward acceleration is the same for every sample while it lasts: its
            # variance counts once per sample of its correlation time.
            dt_imu = max(self._imu_dt, 1e-4)
            if self.vehicle.noise.imu_accel_density > 0:
                # Fused item 17. With the inertial speed input the motion filter's dv/dt is the
                # accelerometer's forward reading with gravity removed at the gyro's pitch (since the
                # start, the DUKF's level let in over INERTIAL_PULL_MEMORY), less the bias beta that
                # the images' speed observes: the forward acceleration is subtracted with it (only
                # if the filter's last frame had that input: the images' dv/dt alone would close
                # the loop described below), at its own variance (3 m/s^2 std at a
                # start, ~1.5 m/s^2 at 10 Hz later: the pitch then rests mostly on the gyro, and an
                # acceleration is no longer read as tilt). Against the variance-only model below, on
                # real IMU: the gravity pitch's RMS error 1.50 -> 0.65 deg (94 5 s clips) and 1.14 ->
                # 0.53 deg (59 16 s clips), drift 2.44 -> 1.99 % and 1.69 -> 1.49 %. The cost: a start
                # error converges over tens of seconds, not seconds (10 Hz synthetic `curve`, 6 s:
                # 0.08 -> 0.54 deg; the BEV's road-relative pitch, high-passed, does not see it).
                per_second = max(1.0, ACCEL_ESTIMATE_CORRELATION_TIME / dt_imu)
                f, extra = compensate_floats(a, g, speed, vs.a if self._accel_has_inertial else 0.0, speed_var,
                                             vs.var(1) * per_second)
            else:
                # With the visual speed alone the forward acceleration is not subtracted: a visual
                # dv/dt closes a loop (a pitch error scales the BEV's speed, whose rate tilts the
                # compensated pitch) that ran the KITTI sample's gravity pitch to 11 deg RMS; the
                # speed terms (centripetal v wz, -v wy) have no such loop gain. The forward
                # acceleration only makes the pitch measurement count less: its size from the
                # accelerometer's forward reading at the predicted pitch, low-passed over
                # ACCEL_CORRELATION_TIME (plus the filter's dv/dt; a wrong mean only widens the
                # variance) (10 Hz presets: 18.5 -> 13.6 % per frame against the accelerometer's
                # norm as the cue).
                a_var = ((self._acc_fx or 0.0) ** 2 + vs.a * vs.a) * max(1.0, tc / dt_imu)
                f, extra = compensate_floats(a, g, speed, 0.0, speed_var, a_var)
        restarted = self._state is None or stamp - self._last_imu > self.max_imu_gap
        prev2 = self._gyro_prev2  # (rates, yaw rate) of the sample before the interval's start, or None
        if restarted:
            if self._state is not None:
                self._count("imu_gaps", stamp)
            # Start from the mounting attitude with a wide variance and take the first sample as a
            # measurement: one accelerometer sample read in a bend is not locked in.
            v0 = self.initial_attitude_std**2
            mean, cov, pull, innovation = self.dukf.step_scalar(
                self.mounting_attitude, (v0, 0.0, v0), g, f, 0.0, self._noise, extra, return_pull=True,
                return_innovation=True)
            self._gyro_bias.restart(0.0 if self._last_imu is None else stamp - self._last_imu)
            self._start_share = (cov[0] / v0, cov[2] / v0)
            self._yaw_rate = None
            self._imu_restarts += 1
            h1 = None
        else:
            h1 = self._imu_dt
            self._imu_dt = stamp - self._last_imu
            # The interval's rate by what the gyro's samples are (core/rate_integration): an
            # interval mean as it is (KITTI), instantaneous rates by the quadratic rule (10 Hz
            # presets with instantaneous rates: 13.1 % per frame with the trapezoid, 11.2 % with it).
            rate = interval_rate(self.gyro_sampling, g, self._gyro_prev, None if prev2 is None else prev2[0],
                                 self._imu_dt, h1)
            mean, cov, pull, innovation = self.dukf.step_scalar(*self._state, rate, f, self._imu_dt, self._noise,
                                                                extra, return_pull=True, return_innovation=True)
            if self._prev is None:  # only _move_dukf_start reads it, before the first frame
                # the start's share of the mean, d mean / d start = the product of the updates' (1 - K) =
                # P_post / P_pred per angle
                (o_p, o_r), prior = self._noise[0], self._state[1]
                self._start_share = (self._start_share[0] * cov[0] / (prior[0] + o_p * self._imu_dt),
                                     self._start_share[1] * cov[2] / (prior[2] + o_r * self._imu_dt))
        self._state = (mean, cov)
        # The pitch and roll rates' biases between stops (core/gyro_bias), from the same innovation.
        (o_p, o_r), (q_p, q_r) = self._noise
        self._gyro_bias.step(0.0 if restarted else self._imu_dt, (o_p, o_r), innovation[0], (q_p, q_r), extra,
                             innovation[1])
        # The DUKF's variance above its steady state is uncertainty it has not worked off yet (its
        # start from the mounting attitude, a restart, the accelerometer discounted through an
        # acceleration): that share of its pitch pull moves its level towards gravity and is no
        # pitch change of the car on the road, so it is kept out of the BEV's attitude (the road-
        # tilt low-pass would pass it as one, a start's convergence over the first seconds as a
        # scale error). Measured, 10 Hz: the 59 real-IMU 16 s clips per frame 5.56 -> 4.06 cm,
        # drift mean 1.93 -> 1.73 %, over 3 %: 15 -> 8, the first pair after the cold start
        # 24.8 -> 8.5 cm (0016/0018). The roll's pull stays in: kept out too, the clips' drift
        # was worse (1.88 % on 0016/0018).
        steady = self._steady_state_variances()[0]
        kept_out = pull[0] * min(1.0, max(0.0, (cov[0] - steady) / cov[0]))
        self._pull_kept_out += kept_out
        self._pitch_kept_out_recent = kept_out + (
            0.0 if restarted else self._pitch_kept_out_recent * math.exp(-self._imu_dt / KEPT_OUT_MEMORY))
        self._pull_cum += pull[0] - kept_out
        (pitch, roll) = self._state[0]
        if restarted:  # the gyro's pitch starts at the DUKF's start, the mounting attitude
            self._pitch_pull_inertial = pull[0]
            self._vstate = forget_accel_bias(self._vstate)  # beta held the old start's error
            self._beta_forgotten = True  # said in the next frame's filter inputs (training replays it)
        else:
            step = stamp - self._last_imu
            self._pitch_pull_inertial = pull[0] + self._pitch_pull_inertial * math.exp(-step / INERTIAL_PULL_MEMORY)
            if self.vehicle.noise.imu_accel_density > 0:  # the inertial speed input (an interval mean)
                self._inertial_cum += (a[0] + GRAVITY * math.sin(pitch - self._pitch_pull_inertial)) * step
        self._inertial_log.append((stamp, self._inertial_cum, self._imu_restarts))
        # Yaw rate about the vertical (Z-Y-X Euler kinematics), integrated by the same rule.
        rate = (g[1] * math.sin(roll) + g[2] * math.cos(roll)) / math.cos(pitch)
        if self._yaw_rate is not None:
            self._yaw_cum += interval_rate(self.gyro_sampling, [rate], [self._yaw_rate],
                                           None if prev2 is None else [prev2[1]], self._imu_dt, h1)[0] * self._imu_dt
        # the sample before the next one's interval; none across a restart
        self._gyro_prev2 = None if restarted or self._yaw_rate is None else (self._gyro_prev, self._yaw_rate)
        self._gyro_prev = g
        self._yaw_rate = rate
        self._last_imu = stamp
        # The suspension's lean lasts as long as the acceleration: keep it out of the low-pass
        # (forward acceleration from the accelerometer, no loop through the images' scale).
        dyn_p, dyn_r = suspension_attitude(self._acc_fx or 0.0, speed * g[2], *self.suspension_gradients)
        if self._body_pitch is not None:
            self._body_pitch.append((stamp, dyn_p))
        rp, rr = self._road_tilt.update(stamp, pitch - self._pull_kept_out - dyn_p, roll - dyn_r)
        road = (rp + dyn_p + self._mounting[0], rr + dyn_r + self._mounting[1])
        self._history.append((stamp, road, self._state, self._yaw_cum, self._imu_restarts,
                              (self._pull_cum, self._pull_kept_out)))

    def add_image(self, stamp: float, image, tag: Any = None) -> list[OdometryStep]:
        """Queue or process one image ``(H, W)`` uint8 or float in [0, 1]; ``tag`` comes back as
        its step's ``tag`` (or its drop event's).

        Raises InvalidInputError for a bad image and OutOfOrderError for stamps not after the last image.
        """
        img = np.asarray(image)
        if img.ndim != 2:
            raise InvalidInputError(f"image must be (H, W) grayscale, got shape {img.shape}")
        if (img.shape[1], img.shape[0]) != (self.camera.width, self.camera.height_px):
            raise InvalidInputError(
                f"image size {img.shape[1]}x{img.shape[0]} does not match the calibration "
                f"{self.camera.width}x{self.camera.height_px}"
            )
        if not math.isfinite(stamp):
            raise InvalidInputError("image stamp is not finite")
        if img.dtype.kind == "f" and not np.isfinite(img).all():
            raise InvalidInputError("image has NaN or inf pixels")
        last = max([s for s, _, _ in self._pending] + ([self._last_image] if self._last_image is not None else []),
                   default=None) if self._hold is None else self._hold.last.get("image")
        if last is not None and stamp <= last:
            raise OutOfOrderError("image", stamp, last)
        if self._hold is not None:
            # held images are ordered against the last one held, skipped or not: a little stricter than the
            # running engine (against the last processed), only for an image older than one already received
            self._hold.last["image"] = stamp
            self._hold.add_image(stamp, img, tag, self.camera.K.detach().double().cpu().numpy())
            return self._hold_progress()
        self.counters.images += 1
        if self._last_imu is not None and self._last_imu >= stamp:
            return self._process_or_drop(stamp, img, tag)
        self._pending.append((stamp, img, tag))
        if len(self._pending) > self.max_pending_images:
            old, _, old_tag = self._pending.pop(0)
            self._count("dropped_pending_overflow", old, old_tag)
        return []

    def flush(self) -> list[OdometryStep]:
        """Process every waiting image with the IMU fused so far (drops them if there was none); inputs
        held for the start's tilt go first, at the tilt their pairs show (the configured one with too few)."""
        out = []
        if self._hold is not None:
            self._hold.directions  # every pair, then as _hold_progress decides
            out = self._release_standing() + self._settle_tilt()
        return out + self._release(lambda s: True)

    def poll(self) -> list[OdometryStep]:
        """While the start is held: its release if the pairs done since the latest input allow it (a node calls
        it on a timer: after a bag that ended flat out, or a camera that stopped, no input comes to release
        them, and a flush would run the last frames without the IMU still on its way). -> the steps."""
        return self._hold_progress() if self._hold is not None else []

    def close(self) -> None:
        """Stop the start tilt's measurement threads (an engine replaced while it holds its start)."""
        if self._hold is not None:
            self._hold.close()

    @property
    def held_images(self) -> int:
        """Images held until the start's camera tilt is measured (``tilt_from_images``)."""
        return self._hold.images if self._hold is not None else 0

    @property
    def holding(self) -> bool:
        """Inputs are held until the start's camera tilt is measured."""
        return self._hold is not None

    @property
    def measuring(self) -> bool:
        """Held frame pairs are still being measured (in their threads) for the start's tilt."""
        return self._hold is not None and self._hold.measuring

    @property
    def held_pairs(self) -> int:
        """Frame pairs held so far that showed a forward direction of travel."""
        return self._hold.forward_pairs if self._hold is not None else 0

    def _start_body_pitch(self, inputs: list, stamps: list[float], mounting: tuple[float, float], T) -> list[float]:
        """The suspension's pitch (rad, nose down +) at each held frame pair's first frame (``stamps``): a pass
        of an engine like this one over the held ``inputs`` with the base's ``mounting`` for the camera ``T (4,
        4)``. Braking dives the nose and a pull-away squats it, and the direction of travel measured
        then has that pitch in it (rendered `urban`, braking from 8 to 4.5 m/s over its first 3 s:
        +0.45 deg mean); the engine adds its suspension model to the mounting, so the mounting is the
        rest pitch. The model reads the accelerometer less gravity at the DUKF's pitch, which starts at
        the mounting: a pass at a mounting 1 deg off reads -0.09 deg of squat at a steady speed, so
        the pass is at the pairs' own tilt (``_settle_tilt``). At a steady speed the model still reads
        a few hundredths of a degree (rendered `curve`, 15 m/s on 100 m: +0.05; the KITTI sample -0.04), so
        only its pitch beyond :data:`START_TILT_BODY_DEADBAND` is taken out: the dives and squats of braking
        and pulling away. Measured deadbands (docs/FUSED_ODOMETRY.md): 0, 0.05 (kept), 0.1 deg."""
        # eager kernels: the pass needs the suspension's pitch, not the compiled kernels' last bit
        shadow = BevoOdometry(**{**self._settings, "camera": self.camera, "tilt_from_images": 0, "kernels": "eager",
                                 "mounting_attitude": mounting, "mounting_extrinsics": T})
        for name in _LIVE_SETTINGS:  # settings a caller may have changed since the construction
            setattr(shadow, name, getattr(self, name))
        shadow.reset()
        shadow._body_pitch = []
        for kind, args in inputs:
            try:
                shadow._feed_held(kind, args)
            except (InvalidInputError, ImplausibleImuError):  # as _settle_tilt's run: counted there
                continue
        shadow.flush()
        log = shadow._body_pitch
        logged = [t for t, _ in log]
        at = [log[max(bisect.bisect_right(logged, t) - 1, 0)][1] if log else 0.0 for t in stamps]
        return [math.copysign(max(abs(b) - START_TILT_BODY_DEADBAND, 0.0), b) for b in at]

    def _settle_tilt(self) -> list[OdometryStep]:
        """The start's camera tilt from the held pairs (:mod:`~bevo_ros.core.start_tilt`), then the held
        inputs run in their order. -> their steps."""
        hold = self._hold  # kept until measured: an error escaping the measurement loses no input
        pitch, roll = self.mounting_attitude
        T = self.camera.T_base_cam.detach().double().cpu().numpy()
        body = None
        pre: list[OdometryStep] = []  # standing frames run before a restart at the measured tilt
        # the pairs it takes (the first tilt_from_images forward ones, else all), the inputs up to them
        directions, inputs, stamps = hold.taken()
        # the held frames begin after standing ones: the IMU before the first too
        bridge = self._standing_bridge(hold) if self._standing_released else []
        inputs = bridge + inputs
        try:
            direction = direction_of_pairs(directions)  # the pairs as measured
        except ValueError as exc:  # too few pairs: nothing else here may pass for that
            self.tilt_measurement = TiltMeasurement(0.0, 0, len(directions), 0.0, False, str(exc),
                                                    failed=tuple(hold.failed), standing_frames=self._standing_released)
        else:
            # less the suspension's pitch that a pass at the pairs' tilt models (the same pairs: no ValueError)
            for _ in range(START_TILT_PASSES if self.mode == "fused" else 0):
                mounting = (mounting_pitch_from_travel(direction, T[:3, :3], roll)[0], roll)
                body = self._start_body_pitch(inputs, stamps, mounting, T)
                direction = direction_of_pairs(directions, body)
            measured, _ = mounting_pitch_from_travel(direction, T[:3, :3], roll)
            # the camera's tilt measured: a later camera with other extrinsics keeps it (set_camera)
            self._mounting_calibration = ((measured, roll), T)
            self.mounting_attitude = (measured, roll)
            self._standstill.set_attitude(self.mounting_attitude)
            self._mounting = self.mounting_attitude
            self.tilt_measurement = TiltMeasurement(measured - pitch, direction.pairs, direction.pairs_skipped,
                                                    direction.elevation_sem, True,
                                                    body_pitch=mean_offset(directions, body), failed=tuple(hold.failed),
                                                    standing_frames=self._standing_released)
            if self._standing_released:
                # Frames stood still at the configured tilt before: the held ones start afresh at the measured
                # one, where those left the car (a BEV whose tilt jumps between two frames reads a shift), the
                # filters from the held inputs, which begin standing still.
                # Kept: the trajectory (its pose, a set_pose waiting for a frame, the frames a stamped one
                # reaches back over) and the gyro's biases, learnt best standing still.
                pre = self._release(lambda s: True)  # a standing frame still waiting for IMU: run with what came
                kept = (copy.deepcopy(self._trajectory), self._gyro_bias, self._xy_bias_time, self.counters.imu)
                self.reset()
                self.counters.resets -= 1  # the engine's own restart, not an explicit reset (counted)
                self._trajectory, self._gyro_bias, self._xy_bias_time, imu_count = kept
                for kind, args in bridge:  # fed before, to the engine now forgotten
                    try:
                        self._feed_held(kind, args)
                    except (InvalidInputError, ImplausibleImuError):
                        pass  # refused (and counted) when it was fed the first time
                self.counters.imu = imu_count
        self._hold = None
        self.held_until = hold.stamps[-1] if hold.stamps else self.held_until
        out: list[OdometryStep] = pre
        for kind, args in hold.inputs:
            try:
                out += self._feed_held(kind, args)
            except (InvalidInputError, ImplausibleImuError):  # checked when held: a camera changed meanwhile
                self._count("dropped_held_invalid", args[0], args[2] if kind == "image" else None)
        return out

    def _hold_progress(self) -> list[OdometryStep]:
        """While the start is held, after each input: the frames of a car standing still released, and the
        tilt measured once enough pairs are (or as many images as may be held). At the most images held it
        waits for every pair first, so that what is released and measured depends on the pairs alone, not on
        how far their threads had got (a node paced by its camera and ``bevo run`` give the same poses)."""
        if self._hold.images >= self._hold.max_frames:
            self._hold.directions  # waits for them
        ready = self._hold.ready  # the pairs it counted are done: a standing start among them goes first
        out = self._release_standing()
        return out + (self._settle_tilt() if ready and self._hold.ready else [])

    def _standing_bridge(self, hold: StartHold) -> list[tuple[str, tuple]]:
        """The released IMU inputs a restart feeds before the held ones: from the last stamped at or before the
        first held frame (in the order they came), so that frame has an attitude."""
        imu = self._standing_imu
        if not imu or not hold.stamps:
            return list(imu)
        before = [i for i, (_, args) in enumerate(imu) if args[0] <= hold.stamps[0]]
        return imu[before[-1]:] if before else list(imu)

    def _release_standing(self) -> list[OdometryStep]:
        """The held frames of a car standing still at its start, run as they came while the hold goes on
        (:data:`STANDING_RELEASE_PAIRS`). What is released depends on the pairs' content alone, not on when
        their threads finished. -> their steps."""
        out: list[OdometryStep] = []
        hold = self._hold
        while hold.standing_prefix(STANDING_RELEASE_PAIRS):
            released = hold.release_prefix(STANDING_RELEASE_PAIRS)
            self._hold = None  # run through the public methods as a running engine
            try:
                for kind, args in released:
                    try:
                        out += self._feed_held(kind, args)
                    except (InvalidInputError, ImplausibleImuError):  # checked when held
                        self._count("dropped_held_invalid", args[0], args[2] if kind == "image" else None)
            finally:
                self._hold = hold
            self._standing_released += STANDING_RELEASE_PAIRS
            self.held_until = max([a[0] for k, a in released if k == "image"], default=self.held_until)
            # the IMU released lately: a restart at the measured tilt needs the samples from the last one stamped
            # at or before the first held frame (_settle_tilt), or that frame has no attitude and is dropped
            self._standing_imu = (self._standing_imu + [e for e in released if e[0] == "imu"])[-4000:]
        return out

    def _feed_held(self, kind: str, args: tuple) -> list[OdometryStep]:
        """One held input (:class:`~bevo_ros.core.start_tilt.StartHold`'s ``inputs``) through the public
        method of its kind, as it came. -> the steps it gives."""
        if kind == "imu":
            return self.add_imu(*args)
        if kind == "image":
            return self.add_image(*args[:2], tag=args[2])
        self.add_speed(*args)
        return []

    # ------------------------------------------------------------------ internals
    def _release(self, ready) -> list[OdometryStep]:
        out = []
        while self._pending and ready(self._pending[0][0]):
            stamp, img, tag = self._pending.pop(0)
            if self._state is None:
                self._count("dropped_no_imu", stamp, tag)
                continue
            out += self._process_or_drop(stamp, img, tag)
        return out

    def _process_or_drop(self, stamp: float, img: np.ndarray, tag: Any = None) -> list[OdometryStep]:
        """One frame, or a counted drop when its BEV has no valid pixel (e.g. an absurd attitude):
        ``_process`` changes no state before that check, so the next frame simply carries on.
        Any other exception is a bug and propagates. A frame stamped before the oldest IMU sample
        kept (before the first since the start or a reset, whichever way the two arrived; or older
        than the whole history: 4000 samples, 4 s at 1 kHz) has no attitude and no gyro yaw: dropped
        and counted too (it was given the oldest sample's)."""
        if not self._history or stamp < self._history[0][0]:
            self._count("dropped_no_imu", stamp, tag)
            return []
        if self._prev is not None and stamp - self._prev_stamp < self.min_frame_interval:
            self.counters.skipped_frame_rate += 1  # a state, not a fault: the camera is faster than needed
            return []
        try:
            return [self._process(stamp, img, tag)]
        except InvalidBevError:
            self._count("dropped_invalid_bev", stamp, tag)
            return []

    @torch.inference_mode()  # no autograd bookkeeping at all (cached grids: core.device.constant_cache)
    def _process(self, stamp: float, img: np.ndarray, tag: Any = None) -> OdometryStep:
        image = torch.as_tensor(np.require(img, requirements="W"), device=self.device)  # bag buffers are read-only
        if image.dtype != torch.uint8:
            image = image.to(self.dtype)
        road, state, yaw_cum, epoch, pull_cum = self._attitude_at(stamp)
        pitch_t, roll_t = (torch.tensor([v], dtype=self.dtype, device=self.device) for v in road)
        bev, mask = self.kernels.project_to_bev(image[None, None], self.camera, pitch_t, roll_t, self.spec)
        curr = self.kernels.prepare(bev, mask, self.dpc, self._mask_weight(mask, bev.dtype))
        first = self._prev is None
        dt = 0.0 if first else stamp - self._prev_stamp
        stamped_dt = dt
        if self.mode == "fused" and not first:
            dt = self._frame_clock.interval(dt)  # stamp jitter is no speed change
        measured, accepted, speed, shift, still = None, (True, True), float("nan"), 0.0, False
        if first:
            motion = np.zeros(3)
            motion_cov = np.zeros((3, 3))
            quality = float("nan")
        elif self.mode == "fused":
            # The DUKF's accelerometer pull since the previous frame; across a DUKF restart the BEV
            # pitch's whole jump is as unexplained (_pitch_change_shift takes nothing off there).
            prev = self._prev_pitch
            same = prev[2] == epoch
            pull = pull_cum[0] - prev[3][0] if same else road[0] - prev[0]
            kept_out = pull_cum[1] - prev[3][1] if same else 0.0
            turn = abs(yaw_cum - self._prev_yaw_cum) / stamped_dt  # rad/s; add_image keeps stamps increasing
            shift = self._pitch_change_shift(road[0], state, epoch, pull, dt, kept_out, turn)
            # The gyro's yaw was integrated over the stamped interval: over the frame's, it is that
            # much more or less (frames and a 10 Hz IMU sharing jittered stamps: 10 Hz on-ramp
            # preset with +-10 ms stamps, yaw 0.131 -> 0.027 deg per frame, as with exact stamps).
            frame_yaw = self._prev_yaw_cum + (yaw_cum - self._prev_yaw_cum) * dt / stamped_dt
            reg, motion, motion_cov, measured, accepted, speed, still = self._fused_motion(
                curr, stamp, dt, frame_yaw, state, shift, image, pull)
            quality = reg.quality.item()
        else:
            reg = self.kernels.register_prepared(self._prev, curr, self.dpc, envelope=self._envelope(curr))
            motion = self._vehicle_motion(reg)
            motion_cov = self._motion_covariance(reg, motion, state)
            quality = reg.quality.item()
        if not first and abs(float(motion[0])) > self.reach:
            self.counters.beyond_reach += 1
        self._trajectory.add(stamp, motion, motion_cov)
        self._prev, self._prev_stamp, self._last_image = curr, stamp, stamp
        if self.mode == "fused":
            self._standstill.remember(image)
        self._prev_yaw_cum = yaw_cum
        self._prev_pitch = (road[0], state[0][0], epoch, pull_cum)
        if dt > 0:
            self._speed = float(motion[0] / dt)
        self.counters.frames_out += 1

        (pitch, roll), (c00, c01, c11) = state
        att_cov = np.array([[c00, c01], [c01, c11]])  # [pitch, roll]
        pose_cov = np.zeros((6, 6))
        pose_cov[_PLANAR] = self._trajectory.cov
        pose_cov[2, 2] = Z_VARIANCE
        pose_cov[3, 3], pose_cov[4, 4] = att_cov[1, 1], att_cov[0, 0]
        pose_cov[3, 4] = pose_cov[4, 3] = att_cov[0, 1]
        twist_cov = np.zeros((6, 6))
        if dt > 0:
            # nav_msgs/Odometry's twist is in child_frame_id at t: rotate the step (base at t-1) by -dyaw.
            c, s_ = math.cos(motion[2]), math.sin(motion[2])
            rot = np.array([[c, s_, 0.0], [-s_, c, 0.0], [0.0, 0.0, 1.0]])
            twist_cov[_PLANAR] = rot @ motion_cov @ rot.T / dt**2
            lin = np.array([c * motion[0] + s_ * motion[1], -s_ * motion[0] + c * motion[1], 0.0]) / dt
            ang = np.array([0.0, 0.0, motion[2] / dt])
        else:
            lin, ang = np.zeros(3), np.zeros(3)
            twist_cov[0, 0] = twist_cov[1, 1] = twist_cov[5, 5] = Z_VARIANCE  # first frame: velocity unknown
        twist_cov[2, 2] = twist_cov[3, 3] = twist_cov[4, 4] = Z_VARIANCE
        x, y, yaw = self._trajectory.pose
        return OdometryStep(
            stamp=stamp,
            motion=motion,
            dt=dt,
            position=np.array([x, y, self._trajectory.z]),
            rpy=np.array([roll, pitch, yaw]),
            pose_covariance=pose_cov,
            twist_linear=lin,
            twist_angular=ang,
            twist_covariance=twist_cov,
            pitch_roll_road=np.array(road),
            bev=bev[0, 0].cpu().numpy(),
            bev_mask=mask[0, 0].cpu().numpy(),
            peak_quality=quality,
            first=first,
            correlation=None if first else reg.translation_corr[0].detach().cpu().numpy(),
            measured_motion=measured,
            accepted=accepted,
            speed=speed,
            filter_inputs=None if first or self.mode != "fused" else self._last_filter_inputs,
            tag=tag,
            pitch_shift=shift,
            standstill=still,
            direction_of_travel=self.direction_of_travel,
        )

    def _pitch_change_shift(self, bev_pitch: float, state: tuple, epoch: int, pull: float, dt: float,
                            kept_out: float = 0.0, yaw_rate: float = 0.0) -> float:
        """Fused mode: the forward shift (m) this frame's correlation reads from the engine's own
        change of the BEV pitch since the previous frame.

        The BEV pitch is the DUKF's pitch minus the road-tilt low-pass (whose input has the
        suspension model's lean taken out). What the low-pass changes between two frames is no
        motion of the car, yet it moves the whole current BEV by :func:`~bevo_ros.core.motion.pitch_change_shift` per radian
        (0.01 deg: 1.4 cm on KITTI), read as forward motion. The DUKF's change is taken as the
        car's. Zero across a DUKF restart (the attitude jumps), when the DUKF's accelerometer
        updates moved its pitch by more than ACCEL_PULL_RATE_GATE x ``dt`` between the two frames
        (``pull``, their pitch changes summed over the pair; converging from its start, or at
        10 Hz pulled hard by an acceleration: its change is then not the car's, and the low-pass
        following it is right), and with the correction off. A gate on the DUKF's variance
        (within 10x of its steady state) kept it off for the first ~5 s of a 10 Hz drive and
        through every acceleration, whose inflated measurement variance holds the variance up.
        With this gate: 10 Hz presets
        9.9 -> 7.7 % per frame, drift 3.5 -> 2.1 %; KITTI sample 5.6 -> 5.3 cm per frame (`bevo
        evaluate`); a 100 Hz braking start's first pair -104 -> -54 cm. The DUKF's small
        updates also move the BEV without motion, but telling them from a real pitch change
        needs the pitch gyro's bias, which the DUKF does not estimate. ``pull`` is the pull that
        reached the BEV; ``kept_out``, the share :meth:`_fuse_imu` kept out of the BEV's attitude,
        is no change of the car either. Zero too in a turn while the DUKF's roll is unconverged:
        ``yaw_rate`` (rad/s, the gyro's over the pair) times sqrt(the roll's variance less its steady
        state) over TURN_ROLL_RATE_GATE (a roll error turns the yaw rate into a pitch drift).
        """
        prev = self._prev_pitch
        if not self.pitch_change_correction or prev is None or prev[2] != epoch:
            return 0.0
        if (abs(pull) > ACCEL_PULL_RATE_GATE * dt  # the roll's excess only when the pull gate passes
                or abs(yaw_rate) * math.sqrt(max(0.0, state[1][2] - self._steady_state_variances()[1]))
                > TURN_ROLL_RATE_GATE):
            self.counters.pitch_correction_off += 1  # a state, not an event (a cold start's first seconds)
            return 0.0
        return self._shift_per_pitch_change * ((bev_pitch - prev[0]) - (state[0][0] - prev[1] - kept_out))

    def _fused_motion(self, curr, stamp: float, dt: float, yaw_cum: float, state: tuple, pitch_shift: float = 0.0,
                      image: torch.Tensor | None = None, pull: float = 0.0):
        """Fused mode, one frame: derotate by the gyro's yaw, correlate, take ``pitch_shift``
        (:meth:`_pitch_change_shift`) off the forward motion, its covariance with the DUKF's
        accelerometer ``pull`` over the pair (:meth:`_motion_covariance`), check for standstill on
        the raw ``image`` when the correlation reads little motion, filter, gate."""
        gyro_yaw = yaw_cum - self._prev_yaw_cum
        n = self.vehicle.noise
        speed_forgotten = False
        predicted_bias = self._vstate.b
        dyaw = gyro_yaw - predicted_bias * dt
        dyaw_std = math.sqrt(n.gyro_yaw_density * dt + self._vstate.var(2) * dt * dt)
        dev, dt_ = self.device, self.dtype
        imu_accel = self._inertial_accel(self._prev_stamp, stamp) if n.imu_accel_density > 0 else None
        imu_var = None if imu_accel is None else 0.0  # vibration: imu_accel_density; gravity's error: beta
        predicted = self.vehicle.predict(self.vehicle.inertial_update(self._vstate, dt, imu_accel, imu_var), dt)
        # An unsigned speed after a stop (direction either way): its size now, the correlation's reading
        # gives its sign (below).
        signless = self._speed_unsigned and self._direction == 0
        outside = self._external_speed(self._prev_stamp, stamp, magnitude=signless) if self._speed_log else None
        signless = signless and outside is not None
        if outside is not None and not signless:  # the correlation's prior, and the filter below, start from it
            predicted = self.vehicle.speed_update(predicted, *outside)
        # The BEV shift (px) of no motion of the base over this frame: the pitch-change shift and the
        # turn about the BEV's centre. A base motion (dx, dy) adds (dx, dy) / mpp to it (core/motion).
        row0, col0 = registration_shift_floats(pitch_shift, 0.0, dyaw, self.spec)
        mpp = self.spec.metres_per_pixel
        prior = self._shift_prior(predicted, dt, dyaw, row0, col0, pull)
        direction = self._direction if self.direction_lock else 0
        tolerance = DIRECTION_TOLERANCE
        bounds = (-tolerance if direction > 0 else -math.inf, tolerance if direction < 0 else math.inf)

        def register(prior, bounds):
            reg = self.kernels.register_prepared(
                self._prev, curr, self.dpc, angle=torch.tensor([-dyaw], dtype=dt_, device=dev),
                angle_std=torch.tensor([dyaw_std], dtype=dt_, device=dev), envelope=self._envelope(curr),
                shift_prior=None if prior is None else torch.tensor([prior[0]], dtype=dt_, device=dev),
                shift_prior_std=None if prior is None else torch.tensor([prior[1]], dtype=dt_, device=dev),
                peak_ratio=PEAK_RATIO,
                forward_range=None if bounds == (-math.inf, math.inf) else
                torch.tensor([[row0 + b / mpp for b in bounds]], dtype=dt_, device=dev))
            measured = self._vehicle_motion(reg)
            measured[0] -= pitch_shift
            return reg, measured, self._motion_covariance(reg, measured, state, pull)

        reg, measured, cov = register(prior, bounds)
        rot = -reg.rotation_estimate.item()
        quality = reg.quality.item()
        # The image rotation's spread plus what the correlation spread does not see (an attitude
        # error shears the BEV into a rotation): image_rotation_std.
        rot_var = reg.rotation_estimate_std.item() ** 2 + n.image_rotation_std**2
        # At rest the BEVs still move: the engine's attitude keeps changing (the DUKF on an idling
        # engine's vibration, the road-tilt low-pass), and each 0.01 deg of BEV pitch change reads as
        # 1.4 cm. The raw images say whether the car moved (core/standstill).
        # Only with texture (the correlation's own quality) and when a stop is within reach of the
        # motion filter's speed (a car does not go from 15 m/s to rest in a frame).
        still, rest_var = False, 0.0
        if (image is not None and self._standstill.enabled and abs(float(measured[0])) < STANDSTILL_CHECK_BELOW
                and quality >= n.min_quality and self._stop_is_plausible(dt)):
            sm = self._standstill.measure(image)  # with the coarse look: twice the range, for the least motion
            still = self._standstill.at_rest(sm, dt)
            if still:  # what the threshold leaves possible, and the estimate's own spread
                rest_var = (0.5 * self._standstill.max_speed * dt) ** 2 + sm.forward_std**2
            elif sm is not None and direction >= 0 and math.isfinite(sm.forward):
                # Beyond its linear range the flow reads short (towards zero): a least motion. Once
                # that is more than the correlation can read as a near stop, the correlation's peak
                # moved with the car; the road's is the strong one beyond it, if there is one.
                least = max(sm.forward, sm.coarse_forward) - 3.0 * sm.forward_std
                if least > max(STANDSTILL_CHECK_BELOW, float(measured[0]) + MOVING_MARGIN):
                    half = (self.spec.size // 2 - 2) * mpp
                    alt, alt_measured, alt_cov = register(None, (min(least, half) - tolerance, math.inf))
                    if (float(alt_measured[0]) >= least - 2 * tolerance
                            and _peak_height(alt) >= PEAK_RATIO * alt.quality.item()):
                        reg, measured, cov, quality = alt, alt_measured, alt_cov, alt.quality.item()
                        innovation = float(measured[0]) - predicted.v * dt
                        if innovation**2 >= n.gate**2 * (predicted.var(0) * dt * dt + float(cov[0, 0])):
                            self._vstate = forget_speed(self._vstate)  # its speed followed that peak
                            speed_forgotten = True
        if reg.shift_gated is not None and bool(reg.shift_gated[0]):
            self.counters.gated_peak += 1  # a state, not an event: following a car would crowd the events out
        if signless:
            # the images' direction once their reading is clear of zero (3 sigma); until then no speed
            forward, std = float(measured[0]), math.sqrt(float(cov[0, 0]))
            outside = None if still or abs(forward) <= 3.0 * std else (math.copysign(outside[0], forward), outside[1])
        inputs = dict(dt=dt, gyro_yaw=gyro_yaw, forward=float(measured[0]), forward_var=float(cov[0, 0]),
                      lateral=float(measured[1]), lateral_var=float(cov[1, 1]), rotation=rot, rotation_var=rot_var,
                      quality=quality, imu_accel=imu_accel, imu_accel_var=imu_var, rest_var=rest_var)
        if outside is not None:
            inputs.update(speed=outside[0], speed_var=outside[1])
        frame = self.vehicle.step(self._vstate, **inputs)
        self._vstate = frame.state
        if frame.speed_accepted is False:
            self._count("rejected_speed", stamp)  # an event: the node reports it
        # what training's replay must do to the state before this step, as the engine did
        self._last_filter_inputs = {**inputs, "forget_speed": speed_forgotten,
                                    "forget_accel_bias": self._beta_forgotten}
        self._beta_forgotten = False
        self._accel_has_inertial = imu_accel is not None
        if still:
            self._direction = 0
        elif outside is not None and not self._speed_unsigned and abs(outside[0]) > DIRECTION_SPEED:
            # A signed speed says the direction without a stop the images confirm (dark, plain road,
            # standstill check off).
            self._direction = 1 if outside[0] > 0 else -1
        elif self._direction == 0 and abs(frame.state.v) > DIRECTION_SPEED:
            self._direction = 1 if frame.state.v > 0 else -1
        acc_t, acc_r = bool(frame.accepted[0]), bool(frame.accepted[1])
        if not still:
            self._rest_since = None
        if still:
            self.counters.standstill += 1  # a state, not an event: a long stop would crowd the events out
            self._observe_rest_bias(self._prev_stamp, stamp)
        elif quality < n.min_quality:
            self._count("rejected_textureless", stamp)
        else:
            for kind, accepted in (("rejected_translation", acc_t), ("rejected_rotation", acc_r)):
                if not accepted:
                    self._count(kind, stamp)
        motion = np.array([float(v) for v in frame.motion])
        motion_cov = np.diag([float(v) for v in frame.variance])
        return reg, motion, motion_cov, measured, (acc_t, acc_r), float(frame.state.v), still

    def _shift_prior(self, predicted, dt: float, dyaw: float, row0: float, col0: float,
                     pull: float) -> tuple[list, list] | None:
        """Fused mode: the BEV shift (px, ``(d_row, d_col)``) the motion filter predicts for this
        frame (``predicted``: its state predicted over ``dt``, the accelerometer's input in, as
        :meth:`VehicleFilter.step` makes it; ``row0, col0``: the shift of no base motion) and its
        standard deviations (the prediction's and a measurement's,
        :data:`PEAK_PRIOR_MEASUREMENT_STD` plus the ``pull``'s shift).

        A car ahead (and its shadow) moves in the BEV with its own speed, and near a queue it covers
        as much of the BEV as the road: its correlation peak can be the higher one. The road's is
        the one nearest the filter's prediction (:func:`estimate_translation`'s prior), and what
        moves unlike it is left out of the correlation (:func:`motion_consistency_weight`).
        None (the highest peak, no weight) while the prediction is wider than
        :data:`PEAK_PRIOR_MAX_STD` (a start, a reset, after a gap)."""
        v, var_v = predicted.v, predicted.var(0)
        dx = v * dt
        n = self.vehicle.noise
        meas_var = PEAK_PRIOR_MEASUREMENT_STD**2 + (self._shift_per_pitch_change * pull) ** 2
        std_x = math.sqrt(max(var_v, 0.0) * dt * dt + meas_var)
        if std_x > PEAK_PRIOR_MAX_STD:
            return None
        if self.direction_lock and self._direction * dx < 0:
            dx = 0.0  # a prediction overshooting a stop: the car stops, it does not turn round
        std_y = math.sqrt((n.slip_std * dx) ** 2 + meas_var)
        mpp = self.spec.metres_per_pixel
        return [row0 + dx / mpp, col0 + dx * math.tan(dyaw / 2) / mpp], [std_x / mpp, std_y / mpp]

    def _observe_rest_bias(self, start: float, end: float) -> None:
        """Fused mode, the images say the car stood still from ``start`` to ``end`` (s): once the stop
        has lasted REST_BIAS_SETTLE, the gyro's mean x and y rates over the IMU samples in between are
        their biases (REST_BIAS_MEMORY; with the bias state between stops, weighed against it)."""
        if self._rest_since is None:
            self._rest_since = start
        if start - self._rest_since < REST_BIAS_SETTLE:
            return
        rates = []
        for s, x, y in reversed(self._gyro_xy):  # newest first: the interval is at the end
            if s <= start:
                break
            if s <= end:
                rates.append((x, y))
        span = end - start
        if not rates or span <= 0:
            return
        mx, my = (sum(r[i] for r in rates) / len(rates) for i in (0, 1))
        if max(abs(mx), abs(my)) > REST_BIAS_MAX:
            self.counters.rest_bias_skipped += 1
            return
        if self._gyro_bias.enabled:  # the stop against the estimate carried since, by their variances
            self._gyro_bias.observe_rest((mx, my), span, REST_BIAS_PRIOR)
            return
        held = self._xy_bias_time
        (bx, by) = self._gyro_bias.xy
        self._gyro_bias.set_xy(((bx * held + mx * span) / (held + span), (by * held + my * span) / (held + span)))
        self._xy_bias_time = min(held + span, REST_BIAS_MEMORY)

    def _stop_is_plausible(self, dt: float) -> bool:
        """Fused mode: the motion filter's speed can reach zero within ``dt`` braking at 1 g (plus
        0.5 m/s of slack). Its mean, not its variance: rejected frames widen the variance, and a
        frozen camera is a lasting disagreement. A filter whose speed is wrong comes down through
        the correlation's own readings first, as before."""
        v, _ = self._vstate.speed_at(dt)
        return abs(v) <= GRAVITY * dt + 0.5

    def _mask_weight(self, mask: torch.Tensor, dtype: torch.dtype) -> MaskWeight:
        """The BEV mask's correlation weight, reused while the mask (and ``self.dpc``) stays the
        same, as is the weights' overlap envelope (:meth:`_envelope`): about half the frames of the
        bench's bumpy drive keep the mask of the frame before."""
        dpc, cached = self._weight_cache
        if (cached is None or dpc is not self.dpc or cached.weight.dtype != dtype
                or not torch.equal(cached.mask, mask)):
            cached = self.kernels.mask_weight(mask, self.dpc, dtype)
            self._weight_cache = (self.dpc, cached)
        return cached

    def _envelope(self, curr) -> torch.Tensor:
        """``overlap_envelope`` of the previous and current frames' weights, reused while both are
        the same (cached) weights."""
        key = (self._prev.weight_spectrum, curr.weight_spectrum)
        if self._envelope_cache is None or any(a is not b for a, b in zip(self._envelope_cache[0], key)):
            self._envelope_cache = (key, self.kernels.overlap_envelope(*key))
        return self._envelope_cache[1]

    def _attitude_at(self, stamp: float) -> tuple[tuple[float, float], tuple, float, int, tuple[float, float]]:
        """Road-relative attitude, DUKF state, integrated gyro yaw, the DUKF's start count and its
        accelerometer pitch pull integrals, reaching the BEV and kept out of it (:meth:`_pitch_change_shift`) at
        ``stamp``: the last IMU sample at or before it, the yaw interpolated linearly to the stamp
        between samples. Fused mode interpolates the attitudes too (the DUKF's covariance stays
        the earlier sample's): with a 10 Hz IMU whose stamps jitter against the frames' (KITTI
        OXTS stamps, 10 ms steps, beside `times.txt` frame times) the last sample before a frame
        is often the previous frame's, and its attitude is a pitch change between the BEVs that
        the car did not make (10 Hz urban preset with +-10 ms IMU stamps: 20.3 -> 10.4 cm per
        frame; 9.6 with exact stamps). Not across a DUKF restart."""
        i = bisect.bisect_right(self._history, stamp, key=lambda h: h[0]) - 1
        t0, pr_road, state, yaw, epoch, pull = self._history[max(i, 0)]  # (_process_or_drop keeps i >= 0)
        if 0 <= i < len(self._history) - 1:
            t1, road1, state1, yaw1, epoch1, pull1 = self._history[i + 1]
            w = (stamp - t0) / (t1 - t0)
            yaw += (yaw1 - yaw) * w
            if self.mode == "fused" and epoch1 == epoch:
                pr_road = tuple(a + (b - a) * w for a, b in zip(pr_road, road1))
                state = (tuple(a + (b - a) * w for a, b in zip(state[0], state1[0])), state[1])
                pull = (pull[0] + (pull1[0] - pull[0]) * w, pull[1] + (pull1[1] - pull[1]) * w)
        return pr_road, state, yaw, epoch, pull

    def _inertial_accel(self, t0: float, t1: float) -> float | None:
        """The inertial speed input's mean forward acceleration between two frame stamps (m/s^2):
        its integral read at each stamp, linear between IMU samples (each an interval mean), as the
        gyro's yaw. A 10 Hz IMU on its own clock beside the camera's (KITTI with `times.txt`) puts
        no sample between some pairs of frames and two between others; a sum per frame then read
        None and a 0.2 s mean in turn. None when the samples cover less than half the interval
        (the start, a gap) or a DUKF restart lies between the stamps."""
        log = self._inertial_log

        def at(t: float) -> tuple[float, float, int] | None:
            i = bisect.bisect_right(log, t, key=lambda e: e[0]) - 1
            if i < 0:
                return None
            t_a, c_a, e_a = log[i]
            if i + 1 < len(log) and log[i + 1][2] == e_a:
                t_b, c_b, _ = log[i + 1]
                return t, c_a + (c_b - c_a) * (t - t_a) / (t_b - t_a), e_a
            return t_a, c_a, e_a  # beyond the samples: covered up to the last one

        a, b = at(t0), at(t1)
        if a is None or b is None or a[2] != b[2] or b[0] - a[0] <= 0.5 * (t1 - t0):
            return None
        return (b[1] - a[1]) / (b[0] - a[0])

    def _vehicle_motion(self, reg) -> np.ndarray:
        """The registration's (dx, dy, dyaw), float64 ``(3,)`` (the engine's batch of one)."""
        return self.kernels.vehicle_motion_from_registration(reg.angle, reg.shift, self.spec).cpu().numpy()[0].astype(np.float64)

    def _steady_state_variances(self) -> tuple[float, float]:
        """The DUKF's (pitch, roll) steady-state variances at the latest IMU period."""
        dt = max(self._imu_dt, 1e-4)
        (o_p, o_r), (q_p, q_r) = self._noise
        return steady_state_variance(o_p, q_p, dt), steady_state_variance(o_r, q_r, dt)

    def _motion_covariance(self, reg, motion: np.ndarray, state: tuple, pull: float = 0.0) -> np.ndarray:
        """(dx, dy, dyaw) covariance: the correlation distributions' spread (first order) plus what
        the attitude uncertainty does to the BEV, the dominant error on a car, ``G P G^T`` with
        ``G = dx [[-k_p, 0], [0, C_x k_r], [0, -k_r]]`` over (pitch, roll): a pitch error scales
        the forward motion (:func:`pitch_scale_sensitivity`), a roll error shears the BEV into a
        yaw error, and about the BEV centre a lateral one (:func:`roll_yaw_sensitivity`).
        ``P`` is the DUKF's attitude covariance with each variance capped at its steady state
        (:func:`~bevo_ros.core.dukf.steady_state_variance`): right after a start the filter is
        unsure of the absolute attitude, but that error is a constant the road-tilt high-pass
        removes. Fused mode adds the forward shift of ``pull``, the pitch change the DUKF's
        accelerometer updates made between the two frames without the car (across a DUKF restart
        the BEV pitch's whole jump): how much of it the BEV still carries (the low-pass follows
        part) is unknown (10 Hz presets 7.7 -> 6.5 % per frame, drift 2.1 -> 1.7 %; KITTI sample
        5.3 cm, 1.36 -> 1.34 %).
        """
        cov = self.kernels.motion_covariance_from_registration(reg, self.spec).cpu().numpy()[0].astype(np.float64)
        (c00, c01, c11) = state[1]
        ss_p, ss_r = self._steady_state_variances()
        s_p = math.sqrt(min(1.0, ss_p / c00))
        s_r = math.sqrt(min(1.0, ss_r / c11))
        att = np.array([[c00 * s_p * s_p, c01 * s_p * s_r], [c01 * s_p * s_r, c11 * s_r * s_r]])
        dx, k_r = motion[0], self._yaw_per_roll
        G = dx * np.array([[-self._scale_per_pitch, 0.0], [0.0, self.spec.centre[0] * k_r], [0.0, -k_r]])
        cov = cov + G @ att @ G.T
        cov[0, 0] += (self._shift_per_pitch_change * pull) ** 2
        return cov

__all__ = ["BevoOdometry", "OdometryStep", "InvalidInputError", "OutOfOrderError", "Counters", "EngineEvent", "Z_VARIANCE"]
