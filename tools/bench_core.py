#!/usr/bin/env python3
"""Benchmark the core engine on this machine: time per frame and where it goes.

One frame = 10 DUKF updates (100 Hz IMU, 10 Hz camera) + BEV projection + both phase
correlations, on a 1241x376 synthetic image and a 100x100 BEV, through the same
BevoOdometry the node runs. Prints median / p90 per frame, per stage, and peak RSS.
Target on a 2-core CPU: <= 3 ms per frame median (the paper: 21 ms on an RTX 3090).
"""
from __future__ import annotations

import argparse
import resource
import statistics
import sys
import time
from pathlib import Path

try:
    import bevo_ros  # noqa: F401
except ImportError:
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np
import torch

from bevo_ros.config import BevoConfig, LearnedParams, build_odometry
from bevo_ros.core.bev import project_to_bev
from bevo_ros.core.phase_correlation import DpcConfig, prepare, register_prepared
from bevo_ros.synthetic import make_drive


def pct(values: list[float], q: float) -> float:
    return float(np.percentile(np.array(values), q))


def timeit(fn, repeat: int) -> list[float]:
    out = []
    for _ in range(repeat):
        t = time.perf_counter()
        fn()
        out.append((time.perf_counter() - t) * 1e3)
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--frames", type=int, default=150, help="frames to time (default 150)")
    p.add_argument("--threads", type=int, default=1,
                   help="torch threads (default 1, as bevo_node's torch_threads: tiny tensors lose to thread sync)")
    p.add_argument("--device", default="cpu", help="cpu or cuda")
    args = p.parse_args(argv)
    if args.threads > 0:
        torch.set_num_threads(args.threads)
    device = args.device if (args.device == "cpu" or torch.cuda.is_available()) else "cpu"
    sync = torch.cuda.synchronize if device.startswith("cuda") else (lambda: None)

    drive = make_drive(seed=3, duration=(args.frames + 5) / 10.0, render="lazy")
    images = [np.asarray(drive.image(i)) for i in range(len(drive.frame_stamps))]
    config = BevoConfig()
    config.device = device
    odo = build_odometry(config, LearnedParams(), camera=drive.camera)
    spec = odo.spec

    # ---- full step through the engine
    per_frame: list[float] = []
    imu_i = 0
    warmup = 5
    for f, stamp in enumerate(drive.frame_stamps):
        t = time.perf_counter()
        while imu_i < len(drive.imu_stamps) and drive.imu_stamps[imu_i] <= stamp:
            odo.add_imu(float(drive.imu_stamps[imu_i]), drive.gyro[imu_i], drive.accel[imu_i])
            imu_i += 1
        odo.add_image(float(stamp), images[f])
        sync()
        if f >= warmup:
            per_frame.append((time.perf_counter() - t) * 1e3)

    # ---- stages in isolation
    state = odo.dukf.init_state(accel=torch.tensor([[0.0, 0.0, 9.81]], dtype=torch.float64))
    g = torch.tensor([[0.01, 0.02, 0.03]], dtype=torch.float64)
    a = torch.tensor([[0.1, 0.2, 9.8]], dtype=torch.float64)
    dt = torch.tensor([0.01], dtype=torch.float64)
    noise = odo.dukf.noise_floats()
    scalar_state = ((0.0, 0.0), (1e-3, 0.0, 1e-3))
    scalar_ms = timeit(lambda: odo.dukf.step_scalar(*scalar_state, (0.01, 0.02, 0.03), (0.1, 0.2, 9.8), 0.01, noise), 2000)
    add_imu_ms = []
    stamp0 = float(drive.imu_stamps[-1]) + 10.0  # after the drive: a fresh stretch of the same engine
    for k in range(500):
        t = time.perf_counter()
        odo.add_imu(stamp0 + 0.01 * k, drive.gyro[k], drive.accel[k])
        add_imu_ms.append((time.perf_counter() - t) * 1e3)
    with torch.no_grad():
        dukf_ms = timeit(lambda: odo.dukf.step(state, g, a, dt), 500)
        img = torch.as_tensor(images[0], device=device).float()[None, None] / 255.0
        pr = torch.zeros(1, device=device)
        cam = odo.camera
        bev_ms = timeit(lambda: (project_to_bev(img, cam, pr, pr, spec), sync()), 100)
        bev, mask = project_to_bev(img, cam, pr, pr, spec)
        dpc = DpcConfig()
        prep_ms = timeit(lambda: (prepare(bev, mask, dpc), sync()), 100)
        pa = prepare(bev, mask, dpc)
        reg_ms = timeit(lambda: (register_prepared(pa, pa, dpc), sync()), 100)

    rss_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print(f"device {device}, torch threads {torch.get_num_threads()}, {len(per_frame)} frames timed")
    print(f"full step (10 DUKF + BEV + 2 PC) : median {statistics.median(per_frame):7.2f} ms   p90 {pct(per_frame, 90):7.2f} ms")
    print(f"  add_imu (DUKF + road tilt)     : median {statistics.median(add_imu_ms) * 1e3:7.1f} us   p90 {pct(add_imu_ms, 90) * 1e3:7.1f} us")
    print(f"    DUKF step, scalar (engine)   : median {statistics.median(scalar_ms) * 1e3:7.1f} us")
    print(f"    DUKF step, tensor (training) : median {statistics.median(dukf_ms) * 1e3:7.1f} us")
    print(f"  BEV projection                 : median {statistics.median(bev_ms):7.2f} ms")
    print(f"  DPC prepare (window + FFTs)    : median {statistics.median(prep_ms):7.2f} ms")
    print(f"  DPC register (rot + trans)     : median {statistics.median(reg_ms):7.2f} ms")
    stages = 10 * statistics.median(add_imu_ms) + sum(statistics.median(v) for v in (bev_ms, prep_ms, reg_ms))
    print(f"  rest (image to tensor, motion and covariances, pose, result) : ~{statistics.median(per_frame) - stages:5.2f} ms")
    print(f"peak RSS {rss_mb:.0f} MB   (target: <= 3 ms per frame median on a 2-core CPU)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
