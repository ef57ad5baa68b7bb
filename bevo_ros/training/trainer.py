"""End-to-end training of the DUKF's O and Q (paper Sec. 2.4), and the sequence passes the
training and ablation (bevo train, bevo ablation) share.

What is learned: the DUKF's four log-variances (``log_process_var`` = O per axis, a density in
rad^2/s multiplied by each IMU dt; ``log_measurement_var`` = Q per axis, rad^2), with Adam,
supervised only by the frame-rate ground-truth poses through BEV projection and phase correlation:
the loss is the KL divergence between the correlation distributions and Gaussian-blurred one-hot
targets at the ground-truth rotation and shift (:func:`bevo_ros.core.loss.registration_kl_loss`).

Things worth knowing (each measured, see ``bevo train --help`` and the tests):

* **Loss temperature.** The phase correlation turns correlations into distributions with a
  softmax temperature (``DpcConfig.*_temperature``). At the engine's 0.02 the distributions are
  so sharp that the KL loss *rewards* a wrong attitude: a blurred BEV gives a flat, low-loss
  distribution while a sharp one a pixel off is penalised heavily (on a synthetic bumpy drive the
  ground-truth attitude scored the *worst* loss of all variants). The temperature changes only
  the distributions, never the point estimates (argmax + local peak fit), so training uses its
  own, calibrated temperature (``LOSS_TEMPERATURE`` = 0.2: on synthetic drives and on the KITTI
  sample the loss then ranks attitudes as their pose errors do; 0.05 and below do not) and the
  learned O/Q act on the engine unchanged.
* **Identifiability.** Multiplying O, Q (and the initial covariance, which is Q) by the same
  factor leaves the filtered mean unchanged, so the odometry loss only sees the ratio O/Q per
  axis; the common scale stays where initialisation put it.
* **Failed registrations.** A BEV with no valid pixel (the attitude tilts the camera off the
  ground, e.g. raw accelerometer angles on a bumpy drive) cannot be registered: those pairs get
  zero motion and the loss of a uniform (know-nothing) distribution, and are counted.
* **Memory/time.** The DUKF runs once per step over the recording's IMU from its start (the
  filter needs its history); BEV + DPC run in windows of ``window`` frames whose gradients are
  accumulated into the attitude and then pushed through the DUKF once, so the gradient is exact
  and memory is bounded by the window.
"""
from __future__ import annotations

import dataclasses
import json
import math
import sys
import time
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from types import SimpleNamespace
from typing import Any, Callable

import numpy as np
import torch

from bevo_ros.config import BevoConfig, _flatten, bev_spec, read_yaml
from bevo_ros.io.learned_params import LearnedParams, provenance, save_learned_params
from bevo_ros.io.files import atomic_write_text
from bevo_ros.core.device import resolve_device
from bevo_ros.core.dukf import DUKF
from bevo_ros.core.geometry import BevSpec, wrap_angle
from bevo_ros.core.loss import registration_kl_loss
from bevo_ros.core.phase_correlation import DpcConfig, angle_bins, shift_bins
from bevo_ros.core.sequence import registration_targets, run_sequence
from bevo_ros.datasets.rosbag import Recording, split_frames

Tensor = torch.Tensor

LOSS_TEMPERATURE = 0.2
SIGMA_ANGLE = math.radians(1.0)  # target blur, rad
SIGMA_SHIFT = 1.0  # target blur, BEV pixels
CHECKPOINT_FORMAT = "bevo_training_checkpoint/1"
LOG_VAR_LIMIT = 60.0  # |log variance| beyond this (var < 1e-26 or > 1e26) counts as divergence


class TrainingDiverged(RuntimeError):
    """NaN/inf loss or gradient, or variances driven out of any sane range."""


# --------------------------------------------------------------------------- engine pieces
def loss_dpc(temperature: float = LOSS_TEMPERATURE, base: DpcConfig | None = None) -> DpcConfig:
    """The engine's phase-correlation settings with the loss temperature (point estimates unchanged)."""
    base = base or DpcConfig()
    return dataclasses.replace(base, rotation_temperature=float(temperature),
                               translation_temperature=float(temperature))


def make_dukf(process_var, measurement_var, motion_model: str = "euler", device: str | torch.device = "cpu") -> DUKF:
    """A float64 DUKF (as the engine runs it) on ``device``, its log-variances exact in float64."""
    o = tuple(float(v) for v in process_var)
    q = tuple(float(v) for v in measurement_var)
    dukf = DUKF(process_var=o, measurement_var=q, motion_model=motion_model).double().to(device)
    with torch.no_grad():  # DUKF creates its parameters in float32: restore full precision
        dukf.log_process_var.copy_(torch.tensor(o, dtype=torch.float64).log())
        dukf.log_measurement_var.copy_(torch.tensor(q, dtype=torch.float64).log())
    return dukf


def variances(dukf: DUKF) -> tuple[tuple[float, float], tuple[float, float]]:
    """``(O, Q)`` as plain floats."""
    o = dukf.process_var.detach().cpu().tolist()
    q = dukf.measurement_var.detach().cpu().tolist()
    return (o[0], o[1]), (q[0], q[1])


