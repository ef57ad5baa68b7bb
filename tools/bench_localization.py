#!/usr/bin/env python3
"""BEVO+ benchmark: accuracy on a long synthetic drive, what each appearance choice buys, and the
cost per frame (with its ratio to one plain BEV-to-BEV phase correlation measured in the same run).

  .venv/bin/python tools/bench_localization.py                 # 2 km drive, all figures
  .venv/bin/python tools/bench_localization.py --length 500 --no-appearance
"""
from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

try:
    import bevo_ros  # noqa: F401
except ImportError:
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np
import torch

from bevo_ros.core.geometry import BevSpec
from bevo_ros.core.map_localization import LocalizerConfig, MapMatchConfig, measure, se2_between, se2_compose
from bevo_ros.core.mosaic import compose_mosaic, mosaic_anchor
from bevo_ros.core.phase_correlation import DpcConfig, register
from bevo_ros.datasets.synthetic.aerial_map import (HARSH_APPEARANCE, SAME_APPEARANCE, MapAppearance, frame_bev,
                                                    make_localization_drive, render_aerial_map, run_localization)

SPEC = BevSpec()


def reference_dpc_ms(repeats: int = 50) -> float:
    """Median time of one plain phase correlation of two 100x100 BEVs (the odometry's step)."""
    g = torch.Generator().manual_seed(0)
    a, b = torch.rand(1, 1, 100, 100, generator=g), torch.rand(1, 1, 100, 100, generator=g)
    m = torch.ones_like(a)
    cfg = DpcConfig()
    register(a, b, m, m, cfg)
    ts = []
    for _ in range(repeats):
        t = time.perf_counter()
        register(a, b, m, m, cfg)
        ts.append(time.perf_counter() - t)
    return float(np.median(ts)) * 1e3


def appearance_table(seed: int, trials: int) -> list[tuple[str, str, float, float, float]]:
    """Single measurements from a 3 m / 5 deg wrong prediction: success rate (< 0.5 m, < 1 deg),
    median position / yaw error, for each representation, against a heterogeneous map and a map
    of identical appearance."""
    ld = make_localization_drive(seed=seed, length=60.0 + trials * 8.0)
    maps = {"same appearance": render_aerial_map(ld.drive.ground, ld.gt[:, :2], appearance=SAME_APPEARANCE),
            "heterogeneous": render_aerial_map(ld.drive.ground, ld.gt[:, :2], appearance=MapAppearance(), seed=seed),
            "harsh": render_aerial_map(ld.drive.ground, ld.gt[:, :2], appearance=HARSH_APPEARANCE, seed=seed)}
    rng = np.random.default_rng(seed)
    cases = []
    for t in range(trials):
        end = 25 + t * 8
        idx = list(range(end - 20, end + 1, 2))
        bevs = torch.from_numpy(np.stack([frame_bev(ld.drive, i, SPEC, rng)[0] for i in idx]))[:, None]
        masks = torch.from_numpy(np.stack([frame_bev(ld.drive, i, SPEC)[1] for i in idx]))[:, None]
        poses = torch.tensor(ld.gt[idx], dtype=torch.float32)
        ang = rng.uniform(0, 2 * math.pi)
        pert = np.array([3.0 * math.cos(ang), 3.0 * math.sin(ang), math.radians(5.0) * rng.choice([-1, 1])])
        cases.append((bevs, masks, poses, pert))
    rows = []
    for map_name, aerial in maps.items():
        grey = aerial.grey()
        for mode, whitening in VARIANTS:
            cfg = _match_config(mode, whitening)
            errs = []
            for bevs, masks, poses, pert in cases:
                anchor = mosaic_anchor(poses, SPEC)
                mos, cov = compose_mosaic(bevs, masks, poses, anchor, SPEC, cfg.size, cfg.resolution)
                pred = se2_compose(anchor.double().numpy(), pert)
                meas = measure(mos, cov, grey, torch.tensor(pred, dtype=torch.float32)[None], cfg)
                res = se2_between(anchor.double().numpy(), se2_compose(pred, meas.correction[0].double().numpy()))
                errs.append((math.hypot(res[0], res[1]), abs(math.degrees(res[2]))))
            e = np.array(errs)
            ok = float(np.mean((e[:, 0] < 0.5) & (e[:, 1] < 1.0)))
            label = f"{mode}, " + ("phase-only" if whitening == 0 else f"whitening floor {whitening}")
            rows.append((map_name, label, ok, float(np.median(e[:, 0])), float(np.median(e[:, 1]))))
    return rows


VARIANTS = (("raw", 0.5), ("raw", 0.0), ("lcn", 0.0), ("gradient", 0.0))


def _match_config(mode: str, whitening: float) -> MapMatchConfig:
    base = MapMatchConfig()
    return MapMatchConfig(appearance=mode, dpc=type(base.dpc)(**{**base.dpc.__dict__, "whitening_floor": whitening}))


