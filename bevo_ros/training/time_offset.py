"""The IMU's clock against the camera's from a drive: ``bevo calibrate --imu-time-offset``.

Each image is projected at the IMU's attitude at its stamp, so a few milliseconds between the two
clocks show (rendered ``urban``, 100 Hz IMU: 4.9 % per frame aligned, 17.4 % with the IMU 12 ms
ahead). Between two frames the camera turns by what the gyro integrates over the same interval; with
the IMU's stamps off by ``tau`` the gyro's integral over ``[t0 + tau, t1 + tau]`` matches instead.
The images give that rotation without the IMU: per frame pair, the relative pose from their epipolar
geometry (:func:`~bevo_ros.core.travel_direction.relative_pose`, OpenCV). The offset is the
``tau`` at which the gyro's integrals best match the images' rotations (compared in the base's
axes), a constant gyro bias fitted along, the worst pairs (a moving car's matches) trimmed.

What times it is the change of the rate across a frame interval (``integral over [t0 + tau, t1 + tau]``
moves by ``tau (w(t1) - w(t0))``): a drive through bends and over bumps, not a straight smooth road.
The result's standard error comes from the same change; the command refuses a drive that leaves it
over :data:`MAX_STANDARD_ERROR`, a best offset at the edge of the +-:data:`MAX_OFFSET` searched, and
images that do not turn as the gyro does about an axis (a wrong extrinsic rotation or IMU frame).
Clocks further apart than the search can still show a false minimum inside it on a drive whose
motion repeats; its residual (printed) is then several times the usual 0.03-0.1 deg per axis and pair.
"""
from __future__ import annotations

import math
from typing import NamedTuple

import cv2
import numpy as np

from bevo_ros.core.rate_integration import GYRO_SAMPLING
from bevo_ros.core.travel_direction import relative_pose

MAX_OFFSET = 1.0  # s searched either way
COARSE_STEP = 0.005  # s between the offsets tried over the whole search (the cost is smooth on this scale)
GRID_STEP = 0.001  # s between the offsets tried around the coarse minimum, before the parabola's refinement
MIN_PAIRS = 20  # frame pairs with a rotation needed
TRIM = 0.9  # the share of pairs (smallest residuals at each offset) the cost keeps
MAX_STANDARD_ERROR = 0.005  # s: a drive that times the IMU worse than this is refused
# The images' rotation against the gyro's, per base axis (where the pairs give it to GAIN_STANDARD_ERROR).
# About the base's x and y (roll, pitch) it must lie within NORMAL_GAIN: a flipped or mixed axis (a wrong
# extrinsic rotation or IMU frame) can match the bumps' oscillation half a period off (the camera turned
# 180 deg in the extrinsics on a test rig: -0.28 s, gains 0.56 / 0.79). About the vertical, moving cars in
# view turn their features with them (0.40-0.75 on rendered drives with traffic, whose offsets still came
# out within their standard errors: the offset comes from the rates' changes, which a scale does not
# move): outside GAIN_RANGE refused (or a gyro in other units), outside NORMAL_GAIN a note.
GAIN_RANGE = (0.25, 4.0)
NORMAL_GAIN = (0.8, 1.25)
GAIN_STANDARD_ERROR = 0.05
# An IMU interval over GAP_FACTOR times the median and over MIN_GAP s is a gap (a sample spread over it):
# pairs whose search window holds one are left out. Jittered stamps, a lost sample or two are no gap.
GAP_FACTOR = 2.0
MIN_GAP = 0.1


class TimeOffset(NamedTuple):
    """:func:`imu_time_offset`'s result."""

    offset: float  # s to add to every IMU stamp (``odometry.imu_time_offset``): the IMU on the images' clock
    standard_error: float  # s
    residual: float  # rad: RMS per axis of the kept pairs' rotation mismatch at the offset
    gyro_bias: tuple[float, float, float]  # rad/s, base_frame's axes, fitted along
    pairs: int  # pairs kept (the trimmed share of those with a rotation)
    pairs_skipped: int  # pairs without a rotation (too few tracks, standing still), without IMU around them
    # (or a gap in it), or trimmed
    gains: tuple[float, float, float] = (math.nan, math.nan, math.nan)  # the images' rotation over the gyro's about
    # the base's x, y and z (roll, pitch, yaw), NaN where the pairs do not determine it

    def gain_note(self) -> str | None:
        """A line on the axes whose images turned outside :data:`NORMAL_GAIN` times the gyro, or None."""
        g = self.gains[2]
        if not math.isfinite(g) or NORMAL_GAIN[0] <= g <= NORMAL_GAIN[1]:
            return None
        return (f"about the vertical the images turn {g:.2f} times as the gyro does: moving cars in view (their "
                "features turn with them; the offset comes from the rates' changes, which such a scale does not move), "
                "or extrinsics a little off")


