"""The IMU's clock against the camera's (``bevo calibrate --imu-time-offset``,
``bevo_ros.training.time_offset``): the estimator on exact rotations, and end to end on rendered drives."""
from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import yaml

from bevo_ros.commands import calibrate as calibrate_cmd
from bevo_ros.config import REPO_ROOT
from bevo_ros.datasets.rosbag import write_drive_bag
from bevo_ros.datasets.synthetic import kitti_like_camera, preset_drive
from bevo_ros.training.time_offset import imu_time_offset

SYNTH_PARAMS = str(REPO_ROOT / "params" / "synthetic.yaml")
R_BASE_CAM = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])  # optical axes on a level base


def _angle(t: np.ndarray, steady: bool = False) -> np.ndarray:
    """The base's rotation angles (rad, per axis) at ``t``: bumps in roll and pitch at 0.9-2.6 Hz, slow
    turns in yaw, each a sum of sines at incommensurate frequencies (no period within the search: a
    real road's motion does not repeat); ``steady``: a constant turn only (nothing to time an offset
    by). ``(N,)`` -> ``(N, 3)``."""
    if steady:
        return np.stack([0 * t, 0 * t, 0.1 * t], axis=1)

    def sines(*terms: tuple[float, float, float]) -> np.ndarray:
        return sum(a * np.sin(2 * np.pi * f * t + p) for a, f, p in terms)

    return np.stack([sines((0.003, 1.7, 0.0), (0.002, 1.13 * math.sqrt(2), 0.4), (0.0015, 2.61, 2.0)),
                     sines((0.004, 1.1, 1.0), (0.002, 0.9 * math.sqrt(3), 0.3), (0.001, 2.3 * math.pi / 3, 1.0)),
                     sines((0.3, 0.05, 0.0), (0.1, 0.031 * math.sqrt(5), 1.0))], axis=1)


def _rig(clock_ahead: float, imu_rate: float, sampling: str, bias=(0.0, 0.0, 0.0), steady: bool = False,
         seconds: float = 30.0, seed: int = 0):
    """Frames at 10 Hz with jittered stamps, their rotations in the camera's axes (the angles' change,
    0.03 deg of noise per axis and 5 % of pairs 1 deg off: matches on a moving car), and an IMU whose
    clock runs ``clock_ahead`` s ahead of the camera's, its samples of either ``sampling``."""
    rng = np.random.default_rng(seed)
    frames = np.arange(1.2, seconds - 1.2, 0.1)  # the IMU 1 s beyond either end: every offset searched
    frames = frames + rng.uniform(-0.003, 0.003, len(frames))
    true_imu = np.arange(0.0, seconds, 1.0 / imu_rate)
    if sampling == "interval_mean":  # the mean rate since the previous sample
        gyro = np.vstack([np.zeros(3), np.diff(_angle(true_imu, steady), axis=0) * imu_rate])
    else:  # the rate at the stamp, by a central difference
        h = 1e-5
        gyro = (_angle(true_imu + h, steady) - _angle(true_imu - h, steady)) / (2 * h)
    gyro = gyro + np.asarray(bias)
    rotations = np.diff(_angle(frames, steady), axis=0) @ R_BASE_CAM  # R_cam_base @ the base's rotation
    rotations += rng.normal(0.0, math.radians(0.03), rotations.shape)
    bad = rng.random(len(rotations)) < 0.05
    rotations[bad] += math.radians(1.0)
    return frames, np.arange(len(rotations)), rotations, true_imu + clock_ahead, gyro


@pytest.mark.parametrize("sampling,imu_rate", [("interval_mean", 100.0), ("interval_mean", 10.0),
                                               ("instantaneous", 100.0)])
def test_the_offset_comes_back_from_exact_rotations(sampling, imu_rate):
    """An IMU 12 ms ahead of the camera and one 30 ms behind, a gyro bias, a few bad pairs: the offset
    to set (-12 / +30 ms) comes back within three standard errors, each under 1 ms, and the bias along."""
    bias = (0.004, -0.003, 0.005)
    for ahead in (0.012, -0.030):
        frames, index, rotations, imu_stamps, gyro = _rig(ahead, imu_rate, sampling, bias)
        got = imu_time_offset(frames, index, rotations, imu_stamps, gyro, R_BASE_CAM, sampling)
        assert got.standard_error < 0.001
        assert abs(got.offset + ahead) < 3 * got.standard_error + 1e-4, got
        np.testing.assert_allclose(got.gyro_bias, bias, atol=1e-3)
        assert got.pairs == int(0.9 * len(index))