# --------------------------------------------------------------------------- one pass over a recording
@dataclass
class PassResult:
    """BEVO over a recording (or a part of one), with the loss and per-frame errors vs. ground truth.

    ``loss`` is the mean KL per frame pair (failed pairs at the uniform distribution's KL); NaN
    without ground truth. Errors are per pair: translation (m) and |yaw| (rad).
    """

    loss: float
    motion: Tensor  # (P, 3) float64 cpu, zero where failed
    failed: Tensor  # (P,) bool
    pitch_roll_gravity: Tensor  # (F, 2)
    pitch_roll_road: Tensor  # (F, 2)
    gt_motion: Tensor | None = None  # (P, 3)
    trans_err: Tensor | None = None  # (P,) m
    yaw_err: Tensor | None = None  # (P,) rad

    @property
    def pairs(self) -> int:
        return int(self.motion.shape[0])

    @property
    def n_failed(self) -> int:
        return int(self.failed.sum())

    @property
    def mean_trans_err(self) -> float:
        return float(self.trans_err.mean()) if self.trans_err is not None and self.pairs else float("nan")

    @property
    def mean_yaw_err_deg(self) -> float:
        return math.degrees(float(self.yaw_err.mean())) if self.yaw_err is not None and self.pairs else float("nan")


def _uniform_kl(target_angle: Tensor, target_shift: Tensor, dpc: DpcConfig, size: int,
                sigma_angle: float, sigma_shift: float) -> Tensor:
    """Summed KL of the targets against uniform distributions: the loss of a failed pair."""
    n = target_angle.shape[0]
    a_bins = angle_bins(dpc, torch.float64, target_angle.device)
    s_bins = shift_bins(size, torch.float64, target_angle.device)
    fake = SimpleNamespace(
        rotation_log_prob=torch.full((n, a_bins.shape[0]), -math.log(a_bins.shape[0]), dtype=torch.float64,
                                     device=target_angle.device),
        rotation_bins=a_bins,
        translation_log_prob=torch.full((n, size, size), -2.0 * math.log(size), dtype=torch.float64,
                                        device=target_angle.device),
        translation_bins=s_bins,
    )
    return registration_kl_loss(fake, target_angle.double(), target_shift.double(), sigma_angle, sigma_shift) * n


def sequence_pass(
    dukf: DUKF | None,
    seq: Recording,
    config: BevoConfig,
    *,
    source: str = "dukf",
    given_pitch_roll_road: Tensor | None = None,
    backward: bool = False,
    window: int = 32,
    temperature: float = LOSS_TEMPERATURE,
    sigma_angle: float = SIGMA_ANGLE,
    sigma_shift: float = SIGMA_SHIFT,
    device: str | torch.device = "cpu",
    dpc: DpcConfig | None = None,
    turn_compensation: bool | None = None,
) -> PassResult:
    """BEVO over ``seq`` (its frames; its IMU from the recording start), windowed: the loss on
    :func:`~bevo_ros.core.sequence.run_sequence` (the engine's point estimates, with the static
    mounting attitude and the turn compensation of ``config.filter``; ``turn_compensation``
    overrides the latter). Only the distributions the loss reads use ``temperature``.

    With ``backward=True`` the gradient of ``loss`` (mean over pairs) w.r.t. the DUKF's parameters
    is accumulated into their ``.grad`` (call ``zero_grad`` first).
    """
    if len(seq) < 2:
        raise ValueError(f"{seq.name or 'sequence'}: needs at least 2 frames, got {len(seq)}")
    if window < 1:
        raise ValueError(f"window must be >= 1 frame pair, got {window}")
    dev = torch.device(device)
    spec = bev_spec(config)
    dpc = dpc if dpc is not None else loss_dpc(temperature, getattr(config, "dpc", None))
    n_pairs = len(seq) - 1
    need_grad = backward and source == "dukf" and dukf is not None
    if turn_compensation is None:
        turn_compensation = bool(getattr(config.filter, "turn_compensation", False))
    # the engine's mounting for this recording's camera (re-derived for other extrinsics, e.g. the bag's /tf_static),
    # or the one it measured at the recording's start (filter.tilt_from_images: with_start_tilt)
    mounting = seq.mounting_in_use(config)
    gt = seq.gt_motion() if seq.gt_poses is not None else None
    targets = registration_targets(gt.to(dev), spec) if gt is not None else None

    def pair_loss(reg, pairs: Tensor) -> Tensor:
        idx = pairs.to(dev)
        return registration_kl_loss(reg, targets[0][idx], targets[1][idx], sigma_angle, sigma_shift) * len(pairs)

    with torch.set_grad_enabled(need_grad):
        res = run_sequence(
            dukf, seq.camera, spec, dpc, seq.imu_stamps.to(dev), seq.gyro.to(dev), seq.accel.to(dev),
            seq.frame_stamps.to(dev), seq.images, config.filter.road_tilt_time_constant, source,
            None if given_pitch_roll_road is None else given_pitch_roll_road.to(dev), mounting, turn_compensation,
            config.filter.max_imu_gap, window=window, pair_loss=None if targets is None else pair_loss)
    loss_sum = res.loss
    if targets is not None and bool(res.failed.any()):
        bad = res.failed.to(dev)
        loss_sum += float(_uniform_kl(targets[0][bad], targets[1][bad], dpc, spec.size, sigma_angle, sigma_shift))

    motion = res.motion
    result = PassResult(
        loss=loss_sum / n_pairs if targets is not None else float("nan"),
        motion=motion, failed=res.failed,
        pitch_roll_gravity=res.pitch_roll_gravity.detach().double().cpu(),
        pitch_roll_road=res.pitch_roll_road.detach().double().cpu(),
    )
    if gt is not None:
        gt = gt.double().cpu()
        result.gt_motion = gt
        result.trans_err = torch.linalg.norm(motion[:, :2] - gt[:, :2], dim=-1)
        result.yaw_err = wrap_angle(motion[:, 2] - gt[:, 2]).abs()
    return result


