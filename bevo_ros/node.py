"""``bevo_node``: the rclpy wiring around :class:`bevo_ros.core.odometry.BevoOdometry`.

    ros2 run bevo_ros bevo_node --ros-args --params-file $(ros2 pkg prefix --share bevo_ros)/params/kitti.yaml

Subscribes (relative topic names) to IMU, images (raw or compressed) and CameraInfo, and reads
the rig from /tf_static; runs the DUKF on every IMU message and BEV + phase correlation on every
frame through the same engine the offline tools use; publishes nav_msgs/Odometry (header stamp =
the image's stamp), a bounded nav_msgs/Path, a BEV image (only when subscribed), TF
``odom -> base_link`` and ``/diagnostics``. Every parameter is documented in
``params/kitti.yaml``. Bad input is dropped, counted (``/diagnostics``) and logged (throttled per
reason); no callback exception can kill the node. A missing or malformed learned-parameters file,
or an unusable configuration, stops the node at start with one log line and exit code 2.

The logic lives in :mod:`bevo_ros.ros`: ``settings`` (parameters), ``rig`` (calibration,
extrinsics, IMU axes), ``intake`` (ordered intake, time jumps, the engine calls), ``publishers``
and ``diagnostics``; this module only connects them.
"""
from __future__ import annotations

import dataclasses
import math
import sys
import time
import traceback
from typing import Callable

from rclpy.node import Node

from bevo_ros.config import ConfigError, build_odometry, gyro_bias_prior_note
from bevo_ros.core.frame_clock import fast_camera_note
from bevo_ros.core.odometry import InvalidInputError
from bevo_ros.io.learned_params import load_learned_params
from bevo_ros.core.device import resolve_device
from bevo_ros.ros import parameters as ros_params
from bevo_ros.ros import settings as node_settings
from bevo_ros.ros.diagnostics import (BLIND_FRAME_EVENTS, ERROR, WARN, Report, SensorMonitor, odometry_state,
                                     status_message)
from bevo_ros.ros.intake import EngineFeed, Intake, watch_clock_jumps
from bevo_ros.ros.publishers import Outputs
from bevo_ros.ros.rig import Rig
from bevo_ros.ros.tf import StaticTransforms
from bevo_ros.io.ros_conversions import forward_speed_from_msg, imu_to_arrays, speed_frame, planar_pose_from_msg, stamp_to_sec

NODE_NAME = "bevo_node"


