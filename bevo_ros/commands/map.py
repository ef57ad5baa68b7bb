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
from pathlib import Path

import torch

from bevo_ros.commands import add_params_option, bag_errors, guarded, new_parser, prog_name
from bevo_ros.config import bev_spec, load_config
from bevo_ros.datasets.rosbag import RigSettings
from bevo_ros.io import bag
from bevo_ros.io.maps import save_map
from bevo_ros.pipeline import map_from_steps, run_bag


def build_parser() -> argparse.ArgumentParser:
    p = new_parser(__doc__)
    p.add_argument("bag", help="rosbag2 directory with /ground_truth/odometry")
    p.add_argument("--out", required=True, help="map YAML to write (the PNG goes beside it)")
    add_params_option(p, learned=True)
    p.add_argument("--resolution", type=float, default=0.1, help="metres per pixel (default 0.1, the BEV's)")
    p.add_argument("--margin", type=float, default=2.0, help="metres around the BEVs (default 2)")
    p.add_argument("--frames", default=":", type=frame_range,
                   help="frame range FIRST:STOP of the frames with odometry, STOP excluded, either may be left out "
                        "(default all)")
    p.add_argument("--every", type=int, default=1, help="use every n-th frame (default 1)")
    return p


def frame_range(text: str) -> tuple[int | None, int | None]:
    """``--frames FIRST:STOP`` as ``(first, stop)``, None where left out: frame numbers >= 0 (a
    negative one would count from the end, unasked), STOP after FIRST."""
    first, colon, stop = text.partition(":")
    try:
        a, b = (int(v) if v.strip() else None for v in (first, stop))
    except ValueError:
        a = b = None
        colon = ""
    if not colon:
        raise argparse.ArgumentTypeError(f"{text!r}: expected FIRST:STOP, frame numbers (either may be left out)")
    if any(v is not None and v < 0 for v in (a, b)):
        raise argparse.ArgumentTypeError(f"{text!r}: frame numbers count from 0")
    if a is not None and b is not None and b <= a:
        raise argparse.ArgumentTypeError(f"{text!r}: STOP must be after FIRST (STOP excluded)")
    return a, b


def _check_frames(args: argparse.Namespace, count: int, what: str) -> None:
    """``--frames`` within ``count`` frames: past the end it was cut silently (0:500 of 51 frames mapped 51)."""
    first, stop = args.frames
    if (first is not None and first >= count) or (stop is not None and stop > count):
        spec = f"{'' if first is None else first}:{'' if stop is None else stop}"
        raise ValueError(f"--frames {spec}: {what} {count} frames, counted from 0 (--frames : is every frame with "
                         "odometry)")


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    torch.set_num_threads(1)
    return guarded("map_from_bag", lambda: _map(args), bag_errors())


def _map(args: argparse.Namespace) -> int:
    if not (args.resolution > 0 and math.isfinite(args.resolution)) or args.every < 1:
        raise ValueError("--resolution must be > 0 and --every >= 1")
    if not (args.margin >= 0 and math.isfinite(args.margin)):  # < 0 cut the BEVs' own edges off the map
        raise ValueError(f"--margin {args.margin}: must be >= 0 m (the ground kept around the BEVs)")
    if Path(args.out).suffix.lower() == ".png":  # before the engine's pass: its YAML would overwrite the image
        raise ValueError(f"--out {args.out}: give the map's YAML (e.g. {Path(args.out).with_suffix('.yaml')}); its "
                         "image is written beside it as .png")
    config, flat = load_config(args.params)
    topics = bag.bag_topics(args.bag)  # before the engine's pass: its metadata's image count
    images = next((topics[t][1] for t in (bag.IMAGE_TOPIC, bag.LEGACY_IMAGE_TOPIC) if t in topics), None)
    if images is not None:
        _check_frames(args, images, f"{args.bag} has")
    steps, rec, _ = run_bag(args.bag, config, args.learned or config.learned_params_file,
                            rig=RigSettings.from_params(flat, str(args.params)),
                            prog=prog_name("map_from_bag"))
    if rec.gt_poses is None:
        raise ValueError(f"{args.bag}: no /ground_truth/odometry messages: a map needs ground-truth poses")
    _check_frames(args, len(steps), f"{args.bag} gave odometry for")  # frames before any IMU give none
    first, stop = args.frames
    sel = steps[first:stop:args.every]
    if len(sel) < 1:
        raise ValueError(f"{args.bag}: no frame gave odometry (see the counts above)")
    aerial = map_from_steps(sel, rec, bev_spec(config), args.resolution, args.margin)
    path = save_map(aerial, args.out)
    w, h = aerial.extent
    print(f"{prog_name('map_from_bag')}: {len(sel)} BEVs -> {aerial.width}x{aerial.height} px at "
          f"{aerial.resolution:.3f} m/px "
          f"({w:.0f} x {h:.0f} m, origin {aerial.origin[0]:.2f}, {aerial.origin[1]:.2f}); wrote {path}")
    return 0
