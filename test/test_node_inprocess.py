"""bevo_node in-process: an executor, synthetic messages in through DDS (localhost), odometry out.

* The node's odometry on a synthetic drive equals the offline core's (``build_odometry`` fed the
  same messages in stamp order) within 1e-6; stamps are copied from the image headers.
* Every kind of bad input is dropped, counted and logged with its reason; the node survives.
* ``~/reset``, TF (tf2_msgs fallback, or disabled with one clear message), CameraInfo, the
  image wait, use_sim_time with a /clock jump, path/BEV/diagnostics outputs.
"""
from __future__ import annotations

import copy
import math
import sys
from pathlib import Path

import numpy as np
import pytest

from helpers.node_support import (camera_overrides, delivered_late, drive_messages, image_msg, imu_msg,  # noqa: E402
                                  offline_steps, pitched, small_drive, spin_until, tf_static_msg, with_wheel_speed)

rclpy = pytest.importorskip("rclpy")
from diagnostic_msgs.msg import DiagnosticArray  # noqa: E402
from nav_msgs.msg import Odometry, Path as PathMsg  # noqa: E402
from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy  # noqa: E402
from sensor_msgs.msg import CameraInfo, Image, Imu  # noqa: E402
from std_srvs.srv import Trigger  # noqa: E402

from bevo_ros.config import ConfigError  # noqa: E402
from bevo_ros.io.ros_conversions import stamp_to_sec  # noqa: E402
from bevo_ros.rotations import rpy_from_quaternion  # noqa: E402

from helpers.env import import_outside_ci, in_ci  # noqa: E402
from helpers.ros import domain_id_for, ros_context  # noqa: E402

DOMAIN_ID = domain_id_for(11)
pytestmark = [pytest.mark.ros, pytest.mark.timeout(180)]
RELIABLE = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE)


@pytest.fixture(scope="module")
def context():
    yield from ros_context(DOMAIN_ID)


@pytest.fixture(scope="module")
def drive():
    return small_drive(duration=1.2)  # 13 frames, 121 IMU samples


def base_overrides(drive, **extra):
    ov = camera_overrides(drive.camera)
    ov.update(input_qos="reliable", imu_qos_depth=1000, image_qos_depth=100, log_throttle_period=0.0,
              diagnostics_period=0.2, use_camera_info=False)  # the camera.* parameters only (CameraInfo: below)
    ov.update(extra)
    return ov


class Harness:
    """The node under test plus a tester node (publishers, subscribers) on one executor."""

    def __init__(self, context, overrides: dict, topics_prefix: str = "", subscribe_outputs: bool = True,
                 engine_factory=None, node_name: str = "bevo_node"):
        from bevo_ros.node import BevoNode

        self.ns = topics_prefix
        ov = dict(overrides)
        for key, default in (("imu_topic", "/imu/data"), ("image_topic", "/camera/image_raw"),
                             ("camera_info_topic", "/camera/camera_info"), ("odometry_topic", "/bevo/odometry"),
                             ("path_topic", "/bevo/path"), ("bev_image_topic", "/bevo/bev_image")):
            ov.setdefault(key, topics_prefix + default)
        self.topics = ov
        params = [Parameter(k, value=v) for k, v in ov.items()]
        self.node = BevoNode(context=context, parameter_overrides=params, engine_factory=engine_factory,
                             node_name=node_name)
        self.tester = rclpy.create_node("tester" + topics_prefix.replace("/", "_"), context=context)
        self.executor = SingleThreadedExecutor(context=context)
        self.executor.add_node(self.node)
        self.executor.add_node(self.tester)
        t = self.tester
        self.imu_pub = t.create_publisher(Imu, ov["imu_topic"], RELIABLE)
        self.image_pub = t.create_publisher(Image, ov["image_topic"], RELIABLE)
        self.info_pub = t.create_publisher(CameraInfo, ov["camera_info_topic"], RELIABLE)
        self.odom, self.tf, self.diag, self.paths, self.bevs = [], [], [], [], []
        t.create_subscription(Odometry, ov["odometry_topic"], self.odom.append, RELIABLE)
        t.create_subscription(DiagnosticArray, "/diagnostics", self.diag.append, 10)
        if subscribe_outputs:
            try:
                from tf2_msgs.msg import TFMessage

                t.create_subscription(TFMessage, "/tf", self.tf.append, QoSProfile(depth=100))
            except ImportError:
                pass
            t.create_subscription(PathMsg, ov["path_topic"], self.paths.append, 10)
            t.create_subscription(Image, ov["bev_image_topic"], self.bevs.append, 10)
        self.speed_pub = t.create_publisher(Odometry, ov["speed_topic"], RELIABLE) if ov.get("speed_topic") else None
        wanted = [self.imu_pub, self.image_pub] + ([self.info_pub] if ov.get("use_camera_info") else []) + \
            ([self.speed_pub] if self.speed_pub else [])
        assert spin_until(self.executor, lambda: all(p.get_subscription_count() > 0 for p in wanted), 10), \
            "the node's subscriptions were not discovered"
        assert spin_until(self.executor, lambda: self.node.outputs.odom_pub.get_subscription_count() > 0, 10)
        if subscribe_outputs:
            spin_until(self.executor, lambda: self.node.outputs.bev_pub.get_subscription_count() > 0, 10)

    def send(self, kind: str, msg, timeout: float = 10.0) -> None:
        """Publish one message and spin until the node has taken it (lock-step, deterministic)."""
        key = {"imu": "imu_in", "image": "images_in", "info": "camera_info_in", "speed": "speed_in"}[kind]
        before = self.node.counts[key]
        {"imu": self.imu_pub, "image": self.image_pub, "info": self.info_pub, "speed": self.speed_pub}[kind].publish(msg)
        assert spin_until(self.executor, lambda: self.node.counts[key] > before, timeout), f"{kind} not received"

    def send_all(self, messages) -> None:
        for kind, msg in messages:
            self.send(kind, msg)

    def settle(self, timeout: float = 5.0) -> None:
        """Spin until every published odometry message has been received."""
        spin_until(self.executor, lambda: len(self.odom) >= self.node.counts["odometry_out"], timeout)
        self.executor.spin_once(timeout_sec=0.02)

    def set_clock(self, stamp) -> None:
        """Publish ``stamp`` on /clock (use_sim_time) and spin until the node's clock reads it."""
        from rosgraph_msgs.msg import Clock

        if getattr(self, "_clock_pub", None) is None:
            self._clock_pub = self.tester.create_publisher(Clock, "/clock", 10)
            assert spin_until(self.executor, lambda: self._clock_pub.get_subscription_count() > 0, 5)
        self._clock_pub.publish(Clock(clock=stamp))
        target = stamp_to_sec(stamp)
        assert spin_until(self.executor, lambda: abs(self.node.get_clock().now().nanoseconds * 1e-9 - target) < 1e-6, 5)

    def logged(self, reason: str) -> list[str]:
        return [text for key, text in self.node.log_history if key == reason]

    def close(self) -> None:
        self.executor.remove_node(self.node)
        self.executor.remove_node(self.tester)
        self.node.destroy_node()
        self.tester.destroy_node()
        self.executor.shutdown()


