"""Shared helpers of the bevo_node tests (no tests here): a small synthetic drive as ROS
messages, the offline reference run, parameters files and a node subprocess.

Every DDS participant of these tests stays on localhost (ROS_AUTOMATIC_DISCOVERY_RANGE) and
each test module uses its own ROS_DOMAIN_ID.
"""
from __future__ import annotations

import contextlib
import functools
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any, Callable

import numpy as np
import yaml

from helpers.env import REPO

KITTI_PARAMS = REPO / "params" / "kitti.yaml"
VENV_BIN = Path(sys.executable).parent

os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")


# ------------------------------------------------------------------------------ synthetic data
def small_camera():
    """The KITTI-like camera at a quarter of the resolution (fast to render and project)."""
    from bevo_ros.core.geometry import CameraModel
    from bevo_ros.datasets.synthetic import kitti_like_camera

    cam = kitti_like_camera()
    K = cam.K.clone()
    K[:2] *= 0.25  # 1241x376 -> ~310x94; a 320x96 image keeps the principal point inside
    return CameraModel(K, 320, 96, cam.T_base_cam.clone(), cam.mount_height)


@functools.lru_cache(maxsize=8)
def small_drive(seed: int = 3, duration: float = 2.0, frame_rate: float = 10.0, imu_rate: float = 100.0):
    from bevo_ros.datasets.synthetic import make_drive

    return make_drive(seed=seed, duration=duration, frame_rate=frame_rate, imu_rate=imu_rate,
                      camera=small_camera(), render=True)


def camera_overrides(camera) -> dict[str, Any]:
    K = camera.K.detach().cpu().double().numpy()
    return {
        "camera.fx": float(K[0, 0]), "camera.fy": float(K[1, 1]),
        "camera.cx": float(K[0, 2]), "camera.cy": float(K[1, 2]),
        "camera.width": int(camera.width), "camera.height_px": int(camera.height_px),
        "camera.mount_height": float(camera.mount_height),
        "camera.base_T_camera": [float(v) for v in camera.T_base_cam.detach().cpu().double().reshape(-1)],
    }


def imu_msg(t: float, gyro, accel, frame_id: str = "imu_link"):
    from sensor_msgs.msg import Imu

    from bevo_ros.io.ros_conversions import sec_to_stamp

    m = Imu()
    m.header.stamp = sec_to_stamp(t)
    m.header.frame_id = frame_id
    m.angular_velocity.x, m.angular_velocity.y, m.angular_velocity.z = (float(v) for v in gyro)
    m.linear_acceleration.x, m.linear_acceleration.y, m.linear_acceleration.z = (float(v) for v in accel)
    return m


def image_msg(t: float, img: np.ndarray, encoding: str = "mono8", frame_id: str = "camera"):
    from bevo_ros.io.ros_conversions import gray_to_image_msg, sec_to_stamp

    m = gray_to_image_msg(img, encoding=encoding)
    m.header.stamp = sec_to_stamp(t)
    m.header.frame_id = frame_id
    return m


def drive_messages(drive, start: int = 0, stop: int | None = None, offset: float = 0.0) -> list[tuple[str, Any]]:
    """``[("imu"|"image", msg)]`` in stamp order (an image after the IMU sample of its stamp);
    ``offset`` seconds are added to every stamp."""
    frames = {int(i): k for k, i in enumerate(drive.frame_imu_index)}
    out = []
    for i in range(start, len(drive.imu_stamps) if stop is None else stop):
        t = float(drive.imu_stamps[i]) + offset
        out.append(("imu", imu_msg(t, drive.gyro[i], drive.accel[i])))
        if i in frames:
            out.append(("image", image_msg(t, drive.images[frames[i]])))
    return out


def with_wheel_speed(drive, messages: list[tuple[str, Any]], scale: float = 1.0) -> list[tuple[str, Any]]:
    """``messages`` with a wheel odometry (nav_msgs/Odometry, ``base_link``, the drive's true speed
    times ``scale``) after each IMU sample, at its stamp."""
    from nav_msgs.msg import Odometry

    speeds = iter(np.linalg.norm(drive.imu_velocity_gravity, axis=1))
    out = []
    for kind, msg in messages:
        out.append((kind, msg))
        if kind == "imu":
            odom = Odometry()
            odom.header.stamp, odom.header.frame_id, odom.child_frame_id = msg.header.stamp, "odom", "base_link"
            odom.twist.twist.linear.x = float(next(speeds)) * scale
            out.append(("speed", odom))
    return out


