"""Learning the pitch and roll gyro's bias prior (fused item 18) from the ground truth's attitude.

Fused item 18 (:mod:`bevo_ros.core.gyro_bias`) carries the x / y rate biases between stops from a
prior: how large a turn-on bias the IMU may have (``std``, rad/s) and how fast it wanders (``walk``,
rad/s/sqrt(s)). The defaults (``filter.gyro_bias_std`` / ``gyro_bias_walk``) are a calibrated MEMS
part's datasheet values; ``params/kitti.yaml`` has 0 (KITTI's OXTS corrects its own rates). A bag
with ground truth measures them: over each frame interval the gyro's x / y integral less the ground
truth's body rotation (the rotation vector of ``inv(P_k) P_k+1``) is the bias times the interval,
plus noise. Per bag the mean over its training frames is its bias, with a standard error from
its :data:`WINDOW` s windows' scatter; the prior's ``std`` is their RMS over the bags and both axes
(less its own noise) where that is resolved (:func:`fit_gyro_bias`), else the data only bound it
(the shared OXTS drives read 0.002-0.008 deg/s: not resolved; 12 s of a 10 Hz MEMS gyro cannot tell
0.1 deg/s from nothing). ``walk`` comes from consecutive windows and each window's halves (``None``
with fewer than two pairs of consecutive windows).

Like the other fused-mode fits, ``bevo train`` keeps the measured prior only if the engine reads the
validation frames clearly better with it (:func:`~bevo_ros.training.suspension.engine_judgement`),
and writes it as the learned file's ``gyro_bias``, which the engine then takes over the parameters'.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

__all__ = ["WINDOW", "GyroBiasFit", "interval_residuals", "fit_gyro_bias", "fit_gyro_bias_on_sequences"]

# s: the windows whose biases measure the walk (a MEMS walk of 2e-4 rad/s/sqrt(s) moves the bias by
# ~0.04 deg/s in 10 s, the shared OXTS drives' 10 s windows scatter by ~0.015 deg/s).
WINDOW = 10.0
# The prior is refitted in the engine only if it differs from the one in use by more than this
# factor (a prior within it changes the engine by nothing a judgement could see).
AGREEMENT_FACTOR = 1.5


@dataclass(frozen=True)
class GyroBiasFit:
    """What the ground truth says of the x / y gyro's bias.

    Attributes:
        biases: ``(B, 2)`` each recording's mean (x, y) rate bias over the frames used, rad/s.
        standard_errors: ``(B, 2)`` their standard errors (from the windows' scatter), rad/s.
        rms: rad/s, the biases' RMS over the recordings and both axes.
        bound: rad/s, ``rms`` plus its standard error times Student's t at 97.5 %: what the bias is
            not above.
        resolved: ``rms`` is above that many standard errors (a bias was measured, not only bounded).
        walk: rad/s/sqrt(s), the random walk the windows say; None with fewer than two pairs of
            consecutive full windows.
        seconds: the time measured over, all recordings.
    """

    biases: np.ndarray
    standard_errors: np.ndarray
    rms: float
    bound: float
    resolved: bool
    walk: float | None
    seconds: float

    def prior_std(self, in_use: float) -> float | None:
        """The prior's standard deviation the measurement says, against the one ``in_use`` (rad/s):
        the biases' RMS less their own noise where resolved; 0 where the bias is bounded well below ``in_use`` (by
        :data:`AGREEMENT_FACTOR`); None where the data cannot tell."""
        if self.resolved:  # less the biases' own noise, which their RMS includes
            return math.sqrt(max(self.rms**2 - float(np.mean(self.standard_errors**2)), 0.0))
        return 0.0 if self.bound * AGREEMENT_FACTOR < in_use else None


def interval_residuals(sequence, start: int = 0, stop: int | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per frame interval ``k`` in ``[start, stop - 1)`` of a :class:`~bevo_ros.datasets.rosbag.Recording`
    with ground truth: ``(t, dt, r)``, the interval's midpoint (s), its length (s) and ``r (K, 2)`` the
    gyro's x / y integral over it (trapezoid over the IMU samples, the ends interpolated) less the
    ground truth's body rotation about x / y (rad): between its gravity-referenced attitudes
    (``gt_pitch_roll``) under the poses' heading, else between the poses. Intervals not covered by the IMU, or with a sample
    filled in by linear interpolation (:func:`~bevo_ros.datasets.kitti.linear_fill`) or next to one,
    are left out."""
    from scipy.spatial.transform import Rotation

    from bevo_ros.datasets.kitti import linear_fill

    if sequence.gt_poses is None:
        raise ValueError(f"{sequence.name}: no ground truth to measure the gyro's bias against")
    stop = len(sequence) if stop is None else stop
    ft = sequence.frame_stamps.double().numpy()[start:stop]
    poses = sequence.gt_poses.double().numpy()[start:stop]
    ts = sequence.imu_stamps.double().numpy()
    g = sequence.gyro.double().numpy()[:, :2]
    if len(ft) < 2 or len(ts) < 2:
        return np.zeros(0), np.zeros(0), np.zeros((0, 2))
    cum = np.concatenate([np.zeros((1, 2)), np.cumsum(0.5 * (g[1:] + g[:-1]) * np.diff(ts)[:, None], axis=0)])
    at = np.stack([np.interp(ft, ts, cum[:, i]) for i in range(2)], axis=1)  # (F, 2) the gyro's integral
    R = poses[:, :3, :3]
    if sequence.gt_pitch_roll is not None:
        # The gravity-referenced attitude (/ground_truth/imu) under the poses' heading: a synthetic drive's
        # poses carry the attitude to the road, whose tilt turns with the car (a bend on a cambered road
        # read as 0.3 deg/s of pitch-rate bias).
        pr = sequence.gt_pitch_roll.double().numpy()[start:stop]
        R = Rotation.from_euler("ZYX", np.stack([np.arctan2(R[:, 1, 0], R[:, 0, 0]), pr[:, 0], pr[:, 1]], axis=1)
                                ).as_matrix()
    rel = np.swapaxes(R[:-1], 1, 2) @ R[1:]  # the body's rotation over each interval
    truth = Rotation.from_matrix(rel).as_rotvec()[:, :2]
    covered = (ft[:-1] >= ts[0]) & (ft[1:] <= ts[-1]) & np.isfinite(truth).all(axis=1)
    # Samples filled in by linear interpolation over lost packets (KITTI's synced OXTS: its ground
    # truth is interpolated there too) and the real samples they were drawn from are no measurement
    # of either: the KITTI sample's first 1.2 s read 0.14 deg/s of x / y "bias" with them.
    filled = linear_fill(np.concatenate([sequence.accel.double().numpy(), sequence.gyro.double().numpy()], axis=1))
    filled[:-1] |= filled[1:]
    filled[1:] |= filled[:-1]
    if filled.any():
        bad = ts[filled]
        first = np.searchsorted(bad, ft[:-1], side="left")  # a filled sample in [t_k, t_k+1]
        covered &= ~((first < len(bad)) & (bad[np.minimum(first, len(bad) - 1)] <= ft[1:]))
    dt = np.diff(ft)
    return (0.5 * (ft[:-1] + ft[1:]))[covered], dt[covered], (np.diff(at, axis=0) - truth)[covered]


