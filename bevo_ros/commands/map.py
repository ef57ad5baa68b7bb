"""``bevo map``: a BEVO+ map from any bag with ground truth: the BEVs of a drive mosaicked with the
ground-truth poses ("a previous drive" map), written as a nav2 map_server YAML + PNG (atomically).

The BEVs come from the very engine bevo_node runs (bevo_ros.pipeline, as bevo run); the poses from the bag's
/ground_truth/odometry at the image stamps (base_link in its odom frame, which becomes the map
frame). The PNG's alpha channel marks the ground some BEV covered.

  bevo map bags/kitti06 --out maps/kitti06.yaml --every 2
  .venv/bin/bevo_localizer --ros-args -p map_file:=maps/kitti06.yaml
"""
from __future__ import annotations

import argparse
import math

import torch

from bevo_ros.commands import add_params_option, bag_errors, guarded, new_parser
from bevo_ros.config import bev_spec, load_config
from bevo_ros.datasets.rosbag import RigSettings
from bevo_ros.io.maps import save_map
from bevo_ros.pipeline import map_from_steps, run_bag


def build_parser() -> argparse.ArgumentParser:
    p = new_parser(__doc__)
    p.add_argument("bag", help="rosbag2 directory with /ground_truth/odometry")
    p.add_argument("--out", required=True, help="map YAML to write (the PNG goes beside it)")
    add_params_option(p, learned=True)
    p.add_argument("--resolution", type=float, default=0.1, help="metres per pixel (default 0.1, the BEV's)")
    p.add_argument("--margin", type=float, default=2.0, help="metres around the BEVs (default 2)")
    p.add_argument("--frames", default=":", help="frame range first:stop (default all)")
    p.add_argument("--every", type=int, default=1, help="use every n-th frame (default 1)")
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    torch.set_num_threads(1)
    return guarded("map_from_bag", lambda: _map(args), bag_errors())


def _map(args: argparse.Namespace) -> int:
    if not (args.resolution > 0 and math.isfinite(args.resolution)) or args.every < 1:
        raise ValueError("--resolution must be > 0 and --every >= 1")
    config, flat = load_config(args.params)
    steps, rec, _ = run_bag(args.bag, config, args.learned or config.learned_params_file,
                            rig=RigSettings.from_params(flat, str(args.params)))
    if rec.gt_poses is None:
        raise ValueError(f"{args.bag}: no /ground_truth/odometry messages: a map needs ground-truth poses")
    first, _, stop = args.frames.partition(":")
    sel = steps[int(first) if first else 0:int(stop) if stop else None:args.every]
    if len(sel) < 1:
        raise ValueError(f"--frames {args.frames} --every {args.every} selects no frame")
    aerial = map_from_steps(sel, rec, bev_spec(config), args.resolution, args.margin)
    path = save_map(aerial, args.out)
    w, h = aerial.extent
    print(f"map_from_bag: {len(sel)} BEVs -> {aerial.width}x{aerial.height} px at {aerial.resolution:.3f} m/px "
          f"({w:.0f} x {h:.0f} m, origin {aerial.origin[0]:.2f}, {aerial.origin[1]:.2f}); wrote {path}")
    return 0
