"""A whole recording through BEVO at once: batched, differentiable, for training and ablations.

It runs the very functions :class:`~bevo_ros.core.odometry.BevoOdometry` runs per message (the
DUKF over every IMU sample, the road-tilt low-pass, the BEV projection, the phase correlation),
with the same rule for which IMU sample a frame sees: the last one with ``stamp <= frame stamp``.
So a model trained here behaves the same online.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import torch

from .bev import project_to_bev
from .dukf import DUKF, accel_to_pitch_roll, remove_turn_acceleration
from .geometry import BevSpec, CameraModel
from .motion import registration_from_vehicle_motion, vehicle_motion_from_registration
from .phase_correlation import DpcConfig, Registration, prepare, register_prepared, soft_weight
from .road_tilt import is_enabled, road_relative_attitude

Tensor = torch.Tensor

ATTITUDE_SOURCES = ("dukf", "accel", "given")
MIN_BEV_WEIGHT = 1e-6  # the engine's own test (phase_correlation.prepare) for "no valid pixel"


def frame_imu_indices(imu_stamps: Tensor, frame_stamps: Tensor) -> Tensor:
    """Index of the last IMU sample with ``stamp <= frame stamp``; -1 if none. ``(N,), (F,) -> (F,)``."""
    return torch.searchsorted(imu_stamps.contiguous(), frame_stamps.contiguous(), right=True) - 1


def imu_attitude(
    dukf: DUKF | None,
    imu_stamps: Tensor,
    gyro: Tensor,
    accel: Tensor,
    source: str = "dukf",
    speed: Tensor | None = None,
    max_imu_gap: float | None = None,
) -> tuple[Tensor, Tensor | None]:
    """Gravity-referenced [pitch, roll] at every IMU sample.

    Args:
        dukf: the filter (``source="dukf"``).
        imu_stamps: ``(N,)`` seconds (float64); gyro, accel: ``(N, 3)``.
        source: ``"dukf"`` (filtered, the paper) or ``"accel"`` (raw accelerometer angles:
            the "w/o DUKF" ablation).
        speed: ``(N,)`` forward speed for the turn compensation of the accelerometer (None: off).
        max_imu_gap: seconds; after a longer gap the filter restarts from the accelerometer, as
            the engine does (None: never).

    Returns:
        ``(N, 2)`` attitude and ``(N, 2, 2)`` covariance (None for ``"accel"``).
    """
    if speed is not None:
        accel = remove_turn_acceleration(accel, gyro, speed)
    if source == "accel":
        return accel_to_pitch_roll(accel), None
    if source != "dukf" or dukf is None:
        raise ValueError(f"attitude source must be 'dukf' (with a DUKF) or 'accel', got {source!r}")
    dtype = dukf.log_process_var.dtype
    dt = torch.diff(imu_stamps, prepend=imu_stamps[:1]).to(dtype)
    if imu_stamps.numel() > 1 and bool((dt[1:] <= 0).any()):
        raise ValueError("IMU stamps must be strictly increasing")
    dt = dt.clone()
    dt[0] = 1.0  # unused: sample 0 initialises the filter
    starts = [0]
    if max_imu_gap is not None:
        starts += (torch.nonzero(dt[1:] > max_imu_gap).flatten() + 1).tolist()
    means, covs = [], []
    for a, b in zip(starts, starts[1:] + [dt.numel()]):  # each stretch starts a fresh filter
        mean, cov, _ = dukf.filter(gyro[a:b].to(dtype)[None], accel[a:b].to(dtype)[None], dt[None, a:b])
        means.append(mean[0])
        covs.append(cov[0])
    return torch.cat(means), torch.cat(covs)


def imu_speeds(imu_stamps: Tensor, frame_stamps: Tensor, motion: Tensor) -> Tensor:
    """Forward speed each IMU sample sees online: that of the latest VO step whose frame is strictly
    earlier (the engine processes a frame before fusing the next later IMU sample); 0 before.

    Args:
        imu_stamps: ``(N,)``; frame_stamps: ``(F,)``; motion: ``(F-1, 3)`` estimated steps.

    Returns:
        ``(N,)`` m/s, detached.
    """
    dt = (frame_stamps[1:] - frame_stamps[:-1]).to(motion.dtype)
    frame_speed = torch.cat([motion.new_zeros(1), motion[:, 0].detach() / dt])  # (F,): speed known at frame k
    k = torch.searchsorted(frame_stamps.contiguous(), imu_stamps.contiguous(), right=False) - 1
    return torch.where(k >= 0, frame_speed[k.clamp_min(0)], torch.zeros_like(frame_speed[0])).to(torch.float64)


def road_attitude_at_frames(
    attitude: Tensor, imu_stamps: Tensor, frame_idx: Tensor, road_tilt_time_constant: float
) -> Tensor:
    """Road-relative attitude ``(F, 2)`` at the frames from the IMU-rate attitude ``(N, 2)``."""
    dt = torch.diff(imu_stamps, prepend=imu_stamps[:1]).to(attitude.dtype)
    road = road_relative_attitude(attitude[None], dt[None], road_tilt_time_constant)[0]
    return road[frame_idx]


def project_frames(
    images: Tensor, camera: CameraModel, pitch_roll_road: Tensor, spec: BevSpec, chunk: int = 32
) -> tuple[Tensor, Tensor]:
    """BEVs of many frames, in chunks to bound memory.

    Args:
        images: ``(F, H, W)`` uint8 or float in [0, 1].
        pitch_roll_road: ``(F, 2)``.

    Returns:
        ``bev (F, 1, S, S)`` and ``mask (F, 1, S, S)``.
    """
    dtype = pitch_roll_road.dtype if pitch_roll_road.is_floating_point() else torch.float32
    cam = camera.to(images.device, dtype)
    bevs, masks = [], []
    for i in range(0, images.shape[0], chunk):
        img = images[i : i + chunk]
        img = img if img.dtype == torch.uint8 else img.to(dtype)
        pr = pitch_roll_road[i : i + chunk]
        b, m = project_to_bev(img[:, None], cam, pr[:, 0], pr[:, 1], spec)
        bevs.append(b)
        masks.append(m)
    return torch.cat(bevs), torch.cat(masks)


def register_consecutive(bev: Tensor, mask: Tensor, config: DpcConfig) -> Registration:
    """Registrations of every consecutive pair ``(F-1)`` with each frame prepared once."""
    prepared = prepare(bev, mask, config)
    return register_prepared(prepared[:-1], prepared[1:], config)


@dataclass
class SequenceResult:
    """Everything a training step or an ablation needs from one pass."""

    registration: Registration | None  # over the registered pairs (not ``failed``); None when windowed
    motion: Tensor  # (F-1, 3) float64 cpu estimated (dx, dy, dyaw), zero where failed
    failed: Tensor  # (F-1,) bool cpu: a BEV of the pair has no valid pixel (the camera tilted off the road)
    pitch_roll_gravity: Tensor  # (F, 2) at the frames
    pitch_roll_road: Tensor  # (F, 2) used for the BEVs
    loss: float = 0.0  # sum of ``pair_loss`` over the windows


def run_sequence(
    dukf: DUKF | None,
    camera: CameraModel,
    spec: BevSpec,
    dpc: DpcConfig,
    imu_stamps: Tensor,
    gyro: Tensor,
    accel: Tensor,
    frame_stamps: Tensor,
    images: Tensor,
    road_tilt_time_constant: float = 1.0,
    source: str = "dukf",
    given_pitch_roll_road: Tensor | None = None,
    mounting_attitude: tuple[float, float] = (0.0, 0.0),
    turn_compensation: bool = False,
    max_imu_gap: float | None = None,
    window: int | None = None,
    pair_loss: Callable[[Registration, Tensor], Tensor] | None = None,
) -> SequenceResult:
    """BEVO over a recording; differentiable in the DUKF's O and Q.

    Args:
        imu_stamps: ``(N,)`` float64 seconds; gyro, accel ``(N, 3)``.
        frame_stamps: ``(F,)`` float64 seconds, each >= ``imu_stamps[0]``.
        images: ``(F, H, W)`` (any device; each window is moved to the attitude's).
        source: ``"dukf"``, ``"accel"`` (w/o DUKF) or ``"given"`` (``given_pitch_roll_road``, e.g.
            ground truth: the "w/ GT" ablation; used as is, without ``mounting_attitude``).
        mounting_attitude: static (pitch, roll) of the base on the road, added to the filtered
            road-relative attitude when the road-tilt low-pass is on (it removes every constant;
            without it the gravity-referenced attitude holds the mounting already), as
            :class:`~bevo_ros.core.odometry.BevoOdometry` does.
        turn_compensation: remove speed x turn rate from the accelerometer like the engine does;
            the speeds come from a first, gradient-free pass (online they come from the previous
            frame's estimate, so the two differ only by what that first pass changes).
        max_imu_gap: longer IMU gaps restart the filter (the engine's ``max_imu_gap``).
        window: frame pairs per BEV/DPC chunk, to bound memory (None: one chunk, and the
            registration is kept in the result).
        pair_loss: ``(registration of a window's registered pairs, their pair indices (K,) cpu) ->
            summed loss``. With gradients enabled, the gradient of the mean over all ``F-1`` pairs is
            accumulated into the DUKF's ``.grad``: each window's gradient w.r.t. the attitude is
            accumulated, then pushed through the DUKF once (exact, memory bounded by the window).
    """
    if source not in ATTITUDE_SOURCES:
        raise ValueError(f"source must be one of {ATTITUDE_SOURCES}, got {source!r}")
    n_pairs = frame_stamps.shape[0] - 1
    if window is not None and window < 1:
        raise ValueError(f"window must be >= 1 frame pair, got {window}")
    speed = None
    if turn_compensation and source != "given":
        with torch.no_grad():
            first = run_sequence(dukf, camera, spec, dpc, imu_stamps, gyro, accel, frame_stamps, images,
                                 road_tilt_time_constant, source, None, mounting_attitude, turn_compensation=False,
                                 max_imu_gap=max_imu_gap, window=window)
        speed = imu_speeds(imu_stamps, frame_stamps, first.motion.to(frame_stamps.device))
    gravity, road = frame_attitudes(dukf, imu_stamps, gyro, accel, frame_stamps, road_tilt_time_constant, source,
                                    given_pitch_roll_road, mounting_attitude, speed, max_imu_gap)
    accumulate = pair_loss is not None and road.requires_grad
    road_in = road.detach().requires_grad_() if accumulate else road  # the windows' gradients gather here
    motion = torch.zeros(n_pairs, 3, dtype=torch.float64)
    failed = torch.zeros(n_pairs, dtype=torch.bool)
    registration, loss_sum = None, 0.0
    step = window or max(n_pairs, 1)
    for w0 in range(0, n_pairs, step):
        w1 = min(w0 + step, n_pairs)  # pairs w0..w1-1 = frames w0..w1
        reg, m, bad = register_frames(images[w0:w1 + 1].to(road.device), camera, road_in[w0:w1 + 1], spec, dpc)
        motion[w0:w1] = m.detach().double().cpu()
        failed[w0:w1] = bad.cpu()
        registration = reg if window is None else None
        if pair_loss is not None and reg is not None:
            loss = pair_loss(reg, torch.arange(w0, w1)[~bad.cpu()])
            if accumulate and loss.requires_grad:
                (loss / n_pairs).backward()
            loss_sum += float(loss.detach())
    if accumulate and road_in.grad is not None:
        road.backward(road_in.grad)
    return SequenceResult(registration, motion, failed, gravity, road, loss_sum)


def frame_attitudes(dukf: DUKF | None, imu_stamps: Tensor, gyro: Tensor, accel: Tensor, frame_stamps: Tensor,
                    road_tilt_time_constant: float, source: str = "dukf",
                    given_pitch_roll_road: Tensor | None = None,
                    mounting_attitude: tuple[float, float] = (0.0, 0.0),
                    speed: Tensor | None = None, max_imu_gap: float | None = None) -> tuple[Tensor, Tensor]:
    """Gravity-referenced and road-relative ``[pitch, roll]`` at the frames, ``(F, 2)`` each, as the
    engine computes them (differentiable for ``"dukf"``): the filter over every IMU sample
    (restarted after gaps longer than ``max_imu_gap``), the road-tilt low-pass, then the static
    mounting attitude (only with the low-pass on); ``"given"`` is used as is. ``speed`` (``(N,)``,
    see :func:`imu_speeds`) turns on the turn compensation of the accelerometer."""
    if source == "given":
        if given_pitch_roll_road is None or given_pitch_roll_road.shape != (frame_stamps.shape[0], 2):
            raise ValueError("source='given' needs given_pitch_roll_road of shape (F, 2)")
        given = given_pitch_roll_road.to(frame_stamps.device, torch.float64)
        return given, given
    idx = frame_imu_indices(imu_stamps, frame_stamps)
    if bool((idx < 0).any()):
        raise ValueError("every frame needs an IMU sample at or before its stamp; trim the frames")
    attitude, _ = imu_attitude(dukf, imu_stamps, gyro, accel, source, speed, max_imu_gap)
    road = road_attitude_at_frames(attitude, imu_stamps, idx, road_tilt_time_constant)
    if is_enabled(road_tilt_time_constant):
        road = road + torch.tensor(mounting_attitude, dtype=road.dtype, device=road.device)
    return attitude[idx], road


def register_frames(images: Tensor, camera: CameraModel, road: Tensor, spec: BevSpec,
                    dpc: DpcConfig) -> tuple[Registration | None, Tensor, Tensor]:
    """The per-frame batched math: BEVs at the road-relative attitude, each frame prepared once,
    consecutive pairs registered, motion. A frame whose BEV has no valid pixel (the engine's
    :func:`~bevo_ros.core.phase_correlation.prepare` would refuse it) fails both its pairs.

    Args:
        images: ``(F, H, W)``; road: ``(F, 2)`` [pitch, roll].

    Returns:
        registration of the ``K`` registered pairs (None if none), motion ``(F-1, 3)`` (zero where
        failed) and failed ``(F-1,)`` bool.
    """
    bev, mask = project_frames(images, camera, road.float(), spec)
    valid = soft_weight(mask, dpc).sum(dim=(-1, -2)) > MIN_BEV_WEIGHT  # (F,)
    ok = valid[:-1] & valid[1:]
    motion = bev.new_zeros(ok.shape[0], 3)
    if not bool(ok.any()):
        return None, motion, ~ok
    pos = torch.cumsum(valid.long(), 0) - 1  # frame -> index among the valid ones
    prepared = prepare(bev[valid], mask[valid], dpc)
    reg = register_prepared(prepared[pos[:-1][ok]], prepared[pos[1:][ok]], dpc)
    motion = motion.index_put((ok,), vehicle_motion_from_registration(reg.angle, reg.shift, spec))
    return reg, motion, ~ok


def registration_targets(motion: Tensor, spec: BevSpec) -> tuple[Tensor, Tensor]:
    """Ground-truth ``(F-1, 3)`` motion -> the angle and pixel shift the correlation should find."""
    return registration_from_vehicle_motion(motion, spec)
