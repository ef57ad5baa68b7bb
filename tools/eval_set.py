#!/usr/bin/env python3
"""The measurement set behind docs/FUSED_ODOMETRY.md's tables, in one command (~2-3 min once the
frames are rendered; the first run renders them, ~10 min): a change to the engine or a candidate
learned file is judged on all of it, not on the one set it was made for.

  the KITTI 06 sample       bevo convert (once) + bevo run + bevo evaluate: per frame, yaw, drift
  real-IMU clips            tools/eval_real_imu.py: 59 clips of 16 s and 94 of 5 s, each a cold
                            start, on a plane and over the roads' crests and sags; the 16 s with traffic
  synthetic presets         tools/eval_real_imu.py --presets all --acceptance, on a plane and over hills

  .venv/bin/python tools/eval_set.py                          # the engine and params/learned_default.yaml
  .venv/bin/python tools/eval_set.py --learned my_learned.yaml  # a candidate learned file (fused mode)

Needs ../shared/data/kitti for the sample and the real-IMU clips (skipped with a note without it).
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
KITTI = REPO.parent / "shared" / "data" / "kitti"
EVAL = [str(REPO / "tools" / "eval_real_imu.py"), "--modes", "fused"]
CLIPS = [  # (label, extra arguments, needs the shared drives)
    ("16 s clips, plane", [], True),
    ("16 s clips, crests and sags", ["--vertical-curves"], True),
    ("5 s clips, plane", ["--length", "51", "--step", "51"], True),
    ("5 s clips, crests and sags", ["--length", "51", "--step", "51", "--vertical-curves"], True),
    ("16 s clips, traffic", ["--traffic"], True),
    ("presets, plane", ["--presets", "all", "--acceptance"], False),
    ("presets, hills", ["--presets", "all", "--acceptance", "--vertical-curves"], False),
]


def bevo(command: str, *args: str) -> None:
    """One ``bevo`` command in a child process (its output kept unless it fails)."""
    done = subprocess.run([sys.executable, "-m", "bevo_ros.cli", command, *args], cwd=REPO, capture_output=True,
                          text=True)
    if done.returncode != 0:
        raise RuntimeError(f"bevo {command} failed ({done.returncode}):\n{done.stderr[-2000:]}")


def kitti_sample(out: Path, learned: Path | None) -> str:
    bag = out / "kitti06_bag"
    if not (bag / "metadata.yaml").exists():
        bevo("convert", "--odometry", str(KITTI / "odometry"), "--sequence", "06", "-o", str(bag))
    run, ev = out / "run_kitti06", out / "eval_kitti06"
    bevo("run", str(bag), "--out", str(run), "-q", *(["--learned", str(learned)] if learned else []))
    bevo("evaluate", "--gt", str(run / "gt_kitti.txt"), "--est", str(run / "trajectory_kitti.txt"), "--out", str(ev))
    m = json.loads((ev / "metrics.json").read_text())
    return (f"{m['rpe_trans_rmse'] * 100:.2f} cm, {m['rpe_yaw_rmse']:.4f} deg per frame, drift "
            f"{m['drift_percent']:.2f} %")


def clips(extra: list[str], learned: Path | None) -> str:
    done = subprocess.run([sys.executable, *EVAL, *extra, *(["--learned", str(learned)] if learned else [])],
                          cwd=REPO, capture_output=True, text=True)
    lines = done.stdout.splitlines()
    if done.returncode != 0 or not lines:
        raise RuntimeError(f"eval_real_imu {' '.join(extra)} failed ({done.returncode}):\n{done.stderr[-2000:]}")
    # "fused: the published gravity attitude ... pitch / roll RMS[, mean of the drives] P / R deg"
    gravity = next(line for line in lines if line.startswith("fused: the published gravity attitude"))
    pitch, roll = gravity.split(" deg")[0].split()[-3::2]
    if "--acceptance" in extra:  # "mean of 9  fused  pitch / roll  per frame  yaw  drift  scale"
        row = next(line for line in lines if line.startswith("mean of")).split()
        return (f"road pitch / roll {row[4]} / {row[6]} deg, per frame {row[7]} %, yaw {row[8]} deg, "
                f"drift {row[9]} %; gravity pitch / roll {pitch} / {roll} deg")
    row = next(line for line in lines if line.startswith("fused ("))
    head, _, rest = row.partition("): ")
    return f"{head.removeprefix('fused (')}: {rest}; gravity pitch / roll {pitch} / {roll} deg"


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--learned", type=Path, help="fused mode's learned-parameters YAML (default: the engine's)")
    p.add_argument("--out", type=Path, default=REPO / "out" / "eval_set", help="work folder (the KITTI bag, runs)")
    args = p.parse_args(argv)
    learned = args.learned.resolve() if args.learned else None
    args.out.mkdir(parents=True, exist_ok=True)
    shared = (KITTI / "odometry" / "sequences" / "06").is_dir()
    t0 = time.perf_counter()
    print(f"learned: {learned or 'params/learned_default.yaml'}")
    print(f"  {'KITTI 06 sample':32s} " + (kitti_sample(args.out, learned) if shared else
                                           f"skipped: no KITTI sample at {KITTI}"), flush=True)
    for label, extra, needs_shared in CLIPS:
        said = clips(extra, learned) if shared or not needs_shared else f"skipped: no shared drives at {KITTI}"
        print(f"  {label:32s} {said}", flush=True)
    print(f"({time.perf_counter() - t0:.0f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