def image_rotations(images, K) -> tuple[np.ndarray, np.ndarray]:
    """Per consecutive pair of ``images`` (``(F, H, W)`` uint8, rectified, intrinsics ``K (3, 3)``) the
    camera's rotation from the first frame to the second as a rotation vector in the first camera's
    optical frame (rad). -> ``(P,)`` index of each pair's first frame, ``(P, 3)`` rotation vectors;
    pairs the epipolar geometry does not determine are left out."""
    K = np.asarray(K, dtype=np.float64)
    cv2.setRNGSeed(0)  # RANSAC's draws: the same bag gives the same offset
    index, rotations = [], []
    for k in range(len(images) - 1):
        pose = relative_pose(np.ascontiguousarray(images[k]), np.ascontiguousarray(images[k + 1]), K)
        if pose is None:
            continue
        R = pose[0]  # x1 = R x0 + t: the second camera's axes in the first's are R^T
        index.append(k)
        rotations.append(cv2.Rodrigues(R.T)[0].ravel())
    return np.array(index, dtype=np.int64), np.array(rotations, dtype=np.float64).reshape(-1, 3)


def _rate_integral(stamps: np.ndarray, gyro: np.ndarray, sampling: str):
    """The gyro's integral as a function of time ``(M,) -> (M, 3)`` over ``stamps`` ``(N,)`` / ``gyro (N, 3)``:
    with ``"interval_mean"`` each sample is the mean rate since the previous one (the rate is
    piecewise constant), with ``"instantaneous"`` the rate at its stamp (piecewise linear)."""
    h = np.diff(stamps)
    step = gyro[1:] if sampling == "interval_mean" else 0.5 * (gyro[1:] + gyro[:-1])
    F = np.vstack([np.zeros(3), np.cumsum(step * h[:, None], axis=0)])

    def integral(t: np.ndarray) -> np.ndarray:
        i = np.clip(np.searchsorted(stamps, t, side="right") - 1, 0, len(stamps) - 2)
        u = (t - stamps[i])[:, None]
        if sampling == "interval_mean":
            return F[i] + gyro[i + 1] * u
        slope = (gyro[i + 1] - gyro[i]) / h[i][:, None]
        return F[i] + gyro[i] * u + 0.5 * slope * u * u

    return integral


