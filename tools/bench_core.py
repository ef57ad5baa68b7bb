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
from bevo_ros.core import odometry as engine_module
from bevo_ros.synthetic import make_drive

# Engine stages timed where they run (inside BevoOdometry, on a new image each frame: cold caches,
# as in the node), by wrapping the functions the engine module calls.
STAGES = {
    "project_to_bev": "BEV projection (image -> 100x100)",
    "prepare": "DPC prepare (weight + FFTs)",
    "register_prepared": "DPC register (rotation + translation)",
}


class StageTimer:
    """Wrap ``engine_module.<name>`` so every call adds its duration (ms) to ``self.last[name]``."""

    def __init__(self, sync) -> None:
        self.last: dict[str, float] = {}
        for name in STAGES:
            setattr(engine_module, name, self._wrap(name, getattr(engine_module, name), sync))

    def _wrap(self, name, fn, sync):
        def timed(*args, **kwargs):
            t = time.perf_counter()
            out = fn(*args, **kwargs)
            sync()
            self.last[name] = self.last.get(name, 0.0) + (time.perf_counter() - t) * 1e3
            return out
        return timed


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
    p.add_argument("--frames", type=int, default=100, help="frames per pass (default 100)")
    p.add_argument("--passes", type=int, default=3,
                   help="passes over the drive (default 3); a busy shared host shows up as one slow pass")
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
    timer = StageTimer(sync)
    odo = build_odometry(config, LearnedParams(), camera=drive.camera)

    # ---- full step through the engine, frame by frame, as the node drives it
    per_frame: list[float] = []
    imu_part: list[float] = []  # the frame's IMU messages
    stage_ms: dict[str, list[float]] = {name: [] for name in STAGES}
    pass_medians: list[float] = []
    warmup = 5
    for _ in range(max(1, args.passes)):
        odo.reset()
        this_pass: list[float] = []
        imu_i = 0
        for f, stamp in enumerate(drive.frame_stamps):
            timer.last.clear()
            t = time.perf_counter()
            while imu_i < len(drive.imu_stamps) and drive.imu_stamps[imu_i] <= stamp:
                odo.add_imu(float(drive.imu_stamps[imu_i]), drive.gyro[imu_i], drive.accel[imu_i])
                imu_i += 1
            t_imu = time.perf_counter()
            odo.add_image(float(stamp), images[f])
            sync()
            if f >= warmup and len(timer.last) == len(STAGES):
                this_pass.append((time.perf_counter() - t) * 1e3)
                imu_part.append((t_imu - t) * 1e3)
                for name in STAGES:
                    stage_ms[name].append(timer.last[name])
        per_frame += this_pass
        pass_medians.append(statistics.median(this_pass))

    # ---- one DUKF step in isolation: the engine's float path and the differentiable tensor path
    state = odo.dukf.init_state(accel=torch.tensor([[0.0, 0.0, 9.81]], dtype=torch.float64))
    g = torch.tensor([[0.01, 0.02, 0.03]], dtype=torch.float64)
    a = torch.tensor([[0.1, 0.2, 9.8]], dtype=torch.float64)
    dt = torch.tensor([0.01], dtype=torch.float64)
    noise = odo.dukf.noise_floats()
    scalar_state = ((0.0, 0.0), (1e-3, 0.0, 1e-3))
    scalar_ms = timeit(lambda: odo.dukf.step_scalar(*scalar_state, (0.01, 0.02, 0.03), (0.1, 0.2, 9.8), 0.01, noise), 2000)
    add_imu_ms = []
    stamp0 = float(drive.imu_stamps[-1]) + 10.0  # after the drive: a fresh stretch of the same engine
    for k in range(min(500, len(drive.gyro))):
        t = time.perf_counter()
        odo.add_imu(stamp0 + 0.01 * k, drive.gyro[k], drive.accel[k])
        add_imu_ms.append((time.perf_counter() - t) * 1e3)
    with torch.no_grad():
        dukf_ms = timeit(lambda: odo.dukf.step(state, g, a, dt), 500)

    rss_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print(f"device {device}, torch threads {torch.get_num_threads()}, {len(per_frame)} frames timed "
          f"in {len(pass_medians)} passes")
    print(f"full step (10 DUKF + BEV + 2 PC) : median {statistics.median(per_frame):7.2f} ms   p90 {pct(per_frame, 90):7.2f} ms"
          f"   (pass medians {' / '.join(f'{m:.2f}' for m in pass_medians)} ms)")
    med = statistics.median
    print("  where it goes (medians inside the frame loop):")
    print(f"    10 x add_imu (DUKF + road tilt)       : {med(imu_part):6.2f} ms"
          f"   (one add_imu alone: {med(add_imu_ms) * 1e3:.1f} us)")
    for name, label in STAGES.items():
        print(f"    {label:38s}: {med(stage_ms[name]):6.2f} ms")
    rest = [f - i - sum(stage_ms[n][k] for n in STAGES) for k, (f, i) in enumerate(zip(per_frame, imu_part))]
    print(f"    {'rest (to tensor, motion, covariance, pose)':38s}: {med(rest):6.2f} ms")
    print(f"  one DUKF step: float path (engine) {med(scalar_ms) * 1e3:.1f} us, tensor path (training) {med(dukf_ms) * 1e3:.1f} us")
    print(f"peak RSS {rss_mb:.0f} MB   (target: <= 3 ms per frame median on a 2-core CPU)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
