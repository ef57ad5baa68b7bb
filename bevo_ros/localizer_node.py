"""``bevo_localizer``: BEVO+, the odometry localised in an aerial map (a thin rclpy layer around
:class:`bevo_ros.core.map_localization.MapLocalizer`).

    ros2 run bevo_ros bevo_localizer --ros-args -p map_file:=maps/area.yaml

In: ``bevo_node``'s nav_msgs/Odometry (``odometry_topic``) and its mono8 BEV image
(``bev_image_topic``, published by ``bevo_node`` only while someone subscribes: this node does;
a heat-map appended beside the BEV is cut off), and RViz's "2D Pose Estimate"
(geometry_msgs/PoseWithCovarianceStamped on ``initialpose_topic``). Out: TF ``map -> odom``
(REP-105), the base pose with covariance in ``map`` (``pose_topic``), ``/diagnostics`` (match
quality, updates accepted / gated / low quality, status) and a debug image of the last match
(map crop | mosaic | correlation, only while subscribed). Topic names are relative (a namespace
applies; ``initialpose`` resolves to RViz's ``/initialpose`` in the root namespace).

Why its own node: REP-105 splits the continuous odometry (``odom -> base_link``, bevo_node) from
the map correction (``map -> odom``) as AMCL and robot_localization do; the map, the mosaic and
the map updates (40 ms every few metres) then never delay the odometry, the localiser can be
restarted or re-initialised on its own, and it reuses bevo_node's BEVs instead of running a
second engine on the camera. Frames are paired by stamp (bevo_node stamps both with the image's);
an odometry message waits for its BEV until the next odometry arrives.
"""
from __future__ import annotations

import collections
import dataclasses
import math
import sys
import time
import traceback
from dataclasses import dataclass

import numpy as np
from rclpy.node import Node

from bevo_ros.config import ConfigError, resolve_path
from bevo_ros.core.geometry import BevSpec
from bevo_ros.core.map_localization import (APPEARANCES, LocalizerConfig, MapLocalizer, MapMatchConfig,
                                            se2_between)
from bevo_ros.io.maps import load_map
from bevo_ros.io.ros_conversions import (ImageConversionError, gray_to_image_msg, heatmap_to_mono8, image_to_gray,
                                         planar_pose_from_msg, stamp_to_ns, stamp_to_sec, yaw_from_quaternion_msg)
from bevo_ros.ros.diagnostics import counter_values
from bevo_ros.rotations import quaternion_from_rpy

NODE_NAME = "bevo_localizer"
EXIT_CONFIG_ERROR = 2


@dataclass
class LocalizerSettings:
    map_file: str = ""
    odometry_topic: str = "bevo/odometry"
    bev_image_topic: str = "bevo/bev_image"
    initialpose_topic: str = "initialpose"
    set_pose_topic: str = "bevo/set_pose"
    pose_topic: str = "bevo/map_pose"
    debug_image_topic: str = "bevo/localizer/debug_image"
    map_frame: str = "map"
    publish_tf: bool = True
    initial_pose: list = dataclasses.field(default_factory=list)  # [x, y, yaw] to start without RViz
    initial_std: list = dataclasses.field(default_factory=lambda: [3.0, 3.0, 5.0])  # m, m, deg
    bev_size: int = 100
    bev_metres_per_pixel: float = 0.1
    bev_forward_offset: float = 7.5
    match_resolution: float = 0.25
    match_size: int = 128
    appearance: str = "lcn"
    min_quality: float = 0.12
    mosaic_length: float = 20.0
    keyframe_spacing: float = 2.0
    update_distance: float = 4.0
    gate_probability: float = 0.999
    max_odometry_jump: float = 10.0  # m in one step: bevo_node was reset, the mosaic restarts
    device: str = "cpu"
    diagnostics_period: float = 1.0
    torch_threads: int = 1