def imu_time_offset(frame_stamps, rotations_index, rotations, imu_stamps, gyro, R_base_cam,
                    sampling: str = "interval_mean") -> TimeOffset:
    """The offset to add to the IMU's stamps to put them on the images' clock.

    Args:
        frame_stamps: ``(F,)`` s, the images' stamps.
        rotations_index, rotations: :func:`image_rotations`' ``(P,)`` pair indices and ``(P, 3)`` rotations.
        imu_stamps, gyro: ``(N,)`` s and ``(N, 3)`` rad/s in base_frame's axes (as the engine takes them).
        R_base_cam: ``(3, 3)`` the camera's axes in base_frame (the extrinsics' rotation).
        sampling: what each gyro sample is (``filter.gyro_sampling``).

    Raises:
        ValueError: inputs of the wrong shape, not finite or not increasing; too few pairs within the
            IMU's span; the best offset at the edge of the +-:data:`MAX_OFFSET` searched (further
            apart, or a wrong rig); the images' rotations not the gyro's (a wrong extrinsic rotation,
            IMU frame or gyro unit: :data:`GAIN_RANGE`); or a drive that does not time the IMU to
            :data:`MAX_STANDARD_ERROR` (too little change of the rotation rate: drive through bends).
    """
    if sampling not in GYRO_SAMPLING:
        raise ValueError(f"gyro sampling must be one of {GYRO_SAMPLING}, got {sampling!r}")
    fs = np.asarray(frame_stamps, dtype=np.float64)
    ts, w = np.asarray(imu_stamps, dtype=np.float64), np.asarray(gyro, dtype=np.float64)
    idx, rot = np.asarray(rotations_index), np.asarray(rotations, dtype=np.float64)
    if idx.size == 0:
        idx = idx.astype(np.int64)  # none: "only 0 frame pairs" below
    R_cb = np.asarray(R_base_cam, dtype=np.float64).T
    _check_inputs(fs, ts, w, idx, rot, R_cb)
    t0, t1 = fs[idx], fs[idx + 1]
    h = np.diff(ts)
    # Every offset tried stays within the IMU, and no gap in it (a late sample spread over the gap; the
    # engine restarts past filter.max_imu_gap) lies within the pair's widest window.
    gap = h > max(GAP_FACTOR * float(np.median(h)), MIN_GAP)
    gap_start, gap_end = ts[:-1][gap], ts[1:][gap]  # sorted, disjoint
    overlapping = (np.searchsorted(gap_start, t1 + MAX_OFFSET, side="left")
                   - np.searchsorted(gap_end, t0 - MAX_OFFSET, side="right"))
    clear = overlapping <= 0
    inside = (t0 - MAX_OFFSET >= ts[0]) & (t1 + MAX_OFFSET <= ts[-1]) & clear
    skipped = len(fs) - 1 - int(inside.sum())
    t0, t1 = t0[inside], t1[inside]
    rot = rot[inside] @ R_cb  # the images' rotations in the base's axes, the gyro's: compared there
    if len(rot) < MIN_PAIRS:
        raise ValueError(f"only {len(rot)} frame pairs with a rotation from the images and the IMU {MAX_OFFSET:g} s "
                         f"around them, without a gap (at least {MIN_PAIRS}: the car must move past textured "
                         "surroundings)")
    integral = _rate_integral(ts, w, sampling)
    dt = (t1 - t0)[:, None]
    keep = max(MIN_PAIRS, int(TRIM * len(rot)))

    def fit(tau: float) -> tuple[float, np.ndarray, np.ndarray, np.ndarray]:
        """Trimmed cost at ``tau``, the gyro's bias, the kept pairs and the gyro's rotations less the bias
        (all pairs; the base's axes)."""
        gyro_rot = integral(t1 + tau) - integral(t0 + tau)
        diff = gyro_rot - rot  # the gyro's bias integrates into it
        kept = np.arange(len(rot))
        for _ in range(2):  # the bias from the kept pairs, then the pairs from the bias
            bias = (diff[kept] * dt[kept]).sum(axis=0) / float((dt[kept] ** 2).sum())
            res = diff - bias * dt
            kept = np.argsort((res**2).sum(axis=1))[:keep]
        return float((res[kept] ** 2).sum()), bias, kept, gyro_rot - bias * dt

    coarse = np.linspace(-MAX_OFFSET, MAX_OFFSET, int(round(2 * MAX_OFFSET / COARSE_STEP)) + 1)
    best = float(coarse[int(np.argmin([fit(t)[0] for t in coarse]))])
    fine = GRID_STEP * np.arange(-COARSE_STEP / GRID_STEP, COARSE_STEP / GRID_STEP + 0.5)
    for _ in range(10):  # the fine grid follows its minimum off its edge (a cost rougher than the coarse steps)
        taus = np.clip(best + fine, -MAX_OFFSET, MAX_OFFSET)
        costs = np.array([fit(t)[0] for t in taus])
        j = int(np.argmin(costs))
        if 1 <= j <= len(taus) - 2 or abs(taus[j]) >= MAX_OFFSET - GRID_STEP / 2:
            break
        best = float(taus[j])
    if abs(taus[j]) >= MAX_OFFSET - GRID_STEP / 2 or not 1 <= j <= len(taus) - 2:
        # no minimum inside: the clocks are further apart, or the rig is wrong
        raise ValueError(f"the best offset lies at the edge of the +-{MAX_OFFSET:g} s searched: the clocks are further "
                         "apart than that (align the stamps roughly first), or the gyro and the images do not match "
                         "(check the camera's extrinsics and the IMU's frame on /tf_static)")
    c_m, c_0, c_p = costs[j - 1:j + 2]
    curvature = c_m - 2 * c_0 + c_p
    step = 0.5 * GRID_STEP * (c_m - c_p) / curvature if curvature > 0 else 0.0
    tau = float(taus[j] + np.clip(step, -GRID_STEP, GRID_STEP))
    cost, bias, kept, gyro_rot = fit(tau)
    sigma = math.sqrt(cost / max(1, 3 * len(kept) - 4))  # per axis; 3 bias terms and the offset fitted
    # The images turn as the gyro says, about each of the base's axes (NORMAL_GAIN, GAIN_RANGE)
    g, r = gyro_rot[kept], rot[kept]
    power = (g**2).sum(axis=0)
    gains = [math.nan, math.nan, math.nan]
    for axis in range(3):
        if power[axis] > 0 and sigma / math.sqrt(power[axis]) <= GAIN_STANDARD_ERROR:
            gains[axis] = gain = float((r[:, axis] * g[:, axis]).sum() / power[axis])
            low, high = NORMAL_GAIN if axis < 2 else GAIN_RANGE
            if not low <= gain <= high:
                raise ValueError(
                    f"about the base's {'xyz'[axis]} axis ({('roll', 'pitch', 'yaw')[axis]}) the images turn "
                    f"{gain:.2f} times as the gyro does (residual {math.degrees(sigma):.3f} deg per axis and pair): "
                    "check the camera's extrinsics, the IMU's frame (/tf_static, camera.base_T_camera) and that the "
                    "gyro is in rad/s" + (", or use a stretch without cars turning in view" if axis == 2 else ""))
    # Gauss-Newton: d(gyro_rot)/d(tau) = the rate's change across the pair. The rate
    # over half a frame interval: a gyro's white noise changes it from sample to sample, which times nothing
    # (a steady turn, 100 Hz of 0.005 rad/s noise: +-4 ms read from the samples' noise, offsets at random).
    half = 0.25 * float(np.median(dt))

    def smooth_rate(t: np.ndarray) -> np.ndarray:
        return (integral(t + half) - integral(t - half)) / (2 * half)

    slope = smooth_rate(t1[kept] + tau) - smooth_rate(t0[kept] + tau)
    information = float((slope**2).sum())
    se = sigma / math.sqrt(information) if information > 0 else math.inf
    if not se <= MAX_STANDARD_ERROR:
        raise ValueError(f"the drive times the IMU only to +-{se * 1e3:.1f} ms (at most {MAX_STANDARD_ERROR * 1e3:g}; "
                         f"the gyro matches the images to {math.degrees(sigma):.3f} deg per axis and pair): too little "
                         "change of the rotation rate between frames; drive through bends and over bumps")
    return TimeOffset(-tau, se, sigma, tuple(float(b) for b in bias), len(kept), skipped + len(rot) - len(kept),
                      tuple(gains))


