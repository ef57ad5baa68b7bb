"""bevo_node's own settings (the ROS wiring; the engine's are :class:`bevo_ros.config.BevoConfig`):
the dataclass, every parameter's description, and their declaration as ROS parameters.

``bevo dump-config`` prints them (no ROS needed to import this module).
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

from bevo_ros.config import (RENAMED, BevoConfig, ConfigError, coerce_setting, extrinsics_problem, resolve_path,
                             unknown_parameters)
from bevo_ros.io import bag
from bevo_ros.ros import parameters as ros_params


@dataclass
class NodeSettings:
    """Parameters of the ROS wiring (the engine's come from :class:`BevoConfig`)."""

    # relative names (REP-144 style): a namespace (__ns, launch) moves them all
    imu_topic: str = "imu/data"
    image_topic: str = "camera/image_rect"
    camera_info_topic: str = "camera/camera_info"
    use_camera_info: bool = True
    camera_info_use_p: bool = True
    odometry_topic: str = "bevo/odometry"
    set_pose_topic: str = "bevo/set_pose"
    speed_topic: str = ""
    speed_type: str = "odometry"
    speed_variance: float = 0.01
    path_topic: str = "bevo/path"
    bev_image_topic: str = "bevo/bev_image"
    bev_image_heatmap: bool = True
    odom_frame: str = "odom"
    base_frame: str = "base_link"
    publish_tf: bool = True
    path_max_length: int = 1000
    input_qos: str = "sensor_data"
    imu_qos_depth: int = 100
    image_qos_depth: int = 5
    output_qos_depth: int = 10
    image_wait: float = 0.2
    ordered_intake: bool = True
    max_pending_images: int = 20
    max_time_jump_back: float = 1.0
    max_time_jump_forward: float = 1.0
    time_jump_confirmations: int = 3
    diagnostics_period: float = 1.0
    log_throttle_period: float = 5.0
    latency_window: int = 1000
    torch_threads: int = 1
    # ---- the ROS graph (issue 11): calibration, extrinsics, input health, transports
    camera_info_timeout: float = 2.0
    undistort: str = "auto"
    extrinsics_from_tf: bool = True
    image_transport: str = "raw"
    imu_timeout: float = 1.0
    image_timeout: float = 2.0
    speed_timeout: float = 1.0
    sensor_late_factor: float = 5.0


# speed_type -> speed_topic's message type (the readable speeds, io.bag.SPEED_MSGS: Odometry, TwistStamped,
# TwistWithCovarianceStamped)
SPEED_TYPES = dict(zip(("odometry", "twist", "twist_with_covariance"), bag.SPEED_MSGS))

DESCRIPTIONS = {
    # node wiring
    "imu_topic": "sensor_msgs/Imu input topic",
    "image_topic": "sensor_msgs/Image input topic, relative (rectified: image_rect; mono8, rgb8/bgr8/rgba8/bgra8, "
                   "mono16, bayer_*, yuv422/uyvy accepted)",
    "camera_info_topic": "sensor_msgs/CameraInfo topic (read when use_camera_info is true)",
    "use_camera_info": "calibrate from CameraInfo (intrinsics, size, distortion); the camera.* parameters are "
                       "the fallback, used only if no CameraInfo arrives within camera_info_timeout",
    "camera_info_timeout": "seconds after the first image without CameraInfo before the camera.* parameters are "
                           "used instead (0: use them at once)",
    "undistort": "'auto' (undistort with OpenCV when CameraInfo D is non-zero and the topic is not image_rect*), "
                 "'on' (whenever D is non-zero) or 'off' (images are rectified)",
    "extrinsics_from_tf": "take base_frame -> camera frame and base_frame -> IMU frame from /tf_static when "
                          "published (camera.base_T_camera and an IMU aligned with base_frame otherwise)",
    "image_transport": "'raw' (sensor_msgs/Image on image_topic) or 'compressed' (sensor_msgs/CompressedImage "
                       "on <image_topic>/compressed, decoded with OpenCV)",
    "imu_timeout": "/diagnostics: IMU silent for longer than this (s) is an ERROR",
    "image_timeout": "/diagnostics: images silent for longer than this (s) are an ERROR",
    "speed_timeout": "/diagnostics: speed_topic silent for longer than this (s) is an ERROR of its input (the "
                     "odometry, which goes on on the images, a WARN)",
    "sensor_late_factor": "/diagnostics: an input is late (WARN) when silent for this many times its measured period",
    "camera_info_use_p": "use CameraInfo P[:3,:3] (rectified camera matrix) rather than K",
    "odometry_topic": "nav_msgs/Odometry output topic",
    "set_pose_topic": "geometry_msgs/PoseWithCovarianceStamped input (as robot_localization's set_pose): the vehicle's "
                      "pose in odom_frame at the header stamp (0: at the latest frame); x, y, z and yaw are set, the "
                      "attitude is measured; empty disables",
    "speed_topic": "a vehicle speed input the motion filter fuses each frame (wheel odometry, CAN, GNSS; empty "
                   "disables): in base_frame its linear.x (signed), in another frame its horizontal speed "
                   "(unsigned: the direction of travel from the images); the odometry's scale is then that "
                   "speed's, so calibrate it",
    "speed_type": "speed_topic's message type: 'odometry' (nav_msgs/Odometry), 'twist' (geometry_msgs/TwistStamped) "
                  "or 'twist_with_covariance' (geometry_msgs/TwistWithCovarianceStamped)",
    "speed_variance": "variance of speed_topic's speed, (m/s)^2, where the message's twist covariance has none",
    "path_topic": "nav_msgs/Path output topic (published only when subscribed)",
    "bev_image_topic": "sensor_msgs/Image mono8 BEV output (computed only when subscribed)",
    "bev_image_heatmap": "put the correlation heat-map beside the BEV when the engine provides it",
    "odom_frame": "frame_id of the odometry (the fixed odometry frame)",
    "base_frame": "child_frame_id of the odometry (the vehicle frame, REP-103 x forward z up)",
    "publish_tf": "broadcast odom_frame -> base_frame on /tf",
    "path_max_length": "poses kept in the path (oldest dropped first); 0 disables the path",
    "input_qos": "'sensor_data' (best effort, live sensors) or 'reliable' (bag replay: reliable keep-all, the "
                 "publisher held back rather than samples lost)",
    "imu_qos_depth": "history depth of the IMU subscription (sensor_data; keep-all with reliable)",
    "image_qos_depth": "history depth of the image (and CameraInfo) subscription (sensor_data; keep-all with reliable)",
    "output_qos_depth": "history depth of the odometry/path/BEV publishers",
    "image_wait": "seconds an image waits for IMU past its stamp before it is processed anyway",
    "ordered_intake": "take every IMU/image message already received and process them in stamp order "
                      "(offline order, IMU keeps up under load) instead of one per topic per executor turn; "
                      "IMU past the sample a frame waits for is held until the next image arrives (at most "
                      "image_wait), so a late image is processed as offline",
    "max_pending_images": "images waiting for IMU (or, before any calibration, for CameraInfo) beyond this are dropped "
                          "(oldest first, counted)",
    "max_time_jump_back": "a stamp earlier than the previous by more than this (s) is a time jump back: once "
                          "confirmed (time_jump_confirmations) it resets the odometry",
    "max_time_jump_forward": "a stamp later than the previous by more than this (s) is a time jump forward: held "
                             "until confirmed (time_jump_confirmations), else dropped as an outlier",
    "time_jump_confirmations": "messages on a new timeline needed to accept a time jump; a lone outlier stamp is "
                               "dropped (stamp_outlier) instead of resetting the odometry; 1 = accept at once",
    "diagnostics_period": "seconds between /diagnostics messages",
    "log_throttle_period": "seconds between two log lines of the same drop reason",
    "latency_window": "number of recent frames the latency percentiles cover",
    "torch_threads": "torch CPU threads of the node (1: the engine's small tensors gain nothing from more); 0 = torch's default",
    # engine (bevo_ros.config.BevoConfig)
    "camera.fx": "focal length x (px) of the rectified image (fallback when no CameraInfo arrives)",
    "camera.fy": "focal length y (px); 0 = from CameraInfo",
    "camera.cx": "principal point x (px)",
    "camera.cy": "principal point y (px)",
    "camera.width": "image width (px); images of another size are dropped",
    "camera.height_px": "image height (px)",
    "camera.mount_height": "camera centre height above the road (m)",
    "camera.base_T_camera": "camera optical frame pose in base_frame, 4x4 row-major (used when /tf_static has no "
                            "base_frame -> camera frame)",
    "bev.size": "BEV grid is size x size pixels",
    "bev.metres_per_pixel": "BEV ground sampling distance (m/px)",
    "bev.forward_offset": "distance from the base origin to the BEV near edge (m)",
    "filter.motion_model": "'euler' (exact Euler-angle kinematics) or 'additive' (the paper's)",
    "filter.road_tilt_time_constant": "low-pass time constant (s) separating road tilt from vehicle attitude; 0 disables",
    "filter.gyro_sampling": "fused mode: 'interval_mean' (each gyro sample is the mean rate since the previous one: "
                            "KITTI's OXTS, delta-angle IMUs) or 'instantaneous' (the rate at its stamp)",
    "filter.gyro_bias_std": "fused mode: the pitch and roll gyro's bias prior std (rad/s; ~0.1 deg/s for a calibrated "
                            "MEMS part), a bias state beside the DUKF observed by its accelerometer innovations "
                            "between stops; 0 = the stops alone; the learned file's gyro_bias (bevo train) takes its "
                            "place when it has one",
    "filter.gyro_bias_walk": "fused mode: that bias's random walk (rad/s/sqrt(s)); the learned file's gyro_bias "
                             "takes its place when it has one",
    "filter.turn_compensation": "subtract speed x yaw rate (centripetal) from the accelerometer before the DUKF update",
    "filter.max_imu_gap": "longest IMU gap (s) the filter predicts across; longer gaps re-initialise it",
    "filter.mounting_pitch": "static pitch (rad, nose down +) of the base relative to a level road (rig calibration; only with the road-tilt low-pass on)",
    "filter.mounting_roll": "static roll (rad, left side up +) of the base relative to a level road (rig calibration; only with the road-tilt low-pass on)",
    "filter.mounting_reference": "'base' (mounting_pitch/roll are the base's attitude on the road, whatever the "
                                 "extrinsics) or 'camera' (they were calibrated through camera.base_T_camera: with "
                                 "extrinsics from /tf_static that differ, the camera's tilt to the road they make is kept)",
    "filter.max_acceleration": "IMU samples whose specific-force norm exceeds this (m/s^2) are dropped (imu_accel_range)",
    "filter.max_angular_rate": "IMU samples with a gyro axis above this (rad/s) are dropped (imu_gyro_range)",
    "odometry.standstill_max_speed": "fused mode: below this speed (m/s, the small motion over a frame interval read on "
                                     "the raw images when the correlation reads under 0.15 m) the vehicle is at rest: zero "
                                     "motion, the gyro's biases observed; 0 disables",
    "odometry.direction_lock": "fused mode: forward from the start, the direction of travel changes only at a stop the "
                               "images confirm, and the correlation's peak is taken in it (the car ahead pulling away "
                               "reads as reversing); false for a vehicle that reverses without a confirmed stop",
    "learned_params_file": "learned O/Q YAML; a relative path resolves beside the parameters file that set it, "
                           "then the package share",
    "device": "'cpu' or 'cuda' (falls back to CPU with a warning)",
    "kernels": "'eager' (default), 'compiled' (torch.compile; first frames compile) or 'auto' (compiled when a C++ "
               "compiler is found)",
}


def validate(s: NodeSettings) -> None:
    """ConfigError naming the first parameter out of its range."""
    if s.input_qos not in ("sensor_data", "reliable"):
        raise ConfigError(f"parameter 'input_qos' must be 'sensor_data' or 'reliable', got {s.input_qos!r}")
    for name in ("imu_qos_depth", "image_qos_depth", "output_qos_depth", "max_pending_images", "latency_window",
                 "time_jump_confirmations"):
        if getattr(s, name) < 1:
            raise ConfigError(f"parameter '{name}' must be >= 1, got {getattr(s, name)}")
    if s.speed_type not in SPEED_TYPES:
        raise ConfigError(f"parameter 'speed_type' must be one of {', '.join(SPEED_TYPES)}, got {s.speed_type!r}")
    for name in ("image_wait", "max_time_jump_back", "max_time_jump_forward", "diagnostics_period", "speed_variance"):
        if getattr(s, name) <= 0:
            raise ConfigError(f"parameter '{name}' must be > 0, got {getattr(s, name)}")
    for name in ("path_max_length", "torch_threads"):
        if getattr(s, name) < 0:
            raise ConfigError(f"parameter '{name}' must be >= 0, got {getattr(s, name)}")
    for name in ("odom_frame", "base_frame", "imu_topic", "image_topic", "odometry_topic"):
        if not getattr(s, name):
            raise ConfigError(f"parameter '{name}' must not be empty")
    for name in ("odom_frame", "base_frame"):
        if getattr(s, name).startswith("/"):  # tf2 refuses such frame ids (and set_pose compared them stripped)
            raise ConfigError(f"parameter '{name}' = {getattr(s, name)!r}: a frame id must not start with '/'")
    if s.odom_frame == s.base_frame:
        raise ConfigError(f"parameters 'odom_frame' and 'base_frame' are both {s.odom_frame!r}: the odometry is the "
                          "transform between two frames")


def settings_from_flat(flat: dict[str, Any]) -> NodeSettings:
    """The node's own settings from flat parameters (a parameters file's, or those declared), each
    coerced to its field's type; the default where ``flat`` has none. ConfigError when one is unusable."""
    base = NodeSettings()
    return NodeSettings(**{f.name: coerce_setting(flat[f.name], getattr(base, f.name), f.name) if f.name in flat
                           else getattr(base, f.name) for f in dataclasses.fields(NodeSettings)})


def defaults() -> dict[str, Any]:
    """Every parameter of the node with its default: NodeSettings' fields, then BevoConfig's flat keys."""
    flat = {f.name: getattr(NodeSettings(), f.name) for f in dataclasses.fields(NodeSettings)}
    flat.update(BevoConfig().to_flat())
    return flat


def declare(node, node_name: str) -> tuple[NodeSettings, BevoConfig]:
    """Declare one parameter per NodeSettings field and per flat BevoConfig key (descriptors with
    ranges, read_only for what is fixed at start) and read them; ConfigError when one is unusable."""
    from rcl_interfaces.msg import ParameterDescriptor
    from rclpy.exceptions import InvalidParameterTypeException, InvalidParameterValueException

    flat: dict[str, Any] = {}
    names = defaults()
    for name, default in names.items():
        desc = ros_params.descriptor(name, default, DESCRIPTIONS.get(name, "engine setting, see params/kitti.yaml"))
        try:
            flat[name] = node.declare_parameter(name, default, desc).value
        except (InvalidParameterValueException, InvalidParameterTypeException) as exc:
            raise ConfigError(f"parameter '{name}': {exc}") from None
    for old, new in RENAMED.items():  # old names still read (BevoConfig.from_flat warns)
        value = node.declare_parameter(old, None, ParameterDescriptor(  # read at start only, as its new name
            description=f"deprecated: renamed {new} [read-only: fixed at start]", dynamic_typing=True,
            read_only=True)).value
        if value is not None:
            flat[old] = value
    settings = settings_from_flat(flat)
    validate(settings)
    config = BevoConfig.from_flat(flat, source=f"{node_name} parameters", warn=node.get_logger().warning)
    if (why := extrinsics_problem(config.camera.base_T_camera)) is not None:  # else no odometry, only drops
        raise ConfigError(f"parameter 'camera.base_T_camera' is no rigid transform: {why}")
    config_flat = config.to_flat()
    for name in names:
        why = ros_params.check(name, getattr(settings, name) if hasattr(settings, name) else config_flat.get(name))
        if why:
            raise ConfigError(why)
    # A parameter the node does not have (a typo in a parameters file) would be ignored without a word
    # by ROS: named here (rclpy keeps a node's overrides, files and -p alike, in _parameter_overrides).
    overrides = getattr(node, "_parameter_overrides", None)
    if isinstance(overrides, dict):
        unknown = unknown_parameters(overrides, names)
        if unknown:
            node.get_logger().warning(f"parameter(s) that {node_name} does not have, ignored: {', '.join(unknown)}")
    return settings, config


def learned_params_path(config: BevoConfig, params_file: str | list[str] | None, fq_node_name: str) -> Path:
    """``learned_params_file`` resolved beside the parameters file that set it (``params_file``: the
    one file, or every ``--params-file`` of the command line in order), then the package share."""
    if isinstance(params_file, (list, tuple)):
        params_file = ros_params.params_file_setting([a for f in params_file for a in ("--params-file", f)],
                                                     "learned_params_file", fq_node_name)
    base_dir = Path(params_file).resolve().parent if params_file else None
    return resolve_path(config.learned_params_file, base_dir)


def live_value(name: str, value: Any) -> Any:
    """A live parameter's new value, coerced to its setting's type; ConfigError when unusable."""
    value = coerce_setting(value, defaults()[name], name)
    why = ros_params.check(name, value)
    if why:
        raise ConfigError(why)
    return value


def check_live(params: list):
    """The node's on-set-parameters callback: validates ``ros2 param set`` of the live parameters
    (rclpy refuses read-only ones itself, with the reason)."""
    from rcl_interfaces.msg import SetParametersResult

    for p in params:
        if p.name in ros_params.LIVE:
            try:
                live_value(p.name, p.value)
            except ConfigError as exc:
                return SetParametersResult(successful=False, reason=str(exc))
    return SetParametersResult(successful=True)


def input_qos(s: NodeSettings) -> Callable[[int], Any]:
    """``depth -> QoSProfile`` of the inputs: ``input_qos`` 'sensor_data' (best effort, as
    qos_profile_sensor_data, keep-last ``depth``) or 'reliable' (bag replay: reliable keep-all, so a
    player that outruns the node is held back by DDS instead of its oldest samples being replaced:
    keep-last 1000 / 50 lost 85 of 201 frames, silently, at --rate 30)."""
    from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy, qos_profile_sensor_data

    def profile(depth: int) -> QoSProfile:
        if s.input_qos == "reliable":
            return QoSProfile(history=HistoryPolicy.KEEP_ALL, reliability=ReliabilityPolicy.RELIABLE)
        return QoSProfile(**{k: getattr(qos_profile_sensor_data, k) for k in ("history", "reliability", "durability")},
                          depth=depth)

    return profile


__all__ = ["NodeSettings", "DESCRIPTIONS", "validate", "settings_from_flat", "defaults", "declare", "learned_params_path", "live_value", "check_live",
           "input_qos"]