DESCRIPTIONS = {
    "map_file": "map YAML (nav2 map_server convention: image, resolution, origin); required",
    "odometry_topic": "nav_msgs/Odometry from bevo_node (odom -> base_link)",
    "bev_image_topic": "mono8 BEV from bevo_node (a heat-map beside it is cut off)",
    "initialpose_topic": "geometry_msgs/PoseWithCovarianceStamped in the map frame (RViz 2D Pose Estimate)",
    "set_pose_topic": "bevo_node's set_pose input, listened to: the odometry's jump at its stamp is no motion "
                      "(the map pose stays, the mosaic restarts); '' = off",
    "pose_topic": "geometry_msgs/PoseWithCovarianceStamped output: base_link in map",
    "debug_image_topic": "mono8 debug image: map crop | mosaic | correlation (only while subscribed)",
    "map_frame": "the map's frame id (REP-105)",
    "publish_tf": "publish TF map -> odom",
    "initial_pose": "[x, y, yaw(rad)] start pose in map without /initialpose; [] waits for /initialpose",
    "initial_std": "[m, m, deg] standard deviations of initial_pose",
    "bev_size": "BEV size in pixels (bevo_node's bev.size)",
    "bev_metres_per_pixel": "BEV resolution (bevo_node's bev.metres_per_pixel)",
    "bev_forward_offset": "BEV near edge ahead of base_link, m (bevo_node's bev.forward_offset)",
    "match_resolution": "metres per pixel of the map matching (about the map's)",
    "match_size": "matching grid size in pixels (power of two)",
    "appearance": "raw | lcn | gradient: illumination-robust representation of map and mosaic",
    "min_quality": "correlation peak below this = no match (rejected, counted)",
    "mosaic_length": "metres of path composed into the mosaic",
    "keyframe_spacing": "metres between mosaic keyframes",
    "update_distance": "metres driven between map measurements",
    "gate_probability": "Mahalanobis gate of the map update (chi-square, 3 dof)",
    "max_odometry_jump": "an odometry step longer than this (m) is a reset of bevo_node",
    "device": "torch device of the matching (cuda falls back to cpu)",
    "diagnostics_period": "seconds between /diagnostics messages",
    "torch_threads": "torch CPU threads (0 = torch's default)",
}


SET_POSE_EXPIRY = 5  # odometry messages at or after a set_pose's stamp that may come before its jump
# Consecutive steps whose pose difference agreed with their twist before a disagreeing one is read as a
# jump of the odometry frame without its set_pose (it crossed the odometry on DDS), not as motion: an
# odometry source whose twist is unset or stale never earns it.
TWIST_TRUST = 3


def _twist_motion(msg, dt: float) -> np.ndarray | None:
    """The frame's motion ``(dx, dy, dyaw)`` in the previous base frame from an Odometry's twist (in
    the child frame at its stamp, as bevo_node publishes it) over ``dt``; None when not finite."""
    tw = msg.twist.twist
    dyaw = tw.angular.z * dt
    c, s = math.cos(dyaw), math.sin(dyaw)
    vx, vy = tw.linear.x * dt, tw.linear.y * dt
    out = np.array([c * vx - s * vy, s * vx + c * vy, dyaw])
    return out if np.isfinite(out).all() and dt > 0 else None


def _due(entry: list, stamp: float) -> bool:
    """A set_pose's jump may be in the odometry of ``stamp``: received after the set_pose (bevo_node
    outputs it after taking the set_pose), at or after its stamp (a stamp ahead waits for its frame)."""
    return stamp > entry[1] and (entry[0] is None or entry[0] <= stamp)


def _is_jump(motion: np.ndarray, twist_motion: np.ndarray) -> bool:
    """The pose difference disagrees with the twist by more than a frame's jitter can (the twist's
    interval is bevo_node's regularised one: up to ~25 % off the stamps')."""
    dist = math.hypot(motion[0] - twist_motion[0], motion[1] - twist_motion[1])
    dyaw = abs(math.remainder(motion[2] - twist_motion[2], 2 * math.pi))
    # relative to the larger of the two: an interval 25 % off either way is no jump at any speed
    size = max(math.hypot(motion[0], motion[1]), math.hypot(twist_motion[0], twist_motion[1]))
    return dist > max(0.3, 0.3 * size) or dyaw > max(math.radians(2.0), 0.3 * max(abs(motion[2]), abs(twist_motion[2])))