def filter_table(seed: int, length: float) -> list[tuple[str, str, float, float, int, int]]:
    """The whole localiser per representation on a drive of ``length`` m, 3 m / 5 deg start."""
    ld = make_localization_drive(seed=seed, length=length)
    start = se2_compose(ld.gt[0], np.array([3 / math.sqrt(2), -3 / math.sqrt(2), math.radians(5)]))
    rows = []
    for map_name, app in (("heterogeneous", MapAppearance()), ("harsh", HARSH_APPEARANCE)):
        aerial = render_aerial_map(ld.drive.ground, ld.gt[:, :2], appearance=app, seed=seed)
        for mode, whitening in VARIANTS:
            cfg = LocalizerConfig(match=_match_config(mode, whitening))
            run = run_localization(ld, aerial, start, config=cfg, seed=seed)
            e = run.errors(start=len(ld.gt) // 10)
            label = f"{mode}, " + ("phase-only" if whitening == 0 else f"whitening floor {whitening}")
            rows.append((map_name, label, e["pos_rms"], e["yaw_rms_deg"], run.counters.accepted,
                         run.counters.measurements))
    return rows


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="bench_localization.py", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--length", type=float, default=2000.0, help="synthetic drive length, m (default 2000; 0 skips)")
    p.add_argument("--seed", type=int, default=2)
    p.add_argument("--trials", type=int, default=24, help="measurements per appearance variant (default 24)")
    p.add_argument("--filter-length", type=float, default=400.0, help="drive of the per-representation runs, m")
    p.add_argument("--no-appearance", action="store_true", help="skip the appearance comparison")
    p.add_argument("--device", default="cpu")
    args = p.parse_args(argv)
    torch.set_num_threads(1)

    ref = reference_dpc_ms()
    print(f"reference: one plain BEV-to-BEV phase correlation (100x100): {ref:.2f} ms")

    t = time.perf_counter()
    ld = make_localization_drive(seed=args.seed, length=max(args.length, 50.0))
    aerial = render_aerial_map(ld.drive.ground, ld.gt[:, :2], appearance=MapAppearance(), seed=args.seed)
    print(f"drive {ld.length:.0f} m, {len(ld.gt)} frames; map {aerial.width}x{aerial.height} px at "
          f"{aerial.resolution} m/px ({time.perf_counter() - t:.1f} s to make)")
    for name, off in () if args.length <= 0 else (("3 m / 5 deg initial error", np.array([3 / math.sqrt(2), -3 / math.sqrt(2), math.radians(5)])),
                      ("50 m off (wrong place)", np.array([0.0, 50.0, 0.0]))):
        t = time.perf_counter()
        run = run_localization(ld, aerial, se2_compose(ld.gt[0], off), config=LocalizerConfig(), seed=args.seed,
                               device=args.device)
        e = run.errors(start=len(ld.gt) // 10)
        c = run.counters
        print(f"\n{name}: {time.perf_counter() - t:.1f} s")
        print(f"  BEVO+          : position RMS {e['pos_rms']:.3f} m (max {e['pos_max']:.2f}), yaw RMS "
              f"{e['yaw_rms_deg']:.3f} deg (frames after the first 10 %)")
        print(f"  odometry alone : position RMS {e['odom_pos_rms']:.2f} m, yaw RMS {e['odom_yaw_rms_deg']:.2f} deg, "
              f"end error {e['odom_end_error']:.1f} m ({100 * e['odom_end_error'] / ld.length:.2f} % of the path)")
        print(f"  map updates    : {c.measurements} measured, {c.accepted} accepted, {c.rejected_quality} low quality, "
              f"{c.rejected_gate} gated, {c.skipped_no_map} outside the map; final status {run.steps[-1].status}")
        print(f"  cost           : {run.seconds_per_frame * 1e3:.2f} ms per frame on average "
              f"({run.seconds_per_frame * 1e3 / ref:.1f}x the reference), {run.seconds_per_update * 1e3:.1f} ms per "
              f"map update ({run.seconds_per_update * 1e3 / ref:.1f}x), one update every "
              f"{LocalizerConfig().update_distance:.0f} m")

    if not args.no_appearance:
        print("\nappearance choices: single measurements from a 3 m / 5 deg wrong prediction "
              f"({args.trials} mosaics)")
        print("| map | representation | success (< 0.5 m, < 1 deg) | median position error (m) | median yaw error (deg) |")
        print("|---|---|---|---|---|")
        for map_name, label, ok, pe, ye in appearance_table(args.seed, args.trials):
            print(f"| {map_name} | {label} | {100 * ok:.0f} % | {pe:.3f} | {ye:.2f} |")
        print(f"\nappearance choices through the whole localiser ({args.filter_length:.0f} m drive, 3 m / 5 deg start)")
        print("| map | representation | position RMS (m) | yaw RMS (deg) | map updates accepted |")
        print("|---|---|---|---|---|")
        for map_name, label, pe, ye, acc, n in filter_table(args.seed + 1, args.filter_length):
            print(f"| {map_name} | {label} | {pe:.3f} | {ye:.3f} | {acc}/{n} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