def test_a_drive_that_cannot_time_the_imu_is_refused():
    """A steady turn (the rate never changes between frames) gives no information on the offset, nor
    does a MEMS gyro's white noise on it (0.005 rad/s per sample, the synthetic IMU's, and the images'
    rotation 0.1 deg off per pair; 120 s at 100 Hz, 60 s at 400 Hz: read from the samples' noise, the
    offsets came out at random, each +-3-4 ms, before the rate was taken over half a frame interval), and
    a short stretch has too few pairs: each refused with the reason, not a number."""
    frames, index, rotations, imu_stamps, gyro = _rig(0.0, 100.0, "interval_mean", steady=True)
    with pytest.raises(ValueError, match=r"times the IMU only to .* drive through bends"):
        imu_time_offset(frames, index, rotations, imu_stamps, gyro, R_BASE_CAM)
    rng = np.random.default_rng(5)
    for rate, seconds in ((100.0, 120.0), (400.0, 60.0)):
        frames, index, rotations, imu_stamps, gyro = _rig(0.0, rate, "interval_mean", steady=True, seconds=seconds)
        rotations = rotations + rng.normal(0.0, math.radians(0.1), rotations.shape)
        with pytest.raises(ValueError, match=r"times the IMU only to"):
            imu_time_offset(frames, index, rotations, imu_stamps, gyro + rng.normal(0.0, 0.005, gyro.shape), R_BASE_CAM)
    with pytest.raises(ValueError, match="gyro sampling"):
        imu_time_offset(frames, index, rotations, imu_stamps, gyro, R_BASE_CAM, "trapezoid")
    frames, index, rotations, imu_stamps, gyro = _rig(0.0, 100.0, "interval_mean", seconds=4.0)
    with pytest.raises(ValueError, match=r"only 15 frame pairs"):
        imu_time_offset(frames, index, rotations, imu_stamps, gyro, R_BASE_CAM)


def test_a_wrong_rig_or_an_offset_past_the_search_is_refused():
    """No silent wrong answer from a wrong rig: the camera turned 180 deg about the vertical in the
    extrinsics (pitch and roll flipped, which match the bumps half a period off), the optical axes taken
    for the base's and a gyro in deg/s are refused with the reason; the images' yaw at half the gyro's (cars in view) is
    a note, not a refusal; clocks 0.5 s apart are found, 1.012 s apart (just past the +-1 s searched) are
    refused; an IMU gap leaves the pairs around it out (counted) and the offset stands."""
    frames, index, rotations, imu_stamps, gyro = _rig(0.012, 100.0, "interval_mean", seconds=60.0)
    turned = np.diag([-1.0, -1.0, 1.0]) @ R_BASE_CAM  # pitch and roll flipped: the bumps match half a period off
    for rig, gyro_scale in ((turned, 1.0), (np.eye(3), 1.0), (R_BASE_CAM, 180.0 / math.pi)):  # the last in deg/s
        with pytest.raises(ValueError, match=r"the images turn -?[\d.]+ times as the gyro does .* check the camera's"):
            imu_time_offset(frames, index, rotations, imu_stamps, gyro * gyro_scale, rig)
    # Moving cars in view turn their features with them: the images' yaw 0.5 of the gyro's is a note, and
    # the offset, timed by the rates' changes, stands
    damped = rotations.copy()
    damped[:, 1] *= 0.5  # the camera's y axis: the base's vertical
    got = imu_time_offset(frames, index, damped, imu_stamps, gyro, R_BASE_CAM)
    assert abs(got.offset + 0.012) < 3 * got.standard_error + 1e-4 and got.gains[2] == pytest.approx(0.5, abs=0.05)
    assert "about the vertical the images turn 0.50 times as the gyro does" in got.gain_note()
    assert imu_time_offset(frames, index, rotations, imu_stamps, gyro, R_BASE_CAM).gain_note() is None
    far = imu_time_offset(frames, index, rotations, imu_stamps + 0.5, gyro, R_BASE_CAM)
    assert abs(far.offset + 0.512) < 3 * far.standard_error + 1e-4
    with pytest.raises(ValueError, match="edge of the"):
        imu_time_offset(frames, index, rotations, imu_stamps + 1.0, gyro, R_BASE_CAM)
    whole = imu_time_offset(frames, index, rotations, imu_stamps, gyro, R_BASE_CAM)
    gap = (imu_stamps < 30.0) | (imu_stamps > 31.0)  # a second lost
    with_gap = imu_time_offset(frames, index, rotations, imu_stamps[gap], gyro[gap], R_BASE_CAM)
    assert with_gap.pairs_skipped - whole.pairs_skipped >= 25  # the lost second and the 1 s searched either side
    assert abs(with_gap.offset + 0.012) < 3 * with_gap.standard_error + 1e-4


