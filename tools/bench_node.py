#!/usr/bin/env python3
"""Benchmark bevo_node end to end: replay a recording through DDS into a node subprocess.

    .venv/bin/python tools/bench_node.py                      # synthetic KITTI-like drive, 1x and 10x
    .venv/bin/python tools/bench_node.py --bag out/kitti06     # a rosbag2 (e.g. from bevo convert)
    .venv/bin/python tools/bench_node.py --rates 10 --duration 10 --torch-threads 1

For each replay rate a fresh ``bevo_node`` starts (``--ros-args --params-file``), this process
publishes the IMU and image messages on their stamps' schedule divided by the rate, and reports:
messages in/out, drops (DDS losses + the node's own drop counters by reason), latency from image
arrival in the node to odometry publication (the node's /diagnostics p50/p99), the end-to-end
latency publish -> odometry received here, and the node's CPU use and peak RSS (VmHWM).
Targets (KITTI at 10x: 100 Hz images, 1000 Hz IMU): zero drops, p99 <= 20 ms, RSS <= 400 MB.
Prints figures; not a test. DDS stays on localhost (ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST).
"""
from __future__ import annotations

import argparse
import array
import os
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

os.environ["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

import numpy as np  # noqa: E402
import yaml  # noqa: E402

TARGET_P99_MS = 20.0
TARGET_RSS_MB = 400.0


# ----------------------------------------------------------------------------------- inputs
def synthetic_messages(args) -> tuple[list, dict, str]:
    """``([(stamp, kind, msg)], camera parameter overrides, description)``; frames cached on disk."""
    from bevo_ros.core.geometry import CameraModel
    from bevo_ros.datasets.synthetic import kitti_like_camera, make_drive
    from bevo_ros.io.ros_conversions import gray_to_image_msg, sec_to_stamp
    from sensor_msgs.msg import Imu

    camera = kitti_like_camera()
    if args.quarter:
        K = camera.K.clone()
        K[:2] *= 0.25
        camera = CameraModel(K, 320, 96, camera.T_base_cam.clone(), camera.mount_height)
    drive = make_drive(seed=args.seed, duration=args.duration, frame_rate=args.frame_rate, imu_rate=args.imu_rate,
                       camera=camera, render=False)
    cache = Path(args.cache_dir) / (f"drive_s{args.seed}_d{args.duration:g}_f{args.frame_rate:g}_i{args.imu_rate:g}_"
                                    f"{camera.width}x{camera.height_px}.npy")
    if cache.is_file():
        images = np.load(cache)
    else:
        from bevo_ros.datasets.synthetic import render_frame

        t = time.monotonic()
        print(f"rendering {drive.num_frames} frames {camera.width}x{camera.height_px} (cached in {cache}) ...",
              flush=True)
        images = np.stack([render_frame(drive, i) for i in range(drive.num_frames)])
        cache.parent.mkdir(parents=True, exist_ok=True)
        np.save(cache, images)
        print(f"  {time.monotonic() - t:.1f} s", flush=True)
    frames = {int(i): k for k, i in enumerate(drive.frame_imu_index)}
    out = []
    for i, ts in enumerate(drive.imu_stamps):
        m = Imu()
        m.header.stamp = sec_to_stamp(float(ts))
        m.header.frame_id = "imu_link"
        m.angular_velocity.x, m.angular_velocity.y, m.angular_velocity.z = (float(v) for v in drive.gyro[i])
        m.linear_acceleration.x, m.linear_acceleration.y, m.linear_acceleration.z = (float(v) for v in drive.accel[i])
        out.append((float(ts), "imu", m))
        if i in frames:
            img = gray_to_image_msg(images[frames[i]])
            img.header.stamp = m.header.stamp
            img.header.frame_id = "camera"
            out.append((float(ts), "image", img))
    K = camera.K.double().numpy()
    overrides = {
        "camera.fx": float(K[0, 0]), "camera.fy": float(K[1, 1]), "camera.cx": float(K[0, 2]),
        "camera.cy": float(K[1, 2]), "camera.width": int(camera.width), "camera.height_px": int(camera.height_px),
        "camera.mount_height": float(camera.mount_height),
        "camera.base_T_camera": [float(v) for v in camera.T_base_cam.double().reshape(-1)],
    }
    desc = (f"synthetic drive seed {args.seed}, {args.duration:g} s, {camera.width}x{camera.height_px}, "
            f"IMU {args.imu_rate:g} Hz, images {args.frame_rate:g} Hz")
    return out, overrides, desc


def bag_messages(args) -> tuple[list, dict, str]:
    """IMU and image messages of a rosbag2, as rclpy messages in stamp order."""
    from bevo_ros.io.bag import iter_messages
    from builtin_interfaces.msg import Time
    from sensor_msgs.msg import Image, Imu

    out = []
    for topic, _, msg in iter_messages(args.bag, topics=[args.imu_topic, args.image_topic]):
        stamp = Time(sec=int(msg.header.stamp.sec), nanosec=int(msg.header.stamp.nanosec))
        t = stamp.sec + stamp.nanosec * 1e-9
        if topic == args.imu_topic:
            m = Imu()
            m.header.stamp, m.header.frame_id = stamp, msg.header.frame_id
            w, a = msg.angular_velocity, msg.linear_acceleration
            m.angular_velocity.x, m.angular_velocity.y, m.angular_velocity.z = float(w.x), float(w.y), float(w.z)
            m.linear_acceleration.x, m.linear_acceleration.y, m.linear_acceleration.z = float(a.x), float(a.y), float(a.z)
            out.append((t, "imu", m))
        else:
            m = Image(height=int(msg.height), width=int(msg.width), encoding=msg.encoding,
                      is_bigendian=int(msg.is_bigendian), step=int(msg.step))
            m.header.stamp, m.header.frame_id = stamp, msg.header.frame_id
            m.data = array.array("B", np.asarray(msg.data, dtype=np.uint8).tobytes())
            out.append((t, "image", m))
    out.sort(key=lambda x: (x[0], x[1] == "image"))
    if not out:
        raise SystemExit(f"no messages on {args.imu_topic} / {args.image_topic} in {args.bag}")
    n_img = sum(1 for _, k, _ in out if k == "image")
    span = out[-1][0] - out[0][0]
    desc = f"bag {args.bag}: {len(out) - n_img} IMU + {n_img} images over {span:.1f} s"
    return out, {}, desc


# ----------------------------------------------------------------------------------- one run
def proc_status(pid: int, key: str) -> float:
    """A ``/proc/<pid>/status`` value in MB (VmHWM = peak RSS, VmRSS = current)."""
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith(key + ":"):
                return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    return float("nan")


def run_once(messages, params_file: Path, rate: float, args) -> dict:
    import psutil
    import rclpy
    from diagnostic_msgs.msg import DiagnosticArray
    from nav_msgs.msg import Odometry
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.qos import QoSProfile, ReliabilityPolicy, qos_profile_sensor_data
    from sensor_msgs.msg import Image, Imu

    env = dict(os.environ, ROS_DOMAIN_ID=str(args.domain_id), ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST",
               PYTHONUNBUFFERED="1")
    cmd = [args.node, "--ros-args", "--params-file", str(params_file)]
    log = open(params_file.with_suffix(f".{rate:g}x.log"), "w")
    node = subprocess.Popen(cmd, env=env, stdout=log, stderr=subprocess.STDOUT, cwd=REPO)
    ctx = rclpy.context.Context()
    rclpy.init(context=ctx, domain_id=args.domain_id)
    tester = rclpy.create_node("bench_player", context=ctx)
    qos = (QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE) if args.qos == "reliable"
           else qos_profile_sensor_data)
    imu_pub = tester.create_publisher(Imu, args.imu_topic, qos)
    image_pub = tester.create_publisher(Image, args.image_topic, qos)
    sent_at: dict[tuple[int, int], float] = {}
    received: list[tuple[tuple[int, int], float]] = []
    diag: dict[str, str] = {}

    def on_odom(msg):
        received.append(((msg.header.stamp.sec, msg.header.stamp.nanosec), time.perf_counter()))

    def on_diag(msg):
        # the node publishes several statuses (odometry, calibration, each input): the counts are in
        # "bevo_node: odometry"; merged, so that none of the others' order hides them
        values = {kv.key: kv.value for st in msg.status if st.name.startswith("bevo_node") for kv in st.values}
        if "imu_received" in values:
            diag.clear()
            diag.update(values)

    tester.create_subscription(Odometry, "/bevo/odometry", on_odom, QoSProfile(depth=1000))
    tester.create_subscription(DiagnosticArray, "/diagnostics", on_diag, 10)
    executor = SingleThreadedExecutor(context=ctx)
    executor.add_node(tester)
    spinner = threading.Thread(target=executor.spin, daemon=True)
    spinner.start()
    result: dict = {"rate": rate}
    try:
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline and not (imu_pub.get_subscription_count() and
                                                   image_pub.get_subscription_count() and diag):
            if node.poll() is not None:
                raise SystemExit(f"bevo_node exited with {node.returncode}; see {log.name}")
            time.sleep(0.05)
        if not diag:
            raise SystemExit(f"bevo_node did not come up in 120 s; see {log.name}")
        time.sleep(0.5)
        proc = psutil.Process(node.pid)
        cpu0 = proc.cpu_times()
        rss_before = proc_status(node.pid, "VmRSS")
        t_first = messages[0][0]
        n_imu = n_img = 0
        start = time.perf_counter()
        late = 0.0
        for ts, kind, msg in messages:
            target = start + (ts - t_first) / rate
            while True:
                now = time.perf_counter()
                if now >= target:
                    break
                if target - now > 0.002:
                    time.sleep(target - now - 0.001)
            late = max(late, time.perf_counter() - target)
            if kind == "imu":
                imu_pub.publish(msg)
                n_imu += 1
            else:
                sent_at[(msg.header.stamp.sec, msg.header.stamp.nanosec)] = time.perf_counter()
                image_pub.publish(msg)
                n_img += 1
        replay_s = time.perf_counter() - start
        cpu_replay = proc.cpu_times()
        deadline = time.monotonic() + 10
        while time.monotonic() < deadline and len(received) < n_img:
            time.sleep(0.02)
        wall = time.perf_counter() - start
        cpu1 = proc.cpu_times()
        time.sleep(float(args.diag_period) * 2.5)  # a fresh /diagnostics with every frame in it
        values = dict(diag)
        result.update(
            imu_sent=n_imu, images_sent=n_img, replay_s=replay_s, player_max_late_ms=late * 1e3,
            odometry_received=len(received),
            imu_in=int(values.get("imu_received", 0)), images_in=int(values.get("images_received", 0)),
            odometry_out=int(values.get("odometry_published", 0)),
            node_drops={k[5:]: int(v) for k, v in values.items() if k.startswith("drop.")},
            events={k[6:]: int(v) for k, v in values.items() if k.startswith("event.")},
            latency_p50_ms=float(values.get("latency_p50_ms", "nan")),
            latency_p99_ms=float(values.get("latency_p99_ms", "nan")),
            latency_max_ms=float(values.get("latency_max_ms", "nan")),
            peak_quality_mean=values.get("peak_quality_mean", "nan"),
            cpu_percent=100.0 * ((cpu1.user + cpu1.system) - (cpu0.user + cpu0.system)) / max(wall, 1e-9),
            cpu_replay_percent=100.0 * ((cpu_replay.user + cpu_replay.system) - (cpu0.user + cpu0.system))
            / max(replay_s, 1e-9),
            rss_start_mb=rss_before, peak_rss_mb=proc_status(node.pid, "VmHWM"),
        )
        e2e = [t - sent_at[k] for k, t in received if k in sent_at]
        result["e2e_p50_ms"] = float(np.percentile(e2e, 50) * 1e3) if e2e else float("nan")
        result["e2e_p99_ms"] = float(np.percentile(e2e, 99) * 1e3) if e2e else float("nan")
        result["dds_lost"] = (n_imu - result["imu_in"]) + (n_img - result["images_in"])
        result["drops"] = result["dds_lost"] + sum(result["node_drops"].values())
    finally:
        if node.poll() is None:
            node.send_signal(signal.SIGINT)
            try:
                node.wait(timeout=20)
            except subprocess.TimeoutExpired:
                node.kill()
                node.wait()
        result["exit_code"] = node.returncode
        executor.shutdown()
        tester.destroy_node()
        rclpy.shutdown(context=ctx)
        spinner.join(timeout=5)
        log.close()
    return result