class BevoNode(Node):
    """See the module docstring. ``engine_factory(config, learned, camera)`` is for tests."""

    def __init__(self, params_file: str | list[str] | None = None, engine_factory: Callable | None = None,
                 node_name: str = NODE_NAME, **node_kwargs) -> None:
        super().__init__(node_name, **node_kwargs)
        try:
            self._setup(params_file, engine_factory or build_odometry, node_name)
        except BaseException:
            self.destroy_node()  # a node that refuses to start leaves nothing behind in the context
            raise

    def _setup(self, params_file: str | list[str] | None, engine_factory: Callable, node_name: str) -> None:
        """Parameters, then the parts (bevo_ros.ros), then the ROS interfaces (:meth:`_connect`)."""
        import torch

        # ---- parameters (read_only for what is fixed at start, live ones applied by _on_parameters_applied)
        s, self.config = node_settings.declare(self, node_name)
        self.settings = s
        self.learned_path = node_settings.learned_params_path(self.config, params_file, self.get_fully_qualified_name())
        self.learned = load_learned_params(self.learned_path)  # ConfigError: refuse to start
        self.config.learned_params_file = str(self.learned_path)
        if s.torch_threads > 0:
            torch.set_num_threads(s.torch_threads)
        try:  # the one CUDA fallback rule, logged (build_odometry applies it again for the engine)
            resolve_device(self.config.device, log=self.get_logger().warning)
        except ValueError as exc:
            raise ConfigError(f"parameter 'device': {exc}") from None

        # ---- parts (bevo_ros.ros); drops, events, counts and log_history are the report's
        self.report = report = Report(self.get_logger(), s)
        self.drops, self.events, self.counts, self.log_history = report.drops, report.events, report.counts, \
            report.log_history
        self.image_input_topic = s.image_topic.rstrip("/") + "/compressed" if s.image_transport == "compressed" \
            else s.image_topic  # image_transport's naming: <base topic>/compressed
        self.monitors = {kind: SensorMonitor(label, self.resolve_topic_name(topic), timeout, s.sensor_late_factor,
                                             clock=time.monotonic)
                         for kind, label, topic, timeout in (("imu", "IMU", s.imu_topic, s.imu_timeout),
                                                             ("image", "images", self.image_input_topic,
                                                              s.image_timeout))
                                                             + ((("speed", "speed", s.speed_topic, s.speed_timeout),)
                                                                if s.speed_topic else ())}
        self._engine_factory = engine_factory
        self._published_stamp: float | None = None  # the newest frame published since the start (or reset)
        self._fast_camera_noted = False  # fast_camera_note said once
        self.feed = EngineFeed(s, self.config.filter.max_imu_gap, report, self._reset,
                               lambda kind, t, raw: self.rig.engine_input(kind, t, raw))
        self.intake = Intake(s, report, self.monitors, self._dispatch, self._reset)
        self.static_tf = StaticTransforms(self) if s.extrinsics_from_tf else None
        self._info_sub = None
        self._mounting_logged: tuple[float, float] | None = None  # the re-derived mounting last logged
        self._tilt_logged = None  # the engine's start tilt measurement last logged
        self.rig = Rig(s, self.config, report, self.get_logger(), self.static_tf,
                       self.resolve_topic_name(s.camera_info_topic),
                       lambda: self.intake.take_all(self._info_sub) if self._info_sub is not None else [],
                       lambda camera: self._set_camera(engine_factory, camera))
        self.rig.start()
        self._connect()

    def _connect(self) -> None:
        """Publishers, subscriptions, parameter callbacks, the reset service, timers."""
        from diagnostic_msgs.msg import DiagnosticArray
        from rclpy.clock import Clock, ClockType
        from sensor_msgs.msg import CameraInfo, CompressedImage, Image, Imu
        from std_srvs.srv import Trigger

        s, report = self.settings, self.report
        in_qos = node_settings.input_qos(s)
        self.outputs = Outputs(self, s, report)
        self.diag_pub = self.create_publisher(DiagnosticArray, "/diagnostics", 10)
        self._handlers = {"imu": self._guard("imu", self._on_imu), "image": self._guard("image", self._on_image)}
        received = {kind: self._guard(kind, lambda msg, info, k=kind: self.intake.received(k, msg, info))
                    for kind in ("imu", "image")}
        # two-argument callbacks: rclpy then passes the message info (DDS reception time)
        self.intake.subs["imu"] = self.create_subscription(Imu, s.imu_topic, lambda msg, info: received["imu"](
            msg, info), in_qos(s.imu_qos_depth))
        self.intake.subs["image"] = self.create_subscription(
            CompressedImage if s.image_transport == "compressed" else Image, self.image_input_topic,
            lambda msg, info: received["image"](msg, info), in_qos(s.image_qos_depth))
        if s.use_camera_info:
            self._info_sub = self.create_subscription(CameraInfo, s.camera_info_topic, self._guard(
                "camera_info", self.rig.camera_info), in_qos(s.image_qos_depth))
        self.add_on_set_parameters_callback(self._guard("parameters", node_settings.check_live))
        self.add_post_set_parameters_callback(self._guard("parameters", self._on_parameters_applied))
        self.create_service(Trigger, "~/reset", self._guard("reset", self._on_reset))
        if s.set_pose_topic:  # reliable, as robot_localization's set_pose: a command is not to be lost
            from geometry_msgs.msg import PoseWithCovarianceStamped

            self.create_subscription(PoseWithCovarianceStamped, s.set_pose_topic,
                                     self._guard("set_pose", self._on_set_pose), 10)
        if s.speed_topic:  # a sensor: its input QoS, as the IMU's
            import importlib

            package, _, name = node_settings.SPEED_TYPES[s.speed_type].split("/")
            self._handlers["speed"] = self._guard("speed", self._on_speed)
            take_speed = self._guard("speed", self.intake.speed)
            self._speed_frames_said: set[str] = set()  # frames other than base_frame, warned about once
            # two-argument callback: rclpy then passes the message info (DDS reception time)
            self.create_subscription(getattr(importlib.import_module(f"{package}.msg"), name), s.speed_topic,
                                     lambda msg, info: take_speed(msg, info), in_qos(s.imu_qos_depth))
        # Steady-clock timers: they tick with or without /clock (use_sim_time).
        steady = Clock(clock_type=ClockType.STEADY_TIME)
        self._steady = steady
        self._flush_timer = self.create_timer(min(0.05, s.image_wait / 2), self._guard("flush_timer", self._on_flush_timer),
                                              clock=steady)
        self.create_timer(s.diagnostics_period, self._guard("diagnostics", self._publish_diagnostics), clock=steady)
        self._path_restart_at: float | None = None  # a waiting set_pose's stamp: the path restarts there
        self._diag_drops = 0  # drops_total at the last /diagnostics
        self._diag_frames = (0, 0, 0)  # at the last one: odometry published, blind frames, frames near the reach
        # with use_sim_time, /clock jumping back (bag restarted) resets like robot_localization
        self._jump_handle = watch_clock_jumps(self, s.max_time_jump_back, self._guard("clock_jump", self._on_clock_jump))

        calib = self.rig.calibration
        cam = (calib.describe() if calib is not None else
               f"from CameraInfo on {self.resolve_topic_name(s.camera_info_topic)} (camera.* parameters after "
               f"{s.camera_info_timeout:g} s without it)")
        self.get_logger().info(
            f"ready: imu={self.resolve_topic_name(s.imu_topic)} image={self.resolve_topic_name(self.image_input_topic)} "
            f"({s.input_qos}) -> {self.resolve_topic_name(s.odometry_topic)}, camera {cam}, "
            f"extrinsics {'from /tf_static when published (' + self.static_tf.backend + ')' if self.static_tf else 'parameters'}, "
            f"BEV {self.config.bev.size}px x {self.config.bev.metres_per_pixel} m, "
            f"learned={self.learned_path}, tf={self.outputs.tf_backend}")
        if (note := gyro_bias_prior_note(self.config, self.learned, self.learned_path)) is not None:
            self.get_logger().info(note)  # it overrides two parameters

    def summary(self) -> str:
        """The totals ros_process logs on SIGINT (with images still waiting, never silently lost)."""
        waiting = self.feed.pending_images + self.rig.held_images
        held = self.feed.held_images
        return (self.report.summary() + (f"; {waiting} image(s) still waiting (for IMU or calibration)" if waiting else "")
                + (f"; {held} image(s) held for the start's camera tilt (filter.tilt_from_images)" if held else ""))

    @property
    def engine(self):
        return self.feed.engine

    def _set_camera(self, engine_factory: Callable, camera) -> None:
        if self.feed.engine is not None:
            self._rig_changed(camera, f"camera extrinsics / calibration ({self.rig.extrinsics_source})")
            return
        # The first calibration: the images held for it go in with the IMU that waited, by stamp.
        # They wait for IMU past their stamps (image_wait) from now, not from their arrival.
        now = time.time()
        images = [(stamp_to_sec(msg.header.stamp), msg, (msg.header.stamp, arrival, now))
                  for msg, arrival in self.rig.take_held()]
        engine = engine_factory(self.config, self.learned, camera)
        self._log_mounting(engine)
        self._publish(self.feed.start(engine, images))

    def _rig_changed(self, camera, what: str) -> None:
        """The rig changed under a running engine (e.g. /tf_static arriving after the first frames: a
        startup race between topics). Up to its first frame out, a new engine with ``camera`` is fed
        again every input since the start (the IMU in the new axes, the images through the new
        calibration): what it would have computed had the rig come first, bit for bit. Later (or
        past the journal's bounds) the engine keeps its trajectory and moves to the new camera
        (counted: ``camera_changed``; before its first frame it moves its DUKF start, to first order)."""
        replayed = False
        if self.feed.replayable:
            n = len(self.feed.journal.entries)
            try:
                steps = self.feed.replay(self._engine_factory(self.config, self.learned, camera))
                replayed = True
            except Exception as exc:  # noqa: BLE001 - the running engine stays and takes the camera below
                self.feed.journal.stop()  # not tried again for every later change
                self.report.log("rig_replayed", f"{what} changed before the second frame, but feeding its inputs "
                                                f"again failed ({type(exc).__name__}: {exc}): the running engine "
                                                "takes the new camera instead", level="error")
            if replayed:
                self._publish(steps, replayed=True)
                self.events["rig_replayed"] += 1
                self.report.log("rig_replayed", f"{what} changed before the second frame: the odometry restarted "
                                                f"with it, its {n} input(s) since the start fed again", level="info")
        if not replayed:
            self.events["camera_changed"] += 1
            self.report.log("camera_changed", f"{what} changed after the odometry's second frame (or a start "
                                              "longer than the inputs kept to feed again): the engine takes it from "
                                              "now on, its start stays the old rig's", level="info")
            self.feed.engine.set_camera(camera)
        self._log_mounting()

    def _check_imu_axes(self, frame: str) -> None:
        """Before an IMU sample goes in: its frame's axes on /tf_static changed since its last sample
        went in (the IMU's transform arrived after the first samples)."""
        if self.feed.engine is None or not self.rig.imu_axes_changed(frame):
            return
        replays = self.events["rig_replayed"]
        self.rig.refresh()  # the camera's transform may have come with it: one replay for both
        if self.events["rig_replayed"] > replays:
            return
        if self.feed.replayable:
            self._rig_changed(self.rig.camera, f"IMU frame '{frame}' axes (/tf_static)")
        else:  # the engine has no IMU axes: the samples from now on turn, the start stays as it was
            self.events["imu_axes_changed"] += 1
            self.report.log("imu_axes_changed", f"IMU frame '{frame}' axes (/tf_static) changed after the "
                                                "odometry's second frame: the samples from now on are rotated "
                                                "by the new ones", level="info")

    def _camera_tilt_state(self) -> str:
        """/diagnostics: where the start's camera tilt (filter.tilt_from_images) stands."""
        engine = self.engine
        if not getattr(engine, "tilt_from_images", 0):
            return "configured (filter.mounting_pitch)"
        m = engine.tilt_measurement
        if engine.holding:
            return (f"measuring: {engine.held_pairs} of {engine.tilt_from_images} frame pairs, {engine.held_images} "
                    "image(s) held (no odometry until then, but for the frames of a car standing still)")
        if m is None:
            return "configured (filter.mounting_pitch; no road-tilt low-pass: nothing to measure)"
        if not m.measured:
            return f"configured (not measured: {m.reason})"
        return f"measured at the start: {math.degrees(m.change):+.2f} deg from filter.mounting_pitch ({m.pairs} pairs)"

    def _log_mounting(self, engine=None) -> None:
        """Say so when the mounting in use is not the configured one (``filter.mounting_reference:
        camera`` with extrinsics from /tf_static that differ from ``camera.base_T_camera``)."""
        engine = engine or self.feed.engine
        f = self.config.filter
        used = engine.mounting_attitude
        configured = (f.mounting_pitch, f.mounting_roll)
        if used == (self._mounting_logged or configured):
            return
        if max(abs(used[0] - configured[0]), abs(used[1] - configured[1])) > 1e-5:
            self.get_logger().info(
                f"camera extrinsics ({self.rig.extrinsics_source}) differ from camera.base_T_camera, through which "
                f"filter.mounting_pitch/roll were calibrated: the base's mounting {math.degrees(configured[0]):+.3f} / "
                f"{math.degrees(configured[1]):+.3f} deg becomes {math.degrees(used[0]):+.3f} / "
                f"{math.degrees(used[1]):+.3f} deg, keeping the camera's tilt to the road")
        else:
            self.get_logger().info(f"camera extrinsics ({self.rig.extrinsics_source}): the configured mounting again")
        self._mounting_logged = used

    def _guard(self, name: str, fn: Callable) -> Callable:
        """Wrap a callback: an unexpected exception is logged (throttled) and counted, never raised."""

        def wrapped(*args):
            try:
                return fn(*args)
            except Exception as exc:  # noqa: BLE001 - the node must survive anything
                if not self.context.ok():
                    return None  # shutting down (SIGINT): publishers are gone, nothing to report
                self.report.drop("callback_error", f"unexpected {type(exc).__name__} in the {name} callback: "
                                                   f"{exc}\n{traceback.format_exc()}", level="error")
                if name == "reset" and len(args) == 2:  # a service must still answer
                    response = args[1]
                    response.success, response.message = False, f"{type(exc).__name__}: {exc}"
                    return response
                return None

        return wrapped

    def _reset(self) -> None:
        self.feed.reset()
        self._published_stamp = None
        self._path_restart_at = None
        self.intake.clear()  # IMU held for the next image (ordered_intake): the old trajectory's
        self.rig.drop_held("the odometry was reset (time jump or ~/reset) while they waited for a calibration")
        self.outputs.path.clear()
        self.events["reset"] += 1

    # ------------------------------------------------------------------ live parameters
    def _on_parameters_applied(self, params: list) -> None:
        """Apply live parameters (validated by :func:`bevo_ros.ros.settings.check_live`)."""
        for p in (p for p in params if p.name in ros_params.LIVE):
            value = node_settings.live_value(p.name, p.value)
            setattr(self.settings, p.name, value)
            if p.name == "publish_tf":
                self.outputs.set_publish_tf(value)
                if value and self.outputs.tf_backend in ("none", "disabled"):  # said at start only before
                    self.get_logger().warning("publish_tf: no TF message type (tf2_ros or tf2_msgs) in this "
                                              "installation: odom -> base_link is not broadcast")
            elif p.name == "image_wait":  # the flush timer checks at half the wait (at most 50 ms)
                self.destroy_timer(self._flush_timer)
                self._flush_timer = self.create_timer(min(0.05, value / 2),
                                                      self._guard("flush_timer", self._on_flush_timer), clock=self._steady)
            elif p.name == "path_max_length":
                self.outputs.set_path_length(value)
            elif p.name == "max_pending_images" and self.engine is not None:
                self.engine.max_pending_images = value
            elif p.name == "max_time_jump_back":
                for g in self.intake.guards.values():
                    g.max_back = value
                # the /clock jump handler's threshold too (it kept the start's value)
                if self._jump_handle is not None:
                    self._jump_handle.unregister()
                self._jump_handle = watch_clock_jumps(self, value, self._guard("clock_jump", self._on_clock_jump))
            elif p.name in ("imu_timeout", "image_timeout", "speed_timeout"):
                if p.name.split("_")[0] in self.monitors:
                    self.monitors[p.name.split("_")[0]].timeout = value
            elif p.name == "sensor_late_factor":
                for m in self.monitors.values():
                    m.late_factor = value
            self.get_logger().info(f"parameter {p.name} = {value!r} (live)")

    # ------------------------------------------------------------------ callbacks
    def _dispatch(self, kind: str, item: tuple) -> None:
        self._handlers[kind](*item)

    def _on_imu(self, msg, arrival: float = 0.0) -> None:  # counted (and monitored) by the intake
        t = stamp_to_sec(msg.header.stamp)
        gyro, accel = imu_to_arrays(msg)
        self._check_imu_axes(msg.header.frame_id)
        self._publish(self.feed.imu(t, (msg.header.frame_id, gyro, accel)))

    def _on_image(self, msg, arrival: float | None = None) -> None:  # counted (and monitored) by the intake
        arrival = time.time() if arrival is None else arrival
        if not self.rig.calibrated_for(msg):  # held; the first calibration hands them to the engine (_set_camera)
            self.rig.hold(msg, stamp_to_sec(msg.header.stamp), arrival)
            return
        # the tag comes back on the image's step: the output stamp, the latency, image_wait's start
        self._publish(self.feed.image(stamp_to_sec(msg.header.stamp), msg, (msg.header.stamp, arrival, arrival)))

    def _on_flush_timer(self) -> None:
        if self.rig.held_images:  # the parameters' fallback is due even when no further image comes
            self.rig.await_calibration()
        self.intake.release_stale(self.settings.image_wait)  # no image came for the IMU held for one
        if self.feed.held_images:  # the start's pairs, measured in threads, may release it with no new input
            self._publish(self.feed.poll())
        if not self.feed.flush_due():
            return
        if self.settings.ordered_intake:
            self.intake.merge([], [])  # IMU that was only queued, not missing, releases them
            if not self.feed.pending_images and not self.feed.held_images:
                return
        self._publish(self.feed.flush())

    def _on_reset(self, request, response):
        self._reset()
        self.get_logger().info("reset requested: odometry restarted at identity")
        response.success = True
        response.message = "odometry reset: the trajectory restarts at identity"
        return response

    def _on_set_pose(self, msg) -> None:
        """robot_localization's set_pose: the pose of ``base_frame`` in ``odom_frame`` at the stamp
        (0: the latest frame processed, or the first to come). The frames after the stamp compose onto
        it; the path restarts where it takes effect."""
        frame = msg.header.frame_id.lstrip("/")
        if frame not in ("", self.settings.odom_frame):
            self.report.drop("set_pose_frame", f"set_pose in frame '{msg.header.frame_id}': only "
                                               f"'{self.settings.odom_frame}' (the odometry frame) is taken")
            return
        try:
            x, y, z, yaw, planar = planar_pose_from_msg(msg)
        except ValueError as exc:
            self.report.drop("set_pose_invalid", f"set_pose: {exc}")
            return
        stamp = stamp_to_sec(msg.header.stamp)
        if stamp < 0.0:  # taken as 0, "the latest frame", before
            self.report.drop("set_pose_invalid", f"set_pose stamp {stamp:.6f} is negative (0 means the latest frame)")
            return
        newest = self.feed.last_imu_stamp
        if stamp > 0.0 and newest is not None and stamp > newest + self.settings.max_time_jump_forward:
            # no frame would reach it soon, maybe never (a wall-clock stamp into a sim-time replay)
            self.report.drop("set_pose_future", f"set_pose stamp {stamp:.6f} is more than max_time_jump_forward="
                                                f"{self.settings.max_time_jump_forward} s after the newest IMU "
                                                f"sample ({newest:.6f}); stamp 0 means the latest frame")
            return
        request = {"x": x, "y": y, "yaw": yaw, "z": z, "covariance": planar,
                   "stamp": stamp if stamp > 0.0 else None}
        try:
            how = self.feed.set_pose(request)
        except InvalidInputError as exc:
            self.report.drop("set_pose_invalid", f"set_pose: {exc}")
            return
        if how in ("latest", "at stamp", "oldest"):  # in effect now (else when its frame, or the engine, comes)
            self.outputs.path.clear()
            self._path_restart_at = None
        elif how == "waits":  # the path restarts at the first frame published at or after its stamp
            self._path_restart_at = stamp
        self.events["set_pose"] += 1
        when = {"latest": "at the latest frame", "at stamp": f"at {stamp:.6f}", "oldest": (
            f"at the oldest frame kept (its stamp {stamp:.6f} is older)"), "waits": (
            f"at {stamp:.6f}, when a frame reaches it"), "kept": "when the odometry starts"}[how]
        self.get_logger().info(f"pose set to x {x:.3f} y {y:.3f} z {z:.3f} m, yaw {math.degrees(yaw):.2f} deg "
                               f"{when}")

    def _on_speed(self, msg, arrival: float = 0.0) -> None:  # counted by the intake
        """A vehicle speed (``speed_topic``): the motion filter measures each frame's speed with its
        mean over the frame interval, the DUKF removes the car's acceleration with it."""
        stamp = stamp_to_sec(msg.header.stamp)
        try:
            speed, variance, signed = forward_speed_from_msg(msg, self.settings.base_frame, self.settings.speed_variance)
        except ValueError as exc:
            self.report.drop("speed_invalid", f"speed at {stamp:.6f}: {exc}")
            return
        frame = speed_frame(msg)
        if not signed and frame not in self._speed_frames_said:
            self._speed_frames_said.add(frame)
            self.get_logger().warning(f"{self.settings.speed_topic}: the twist is in '{frame}', not base_frame "
                                      f"'{self.settings.base_frame}': its horizontal speed is taken, unsigned "
                                      "(the direction of travel from the images: reversing is followed after a "
                                      "stop they confirm)")
        self._publish(self.feed.speed(stamp, speed, variance, signed))

    def _speed_type_mismatch(self, state):
        """A speed input never heard from whose publishers carry another type than ``speed_type``:
        DDS does not connect them, the state says so (ERROR) and what to set."""
        topic = self.monitors["speed"].topic
        want = node_settings.SPEED_TYPES[self.settings.speed_type]
        types = sorted({info.topic_type for info in self.get_publishers_info_by_topic(topic)} - {want})
        if not types:
            return state
        fix = [k for k, msg_type in node_settings.SPEED_TYPES.items() if msg_type in types]
        return dataclasses.replace(state, level=max(state.level, ERROR), message=(
            f"speed: {topic} is published as {', '.join(types)}, not {want} (speed_type: {self.settings.speed_type})"
            + (f": set speed_type: {fix[0]}" if fix else ": not a speed type bevo_node reads")))

    def _on_clock_jump(self, info) -> None:
        if self.feed.last_imu_stamp is None and not self.feed.pending_images:
            return
        self.events["clock_jump_reset"] += 1
        self.report.log("clock_jump_reset", "ROS time jumped backwards (bag restarted?): resetting the odometry")
        self._reset()
        self.intake.rejudge()  # held messages: judged again on the new timeline

    # ------------------------------------------------------------------ outputs
    def _publish(self, steps: list | None, replayed: bool = False) -> None:
        """Publish the engine's steps; of a replay (:meth:`_rig_changed`) only frames after those
        already published (the first one stays as published: its position is the origin either way)."""
        measured = getattr(self.engine, "tilt_measurement", None)  # duck-typed: a test's engine may not measure
        if measured is not None and measured is not self._tilt_logged:
            self._tilt_logged = measured
            self.report.log("camera_tilt", measured.describe(), level="info")
        for step in steps or ():
            if replayed and self._published_stamp is not None and step.stamp <= self._published_stamp:
                continue
            self._published_stamp = step.stamp
            if self._path_restart_at is not None and step.stamp >= self._path_restart_at:
                self._path_restart_at = None  # a set_pose that waited for this frame: in effect from it
                self.outputs.path.clear()
            stamp, arrival, _ = step.tag
            odom = self.outputs.odometry(step, stamp)
            # held: its image waited for the start's tilt (duck-typed: a test's engine may not hold)
            until = getattr(self.engine, "held_until", None)
            self.report.published(arrival, float(step.peak_quality), held=until is not None and step.stamp <= until)
            self.outputs.extras(step, odom)
        if not self._fast_camera_noted and self.engine is not None and self.engine.counters.frames_out >= 20:
            self._fast_camera_noted = True  # once the frame clock has a period
            if (note := fast_camera_note(self.engine.frame_period, self.engine.min_frame_interval)) is not None:
                self.report.log("fast_camera", note)

    def _publish_diagnostics(self) -> None:
        from diagnostic_msgs.msg import DiagnosticArray

        values = self.report.values(self.feed.pending_images + self.rig.held_images, self.outputs.tf_backend)
        drops, prev_drops = int(values["drops_total"]), self._diag_drops
        self._diag_drops = drops
        self.rig.refresh()  # a /tf_static that arrived (or changed) since
        inputs = {key: m.state() for key, m in self.monitors.items()}  # per input: OK / WARN late / ERROR silent
        if "speed" in inputs and not self.monitors["speed"].received:
            inputs["speed"] = self._speed_type_mismatch(inputs["speed"])
        values["calibration"] = self.rig.calibration.source if self.rig.calibration is not None else "none yet"
        values["extrinsics"] = self.rig.extrinsics_source
        values["direction_of_travel"] = self.engine.direction_of_travel if self.engine is not None else "unknown"
        values["camera_tilt"] = self._camera_tilt_state()
        values["imu_held"] = str(self.intake.hold.held)  # waiting for the next image (ordered_intake)
        if self.engine is not None:  # what the engine takes off the gyro (x, y from standstills, z the motion filter's)
            values["gyro_bias_deg_s"] = ", ".join(f"{math.degrees(b):+.4f}" for b in self.engine.gyro_bias)
        name = self.get_name()
        # a silent speed input is its own ERROR; the odometry goes on on the images: a WARN of it
        for_odometry = {k: dataclasses.replace(st, level=min(st.level, WARN)) if k == "speed" else st
                        for k, st in inputs.items()}
        frames = int(values["odometry_published"])
        blind = sum(int(values.get(f"event.{e}", "0")) for e in BLIND_FRAME_EVENTS)
        beyond = int(values.get("event.beyond_reach", "0"))
        (prev_frames, prev_blind, prev_beyond), self._diag_frames = self._diag_frames, (frames, blind, beyond)
        if self.engine is not None:  # the forward motion a frame past which it counts beyond_reach
            values["reach_m"] = f"{self.engine.reach:.2f}"
        statuses = [status_message(name, "odometry", odometry_state(values, for_odometry, self.engine is not None,
                                                                    drops - prev_drops, frames - prev_frames,
                                                                    blind - prev_blind, beyond - prev_beyond))]
        statuses += [status_message(name, f"{key} input", st) for key, st in inputs.items()]
        statuses.append(status_message(name, "calibration", self.rig.state()))
        msg = DiagnosticArray(status=statuses)
        msg.header.stamp = self.get_clock().now().to_msg()
        self.diag_pub.publish(msg)


def main(args: list[str] | None = None) -> int:
    from bevo_ros.ros_process import run_node

    # every --params-file of the command line: the node resolves learned_params_file beside the one that set it
    return run_node(lambda argv: BevoNode(params_file=ros_params.params_files_from_args(argv)), NODE_NAME, args,
                    refuse=(ConfigError,))


if __name__ == "__main__":
    sys.exit(main())