def _window_mean(r: np.ndarray, dt: np.ndarray) -> np.ndarray:
    return r.sum(axis=0) / dt.sum()


def fit_gyro_bias(parts: list[tuple[np.ndarray, np.ndarray, np.ndarray]], window: float = WINDOW) -> GyroBiasFit:
    """The prior from :func:`interval_residuals` of one or more recordings (``parts``; each with at
    least one interval). Raises ValueError without any interval.

    Per recording: the bias (the mean over its intervals) and its standard error from its full
    windows' scatter (Student's t with their count less one degrees of freedom in the ``resolved``
    test and the bound: 2 or 3 windows' scatter is no normal standard error, and at 2 sigma a bias-free
    gyro read "resolved" in 11-19 % of 22-30 s runs); with one window, from the intervals' scatter. The
    walk: consecutive full windows' means differ by ``(2/3) walk^2 W`` (a random walk's window means,
    the Allan variance of a rate random walk) plus their noise, and a window's two halves by
    ``(1/3) walk^2 W`` plus twice the noise of one window's mean, so ``walk^2 = (2 change - halves) / W``
    whatever the noise's size (its scatter per interval overstated it: ground-truth attitude noise
    cancels between intervals, and a 0.03 deg OXTS-class attitude drove the walk to 0)."""
    from scipy.stats import t as student_t

    biases, errors, dofs, changes, halves, seconds = [], [], [], [], [], 0.0
    for t, dt, r in parts:
        if len(dt) == 0:
            continue
        seconds += float(dt.sum())
        biases.append(_window_mean(r, dt))
        k = np.floor((t - t[0]) / window).astype(int)
        full = [i for i in range(int(k.max()) + 1) if dt[k == i].sum() >= 0.8 * window and (k == i).sum() >= 2]
        by_window = {i: _window_mean(r[k == i], dt[k == i]) for i in full}
        means = np.array(list(by_window.values())).reshape(-1, 2)
        if len(means) >= 2:
            errors.append(means.std(axis=0, ddof=1) / math.sqrt(len(means)))
            dofs.append(len(means) - 1)
        else:  # one window: the intervals' own scatter, as if independent
            errors.append((r / dt[:, None]).std(axis=0) / math.sqrt(len(dt)))
            dofs.append(max(len(dt) - 1, 1))
        changes += [(by_window[i + 1] - by_window[i]) ** 2 for i in full if i + 1 in by_window]  # consecutive only
        for i in full:
            ri, di = r[k == i], dt[k == i]
            h = len(di) // 2
            halves.append((_window_mean(ri[h:], di[h:]) - _window_mean(ri[:h], di[:h])) ** 2)
    if not biases:
        raise ValueError("no frame interval with IMU and ground truth to measure the gyro's bias on")
    b, se = np.array(biases), np.array(errors)
    rms, rms_se = float(np.sqrt(np.mean(b**2))), float(np.sqrt(np.mean(se**2)))
    quantile = float(student_t.ppf(0.975, min(dofs)))
    walk = None
    if len(changes) >= 2:
        walk = float(np.sqrt(max(float(np.mean(2.0 * np.mean(changes, axis=0) - np.mean(halves, axis=0))), 0.0) / window))
    return GyroBiasFit(b, se, rms, rms + quantile * rms_se, rms > quantile * rms_se, walk, seconds)