# --------------------------------------------------------------------------- initialisation
def median_imu_dt(seqs: list[Recording]) -> float:
    dts = torch.cat([torch.diff(s.imu_stamps.double()) for s in seqs if s.imu_stamps.numel() > 1])
    if dts.numel() == 0:
        raise ValueError("no IMU samples to infer the IMU rate from")
    return float(dts.median())


def random_init(seed: int | None, imu_dt: float) -> tuple[tuple[float, float], tuple[float, float], list[float]]:
    """The paper's initialisation: O and Q uniform in [0, 1].

    The paper's O is a variance *per IMU step* (rad^2); ours is a density (rad^2/s) times each dt,
    so a per-step draw ``u`` maps to ``O = u / imu_dt`` at the recording's median IMU period. Q is
    per measurement in both (rad^2). Draws are floored at 1e-6 (log-parameters).

    Returns:
        ``(O, Q, [u_O_pitch, u_O_roll, u_Q_pitch, u_Q_roll])``.
    """
    u = np.maximum(np.random.default_rng(seed).uniform(0.0, 1.0, 4), 1e-6)
    return (u[0] / imu_dt, u[1] / imu_dt), (u[2], u[3]), [float(v) for v in u]


# --------------------------------------------------------------------------- training
@dataclass
class TrainOptions:
    epochs: int = 20
    lr: float = 0.3
    # resuming: continue with the checkpoint's learning rate (its decays included) instead of ``lr``
    resume_lr: bool = True
    patience: int = 5  # epochs without a better validation loss before stopping (0 = never)
    lr_decay: float = 0.5  # the learning rate is multiplied by this after an epoch without improvement
    split: str = "3/4"
    steps_per_bag: int = 8  # Adam steps per bag per epoch: its training part is cut into this many chunks
    window: int = 32  # frame pairs per BEV/DPC chunk (memory bound)
    temperature: float = LOSS_TEMPERATURE
    sigma_angle: float = SIGMA_ANGLE
    sigma_shift: float = SIGMA_SHIFT
    seed: int | None = 0
    init: tuple[float, float, float, float] | None = None  # O_pitch O_roll (rad^2/s) Q_pitch Q_roll (rad^2)
    # Coarse search before Adam: O scaled by 10^0, 10^-1, ... (this many decades) at fixed Q, the
    # lowest training loss wins. None = on (9) for the random init, off for a given --init.
    init_search: int | None = None
    device: str = "cpu"

    def check(self) -> None:
        if self.epochs < 0:
            raise ValueError(f"epochs must be >= 0, got {self.epochs}")
        if not (math.isfinite(self.lr) and self.lr > 0):
            raise ValueError(f"lr must be > 0, got {self.lr}")
        if not 0 < self.lr_decay <= 1:
            raise ValueError(f"lr_decay must be in (0, 1], got {self.lr_decay}")
        if self.patience < 0 or self.window < 1 or self.steps_per_bag < 1:
            raise ValueError("need patience >= 0, window >= 1 and steps_per_bag >= 1")
        if not (self.temperature > 0 and self.sigma_angle > 0 and self.sigma_shift > 0):
            raise ValueError("temperature and target blurs must be > 0")
        if self.init is not None:
            if len(self.init) != 4 or not all(math.isfinite(v) and v > 0 for v in self.init):
                raise ValueError(f"init needs 4 finite values > 0 (O1 O2 Q1 Q2), got {self.init}")
        if self.init_search is not None and self.init_search < 0:
            raise ValueError(f"init_search must be >= 0, got {self.init_search}")
        split_frames(10, self.split)  # validates the name

    def search_decades(self) -> int:
        if self.init_search is not None:
            return self.init_search
        return 0 if self.init is not None else 9


@dataclass
class Evaluation:
    loss: float
    trans_m: float
    yaw_deg: float
    pairs: int
    failed: int

    def as_dict(self) -> dict[str, Any]:
        return {"loss": _f(self.loss), "rpe_trans_m": _f(self.trans_m), "rpe_yaw_deg": _f(self.yaw_deg),
                "pairs": self.pairs, "failed_pairs": self.failed}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> "Evaluation":
        nan = float("nan")
        return cls(d.get("loss") if d.get("loss") is not None else nan,
                   d.get("rpe_trans_m") if d.get("rpe_trans_m") is not None else nan,
                   d.get("rpe_yaw_deg") if d.get("rpe_yaw_deg") is not None else nan,
                   int(d.get("pairs", 0)), int(d.get("failed_pairs", 0)))


@dataclass
class TrainResult:
    status: str  # "completed", "early-stopped" or "diverged"
    message: str
    learned: LearnedParams  # the best validated O/Q with provenance
    last_good: tuple[tuple[float, float], tuple[float, float]]
    best_epoch: int
    epochs_run: int
    before: Evaluation
    after: Evaluation
    history: list[dict[str, Any]] = field(default_factory=list)
    seconds_per_epoch: float = float("nan")


def _f(v: float) -> float | None:
    return None if v is None or not math.isfinite(v) else float(v)


def _split_parts(seqs: list[Recording], split: str, steps_per_bag: int):
    """Per bag: the training steps' frame ranges (consecutive chunks sharing their boundary frame,
    so every training pair is used once) and the validation part."""
    steps, vals = [], []
    for s in seqs:
        (a, b), (c, d) = split_frames(len(s), split)
        n_pairs = b - a - 1
        k = max(1, min(steps_per_bag, n_pairs))
        edges = [a + round(i * n_pairs / k) for i in range(k + 1)]
        steps += [(s, lo, hi + 1) for lo, hi in zip(edges[:-1], edges[1:]) if hi > lo]
        vals.append((s, c, d))
    return steps, vals