def delivered_late(messages: list[tuple[str, Any]], delay: int) -> list[tuple[str, Any]]:
    """``[(kind, item)]`` in stamp order with every ``"image"`` delivered after the next ``delay``
    ``"imu"`` messages (images keep their own order): a large image behind the small IMU messages
    published after it (DDS orders no topic against another)."""
    out: list[tuple[str, Any]] = []
    waiting: list[list] = []  # [image, IMU messages still to come before it]
    for e in messages:
        if e[0] == "image":
            waiting.append([e, delay])
        else:
            out.append(e)
            for w in waiting:
                w[1] -= 1
        while waiting and waiting[0][1] <= 0:
            out.append(waiting.pop(0)[0])
    return out + [w[0] for w in waiting]


def tf_static_msg(transforms):
    """A tf2_msgs/TFMessage of ``[(parent, child, T (4, 4))]``, as a robot's /tf_static carries them."""
    from geometry_msgs.msg import TransformStamped
    from tf2_msgs.msg import TFMessage

    from bevo_ros.rotations import quaternion_from_matrix

    msg = TFMessage()
    for parent, child, T in transforms:
        t = TransformStamped()
        t.header.frame_id, t.child_frame_id = parent, child
        t.transform.translation.x, t.transform.translation.y, t.transform.translation.z = (float(v) for v in T[:3, 3])
        q = quaternion_from_matrix(T[:3, :3])
        t.transform.rotation.x, t.transform.rotation.y, t.transform.rotation.z, t.transform.rotation.w = \
            (float(v) for v in q)
        msg.transforms.append(t)
    return msg


def pitched(T: np.ndarray, degrees: float) -> np.ndarray:
    """``T_base_cam`` with the camera pitched ``degrees`` more nose down about the base's y axis."""
    a = np.radians(degrees)
    R = np.array([[np.cos(a), 0.0, np.sin(a)], [0.0, 1.0, 0.0], [-np.sin(a), 0.0, np.cos(a)]])
    out = T.copy()
    out[:3, :3] = R @ T[:3, :3]
    return out


def offline_steps(messages: list[tuple[str, Any]], overrides: dict[str, Any]) -> list:
    """The offline core (``build_odometry``) fed the same messages in order; an engine still holding its start
    for the camera's tilt (its pairs measured in threads, not yet all done) is flushed, as the node flushes
    held images after ``image_timeout``."""
    from bevo_ros.config import BevoConfig, build_odometry, camera_model, resolve_path
    from bevo_ros.io.learned_params import load_learned_params
    from bevo_ros.io.ros_conversions import forward_speed_from_msg, image_to_gray, imu_to_arrays, stamp_to_sec

    config = BevoConfig.from_flat(overrides)
    learned = load_learned_params(resolve_path(config.learned_params_file))
    odo = build_odometry(config, learned, camera_model(config.camera))
    steps = []
    for kind, msg in messages:
        t = stamp_to_sec(msg.header.stamp)
        if kind == "imu":
            steps += odo.add_imu(t, *imu_to_arrays(msg))
        elif kind == "speed":  # as bevo_node's speed_topic (its defaults: base_link, 0.01 (m/s)^2)
            odo.add_speed(t, *forward_speed_from_msg(msg, overrides.get("base_frame", "base_link"),
                                                     overrides.get("speed_variance", 0.01)))
        else:
            steps += odo.add_image(t, image_to_gray(msg))
    return steps + (odo.flush() if odo.holding else [])


# ------------------------------------------------------------------------------ parameters files
def write_params(path: Path, overrides: dict[str, Any], base: Path = KITTI_PARAMS) -> Path:
    """``base`` (a bevo_node parameters file) with ``overrides`` applied, written to ``path``."""
    doc = yaml.safe_load(base.read_text())
    params = (doc.get("/**") or doc["bevo_node"])["ros__parameters"]
    for k, v in overrides.items():
        params[k] = v
    if not Path(str(params.get("learned_params_file", ""))).is_absolute():
        params["learned_params_file"] = str(REPO / params["learned_params_file"])
    path.write_text(yaml.safe_dump(doc, sort_keys=False))
    return path


