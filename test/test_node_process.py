"""bevo_node as a subprocess (``.venv/bin/bevo_node --ros-args --params-file ...``) with a test
publisher and subscriber in this process: odometry, TF, diagnostics, the reset service, a bad
input reported in the log and /diagnostics, a clean exit on SIGINT, and a clear refusal (exit 2,
no traceback) when the learned-parameters file is missing or malformed.
"""
from __future__ import annotations

import numpy as np
import pytest

from helpers.node_support import (VENV_BIN, NodeProcess, camera_overrides, drive_messages, image_msg,  # noqa: E402
                                  small_drive, spin_until, write_params)

rclpy = pytest.importorskip("rclpy")
from diagnostic_msgs.msg import DiagnosticArray  # noqa: E402
from nav_msgs.msg import Odometry  # noqa: E402
from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from rclpy.qos import QoSProfile, ReliabilityPolicy  # noqa: E402
from sensor_msgs.msg import Image, Imu  # noqa: E402
from std_srvs.srv import Trigger  # noqa: E402

from helpers.env import skip_outside_ci  # noqa: E402
from helpers.ros import domain_id_for, ros_context  # noqa: E402

DOMAIN_ID = domain_id_for(12)
pytestmark = [pytest.mark.ros, pytest.mark.timeout(240)]
RELIABLE = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE)

if not (VENV_BIN / "bevo_node").exists():
    skip_outside_ci(f"{VENV_BIN / 'bevo_node'} not installed (make setup)")


@pytest.fixture(scope="module")
def context():
    yield from ros_context(DOMAIN_ID)


def test_node_process_end_to_end(context, tmp_path):
    drive = small_drive(duration=1.2)
    ov = camera_overrides(drive.camera)
    ov.update(input_qos="reliable", imu_qos_depth=1000, image_qos_depth=100, diagnostics_period=0.3,
              use_camera_info=False)
    params = write_params(tmp_path / "params.yaml", ov)
    node = NodeProcess(params, str(DOMAIN_ID)).start()
    tester = rclpy.create_node("process_tester", context=context)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(tester)
    try:
        assert node.wait_for("ready:", 90), f"bevo_node did not start:\n{node.output}"
        imu_pub = tester.create_publisher(Imu, "/imu/data", RELIABLE)
        image_pub = tester.create_publisher(Image, "/camera/image_rect", RELIABLE)
        odom, tf, diag = [], [], []
        tester.create_subscription(Odometry, "/bevo/odometry", odom.append, RELIABLE)
        tester.create_subscription(DiagnosticArray, "/diagnostics", diag.append, 10)
        from tf2_msgs.msg import TFMessage  # built by make setup (tools/build_tf2_msgs.sh)

        tester.create_subscription(TFMessage, "/tf", tf.append, QoSProfile(depth=100))
        assert spin_until(executor, lambda: imu_pub.get_subscription_count() > 0
                          and image_pub.get_subscription_count() > 0, 30), "node subscriptions not discovered"
        assert spin_until(executor, lambda: tester.count_publishers("/bevo/odometry") > 0, 30)

        messages = drive_messages(drive)
        for kind, msg in messages:
            (imu_pub if kind == "imu" else image_pub).publish(msg)
            executor.spin_once(timeout_sec=0.001)
        assert spin_until(executor, lambda: len(odom) >= drive.num_frames, 60), \
            f"{len(odom)} of {drive.num_frames} odometry messages\n{node.output}"
        image_stamps = [m.header.stamp for k, m in messages if k == "image"]
        assert [m.header.stamp for m in odom] == image_stamps
        assert odom[0].header.frame_id == "odom" and odom[0].child_frame_id == "base_link"
        assert np.linalg.norm([odom[-1].pose.pose.position.x, odom[-1].pose.pose.position.y]) > 1.0
        assert spin_until(executor, lambda: len(tf) >= drive.num_frames, 10), "no TF from the node"
        t = tf[-1].transforms[0]
        assert (t.header.frame_id, t.child_frame_id, t.header.stamp) == ("odom", "base_link", image_stamps[-1])

        # a bad input: logged with its reason and counted in /diagnostics; the node carries on
        bad = image_msg(float(drive.imu_stamps[-1]) + 0.05, drive.images[0])
        bad.encoding = "32FC1"
        image_pub.publish(bad)

        def diag_value(key):
            for d in reversed(diag):
                for kv in d.status[0].values:
                    if kv.key == key:
                        return kv.value
            return None

        assert spin_until(executor, lambda: diag_value("drop.bad_encoding") == "1", 10), diag[-1:] or "no diagnostics"
        assert node.wait_for("unsupported image encoding '32FC1'", 5), node.output
        assert diag_value("odometry_published") == str(drive.num_frames)
        # params/kitti.yaml measures the camera's tilt at the start: its frames held for it are counted apart
        # from the running latency (here all of them: fewer pairs than 30, flushed after image_timeout)
        assert int(diag_value("start_hold_frames")) == drive.num_frames and float(diag_value("start_hold_max_ms")) > 0

        # ~/reset: the trajectory restarts at identity
        client = tester.create_client(Trigger, "/bevo_node/reset")
        assert client.wait_for_service(timeout_sec=10)
        future = client.call_async(Trigger.Request())
        assert spin_until(executor, future.done, 10) and future.result().success
        n = len(odom)
        for kind, msg in drive_messages(drive, stop=25, offset=10.0):
            (imu_pub if kind == "imu" else image_pub).publish(msg)
            executor.spin_once(timeout_sec=0.001)
        assert spin_until(executor, lambda: len(odom) >= n + 2, 30), node.output
        p = odom[n].pose.pose.position
        assert (p.x, p.y, p.z) == (0.0, 0.0, 0.0)
        # the tilt measured, a reset holds nothing: these frames' latency is the running one
        assert spin_until(executor, lambda: float(diag_value("latency_p99_ms") or "nan") > 0, 10), diag[-1:]

        rc = node.interrupt()
        assert rc == 0, f"exit code {rc} on SIGINT\n{node.output}"
        assert "Traceback" not in node.output, node.output
    finally:
        node.kill()
        executor.remove_node(tester)
        tester.destroy_node()
        executor.shutdown()


@pytest.mark.parametrize("problem", ["missing", "malformed", "yaml_syntax"])
def test_bad_learned_file_refuses_to_start(tmp_path, problem):
    learned = tmp_path / "learned.yaml"
    if problem == "malformed":
        learned.write_text("format: bevo_learned_params/1\nprocess_noise_density: {pitch: 1e-4}\n")
    elif problem == "yaml_syntax":
        learned.write_text("format: bevo_learned_params/1\nprocess_noise_density: {pitch: 1e-4\n  roll: [\n")
    params = write_params(tmp_path / "params.yaml", {"learned_params_file": str(learned)})
    node = NodeProcess(params, str(DOMAIN_ID)).start()
    try:
        rc = node.wait_exit(60)
    finally:
        node.kill()
    out = node.output
    assert rc == 2, f"exit code {rc}\n{out}"
    assert "Traceback" not in out, out
    expected = {"missing": "not found", "malformed": "'process_noise_density.roll' missing",
                "yaml_syntax": "is not valid YAML: line 3, column"}[problem]
    lines = [line for line in out.splitlines() if line.strip()]
    assert len(lines) == 1 and "refusing to start" in lines[0], out  # one line, whatever the problem
    assert str(learned) in lines[0] and expected in lines[0], out