def training_loss(dukf: DUKF, steps, config: BevoConfig, options: TrainOptions, device) -> float:
    """Mean KL per pair over the training parts (no gradient)."""
    total, pairs = 0.0, 0
    for s, a, b in steps:
        r = sequence_pass(dukf, s.frames(a, b), config, window=options.window, temperature=options.temperature,
                          sigma_angle=options.sigma_angle, sigma_shift=options.sigma_shift, device=device)
        total += r.loss * r.pairs
        pairs += r.pairs
    return total / pairs


def evaluate_parts(dukf: DUKF, parts, config: BevoConfig, options: TrainOptions, device) -> Evaluation:
    losses, trans, yaw, failed = [], [], [], 0
    for s, c, d in parts:
        r = sequence_pass(dukf, s.frames(c, d), config, window=options.window, temperature=options.temperature,
                          sigma_angle=options.sigma_angle, sigma_shift=options.sigma_shift, device=device)
        losses.append(r.loss * r.pairs)
        trans.append(r.trans_err)
        yaw.append(r.yaw_err)
        failed += r.n_failed
    pairs = sum(int(t.numel()) for t in trans)
    return Evaluation(sum(losses) / pairs, float(torch.cat(trans).mean()),
                      math.degrees(float(torch.cat(yaw).mean())), pairs, failed)


def _finite_params(dukf: DUKF) -> str | None:
    for name, p in (("O", dukf.log_process_var), ("Q", dukf.log_measurement_var)):
        v = p.detach()
        if not bool(torch.isfinite(v).all()):
            return f"log {name} became non-finite ({v.tolist()})"
        if bool((v.abs() > LOG_VAR_LIMIT).any()):
            return f"{name} left the sane range (variances {v.exp().tolist()})"
    return None


def _adam_state_to_plain(opt: torch.optim.Adam, params: list[Tensor]) -> dict[str, Any]:
    out = {}
    for name, p in zip(("log_process_var", "log_measurement_var"), params):
        st = opt.state.get(p)
        if st:
            out[name] = {"step": float(st["step"]), "exp_avg": [float(v) for v in st["exp_avg"].tolist()],
                         "exp_avg_sq": [float(v) for v in st["exp_avg_sq"].tolist()]}
    return out


def _adam_state_from_plain(opt: torch.optim.Adam, params: list[Tensor], plain: dict[str, Any]) -> None:
    for name, p in zip(("log_process_var", "log_measurement_var"), params):
        st = plain.get(name)
        if st:
            opt.state[p] = {"step": torch.tensor(float(st["step"]), dtype=torch.float32),
                            "exp_avg": torch.tensor(st["exp_avg"], dtype=p.dtype, device=p.device),
                            "exp_avg_sq": torch.tensor(st["exp_avg_sq"], dtype=p.dtype, device=p.device)}


def _pair(v) -> list[float]:
    return [float(v[0]), float(v[1])]


def _plain(obj: Any) -> Any:
    """Plain JSON-like copy (no shared references, tuples as lists): YAML without anchors."""
    return json.loads(json.dumps(obj))


def save_checkpoint(path: str | Path, state: dict[str, Any]) -> None:
    """Human-readable YAML checkpoint, written atomically (no pickle)."""
    import yaml

    state = _plain(state)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    header = ("# BEVO training checkpoint (bevo train --resume THIS). Plain numbers only.\n"
              "# O = process noise density (rad^2/s), Q = measurement noise variance (rad^2), [pitch, roll].\n")
    atomic_write_text(path, header + yaml.safe_dump(state, sort_keys=False, default_flow_style=None))


def _number_problem(value: Any, integer: bool = False, minimum: float | None = None,
                    positive: bool = False) -> str | None:
    """Why ``value`` is not a plain finite number (an int with ``integer``) >= ``minimum`` (> 0 with
    ``positive``), or None. A bool is no number here (YAML's ``yes`` would count as 1)."""
    kinds = (int,) if integer else (int, float)
    if isinstance(value, bool) or not isinstance(value, kinds):
        return f"must be {'an integer' if integer else 'a number'}, got {value!r}"
    if not math.isfinite(value):
        return f"must be finite, got {value}"
    if positive and value <= 0:
        return f"must be > 0, got {value}"
    if minimum is not None and value < minimum:
        return f"must be >= {minimum:g}, got {value}"
    return None


