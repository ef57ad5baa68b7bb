"""``bevo train``: the DUKF's O and Q end to end through BEV + DPC from rosbag2 recordings (paper Sec. 2.4).

Supervision is only the frame-rate ground-truth poses in the bags (/ground_truth/odometry); the
loss is the KL divergence between the phase-correlation distributions and Gaussian-blurred
one-hot targets at the ground-truth rotation and shift. Adam on the four log-variances.

Each bag is split (--split 3/4: first three quarters train, last quarter validates; --split 20%:
train on the first 20 %, validate on the rest). Each epoch: --steps-per-bag Adam steps per bag
(the DUKF runs over the bag's IMU from its start every step: the filter needs its history), then
validation on the held-out frames (loss and per-frame relative pose error). The best validated
O/Q are written to --out as the learned-parameters YAML bevo_node loads; a YAML checkpoint
(current and best O/Q, Adam state, history: plain numbers) is written atomically every epoch.

Fused mode (odometry.mode: fused, the default) then fits what its engine adds, on the training
frames: the suspension gradients (--suspension-evals engine runs per axis), the vehicle motion
filter's noise (--vehicle-steps) and the pitch and roll gyro's bias prior, measured against the ground
truth's attitude (--no-gyro-bias to skip). Each of these, and the trained O/Q themselves, is kept only if the
fused engine reads the validation frames clearly better than with the configuration's learned file's
values (the squared translation errors of the validation frame pairs fall, over blocks of 10 pairs,
by more than chance would at 95 %, one-sided Student's t; at least 20 pairs); the file written says
which were kept (info).
"""
from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path


from bevo_ros.commands import (add_params_option, add_threads_option, bag_errors, guarded, new_parser, prog_name,
                               set_threads)
from bevo_ros.config import load_config

EPILOG = """\
initial values (paper: O and Q uniform in [0, 1]):
  The paper's O is a variance per IMU step (rad^2); ours is a density (rad^2/s) multiplied by
  each IMU dt. A draw u ~ U[0, 1] therefore becomes O = u / T_imu with T_imu the bags' median IMU
  period (e.g. O in [0, 100] rad^2/s at 100 Hz, [0, 10] at KITTI's 10 Hz OXTS); Q = u' rad^2 as
  in the paper. Such values trust the accelerometer almost completely; on a bumpy drive that
  breaks the registration so badly that the loss has no usable gradient there. So by default a
  coarse search first scales O by 10^0 .. 10^-8 at fixed Q (only the O/Q ratio matters to the
  odometry) and Adam starts from the lowest training loss (--init-search 0 disables it; the YAML's
  info.init records the draw and the search). --init O1 O2 Q1 Q2 (O in rad^2/s, Q in rad^2,
  [pitch, roll]) sets the start explicitly (no search unless --init-search N is given).

loss temperature:
  The DPC's softmax temperature shapes only the distributions the KL loss reads, never the point
  estimates. At the engine's 0.02 the KL loss prefers wrong attitudes (blurred BEVs give flat,
  cheap distributions); at --temperature 0.2 (default) it ranks attitudes as their pose errors do.

exit status: 0 done (completed or early-stopped), 3 diverged (NaN/inf loss or gradient, or
variances out of range: the output holds the best validated values, the checkpoint the last good
ones), 2 bad input, 130 interrupted (the checkpoint of the last finished epoch stays).

examples:
  bevo train seq06_bag --out params/learned.yaml
  bevo train synth_bag --params params/synthetic.yaml --out out/learned.yaml --epochs 10 --seed 3
  bevo train a_bag b_bag --out l.yaml --split 20% --init 1e-4 1e-4 1e-2 1e-2 --lr 0.2
  bevo train a_bag --out l.yaml --resume l.yaml.ckpt.yaml --epochs 30
  bevo train b_bag --out l2.yaml --resume l.yaml.ckpt.yaml --resume-anyway   # a_bag's O/Q as the start

resuming: the checkpoint records its setup (the bags' paths, --split, the loss options, the
parameters the loss depends on); --resume with another is refused, naming what differs: its best
validation loss was measured on those bags and might never be beaten on these, so the output would
silently keep its O/Q. --resume-anyway takes it as the start and measures the best anew.
"""


