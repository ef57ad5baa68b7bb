"""``bevo_node``: the thin rclpy layer around :class:`bevo_ros.core.odometry.BevoOdometry`.

    ros2 run bevo_ros bevo_node --ros-args --params-file params/kitti.yaml

Subscribes (relative topic names) to IMU, images (raw or compressed) and CameraInfo, and reads
the rig from /tf_static (bevo_ros.ros: calibration, extrinsics, per-input diagnostics, parameter
descriptors); runs the DUKF on every IMU message and
BEV + phase correlation on every frame through the same engine the offline tools use; publishes
nav_msgs/Odometry (header stamp = the image's stamp), a bounded nav_msgs/Path, a BEV image (only
when subscribed), TF ``odom -> base_link`` and ``/diagnostics``. Every parameter is documented in
``params/kitti.yaml``. Bad input is dropped, counted (``/diagnostics``) and logged (throttled per
reason); no callback exception can kill the node. A missing or malformed learned-parameters file,
or an unusable configuration, stops the node at start with one log line and exit code 2.
"""
from __future__ import annotations

import collections
import dataclasses
import math
import sys
import time
import traceback
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

import numpy as np
from rclpy.node import Node

from bevo_ros.config import (BevoConfig, ConfigError, build_odometry, camera_model, coerce_setting, load_learned_params,
                             resolve_path)
from bevo_ros.core.device import resolve_device
from bevo_ros.core.validation import TimeJumpGuard, intrinsics_problem
from bevo_ros.ros import parameters as ros_params
from bevo_ros.ros.camera import (Calibration, CalibrationError, calibration_from_camera_info,
                                 calibration_from_parameters, same_camera_info)
from bevo_ros.ros.diagnostics import SensorMonitor, status_message
from bevo_ros.ros.tf import StaticTransforms
from bevo_ros.ros_conversions import (ImageConversionError, bev_to_mono8,
                                      gray_to_image_msg, heatmap_to_mono8, image_to_gray, imu_to_arrays,
                                      odometry_msg, pose_stamped_from_odometry, stamp_to_sec,
                                      transform_from_odometry)

NODE_NAME = "bevo_node"
EXIT_CONFIG_ERROR = 2


# ------------------------------------------------------------------------------------ parameters
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
    sensor_late_factor: float = 5.0


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
    "sensor_late_factor": "/diagnostics: an input is late (WARN) when silent for this many times its measured period",
    "camera_info_use_p": "use CameraInfo P[:3,:3] (rectified camera matrix) rather than K",
    "odometry_topic": "nav_msgs/Odometry output topic",
    "path_topic": "nav_msgs/Path output topic (published only when subscribed)",
    "bev_image_topic": "sensor_msgs/Image mono8 BEV output (computed only when subscribed)",
    "bev_image_heatmap": "put the correlation heat-map beside the BEV when the engine provides it",
    "odom_frame": "frame_id of the odometry (the fixed odometry frame)",
    "base_frame": "child_frame_id of the odometry (the vehicle frame, REP-103 x forward z up)",
    "publish_tf": "broadcast odom_frame -> base_frame on /tf",
    "path_max_length": "poses kept in the path (oldest dropped first); 0 disables the path",
    "input_qos": "'sensor_data' (best effort, live sensors) or 'reliable' (bag replay)",
    "imu_qos_depth": "history depth of the IMU subscription",
    "image_qos_depth": "history depth of the image (and CameraInfo) subscription",
    "output_qos_depth": "history depth of the odometry/path/BEV publishers",
    "image_wait": "seconds an image waits for IMU past its stamp before it is processed anyway",
    "ordered_intake": "take every IMU/image message already received and process them in stamp order "
                      "(offline order, IMU keeps up under load) instead of one per topic per executor turn",
    "max_pending_images": "images waiting for IMU beyond this are dropped (oldest first, counted)",
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
    "camera.height": "camera centre height above the road (m)",
    "camera.base_T_camera": "camera optical frame pose in base_frame, 4x4 row-major (used when /tf_static has no "
                            "base_frame -> camera frame)",
    "bev.size": "BEV grid is size x size pixels",
    "bev.metres_per_pixel": "BEV ground sampling distance (m/px)",
    "bev.forward_offset": "distance from the base origin to the BEV near edge (m)",
    "filter.motion_model": "'euler' (exact Euler-angle kinematics) or 'additive' (the paper's)",
    "filter.road_tilt_time_constant": "low-pass time constant (s) separating road tilt from vehicle attitude; 0 disables",
    "filter.turn_compensation": "subtract speed x yaw rate (centripetal) from the accelerometer before the DUKF update",
    "filter.max_imu_gap": "longest IMU gap (s) the filter predicts across; longer gaps re-initialise it",
    "filter.mounting_pitch": "static pitch (rad, nose down +) of the base relative to a level road (rig calibration; only with the road-tilt low-pass on)",
    "filter.mounting_roll": "static roll (rad, left side up +) of the base relative to a level road (rig calibration; only with the road-tilt low-pass on)",
    "filter.max_acceleration": "IMU samples whose specific-force norm exceeds this (m/s^2) are dropped (imu_accel_range)",
    "filter.max_angular_rate": "IMU samples with a gyro axis above this (rad/s) are dropped (imu_gyro_range)",
    "learned_params_file": "learned O/Q YAML; a relative path resolves beside the parameters file that set it, "
                           "then the package share",
    "device": "'cpu' or 'cuda' (falls back to CPU with a warning)",
}


def _validate(s: NodeSettings) -> None:
    if s.input_qos not in ("sensor_data", "reliable"):
        raise ConfigError(f"parameter 'input_qos' must be 'sensor_data' or 'reliable', got {s.input_qos!r}")
    for name in ("imu_qos_depth", "image_qos_depth", "output_qos_depth", "max_pending_images", "latency_window",
                 "time_jump_confirmations"):
        if getattr(s, name) < 1:
            raise ConfigError(f"parameter '{name}' must be >= 1, got {getattr(s, name)}")
    for name in ("image_wait", "max_time_jump_back", "max_time_jump_forward", "diagnostics_period"):
        if getattr(s, name) <= 0:
            raise ConfigError(f"parameter '{name}' must be > 0, got {getattr(s, name)}")
    for name in ("path_max_length", "torch_threads"):
        if getattr(s, name) < 0:
            raise ConfigError(f"parameter '{name}' must be >= 0, got {getattr(s, name)}")
    for name in ("odom_frame", "base_frame", "imu_topic", "image_topic", "odometry_topic"):
        if not getattr(s, name):
            raise ConfigError(f"parameter '{name}' must not be empty")


