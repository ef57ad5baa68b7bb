"""bevo play: a small bag played into an rclpy subscriber (localhost DDS, domain 61)."""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from bevo_ros.io import bag

pytestmark = pytest.mark.ros

REPO = Path(__file__).resolve().parents[1]
PLAY = ("-m", "bevo_ros.cli", "play")  # `bevo play`, from this checkout
from helpers.ros import domain_id_for  # noqa: E402

DOMAIN_ID = domain_id_for(1)
N_IMU, N_FRAMES = 40, 8
T0 = 1_700_000_000_000_000_000  # ns


def _env() -> dict[str, str]:
    env = dict(os.environ)
    env.update(ROS_DOMAIN_ID=str(DOMAIN_ID), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST", PYTHONUNBUFFERED="1")
    return env


@pytest.fixture(scope="module")
def small_bag(tmp_path_factory) -> Path:
    """2 s of data: 20 Hz IMU, 4 Hz images (16x24 mono8), camera info and odometry."""
    path = tmp_path_factory.mktemp("play") / "small"
    rng = np.random.default_rng(0)
    with bag.BagWriter(path, storage="mcap") as w:
        for i in range(N_IMU):
            w.write_imu(T0 + i * 50_000_000, [0.01 * i, -0.02, 0.03], [0.1, 0.2, 9.81 + 0.001 * i])
        for k in range(N_FRAMES):
            t = T0 + k * 250_000_000 + 1_000_000
            w.write_image(t, rng.integers(0, 256, size=(16, 24), dtype=np.uint8))
            w.write_camera_info(t, np.array([[20.0, 0, 12], [0, 20, 8], [0, 0, 1]]), 24, 16)
            T = np.eye(4)
            T[0, 3] = 0.5 * k
            w.write_odometry(t, T)
    return path


class Listener:
    """An rclpy node in its own context (domain 61) counting what arrives."""

    def __init__(self):
        import rclpy
        from nav_msgs.msg import Odometry
        from rclpy.context import Context
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.qos import QoSProfile, ReliabilityPolicy
        from rosgraph_msgs.msg import Clock
        from sensor_msgs.msg import CameraInfo, Image, Imu

        os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
        self.context = Context()
        rclpy.init(context=self.context, domain_id=DOMAIN_ID)
        self.node = rclpy.create_node("play_bag_test_listener", context=self.context)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        qos = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE)
        self.msgs: dict[str, list] = {}
        for topic, cls in ((bag.IMU_TOPIC, Imu), (bag.IMAGE_TOPIC, Image), (bag.CAMERA_INFO_TOPIC, CameraInfo),
                           (bag.GT_ODOMETRY_TOPIC, Odometry), ("/clock", Clock)):
            self.msgs[topic] = []
            self.node.create_subscription(cls, topic, lambda m, t=topic: self.msgs[t].append(m), qos)

    def spin_while(self, proc: subprocess.Popen, extra: float = 1.0, until=None) -> None:
        """Spin until ``proc`` exits (then ``extra`` seconds more) or ``until()`` is true."""
        end = None
        while True:
            self.executor.spin_once(timeout_sec=0.02)
            if until is not None and until():
                return
            if proc.poll() is not None:
                end = end or time.monotonic() + extra
                if time.monotonic() > end:
                    return

    def close(self) -> None:
        self.executor.shutdown()
        self.node.destroy_node()
        self.context.try_shutdown()


@pytest.fixture()
def listener():
    lis = Listener()
    yield lis
    lis.close()


_STARTED: list[subprocess.Popen] = []