def build_parser() -> argparse.ArgumentParser:
    p = new_parser(__doc__, EPILOG)
    p.add_argument("bags", nargs="+", metavar="BAG", help="rosbag2 directories with /ground_truth/odometry")
    p.add_argument("--out", required=True, help="learned-parameters YAML to write (best validated O/Q)")
    add_params_option(p)
    p.add_argument("--split", default="3/4", choices=["3/4", "20%"], help="train/validation split per bag")
    p.add_argument("--epochs", type=int, default=20, help="epochs (total, also when resuming; default 20)")
    p.add_argument("--lr", type=float, default=None,
                   help="Adam learning rate on the log-variances (default 0.3; with --resume the checkpoint's, "
                        "its decays included, unless given)")
    p.add_argument("--patience", type=int, default=5, help="early stopping: epochs without a better validation "
                                                           "loss (default 5, 0 = never stop early)")
    p.add_argument("--steps-per-bag", type=int, default=8, help="Adam steps per bag per epoch (default 8)")
    p.add_argument("--seed", type=int, default=0, help="seed of the random initial O/Q (default 0)")
    p.add_argument("--init", type=float, nargs=4, metavar=("O1", "O2", "Q1", "Q2"),
                   help="initial O (rad^2/s) and Q (rad^2), [pitch, roll] each, instead of the random draw")
    p.add_argument("--init-search", type=int, default=None, metavar="N",
                   help="decades of O tried before Adam (default 9 for the random init, 0 with --init)")
    p.add_argument("--lr-decay", type=float, default=0.5,
                   help="learning rate factor after an epoch without improvement (default 0.5, 1 = constant)")
    p.add_argument("--temperature", type=float, default=None, help="DPC softmax temperature of the loss (default 0.2)")
    p.add_argument("--sigma-angle", type=float, default=1.0, help="rotation target blur, degrees (default 1)")
    p.add_argument("--sigma-shift", type=float, default=1.0, help="translation target blur, BEV pixels (default 1)")
    p.add_argument("--window", type=int, default=32, help="frame pairs per BEV/DPC chunk: bounds memory (default 32)")
    p.add_argument("--checkpoint", help="checkpoint YAML (default: OUT.ckpt.yaml)")
    p.add_argument("--resume", metavar="CHECKPOINT",
                   help="continue from a checkpoint (its O/Q, Adam state and learning rate; --epochs is the total); "
                        "one made with other bags, --split, loss options or parameters is refused, naming them")
    p.add_argument("--resume-anyway", action="store_true",
                   help="with --resume: take a checkpoint of other bags or parameters as the start (its O/Q, Adam "
                        "state, learning rate); its best validation loss is dropped and measured anew on these bags")
    p.add_argument("--device", default="cpu", help="cpu (default) or cuda (falls back to CPU with a warning)")
    add_threads_option(p, ": fastest for 100x100 BEVs")
    p.add_argument("--vehicle-steps", type=int, default=100,
                   help="fused mode: Adam steps fitting the vehicle motion filter's noise after O/Q (0 = keep it)")
    p.add_argument("--suspension-evals", type=int, default=8,
                   help="fused mode: engine runs per axis searching the suspension gradients after O/Q, scored by "
                        "the per-frame translation error (0 = keep the configuration's; default 8)")
    p.add_argument("--no-gyro-bias", action="store_true",
                   help="fused mode: do not measure the pitch and roll gyro's bias prior (filter.gyro_bias_std / "
                        "walk) against the ground truth; the learned file then keeps the configuration's")
    p.add_argument("--quiet", "-q", action="store_true", help="no progress bar")
    return p


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if 0 < args.suspension_evals < 3 or args.suspension_evals < 0:
        parser.error(f"--suspension-evals must be 0 or >= 3, got {args.suspension_evals}")
    if args.resume_anyway and not args.resume:
        parser.error("--resume-anyway applies to --resume CHECKPOINT only")
    from bevo_ros.training.trainer import TrainingDiverged

    set_threads(args.threads)
    # TrainingDiverged here: before any good parameters existed (e.g. the initial loss)
    return guarded("train_from_bag", lambda: _train(args), bag_errors(TrainingDiverged), codes={TrainingDiverged: 3},
                   interrupted=f"interrupted; the checkpoint {_checkpoint(args)} holds the last finished epoch")


def _checkpoint(args: argparse.Namespace) -> Path:
    out = Path(args.out)
    return Path(args.checkpoint) if args.checkpoint else out.with_name(out.name + ".ckpt.yaml")


