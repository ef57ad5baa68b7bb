"""Learning the vehicle motion filter's noise (fused mode), like the DUKF's O and Q.

The engine records, per frame, exactly what it gave :meth:`VehicleFilter.step`
(``OdometryStep.filter_inputs``). Replaying those inputs through the filter's tensor form is the
engine's computation, differentiable in the log-noises; the loss is the Gaussian negative
log-likelihood of the ground-truth frame motion ``(dx, dy, dyaw)`` under the filter's output
(mean and variance), so the fit learns how much to smooth *and* how confident to be. Adam on the
log-variances; the measurements themselves (BEV, correlation, gyro) are held fixed.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, replace

import numpy as np
import torch

from bevo_ros.core.vehicle_filter import (VehicleFilter, VehicleNoise, forget_accel_bias, forget_speed,
                                          initial_vehicle_state)

Tensor = torch.Tensor

# The learned fields and how each enters the filter (all positive: learned as logs).
# image_rotation_std: in the engine. imu_accel_density only where it is on (> 0: a log).
TRAINED = ("jerk_density", "bias_walk_density", "gyro_yaw_density", "slip_std", "imu_accel_density")
RESETS = ("forget_speed", "forget_accel_bias")  # OdometryStep.filter_inputs flags, not VehicleFilter.step arguments

__all__ = ["TRAINED", "RESETS", "trained_fields", "VehicleFit", "replay", "motion_nll", "fit_vehicle_noise",
           "record_inputs", "fit_vehicle_on_sequences"]


@dataclass
class VehicleFit:
    noise: VehicleNoise
    nll_before: float
    nll_after: float
    rmse_before: tuple[float, float, float]  # dx, dy (m), dyaw (rad) per frame on the given frames
    rmse_after: tuple[float, float, float]
    steps: int


def trained_fields(base: VehicleNoise) -> tuple[str, ...]:
    """The :data:`TRAINED` fields ``base`` has on (an input switched off by 0 stays off)."""
    return tuple(k for k in TRAINED if k not in VehicleNoise.OFF_WHEN_ZERO or getattr(base, k) > 0)


def _noise_with(base: VehicleNoise, log_params: Tensor) -> VehicleNoise:
    return replace(base, **{k: log_params[i].exp() for i, k in enumerate(trained_fields(base))})


def replay(noise: VehicleNoise, inputs: list[dict]) -> tuple[Tensor, Tensor]:
    """Run the filter over recorded per-frame inputs (``OdometryStep.filter_inputs`` of frames
    1..F) from an unknown-speed start, as the engine does. Returns motion ``(F, 3)`` and variance
    ``(F, 3)``, float64 tensors (differentiable in ``noise`` when it holds tensors)."""
    vf = VehicleFilter(noise)
    like = torch.zeros(1, dtype=torch.float64)
    state = initial_vehicle_state(like=like)
    motions, variances = [], []
    for inp in inputs:
        # the engine's resets before this frame's step (a speed that followed another peak, a DUKF restart)
        if inp.get("forget_speed"):
            state = forget_speed(state)
        if inp.get("forget_accel_bias"):
            state = forget_accel_bias(state)
        kw = {k: (torch.as_tensor(v, dtype=torch.float64).reshape(1) if v is not None and k != "dt" else v)
              for k, v in inp.items() if k not in RESETS}
        frame = vf.step(state, **kw)
        state = frame.state
        motions.append(torch.stack([torch.as_tensor(m, dtype=torch.float64).reshape(1) for m in frame.motion], -1))
        variances.append(torch.stack([torch.as_tensor(v, dtype=torch.float64).reshape(1) for v in frame.variance], -1))
    return torch.cat(motions, 0), torch.cat(variances, 0)


def motion_nll(motion: Tensor, variance: Tensor, truth: Tensor) -> Tensor:
    """Mean Gaussian negative log-likelihood (per frame and axis) of ``truth (F, 3)``."""
    var = variance.clamp_min(1e-12)
    return 0.5 * (((truth - motion) ** 2) / var + var.log() + math.log(2 * math.pi)).mean()


def _rmse(motion: Tensor, truth: Tensor) -> tuple[float, float, float]:
    return tuple(float(v) for v in ((motion - truth) ** 2).mean(0).sqrt())


def fit_vehicle_noise(sequences: list[tuple[list[dict], np.ndarray]], init: VehicleNoise | None = None,
                      steps: int = 150, lr: float = 0.1, log=print) -> VehicleFit:
    """Fit the filter's noise on ``[(inputs, truth (F, 3)), ...]`` (one pair per recording).

    Returns the noise with the lowest training NLL seen (Adam can overshoot).
    """
    base = init or VehicleNoise()
    if not sequences or not any(len(i) for i, _ in sequences):
        raise ValueError("no frames to fit the vehicle filter on")
    truths = [torch.as_tensor(np.asarray(t), dtype=torch.float64) for _, t in sequences]
    params = torch.tensor([math.log(getattr(base, k)) for k in trained_fields(base)], dtype=torch.float64,
                          requires_grad=True)
    opt = torch.optim.Adam([params], lr=lr)

    def evaluate(p: Tensor) -> tuple[Tensor, list[Tensor]]:
        noise = _noise_with(base, p)
        total, outs = 0.0, []
        for (inputs, _), truth in zip(sequences, truths):
            m, v = replay(noise, inputs)
            total = total + motion_nll(m, v, truth) * len(inputs)
            outs.append(m)
        return total / sum(len(i) for i, _ in sequences), outs

    with torch.no_grad():
        nll0, outs0 = evaluate(params)
    best = (float(nll0), params.detach().clone())
    for i in range(steps):
        opt.zero_grad()
        nll, _ = evaluate(params)
        if not torch.isfinite(nll):
            log(f"vehicle filter fit: non-finite loss at step {i}; keeping the best so far")
            break
        if nll.item() < best[0]:  # the NLL measured is that of the parameters before this step's move
            best = (nll.item(), params.detach().clone())
        nll.backward()
        opt.step()
        with torch.no_grad():
            params.clamp_(-40.0, 20.0)
    with torch.no_grad():
        nll1, outs1 = evaluate(best[1])
    m0, m1, t = torch.cat(outs0), torch.cat(outs1), torch.cat(truths)
    fitted = replace(base, **{k: float(best[1][i].exp()) for i, k in enumerate(trained_fields(base))})
    return VehicleFit(fitted, float(nll0), float(nll1), _rmse(m0, t), _rmse(m1, t), steps)


def record_inputs(sequence, config, learned) -> tuple[list[dict], np.ndarray]:
    """Run the fused engine (the node's, with ``learned``) over a :class:`~bevo_ros.datasets.rosbag.Recording`;
    returns the filter inputs of frames 1.. and their ground-truth motion."""
    from bevo_ros.datasets.rosbag import run_engine

    steps = run_engine(sequence, config, learned, mode="fused")
    if len(steps) != len(sequence):
        raise ValueError(f"{sequence.name}: {len(sequence) - len(steps)} frame(s) dropped while recording filter inputs")
    return [s.filter_inputs for s in steps[1:]], sequence.gt_motion().double().numpy()


def fit_vehicle_on_sequences(learned, seqs, config, split: str = "3/4", steps: int = 100,
                             memo: dict | None = None) -> None:
    """Fused mode: learn the vehicle motion filter's noise on the training frames (NLL of the
    ground-truth motion, filter inputs recorded by the engine with the learned O/Q), keep it if the
    validation frames' NLL is not worse and the engine reads them clearly better
    (:func:`~bevo_ros.training.suspension.engine_judgement`)."""
    from bevo_ros.config import vehicle_noise
    from bevo_ros.datasets.rosbag import split_frames

    t0 = time.perf_counter()
    train_parts, val_parts = [], []
    for s in seqs:
        inputs, truth = record_inputs(s, config, learned)
        (_, cut), _ = split_frames(len(s), split)
        train_parts.append((inputs[: cut - 1], truth[: cut - 1]))
        val_parts.append((inputs, truth, cut - 1))
    base = vehicle_noise(config, learned)  # the engine's gates, not the defaults
    fit = fit_vehicle_noise(train_parts, base, steps=steps)

    def val_nll(noise) -> float:
        total, n = 0.0, 0
        for inputs, truth, cut in val_parts:
            m, v = replay(noise, inputs)
            t = torch.as_tensor(truth, dtype=torch.float64)
            total += float(motion_nll(m[cut:], v[cut:], t[cut:])) * (len(inputs) - cut)
            n += len(inputs) - cut
        return total / max(n, 1)

    before, after = val_nll(base), val_nll(fit.noise)
    print(f"vehicle filter ({time.perf_counter() - t0:.1f} s): train NLL {fit.nll_before:.3f} -> {fit.nll_after:.3f}, "
          f"validation NLL {before:.3f} -> {after:.3f}; per-frame RMSE (train) dx {fit.rmse_before[0]:.4f} -> "
          f"{fit.rmse_after[0]:.4f} m, dy {fit.rmse_before[1]:.4f} -> {fit.rmse_after[1]:.4f} m")
    if after <= before:
        # the fitted fields over the file's own (accel_bias_walk_density, image_rotation_std stay as they were)
        fitted = {**learned.vehicle, **{k: float(getattr(fit.noise, k)) for k in trained_fields(fit.noise)}}
        # The replay feeds the filter the measurements the engine made with the old noise; in the engine
        # the noise also moves its gates and its prediction behind other cars. Judged in the engine too:
        # fitted on one 30 s synthetic drive (make demo) the noise went far tighter than any car's (jerk
        # 0.15 m^2/s^5, slip 0.0002) with a better likelihood, and the held-out frames read worse.
        from bevo_ros.training.suspension import engine_judgement

        rmse_before, rmse_after, keep, why = engine_judgement(seqs, config, learned, replace(learned, vehicle=fitted),
                                                              split, memo)
        print(f"vehicle filter in the engine: validation per-frame translation RMSE {rmse_before:.4f} -> "
              f"{rmse_after:.4f} m")
        if not keep:
            print(f"vehicle filter: not clearly better in the engine ({why}); keeping the previous values")
            return
        learned.vehicle = fitted
        learned.info["vehicle_filter_fit"] = {"train_nll": [fit.nll_before, fit.nll_after],
                                             "validation_nll": [before, after],
                                             "validation_rmse": [rmse_before, rmse_after]}
    else:
        print("vehicle filter: the fit did not improve the validation frames; keeping the previous values")