def _play(*args: str) -> subprocess.Popen:
    # SIGINT back to its default in the child: a suite run as a background job (`make test &` in a
    # script) ignores SIGINT, the child inherits that and Python then installs no KeyboardInterrupt
    # handler, so the Ctrl-C test would see the player play on (exit 0) instead of stopping (130).
    proc = subprocess.Popen([sys.executable, *PLAY, *args], env=_env(), stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    _STARTED.append(proc)
    return proc


@pytest.fixture(autouse=True)
def _no_player_outlives_its_test():
    """A player left running by a failed test (a timeout under load) would keep publishing into
    the next test's domain: kill it at teardown."""
    yield
    while _STARTED:
        proc = _STARTED.pop()
        if proc.poll() is None:
            proc.kill()
            proc.communicate(timeout=30)


def test_play_delivers_every_message_and_clock(small_bag, listener):
    t0 = time.monotonic()
    proc = _play(str(small_bag), "--rate", "4", "--wait-for-subscribers", "20")
    listener.spin_while(proc, extra=1.0)
    out, err = proc.communicate(timeout=60)
    got = {t: len(v) for t, v in listener.msgs.items()}
    print(f"play_bag rc {proc.returncode} in {time.monotonic() - t0:.1f} s; received {got}\n{out}{err}")
    assert proc.returncode == 0, err
    assert got[bag.IMU_TOPIC] == N_IMU and got[bag.IMAGE_TOPIC] == N_FRAMES
    assert got[bag.CAMERA_INFO_TOPIC] == N_FRAMES and got[bag.GT_ODOMETRY_TOPIC] == N_FRAMES
    assert f"{bag.IMU_TOPIC}: {N_IMU} msgs" in out
    # Contents arrive bit-exact, in order.
    imu = listener.msgs[bag.IMU_TOPIC]
    assert [m.angular_velocity.x for m in imu] == [0.01 * i for i in range(N_IMU)]
    stamps = [m.header.stamp.sec * 10**9 + m.header.stamp.nanosec for m in imu]
    assert stamps == [T0 + i * 50_000_000 for i in range(N_IMU)]
    expected_images = [m.data.tobytes() for _, _, m in bag.iter_messages(small_bag, [bag.IMAGE_TOPIC])]
    assert [bytes(m.data) for m in listener.msgs[bag.IMAGE_TOPIC]] == expected_images
    # /clock carries bag time and ends at the last message.
    clock = [m.clock.sec * 10**9 + m.clock.nanosec for m in listener.msgs["/clock"]]
    last = max(stamps[-1], T0 + (N_FRAMES - 1) * 250_000_000 + 1_000_000)
    print(f"/clock: {len(clock)} msgs, {(clock[0] - T0) * 1e-9:.3f} .. {(clock[-1] - T0) * 1e-9:.3f} s")
    assert len(clock) >= N_IMU and clock[-1] == last and clock == sorted(clock)


def test_topics_and_start(small_bag, listener):
    proc = _play(str(small_bag), "--rate", "0", "--topics", bag.IMU_TOPIC, "--start", "1.0",
                 "--wait-for-subscribers", "20", "--no-clock", "-q")
    listener.spin_while(proc, extra=1.0)
    out, err = proc.communicate(timeout=60)
    got = {t: len(v) for t, v in listener.msgs.items()}
    print(f"--topics /imu/data --start 1.0: received {got}")
    assert proc.returncode == 0, err
    assert got[bag.IMU_TOPIC] == N_IMU // 2 and got[bag.IMAGE_TOPIC] == 0 and got["/clock"] == 0
    first = listener.msgs[bag.IMU_TOPIC][0].header.stamp
    assert first.sec * 10**9 + first.nanosec == T0 + 1_000_000_000


def test_ctrl_c_exits_130_without_traceback(small_bag, listener):
    proc = _play(str(small_bag), "--rate", "0.05", "--wait-for-subscribers", "20")
    listener.spin_while(proc, until=lambda: len(listener.msgs[bag.IMU_TOPIC]) >= 1)
    proc.send_signal(signal.SIGINT)
    out, err = proc.communicate(timeout=60)
    print(f"rc {proc.returncode}; stderr: {err.strip()}")
    assert proc.returncode == 130
    assert "interrupted" in err and "Traceback" not in err


def test_bad_input_exit_2(tmp_path):
    proc = subprocess.run([sys.executable, *PLAY, str(tmp_path / "missing")], env=_env(),
                          capture_output=True, text=True, timeout=60)
    print(proc.stderr.strip())
    assert proc.returncode == 2 and "missing: bag not found" in proc.stderr and "Traceback" not in proc.stderr


def test_a_bad_namespace_clock_topic_or_rate_is_exit_2(small_bag):
    """rclpy's name check raised out of the player (a traceback, exit 1); --rate nan played flat out."""
    proc = subprocess.run([sys.executable, *PLAY, str(small_bag), "--rate", "nan"], env=_env(), capture_output=True,
                          text=True, timeout=60)
    assert proc.returncode == 2 and "--rate and --start must be >= 0" in proc.stderr  # NaN played flat out
    proc = subprocess.run([sys.executable, *PLAY, str(small_bag), "--start", "1000"], env=_env(), capture_output=True,
                          text=True, timeout=60)
    assert proc.returncode == 2 and "past the bag's end" in proc.stderr  # played nothing, exit 0
    for argv in (["--namespace", "bad ns"], ["--clock-topic", "bad topic"]):
        proc = subprocess.run([sys.executable, *PLAY, str(small_bag), "--rate", "0", "--linger", "0", "-q", *argv],
                              env=_env(), capture_output=True, text=True, timeout=60)
        assert proc.returncode == 2 and "Invalid topic name" in proc.stderr and "Traceback" not in proc.stderr, (
            argv, proc.stderr)


def test_wait_params_waits_for_the_nodes_inputs(tmp_path, small_bag, capsys):
    """``--wait-params FILE`` (what the launch file gives): the topics bevo_node subscribes to with
    that parameters file, its speed input and compressed images among them, as the bag's names. A
    file whose node section cannot be read (a namespaced one) or an absolute name under a namespace
    is said, and the replay goes on with the default inputs."""
    from bevo_ros.commands import play

    params = tmp_path / "car.yaml"
    params.write_text("/**:\n  ros__parameters:\n    imu_topic: sensors/imu\n    use_camera_info: false\n"
                      "    speed_topic: /wheel/odometry\n    image_transport: compressed\n")
    assert play.node_input_topics(str(params)) == ["sensors/imu", "camera/image_rect/compressed", "/wheel/odometry"]
    assert play._wait_topics_from_params(str(params), "car1") == [
        "/sensors/imu", "/camera/image_rect/compressed", "/wheel/odometry"]  # the bag's names
    assert "/wheel/odometry are absolute" in capsys.readouterr().err
    ns = tmp_path / "ns.yaml"
    ns.write_text("/car1/bevo_node:\n  ros__parameters:\n    speed_topic: wheel/odometry\n")
    proc = subprocess.run([sys.executable, *PLAY, str(small_bag), "--wait-for-subscribers", "0.5", "--wait-params",
                           str(ns), "--namespace", "car1", "-q"],
                          env=_env(), capture_output=True, text=True, timeout=120)
    print(proc.stderr.strip())
    assert proc.returncode == 0 and "Traceback" not in proc.stderr
    assert "waiting for the default inputs /imu/data, /camera/image_rect, /camera/camera_info" in proc.stderr


def test_recorded_qos_replays_tf_static_latched_and_namespace(tmp_path, listener):
    """/tf_static recorded transient local is offered latched: a subscriber that appears after it
    was published still gets it; --namespace moves the sensor topics but not /tf_static."""
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import Imu
    from tf2_msgs.msg import TFMessage

    path = tmp_path / "latched"
    with bag.BagWriter(path, storage="mcap") as w:
        w.write_tf_static(T0, [("base_link", "imu_link", np.eye(4))])
        for i in range(N_IMU):
            w.write_imu(T0 + i * 50_000_000, [0.0, 0.0, 0.0], [0.0, 0.0, 9.81])
    assert bag.topic_qos(path)[bag.TF_STATIC_TOPIC].transient_local
    ns_imu: list = []
    listener.node.create_subscription(Imu, "/car1/imu/data", ns_imu.append,
                                      QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE))
    proc = _play(str(path), "--rate", "0.5", "--namespace", "car1", "--wait-for-subscribers", "5", "-q")
    try:
        listener.spin_while(proc, until=lambda: len(ns_imu) >= 2)
        assert not listener.msgs[bag.IMU_TOPIC], "--namespace: the root topic must stay silent"
        late: list = []  # subscribed after /tf_static went out
        listener.node.create_subscription(TFMessage, "/tf_static", late.append, QoSProfile(
            depth=10, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL))
        listener.spin_while(proc, until=lambda: len(late) >= 1)
        assert late and late[0].transforms[0].child_frame_id == "imu_link"
    finally:
        proc.send_signal(signal.SIGINT)
        proc.communicate(timeout=60)


