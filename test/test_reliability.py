"""Reliability under bad input and faults (issue 12): no false motion, clean shutdown, no leftovers.

* A stationary vehicle stays put (per-frame motion < 0.2 m) under absurd IMU samples (1e30,
  100 g: dropped with the reason by the engine, so the node and run_bag agree), absurd
  CameraInfo (rejected by the node, the last good calibration kept) and one black frame
  (rejected by the fused engine's texture gate, issue 9).
* A lone outlier stamp is dropped; it does not reset the trajectory. Reset logs are throttled.
* A live bevo_node survives a few thousand adversarial messages, then gives odometry for valid
  data and answers ~/reset; SIGINT/SIGTERM while data streams exit 0 without a traceback.
* A killed bag writer leaves a partial directory that the next writer of that bag removes.
"""
from __future__ import annotations

import collections
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from helpers.node_support import (REPO, VENV_BIN, NodeProcess, camera_overrides, drive_messages,  # noqa: E402
                                  image_msg, imu_msg, offline_steps, small_drive, spin_until, write_params)

from bevo_ros.config import BevoConfig, build_odometry, camera_model, resolve_path  # noqa: E402
from bevo_ros.io.learned_params import load_learned_params
from bevo_ros.core.validation import STANDARD_GRAVITY as G  # noqa: E402

from helpers.env import skip_outside_ci  # noqa: E402
from helpers.ros import domain_id_for, ros_context  # noqa: E402

T0 = 1000.0
MAX_STEP = 0.2  # m: the bound on a stationary vehicle's per-frame motion


# ------------------------------------------------------------------------------ a stationary vehicle
@pytest.fixture(autouse=True)
def one_torch_thread():
    """The engine as the node runs it (torch_threads: 1): 10x faster on a shared 2-core machine."""
    import torch

    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


