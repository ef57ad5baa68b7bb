#!/usr/bin/env python3
"""Record the pinned behaviour (test/data/pinned_behaviour.json) that test/test_pinned_behaviour.py
compares against: a refactor must leave these numbers identical.

Recorded:
  kitti/<mode>      run_bag's trajectory (stamp, x, y, z of base_link in odom per frame) on the KITTI
                    sample (odometry sequence 06, converted by kitti_to_bag), modes fused and paper, at
                    params/kitti.yaml's filter.mounting_pitch as is (filter.tilt_from_images: 0)
  kitti/start_tilt  the camera's tilt change (deg) the engine's start measures on the sample with
                    params/kitti.yaml (filter.tilt_from_images: OpenCV's tracks and RANSAC, pinned to a
                    tolerance of its own: a pair's inliers may differ with another CPU's SIMD rounding)
  synthetic/<mode>  the same on a short synthetic bumpy drive (test/helpers/drives.py make_bumpy_bag)
  training          a 1-epoch train_from_bag on that synthetic drive (fixed seed: random init and
                    its O search; the vehicle-filter and suspension fits off): the learned (best validated) O and
                    Q, and the O and Q after the epoch's Adam steps

Re-record (after an intended change of the numbers, e.g. a new fused engine), one command:
  .venv/bin/python tools/record_pinned.py            # everything (KITTI parts need the sample)
  .venv/bin/python tools/record_pinned.py --only kitti/fused synthetic/fused
Parts not selected (or the KITTI ones without the sample) keep their recorded values.
"""
from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

try:
    import bevo_ros  # noqa: F401
except ImportError:  # running from a source checkout without installing
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

REPO = Path(__file__).resolve().parents[1]
PINNED = REPO / "test" / "data" / "pinned_behaviour.json"
KITTI_ROOT = REPO.parent / "shared" / "data" / "kitti"
MODES = ("fused", "paper")
PARTS = (*(f"kitti/{m}" for m in MODES), "kitti/start_tilt", *(f"synthetic/{m}" for m in MODES), "training")
SYNTH_SECONDS = 3.0  # the short synthetic drive (30 frames at 10 Hz)
TRAIN_ARGS = ("--epochs", "1", "--steps-per-bag", "2", "--seed", "0", "--vehicle-steps", "0", "--suspension-evals", "0",
              "--threads", "1")


def kitti_bag(kitti_root: Path, out: Path) -> Path:
    """The KITTI sample (odometry sequence 06) converted by bevo convert."""
    from bevo_ros.commands import convert

    rc = convert.main(["--odometry", str(kitti_root / "odometry"), "--sequence", "06",
                       "-o", str(out), "--overwrite", "-q"])
    if rc != 0:
        raise RuntimeError(f"kitti_to_bag failed ({rc})")
    return out


def synthetic_bag(out: Path) -> Path:
    sys.path.insert(0, str(REPO / "test"))
    from helpers.drives import make_bumpy_bag

    return make_bumpy_bag(out, seconds=SYNTH_SECONDS)


def trajectory(bag_path: Path, params: Path, mode: str) -> list[list[float]]:
    """``[[stamp, x, y, z], ...]`` of ``pipeline.run_bag`` (the node's engine) over ``bag_path``, at the
    params' mounting pitch as is (the start's measurement of it is ``start_tilt``'s)."""
    import torch

    from bevo_ros.config import load_config
    from bevo_ros.pipeline import run_bag

    torch.set_num_threads(1)
    config, _ = load_config(params)
    config.odometry.mode = mode
    config.filter.tilt_from_images = 0
    steps, _, _ = run_bag(bag_path, config, config.learned_params_file)
    return [[float(s.stamp), *map(float, s.position)] for s in steps]


def start_tilt(bag_path: Path, params: Path) -> float:
    """The tilt change (deg) the engine's start measures over ``bag_path`` with ``params``."""
    import math

    import torch

    from bevo_ros.config import load_config
    from bevo_ros.pipeline import run_bag

    torch.set_num_threads(1)
    config, _ = load_config(params)
    _, _, odo = run_bag(bag_path, config, config.learned_params_file)
    if odo.tilt_measurement is None or not odo.tilt_measurement.measured:
        raise RuntimeError(f"the start's tilt was not measured: {odo.tilt_measurement}")
    return math.degrees(odo.tilt_measurement.change)