def fit_gyro_bias_on_sequences(learned, seqs, config, split: str = "3/4", memo: dict | None = None) -> GyroBiasFit:
    """Fused mode (``bevo train``): measure the prior on the recordings' training frames and keep it in
    ``learned`` (its ``gyro_bias``) only if it differs from the one in use (``learned``'s, else the
    parameters') by more than :data:`AGREEMENT_FACTOR` and the engine reads the validation frames
    clearly better with it (:func:`~bevo_ros.training.suspension.engine_judgement`). Prints what it
    found and decided; returns the measurement."""
    from bevo_ros.config import gyro_bias_prior
    from bevo_ros.datasets.rosbag import split_frames
    from bevo_ros.training.suspension import engine_judgement

    parts = [interval_residuals(s, 0, split_frames(len(s), split)[0][1]) for s in seqs]
    fit = fit_gyro_bias(parts)
    std0, walk0 = gyro_bias_prior(config, learned)
    std = fit.prior_std(std0)
    walk = walk0 if fit.walk is None else fit.walk
    deg = math.degrees
    said = ", ".join(f"{deg(x):+.4f} / {deg(y):+.4f}" for x, y in fit.biases)
    print(f"gyro bias (x / y, deg/s, against the ground truth over {fit.seconds:.0f} s of training frames): {said}; "
          + (f"RMS {deg(fit.rms):.4f}" if fit.resolved else f"not resolved, below {deg(fit.bound):.4f}")
          + ("" if fit.walk is None else f", walk {fit.walk:.2e} rad/s/sqrt(s)")
          + f" (the prior in use: std {deg(std0):.4f} deg/s, walk {walk0:.2e})")
    learned.info["gyro_bias_measured"] = {"biases_rad_s": fit.biases.tolist(), "rms": fit.rms, "bound": fit.bound,
                                          "resolved": fit.resolved, "walk": fit.walk, "seconds": fit.seconds}
    lo, hi = sorted((std0, std if std is not None else std0))
    if std is None or hi == 0.0 or (lo > 0.0 and hi / lo <= AGREEMENT_FACTOR):
        print("gyro bias: " + ("the ground truth cannot tell it from the prior in use" if std is None else
                               "the measured prior agrees with the one in use") + "; nothing to change")
        return fit
    candidate = replace(learned, gyro_bias=(std, walk))
    before, after, keep, why = engine_judgement(seqs, config, learned, candidate, split, memo)
    print(f"gyro bias prior std {deg(std):.4f} deg/s in the engine: validation per-frame translation RMSE "
          f"{before:.4f} -> {after:.4f} m")
    learned.info["gyro_bias_measured"]["validation_rmse"] = [before, after]
    if not keep:
        print(f"gyro bias: the measured prior is not clearly better in the engine ({why}); keeping the one in use")
        return fit
    learned.gyro_bias = (std, walk)
    return fit