def test_bad_input_is_refused_with_the_reason():
    frames, index, rotations, imu_stamps, gyro = _rig(0.0, 100.0, "interval_mean")
    nan_gyro = gyro.copy()
    nan_gyro[50, 1] = np.nan
    cases = [((frames[::-1], index, rotations, imu_stamps, gyro), "frames' stamps"),
             ((frames, index, rotations, imu_stamps[::-1], gyro), "IMU's stamps"),
             ((frames, index, rotations, imu_stamps, nan_gyro), "gyro must be"),
             ((frames, index, rotations, imu_stamps, gyro[:-1]), "gyro must be"),
             ((frames, index[:-1], rotations, imu_stamps, gyro), "rotations must be"),
             ((frames, index + 1, rotations, imu_stamps, gyro), "pair indices"),
             ((frames, index.astype(float), rotations, imu_stamps, gyro), "pair indices"),
             ((frames, [], np.zeros((0, 3)), imu_stamps, gyro), "only 0 frame pairs")]
    for args, reason in cases:
        with pytest.raises(ValueError, match=reason):
            imu_time_offset(*args, R_BASE_CAM)


def test_calibrate_imu_time_offset_on_rendered_drives(tmp_path, capsys):
    """End to end (``bevo calibrate --imu-time-offset``): a bumpy rendered drive (100 Hz MEMS IMU with its
    bias, 620x188 camera) written with the IMU's clock 12 ms ahead of the camera's and 30 ms behind it:
    the printed ``odometry.imu_time_offset`` is -0.012 / +0.030 s to 1.5 ms (measured -0.0120 / +0.0301,
    +- 0.4 ms)."""
    drive = preset_drive("bumpy", seed=1, duration=10.0, imu_rate=100.0, camera=kitti_like_camera(scale=0.5),
                         render="lazy")
    drive = dataclasses.replace(drive, images=np.stack([np.asarray(drive.image(k)) for k in range(drive.num_frames)]))
    got = {}
    for ahead in (0.012, -0.030):  # the camera's stamps moved the other way: the IMU ahead by that much
        shifted = dataclasses.replace(drive, frame_stamps=drive.frame_stamps - ahead)
        path = write_drive_bag(shifted, tmp_path / f"ahead{ahead:+.3f}", ground_truth=False)
        capsys.readouterr()
        assert calibrate_cmd.main([str(path), "--params", SYNTH_PARAMS, "--imu-time-offset"]) == 0
        out = capsys.readouterr().out
        got[ahead] = yaml.safe_load(out.splitlines()[1].split("#")[0])["odometry.imu_time_offset"]
        with capsys.disabled():
            print(f"\nIMU clock {ahead * 1e3:+.0f} ms ahead: {out.splitlines()[1].strip()}")
    for ahead, offset in got.items():
        assert abs(offset + ahead) < 0.0015, got


def test_jittered_imu_stamps_are_no_gap():
    """IMU stamps jittered by 3 ms at 100 Hz (a driver stamping on receipt) and a lost sample or two:
    no pair is left out for a gap (twice the median interval counted 43 gaps in 60 s and dropped 451 of
    575 pairs; a read-only review) and the offset comes back."""
    frames, index, rotations, imu_stamps, gyro = _rig(0.012, 100.0, "interval_mean", seconds=60.0)
    rng = np.random.default_rng(3)
    jittered = np.sort(imu_stamps + rng.normal(0.0, 0.003, len(imu_stamps)))
    lost = np.ones(len(imu_stamps), dtype=bool)
    lost[[1500, 1501, 3200]] = False
    got = imu_time_offset(frames, index, rotations, jittered[lost], gyro[lost], R_BASE_CAM)
    assert got.pairs + got.pairs_skipped == len(index) and got.pairs == int(0.9 * len(index))
    assert abs(got.offset + 0.012) < 3 * got.standard_error + 0.001