@pytest.fixture
def harness_factory(context):
    made = []

    def make(overrides, **kw):
        h = Harness(context, overrides, **kw)
        made.append(h)
        return h

    yield make
    for h in made:
        h.close()


def _odom_arrays(msg: Odometry):
    p, q = msg.pose.pose.position, msg.pose.pose.orientation
    tw = msg.twist.twist
    return (np.array([p.x, p.y, p.z]), np.array(rpy_from_quaternion(q.x, q.y, q.z, q.w)),
            np.asarray(msg.pose.covariance).reshape(6, 6), np.array([tw.linear.x, tw.linear.y, tw.linear.z]),
            np.array([tw.angular.x, tw.angular.y, tw.angular.z]), np.asarray(msg.twist.covariance).reshape(6, 6))


# ------------------------------------------------------------------------------------ behaviour
def test_odometry_equals_offline_core(harness_factory, drive):
    ov = base_overrides(drive, path_max_length=5)
    messages = drive_messages(drive)
    expected = offline_steps(messages, ov)
    assert len(expected) == drive.num_frames
    h = harness_factory(ov)
    h.send_all(messages)
    h.settle()
    assert len(h.odom) == len(expected), (len(h.odom), len(expected), dict(h.node.drops))
    images = [m for k, m in messages if k == "image"]
    for msg, step, img in zip(h.odom, expected, images):
        assert msg.header.stamp == img.header.stamp  # copied, never now()
        assert (msg.header.frame_id, msg.child_frame_id) == ("odom", "base_link")
        pos, rpy, pcov, lin, ang, tcov = _odom_arrays(msg)
        assert np.allclose(pos, step.position, atol=1e-6, rtol=0)
        assert np.allclose(np.angle(np.exp(1j * (rpy - step.rpy))), 0, atol=1e-6)
        assert np.allclose(pcov, step.pose_covariance, atol=1e-6, rtol=1e-9)
        assert np.allclose(lin, step.twist_linear, atol=1e-6, rtol=0)
        assert np.allclose(ang, step.twist_angular, atol=1e-6, rtol=0)
        assert np.allclose(tcov, step.twist_covariance, atol=1e-6, rtol=1e-9)
    assert sum(h.node.drops.values()) == 0, dict(h.node.drops)
    # the drive moves: the odometry is not a constant
    assert np.linalg.norm(_odom_arrays(h.odom[-1])[0]) > 1.0

    # TF through the locally built tf2_msgs (or tf2_ros), one transform per odometry message
    assert h.node.outputs.tf_backend != "none" or not in_ci(), "no TF backend: CI=true requires tf2_msgs (make setup)"
    if h.node.outputs.tf_backend != "none":
        assert spin_until(h.executor, lambda: len(h.tf) >= len(h.odom), 5)
        tf = h.tf[-1].transforms[0]
        assert (tf.header.frame_id, tf.child_frame_id) == ("odom", "base_link")
        assert tf.header.stamp == h.odom[-1].header.stamp
        assert tf.transform.translation.x == h.odom[-1].pose.pose.position.x
    # bounded path, BEV image (subscribed), diagnostics with rates and latency
    assert spin_until(h.executor, lambda: len(h.paths) >= len(h.odom), 5)
    assert len(h.paths[-1].poses) == 5 and h.paths[-1].poses[-1].header.stamp == h.odom[-1].header.stamp
    assert spin_until(h.executor, lambda: len(h.bevs) >= len(h.odom), 5)
    bev = h.bevs[-1]
    assert bev.encoding == "mono8" and bev.height == 100 and bev.width >= 100
    assert bev.header.stamp == h.odom[-1].header.stamp
    h.diag.clear()
    assert spin_until(h.executor, lambda: len(h.diag) > 0, 5)
    values = {kv.key: kv.value for kv in h.diag[-1].status[0].values}
    for key in ("imu_rate_hz", "image_rate_hz", "odometry_rate_hz", "latency_p50_ms", "latency_p99_ms",
                "peak_quality_mean", "drops_total"):
        assert key in values, values
    assert values["drops_total"] == "0" and int(values["odometry_published"]) == len(expected)
    assert 0.0 <= float(values["peak_quality_mean"]) <= 1.0
    # the gyro biases the engine takes off, deg/s (x, y from standstills, z the motion filter's)
    assert [float(v) for v in values["gyro_bias_deg_s"].split(",")] == pytest.approx(
        [math.degrees(b) for b in h.node.engine.gyro_bias], abs=1e-4)
    p50, p99, _ = h.node.report.latency_percentiles()
    assert 0 < p50 <= p99 < 60.0  # figures: tools/bench_node.py


def test_a_speed_topic_is_fused_as_offline(harness_factory, drive):
    """speed_topic (wheel odometry here): the node's odometry equals the offline core fed the same
    speeds; the speed sets the scale (a wheel 3 % long: the odometry 3 % long); a speed that is not
    finite is dropped and counted."""
    ov = base_overrides(drive, speed_topic="/wheel/odometry", speed_timeout=0.3)
    plain = drive_messages(drive)
    truth = offline_steps(with_wheel_speed(drive, plain), ov)
    long = with_wheel_speed(drive, plain, scale=1.03)
    expected = offline_steps(long, ov)
    h = harness_factory(ov)
    h.send_all(long)
    h.settle()
    assert len(h.odom) == len(expected) == drive.num_frames, (len(h.odom), dict(h.node.drops))
    for msg, step in zip(h.odom, expected):
        assert np.allclose(_odom_arrays(msg)[0], step.position, atol=1e-6, rtol=0)
    path = lambda steps: sum(float(np.hypot(*s.motion[:2])) for s in steps[1:])  # noqa: E731
    ratio = path(expected) / path(truth)
    print(f"\nspeed_topic: {h.node.counts['speed_in']} speeds; a wheel 3 % long -> a path {100 * (ratio - 1):+.2f} % long")
    assert 1.02 < ratio < 1.04
    assert h.node.counts["speed_in"] == sum(k == "speed" for k, _ in long) and sum(h.node.drops.values()) == 0
    bad = [m for k, m in long if k == "speed"][-1]
    bad.twist.twist.linear.x = float("nan")
    h.send("speed", bad)
    assert h.node.drops["speed_invalid"] == 1 and h.logged("speed_invalid")
    bad.twist.twist.linear.x = 5.0
    bad.header.stamp.sec -= 100  # far back (another clock, a restarted driver): dropped, never a reset
    h.send("speed", bad)
    assert h.node.drops["speed_out_of_order"] == 1 and h.node.events["time_jump_reset"] == 0
    bad.header.stamp.sec += 200  # far ahead of the IMU: dropped, or every later speed would be out of order
    h.send("speed", bad)
    assert h.node.drops["speed_future"] == 1
    # wheel odometry in base_link is signed; a twist in another frame reaches the engine unsigned (its
    # sign then the direction of travel's), with one warning
    assert h.node.engine._speed_unsigned is False
    gnss = copy.deepcopy(bad)
    gnss.child_frame_id = "gnss"
    gnss.header.stamp.sec -= 100  # 1 us after the last speed
    gnss.header.stamp.nanosec += 1000
    h.send("speed", gnss)
    assert h.node.engine._speed_unsigned is True and h.node._speed_frames_said == {"gnss"}
    # /diagnostics: the speed input's own status; silent past speed_timeout it is an ERROR, which
    # makes the odometry (going on on the images) no more than a WARN

    def levels():
        return {st.name.split(": ", 1)[1]: st.level[0] if isinstance(st.level, bytes) else int(st.level)
                for st in h.diag[-1].status} if h.diag else {}

    assert spin_until(h.executor, lambda: levels().get("speed input") == 2, 5), levels()
    odometry = next(st for st in h.diag[-1].status if st.name.endswith(": odometry"))
    assert {kv.key: kv.value for kv in odometry.values}["speeds_received"] == str(h.node.counts["speed_in"])
    got = levels()
    if max(got["imu input"], got["image input"]) < 2:
        assert got["odometry"] < 2, got