def test_a_sensor_recording_replays_reliably_with_the_rig_first_even_from_start(tmp_path, listener, monkeypatch):
    """A bag recorded from best-effort sensor drivers (and /tf_static recorded volatile) was replayed as
    recorded: the node's reliable replay inputs matched nothing (0 frames), its transient-local /tf_static
    listener nothing either; with --start the latched /tf_static (stamped at the bag's start) was never
    played. Now every topic is offered reliable, /tf_static latched, and the latched messages up to the
    start go out (acknowledged) before the clock and the data."""
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
    from rosbags.interfaces import QosReliability
    from tf2_msgs.msg import TFMessage

    def as_recorded_from_sensors(latched: bool = False, depth: int = 10):  # best effort, and /tf_static volatile
        return real_offered_qos(False, depth)._replace(reliability=QosReliability.BEST_EFFORT)  # a NamedTuple

    real_offered_qos = bag.offered_qos
    monkeypatch.setattr(bag, "offered_qos", as_recorded_from_sensors)
    path = tmp_path / "sensors"
    with bag.BagWriter(path, storage="mcap") as w:
        w.write_tf_static(T0, [("base_link", "imu_link", np.eye(4))])
        for i in range(N_IMU):
            w.write_imu(T0 + i * 50_000_000, [0.0, 0.0, 0.0], [0.0, 0.0, 9.81])
    monkeypatch.undo()
    recorded = bag.topic_qos(path)
    assert not recorded[bag.IMU_TOPIC].reliable and not recorded[bag.TF_STATIC_TOPIC].transient_local
    order: list[str] = []
    tf: list = []
    listener.node.create_subscription(TFMessage, "/tf_static", lambda m: (tf.append(m), order.append("tf")), QoSProfile(
        depth=10, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL))
    from sensor_msgs.msg import Imu

    listener.node.create_subscription(Imu, "/imu/data", lambda m: order.append("imu"),
                                      QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE))
    proc = _play(str(path), "--rate", "0", "--start", "0.5", "--wait-for-subscribers", "5",
                 "--wait-topics", "/imu/data", "-q")
    try:
        listener.spin_while(proc, extra=1.0)
    finally:
        out, err = proc.communicate(timeout=60)
    assert proc.returncode == 0, err
    assert len(listener.msgs[bag.IMU_TOPIC]) == N_IMU - 10, out  # from 0.5 s on, reliable
    assert tf and tf[0].transforms[0].child_frame_id == "imu_link" and order[0] == "tf", order[:3]
    assert "/tf_static: 1 msgs" in out