def _keep_trained_oq_if_the_engine_agrees(learned, base, seqs, config, split: str, memo: dict | None = None) -> None:
    """Fused mode: O/Q are learned on the paper pipeline's loss (the batched KL path), which is not
    the fused engine. Keep them only if the engine reads the validation frames clearly better than with
    the configuration's learned file's O/Q (``engine_judgement``; trained on the 51-frame KITTI sample
    they read it worse: 4.2 -> 4.7 cm, 1.33 -> 1.46 %; on make demo's 30 s drive 3.6 -> 6.6 cm), else
    keep that file's, and say which."""
    from dataclasses import replace

    from bevo_ros.training.suspension import engine_judgement

    same = (tuple(learned.process_noise_density) == tuple(base.process_noise_density)
            and tuple(learned.measurement_noise_variance) == tuple(base.measurement_noise_variance))
    if same:
        return
    prior = replace(learned, process_noise_density=base.process_noise_density,
                    measurement_noise_variance=base.measurement_noise_variance)
    before, after, keep, why = engine_judgement(seqs, config, prior, learned, split, memo)
    print(f"O/Q in the fused engine: validation per-frame translation RMSE {before:.4f} m with the params' learned "
          f"file's, {after:.4f} m trained")
    if not keep:
        print(f"O/Q: the trained values are not clearly better in the fused engine ({why}); keeping the learned "
              f"file's (O = {list(base.process_noise_density)}, Q = {list(base.measurement_noise_variance)})")
        learned.process_noise_density = base.process_noise_density
        learned.measurement_noise_variance = base.measurement_noise_variance
        learned.info["oq_kept_from"] = {"reason": f"trained O/Q not clearly better in the fused engine: {why}",
                                        "validation_rmse": [before, after],
                                        # validation_after (the KL loss's) scored the trained O/Q, not these
                                        "validation_after_is": "the trained O/Q's, refused: not the file's"}
    else:
        learned.info["oq_engine_check"] = {"validation_rmse": [before, after]}