def load_checkpoint(path: str | Path) -> dict[str, Any]:
    """A checkpoint of :func:`save_checkpoint`, every number training reads from it checked (a
    hand-edited ``lr: .nan`` or ``-0.1`` would train NaNs or climb the loss): a bad one is a
    ValueError naming the file and the field."""
    path = Path(path)
    doc = read_yaml(path, "checkpoint")  # ConfigError is a ValueError
    if not isinstance(doc, dict) or doc.get("format") != CHECKPOINT_FORMAT:
        raise ValueError(f"{path} is not a BEVO training checkpoint (format {CHECKPOINT_FORMAT!r})")
    for key in ("epoch", "current", "best"):
        if key not in doc:
            raise ValueError(f"checkpoint {path}: missing '{key}'")
    for key in ("current", "best"):
        for sub in ("process_noise_density", "measurement_noise_variance"):
            vals = doc[key].get(sub) if isinstance(doc[key], dict) else None
            if not (isinstance(vals, list) and len(vals) == 2 and all(
                    isinstance(v, (int, float)) and math.isfinite(v) and v > 0 for v in vals)):
                raise ValueError(f"checkpoint {path}: '{key}.{sub}' must be 2 finite numbers > 0")

    def check(name: str, value: Any, **rules: Any) -> None:
        if (problem := _number_problem(value, **rules)) is not None:
            raise ValueError(f"checkpoint {path}: '{name}' {problem}")

    def section(name: str) -> dict[str, Any]:
        value = doc.get(name)
        if value is None:
            return {}
        if not isinstance(value, dict):
            raise ValueError(f"checkpoint {path}: '{name}' must be a mapping, got {value!r}")
        return value

    check("epoch", doc["epoch"], integer=True, minimum=0)
    for name in ("lr", "bad_epochs"):  # optional: older checkpoints may lack them (options.lr, 0)
        if doc.get(name) is not None:
            check(name, doc[name], **({"positive": True} if name == "lr" else {"integer": True, "minimum": 0}))
    best = doc["best"]
    if best.get("val_loss") is not None:  # None: not validated yet (inf); NaN would never be beaten
        check("best.val_loss", best["val_loss"])
    if best.get("epoch") is not None:
        check("best.epoch", best["epoch"], integer=True, minimum=0)
        if best["epoch"] > doc["epoch"]:
            raise ValueError(f"checkpoint {path}: 'best.epoch' {best['epoch']} is after 'epoch' {doc['epoch']}")
    before = section("before")
    for name in ("loss", "rpe_trans_m", "rpe_yaw_deg"):
        if before.get(name) is not None:  # None: re-measured at the start
            check(f"before.{name}", before[name], minimum=0)
    for name in ("pairs", "failed_pairs"):
        if name in before:
            check(f"before.{name}", before[name], integer=True, minimum=0)
    for name, st in section("adam").items():  # Adam's moments go straight into the steps
        where = f"adam.{name}"
        if name not in ("log_process_var", "log_measurement_var") or not isinstance(st, dict):
            raise ValueError(f"checkpoint {path}: '{where}' is not Adam state of log_process_var or "
                             "log_measurement_var")
        check(f"{where}.step", st.get("step"), minimum=0)
        for moment in ("exp_avg", "exp_avg_sq"):
            vals = st.get(moment)
            if not (isinstance(vals, list) and len(vals) == 2):
                raise ValueError(f"checkpoint {path}: '{where}.{moment}' must be 2 numbers, got {vals!r}")
            for v in vals:
                check(f"{where}.{moment}", v, minimum=0 if moment == "exp_avg_sq" else None)
    history = doc.get("history", [])
    if not isinstance(history, list) or not all(isinstance(h, dict) for h in history):
        raise ValueError(f"checkpoint {path}: 'history' must be a list of epoch records")
    for h in history:
        check("history[].epoch", h.get("epoch"), integer=True, minimum=0)
    section("setup")
    return doc


# What a checkpoint's validation losses depend on besides O/Q: the bags, their split, the loss's
# shape, and the settings sequence_pass runs with (the camera, BEV, phase correlation but its
# temperatures, which the loss sets, and the filter's parts the O/Q training uses). Resumed with
# another, the checkpoint's best loss is a number from elsewhere that the new bags may never beat:
# the output would silently keep its O/Q.
_LOSS_FILTER_SETTINGS = ("filter.motion_model", "filter.road_tilt_time_constant", "filter.max_imu_gap",
                         "filter.mounting_pitch", "filter.mounting_roll", "filter.mounting_reference",
                         "filter.turn_compensation")
_SETUP_NAMES = {"split": "--split", "loss.temperature": "--temperature", "loss.sigma_angle_deg": "--sigma-angle",
                "loss.sigma_shift_px": "--sigma-shift"}


def training_setup(bags: list[str], config: BevoConfig, options: TrainOptions,
                   rig: dict[str, Any] | None = None) -> dict[str, Any]:
    """The setup a checkpoint records and a resume must match (plain values): ``bags`` as given
    (``bevo train``: resolved paths), the split, the loss's temperature and blurs, and the settings
    the validation loss depends on (``rig``: the rig settings that choose the bags' camera, e.g.
    ``dataclasses.asdict(RigSettings)``)."""
    flat = config.to_flat()
    settings = {k: v for k, v in flat.items()
                if (k.split(".")[0] in ("camera", "bev", "dpc") and not k.endswith("_temperature"))
                or k in _LOSS_FILTER_SETTINGS}
    settings.update(rig or {})
    # the order differences are named in: the camera's intrinsics last (mostly fallbacks to CameraInfo)
    intrinsics = {f"camera.{k}" for k in ("fx", "fy", "cx", "cy", "width", "height_px")}
    settings = dict(sorted(settings.items(), key=lambda kv: (kv[0] in intrinsics, not kv[0].startswith("filter."))))
    return _plain({"bags": sorted(str(b) for b in bags), "split": options.split,
                   "loss": {"temperature": options.temperature, "sigma_angle_deg": math.degrees(options.sigma_angle),
                            "sigma_shift_px": options.sigma_shift},
                   "settings": settings})