def _check_inputs(fs: np.ndarray, ts: np.ndarray, w: np.ndarray, idx: np.ndarray, rot: np.ndarray,
                  R_cb: np.ndarray) -> None:
    """ValueError naming what is wrong with :func:`imu_time_offset`'s inputs."""
    if fs.ndim != 1 or len(fs) < 2 or not np.all(np.isfinite(fs)) or not np.all(np.diff(fs) > 0):
        raise ValueError("the frames' stamps must be at least 2, finite and increasing")
    if ts.ndim != 1 or len(ts) < 2 or not np.all(np.isfinite(ts)) or not np.all(np.diff(ts) > 0):
        raise ValueError("the IMU's stamps must be at least 2, finite and increasing")
    if w.shape != (len(ts), 3) or not np.all(np.isfinite(w)):
        raise ValueError(f"the gyro must be (N, 3) finite rates for the {len(ts)} IMU stamps, got {w.shape}")
    if R_cb.shape != (3, 3) or not np.all(np.isfinite(R_cb)):
        raise ValueError(f"R_base_cam must be a finite (3, 3) rotation, got {R_cb.shape}")
    if rot.ndim != 2 or rot.shape[1:] != (3,) or idx.shape != (len(rot),) or not np.all(np.isfinite(rot)):
        raise ValueError(f"the rotations must be (P, 3) finite with one pair index each, got {rot.shape} and "
                         f"{idx.shape}")
    if len(idx) and (not np.issubdtype(idx.dtype, np.integer) or idx.min() < 0 or idx.max() >= len(fs) - 1):
        raise ValueError(f"the pair indices must be integers within 0..{len(fs) - 2} (a pair's first frame)")


__all__ = ["TimeOffset", "image_rotations", "imu_time_offset", "MAX_OFFSET", "MAX_STANDARD_ERROR", "GAIN_RANGE",
           "NORMAL_GAIN"]