def _twist_motion_covariance(msg, dt: float) -> np.ndarray | None:
    cov = np.asarray(msg.twist.covariance, dtype=np.float64).reshape(6, 6)[np.ix_([0, 1, 5], [0, 1, 5])] * dt * dt
    return cov if np.isfinite(cov).all() and dt > 0 else None


class BevoLocalizerNode(Node):
    """See the module docstring."""

    def __init__(self, node_name: str = NODE_NAME, **node_kwargs) -> None:
        super().__init__(node_name, **node_kwargs)
        try:
            self._setup()
        except BaseException:
            self.destroy_node()
            raise

    def _setup(self) -> None:
        from diagnostic_msgs.msg import DiagnosticArray
        from geometry_msgs.msg import PoseWithCovarianceStamped
        from nav_msgs.msg import Odometry
        from rcl_interfaces.msg import ParameterDescriptor
        from rclpy.qos import QoSProfile
        from sensor_msgs.msg import Image

        values = {}
        for f in dataclasses.fields(LocalizerSettings):
            default = getattr(LocalizerSettings(), f.name)
            desc = ParameterDescriptor(description=DESCRIPTIONS.get(f.name, ""), dynamic_typing=True)
            if isinstance(default, list):
                v = self.declare_parameter(f.name, [float(x) for x in default] or [0.0], desc).value
                v = [] if (not default and list(v) == [0.0]) else list(v)
            else:
                v = self.declare_parameter(f.name, default, desc).value
                try:
                    v = type(default)(v)
                except (TypeError, ValueError):
                    raise ConfigError(f"parameter '{f.name}' = {v!r} is not a {type(default).__name__}") from None
            values[f.name] = v
        s = self.settings = LocalizerSettings(**values)
        if not s.map_file:
            raise ConfigError("parameter 'map_file' is required (a nav2 map_server YAML: image, resolution, origin)")
        if s.appearance not in APPEARANCES:
            raise ConfigError(f"parameter 'appearance' must be one of {APPEARANCES}, got {s.appearance!r}")
        if s.initial_pose and len(s.initial_pose) != 3:
            raise ConfigError(f"parameter 'initial_pose' must be [x, y, yaw] or [], got {s.initial_pose}")
        import torch

        if s.torch_threads > 0:
            torch.set_num_threads(s.torch_threads)
        self.map_path = resolve_path(s.map_file)
        aerial = load_map(self.map_path)  # ConfigError: refuse to start
        self.spec = BevSpec(s.bev_size, s.bev_metres_per_pixel, s.bev_forward_offset)
        try:
            match = MapMatchConfig(resolution=s.match_resolution, size=s.match_size, appearance=s.appearance,
                                   min_quality=s.min_quality)
            config = LocalizerConfig(match=match, mosaic_length=s.mosaic_length, keyframe_spacing=s.keyframe_spacing,
                                     update_distance=s.update_distance, gate_probability=s.gate_probability)
            self.localizer = MapLocalizer(aerial, self.spec, config, device=s.device)
        except ValueError as exc:
            raise ConfigError(str(exc)) from None

        self.counts: collections.Counter[str] = collections.Counter()
        self.drops: collections.Counter[str] = collections.Counter()
        self._bevs: collections.OrderedDict[int, tuple[np.ndarray, np.ndarray]] = collections.OrderedDict()
        self._pending: collections.deque = collections.deque()  # odometry messages waiting for their BEV
        self._last_odom: tuple[float, np.ndarray] | None = None
        self._odom_frame = "odom"
        self._last_step = None
        self._quality: collections.deque[float] = collections.deque(maxlen=50)
        self._proc_time: collections.deque[float] = collections.deque(maxlen=200)

        q = QoSProfile(depth=100)
        self.create_subscription(Odometry, s.odometry_topic, self._guard("odometry", self._on_odometry), q)
        self.create_subscription(Image, s.bev_image_topic, self._guard("bev", self._on_bev), q)
        self.create_subscription(PoseWithCovarianceStamped, s.initialpose_topic,
                                 self._guard("initialpose", self._on_initialpose), 10)
        # set_poses whose jump has not come: [stamp (None: 0), newest odometry received before it, messages left]
        self._rebase: list[list] = []
        self._last_received = -math.inf
        self._twist_agreed = 0  # consecutive steps whose pose difference agreed with their twist
        if s.set_pose_topic:
            self.create_subscription(PoseWithCovarianceStamped, s.set_pose_topic,
                                     self._guard("set_pose", self._on_set_pose), 10)
        self.pose_pub = self.create_publisher(PoseWithCovarianceStamped, s.pose_topic, 10)
        self.debug_pub = self.create_publisher(Image, s.debug_image_topic, 2)
        self.diag_pub = self.create_publisher(DiagnosticArray, "/diagnostics", 10)
        self._tf_name, self._send_tf = ("none", None)
        if s.publish_tf:
            from bevo_ros.ros.publishers import tf_backend

            self._tf_name, self._send_tf = tf_backend(self)
            if self._send_tf is None:
                self.get_logger().error("publish_tf is true but neither tf2_ros nor tf2_msgs is available: "
                                        "TF map -> odom is DISABLED (the pose is still published)")
        if s.initial_pose:
            std = np.array(s.initial_std, dtype=np.float64)
            std[2] = math.radians(std[2])
            self.localizer.set_initial_pose(s.initial_pose, np.diag(std**2))
        self.create_timer(s.diagnostics_period, self._guard("diagnostics", self._publish_diagnostics))
        w, h = aerial.extent
        self.get_logger().info(f"ready: map {self.map_path} ({aerial.width}x{aerial.height} px, {w:.0f} x {h:.0f} m "
                               f"at {aerial.resolution:.3f} m/px); TF: {self._tf_name}; "
                               + ("initial pose from parameters" if s.initial_pose else
                                  f"waiting for {s.initialpose_topic}"))

    # ------------------------------------------------------------------------ callbacks
    def _guard(self, name: str, fn):
        def wrapped(*args):
            try:
                fn(*args)
            except Exception as exc:  # noqa: BLE001 - never let a callback kill the node
                self.drops[f"{name}_exception"] += 1
                self.get_logger().error(f"{name} callback failed: {type(exc).__name__}: {exc}\n"
                                        + traceback.format_exc(limit=3))
        return wrapped

    def _on_set_pose(self, msg) -> None:
        """bevo_node's set_pose (the same topic): its odometry jumps at the first frame at or after the
        stamp (stamp 0: the next one). Kept as bevo_node keeps it (the same checks; a new one replaces
        one still waiting for its frame) until an odometry at or after its stamp jumps, i.e. disagrees
        with the previous pose moved by its own twist (a frame bevo_node published before it took the
        set_pose does not); that jump is no motion. One that waits more than SET_POSE_EXPIRY odometry
        messages is let go: it reached this node after its jump, which a twist that agreed with the
        poses before it (TWIST_TRUST) had already told from motion."""
        frame = msg.header.frame_id.lstrip("/")
        if frame not in ("", self._odom_frame):
            self.drops["set_pose_frame"] += 1
            return
        try:
            planar_pose_from_msg(msg)  # what bevo_node refuses, it does not apply
        except ValueError:
            self.drops["set_pose_invalid"] += 1
            return
        stamp = stamp_to_sec(msg.header.stamp)
        last = self._last_received
        kept = [e for e in self._rebase if e[0] is None or e[0] <= last]  # bevo_node drops one still waiting
        self._rebase = kept[-9:] + [[stamp if stamp > 0.0 else None, last, SET_POSE_EXPIRY]]
        self.counts["set_pose_in"] += 1

    def _on_initialpose(self, msg) -> None:
        if msg.header.frame_id and msg.header.frame_id != self.settings.map_frame:
            self.drops["initialpose_wrong_frame"] += 1
            self.get_logger().warning(f"/initialpose in frame '{msg.header.frame_id}', expected "
                                      f"'{self.settings.map_frame}': ignored")
            return
        p, o = msg.pose.pose.position, msg.pose.pose.orientation
        try:  # normalised (z: 1, w: 1 read 116.6 deg); an orientation left out (all zero) is no pose, not yaw 0
            yaw = yaw_from_quaternion_msg(o)
        except ValueError as exc:
            self.drops["initialpose_invalid"] += 1
            self.get_logger().warning(f"/initialpose ignored: {exc}")
            return
        cov = np.asarray(msg.pose.covariance, dtype=np.float64).reshape(6, 6)[np.ix_([0, 1, 5], [0, 1, 5])]
        floor = np.diag([0.25**2, 0.25**2, math.radians(2.0) ** 2])  # RViz sends 0.25 m / 15 deg; never zero
        cov = np.maximum(cov, 0.0) * (np.eye(3) > 0) + floor if not np.all(np.linalg.eigvalsh(cov) > 0) else cov
        try:
            self.localizer.set_initial_pose([p.x, p.y, yaw], cov)
        except ValueError as exc:
            self.drops["initialpose_invalid"] += 1
            self.get_logger().warning(f"/initialpose ignored: {exc}")
            return
        self.counts["initialpose"] += 1
        self.get_logger().info(f"initial pose x {p.x:.2f} y {p.y:.2f} yaw {math.degrees(yaw):.1f} deg")

    def _on_bev(self, msg) -> None:
        try:
            img = image_to_gray(msg)
        except ImageConversionError as exc:
            self.drops[f"bev_{exc.reason}"] += 1
            return
        S = self.spec.size
        if img.shape[0] != S or img.shape[1] < S:
            self.drops["bev_wrong_size"] += 1
            return
        img = np.asarray(img[:, :S], dtype=np.float32) / 255.0  # mono8 always (a dark one was taken as 0..1)
        self._bevs[stamp_to_ns(msg.header.stamp)] = (img, (img > 0).astype(np.float32))
        while len(self._bevs) > 50:
            self._bevs.popitem(last=False)
        self.counts["bev_in"] += 1
        if self._pending and stamp_to_ns(self._pending[-1].header.stamp) in self._bevs:
            self._process(self._pending.pop())

    def _on_odometry(self, msg) -> None:
        self.counts["odometry_in"] += 1
        self._last_received = max(self._last_received, stamp_to_sec(msg.header.stamp))
        while self._pending:  # the previous one's BEV did not come: go on without it
            self._process(self._pending.popleft())
        if stamp_to_ns(msg.header.stamp) in self._bevs:
            self._process(msg)
        else:
            self._pending.append(msg)

    def _process(self, msg) -> None:
        t0 = time.perf_counter()
        stamp = stamp_to_sec(msg.header.stamp)
        self._odom_frame = msg.header.frame_id or "odom"
        p, o = msg.pose.pose.position, msg.pose.pose.orientation
        try:
            yaw = yaw_from_quaternion_msg(o)
        except ValueError:
            yaw = math.nan  # dropped below as not finite
        pose = np.array([p.x, p.y, yaw])
        if not np.isfinite(pose).all():
            self.drops["odometry_not_finite"] += 1
            return
        if self._last_odom is None:
            motion, cov = np.zeros(3), None
            self._rebase = [e for e in self._rebase if not _due(e, stamp)]  # no motion to lose
        else:
            t_prev, prev = self._last_odom
            motion = se2_between(prev, pose)
            cov = _twist_motion_covariance(msg, stamp - t_prev)
            twist_motion = _twist_motion(msg, stamp - t_prev)
            due = [e for e in self._rebase if _due(e, stamp)]
            jump = twist_motion is not None and _is_jump(motion, twist_motion)
            announced = bool(due) and jump
            # A jump whose set_pose has not come (DDS does not order topics): the twist, trusted, says so.
            rebased = announced or jump and self._twist_agreed >= TWIST_TRUST
            # Trust grows with each agreeing step; a set_pose's jump leaves it; any other jump ends it (one
            # read as a jump without its set_pose happens once: trust is earned again over TWIST_TRUST steps).
            if not announced:
                self._twist_agreed = self._twist_agreed + 1 if twist_motion is not None and not jump else 0
            for e in due:
                e[2] -= 1
            self._rebase = [e for e in self._rebase if not _due(e, stamp) or not announced and e[2] > 0]
            if announced:
                self.counts["odometry_set_pose"] += 1
            elif rebased:  # a bevo_node reset, or a set_pose this node has not received yet
                self.counts["odometry_jump"] += 1
            if rebased or stamp <= t_prev or math.hypot(motion[0], motion[1]) > self.settings.max_odometry_jump:
                # bevo_node reset or set_pose (or a bag restarted): keep the map pose, restart the mosaic;
                # after a jump the frame's own motion is its twist's (bevo_node's twist stays valid).
                self.counts["odometry_resets"] += 1
                if not announced:  # a reset: bevo_node forgot the set_poses waiting for their frames
                    self._rebase = []
                pose_map = None if self.localizer.filter.x is None else self.localizer.filter.x.copy()
                self.localizer.mosaic.reset()
                self.localizer.pose_odom = pose
                motion, cov = (twist_motion, cov) if rebased else (np.zeros(3), None)
                if pose_map is not None:
                    self.localizer.filter.state[:3] = pose_map
        self._last_odom = (stamp, pose)
        bev = self._bevs.pop(stamp_to_ns(msg.header.stamp), None)
        step = self.localizer.step(pose, motion, cov, *(bev if bev is not None else (None, None)))
        self._last_step = step
        if step.measured:
            self.counts["measurements"] += 1
            self._quality.append(step.quality)
            if self.debug_pub.get_subscription_count() > 0:
                self._publish_debug(msg.header.stamp)
        if step.pose is not None:
            self._publish_pose(msg.header.stamp, step)
        self._proc_time.append(time.perf_counter() - t0)

    # ------------------------------------------------------------------------ outputs
    def _publish_pose(self, stamp, step) -> None:
        from geometry_msgs.msg import PoseWithCovarianceStamped, TransformStamped

        s = self.settings
        out = PoseWithCovarianceStamped()
        out.header.stamp = stamp
        out.header.frame_id = s.map_frame
        x, y, yaw = (float(v) for v in step.pose)
        out.pose.pose.position.x, out.pose.pose.position.y = x, y
        q = quaternion_from_rpy(0.0, 0.0, yaw)
        o = out.pose.pose.orientation
        o.x, o.y, o.z, o.w = q
        cov = np.zeros((6, 6))
        idx = [0, 1, 5]
        cov[np.ix_(idx, idx)] = step.covariance
        cov[2, 2] = cov[3, 3] = cov[4, 4] = 1e6  # z, roll, pitch: not estimated here
        out.pose.covariance = [float(v) for v in cov.reshape(-1)]
        self.pose_pub.publish(out)
        self.counts["pose_out"] += 1
        if self._send_tf is not None and step.map_to_odom is not None:
            t = TransformStamped()
            t.header.stamp = stamp
            t.header.frame_id = s.map_frame
            t.child_frame_id = self._odom_frame
            mx, my, myaw = (float(v) for v in step.map_to_odom)
            t.transform.translation.x, t.transform.translation.y = mx, my
            qq = quaternion_from_rpy(0.0, 0.0, myaw)
            r = t.transform.rotation
            r.x, r.y, r.z, r.w = qq
            self._send_tf(t)
            self.counts["tf_out"] += 1

    def _publish_debug(self, stamp) -> None:
        from std_msgs.msg import Header

        m = self.localizer.last_measurement
        if m is None:
            return

        def to8(a):
            a = a.detach().float().cpu().numpy()
            lo, hi = np.percentile(a, 1), np.percentile(a, 99)
            return np.clip((a - lo) / max(hi - lo, 1e-9) * 255, 0, 255).astype(np.uint8)

        crop, mos = to8(m.crop[0, 0]), to8(m.mosaic[0, 0])
        heat = heatmap_to_mono8(m.correlation[0].detach().cpu().numpy(), crop.shape)
        sep = np.full((crop.shape[0], 2), 128, np.uint8)
        img = np.hstack([crop, sep, mos, sep, heat])
        self.debug_pub.publish(gray_to_image_msg(img, Header(stamp=stamp, frame_id=self.settings.map_frame)))

    def diagnostics_values(self) -> dict[str, str]:
        c = self.localizer.counters
        q = np.asarray(self._quality)
        pt = np.asarray(self._proc_time)
        v = {
            "status": self.localizer.status,
            "map_measurements": str(c.measurements), "accepted": str(c.accepted),
            "rejected_low_quality": str(c.rejected_quality), "rejected_gate": str(c.rejected_gate),
            "skipped_outside_map": str(c.skipped_no_map), "consecutive_rejections": str(c.consecutive_rejections),
            "consecutive_outside_map": str(c.consecutive_outside),
            # the last map match's (most steps make none: the newest step's read n/a 3 times in 4)
            "match_quality_last": f"{self._quality[-1]:.3f}" if self._quality else "n/a",
            "match_quality_median": f"{np.median(q):.3f}" if q.size else "n/a",
            "odometry_scale": f"{self.localizer.filter.state[3]:.4f}" if self.localizer.filter.initialised else "n/a",
            "processing_ms_p50": f"{np.median(pt) * 1e3:.2f}" if pt.size else "n/a",
            "processing_ms_max": f"{pt.max() * 1e3:.2f}" if pt.size else "n/a",
        }
        if self.localizer.filter.initialised:
            sd = np.sqrt(np.diag(self.localizer.filter.P))
            v["position_std_m"] = f"{math.hypot(sd[0], sd[1]):.3f}"
            v["yaw_std_deg"] = f"{math.degrees(sd[2]):.3f}"
        v.update(counter_values("count", self.counts))
        v.update(counter_values("drop", self.drops))
        return v

    def _publish_diagnostics(self) -> None:
        from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue

        values = self.diagnostics_values()
        status = DiagnosticStatus(name=f"{self.get_name()}: map localisation", hardware_id="bevo")
        state = values["status"]
        if state == "tracking":
            status.level, status.message = DiagnosticStatus.OK, "tracking"
        elif state == "lost":
            status.level = DiagnosticStatus.ERROR
            status.message = f"lost: {values['consecutive_rejections']} map matches rejected in a row"
        elif state == "outside_map":
            status.level = DiagnosticStatus.WARN
            status.message = (f"outside the map: the last {values['consecutive_outside_map']} updates found too little "
                              "map under the mosaic (the pose is the odometry's, its covariance growing)")
        else:
            status.level, status.message = DiagnosticStatus.WARN, state
        status.values = [KeyValue(key=k, value=val) for k, val in values.items()]
        msg = DiagnosticArray(status=[status])
        msg.header.stamp = self.get_clock().now().to_msg()
        self.diag_pub.publish(msg)


def main(args: list[str] | None = None) -> int:
    from bevo_ros.ros_process import run_node  # SIGINT/SIGTERM: exit 0, no traceback

    return run_node(lambda argv: BevoLocalizerNode(), NODE_NAME, args, refuse=(ConfigError,))


if __name__ == "__main__":
    sys.exit(main())