# ------------------------------------------------------------------------------ node subprocess
class NodeProcess:
    """``bevo_node --ros-args --params-file ...`` as a subprocess; output collected in ``lines``."""

    def __init__(self, params_file: Path, domain_id: str, extra_args: list[str] | None = None,
                 executable: Path | None = None, env: dict[str, str] | None = None):
        exe = executable or (VENV_BIN / "bevo_node")
        self.cmd = [str(exe), "--ros-args", "--params-file", str(params_file)] + list(extra_args or [])
        self.env = dict(os.environ, ROS_DOMAIN_ID=domain_id, ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST",
                        PYTHONUNBUFFERED="1", RCUTILS_LOGGING_BUFFERED_STREAM="0", **(env or {}))
        self.lines: list[str] = []
        self.proc: subprocess.Popen | None = None
        self._reader: threading.Thread | None = None

    def start(self) -> "NodeProcess":
        self.proc = subprocess.Popen(self.cmd, env=self.env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                                     text=True, cwd=REPO)

        def read() -> None:
            for line in self.proc.stdout:
                self.lines.append(line)

        self._reader = threading.Thread(target=read, daemon=True)
        self._reader.start()
        return self

    @property
    def output(self) -> str:
        return "".join(self.lines)

    def wait_for(self, text: str, timeout: float = 60.0) -> bool:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if text in self.output:
                return True
            if self.proc.poll() is not None:
                time.sleep(0.2)
                return text in self.output
            time.sleep(0.05)
        return False

    def wait_exit(self, timeout: float = 60.0) -> int:
        rc = self.proc.wait(timeout=timeout)
        if self._reader:
            self._reader.join(timeout=5)
        return rc

    def interrupt(self, timeout: float = 20.0) -> int:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGINT)
        return self.wait_exit(timeout)

    def kill(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait()


def spin_until(executor, cond: Callable[[], bool], timeout: float = 10.0, step: float = 0.005) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if cond():
            return True
        executor.spin_once(timeout_sec=step)
    return cond()


class OdometryListener:
    """A tester node on ``domain_id`` collecting ``/bevo/odometry`` (reliable, deep) into ``odom``;
    ``spin_until(cond, timeout)`` spins it; ``close()`` tears it down."""

    def __init__(self, domain_id: int, name: str) -> None:
        import rclpy
        from nav_msgs.msg import Odometry
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.qos import QoSProfile, ReliabilityPolicy

        os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
        self.context = rclpy.context.Context()
        rclpy.init(context=self.context, domain_id=domain_id)
        self.node = rclpy.create_node(name, context=self.context)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self.odom: list = []
        self.node.create_subscription(Odometry, "/bevo/odometry", self.odom.append,
                                      QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE))

    def spin_until(self, cond: Callable[[], bool], timeout: float) -> bool:
        return spin_until(self.executor, cond, timeout)

    def wait_for_publisher(self, timeout: float = 30.0) -> bool:
        """Until the node's odometry publisher is discovered (its volatile messages published before
        that would be lost to this listener), plus a moment for the reliable match."""
        found = self.spin_until(lambda: self.node.count_publishers("/bevo/odometry") > 0, timeout)
        self.spin_until(lambda: False, 0.5)
        return found

    def positions(self) -> np.ndarray:
        """``(N, 3)`` stamp, x, y of the odometry received."""
        return np.array([[m.header.stamp.sec + m.header.stamp.nanosec * 1e-9, m.pose.pose.position.x,
                          m.pose.pose.position.y] for m in self.odom])

    def close(self) -> None:
        import rclpy

        self.executor.remove_node(self.node)
        self.node.destroy_node()
        rclpy.shutdown(context=self.context)



REPLAY_PARAMS = REPO / "params" / "replay.yaml"


@contextlib.contextmanager
def replay_into_node(params_file: Path, domain_id: int, name: str, bag_path: Path, play_args: list[str],
                     node_args: list[str] | None = None):
    """bevo_node on ``params_file`` + params/replay.yaml (the product's replay overlay) + ``node_args``
    (e.g. ``-p name:=value``), an :class:`OdometryListener`, and ``bevo play BAG play_args`` started once
    the node is ready and its odometry publisher discovered. Yields ``(node, listener, play)``; stops
    the node and the listener."""
    node = NodeProcess(params_file, str(domain_id),
                       extra_args=["--params-file", str(REPLAY_PARAMS), *(node_args or [])]).start()
    listener = OdometryListener(domain_id, name)
    try:
        assert node.wait_for("ready:", 90), f"bevo_node did not start:\n{node.output}"
        assert listener.wait_for_publisher(), "the odometry publisher was not discovered"
        env = dict(os.environ, ROS_DOMAIN_ID=str(domain_id), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST")
        play = subprocess.Popen([str(VENV_BIN / "python"), "-m", "bevo_ros.cli", "play", str(bag_path), *play_args],
                                env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        yield node, listener, play
    finally:
        node.interrupt()
        listener.close()