def resume_differences(state: dict[str, Any], setup: dict[str, Any]) -> list[str]:
    """What differs between a checkpoint's setup and ``setup`` (:func:`training_setup`), one
    ``"NAME NEW (checkpoint: OLD)"`` each; a setting only one of them records is not compared (a
    checkpoint from before the setup was recorded: only its bags' names and split)."""
    old = state.get("setup")
    new = _plain(setup)
    if not old:
        old = {"bags": sorted(state.get("bags") or []), "split": state.get("split")}
        new = {"bags": sorted(Path(b).name for b in new["bags"]) if state.get("bags") else None,
               "split": new["split"] if state.get("split") else None}
    old, new = _flatten(old), _flatten(new)
    out = []
    for key in new:
        if key in old and old[key] != new[key] and new[key] is not None:
            name = _SETUP_NAMES.get(key, key.removeprefix("settings."))
            out.append(f"{name} {_short(new[key])} (checkpoint: {_short(old[key])})")
    return out


def _short(value: Any, limit: int = 160) -> str:
    text = repr(value)
    return text if len(text) <= limit else text[:limit - 3] + "..."


def check_resume(path: str | Path, setup: dict[str, Any], anyway: bool = False) -> tuple[dict[str, Any], list[str]]:
    """``(checkpoint, differences)``: the checkpoint at ``path`` (:func:`load_checkpoint`) and what
    differs from ``setup``; differences are a ValueError unless ``anyway`` (then the resumed run
    measures its best validation loss anew)."""
    state = load_checkpoint(path)
    differs = resume_differences(state, setup)
    if differs and not anyway:
        best = state["best"]
        loss = f"{best['val_loss']:.4f}" if best.get("val_loss") is not None else "none yet"
        shown = differs[:8] + ([f"and {len(differs) - 8} more"] if len(differs) > 8 else [])
        raise ValueError(f"--resume {path}: made with other bags or settings: {'; '.join(shown)}. Its best "
                         f"validation loss ({loss}, epoch {best.get('epoch', 0)}) was measured there: these bags "
                         "might never beat it and the output would keep its O/Q. Train without --resume, or "
                         "--resume-anyway to start from its O/Q with the best validation loss measured anew")
    return state, differs