def training_result(bag_path: Path, workdir: Path) -> dict[str, list[float]]:
    """O (rad^2/s) and Q (rad^2), [pitch, roll], of a 1-epoch fixed-seed train_from_bag: the learned
    (best validated) ones and the checkpoint's current ones after the epoch's Adam steps, both from the
    checkpoint (the trainer's; the file written holds what the fused engine then accepted)."""
    from bevo_ros.io.learned_params import load_learned_params

    out = workdir / "learned.yaml"
    from bevo_ros.commands import train

    rc = train.main([str(bag_path), "--out", str(out), "--params",
                     str(REPO / "params" / "synthetic.yaml"), *TRAIN_ARGS, "-q"])
    if rc != 0:
        raise RuntimeError(f"train_from_bag failed ({rc})")
    from bevo_ros.training.trainer import load_checkpoint

    load_learned_params(out)  # written and loadable
    ckpt = load_checkpoint(out.with_name(out.name + ".ckpt.yaml"))
    best, current = ckpt["best"], ckpt["current"]  # the best validated; after the epoch's Adam steps
    return {"O": [float(v) for v in best["process_noise_density"]],
            "Q": [float(v) for v in best["measurement_noise_variance"]],
            "O_after_adam": [float(v) for v in current["process_noise_density"]],
            "Q_after_adam": [float(v) for v in current["measurement_noise_variance"]]}


def compute(parts, workdir: Path, kitti_root: Path | None = KITTI_ROOT) -> dict:
    """The selected parts' values, ``{part: value}``; KITTI parts are left out without the sample."""
    parts = list(parts)
    values: dict = {}
    if any(p.startswith("synthetic/") or p == "training" for p in parts):
        synth = synthetic_bag(workdir / "synthetic")
        for p in parts:
            if p.startswith("synthetic/"):
                values[p] = trajectory(synth, REPO / "params" / "synthetic.yaml", p.split("/")[1])
        if "training" in parts:
            values["training"] = training_result(synth, workdir)
    kitti_parts = [p for p in parts if p.startswith("kitti/")]
    if kitti_parts and kitti_root is not None and (kitti_root / "odometry" / "sequences" / "06").is_dir():
        kbag = kitti_bag(kitti_root, workdir / "kitti06")
        for p in kitti_parts:
            values[p] = (start_tilt(kbag, REPO / "params" / "kitti.yaml") if p == "kitti/start_tilt"
                         else trajectory(kbag, REPO / "params" / "kitti.yaml", p.split("/")[1]))
    return values


def to_json(pinned: dict) -> str:
    """One row per line (reviewable diffs); floats as Python's repr, which JSON reads back exactly."""
    parts = []
    for key in sorted(pinned):
        value = pinned[key]
        if isinstance(value, list):
            body = "[\n" + ",\n".join("  " + json.dumps(row) for row in value) + "\n ]"
        else:
            body = json.dumps(value)
        parts.append(f" {json.dumps(key)}: {body}")
    return "{\n" + ",\n".join(parts) + "\n}\n"


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="record_pinned.py", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--only", nargs="+", choices=PARTS, default=list(PARTS), help="parts to re-record")
    p.add_argument("--kitti-root", type=Path, default=KITTI_ROOT, help="KITTI sample root (default ../shared/data/kitti)")
    p.add_argument("--out", type=Path, default=PINNED, help="JSON to update (default test/data/pinned_behaviour.json)")
    args = p.parse_args(argv)
    from bevo_ros.io.files import atomic_write_text

    pinned = json.loads(args.out.read_text()) if args.out.is_file() else {}
    with tempfile.TemporaryDirectory(prefix="bevo-pinned-") as tmp:
        values = compute(args.only, Path(tmp), args.kitti_root)
    missing = sorted(set(args.only) - set(values))
    if missing:
        print(f"record_pinned: not recorded (no KITTI sample at {args.kitti_root}): {', '.join(missing)}",
              file=sys.stderr)
    pinned.update(values)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_text(args.out, to_json(pinned))
    print(f"record_pinned: wrote {', '.join(sorted(values))} to {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