def test_a_speed_topic_of_another_type_is_named_in_diagnostics(harness_factory, drive):
    """speed_type says nav_msgs/Odometry, the car publishes TwistStamped: DDS never connects them, and
    the speed input's status says what to set instead of a bare silence. (One DDS participant cannot
    hold both types on a topic: the graph's answer is given to the node here.)"""
    from types import SimpleNamespace

    h = harness_factory(base_overrides(drive, speed_topic="/wheel/speed"))
    graph = h.node.get_publishers_info_by_topic
    h.node.get_publishers_info_by_topic = lambda topic: graph(topic) + [
        SimpleNamespace(topic_type="geometry_msgs/msg/TwistStamped")]

    def speed_status():
        return next((st for m in reversed(h.diag) for st in m.status if st.name.endswith(": speed input")), None)

    assert spin_until(h.executor, lambda: (st := speed_status()) is not None and "set speed_type: twist" in st.message,
                      5), speed_status()
    st = speed_status()
    assert st.level == bytes([2]) and "/wheel/speed is published as geometry_msgs/msg/TwistStamped" in st.message


@pytest.mark.parametrize("imu_rate", [10.0, 400.0])
def test_imu_rates_10_to_400_hz_match_offline(harness_factory, imu_rate):
    drive = small_drive(seed=4, duration=0.6 if imu_rate > 100 else 1.5, imu_rate=imu_rate)
    ov = base_overrides(drive)
    messages = drive_messages(drive)
    expected = offline_steps(messages, ov)
    h = harness_factory(ov, subscribe_outputs=False)
    h.send_all(messages)
    h.settle()
    assert len(h.odom) == len(expected) == drive.num_frames and sum(h.node.drops.values()) == 0
    for msg, step in zip(h.odom, expected):
        assert np.allclose(_odom_arrays(msg)[0], step.position, atol=1e-6, rtol=0)
        assert np.allclose(np.asarray(msg.pose.covariance).reshape(6, 6), step.pose_covariance, atol=1e-6, rtol=1e-9)