def train(
    seqs: list[Recording],
    config: BevoConfig,
    options: TrainOptions,
    *,
    checkpoint: str | Path | None = None,
    resume: str | Path | None = None,
    progress: bool = True,
    log: Callable[[str], None] = print,
    extra_info: dict[str, Any] | None = None,
    setup: dict[str, Any] | None = None,
    resume_anyway: bool = False,
) -> TrainResult:
    """Train O and Q on the training parts of ``seqs``; validate each epoch on the held-out parts.

    Every step runs the DUKF (from the recording start), BEV and DPC over one of the
    ``steps_per_bag`` chunks of a bag's training part and takes one Adam step on the four
    log-variances. Returns the best validated parameters (``learned``), also when the run diverges
    (``status == "diverged"``).

    ``setup`` (:func:`training_setup`; default: the bags' names, ``config`` and ``options``) is
    recorded in the checkpoint; ``resume`` from a checkpoint of another setup is a ValueError
    naming the differences, unless ``resume_anyway``: then its O/Q, Adam state and learning rate
    are taken and the best validation loss measured anew on ``seqs``.
    """
    options.check()
    if not seqs:
        raise ValueError("no recordings to train on")
    for s in seqs:
        if s.gt_poses is None:
            raise ValueError(f"{s.name}: no ground truth; training needs /ground_truth/odometry")
        if len(s) < 4:
            raise ValueError(f"{s.name}: {len(s)} frames; need at least 4 to split train/validation")
    device = resolve_device(options.device, lambda m: log("warning: " + m), what="training")
    steps, vals = _split_parts(seqs, options.split, options.steps_per_bag)
    imu_dt = median_imu_dt(seqs)

    setup = setup if setup is not None else training_setup([s.name for s in seqs], config, options)
    state: dict[str, Any] | None = None
    differs: list[str] = []
    if resume:
        state, differs = check_resume(resume, setup, resume_anyway)
    init_info: dict[str, Any]
    if state is not None:
        o, q = state["current"]["process_noise_density"], state["current"]["measurement_noise_variance"]
        init_info = dict(state.get("init") or {})
        if differs:
            log(f"warning: resuming anyway from {resume} (epoch {state['epoch']}), made with other bags or settings: "
                + "; ".join(differs) + ". Its best validation loss is dropped: measured anew on these bags")
            init_info["resumed_anyway"] = {"checkpoint": str(resume), "epoch": int(state["epoch"]),
                                           "differences": differs}
    elif options.init is not None:
        o, q = options.init[:2], options.init[2:]
        init_info = {"mode": "given (--init)", "process_noise_density": _pair(o), "measurement_noise_variance": _pair(q)}
    else:
        o, q, u = random_init(options.seed, imu_dt)
        init_info = {"mode": "paper: uniform in [0, 1], O per IMU step (density = draw / IMU period), Q per sample",
                     "seed": options.seed, "imu_period_s": imu_dt, "draws_per_step": u,
                     "process_noise_density": _pair(o), "measurement_noise_variance": _pair(q)}
    decades = options.search_decades() if state is None else 0
    if decades:
        o, q = _init_search(o, q, decades, steps, config, options, device, log, init_info)
    dukf = make_dukf(o, q, config.filter.motion_model, device)
    params = [dukf.log_process_var, dukf.log_measurement_var]
    opt = torch.optim.Adam(params, lr=options.lr)

    if state is not None:
        _adam_state_from_plain(opt, params, state.get("adam") or {})
        for group in opt.param_groups:
            group["lr"] = float(state.get("lr", options.lr)) if options.resume_lr else options.lr
        start_epoch = int(state["epoch"]) + 1
        best = state["best"]
        best_loss = float(best["val_loss"]) if best.get("val_loss") is not None else math.inf
        best_params = (tuple(best["process_noise_density"]), tuple(best["measurement_noise_variance"]))
        best_epoch = int(best.get("epoch", 0))
        bad_epochs = int(state.get("bad_epochs", 0))
        history = list(state.get("history", []))
        before = Evaluation.from_dict(state["before"]) if state.get("before") else None
        if differs:  # its numbers are other bags' or settings': the start (its O/Q) is measured anew below
            before, bad_epochs = None, 0
            history = [{**h, "other_setup": True} for h in history]  # kept, but not these bags' losses
        else:
            log(f"resumed from {resume}: epoch {start_epoch - 1} done, best val loss {best_loss:.4f} at epoch "
                f"{best_epoch}")
    else:
        start_epoch, bad_epochs, history, before = 1, 0, [], None
    if before is None or not math.isfinite(before.loss):
        with torch.no_grad():
            before = evaluate_parts(dukf, vals, config, options, device)
        log(f"initial O {_fmt(variances(dukf)[0])} rad^2/s, Q {_fmt(variances(dukf)[1])} rad^2: "
            f"val loss {before.loss:.4f}, RPE {before.trans_m:.4f} m / {before.yaw_deg:.4f} deg"
            + (f", {before.failed} failed pairs" if before.failed else ""))
    if state is None or differs:  # the start is the best so far (epoch 0: "after" is then "before")
        best_loss, best_params, best_epoch = before.loss, variances(dukf), 0
        if not math.isfinite(best_loss):
            raise TrainingDiverged(f"the initial validation loss is {best_loss}; check the data and --init")
    after = before
    last_good = variances(dukf)
    status, message = "completed", ""
    epoch = start_epoch - 1
    epoch_times: list[float] = []

    def snapshot() -> dict[str, Any]:
        o_, q_ = last_good
        return {
            "format": CHECKPOINT_FORMAT, "epoch": epoch,
            "bags": [s.name for s in seqs], "split": options.split, "setup": setup,
            "options": {k: (list(v) if isinstance(v, tuple) else v) for k, v in dataclasses.asdict(options).items()},
            "init": init_info,
            "current": {"process_noise_density": _pair(o_), "measurement_noise_variance": _pair(q_)},
            "best": {"epoch": best_epoch, "val_loss": _f(best_loss), "process_noise_density": _pair(best_params[0]),
                     "measurement_noise_variance": _pair(best_params[1])},
            "bad_epochs": bad_epochs,
            "lr": opt.param_groups[0]["lr"],
            "before": before.as_dict(),
            "adam": _adam_state_to_plain(opt, params),
            "history": history,
        }

    try:
        from tqdm import tqdm
    except ImportError:  # pragma: no cover - tqdm is a dependency
        tqdm = None
    try:
        for epoch in range(start_epoch, options.epochs + 1):
            t0 = time.perf_counter()
            bar = tqdm(total=len(steps), desc=f"epoch {epoch}/{options.epochs}", unit="step", leave=False,
                       disable=not progress or tqdm is None, file=sys.stderr) if tqdm else None
            train_losses, train_pairs = [], 0
            for k, (s, a, b) in enumerate(steps):
                opt.zero_grad(set_to_none=True)
                try:
                    r = sequence_pass(dukf, s.frames(a, b), config, backward=True, window=options.window,
                                      temperature=options.temperature, sigma_angle=options.sigma_angle,
                                      sigma_shift=options.sigma_shift, device=device)
                except ValueError as exc:
                    if "non-finite" in str(exc) or "NaN" in str(exc):
                        raise TrainingDiverged(f"epoch {epoch} step {k + 1}: {exc}") from exc
                    raise
                where = f"epoch {epoch} step {k + 1} ({s.name} frames {a}..{b - 1})"
                if not math.isfinite(r.loss):
                    raise TrainingDiverged(f"{where}: loss is {r.loss}")
                grads = [p.grad for p in params]
                if r.n_failed == r.pairs:
                    log(f"{where}: every BEV pair failed (no valid pixels): no gradient, step skipped")
                    train_losses.append(r.loss * r.pairs)
                    train_pairs += r.pairs
                    if bar is not None:
                        bar.update(1)
                    continue
                if any(g is None for g in grads):
                    raise RuntimeError(f"{where}: the loss does not reach O and Q (no gradient)")
                if not all(bool(torch.isfinite(g).all()) for g in grads):
                    raise TrainingDiverged(f"{where}: gradient is not finite ({[g.tolist() for g in grads]})")
                last_good = variances(dukf)
                opt.step()
                bad = _finite_params(dukf)
                if bad:
                    raise TrainingDiverged(f"{where}: after the step {bad}")
                train_losses.append(r.loss * r.pairs)
                train_pairs += r.pairs
                if bar is not None:
                    bar.set_postfix(loss=f"{r.loss:.4f}")
                    bar.update(1)
            if bar is not None:
                bar.close()
            with torch.no_grad():
                val = evaluate_parts(dukf, vals, config, options, device)
            if not math.isfinite(val.loss):
                raise TrainingDiverged(f"epoch {epoch}: validation loss is {val.loss}")
            last_good = variances(dukf)
            after = val
            seconds = time.perf_counter() - t0
            epoch_times.append(seconds)
            improved = val.loss < best_loss - 1e-6
            if improved:
                best_loss, best_params, best_epoch, bad_epochs = val.loss, last_good, epoch, 0
            else:
                bad_epochs += 1
                for group in opt.param_groups:
                    group["lr"] *= options.lr_decay
            o_, q_ = last_good
            history.append({"epoch": epoch, "train_loss": _f(sum(train_losses) / max(train_pairs, 1)),
                            "val_loss": _f(val.loss), "val_rpe_trans_m": _f(val.trans_m),
                            "val_rpe_yaw_deg": _f(val.yaw_deg), "val_failed_pairs": val.failed,
                            "process_noise_density": _pair(o_), "measurement_noise_variance": _pair(q_),
                            "lr": opt.param_groups[0]["lr"], "seconds": round(seconds, 3)})
            log(f"epoch {epoch}/{options.epochs}: train loss {history[-1]['train_loss']:.4f}, val loss {val.loss:.4f}, "
                f"val RPE {val.trans_m:.4f} m / {val.yaw_deg:.4f} deg, O {_fmt(o_)}, Q {_fmt(q_)}, {seconds:.1f} s"
                + (" *best*" if improved else ""))
            if checkpoint:
                save_checkpoint(checkpoint, snapshot())
            if options.patience and bad_epochs >= options.patience:
                status = "early-stopped"
                message = f"no better validation loss for {bad_epochs} epochs: stopped after epoch {epoch}"
                log(message)
                break
    except TrainingDiverged as exc:
        status = "diverged"
        message = (f"training diverged: {exc}. Stopped; the last good parameters (O {_fmt(last_good[0])}, "
                   f"Q {_fmt(last_good[1])}) are kept and the best validated ones (epoch {best_epoch}) written")
        log(message)
        with torch.no_grad():
            dukf.log_process_var.copy_(torch.tensor(last_good[0], dtype=torch.float64).log())
            dukf.log_measurement_var.copy_(torch.tensor(last_good[1], dtype=torch.float64).log())
        epoch = max(epoch - 1, start_epoch - 1)  # the diverged epoch did not complete
        if checkpoint:
            save_checkpoint(checkpoint, snapshot() | {"diverged": str(exc)})

    # "after" = the written (best validated) parameters on the validation parts.
    if best_epoch == 0:
        after = before
    # (no epoch run in this call: a resume with none left, whose "after" was never measured here)
    elif not epoch_times or not history or best_epoch != history[-1]["epoch"] or status == "diverged":
        with torch.no_grad():
            probe = make_dukf(best_params[0], best_params[1], config.filter.motion_model, device)
            after = evaluate_parts(probe, vals, config, options, device)
    info = {
        "trainer": "bevo train (bevo_ros.training.trainer)",
        "training_bags": [s.name for s in seqs],
        "split": options.split,
        "status": status,
        "epochs_run": len(history),
        "best_epoch": best_epoch,
        "lr": options.lr,
        "lr_decay": options.lr_decay,
        "loss": {"kind": "KL(target || DPC distribution), rotation + translation", "temperature": options.temperature,
                 "sigma_angle_deg": math.degrees(options.sigma_angle), "sigma_shift_px": options.sigma_shift},
        "init": init_info,
        "validation_before": before.as_dict(),
        "validation_after": after.as_dict(),
        "seconds_per_epoch": _f(float(np.mean(epoch_times))) if epoch_times else None,
    }
    if message:
        info["message"] = message
    if extra_info:
        info.update(extra_info)
    learned = LearnedParams(tuple(best_params[0]), tuple(best_params[1]), _plain(provenance(info)))
    return TrainResult(status, message, learned, last_good, best_epoch, len(history), before, after, history,
                       float(np.mean(epoch_times)) if epoch_times else float("nan"))