def stationary(seconds: float = 4.0, imu_rate: int = 100, frame_rate: int = 10, seed: int = 0) -> list[tuple]:
    """``[("imu", t, gyro, accel) | ("image", t, img)]`` of a car standing still on the synthetic
    road: the same view every frame with fresh sensor noise, level IMU with noise."""
    rng = np.random.default_rng(seed)
    view = small_drive(duration=1.2).images[0].astype(np.float32)
    out = []
    for i in range(int(seconds * imu_rate)):
        t = T0 + i / imu_rate
        out.append(("imu", t, rng.normal(0, 0.002, 3), np.array([0.0, 0.0, G]) + rng.normal(0, 0.05, 3)))
        if i % (imu_rate // frame_rate) == 0:
            out.append(("image", t, np.clip(view + rng.normal(0, 2.0, view.shape), 0, 255).astype(np.uint8)))
    return out


def merged(*streams: list[tuple]) -> list[tuple]:
    return sorted((m for s in streams for m in s), key=lambda m: (m[1], m[0] != "imu"))


def as_ros(messages: list[tuple]) -> list[tuple]:
    return [(m[0], imu_msg(m[1], m[2], m[3]) if m[0] == "imu" else image_msg(m[1], m[2])) for m in messages]


def overrides() -> dict:
    return camera_overrides(small_drive(duration=1.2).camera)


def run_engine(messages: list[tuple], **extra) -> tuple[list, collections.Counter]:
    """The engine as the node and run_bag build it; ValueErrors are drops, counted by reason."""
    config = BevoConfig.from_flat({**overrides(), **extra})
    odo = build_odometry(config, load_learned_params(resolve_path(config.learned_params_file)),
                         camera_model(config.camera))
    steps, drops = [], collections.Counter()
    for m in messages:
        try:
            steps += odo.add_imu(m[1], m[2], m[3]) if m[0] == "imu" else odo.add_image(m[1], m[2])
        except ValueError as exc:
            drops[getattr(exc, "reason", type(exc).__name__)] += 1
    return steps + odo.flush(), drops


def step_lengths(positions: np.ndarray) -> np.ndarray:
    return np.linalg.norm(np.diff(np.asarray(positions)[:, :2], axis=0), axis=1)


@pytest.mark.parametrize("mode", ["fused", "paper"])
@pytest.mark.parametrize("value", [1e30, 100 * G], ids=["1e30", "100g"])
def test_absurd_imu_samples_are_dropped_and_a_stationary_vehicle_stays_put(value, mode):
    still = stationary()
    burst = [("imu", T0 + 1.0 + k * (2.0 / 300) + 1e-4, np.zeros(3), np.array([value, 0.0, G])) for k in range(300)]
    lone = [("imu", T0 + 3.2 + 1e-4, np.zeros(3), np.array([0.0, 0.0, value])),
            ("imu", T0 + 3.5 + 1e-4, np.array([0.0, 0.0, value]), np.array([0.0, 0.0, G]))]
    steps, drops = run_engine(merged(still, burst, lone), **{"odometry.mode": mode})
    frames = sum(m[0] == "image" for m in still)
    assert len(steps) == frames  # nothing lost
    lengths = step_lengths([s.position for s in steps])
    assert lengths.max() < MAX_STEP, lengths.round(3)
    assert drops == {"imu_accel_range": 301, "imu_gyro_range": 1}, drops


def test_a_black_frame_leaves_a_stationary_vehicle_still():
    """The fused engine's texture gate (issue 9): the frame is rejected, the pose carried."""
    still = stationary()
    t_black = T0 + 2.0
    msgs = [m if not (m[0] == "image" and abs(m[1] - t_black) < 1e-9) else ("image", m[1], np.zeros_like(m[2]))
            for m in still]
    steps, _ = run_engine(msgs)
    assert len(steps) >= sum(m[0] == "image" for m in still) - 1
    lengths = step_lengths([s.position for s in steps])
    assert lengths.max() < MAX_STEP, lengths.round(3)


# ------------------------------------------------------------------------------ the node in-process
rclpy = pytest.importorskip("rclpy")
from sensor_msgs.msg import CameraInfo  # noqa: E402

DOMAIN_ID = domain_id_for(17)  # in-process tests
PROCESS_DOMAIN_ID = domain_id_for(18)  # node subprocess tests


@pytest.fixture(scope="module")
def context():
    yield from ros_context(DOMAIN_ID)


@pytest.fixture
def harness(context):
    from test_node_inprocess import Harness

    made = []

    def make(**extra):
        ov = overrides()
        ov.update(input_qos="reliable", imu_qos_depth=1000, image_qos_depth=100, log_throttle_period=0.0,
                  use_camera_info=False)  # the camera.* parameters unless a test asks for CameraInfo
        ov.update(extra)
        made.append(Harness(context, ov, subscribe_outputs=False))
        return made[-1]

    yield make
    for h in made:
        h.close()


def camera_info(K, width: int, height: int) -> CameraInfo:
    info = CameraInfo(width=int(width), height=int(height))
    K = np.asarray(K, dtype=np.float64)
    info.k = K.reshape(-1).tolist()
    P = np.zeros((3, 4))
    P[:, :3] = K
    info.p = P.reshape(-1).tolist()
    return info


def odom_positions(odom) -> np.ndarray:
    return np.array([[m.pose.pose.position.x, m.pose.pose.position.y, m.pose.pose.position.z] for m in odom])


def test_absurd_camera_info_is_rejected_and_the_last_good_calibration_kept(harness):
    h = harness(use_camera_info=True)
    cam = small_drive(duration=1.2).camera
    K = cam.K.double().numpy()
    w, hh = cam.width, cam.height_px
    h.send("info", camera_info(K, w, hh))
    good = h.node.rig.camera.K.clone()
    tiny_f, far_c, big = K.copy(), K.copy(), K.copy()
    tiny_f[0, 0] = tiny_f[1, 1] = 1e-300
    far_c[0, 2] = 1e30
    big[:2] *= 2.0  # a plausible camera, but for 2x the images' size
    nan = K.copy()
    nan[1, 2] = np.nan
    bad = [camera_info(tiny_f, w, hh), camera_info(far_c, w, hh), camera_info(big, 2 * w, 2 * hh),
           camera_info(nan, w, hh)]
    messages = as_ros(stationary(seconds=2.0))
    frames = sum(k == "image" for k, _ in messages)
    every = len(messages) // (len(bad) + 1)
    for i, (kind, msg) in enumerate(messages):
        h.send(kind, msg)
        if i % every == every - 1 and bad:
            h.send("info", bad.pop(0))  # between frames, once the odometry runs
    h.settle()
    assert not bad
    assert len(h.odom) == frames
    lengths = step_lengths(odom_positions(h.odom))
    assert lengths.max() < MAX_STEP, lengths.round(3)
    assert h.node.drops["bad_camera_info"] == 4 and sum(h.node.drops.values()) == 4, dict(h.node.drops)
    assert bool((h.node.rig.camera.K == good).all())
    log = h.logged("bad_camera_info")
    assert "keeping the last good calibration" in log[0] and "fx = 1e-300" in log[0]
    assert "principal point (1e+30" in log[1]
    assert f"disagrees with the images ({w}x{hh})" in log[2]


def test_the_node_reports_a_rejected_black_frame_and_keeps_publishing(harness):
    """Fused mode in the node: the black frame is an event in /diagnostics, not a drop, and its
    odometry is the motion filter's prediction (a still car stays still)."""
    still = stationary(seconds=2.0)
    t_black = T0 + 1.0
    msgs = [m if not (m[0] == "image" and abs(m[1] - t_black) < 1e-9) else ("image", m[1], np.zeros_like(m[2]))
            for m in still]
    h = harness()
    for kind, msg in as_ros(msgs):
        h.send(kind, msg)
    h.settle()
    assert h.node.events["rejected_textureless"] >= 1, dict(h.node.events)
    assert not h.node.drops, dict(h.node.drops)
    assert h.node.counts["odometry_out"] >= sum(m[0] == "image" for m in msgs) - 1
    assert "carried by the motion filter's prediction" in h.logged("rejected_textureless")[0]


def test_lone_outlier_stamps_are_dropped_not_a_reset(harness):
    drive = small_drive(duration=1.2)
    messages = drive_messages(drive)
    expected = offline_steps(messages, overrides())
    t_mid = float(drive.imu_stamps[50])
    wild = {30: ("imu", imu_msg(t_mid + 1e6, [0, 0, 0], [0, 0, G])),  # far future
            60: ("image", image_msg(t_mid + 500.0, drive.images[3])),
            90: ("imu", imu_msg(1.0, [0, 0, 0], [0, 0, G]))}  # far past
    h = harness()
    for i, (kind, msg) in enumerate(messages):
        if i in wild:
            h.send(*wild[i])
        h.send(kind, msg)
    h.settle()
    assert h.node.drops["stamp_outlier"] == 3 and sum(h.node.drops.values()) == 3, dict(h.node.drops)
    assert not any(k.startswith("time_jump") or k == "reset" for k in h.node.events), dict(h.node.events)
    assert len(h.odom) == len(expected)
    assert np.allclose(odom_positions(h.odom), [s.position for s in expected], atol=1e-6, rtol=0)
    assert "no other message confirmed the jump" in h.logged("stamp_outlier")[0]


def test_confirmed_time_jumps_reset_and_their_logs_are_throttled(harness):
    h = harness(log_throttle_period=60.0)
    lines = []

    class Spy:
        def __getattr__(self, level):
            return lambda text, *a, **k: lines.append((level, text))

    h.node.report.logger = Spy()  # the throttled log lines go through the report
    drive = small_drive(duration=1.2)
    restarts = 6
    for r in range(restarts):  # a bag restarted 5 times, each time 10 s earlier
        for kind, msg in drive_messages(drive, stop=25, offset=10.0 * (restarts - r)):
            h.send(kind, msg)
    h.settle()
    assert h.node.events["time_jump_back"] == restarts - 1 and h.node.drops["stamp_outlier"] == 0
    jump_lines = [text for _, text in lines if "time jumped back" in text]
    assert len(jump_lines) == 1, lines
    assert len(h.odom) == restarts * 3  # 25 IMU samples at 100 Hz: 3 frames each, none lost


# ------------------------------------------------------------------------------ the node as a process
def adversarial_messages(rng: np.random.Generator, n: int, t: float, camera) -> list[tuple[str, object]]:
    """``n`` messages of every bad kind the issue lists, stamps around ``t`` (and far from it)."""
    from sensor_msgs.msg import Image

    from bevo_ros.io.ros_conversions import sec_to_stamp

    w, h = camera.width, camera.height_px
    K = camera.K.double().numpy()
    wild_floats = [np.nan, np.inf, -np.inf, 1e30, -1e30, 1e-300, 0.0, 100 * G, -5.0]

    def stamp():
        r = rng.random()
        if r < 0.5:
            return sec_to_stamp(t + rng.uniform(-0.5, 0.5))
        if r < 0.7:
            return sec_to_stamp(t + rng.choice([1e6, 3e4, -500.0, 10.0]))
        from builtin_interfaces.msg import Time

        return Time(sec=int(rng.integers(0, 2**31 - 1)), nanosec=int(rng.integers(0, 10**9)))

    out = []
    for _ in range(n):
        kind = rng.choice(["imu", "imu", "image", "info"])
        if kind == "imu":
            vals = rng.normal(0, 1, 6)
            vals[rng.integers(0, 6, rng.integers(1, 3))] = rng.choice(wild_floats)
            m = imu_msg(0.0, vals[:3], vals[3:])
            m.header.stamp = stamp()
        elif kind == "image":
            m = Image()
            m.encoding = str(rng.choice(["mono8", "rgb8", "mono16", "bgra8", "yuv422", "", "32FC1", "bayer_rggb8"]))
            m.width = int(rng.choice([w, 0, 1, w // 2, 100000, 2**31 - 1]))
            m.height = int(rng.choice([h, 0, 1, h * 2]))
            m.step = int(rng.choice([m.width, m.width * 3, 0, 7, 2**31 - 1]))
            m.data = rng.integers(0, 256, int(rng.choice([0, 1, w * h, w * h * 3, 1000]))).astype(np.uint8).tobytes()
            if rng.random() < 0.2:  # a valid image of a black or white frame
                m = image_msg(0.0, np.full((h, w), rng.choice([0, 255]), np.uint8))
            m.header.stamp = stamp()
        else:
            Kb = K.copy()
            Kb[rng.integers(0, 2), rng.integers(0, 3)] = rng.choice(wild_floats)
            m = camera_info(Kb, rng.choice([w, 0, 2 * w, 70000]), rng.choice([h, 0, h // 2]))
            m.header.stamp = stamp()
            kind = "info"
        out.append((str(kind), m))
    burst = sec_to_stamp(t + 0.25)
    for _ in range(500):  # an IMU burst: 500 samples, one stamp
        m = imu_msg(0.0, rng.normal(0, 1, 3), rng.normal(0, 30, 3))
        m.header.stamp = burst
        out.append(("imu", m))
    return out


@pytest.fixture(scope="module")
def process_context():
    """The node as a process (its two tests only: the rest of the module needs no executable)."""
    if not (VENV_BIN / "bevo_node").exists():
        skip_outside_ci(f"{VENV_BIN / 'bevo_node'} not installed (make setup)")
    yield from ros_context(PROCESS_DOMAIN_ID)


class Peer:
    """Publishers for the node's inputs and subscribers for its outputs, on their own executor."""

    def __init__(self, context):
        from diagnostic_msgs.msg import DiagnosticArray
        from nav_msgs.msg import Odometry
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.qos import QoSProfile, ReliabilityPolicy
        from sensor_msgs.msg import Image, Imu

        qos = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE)
        self.node = rclpy.create_node(f"reliability_tester_{os.getpid()}_{time.monotonic_ns()}", context=context)
        self.executor = SingleThreadedExecutor(context=context)
        self.executor.add_node(self.node)
        self.pubs = {"imu": self.node.create_publisher(Imu, "/imu/data", qos),
                     "image": self.node.create_publisher(Image, "/camera/image_rect", qos),
                     "info": self.node.create_publisher(CameraInfo, "/camera/camera_info", qos)}
        self.odom, self.diag = [], []
        self.node.create_subscription(Odometry, "/bevo/odometry", self.odom.append, qos)
        self.node.create_subscription(DiagnosticArray, "/diagnostics", self.diag.append, 10)

    def connected(self, timeout: float = 30.0) -> bool:
        return spin_until(self.executor, lambda: all(p.get_subscription_count() > 0 for p in self.pubs.values())
                          and self.node.count_publishers("/bevo/odometry") > 0, timeout)

    def publish(self, messages, pause: float = 0.0) -> None:
        for kind, msg in messages:
            self.pubs[kind].publish(msg)
            self.executor.spin_once(timeout_sec=pause)

    def diag_values(self) -> dict[str, str]:
        return {kv.key: kv.value for kv in self.diag[-1].status[0].values} if self.diag else {}

    def close(self) -> None:
        self.executor.remove_node(self.node)
        self.node.destroy_node()
        self.executor.shutdown()


def node_params(tmp_path: Path, **extra) -> Path:
    ov = overrides()
    ov.update(input_qos="reliable", imu_qos_depth=1000, image_qos_depth=100, use_camera_info=True,
              diagnostics_period=0.2, log_throttle_period=1.0)
    ov.update(extra)
    return write_params(tmp_path / "params.yaml", ov)


def test_fuzzed_node_survives_then_gives_odometry_and_answers_reset(process_context, tmp_path):
    from std_srvs.srv import Trigger

    drive = small_drive(duration=1.2)
    node = NodeProcess(node_params(tmp_path), str(PROCESS_DOMAIN_ID)).start()
    tester = Peer(process_context)
    try:
        t_start = time.monotonic()
        assert node.wait_for("ready:", 90), node.output
        assert tester.connected(), "discovery failed"
        t_ready = time.monotonic()
        good = drive_messages(drive, stop=40)  # a valid start, then the fuzz on its timeline
        tester.publish(good, 0.001)
        fuzz = adversarial_messages(np.random.default_rng(12), 2500, float(drive.imu_stamps[39]), drive.camera)
        tester.publish(fuzz)
        t_fuzz = time.monotonic()
        # the node has taken the whole fuzz when its received counters stop moving
        last, still = None, 0
        while still < 3:
            assert spin_until(tester.executor, lambda: len(tester.diag) > 0, 10)
            v = tester.diag_values()
            now = (v.get("imu_received"), v.get("images_received"))
            still, last = (still + 1 if now == last else 0), now
            tester.diag.clear()
        t_taken = time.monotonic()
        assert node.proc.poll() is None, node.output
        assert spin_until(tester.executor, lambda: len(tester.diag) > 0, 10)
        drops = {k[5:]: int(x) for k, x in tester.diag_values().items() if k.startswith("drop.")}
        print("fuzz drops:", drops)
        for reason in ("bad_encoding", "bad_image", "bad_image_size", "imu_nonfinite", "imu_accel_range",
                       "bad_camera_info", "stamp_outlier"):
            assert drops.get(reason, 0) > 0, (reason, drops)
        assert "callback_error" not in drops, node.output  # no unexpected exception anywhere

        # valid data on a new timeline: odometry again
        n = len(tester.odom)
        valid = drive_messages(drive, offset=5000.0)
        tester.publish(valid, 0.001)
        frames = [m.header.stamp for k, m in valid if k == "image"]
        # params/kitti.yaml holds the start for the camera's tilt: these 12 frames come after image_timeout
        assert spin_until(tester.executor, lambda: bool(tester.odom) and tester.odom[-1].header.stamp == frames[-1], 30), \
            (len(tester.odom) - n, len(frames), node.output[-3000:])
        got = [m.header.stamp for m in tester.odom[n:]]
        assert sum(f in got for f in frames) >= len(frames) - 1, (got, frames)
        print(f"phases: start {t_ready - t_start:.1f} s, fuzz sent {t_fuzz - t_ready:.1f} s, "
              f"taken {t_taken - t_fuzz:.1f} s, valid {time.monotonic() - t_taken:.1f} s")
        assert np.linalg.norm(odom_positions(tester.odom[-1:])[0, :2]) > 0.5

        client = tester.node.create_client(Trigger, "/bevo_node/reset")
        assert client.wait_for_service(timeout_sec=10)
        future = client.call_async(Trigger.Request())
        assert spin_until(tester.executor, future.done, 10) and future.result().success

        rc = node.interrupt()
        assert rc == 0, f"exit code {rc}\n{node.output}"
        assert "Traceback" not in node.output, node.output
    finally:
        node.kill()
        tester.close()


def kitti_sized(drive, factor: int = 4):
    """The drive with its images upscaled to KITTI's size (1280x384) and the intrinsics to match:
    the node then spends KITTI's time per frame (what made SIGINT land inside a busy callback)."""
    import dataclasses

    import cv2

    from bevo_ros.core.geometry import CameraModel

    cam = drive.camera
    K = cam.K.clone()
    K[:2] *= factor
    big = CameraModel(K, cam.width * factor, cam.height_px * factor, cam.T_base_cam, cam.mount_height)
    images = np.stack([cv2.resize(im, (big.width, big.height_px), interpolation=cv2.INTER_LINEAR)
                       for im in drive.images])
    return dataclasses.replace(drive, camera=big, images=images)


def test_sigint_and_sigterm_while_data_streams_exit_0_without_a_traceback(process_context, tmp_path):
    drive = kitti_sized(small_drive(duration=1.2))
    messages = [m for lap in range(3) for m in drive_messages(drive, offset=2.0 * lap)]
    cam = drive.camera
    info = camera_info(cam.K.double().numpy(), cam.width, cam.height_px)
    # the odometry flows from the first frames (no hold for the start's camera tilt): signals land in its callbacks
    params = node_params(tmp_path, **camera_overrides(cam), **{"filter.tilt_from_images": 0})
    rng = np.random.default_rng(1)
    tester = Peer(process_context)
    try:
        for run, sig in enumerate([signal.SIGINT] * 3 + [signal.SIGTERM]):
            node = NodeProcess(params, str(PROCESS_DOMAIN_ID)).start()
            try:
                assert node.wait_for("ready:", 90), node.output
                assert tester.connected(), "discovery failed"
                n0, sent, k = len(tester.odom), 0, 0
                stop_after = rng.uniform(0.1, 1.0)  # s of streaming before the signal
                start = time.monotonic()
                while node.proc.poll() is None and time.monotonic() - start < 30:
                    kind, msg = messages[k % len(messages)]
                    if kind == "image":
                        info.header.stamp = msg.header.stamp
                        tester.pubs["info"].publish(info)
                    tester.pubs[kind].publish(msg)
                    k += 1
                    tester.executor.spin_once(timeout_sec=0.0005)
                    if not sent and time.monotonic() - start > stop_after:
                        node.proc.send_signal(sig)
                        sent = 1
                rc = node.wait_exit(20)
                print(f"stop {run}: {sig.name} after {stop_after:.2f} s, {len(tester.odom) - n0} odometry, rc {rc}")
                assert rc == 0, f"exit code {rc} on {sig.name}\n{node.output}"
                for bad in ("Traceback", "RuntimeError", "callback_error"):
                    assert bad not in node.output, node.output
            finally:
                node.kill()
        assert len(tester.odom) > 0  # the data did flow
    finally:
        tester.close()


# ------------------------------------------------------------------------------ killed conversions
WRITER = """
import sys, time
from bevo_ros.io.bag import BagWriter
with BagWriter(sys.argv[1]) as w:
    i = 0
    while True:
        w.write_imu(i * 0.01, (0.0, 0.0, 0.0), (0.0, 0.0, 9.8))
        i += 1
        if i == 20:
            print("writing", flush=True)
        time.sleep(0.002)
"""


def start_writer(out: Path) -> subprocess.Popen:
    proc = subprocess.Popen([sys.executable, "-c", WRITER, str(out)], stdout=subprocess.PIPE, text=True,
                            env=dict(os.environ, PYTHONPATH=str(REPO)))
    assert proc.stdout.readline().strip() == "writing"
    return proc


def partials(out: Path) -> list[Path]:
    return sorted(out.parent.glob(f".{out.name}.partial-*"))


def test_a_killed_writer_leaves_a_partial_that_the_next_run_removes(tmp_path):
    from bevo_ros.io import bag

    out = tmp_path / "drive_bag"
    proc = start_writer(out)
    proc.kill()
    proc.wait()
    stale = partials(out)
    assert len(stale) == 1 and not out.exists()  # what a kill leaves
    proc = start_writer(out)  # the next run removes it; killed too
    assert stale[0] not in partials(out)
    proc.kill()
    proc.wait()
    stale = partials(out)
    assert len(stale) == 1
    with bag.BagWriter(tmp_path / "other") as w:  # another bag's partials are not touched
        pass
    assert partials(out) == stale and not w.removed_partials
    alive = start_writer(out)  # a concurrent writer's partial is not stale
    try:
        running = [p for p in partials(out) if p not in stale]
        with bag.BagWriter(out) as w:
            w.write_imu(0.0, (0.0, 0.0, 0.0), (0.0, 0.0, 9.8))
        assert w.removed_partials == [] and partials(out) == running  # `alive` already removed the stale one
        assert out.is_dir() and bag.bag_topics(out)
    finally:
        alive.kill()
        alive.wait()
    with bag.BagWriter(out, overwrite=True) as w:
        pass
    assert partials(out) == [] and w.removed_partials == running
    assert sorted(p.name for p in tmp_path.iterdir()) == ["drive_bag", "other"]


# ------------------------------------------------------------------------------ the engine's edges (review 2026-12-06)
def _engine(**odometry):
    from bevo_ros.datasets.synthetic import kitti_like_camera

    config = BevoConfig()
    for k, v in odometry.items():
        setattr(config.odometry, k, v)
    learned = load_learned_params(resolve_path(config.learned_params_file))
    return build_odometry(config, learned, camera=kitti_like_camera(scale=0.25))


def test_a_gate_below_one_sigma_is_refused_and_a_refused_belief_stays_finite():
    """odometry.gate 0 (in the node's range before) refused every measurement; each refusal widened
    the speed's variance 4x without end, to inf within a minute, and the DUKF's compensation on to
    NaN: every later IMU sample raised. Now refused at construction, and the widening stops at
    MAX_WIDENED_VAR: a wheel speed the gate always refuses leaves the engine finite."""
    from bevo_ros.config import ConfigError
    from bevo_ros.core.vehicle_filter import MAX_WIDENED_VAR
    from bevo_ros.ros.parameters import check

    with pytest.raises(ConfigError, match="odometry.gate must be >= 1"):
        _engine(gate=0.0)
    assert check("odometry.gate", 0.0) is not None and check("odometry.gate", 5.0) is None
    from bevo_ros.core.vehicle_filter import _widen_speed_belief, initial_vehicle_state

    P = initial_vehicle_state().P  # refused 200 times in a row (what gate 0 did to every measurement)
    for _ in range(200):
        P = _widen_speed_belief(P, True, 0.0)
    assert P[0][0] <= MAX_WIDENED_VAR[0] and P[1][1] <= MAX_WIDENED_VAR[1] and np.isfinite(np.array(P)).all()
    odo = _engine(gate=1.0)  # the lowest gate allowed: a wheel speed far off every frame stays finite
    for k in range(3000):
        t = T0 + 0.01 * k
        odo.add_imu(t, (0.0, 0.0, 0.0), (0.0, 0.0, G))
        odo.add_speed(t, 140.0 if k % 2 else -140.0, 1e-6)
    assert np.isfinite(odo._state[0]).all() and np.isfinite(np.array(odo._ext_speed[1].P)).all()
    odo.add_imu(T0 + 31.0, (0.0, 0.0, 0.0), (0.0, 0.0, G))


def test_a_refused_speed_sample_changes_nothing():
    """A speed stamped before the previous one is refused before it touches the engine: its
    unsigned flag no longer stuck (the direction of travel read it)."""
    from bevo_ros.core.odometry import OutOfOrderError

    odo = _engine()
    odo.add_speed(T0 + 10.0, 5.0, 0.01, signed=True)
    with pytest.raises(OutOfOrderError):
        odo.add_speed(T0 + 9.0, 5.0, 0.01, signed=False)
    assert odo._speed_unsigned is False and len(odo._speed_log) == 1
    with pytest.raises(ValueError, match="beyond any car"):  # 1e300 m/s ran the compensation to inf
        odo.add_speed(T0 + 11.0, 1e300, 0.01)
    assert len(odo._speed_log) == 1


def test_a_frame_before_the_imu_is_dropped_whichever_arrives_first():
    """An image stamped before the first IMU sample has no attitude: dropped and counted whether it
    arrives before that sample (the node's usual start: a camera's latency) or after it (it was
    processed with the first sample's attitude then); likewise one older than the kept history."""
    img = np.random.default_rng(0).integers(0, 255, (94, 310), dtype=np.uint8)
    for image_first in (True, False):
        odo = _engine()
        if image_first:
            out = odo.add_image(T0, img)
            out += odo.add_imu(T0 + 0.01, (0.0, 0.0, 0.0), (0.0, 0.0, G))
        else:
            odo.add_imu(T0 + 0.01, (0.0, 0.0, 0.0), (0.0, 0.0, G))
            out = odo.add_image(T0, img)
        assert out == [] and odo.counters.dropped_no_imu == 1, image_first
    odo = _engine()
    for k in range(4500):  # 4.5 s at 1 kHz: more than the history's 4000 samples
        odo.add_imu(T0 + 1e-3 * k, (0.0, 0.0, 0.1), (0.0, 0.0, G))
    assert odo.add_image(T0 + 0.2, img) == [] and odo.counters.dropped_no_imu == 1
    assert len(odo.add_image(T0 + 4.0, img)) == 1


def test_a_bev_size_of_any_number_runs():
    """The motion-consistency weight averaged over 5 px blocks and needed a BEV size that is a
    multiple of 5: the node's range [8, 4096] let 8, 101 or 128 through and every frame after the
    first raised. Partial blocks now: 8 and 101 px BEVs run (100 px, the default, is pinned to its
    trajectories by test_pinned_behaviour.py)."""
    msgs = drive_messages(small_drive(duration=0.6))
    base = camera_overrides(small_drive(duration=0.6).camera)
    for size in (8, 101):
        steps = offline_steps(msgs, dict(base, **{"bev.size": size}))
        assert len(steps) >= 5 and np.isfinite([s.position for s in steps]).all(), size


# ------------------------------------------------------------------------------ the node's edges (review 2026-12-06)
def _status(st) -> tuple[int, str, dict]:
    """A DiagnosticStatus as (level, message, values)."""
    return (st.level[0] if isinstance(st.level, bytes) else st.level, st.message, {kv.key: kv.value for kv in st.values})


def _statuses(h) -> dict[str, tuple[int, str, dict]]:
    h.diag.clear()
    assert spin_until(h.executor, lambda: len(h.diag) > 0, 5)
    return {st.name.split(": ", 1)[1]: _status(st) for st in h.diag[-1].status}


def test_the_node_refuses_unusable_frames_and_extrinsics_at_start(harness):
    """A camera.base_T_camera that is no rotation (or a mirror) started the node, which then dropped
    every image as bad_extrinsics while /diagnostics called the calibration OK; odom_frame equal to
    base_frame, or a frame id with a leading '/' (tf2 refuses both); an infinite count. Refused at
    start now, naming the parameter."""
    from bevo_ros.config import ConfigError, extrinsics_problem

    T = np.eye(4)
    T[1, 1] = -1.0  # orthonormal, determinant -1
    assert "reflection" in extrinsics_problem(T)
    base = list(overrides()["camera.base_T_camera"])
    squashed = base.copy()
    squashed[2] *= 2.0
    for extra, said in (({"camera.base_T_camera": squashed}, "camera.base_T_camera"),
                        ({"odom_frame": "base_link"}, "odom_frame"), ({"odom_frame": "/odom"}, "odom_frame"),
                        ({"path_max_length": float("inf")}, "path_max_length")):
        with pytest.raises(ConfigError, match=said):
            harness(**extra)


def test_a_degenerate_tf_static_and_imu_frame_churn_stay_harmless(harness):
    """A /tf_static base_link -> imu_link with a zero quaternion was stored as a NaN rotation and
    every IMU sample in that frame dropped as non-finite: left out now (logged), the IMU's axes
    taken as the base's. IMU frame ids that keep changing grew the rig's caches and the
    calibration status without bound: kept to MAX_IMU_FRAMES."""
    from geometry_msgs.msg import TransformStamped
    from tf2_msgs.msg import TFMessage
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy

    from bevo_ros.ros.rig import MAX_IMU_FRAMES

    h = harness()
    if h.node.static_tf is None or h.node.static_tf.backend != "tf2_msgs":
        pytest.skip("the node's own /tf_static listener (tf2_msgs) is not the backend here")
    qos = QoSProfile(depth=10, durability=DurabilityPolicy.TRANSIENT_LOCAL, reliability=ReliabilityPolicy.RELIABLE)
    pub = h.tester.create_publisher(TFMessage, "/tf_static", qos)
    t = TransformStamped()
    t.header.frame_id, t.child_frame_id = "base_link", "imu_link"
    t.transform.rotation.w = 0.0  # the quaternion all zero (its default is the identity)
    assert spin_until(h.executor, lambda: pub.get_subscription_count() > 0, 10)
    pub.publish(TFMessage(transforms=[t]))
    spin_until(h.executor, lambda: False, 0.5)
    assert h.node.static_tf.lookup("base_link", "imu_link") is None
    drive = small_drive(duration=1.2)
    msgs = [(k, m) for k, m in drive_messages(drive)]
    for k, m in msgs:
        if k == "imu":
            m.header.frame_id = "imu_link"
    h.send_all(msgs)
    h.settle()
    assert h.node.counts["odometry_out"] >= 5 and h.node.drops.get("imu_nonfinite", 0) == 0
    for i in range(3 * MAX_IMU_FRAMES):
        h.send("imu", imu_msg(100.0 + 0.01 * i, [0, 0, 0], [0, 0, 9.81], frame_id=f"imu_{i}"))
    h.settle()
    rig = h.node.rig
    assert len(rig._R_base_imu) <= MAX_IMU_FRAMES and len(rig._imu_frame_warned) <= MAX_IMU_FRAMES
    assert len(_statuses(h)["calibration"][2]["imu_frames"]) < 40 * MAX_IMU_FRAMES


def test_bad_camera_info_is_a_counted_drop_not_a_black_camera(harness):
    """plumb_bob with 3 coefficients made OpenCV raise inside the callback (an internal error with a
    traceback); a NaN R was accepted and every image remapped to black with the calibration OK. Both
    are bad_camera_info drops now; NaN in a field the calibration ignores no longer makes every
    repeat of the same message a new calibration."""
    drive = small_drive(duration=1.2)
    K = drive.camera.K.double().numpy()
    for case in ("d3", "r_nan"):
        h = harness(use_camera_info=True, camera_info_timeout=30.0, undistort="on")
        info = camera_info(K, drive.camera.width, drive.camera.height_px)
        info.distortion_model = "plumb_bob"
        info.d = [1e-6, 0.0, 0.0] if case == "d3" else [1e-6, 0.0, 0.0, 0.0, 0.0]
        if case == "r_nan":
            info.r = [float("nan")] * 9
        for _ in range(3):
            h.send("info", info)
        h.send_all(drive_messages(drive)[:40])
        h.settle()
        assert h.node.drops.get("bad_camera_info", 0) == 3 and not h.node.drops.get("callback_error"), case
        assert h.node.counts["odometry_out"] == 0, case
    h = harness(use_camera_info=True, camera_info_timeout=30.0)
    info = camera_info(K, drive.camera.width, drive.camera.height_px)
    info.k = [float("nan")] * 9  # ignored: P is used
    for _ in range(5):
        h.send("info", info)
    h.send_all(drive_messages(drive)[:40])
    h.settle()
    assert h.node.counts["odometry_out"] >= 3 and not h.node.events.get("camera_changed")


def test_diagnostics_warn_when_the_images_move_nothing(harness):
    """A covered or black camera: every frame rejected as textureless, the pose the motion filter's
    prediction, and /diagnostics said OK 'running'. A WARN now."""
    from bevo_ros.io.ros_conversions import stamp_to_sec

    drive = small_drive(duration=1.2)
    h = harness(sensor_late_factor=1000.0, imu_timeout=60.0, image_timeout=60.0)
    black = np.zeros((drive.camera.height_px, drive.camera.width), np.uint8)
    msgs = [(k, image_msg(stamp_to_sec(m.header.stamp), black)) if k == "image" else (k, m)
            for k, m in drive_messages(drive)]
    h.send_all(msgs)
    h.settle()
    level, message, _ = _statuses(h)["odometry"]
    assert h.node.events["rejected_textureless"] >= 10 and level == 1 and "rejected" in message


def test_diagnostics_warn_near_the_bevs_reach(harness, monkeypatch):
    """Frames that move past REACH_SHARE of the BEV's forward extent are near where the correlation
    fails (README, Limitations: Top speed): counted by the engine and a WARN with the distance. Here
    the share is made tiny (5 cm) so that this slow drive's frames count."""
    import bevo_ros.core.odometry as odometry

    monkeypatch.setattr(odometry, "REACH_SHARE", 5e-3)  # 5 cm with the default 10 m BEV
    drive = small_drive(duration=1.2)
    h = harness(sensor_late_factor=1000.0, imu_timeout=60.0, image_timeout=60.0)
    h.diag.clear()
    h.send_all(drive_messages(drive))
    h.settle()
    assert spin_until(h.executor, lambda: len(h.diag) > 0, 5)
    # every report while the frames came in (a report counts the frames since the one before it)
    said = [_status(st) for msg in h.diag for st in msg.status if st.name.endswith(": odometry")]
    warned = [(message, values) for level, message, values in said if level == 1 and "near the BEV's reach" in message]
    assert h.node.events["beyond_reach"] >= 5 and warned, said
    bev = h.node.config.bev
    message, values = warned[0]
    assert values["reach_m"] == f"{h.node.engine.reach:.2f}" == f"{5e-3 * bev.size * bev.metres_per_pixel:.2f}" == "0.05"
    assert "moved more than 0.05 m" in message


def test_live_jump_threshold_and_deprecated_names(harness):
    """max_time_jump_back is live: the /clock jump handler kept the start's threshold (a 1.2 s step
    back reset the odometry after the parameter had been raised to 5 s); so is image_wait, whose flush
    timer kept the start's period. The deprecated camera.height could be set and deleted at run time,
    doing nothing: read-only now."""
    from rclpy.parameter import Parameter

    drive = small_drive(duration=1.2)
    h = harness(use_sim_time=True, max_time_jump_back=0.5)
    assert h.node.set_parameters([Parameter("max_time_jump_back", value=5.0)])[0].successful
    assert not h.node.set_parameters([Parameter("camera.height", value=3.0)])[0].successful
    assert h.node.set_parameters([Parameter("image_wait", value=0.02)])[0].successful
    assert h.node._flush_timer.timer_period_ns == 10_000_000  # half the wait (it kept the start's 50 ms)
    msgs = drive_messages(drive)
    h.set_clock(msgs[-1][1].header.stamp)
    h.send_all(msgs[:40])
    h.settle()
    h.set_clock(msgs[0][1].header.stamp)  # 1.2 s back: within the 5 s now set
    assert h.node.events["clock_jump_reset"] == 0


def test_a_set_pose_that_waits_restarts_the_path_where_it_takes_effect(context):
    """A set_pose stamped after the latest frame takes effect when a frame reaches it: the path kept
    the old trajectory and jumped to the set pose; it restarts there now. A negative stamp is dropped
    (it was taken as 0, the latest frame)."""
    from test_node_inprocess import Harness, _set_pose_msg

    from bevo_ros.io.ros_conversions import stamp_to_sec

    drive = small_drive(duration=1.2)
    ov = overrides()
    ov.update(input_qos="reliable", imu_qos_depth=1000, image_qos_depth=100, log_throttle_period=0.0,
              use_camera_info=False, path_max_length=100)
    h = Harness(context, ov)
    try:
        pub = h.tester.create_publisher(type(_set_pose_msg(0, 0, 0, 0, 1.0)), "/bevo/set_pose", 10)
        assert spin_until(h.executor, lambda: pub.get_subscription_count() > 0, 10)
        msgs = drive_messages(drive)
        half = len(msgs) // 2
        h.send_all(msgs[:half])
        h.settle()
        pub.publish(_set_pose_msg(100.0, 100.0, 0.0, 0.0, -5.0))
        assert spin_until(h.executor, lambda: h.node.drops.get("set_pose_invalid", 0) == 1, 5)
        pub.publish(_set_pose_msg(100.0, 100.0, 0.0, 0.0, stamp_to_sec(msgs[half - 1][1].header.stamp) + 0.05))
        assert spin_until(h.executor, lambda: h.node.events["set_pose"] == 1, 5)
        h.send_all(msgs[half:])
        h.settle()
        assert spin_until(h.executor, lambda: h.paths and h.paths[-1].header.stamp == h.odom[-1].header.stamp, 5)
        xs = [p.pose.position.x for p in h.paths[-1].poses]
        assert min(xs) > 50.0 and len(xs) >= 3  # only the poses from the set one on
    finally:
        h.close()