def test_reset_service_restarts_at_identity(harness_factory, drive):
    h = harness_factory(base_overrides(drive), subscribe_outputs=False)
    messages = drive_messages(drive)
    h.send_all(messages[: len(messages) // 2])
    h.settle()
    assert np.linalg.norm(_odom_arrays(h.odom[-1])[0]) > 0.5
    client = h.tester.create_client(Trigger, "/bevo_node/reset")
    assert client.wait_for_service(timeout_sec=5)
    future = client.call_async(Trigger.Request())
    assert spin_until(h.executor, future.done, 5)
    assert future.result().success and "identity" in future.result().message
    n = len(h.odom)
    h.send_all(messages[len(messages) // 2:])
    h.settle()
    assert len(h.odom) > n
    first_after = _odom_arrays(h.odom[n])
    assert np.allclose(first_after[0], 0.0) and abs(first_after[1][2]) < 1e-12
    assert h.node.events["reset"] >= 1


def _set_pose_msg(x: float, y: float, z: float, yaw: float, stamp: float, frame: str = "odom", var=(0.04, 0.09, 0.01),
                  cross: dict | None = None):
    from geometry_msgs.msg import PoseWithCovarianceStamped

    from bevo_ros.io.ros_conversions import sec_to_stamp

    m = PoseWithCovarianceStamped()
    m.header.frame_id, m.header.stamp = frame, sec_to_stamp(stamp)
    m.pose.pose.position.x, m.pose.pose.position.y, m.pose.pose.position.z = x, y, z
    m.pose.pose.orientation.z, m.pose.pose.orientation.w = math.sin(yaw / 2), math.cos(yaw / 2)
    cov = np.zeros((6, 6))
    cov[0, 0], cov[1, 1], cov[5, 5] = var
    cov[2, 2] = cov[3, 3] = cov[4, 4] = 99.0  # z, roll, pitch: not set
    for (r, c), v in (cross or {}).items():
        cov[r, c] = cov[c, r] = v
    m.pose.covariance = cov.reshape(-1).tolist()
    return m


def _planar(pos, yaw) -> tuple[float, float, float]:
    return float(pos[0]), float(pos[1]), float(yaw)


def _relative(a, b) -> np.ndarray:
    """Planar pose ``b`` in the frame of ``a`` (x, y, yaw)."""
    c, s = math.cos(a[2]), math.sin(a[2])
    d = np.subtract(b[:2], a[:2])
    return np.array([c * d[0] + s * d[1], -s * d[0] + c * d[1], math.remainder(b[2] - a[2], 2 * math.pi)])


def test_set_pose_moves_the_odometry_from_its_stamp(harness_factory, drive):
    """robot_localization's set_pose: the pose at the message's stamp, here a frame already published;
    the frames after it go on from there with the offline run's motion; other frames and bad poses are dropped."""
    ov = base_overrides(drive)
    messages = drive_messages(drive)
    expected = offline_steps(messages, ov)
    h = harness_factory(ov, subscribe_outputs=False)
    pub = h.tester.create_publisher(type(_set_pose_msg(0, 0, 0, 0, 1.0)), "/bevo/set_pose", 10)
    assert spin_until(h.executor, lambda: pub.get_subscription_count() > 0, 10)
    half = len(messages) // 2
    h.send_all(messages[:half])
    h.settle()
    n, j = len(h.odom), 2  # the pose is set at frame j's stamp, frames j+1 .. n-1 already out
    assert n > j + 2
    given = (5.0, -3.0, 1.0)
    stamp_j = stamp_to_sec(h.odom[j].header.stamp)
    newest = stamp_to_sec(messages[half - 1][1].header.stamp)
    for bad, reason in ((_set_pose_msg(*given[:2], 0.0, given[2], stamp_j, frame="map"), "set_pose_frame"),
                        (_set_pose_msg(*given[:2], 0.0, given[2], stamp_j, var=(-1.0, 0.1, 0.1)), "set_pose_invalid"),
                        (_set_pose_msg(*given[:2], 0.0, given[2], newest + 5.0), "set_pose_future")):
        pub.publish(bad)
        assert spin_until(h.executor, lambda: h.node.drops[reason] == 1, 5), dict(h.node.drops)
    pub.publish(_set_pose_msg(*given[:2], 1.5, given[2], stamp_j))
    assert spin_until(h.executor, lambda: h.node.events["set_pose"] == 1, 5)
    h.send_all(messages[half:])
    h.settle()
    assert len(h.odom) == len(expected)
    for k in range(n):  # published before it: as they were
        assert np.allclose(_odom_arrays(h.odom[k])[0], expected[k].position, atol=1e-6, rtol=0)
    ref = _planar(expected[j].position, expected[j].rpy[2])
    for msg, step in zip(h.odom[n:], expected[n:]):
        pos, rpy = _odom_arrays(msg)[:2]
        want = _relative(ref, _planar(step.position, step.rpy[2]))
        assert np.allclose(_relative(given, _planar(pos, rpy[2])), want, atol=1e-6), (msg.header.stamp, want)
        assert pos[2] == pytest.approx(1.5) and np.allclose(rpy[:2], step.rpy[:2], atol=1e-9)  # attitude measured
    cov = np.asarray(h.odom[-1].pose.covariance).reshape(6, 6)
    assert cov[0, 0] > 0.04 and cov[5, 5] > 0.01  # the pose's own, grown by the frames after it
    assert np.linalg.norm(_odom_arrays(h.odom[-1])[0][:2] - given[:2]) > 1.0
    assert "only 'odom'" in h.logged("set_pose_frame")[0]


def test_a_pose_set_before_the_calibration_is_the_first_frames(harness_factory, drive):
    ov = base_overrides(drive, use_camera_info=True)
    for k in ("camera.fx", "camera.fy", "camera.cx", "camera.cy"):
        ov[k] = 0.0
    ov["camera.width"] = ov["camera.height_px"] = 0
    h = harness_factory(ov, subscribe_outputs=False)
    assert h.node.engine is None
    pub = h.tester.create_publisher(type(_set_pose_msg(0, 0, 0, 0, 1.0)), "/bevo/set_pose", 10)
    assert spin_until(h.executor, lambda: pub.get_subscription_count() > 0, 10)
    pub.publish(_set_pose_msg(2.0, 3.0, 0.0, -0.5, 0.0, cross={(0, 1): 0.01, (0, 5): 0.005, (1, 5): -0.004,
                                                                (0, 2): 7.0}))  # stamp 0: here the first frame
    assert spin_until(h.executor, lambda: h.node.events["set_pose"] == 1, 5)
    K = drive.camera.K.double().numpy()
    info = CameraInfo(width=drive.camera.width, height=drive.camera.height_px)
    info.k = K.reshape(-1).tolist()
    info.p = np.hstack([K, np.zeros((3, 1))]).reshape(-1).tolist()
    h.send("info", info)
    h.send_all(drive_messages(drive)[:40])
    h.settle()
    assert h.node.engine is not None and len(h.odom) >= 2
    pos, rpy = _odom_arrays(h.odom[0])[:2]
    assert np.allclose(pos, [2.0, 3.0, 0.0], atol=1e-9) and rpy[2] == pytest.approx(-0.5, abs=1e-9)
    cov = np.asarray(h.odom[0].pose.covariance).reshape(6, 6)
    planar = cov[np.ix_([0, 1, 5], [0, 1, 5])]
    assert np.allclose(planar, [[0.04, 0.01, 0.005], [0.01, 0.09, -0.004], [0.005, -0.004, 0.01]], atol=1e-12)
    assert cov[0, 2] == 0.0  # the (x, z) entry given is not the engine's: z is not estimated


def test_time_jump_back_resets_and_small_steps_back_are_dropped(harness_factory, drive):
    h = harness_factory(base_overrides(drive, max_time_jump_back=0.5), subscribe_outputs=False)
    messages = drive_messages(drive)
    h.send_all(messages[:90])  # ~0.8 s of the drive
    h.settle()
    # duplicate and slightly out-of-order IMU and image stamps: dropped, counted, logged
    last_imu = [m for k, m in messages[:90] if k == "imu"][-1]
    h.send("imu", last_imu)
    t_last = stamp_to_sec(last_imu.header.stamp)
    h.send("imu", imu_msg(t_last - 0.005, [0, 0, 0], [0, 0, 9.8]))
    last_img = [m for k, m in messages[:90] if k == "image"][-1]
    h.send("image", last_img)
    assert h.node.drops["imu_duplicate"] == 1 and h.node.drops["imu_out_of_order"] == 1
    assert h.node.drops["image_duplicate"] == 1
    assert "is not after the previous IMU stamp" in h.logged("imu_out_of_order")[0]
    n = len(h.odom)
    # the bag restarts: stamps jump back by the whole drive -> clean reset, odometry restarts
    h.send_all(messages)
    h.settle()
    assert h.node.events["time_jump_back"] == 1 and h.node.drops["stamp_outlier"] == 0  # confirmed, nothing lost
    assert len(h.odom) - n == drive.num_frames
    assert np.allclose(_odom_arrays(h.odom[n])[0], 0.0)
    assert h.odom[n].header.stamp == messages[1][1].header.stamp


def test_bad_inputs_are_dropped_counted_and_logged(harness_factory, drive):
    h = harness_factory(base_overrides(drive, **{"filter.max_imu_gap": 0.3}), subscribe_outputs=False)
    messages = drive_messages(drive)
    imgs = [(k, m) for k, m in messages if k == "image"]
    # frames before any IMU: queued, then dropped when the first IMU comes after them
    h.send("image", imgs[0][1])
    h.send_all(messages[2:40])
    assert h.node.drops["no_imu"] == 1
    assert "frames before any IMU" in h.logged("no_imu")[0]
    t = stamp_to_sec(messages[39][1].header.stamp)
    w, hh = drive.camera.width, drive.camera.height_px
    frame = drive.images[5]

    def img_at(dt, arr=frame, enc="mono8"):
        return image_msg(t + dt, arr, enc)

    # unsupported encoding
    bad = img_at(0.001)
    bad.encoding = "32FC1"
    h.send("image", bad)
    assert h.node.drops["bad_encoding"] == 1
    assert "unsupported image encoding '32FC1'" in h.logged("bad_encoding")[0]
    # wrong size
    h.send("image", img_at(0.002, np.zeros((hh // 2, w // 2), np.uint8)))
    assert h.node.drops["bad_image_size"] == 1
    assert "but the calibration is 320x96" in h.logged("bad_image_size")[0]
    # NaN / inf IMU, zero acceleration (IMU past the sample the last frame waited for is held for the
    # next image, at most image_wait: ordered_intake)
    h.send("imu", imu_msg(t + 0.003, [float("nan"), 0, 0], [0, 0, 9.8]))
    h.send("imu", imu_msg(t + 0.004, [0, 0, 0], [0, float("inf"), 9.8]))
    assert spin_until(h.executor, lambda: h.node.drops["imu_nonfinite"] == 2, 2)
    assert "NaN/inf" in h.logged("imu_nonfinite")[0]
    h.send("imu", imu_msg(t + 0.005, [0, 0, 0], [0, 0, 0]))
    assert spin_until(h.executor, lambda: h.node.drops["imu_invalid"] == 1, 2)
    # converted encodings are used, not dropped: rgb8 / bgr8 / mono16
    n_out = h.node.counts["odometry_out"]
    rgb = np.repeat(frame[..., None], 3, axis=2)
    h.send("image", img_at(0.010, rgb, "rgb8"))
    h.send("imu", imu_msg(t + 0.011, drive.gyro[40], drive.accel[40]))
    h.send("image", img_at(0.020, rgb, "bgr8"))
    h.send("imu", imu_msg(t + 0.021, drive.gyro[40], drive.accel[40]))
    h.send("image", img_at(0.030, frame.astype(np.uint16) * 257, "mono16"))
    h.send("imu", imu_msg(t + 0.031, drive.gyro[40], drive.accel[40]))
    assert h.node.counts["odometry_out"] == n_out + 3
    # an IMU gap longer than filter.max_imu_gap: the filter re-initialises, and says so
    h.send("imu", imu_msg(t + 1.0, drive.gyro[41], drive.accel[41]))
    assert spin_until(h.executor, lambda: h.node.events["imu_gap"] == 1, 2)
    assert "re-initialised" in h.logged("imu_gap")[0]
    # an unexpected exception inside a callback: logged and counted, the node carries on
    real_add_imu = h.node.engine.add_imu

    def boom(*a, **k):
        raise RuntimeError("injected failure")

    h.node.engine.add_imu = boom
    h.send("imu", imu_msg(t + 1.01, drive.gyro[42], drive.accel[42]))
    assert spin_until(h.executor, lambda: h.node.drops["callback_error"] == 1, 2)
    h.node.engine.add_imu = real_add_imu
    assert "RuntimeError" in h.logged("callback_error")[0] and "injected failure" in h.logged("callback_error")[0]
    h.send("image", img_at(1.02))
    h.send("imu", imu_msg(t + 1.03, drive.gyro[43], drive.accel[43]))
    assert h.node.counts["odometry_out"] == n_out + 4
    # everything is visible in /diagnostics
    h.diag.clear()
    assert spin_until(h.executor, lambda: len(h.diag) > 0, 5)
    values = {kv.key: kv.value for kv in h.diag[-1].status[0].values}
    for reason, n in (("no_imu", 1), ("bad_encoding", 1), ("bad_image_size", 1), ("imu_nonfinite", 2),
                      ("imu_invalid", 1), ("callback_error", 1)):
        assert values.get(f"drop.{reason}") == str(n), values
    assert values.get("event.imu_gap") == "1"


def test_a_car_at_rest_stands_still_and_says_so(harness_factory, drive):
    """A car standing 3 s (the same view with fresh sensor noise each frame, an IMU reading gravity
    and a 0.11 deg/s yaw gyro bias): the published pose stays put, the twist is zero and
    /diagnostics counts the frames at rest."""
    h = harness_factory(base_overrides(drive), subscribe_outputs=True)
    rng = np.random.default_rng(0)
    view = drive.images[5].astype(np.float64)
    t0 = 100.0
    for i in range(301):
        t = t0 + 0.01 * i
        h.send("imu", imu_msg(t, [0.0, 0.0, 0.002 + rng.normal(0, 1e-4)], [0.0, 0.0, 9.81] + rng.normal(0, 0.02, 3)))
        if i % 10 == 5:
            img = np.clip(view + rng.normal(0.0, 2.0, view.shape), 0, 255).astype(np.uint8)
            h.send("image", image_msg(t, img))
    h.settle()
    assert len(h.odom) == 30
    for msg in h.odom:
        pos, rpy, _, lin, ang, _ = _odom_arrays(msg)
        assert np.abs(pos).max() < 1e-3 and abs(np.degrees(rpy[2])) < 0.05, (pos, np.degrees(rpy))
    assert np.abs(_odom_arrays(h.odom[-1])[3]).max() == 0.0 and np.abs(_odom_arrays(h.odom[-1])[4]).max() == 0.0
    assert h.node.events["standstill"] >= 25
    h.diag.clear()
    assert spin_until(h.executor, lambda: len(h.diag) > 0, 5)
    values = {kv.key: kv.value for kv in h.diag[-1].status[0].values}
    assert int(values.get("event.standstill", 0)) >= 25, values


def test_an_engine_bug_is_a_callback_error_not_a_bad_input(harness_factory, drive, monkeypatch):
    """Only what the engine refuses as input (InvalidInputError, ImplausibleImuError) is dropped as
    that input; a plain ValueError out of the engine is a bug: counted and logged as callback_error."""
    h = harness_factory(base_overrides(drive), subscribe_outputs=False)
    messages = drive_messages(drive)
    h.send_all(messages[:20])
    assert spin_until(h.executor, lambda: h.node.intake.hold.held == 0, 2)  # the IMU held for a next image: fused
    engine = h.node.feed.engine
    assert engine is not None

    def broken(*args, **kwargs):
        raise ValueError("a bug deep in the engine")

    monkeypatch.setattr(engine, "add_imu", broken)
    t = stamp_to_sec(messages[19][1].header.stamp)
    h.send("imu", imu_msg(t + 0.001, drive.gyro[20], drive.accel[20]))
    assert spin_until(h.executor, lambda: h.node.drops["callback_error"] == 1, 2)  # held for the next image first
    assert h.node.drops["imu_invalid"] == 0, dict(h.node.drops)
    assert "a bug deep in the engine" in h.logged("callback_error")[0]


def test_image_wait_processes_an_image_whose_imu_never_comes(harness_factory, drive):
    h = harness_factory(base_overrides(drive, image_wait=0.1), subscribe_outputs=False)
    messages = drive_messages(drive)
    h.send_all(messages[:25])  # ends with IMU 19 -> frame 2 (IMU 20) not yet sent
    n = h.node.counts["odometry_out"]
    img = next(m for k, m in messages[25:] if k == "image")
    h.send("image", img)
    assert h.node.engine.pending_images == 1 and h.node.counts["odometry_out"] == n
    assert spin_until(h.executor, lambda: h.node.counts["odometry_out"] == n + 1, 3)
    assert h.node.events["flushed_images"] == 1 and h.node.engine.pending_images == 0
    h.settle()
    assert h.odom[-1].header.stamp == img.header.stamp


@pytest.mark.parametrize("delay", [2, 5])
def test_an_image_behind_later_imu_gives_the_offline_odometry(harness_factory, drive, delay):
    """Every image arrives after the next ``delay`` IMU samples: with ordered_intake the IMU past the
    sample a frame waits for is held until that frame arrives, so the poses equal the offline core's
    fed in stamp order; without it (executor order) they do not."""
    messages = drive_messages(drive)
    late = delivered_late(messages, delay)
    assert [k for k, _ in late] != [k for k, _ in messages]
    ov = base_overrides(drive)
    expected = np.array([s.position for s in offline_steps(messages, ov)])
    assert len(expected) == drive.num_frames
    got = {}
    for ordered in (True, False):
        # image_wait long: no held sample goes on for lack of an image however slow this machine is
        h = harness_factory(base_overrides(drive, ordered_intake=ordered, image_wait=5.0), subscribe_outputs=False)
        h.send_all(late)
        h.settle()
        assert h.node.intake.hold.held == 0  # the last image came last: nothing is left waiting
        assert h.node.events["imu_hold_timeout"] == 0
        assert sum(h.node.drops.values()) == 0, dict(h.node.drops)
        got[ordered] = np.array([_odom_arrays(m)[0] for m in h.odom])
        assert len(got[ordered]) == drive.num_frames
    held_diff = np.abs(got[True] - expected).max()
    free_diff = np.abs(got[False] - expected).max()
    print(f"\nimages {delay} IMU samples late: max position difference to offline {held_diff:.1e} m with the "
          f"IMU held, {free_diff:.1e} m without")
    assert held_diff < 1e-9
    assert free_diff > 1e-6  # the test can fail: the order matters


def test_camera_info_supplies_the_intrinsics(harness_factory, drive):
    ov = base_overrides(drive, use_camera_info=True)
    for k in ("camera.fx", "camera.fy", "camera.cx", "camera.cy"):
        ov[k] = 0.0
    ov["camera.width"] = ov["camera.height_px"] = 0
    ov["max_pending_images"] = 3
    h = harness_factory(ov, subscribe_outputs=False)
    assert h.node.engine is None
    messages = drive_messages(drive)
    # DDS orders no topic against another: a frame's CameraInfo may come after the frame itself.
    # The first frames are held for the calibration, the oldest beyond max_pending_images dropped.
    early = [i for i, (k, _) in enumerate(messages) if k == "image"][:4]
    h.send_all(messages[:early[-1] + 1])
    assert h.node.engine is None and h.node.rig.held_images == 3 and h.node.drops["no_camera_info"] == 1
    assert "waiting for CameraInfo" in h.logged("waiting_for_calibration")[0]
    assert "max_pending_images=3" in h.logged("no_camera_info")[0]
    K = drive.camera.K.double().numpy()
    info = CameraInfo(width=drive.camera.width, height=drive.camera.height_px)
    info.k = K.reshape(-1).tolist()
    P = np.zeros((3, 4))
    P[:, :3] = K
    info.p = P.reshape(-1).tolist()
    h.send("info", info)  # the held frames are processed at once, in order, with the IMU kept meanwhile
    assert h.node.engine is not None and h.node.rig.camera.width == drive.camera.width
    assert h.node.rig.held_images == 0 and h.node.counts["odometry_out"] == 3
    h.send_all(messages[early[-1] + 1:80])
    h.settle()
    assert len(h.odom) >= 6 and sum(h.node.drops.values()) == 1
    assert [o.header.stamp for o in h.odom[:3]] == [messages[i][1].header.stamp for i in early[1:]]
    # the held frames went in with the IMU that waited, by stamp: the offline order, the same poses
    expected = offline_steps([m for i, m in enumerate(messages[:80]) if i != early[0]], base_overrides(drive))
    assert len(h.odom) == len(expected)
    for msg, step in zip(h.odom, expected):
        assert np.allclose(_odom_arrays(msg)[0], step.position, atol=1e-6, rtol=0)


def test_held_images_wait_for_their_imu_from_their_release(harness_factory, drive):
    """Held images still ahead of the IMU wait image_wait from when the calibration released them,
    not from their arrival (a bag's CameraInfo may come seconds late, its IMU later still)."""
    ov = base_overrides(drive, use_camera_info=True, camera_info_timeout=3600.0, image_wait=1.5)
    h = harness_factory(ov, subscribe_outputs=False)
    messages = drive_messages(drive)
    h.send("imu", messages[0][1])
    frames = [m for k, m in messages if k == "image"][1:4]  # all after the one IMU sample
    for m in frames:
        h.send("image", m)
    spin_until(h.executor, lambda: False, 2.0)  # held longer than image_wait
    assert h.node.rig.held_images == 3 and h.node.engine is None
    info = CameraInfo(width=drive.camera.width, height=drive.camera.height_px)
    K = drive.camera.K.double().numpy()
    info.k = K.reshape(-1).tolist()
    info.p = np.hstack([K, np.zeros((3, 1))]).reshape(-1).tolist()
    h.send("info", info)
    assert h.node.engine is not None and h.node.engine.pending_images == 3
    spin_until(h.executor, lambda: False, 0.5)
    assert h.node.engine.pending_images == 3 and h.node.events["flushed_images"] == 0  # not due yet
    assert spin_until(h.executor, lambda: h.node.engine.pending_images == 0, 3)
    assert h.node.events["flushed_images"] == 3 and not h.node.drops


def test_images_held_for_the_calibration_are_dropped_by_a_reset(harness_factory, drive):
    """Held images belong to the trajectory a reset ends: dropped and counted, not fed after it."""
    ov = base_overrides(drive, use_camera_info=True, camera_info_timeout=3600.0)
    h = harness_factory(ov, subscribe_outputs=False)
    messages = drive_messages(drive)
    early = [i for i, (k, _) in enumerate(messages) if k == "image"][:2]
    h.send_all(messages[:early[-1] + 1])
    assert h.node.engine is None and h.node.rig.held_images == 2 and not h.node.drops
    assert h.node.summary().endswith("; 2 image(s) still waiting (for IMU or calibration)")  # the stop's log line
    client = h.tester.create_client(Trigger, "/bevo_node/reset")
    assert client.wait_for_service(timeout_sec=5)
    future = client.call_async(Trigger.Request())
    assert spin_until(h.executor, future.done, 5) and future.result().success
    assert h.node.rig.held_images == 0 and h.node.drops["no_camera_info"] == 2
    assert "reset" in h.logged("no_camera_info")[0] and "still waiting" not in h.node.summary()


LATCHED = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)
R_IMU_YAWED = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])  # IMU x along the base's y (left)


def _late_rig(harness_factory, drive, after_frame: int, camera_info: bool = False, before_tf=None):
    """A node whose rig arrives on /tf_static after its ``after_frame``-th frame was published (a
    startup race: another topic than the frames): the params' camera is 1 deg of pitch off the true
    one (the mounting calibrated through it, ``mounting_reference: camera``), the IMU is yawed 90 deg
    in ``imu_link``. The intrinsics from the parameters (the engine starts with the node), or from a
    CameraInfo sent before the first frame (the engine starts with it, the IMU before it its backlog:
    a bag's replay). Messages in lock step. -> ``(harness, messages sent)``."""
    import_outside_ci("tf2_msgs.msg", "built by make setup")
    from tf2_msgs.msg import TFMessage

    from bevo_ros.core.geometry import mounting_for_extrinsics

    T_true = drive.camera.T_base_cam.double().numpy()
    T_params = pitched(T_true, 1.0)
    mounting = mounting_for_extrinsics((0.0, 0.0), T_true, T_params)
    ov = base_overrides(drive, **{"camera.base_T_camera": [float(v) for v in T_params.reshape(-1)],
                                  "filter.mounting_pitch": mounting[0], "filter.mounting_roll": mounting[1],
                                  "filter.mounting_reference": "camera"})
    if camera_info:
        ov.update(use_camera_info=True, camera_info_timeout=3600.0)
    h = harness_factory(ov, subscribe_outputs=False)
    tf_pub = h.tester.create_publisher(TFMessage, "/tf_static", LATCHED)
    T_imu = np.eye(4)
    T_imu[:3, :3] = R_IMU_YAWED
    messages = []
    for kind, msg in drive_messages(drive, start=3):  # 7 IMU samples before the first frame
        if kind == "imu":  # what the yawed IMU measures: base vectors in its axes
            g, a = (R_IMU_YAWED.T @ v for v in _imu_arrays(msg))
            msg = imu_msg(stamp_to_sec(msg.header.stamp), g, a, frame_id="imu_link")
        else:
            msg.header.frame_id = "cam_optical"
        messages.append((kind, msg))
    frames = [i for i, (k, _) in enumerate(messages) if k == "image"]
    first, split = frames[0], frames[after_frame - 1] + 1
    h.send_all(messages[:first])
    if camera_info:
        assert h.node.engine is None
        K = drive.camera.K.double().numpy()
        info = CameraInfo(width=drive.camera.width, height=drive.camera.height_px, k=K.reshape(-1).tolist(),
                          p=np.hstack([K, np.zeros((3, 1))]).reshape(-1).tolist())
        h.send("info", info)
    assert h.node.engine is not None
    h.send_all(messages[first:split])
    assert h.node.counts["odometry_out"] == after_frame  # published with the params' rig
    if before_tf is not None:
        before_tf(h.node)
    tf_pub.publish(tf_static_msg([("base_link", "cam_optical", T_true), ("base_link", "imu_link", T_imu)]))
    assert spin_until(h.executor, lambda: len(h.node.static_tf.tree.edges) == 2, 10)
    h.send_all(messages[split:])
    h.settle()
    images = [m for k, m in messages if k == "image"]
    assert len(h.odom) == len(images) and not h.node.drops, (len(h.odom), dict(h.node.drops))
    assert [o.header.stamp for o in h.odom] == [m.header.stamp for m in images]  # each frame once
    return h, messages


def _imu_arrays(msg) -> tuple[np.ndarray, np.ndarray]:
    from bevo_ros.io.ros_conversions import imu_to_arrays

    return imu_to_arrays(msg)


def _engine_run(node, messages, camera, R_imu) -> list:
    """The offline core with the node's configuration and learned parameters, ``camera`` and the IMU
    turned by ``R_imu`` (None: as measured): what the node's engine computes with that rig from the start."""
    from bevo_ros.config import build_odometry
    from bevo_ros.io.ros_conversions import image_to_gray

    odo = build_odometry(node.config, node.learned, camera)
    steps = []
    for kind, msg in messages:
        t = stamp_to_sec(msg.header.stamp)
        if kind == "imu":
            g, a = _imu_arrays(msg)
            steps += odo.add_imu(t, g, a) if R_imu is None else odo.add_imu(t, R_imu @ g, R_imu @ a)
        else:
            steps += odo.add_image(t, image_to_gray(msg))
    return steps + odo.flush()


@pytest.mark.parametrize("camera_info", [False, True], ids=["parameters", "camera_info"])
def test_a_rig_on_tf_static_after_the_first_frame_gives_the_offline_odometry(harness_factory, drive, camera_info):
    """/tf_static (camera extrinsics and IMU axes) arriving after the first frame was published: the
    node rebuilds its engine with the rig and feeds it again what it had since its start, so every
    pose equals the offline core's with that rig from the start (before: the first frame's BEV and
    the first IMU samples stayed the params' rig's, ~cm off)."""
    h, messages = _late_rig(harness_factory, drive, after_frame=1, camera_info=camera_info)
    node = h.node
    assert node.rig.extrinsics_source == "/tf_static base_link -> cam_optical"
    R = node.rig.imu_rotation("imu_link")
    assert np.allclose(R, R_IMU_YAWED, atol=1e-12)
    expected = _engine_run(node, messages, node.rig.camera, R)
    assert len(expected) == len(h.odom)
    got = np.array([_odom_arrays(m)[0] for m in h.odom])
    want = np.array([s.position for s in expected])
    rpy = np.array([_odom_arrays(m)[1] for m in h.odom[1:]])  # the first frame's went out with the params' rig
    diff = np.abs(got - want).max()
    print(f"/tf_static after the first frame: max |dp| to the offline core {diff:.2e} m over "
          f"{np.linalg.norm(np.diff(want, axis=0), axis=1).sum():.2f} m")
    assert diff < 1e-9
    assert np.abs(np.angle(np.exp(1j * (rpy - np.array([s.rpy for s in expected[1:]]))))).max() < 1e-9
    assert node.events["rig_replayed"] == 1 and not node.events["camera_changed"], dict(node.events)
    assert "before the second frame" in h.logged("rig_replayed")[0]
    # and the true rig's offline run (base-frame IMU, true extrinsics; /tf_static's quaternions round)
    truth = [(k, imu_msg(stamp_to_sec(m.header.stamp), *(R_IMU_YAWED @ v for v in _imu_arrays(m))) if k == "imu"
              else m) for k, m in messages]
    true_run = offline_steps(truth, camera_overrides(drive.camera))
    assert np.abs(got - np.array([s.position for s in true_run])).max() < 1e-6


def test_a_rig_on_tf_static_after_the_third_frame_is_applied_from_then_and_counted(harness_factory, drive):
    """Past the second frame the odometry already published stands: the engine takes the new camera
    and the IMU the new axes from then on, counted (``camera_changed``, ``imu_axes_changed``); the
    frames before equal the offline core's with the params' rig."""
    h, messages = _late_rig(harness_factory, drive, after_frame=3)
    node = h.node
    assert node.events["camera_changed"] == 1 and node.events["imu_axes_changed"] == 1, dict(node.events)
    assert not node.events["rig_replayed"]
    assert "after the odometry's second frame" in h.logged("camera_changed")[0]
    from bevo_ros.config import camera_model

    got = np.array([_odom_arrays(m)[0] for m in h.odom])
    before = _engine_run(node, messages, camera_model(node.config.camera), None)
    assert np.abs(got[:3] - np.array([s.position for s in before[:3]])).max() < 1e-9
    exact = _engine_run(node, messages, node.rig.camera, node.rig.imu_rotation("imu_link"))
    late = np.abs(got - np.array([s.position for s in exact])).max()
    print(f"/tf_static after the third frame: max |dp| to the offline core with the rig from the start {late:.2e} m")
    assert late > 1e-4  # the start stays the params' rig's: the test can tell


def test_a_late_rig_whose_replay_fails_is_taken_by_the_running_engine(harness_factory, drive):
    """Rebuilding the engine for a late rig fails (here its factory raises): the running engine keeps
    its trajectory and takes the new camera (counted ``camera_changed``, the failure logged), no input
    is lost and every frame goes out once."""
    def failing_factory(node):
        def factory(*args):
            raise RuntimeError("no engine today")
        node._engine_factory = factory

    h, _ = _late_rig(harness_factory, drive, after_frame=1, before_tf=failing_factory)
    node = h.node
    assert node.events["camera_changed"] == 1 and not node.events["rig_replayed"], dict(node.events)
    assert any("feeding its inputs again failed (RuntimeError: no engine today)" in text
               for text in h.logged("rig_replayed"))
    assert not node.feed.replayable  # not tried again for the IMU axes or a later change


def test_use_sim_time_clock_jump_resets(harness_factory, drive):
    h = harness_factory(base_overrides(drive, use_sim_time=True, max_time_jump_back=0.5), subscribe_outputs=False)
    messages = drive_messages(drive)
    clock = h.set_clock
    clock(messages[-1][1].header.stamp)
    h.send_all(messages[:40])
    h.settle()
    assert h.odom and h.odom[-1].header.stamp == [m for k, m in messages[:40] if k == "image"][-1].header.stamp
    clock(messages[0][1].header.stamp)  # the bag restarted: /clock jumps back by 1.2 s
    assert h.node.events["clock_jump_reset"] == 1
    n = len(h.odom)
    h.send_all(messages[:40])
    h.settle()
    assert h.node.events["time_jump_reset"] == 0  # the clock handler already reset
    assert np.allclose(_odom_arrays(h.odom[n])[0], 0.0)


def test_tf_disabled_is_said_once(harness_factory, drive, monkeypatch):
    monkeypatch.setitem(sys.modules, "tf2_ros", None)
    monkeypatch.setitem(sys.modules, "tf2_msgs", None)
    monkeypatch.setitem(sys.modules, "tf2_msgs.msg", None)
    h = harness_factory(base_overrides(drive), subscribe_outputs=False)
    assert h.node.outputs.tf_backend == "none"
    h.send_all(drive_messages(drive)[:40])
    h.settle()
    assert len(h.odom) >= 3
    said = [text for key, text in h.node.log_history if key == "tf_unavailable"]
    assert len(said) == 1 and "TF is DISABLED" in said[0] and "tf2_msgs" in said[0]


def test_missing_or_malformed_learned_file_refuses_to_start(context, drive, tmp_path):
    from bevo_ros.node import BevoNode

    missing = tmp_path / "nope.yaml"
    ov = base_overrides(drive, learned_params_file=str(missing))
    with pytest.raises(ConfigError, match=f"not found: {missing}"):
        BevoNode(context=context, parameter_overrides=[Parameter(k, value=v) for k, v in ov.items()])
    bad = tmp_path / "bad.yaml"
    bad.write_text("format: bevo_learned_params/1\nprocess_noise_density: {pitch: -1, roll: 1}\n")
    ov["learned_params_file"] = str(bad)
    with pytest.raises(ConfigError, match=r"bad.yaml.*process_noise_density.pitch"):
        BevoNode(context=context, parameter_overrides=[Parameter(k, value=v) for k, v in ov.items()])


def test_a_parameter_the_node_does_not_have_is_named(context, drive, capfd):
    """A typo in a parameters file is no parameter of the node: ROS would ignore it without a word (the
    mounting left at 0: the KITTI sample at 35 % drift); the node names it, with the nearest name."""
    from bevo_ros.node import BevoNode

    ov = base_overrides(drive, **{"filter.mountng_pitch": 0.027})
    node = BevoNode(context=context, parameter_overrides=[Parameter(k, value=v) for k, v in ov.items()])
    try:
        err = capfd.readouterr().err
        assert "does not have, ignored: filter.mountng_pitch (did you mean filter.mounting_pitch?)" in err, err
    finally:
        node.destroy_node()
    node = BevoNode(context=context, parameter_overrides=[Parameter(k, value=v) for k, v in base_overrides(drive).items()])
    try:
        assert "does not have" not in capfd.readouterr().err
    finally:
        node.destroy_node()


def test_bad_parameters_refuse_to_start_with_the_name(context, drive):
    from bevo_ros.node import BevoNode

    for key, value, pattern in (("input_qos", "fast", "input_qos"), ("camera.width", "wide", "camera.width"),
                                ("image_wait", -1.0, "image_wait")):
        ov = base_overrides(drive, **{key: value})
        with pytest.raises(ConfigError, match=pattern):
            BevoNode(context=context, parameter_overrides=[Parameter(k, value=v) for k, v in ov.items()])


def test_a_fast_camera_is_told_to_thin_its_frames(harness_factory):
    """A 30 Hz camera with every frame processed: the node says once (after 20 frames) to set
    odometry.min_frame_interval; set, the frames are thinned (counted in /diagnostics) and nothing is said."""
    fast = small_drive(duration=1.0, frame_rate=30.0, imu_rate=90.0)
    for interval, said in ((0.0, True), (0.09, False)):
        h = harness_factory(base_overrides(fast, **{"odometry.min_frame_interval": interval}), subscribe_outputs=False)
        h.send_all(drive_messages(fast))
        h.settle()
        assert bool(h.logged("fast_camera")) == said, h.node.log_history
        assert len(h.logged("fast_camera")) <= 1
        if said:
            assert "every 33 ms (30 Hz)" in h.logged("fast_camera")[0]
        else:
            assert h.node.engine.counters.skipped_frame_rate >= 15 and h.node.counts["odometry_out"] <= 12


def test_the_start_s_camera_tilt_holds_the_first_frames_then_gives_the_offline_odometry(harness_factory):
    """``filter.tilt_from_images``: the node publishes nothing while the engine holds the start's frames
    (``/diagnostics`` says how far the measurement is), then every frame at once, equal to the offline
    engine's, the measurement logged; a start whose images stop before enough pairs (a bag that ended)
    runs what it held after ``image_timeout``, at the configured tilt, nothing lost."""
    d = small_drive(seed=5, duration=3.0)
    ov = base_overrides(d, **{"filter.tilt_from_images": 10, "filter.tilt_hold_frames": 40, "image_timeout": 0.5,
                              "filter.mounting_pitch": math.radians(1.0)})
    messages = drive_messages(d)
    expected = offline_steps(messages, ov)
    h = harness_factory(ov, subscribe_outputs=False)
    first_images = [i for i, (k, _) in enumerate(messages) if k == "image"][:5]
    h.send_all(messages[: first_images[-1] + 1])
    assert h.node.counts["odometry_out"] == 0 and h.node.engine.held_images == 5
    h.diag.clear()
    assert spin_until(h.executor, lambda: len(h.diag) > 0, 5)
    values = {kv.key: kv.value for kv in h.diag[-1].status[0].values}
    assert values["camera_tilt"].startswith("measuring: ") and "5 image(s) held" in values["camera_tilt"], values
    h.send_all(messages[first_images[-1] + 1:])
    h.settle()
    m = h.node.engine.tilt_measurement
    assert m is not None and m.measured, m
    assert len(h.odom) == len(expected) == d.num_frames, (len(h.odom), len(expected), dict(h.node.drops))
    for msg, step in zip(h.odom, expected):
        assert np.allclose(_odom_arrays(msg)[0], step.position, atol=1e-6, rtol=0)
    assert any("the camera's tilt from the images' direction of travel at the start" in text
               for _, text in h.node.log_history), h.node.log_history
    # the held frames' wait is no running latency: counted apart, the percentiles are the rest's
    held, longest = h.node.report.start_hold
    assert m.pairs + 1 <= held < d.num_frames and held + len(h.node.report.latency) == d.num_frames, (held, m)
    h.diag.clear()
    assert spin_until(h.executor, lambda: len(h.diag) > 0, 5)
    values = {kv.key: kv.value for kv in h.diag[-1].status[0].values}
    assert values["start_hold_frames"] == str(held) and float(values["start_hold_max_ms"]) == pytest.approx(
        longest * 1e3, abs=0.01), values

    short = harness_factory(base_overrides(d, **{"filter.tilt_from_images": 10, "filter.tilt_hold_frames": 40,
                                                 "image_timeout": 0.5}), topics_prefix="short",
                            subscribe_outputs=False)
    upto = [i for i, (k, _) in enumerate(messages) if k == "image"][6]
    short.send_all(messages[: upto + 1])  # 7 images: 6 pairs, fewer than the 10 asked for
    assert short.node.counts["odometry_out"] == 0
    assert spin_until(short.executor, lambda: short.node.counts["odometry_out"] >= 6, 5), short.node.counts
    m = short.node.engine.tilt_measurement
    assert m is not None and not m.measured and short.node.engine.held_images == 0, m
    assert sum(short.node.drops.values()) == 0, dict(short.node.drops)