def _tf_backend(node) -> tuple[str, Callable[[Any], None] | None]:
    """``(name, send(TransformStamped))``: tf2_ros when installed, else our own /tf publisher."""
    try:
        from tf2_ros import TransformBroadcaster  # full ROS 2 install
    except ImportError:
        pass
    else:
        broadcaster = TransformBroadcaster(node)
        return "tf2_ros", broadcaster.sendTransform
    try:
        from tf2_msgs.msg import TFMessage  # built by tools/build_tf2_msgs.sh (make setup)
    except ImportError:
        return "none", None
    from rclpy.qos import QoSProfile

    pub = node.create_publisher(TFMessage, "/tf", QoSProfile(depth=100))  # tf2_ros's broadcaster QoS

    def send(transform) -> None:
        pub.publish(TFMessage(transforms=[transform]))

    return "tf2_msgs", send


# ------------------------------------------------------------------------------------ the node
class BevoNode(Node):
    """See the module docstring. ``engine_factory(config, learned, camera)`` is for tests."""

    def __init__(self, params_file: str | list[str] | None = None, engine_factory: Callable | None = None,
                 node_name: str = NODE_NAME, **node_kwargs) -> None:
        super().__init__(node_name, **node_kwargs)
        try:
            self._setup(params_file, engine_factory, node_name)
        except BaseException:
            self.destroy_node()  # a node that refuses to start leaves nothing behind in the context
            raise

    def _setup(self, params_file: str | list[str] | None, engine_factory: Callable | None, node_name: str) -> None:
        from rclpy.clock import Clock, ClockType
        from rclpy.exceptions import InvalidParameterTypeException, InvalidParameterValueException

        self._engine_factory = engine_factory or build_odometry
        self._steady = Clock(clock_type=ClockType.STEADY_TIME)

        # ---- parameters: one per NodeSettings field and per flat BevoConfig key (bevo_ros.ros.parameters:
        # ranges, read_only for what is fixed at start, live ones applied by _on_parameters_set)
        flat_defaults = {f.name: getattr(NodeSettings(), f.name) for f in dataclasses.fields(NodeSettings)}
        flat_defaults.update(BevoConfig().to_flat())
        self._flat_defaults = flat_defaults
        flat: dict[str, Any] = {}
        for name, default in flat_defaults.items():
            desc = ros_params.descriptor(name, default, DESCRIPTIONS.get(name, "engine setting, see params/kitti.yaml"))
            try:
                flat[name] = self.declare_parameter(name, default, desc).value
            except (InvalidParameterValueException, InvalidParameterTypeException) as exc:
                raise ConfigError(f"parameter '{name}': {exc}") from None
        self.settings = NodeSettings(**{f.name: coerce_setting(flat[f.name], getattr(NodeSettings(), f.name), f.name)
                                        for f in dataclasses.fields(NodeSettings)})
        _validate(self.settings)
        self.config = BevoConfig.from_flat(flat, source=f"{node_name} parameters")
        config_flat = self.config.to_flat()
        for name in flat_defaults:
            why = ros_params.check(name, getattr(self.settings, name) if hasattr(self.settings, name)
                                   else config_flat.get(name))
            if why:
                raise ConfigError(why)
        if isinstance(params_file, (list, tuple)):  # all --params-file of the command line, in order
            params_file = ros_params.params_file_setting(
                [a for f in params_file for a in ("--params-file", f)], "learned_params_file",
                self.get_fully_qualified_name())
        base_dir = Path(params_file).resolve().parent if params_file else None
        self.learned_path = resolve_path(self.config.learned_params_file, base_dir)
        self.learned = load_learned_params(self.learned_path)  # ConfigError: refuse to start
        self.config.learned_params_file = str(self.learned_path)
        s = self.settings

        import torch

        if s.torch_threads > 0:
            torch.set_num_threads(s.torch_threads)
        try:  # the one CUDA fallback rule, logged (build_odometry applies it again for the engine)
            resolve_device(self.config.device, log=self.get_logger().warning)
        except ValueError as exc:
            raise ConfigError(f"parameter 'device': {exc}") from None

        # ---- state
        self.engine = None
        self.camera = None
        self.drops: collections.Counter[str] = collections.Counter()
        self.events: collections.Counter[str] = collections.Counter()
        self.log_history: collections.deque[tuple[str, str]] = collections.deque(maxlen=200)
        self._throttle: dict[str, list[float]] = {}
        self.counts = collections.Counter()  # imu_in, images_in, odometry_out, camera_info_in
        self._latency: collections.deque[float] = collections.deque(maxlen=s.latency_window)
        self._quality: collections.deque[float] = collections.deque(maxlen=100)
        self._last_imu_stamp: float | None = None
        self._last_gap = 0.0
        self._path = collections.deque(maxlen=max(1, s.path_max_length))
        self._last_diag = (time.monotonic(), collections.Counter())
        self._time_guards = {kind: TimeJumpGuard(s.max_time_jump_back, s.max_time_jump_forward,
                                                 s.time_jump_confirmations) for kind in ("imu", "image")}
        self._image_size: tuple[int, int] | None = None  # (width, height) of the last decoded image

        # calibration: CameraInfo first, the camera.* parameters as the fallback (see _on_image)
        self.calibration: Calibration | None = None
        self._first_image_wait: float | None = None  # steady time of the first image seen without calibration
        self._camera_frame = ""  # header.frame_id of the images (for /tf_static)
        self._imu_frame_warned: set[str] = set()
        self._R_base_imu: dict[str, tuple[int, np.ndarray | None]] = {}  # IMU frame -> (tf version, R_base_imu)
        self._extrinsics_source = "parameters camera.base_T_camera"
        self._tf_version = -1  # /tf_static tree version the camera was built with
        self.static_tf: StaticTransforms | None = None  # made with the interfaces below
        self._imu_backlog: collections.deque = collections.deque(maxlen=max(s.imu_qos_depth, 1000))
        self._info_sub = None
        monotonic = time.monotonic
        self.monitors = {"imu": SensorMonitor("IMU", self.resolve_topic_name(s.imu_topic), s.imu_timeout,
                                              s.sensor_late_factor, clock=monotonic),
                         "image": SensorMonitor("images", self.resolve_topic_name(s.image_topic), s.image_timeout,
                                                s.sensor_late_factor, clock=monotonic)}
        if not s.use_camera_info:
            if not self.config.camera.has_intrinsics():
                raise ConfigError("camera intrinsics are not set (camera.fx, fy, cx, cy, width, height_px) and "
                                  "use_camera_info is false: set them or enable use_camera_info")
            self._apply_calibration(calibration_from_parameters(self.config.camera))
        elif s.camera_info_timeout == 0 and self.config.camera.has_intrinsics():
            self._apply_calibration(calibration_from_parameters(self.config.camera))

        # ---- interfaces
        from diagnostic_msgs.msg import DiagnosticArray
        from nav_msgs.msg import Odometry, Path as PathMsg
        from rclpy.qos import QoSProfile, ReliabilityPolicy, qos_profile_sensor_data
        from sensor_msgs.msg import CameraInfo, Image, Imu
        from std_srvs.srv import Trigger

        def in_qos(depth: int) -> QoSProfile:
            if s.input_qos == "reliable":
                return QoSProfile(depth=depth, reliability=ReliabilityPolicy.RELIABLE)
            q = QoSProfile(**{k: getattr(qos_profile_sensor_data, k) for k in ("history", "reliability", "durability")},
                           depth=depth)
            return q

        self.odom_pub = self.create_publisher(Odometry, s.odometry_topic, s.output_qos_depth)
        self.path_pub = self.create_publisher(PathMsg, s.path_topic, s.output_qos_depth)  # path_max_length is live
        self.bev_pub = self.create_publisher(Image, s.bev_image_topic, s.output_qos_depth)
        self.diag_pub = self.create_publisher(DiagnosticArray, "/diagnostics", 10)
        self.tf_backend, self._send_tf = ("disabled", None)
        self._tf_made = None  # (backend, send) once created (publish_tf is live)
        if s.publish_tf:
            self._tf_made = self.tf_backend, self._send_tf = _tf_backend(self)
            if self._send_tf is None:  # said once, here
                self._log("tf_unavailable",
                          "publish_tf is true but neither tf2_ros nor tf2_msgs is available: TF is DISABLED "
                          "(odometry is still published; run `make setup` to build tf2_msgs, or install "
                          "ROS 2 tf2_ros)")
        self._handle_imu = self._guard("imu", self._on_imu)
        self._handle_image = self._guard("image", self._on_image)
        imu_intake = self._guard("imu", self._imu_received)
        image_intake = self._guard("image", self._image_received)
        # two-argument callbacks: rclpy then passes the message info (DDS reception time)
        self._imu_sub = self.create_subscription(Imu, s.imu_topic, lambda msg, info: imu_intake(msg, info),
                                                 in_qos(s.imu_qos_depth))
        if s.image_transport == "compressed":  # image_transport's naming: <base topic>/compressed
            from sensor_msgs.msg import CompressedImage

            self.image_input_topic, image_type = s.image_topic.rstrip("/") + "/compressed", CompressedImage
        else:
            self.image_input_topic, image_type = s.image_topic, Image
        self.monitors["image"].topic = self.resolve_topic_name(self.image_input_topic)
        self._image_sub = self.create_subscription(image_type, self.image_input_topic,
                                                   lambda msg, info: image_intake(msg, info), in_qos(s.image_qos_depth))
        if s.use_camera_info:
            self._info_sub = self.create_subscription(CameraInfo, s.camera_info_topic,
                                                      self._guard("camera_info", self._on_camera_info),
                                                      in_qos(s.image_qos_depth))
        self.static_tf = StaticTransforms(self) if s.extrinsics_from_tf else None
        self.add_on_set_parameters_callback(self._guard("parameters", self._on_parameters_set))
        self.add_post_set_parameters_callback(self._guard("parameters", self._on_parameters_applied))
        self.create_service(Trigger, "~/reset", self._guard("reset", self._on_reset))
        # Steady-clock timers: they tick with or without /clock (use_sim_time).
        self.create_timer(min(0.05, s.image_wait / 2), self._guard("flush_timer", self._on_flush_timer),
                          clock=self._steady)
        self.create_timer(s.diagnostics_period, self._guard("diagnostics", self._publish_diagnostics),
                          clock=self._steady)
        self._install_clock_jump_handler()

        cam = (self.calibration.describe() if self.calibration is not None else
               f"from CameraInfo on {self.resolve_topic_name(s.camera_info_topic)} (camera.* parameters after "
               f"{s.camera_info_timeout:g} s without it)")
        self.get_logger().info(
            f"ready: imu={self.resolve_topic_name(s.imu_topic)} image={self.resolve_topic_name(self.image_input_topic)} "
            f"({s.input_qos}) -> {self.resolve_topic_name(s.odometry_topic)}, camera {cam}, "
            f"extrinsics {'from /tf_static when published (' + self.static_tf.backend + ')' if self.static_tf else 'parameters'}, "
            f"BEV {self.config.bev.size}px x {self.config.bev.metres_per_pixel} m, "
            f"learned={self.learned_path}, tf={self.tf_backend}")

    # ------------------------------------------------------------------ helpers
    def _guard(self, name: str, fn: Callable) -> Callable:
        """Wrap a callback: an unexpected exception is logged (throttled) and counted, never raised."""

        def wrapped(*args):
            try:
                return fn(*args)
            except Exception as exc:  # noqa: BLE001 - the node must survive anything
                if not self.context.ok():
                    return None  # shutting down (SIGINT): publishers are gone, nothing to report
                self._drop("callback_error", f"unexpected {type(exc).__name__} in the {name} callback: {exc}\n"
                                             f"{traceback.format_exc()}", level="error")
                if name == "reset" and len(args) == 2:  # a service must still answer
                    response = args[1]
                    response.success, response.message = False, f"{type(exc).__name__}: {exc}"
                    return response
                return None

        return wrapped

    def _log(self, key: str, text: str, level: str = "warning") -> None:
        """Log ``text``, at most once per ``log_throttle_period`` per ``key`` (then with a count)."""
        self.log_history.append((key, text))
        now = time.monotonic()
        state = self._throttle.setdefault(key, [-math.inf, 0])
        if now - state[0] < self.settings.log_throttle_period:
            state[1] += 1
            return
        if state[1]:
            text += f" ({state[1]} more since the last report)"
        state[0], state[1] = now, 0
        logger = self.get_logger()
        # rclpy pins one severity per call site: one call per level.
        if level == "error":
            logger.error(text)
        elif level == "info":
            logger.info(text)
        else:
            logger.warning(text)

    def _drop(self, reason: str, text: str, level: str = "warning") -> None:
        self.drops[reason] += 1
        self._log(reason, f"dropped ({reason}): {text}", level)

    # ------------------------------------------------------------------ calibration and extrinsics
    def _apply_calibration(self, calib: Calibration) -> None:
        """Use ``calib`` from now on; the log says where it came from."""
        self.calibration = calib
        self.get_logger().info(f"camera calibration from {calib.describe()}")
        self._refresh_camera(force=True)

    def _camera_extrinsics(self) -> tuple[np.ndarray, str]:
        """``(base_T_camera (4, 4), source)``: /tf_static ``base_frame -> image frame`` when known."""
        base = self.settings.base_frame
        if self.static_tf is not None and self._camera_frame:
            T = self.static_tf.lookup(base, self._camera_frame)
            if T is not None:
                return T, f"/tf_static {base} -> {self._camera_frame}"
        return np.asarray(self.config.camera.base_T_camera, dtype=np.float64).reshape(4, 4), \
            "parameters camera.base_T_camera"

    def _refresh_camera(self, force: bool = False) -> None:
        """(Re)build the camera model when the calibration or the camera's static TF changed."""
        if self.calibration is None:
            return
        T, source = self._camera_extrinsics()
        old = getattr(self, "_base_T_camera", None)
        if not force and old is not None and np.allclose(old, T, rtol=0, atol=1e-9):
            return
        calib = self.calibration
        settings = dataclasses.replace(self.config.camera, base_T_camera=T.reshape(-1).tolist())
        try:
            camera = camera_model(settings, K=calib.K, width=calib.width, height_px=calib.height)
        except ConfigError as exc:  # e.g. a non-rigid transform on /tf_static
            self._drop("bad_extrinsics", f"camera extrinsics from {source} unusable: {exc}", level="error")
            return
        if source != self._extrinsics_source or (old is not None and not np.allclose(old, T, rtol=0, atol=1e-9)):
            self.get_logger().info(f"camera extrinsics from {source}: camera at "
                                   f"{np.round(T[:3, 3], 3).tolist()} m in {self.settings.base_frame}")
        self._base_T_camera, self._extrinsics_source = T, source
        self._set_camera(camera)

    def _imu_rotation(self, frame: str) -> np.ndarray | None:
        """Rotation taking vectors from the IMU's ``frame`` into ``base_frame`` (None: same axes)."""
        base = self.settings.base_frame
        frame = frame.lstrip("/")
        if not frame or frame == base.lstrip("/"):
            return None
        cached = self._R_base_imu.get(frame)
        version = 0
        if self.static_tf is not None:
            if cached is None or cached[1] is None:
                self.static_tf.poll()  # still unknown: a /tf_static already received counts now
            version = self.static_tf.version
        if cached is not None and cached[0] == version:
            return cached[1]
        T = self.static_tf.lookup(base, frame) if self.static_tf is not None else None
        R = None if T is None else T[:3, :3].copy()
        self._R_base_imu[frame] = (version, R)
        if R is not None:
            if cached is None or cached[1] is None or not np.allclose(cached[1], R, rtol=0, atol=1e-12):
                self.get_logger().info(f"IMU frame '{frame}': rates and accelerations rotated into '{base}' "
                                       f"(/tf_static), rotation {np.round(R, 4).tolist()}")
        elif frame not in self._imu_frame_warned:
            self._imu_frame_warned.add(frame)
            self._log("imu_frame", f"IMU frame '{frame}' is not base_frame '{base}' and /tf_static has no "
                                   f"{base} -> {frame}: the IMU axes are taken as the base axes (REP-103 x "
                                   "forward, y left, z up)")
        return R

    def _await_calibration(self) -> None:
        """No camera yet: read a CameraInfo already queued, else fall back to the parameters after
        ``camera_info_timeout`` seconds since the first image."""
        s = self.settings
        if self._info_sub is not None:
            for msg, _ in self._take_all(self._info_sub):
                self._on_camera_info(msg)
        if self.engine is not None:
            return
        now = time.monotonic()
        if self._first_image_wait is None:
            self._first_image_wait = now
        if s.use_camera_info and now - self._first_image_wait >= s.camera_info_timeout and \
                self.config.camera.has_intrinsics():
            self.events["camera_info_timeout"] += 1
            self.get_logger().warning(
                f"no CameraInfo on {self.resolve_topic_name(s.camera_info_topic)} within camera_info_timeout="
                f"{s.camera_info_timeout:g} s of the first image: using the camera.* parameters (a CameraInfo "
                "arriving later replaces them)")
            self._apply_calibration(calibration_from_parameters(self.config.camera))

    def _set_camera(self, camera) -> None:
        self.camera = camera
        if self.engine is None:
            self.engine = self._engine_factory(self.config, self.learned, camera)
            if hasattr(self.engine, "max_pending_images"):
                self.engine.max_pending_images = self.settings.max_pending_images
            backlog, self._imu_backlog = list(self._imu_backlog), collections.deque(maxlen=self._imu_backlog.maxlen)
            for t, gyro, accel in backlog:  # IMU that arrived before the calibration, in order
                steps = self._engine_call("imu", t, lambda: self.engine.add_imu(t, gyro, accel))
                if steps is not None:
                    self._last_imu_stamp = t
        else:
            self.engine.set_camera(camera)

    # fused mode: frames whose measurement the motion filter rejected (the pose is carried by its
    # prediction, the odometry still published): events, not drops
    _ENGINE_REJECTIONS = (
        ("rejected_textureless", "a correlation peak below odometry.min_quality (black, covered or textureless frame)"),
        ("rejected_translation", "a forward motion beyond the odometry.gate Mahalanobis gate"),
        ("rejected_rotation", "an image rotation disagreeing with the gyro beyond the odometry.gate"),
    )
    # engine counter -> node drop reason, and why (formatted with the node settings as ``s``)
    _ENGINE_DROPS = (
        ("dropped_no_imu", "no_imu", "with no IMU sample at or before their stamp (frames before any IMU)"),
        ("dropped_pending_overflow", "pending_overflow",
         "more than max_pending_images={s.max_pending_images} images were waiting for IMU"),
        ("dropped_invalid_bev", "invalid_bev",
         "whose BEV had no valid pixel (pitch/roll put the ground patch out of the image)"),
    )

    def _report_engine_events(self) -> None:
        """Turn what the engine dropped or rejected (its events) into counted, logged node drops/events."""
        d = collections.Counter(e.kind for e in self.engine.take_events()) if self.engine is not None else {}
        if not d:
            return
        for counter, reason, why in self._ENGINE_DROPS:
            if d.get(counter, 0) > 0:
                self.drops[reason] += d[counter]
                self._log(reason, f"dropped ({reason}): {d[counter]} image(s) " + why.format(s=self.settings))
        for counter, why in self._ENGINE_REJECTIONS:
            if d.get(counter, 0) > 0:
                self.events[counter] += d[counter]
                self._log(counter, f"{d[counter]} frame(s) with {why}: carried by the motion filter's prediction")
        if d.get("imu_gaps", 0) > 0:
            self.events["imu_gap"] += d["imu_gaps"]
            self._log("imu_gap", f"IMU gap longer than filter.max_imu_gap={self.config.filter.max_imu_gap} s "
                                 f"(last gap {self._last_gap:.3f} s): the DUKF re-initialised its pitch/roll "
                                 "from the accelerometer")

    def _out_of_order(self, kind: str, exc, stamp: float, retry: Callable[[], list]) -> list | None:
        """A stamp not after the previous one: a big jump back resets and retries, else a drop (None)."""
        jump = float(getattr(exc, "jump", 0.0))
        if jump > self.settings.max_time_jump_back:
            self.events["time_jump_reset"] += 1
            self._log(
                "time_jump_reset", f"{'IMU' if kind == 'imu' else kind} stamp {stamp:.6f} is {jump:.3f} s before the previous one (> max_time_jump_back="
                f"{self.settings.max_time_jump_back} s): time jumped back (bag restarted?) - resetting the "
                "odometry; the trajectory restarts at identity")
            self._reset()
            return retry()
        reason = f"{kind}_duplicate" if jump == 0 else f"{kind}_out_of_order"
        label = "IMU" if kind == "imu" else kind
        self._drop(reason, f"{label} stamp {stamp:.9f} is not after the previous {label} stamp "
                           f"{float(getattr(exc, 'last', stamp)):.9f} ({jump * 1e3:.3f} ms back)")
        return None

    def _reset(self) -> None:
        if self.engine is not None:
            self.engine.reset()
        self._path.clear()
        self._imu_backlog.clear()
        self._last_imu_stamp = None
        self.events["reset"] += 1

    # ------------------------------------------------------------------ live parameters
    def _on_parameters_set(self, params: list):
        """Validate ``ros2 param set`` (read-only ones are refused by rclpy with the reason)."""
        from rcl_interfaces.msg import SetParametersResult

        for p in params:
            if p.name not in ros_params.LIVE:
                continue
            try:
                value = coerce_setting(p.value, self._flat_defaults[p.name], p.name)
            except ConfigError as exc:
                return SetParametersResult(successful=False, reason=str(exc))
            why = ros_params.check(p.name, value)
            if why:
                return SetParametersResult(successful=False, reason=why)
        return SetParametersResult(successful=True)

    def _on_parameters_applied(self, params: list) -> None:
        """Apply live parameters (validated by :meth:`_on_parameters_set`)."""
        s = self.settings
        for p in params:
            if p.name not in ros_params.LIVE:
                continue
            value = coerce_setting(p.value, self._flat_defaults[p.name], p.name)
            setattr(s, p.name, value)
            if p.name == "publish_tf":
                if value and self._tf_made is None:
                    self._tf_made = _tf_backend(self)  # once: a second /tf publisher would be a leak
                self.tf_backend, self._send_tf = self._tf_made if value else ("disabled", None)
            elif p.name == "path_max_length":
                self._path = collections.deque(list(self._path)[-value:] if value else [], maxlen=max(1, value))
            elif p.name == "max_pending_images" and self.engine is not None and hasattr(self.engine,
                                                                                       "max_pending_images"):
                self.engine.max_pending_images = value
            elif p.name == "max_time_jump_back":
                for g in self._time_guards.values():
                    g.max_back = value
            elif p.name in ("imu_timeout", "image_timeout"):
                self.monitors[p.name.split("_")[0]].timeout = value
            elif p.name == "sensor_late_factor":
                for m in self.monitors.values():
                    m.late_factor = value
            self.get_logger().info(f"parameter {p.name} = {value!r} (live)")

    # ------------------------------------------------------------------ intake
    @staticmethod
    def _arrival(info) -> float:
        """Wall-clock seconds when DDS received the message (else now): latency covers queueing."""
        ns = info.get("received_timestamp") if isinstance(info, dict) else None
        return ns * 1e-9 if ns else time.time()

    def _imu_received(self, msg, info) -> None:  # executor callback (message + message info)
        self._intake([(msg, self._arrival(info))], [])

    def _image_received(self, msg, info) -> None:  # executor callback (message + message info)
        self._intake([], [(msg, self._arrival(info))])

    def _take_all(self, sub) -> list:
        """Every message ``sub`` has already received, taken now (not one per executor turn)."""
        out: list = []
        try:
            with sub.handle:
                while len(out) < 100000:
                    taken = sub.handle.take_message(sub.msg_type, sub.raw)
                    if taken is None:
                        break
                    out.append((taken[0], self._arrival(taken[1])))
        except (AttributeError, TypeError, KeyError) as exc:  # rclpy internals changed: executor order then
            self.settings.ordered_intake = False
            self._log("ordered_intake", f"ordered_intake disabled (rclpy cannot take messages directly: {exc})")
        return out

    def _intake(self, imus: list, images: list) -> None:
        """Process IMU and image messages in stamp order (IMU first on equal stamps).

        The executor takes one message per subscription per turn, so when the node is behind,
        images would outrun the IMU they wait for (and see an attitude from the wrong time).
        With ``ordered_intake`` everything already received is taken and merged by stamp: the
        offline order. Two streams whose heads are further apart than ``max_time_jump_back``
        (a bag restart inside the backlog) are taken IMU first, in arrival order.
        """
        if self.settings.ordered_intake:
            imus = imus + self._take_all(self._imu_sub)
            images = images + self._take_all(self._image_sub)
        i = j = 0
        jump = self.settings.max_time_jump_back
        while i < len(imus) or j < len(images):
            if j >= len(images):
                take_imu = True
            elif i >= len(imus):
                take_imu = False
            else:
                ti, tg = stamp_to_sec(imus[i][0].header.stamp), stamp_to_sec(images[j][0].header.stamp)
                take_imu = ti <= tg or abs(ti - tg) > jump
            if take_imu:
                self._gated("imu", imus[i])
                i += 1
            else:
                self._gated("image", images[j])
                j += 1

    def _gated(self, kind: str, item: tuple) -> None:
        """Count one received ``(msg, arrival)`` and hand it to its handler through the stream's
        time-jump guard: a lone outlier stamp is dropped, a confirmed jump back resets first."""
        self.counts["imu_in" if kind == "imu" else "images_in"] += 1
        self.monitors[kind].tick()
        self._gate(kind, item)

    def _gate(self, kind: str, item: tuple) -> None:
        guard = self._time_guards[kind]
        v = guard.check(stamp_to_sec(item[0].header.stamp), item)
        self._drop_outliers(kind, v.outliers)
        if v.accept:
            self._dispatch(kind, item)
            return
        if v.jump is None:
            return  # held until confirmed or found to be an outlier
        self.events[f"time_jump_{v.jump}"] += 1
        release = [(kind, it) for it in v.release]
        if v.jump == "back":
            self._reset()
            for other, g in self._time_guards.items():  # the other inputs move to the new timeline too
                if g is not guard:
                    more, outliers = g.rebase(guard.ref)
                    self._drop_outliers(other, outliers)
                    release += [(other, it) for it in more]
            release.sort(key=lambda r: (stamp_to_sec(r[1][0].header.stamp), r[0] != "imu"))
        self._log(f"time_jump_{v.jump}", f"time jumped {v.jump} by {v.jump_size:.3f} s (confirmed by {len(v.release)} "
                                         f"{'IMU' if kind == 'imu' else kind} messages; bag restarted?): "
                                         + ("odometry reset, the trajectory restarts at identity" if v.jump == "back"
                                            else "continuing on the new timeline"))
        for k, it in release:
            self._dispatch(k, it)

    def _dispatch(self, kind: str, item: tuple) -> None:
        (self._handle_imu if kind == "imu" else self._handle_image)(*item)

    def _drop_outliers(self, kind: str, items: list) -> None:
        label = "IMU" if kind == "imu" else kind
        for msg, _ in items:
            self._drop("stamp_outlier", f"{label} stamp {stamp_to_sec(msg.header.stamp):.6f} is off the {label} "
                                        f"timeline ({self._time_guards[kind].ref:.6f}) by more than "
                                        "max_time_jump_back/forward and no other message confirmed the jump "
                                        f"(time_jump_confirmations={self.settings.time_jump_confirmations})")

    # ------------------------------------------------------------------ per message
    def _on_imu(self, msg, arrival: float = 0.0) -> None:  # counted (and monitored) in _gated
        t = stamp_to_sec(msg.header.stamp)
        gyro, accel = imu_to_arrays(msg)
        R = self._imu_rotation(msg.header.frame_id)
        if R is not None:  # IMU mounted in another orientation (e.g. z down): into base_frame axes
            gyro, accel = R @ gyro, R @ accel
        if not (math.isfinite(t) and np.isfinite(gyro).all() and np.isfinite(accel).all()):
            self._drop("imu_nonfinite", f"IMU message at {t:.6f} has NaN/inf "
                                        f"(gyro {gyro.tolist()}, accel {accel.tolist()})")
            return
        if self.engine is None:  # kept (bounded) and fused once the camera is known: the filter warms up
            self._imu_backlog.append((t, gyro, accel))
            return
        self._last_gap = 0.0 if self._last_imu_stamp is None else t - self._last_imu_stamp
        steps = self._engine_call("imu", t, lambda: self.engine.add_imu(t, gyro, accel))
        if steps is None:
            return
        self._last_imu_stamp = t
        self._publish_steps(steps)

    def _on_image(self, msg, arrival: float | None = None) -> None:
        arrival = time.time() if arrival is None else arrival  # counted (and monitored) in _gated
        t = stamp_to_sec(msg.header.stamp)
        frame = msg.header.frame_id
        tf_version = -1
        if self.static_tf is not None:
            self.static_tf.poll()
            tf_version = self.static_tf.version
        if (frame and frame != self._camera_frame) or tf_version != self._tf_version:
            self._camera_frame, self._tf_version = frame or self._camera_frame, tf_version
            self._refresh_camera()
        if self.engine is None:
            self._await_calibration()
        if self.engine is None:
            s = self.settings
            fallback = (f"camera.* parameters after camera_info_timeout={s.camera_info_timeout:g} s"
                        if self.config.camera.has_intrinsics() else "no camera.* fallback set")
            self._drop("no_camera_info", f"image at {t:.6f}: no calibration yet (waiting for CameraInfo on "
                                         f"{self.resolve_topic_name(s.camera_info_topic)}; {fallback})")
            return
        try:
            img = image_to_gray(msg)
        except ImageConversionError as exc:
            self._drop(exc.reason, f"image at {t:.6f}: {exc}")
            return
        self._image_size = (img.shape[1], img.shape[0])
        calib = self.calibration
        if (img.shape[1], img.shape[0]) != (calib.width, calib.height):
            self._drop("bad_image_size", f"image at {t:.6f} is {img.shape[1]}x{img.shape[0]} but the calibration "
                                         f"is {calib.width}x{calib.height} (from {calib.source})")
            return
        img = calib.rectify(img)
        tag = (msg.header.stamp, arrival)  # back on the image's step: the output stamp, the latency
        steps = self._engine_call("image", t, lambda: self.engine.add_image(t, img, tag=tag))
        if steps is not None:
            self._publish_steps(steps)

    def _engine_call(self, kind: str, t: float, call: Callable[[], list]) -> list | None:
        """Run an engine call. Returns its steps, or None when the input was dropped (counted)."""
        try:
            steps = call()
        except ValueError as exc:
            steps = None
            if hasattr(exc, "jump") and hasattr(exc, "last"):  # core.odometry.OutOfOrderError
                try:
                    steps = self._out_of_order(kind, exc, t, call)
                except ValueError as exc2:
                    self._drop(f"{kind}_invalid", f"{'IMU' if kind == 'imu' else kind} at {t:.6f}: {exc2}")
            else:  # ImplausibleImuError carries its own reason
                self._drop(getattr(exc, "reason", f"{kind}_invalid"), f"{'IMU' if kind == 'imu' else kind} at {t:.6f}: {exc}")
        self._report_engine_events()
        return steps

    def _on_camera_info(self, msg) -> None:
        self.counts["camera_info_in"] += 1
        if same_camera_info(self.calibration, msg):
            return
        s = self.settings
        try:
            calib = calibration_from_camera_info(msg, s.camera_info_use_p, s.undistort, s.image_topic,
                                                 source=f"CameraInfo on {self.resolve_topic_name(s.camera_info_topic)}")
        except CalibrationError as exc:
            self._drop("bad_camera_info", str(exc))
            return
        w, h = calib.width, calib.height
        problem = intrinsics_problem(calib.K, w, h)
        if problem is None and self._image_size not in (None, (w, h)):
            problem = f"its size {w}x{h} disagrees with the images ({self._image_size[0]}x{self._image_size[1]})"
        if problem is not None:
            keep = "keeping the last good calibration" if self.camera is not None else "still waiting for a valid one"
            self._drop("bad_camera_info", f"CameraInfo rejected ({keep}): {problem}")
            return
        self._apply_calibration(calib)

    def _on_flush_timer(self) -> None:
        if self.engine is None or not self.engine.pending_images:
            return
        oldest = min(arrival for _, arrival in self.engine.pending_tags)
        if time.time() - oldest < self.settings.image_wait:
            return
        if self.settings.ordered_intake:
            self._intake([], [])  # IMU that was only queued, not missing, releases them
            if not self.engine.pending_images:
                return
        n = self.engine.pending_images
        steps = self.engine.flush()
        self.events["flushed_images"] += len(steps)
        self._report_engine_events()
        self._log("image_wait", f"{n} image(s) waited more than image_wait={self.settings.image_wait} s for IMU "
                                f"past their stamp: processed with the IMU fused so far ({len(steps)} published)",
                  level="info")
        self._publish_steps(steps)

    def _on_reset(self, request, response):
        self._reset()
        self.get_logger().info("reset requested: odometry restarted at identity")
        response.success = True
        response.message = "odometry reset: the trajectory restarts at identity"
        return response

    def _install_clock_jump_handler(self) -> None:
        """With use_sim_time, /clock jumping back (bag restarted) resets like robot_localization."""
        try:
            from rclpy.clock import JumpThreshold
            from rclpy.duration import Duration

            threshold = JumpThreshold(min_forward=None, on_clock_change=False,
                                      min_backward=Duration(nanoseconds=-int(self.settings.max_time_jump_back * 1e9)))

            def on_jump(info) -> None:
                if self._last_imu_stamp is None and not (self.engine and self.engine.pending_images):
                    return
                self.events["clock_jump_reset"] += 1
                self._log("clock_jump_reset", "ROS time jumped backwards (bag restarted?): resetting the odometry")
                self._reset()
                for kind, guard in self._time_guards.items():  # held messages: judged again on the new timeline
                    for item in guard.reset():
                        self._gate(kind, item)

            self._jump_handle = self.get_clock().create_jump_callback(threshold, post_callback=self._guard(
                "clock_jump", on_jump))
        except Exception as exc:  # noqa: BLE001 - optional feature
            self.get_logger().warning(f"no clock jump handler (resets then rely on message stamps): {exc}")

    # ------------------------------------------------------------------ outputs
    def _publish_steps(self, steps: list) -> None:
        if not steps:
            return
        s = self.settings
        for step in steps:
            stamp_msg, arrival = step.tag
            odom = odometry_msg(step, stamp_msg, s.odom_frame, s.base_frame)
            self.odom_pub.publish(odom)
            if arrival is not None:
                self._latency.append(time.time() - arrival)
            self.counts["odometry_out"] += 1
            q = float(getattr(step, "peak_quality", float("nan")))
            if math.isfinite(q):
                self._quality.append(q)
            if self._send_tf is not None:
                self._send_tf(transform_from_odometry(odom))
            if s.path_max_length > 0:
                self._path.append(pose_stamped_from_odometry(odom))
                if self.path_pub.get_subscription_count() > 0:
                    from nav_msgs.msg import Path as PathMsg

                    self.path_pub.publish(PathMsg(header=odom.header, poses=list(self._path)))
            if self.bev_pub.get_subscription_count() > 0:
                self._publish_bev(step, odom.header)

    def _publish_bev(self, step, header) -> None:
        from std_msgs.msg import Header

        img = bev_to_mono8(step.bev, getattr(step, "bev_mask", None))
        heat = getattr(step, "correlation", None)
        if self.settings.bev_image_heatmap and heat is not None:
            sep = np.full((img.shape[0], 2), 128, np.uint8)
            img = np.hstack([img, sep, heatmap_to_mono8(heat, img.shape)])
        self.bev_pub.publish(gray_to_image_msg(img, Header(stamp=header.stamp, frame_id=self.settings.base_frame)))

    def latency_percentiles(self) -> tuple[float, float, float]:
        """(p50, p99, max) of image arrival -> odometry publication, seconds (nan when empty)."""
        if not self._latency:
            return (math.nan,) * 3
        a = np.asarray(self._latency)
        return float(np.percentile(a, 50)), float(np.percentile(a, 99)), float(a.max())

    def diagnostics_values(self) -> dict[str, str]:
        now = time.monotonic()
        last_t, last_counts = self._last_diag
        dt = max(now - last_t, 1e-9)
        self._last_diag = (now, collections.Counter(self.counts))
        rate = lambda k: (self.counts[k] - last_counts[k]) / dt  # noqa: E731
        p50, p99, pmax = self.latency_percentiles()
        values = {
            "imu_rate_hz": f"{rate('imu_in'):.1f}",
            "image_rate_hz": f"{rate('images_in'):.1f}",
            "odometry_rate_hz": f"{rate('odometry_out'):.1f}",
            "imu_received": str(self.counts["imu_in"]),
            "images_received": str(self.counts["images_in"]),
            "odometry_published": str(self.counts["odometry_out"]),
            "drops_total": str(sum(self.drops.values())),
            "latency_p50_ms": f"{p50 * 1e3:.2f}",
            "latency_p99_ms": f"{p99 * 1e3:.2f}",
            "latency_max_ms": f"{pmax * 1e3:.2f}",
            "peak_quality_last": f"{self._quality[-1]:.3f}" if self._quality else "nan",
            "peak_quality_mean": f"{float(np.mean(self._quality)):.3f}" if self._quality else "nan",
            "pending_images": str(self.engine.pending_images if self.engine else 0),
            "tf": self.tf_backend,
        }
        for reason, n in sorted(self.drops.items()):
            values[f"drop.{reason}"] = str(n)
        for name, n in sorted(self.events.items()):
            values[f"event.{name}"] = str(n)
        return values

    def summary(self) -> str:
        """One line of totals: inputs received, odometry published, drops and filter events by reason."""
        c = self.counts
        drops = ", ".join(f"{k} {n}" for k, n in sorted(self.drops.items()) if n) or "none"
        events = ", ".join(f"{k} {n}" for k, n in sorted(self.events.items()) if n) or "none"
        return (f"imu {c['imu_in']}, images {c['images_in']}, camera_info {c['camera_info_in']} received; "
                f"odometry {c['odometry_out']} published; dropped: {drops}; events: {events}")

    def _calibration_state(self):
        """Where the camera model comes from: OK from CameraInfo (or the parameters when chosen with
        use_camera_info false), WARN while waiting or when the parameters stand in for CameraInfo."""
        from bevo_ros.ros.diagnostics import OK, WARN, SensorState

        s, calib = self.settings, self.calibration
        values = {"intrinsics": calib.source if calib else "none yet", "extrinsics": self._extrinsics_source,
                  "undistorting": str(bool(calib and calib.maps is not None)).lower(),
                  "imu_frames": ", ".join(f"{f}: {'tf' if r[1] is not None else 'as base'}"
                                          for f, r in sorted(self._R_base_imu.items())) or "base_frame"}
        if calib is None:
            return SensorState(WARN, f"waiting for CameraInfo on {self.resolve_topic_name(s.camera_info_topic)}", values)
        if s.use_camera_info and not calib.source.startswith("CameraInfo"):
            return SensorState(WARN, "no CameraInfo: the camera.* parameters stand in for it", values)
        return SensorState(OK, calib.describe(), values)

    def _publish_diagnostics(self) -> None:
        from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue

        prev_drops = getattr(self, "_diag_drops", 0)
        values = self.diagnostics_values()
        drops = int(values["drops_total"])
        self._diag_drops = drops
        status = DiagnosticStatus(name=f"{self.get_name()}: odometry", hardware_id="bevo")
        self._refresh_camera()  # a /tf_static that arrived (or changed) since
        inputs = {key: m.state() for key, m in self.monitors.items()}  # per input: OK / WARN late / ERROR silent
        worst = max((st.level for st in inputs.values()), default=0)
        if self.engine is None:
            status.level, status.message = DiagnosticStatus.WARN, "waiting for CameraInfo"
        elif worst == 2:
            status.level = DiagnosticStatus.ERROR
            status.message = "; ".join(st.message for st in inputs.values() if st.level == 2)
        elif drops > prev_drops:
            status.level, status.message = DiagnosticStatus.WARN, f"{drops - prev_drops} input(s) dropped"
        elif float(values["image_rate_hz"]) > 0 and float(values["odometry_rate_hz"]) == 0:
            status.level, status.message = DiagnosticStatus.WARN, "images arrive but no odometry is produced"
        elif worst == 1:
            status.level = DiagnosticStatus.WARN
            status.message = "; ".join(st.message for st in inputs.values() if st.level == 1)
        else:
            status.level, status.message = DiagnosticStatus.OK, "running"
        values["calibration"] = self.calibration.source if self.calibration is not None else "none yet"
        values["extrinsics"] = self._extrinsics_source
        status.values = [KeyValue(key=k, value=v) for k, v in values.items()]
        statuses = [status] + [status_message(self.get_name(), f"{key} input", st) for key, st in inputs.items()]
        statuses.append(status_message(self.get_name(), "calibration", self._calibration_state()))
        msg = DiagnosticArray(status=statuses)
        msg.header.stamp = self.get_clock().now().to_msg()
        self.diag_pub.publish(msg)


# ------------------------------------------------------------------------------------ entry point
def _params_file_from_args(argv: list[str]) -> list[str]:
    """Every ``--params-file X`` among the ROS arguments, in order; the node picks the one that set
    ``learned_params_file`` (for resolving it relative to that file)."""
    return ros_params.params_files_from_args(argv)


def main(args: list[str] | None = None) -> int:
    from bevo_ros.ros_process import run_node

    return run_node(lambda argv: BevoNode(params_file=_params_file_from_args(argv)), NODE_NAME, args,
                    refuse=(ConfigError,))


if __name__ == "__main__":
    sys.exit(main())