# ----------------------------------------------------------------------------------- main
def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--bag", help="rosbag2 to replay (default: a synthetic KITTI-like drive)")
    ap.add_argument("--params", default=None, help="bevo_node parameters file (default params/kitti.yaml, "
                                                   "with the synthetic camera for a synthetic drive)")
    ap.add_argument("--rates", type=float, nargs="+", default=[1.0, 10.0], help="replay speed factors")
    ap.add_argument("--duration", type=float, default=20.0, help="synthetic drive length, s")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--imu-rate", type=float, default=100.0, help="synthetic IMU rate (KITTI OXTS: 100 Hz)")
    ap.add_argument("--frame-rate", type=float, default=10.0, help="synthetic image rate (KITTI: 10 Hz)")
    ap.add_argument("--quarter", action="store_true", help="synthetic camera at 1/4 resolution (320x96)")
    ap.add_argument("--qos", choices=["reliable", "sensor_data"], default="reliable",
                    help="QoS of the replay and of the node's inputs (bag replay: reliable)")
    ap.add_argument("--image-qos-depth", type=int, default=100,
                    help="the node's image_qos_depth (its default, 5, shows what a live camera's best-effort "
                         "queue loses while the node is busy)")
    ap.add_argument("--torch-threads", type=int, default=None,
                    help="node parameter torch_threads (default: the parameters file's)")
    ap.add_argument("--imu-topic", default="/imu/data")
    ap.add_argument("--image-topic", default="/camera/image_rect")
    ap.add_argument("--domain-id", type=int, default=int(os.environ.get("BEVO_BENCH_DOMAIN_ID", 77)))
    ap.add_argument("--node", default=str(Path(sys.executable).parent / "bevo_node"), help="bevo_node executable")
    ap.add_argument("--cache-dir", default=str(REPO / "out" / "bench_cache"))
    ap.add_argument("--diag-period", type=float, default=0.5)
    args = ap.parse_args()

    messages, overrides, desc = bag_messages(args) if args.bag else synthetic_messages(args)
    base = Path(args.params) if args.params else REPO / "params" / "kitti.yaml"
    doc = yaml.safe_load(base.read_text())
    params = (doc.get("/**") or doc["bevo_node"])["ros__parameters"]
    params.update(overrides)
    learned = Path(str(params.get("learned_params_file", "params/learned_default.yaml")))
    if not learned.is_absolute():
        from bevo_ros.config import resolve_path

        params["learned_params_file"] = str(resolve_path(str(learned), base.resolve().parent))
    params.update(input_qos=args.qos, imu_qos_depth=1000, image_qos_depth=args.image_qos_depth, diagnostics_period=args.diag_period,
                  latency_window=100000, imu_topic=args.imu_topic, image_topic=args.image_topic,
                  use_camera_info=False)
    if args.torch_threads is not None:
        params["torch_threads"] = args.torch_threads
    workdir = Path(tempfile.mkdtemp(prefix="bevo-bench-"))
    params_file = workdir / "params.yaml"
    params_file.write_text(yaml.safe_dump(doc, sort_keys=False))

    n_img = sum(1 for _, k, _ in messages if k == "image")
    span = messages[-1][0] - messages[0][0]
    print(f"bevo_node benchmark: {desc}")
    print(f"  node: {args.node}; QoS {args.qos}; DDS domain {args.domain_id} (localhost); logs in {workdir}")
    results = []
    for rate in args.rates:
        print(f"  replaying at {rate:g}x ({(len(messages) - n_img) / span * rate:.0f} Hz IMU, "
              f"{n_img / span * rate:.0f} Hz images, {span / rate:.1f} s) ...", flush=True)
        results.append(run_once(messages, params_file, rate, args))

    hdr = (f"{'rate':>5} {'IMU sent/in':>12} {'img sent/in':>12} {'odom out/rx':>12} {'drops':>6} "
           f"{'lat p50/p99/max ms':>20} {'e2e p50/p99 ms':>15} {'CPU %':>6} {'RSS start/peak MB':>17} {'exit':>4}")
    print()
    print(hdr)
    print("-" * len(hdr))
    for r in results:
        print(f"{r['rate']:>4g}x {r['imu_sent']:>5}/{r['imu_in']:<6} {r['images_sent']:>5}/{r['images_in']:<6} "
              f"{r['odometry_out']:>5}/{r['odometry_received']:<6} {r['drops']:>6} "
              f"{r['latency_p50_ms']:>6.1f}/{r['latency_p99_ms']:>5.1f}/{r['latency_max_ms']:>6.1f} "
              f"{r['e2e_p50_ms']:>7.1f}/{r['e2e_p99_ms']:>6.1f} {r['cpu_percent']:>6.0f} "
              f"{r['rss_start_mb']:>11.0f}/{r['peak_rss_mb']:<5.0f} {r['exit_code']:>4}")
    for r in results:
        extra = []
        if r["node_drops"]:
            extra.append(f"node drops {r['node_drops']}")
        if r["dds_lost"]:
            extra.append(f"{r['dds_lost']} message(s) lost before the node")
        if r["events"]:
            extra.append(f"events {r['events']}")
        extra.append(f"node CPU during the replay {r['cpu_replay_percent']:.0f} %")
        extra.append(f"player max lateness {r['player_max_late_ms']:.1f} ms")
        extra.append(f"mean peak quality {r['peak_quality_mean']}")
        print(f"  {r['rate']:g}x: " + "; ".join(extra))
    top = max(results, key=lambda r: r["rate"])
    checks = [("zero drops", top["drops"] == 0 and top["odometry_received"] == top["images_sent"]),
              (f"p99 latency <= {TARGET_P99_MS:g} ms", top["latency_p99_ms"] <= TARGET_P99_MS),
              (f"peak RSS <= {TARGET_RSS_MB:g} MB", top["peak_rss_mb"] <= TARGET_RSS_MB)]
    print(f"targets at {top['rate']:g}x: " + ", ".join(f"{name}: {'PASS' if ok else 'FAIL'}" for name, ok in checks))
    return 0


if __name__ == "__main__":
    sys.exit(main())