def _train(args: argparse.Namespace) -> int:
    import dataclasses

    from bevo_ros.datasets.rosbag import RigSettings, load_sequence, with_start_tilt
    from bevo_ros.io.learned_params import load_learned_params, save_learned_params
    from bevo_ros.training.trainer import LOSS_TEMPERATURE, TrainOptions, check_resume, train, training_setup
    from bevo_ros.training.gyro_bias import fit_gyro_bias_on_sequences
    from bevo_ros.training.suspension import fit_suspension_on_sequences
    from bevo_ros.training.vehicle import fit_vehicle_on_sequences

    out, checkpoint = Path(args.out), _checkpoint(args)
    for path, what in ((out, "--out"), (checkpoint, "the checkpoint")):  # before hours of training, not after
        if path.is_dir():
            raise ValueError(f"{what} {path} is a directory: give the learned-parameters YAML file to write")
    if checkpoint.resolve() == out.resolve():  # the learned file would overwrite the checkpoint at the end
        raise ValueError(f"--checkpoint {checkpoint} is --out itself: give the checkpoint another file")
    import torch

    try:  # a device torch cannot name failed only after the bags were read
        torch.device(args.device)
    except RuntimeError:
        raise ValueError(f"--device {args.device!r}: not a torch device (cpu, cuda, cuda:N)") from None
    if args.lr is not None and not (args.lr > 0 and math.isfinite(args.lr)):
        raise ValueError(f"--lr {args.lr}: must be > 0")
    options = TrainOptions(
        epochs=args.epochs, lr=0.3 if args.lr is None else args.lr, resume_lr=args.lr is None,
        patience=args.patience, lr_decay=args.lr_decay, split=args.split,
        steps_per_bag=args.steps_per_bag, window=args.window,
        temperature=LOSS_TEMPERATURE if args.temperature is None else args.temperature,
        sigma_angle=math.radians(args.sigma_angle), sigma_shift=args.sigma_shift, seed=args.seed,
        init=tuple(args.init) if args.init else None, init_search=args.init_search, device=args.device)
    options.check()
    config, flat = load_config(args.params)
    # What O/Q training does not learn comes from the configuration's learned file: the suspension
    # gradients and the vehicle noise as the starts of their own fits (else a trained file would
    # silently drop the suspension model the engine uses). Read before training, so a bad
    # path fails before the epochs, not after them.
    base = load_learned_params(config.learned_params_file)
    rig = RigSettings.from_params(flat, str(args.params))
    setup = training_setup([str(Path(b).resolve()) for b in args.bags], config, options, dataclasses.asdict(rig))
    if args.resume:  # a bad or mismatched checkpoint is refused before the bags are read, not after
        check_resume(args.resume, setup, args.resume_anyway)
    t0 = time.perf_counter()
    seqs = []
    for b in args.bags:
        s = load_sequence(b, config, rig=rig)
        seqs.append(s)
        print(f"{b}: {len(s)} frames, {s.imu_stamps.numel()} IMU samples "
              f"({s.imu_stamps.numel() / max(float(s.imu_stamps[-1] - s.imu_stamps[0]), 1e-9):.0f} Hz)")
    # the loss at the tilt the engine measures at each bag's start (filter.tilt_from_images), not the configured one
    with_start_tilt(seqs, config, base)
    lr_said = "the checkpoint's" if args.resume and args.lr is None else f"{options.lr:g}"
    print(f"loaded {len(seqs)} bag(s) in {time.perf_counter() - t0:.1f} s; split {args.split}, "
          f"{args.epochs} epochs, lr {lr_said}, checkpoint {checkpoint}")
    result = train(seqs, config, options, checkpoint=checkpoint, resume=args.resume, progress=not args.quiet,
                   extra_info={"training_bag_paths": [str(Path(b).resolve()) for b in args.bags],
                               "params_file": str(Path(args.params).resolve())},
                   setup=setup, resume_anyway=args.resume_anyway)
    result.learned.suspension_gradients = base.suspension_gradients
    result.learned.vehicle = dict(base.vehicle)
    result.learned.gyro_bias = base.gyro_bias
    memo: dict = {}  # the engine's validation errors per learned parameters: the judgements share runs
    if config.odometry.mode == "fused":
        _keep_trained_oq_if_the_engine_agrees(result.learned, base, seqs, config, args.split, memo)
    fits = config.odometry.mode == "fused" and (args.suspension_evals > 0 or args.vehicle_steps > 0
                                                or not args.no_gyro_bias)
    if fits:  # the trained O/Q first (the base's other numbers): a Ctrl-C in the fits below keeps them
        save_learned_params(result.learned, out)
        print(f"wrote {out} (O/Q; the suspension, vehicle-filter and gyro-bias fits follow)")
    if config.odometry.mode == "fused" and args.suspension_evals > 0:
        fit_suspension_on_sequences(result.learned, seqs, config, args.split, args.suspension_evals, memo)
    if config.odometry.mode == "fused" and args.vehicle_steps > 0:
        fit_vehicle_on_sequences(result.learned, seqs, config, args.split, args.vehicle_steps, memo)
    if config.odometry.mode == "fused" and not args.no_gyro_bias:
        fit_gyro_bias_on_sequences(result.learned, seqs, config, args.split, memo)
    save_learned_params(result.learned, out)
    o, q = result.learned.process_noise_density, result.learned.measurement_noise_variance
    b, a = result.before, result.after
    print(f"validation before: loss {b.loss:.4f}, RPE {b.trans_m:.4f} m / {b.yaw_deg:.4f} deg per frame"
          + (f" ({b.failed} failed pairs)" if b.failed else ""))
    refused = "oq_kept_from" in result.learned.info  # the fused engine kept the learned file's O/Q
    print(f"validation after:  loss {a.loss:.4f}, RPE {a.trans_m:.4f} m / {a.yaw_deg:.4f} deg per frame"
          + (f" ({a.failed} failed pairs)" if a.failed else "") + f" (best epoch {result.best_epoch})"
          + ("; those are the trained O/Q's, refused: the file holds the learned file's" if refused else ""))
    spe = result.seconds_per_epoch  # NaN when no epoch ran
    per_epoch = f", {spe:.1f} s/epoch" if math.isfinite(spe) else ""
    print(f"final variances: O = [{o[0]:.4g}, {o[1]:.4g}] rad^2/s, Q = [{q[0]:.4g}, {q[1]:.4g}] rad^2 "
          f"(pitch, roll); {result.epochs_run} epoch(s){per_epoch}")
    print(f"wrote {out}" + (f" and {checkpoint}" if checkpoint.is_file() else ""))
    if result.status == "diverged":
        print(f"{prog_name('train_from_bag')}: {result.message}", file=sys.stderr)
        return 3
    return 0