def _init_search(o, q, decades, steps, config, options, device, log, init_info):
    """Coarse search over the O/Q ratio (the only thing the odometry loss sees): O times 10^-k,
    k = 0..decades-1, at fixed Q; the lowest training loss is where Adam starts."""
    tried = []
    for k in range(decades):
        ok = (o[0] * 10.0 ** -k, o[1] * 10.0 ** -k)
        with torch.no_grad():
            loss = training_loss(make_dukf(ok, q, config.filter.motion_model, device), steps, config, options, device)
        tried.append({"process_noise_density": _pair(ok), "train_loss": _f(loss)})
    finite = [t for t in tried if t["train_loss"] is not None]
    if not finite:
        raise TrainingDiverged("every initial O/Q of the coarse search gave a non-finite loss")
    best = min(finite, key=lambda t: t["train_loss"])
    log("init search (O x 10^-k at fixed Q): " + ", ".join(
        f"{t['process_noise_density'][0]:.3g}: {t['train_loss']:.4f}" if t["train_loss"] is not None else "nan"
        for t in tried) + f" -> start at O {_fmt(best['process_noise_density'])}")
    init_info["search"] = {"rule": "O x 10^-k, k = 0..%d, Q fixed; lowest training loss" % (decades - 1),
                           "tried": tried, "chosen": best["process_noise_density"]}
    return tuple(best["process_noise_density"]), q


def _fmt(pair) -> str:
    return "[" + ", ".join(f"{v:.3g}" for v in pair) + "]"


def write_learned(result: TrainResult, path: str | Path) -> Path:
    return save_learned_params(result.learned, path)


__all__ = [
    "LOSS_TEMPERATURE", "PassResult", "TrainOptions", "TrainResult", "TrainingDiverged", "Evaluation", "bev_spec",
    "check_resume", "load_checkpoint", "resume_differences", "training_setup", "loss_dpc", "make_dukf", "median_imu_dt", "random_init",
    "resolve_device", "save_checkpoint", "sequence_pass", "train", "variances", "write_learned",
]
