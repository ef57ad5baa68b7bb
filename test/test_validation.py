"""The pure plausibility checks (bevo_ros/core/validation.py): IMU limits, camera intrinsics, the
time-jump guard; and one-line YAML errors."""
from __future__ import annotations

import math

import numpy as np
import pytest

from bevo_ros.config import (BevoConfig, CameraSettings, ConfigError, build_odometry, camera_model, imu_limits,
                             read_yaml, resolve_path)
from bevo_ros.io.learned_params import load_learned_params
from bevo_ros.core.validation import (STANDARD_GRAVITY, ImplausibleImuError, ImuLimits, TimeJumpGuard,
                                      imu_problem, intrinsics_problem)

G = STANDARD_GRAVITY
KITTI_K = np.array([[707.0912, 0.0, 601.8873], [0.0, 707.0912, 183.1104], [0.0, 0.0, 1.0]])


# ------------------------------------------------------------------------------------------ IMU
@pytest.mark.parametrize("gyro, accel, reason", [
    ((0, 0, 0), (0, 0, G), None),
    ((0.5, -0.3, 1.0), (3 * G, -2 * G, 4 * G), None),  # a hard pothole: still a car
    ((0, 0, 0), (1e30, 0, G), "imu_accel_range"),
    ((0, 0, 0), (0, 0, 100 * G), "imu_accel_range"),
    ((0, 0, 0), (6 * G, 0, 6 * G), "imu_accel_range"),  # each axis < 8 g, the norm is not
    ((0, 0, 40.0), (0, 0, G), "imu_gyro_range"),
    ((0, -1e30, 0), (0, 0, G), "imu_gyro_range"),
    ((0, 0, 0), (1e200, 1e200, 0), "imu_accel_range"),  # the norm overflows to inf
])
def test_imu_problem(gyro, accel, reason):
    got = imu_problem(gyro, accel, ImuLimits())
    assert (got[0] if got else None) == reason
    if got:
        assert "filter.max_" in got[1]


def test_engine_raises_a_value_error_with_the_reason():
    config = BevoConfig.from_flat({"camera.fx": 707.0, "camera.fy": 707.0, "camera.cx": 600.0, "camera.cy": 180.0,
                                   "camera.width": 1226, "camera.height_px": 370, "filter.max_angular_rate": 5.0})
    odo = build_odometry(config, load_learned_params(resolve_path(config.learned_params_file)))
    assert odo.imu_limits == ImuLimits(78.45, 5.0)
    odo.add_imu(0.0, (0, 0, 0), (0, 0, G))
    with pytest.raises(ImplausibleImuError) as info:
        odo.add_imu(0.01, (0, 0, 6.0), (0, 0, G))
    assert isinstance(info.value, ValueError) and info.value.reason == "imu_gyro_range"
    odo.add_imu(0.02, (0, 0, 1.0), (0, 0, G))  # the engine carries on
    assert odo.counters.imu == 2
    with pytest.raises(ConfigError, match="filter.max_acceleration must be > 0"):
        imu_limits(BevoConfig.from_flat({"filter.max_acceleration": 0.0}))


# ------------------------------------------------------------------------------------------ camera
def _k(**kw):
    K = KITTI_K.copy()
    for name, (r, c) in {"fx": (0, 0), "fy": (1, 1), "cx": (0, 2), "cy": (1, 2), "s": (0, 1), "k10": (1, 0),
                         "k22": (2, 2)}.items():
        if name in kw:
            K[r, c] = kw[name]
    return K


@pytest.mark.parametrize("K, size, fragment", [
    (_k(), (1226, 370), None),
    (_k(fx=1e-300), (1226, 370), "fx = 1e-300"),
    (_k(fx=1e30, fy=1e30), (1226, 370), "fx = 1e+30"),
    (_k(cx=1e30), (1226, 370), "principal point"),
    (_k(cy=-5.0), (1226, 370), "principal point"),
    (_k(fy=70.0), (1226, 370), "fy / fx"),
    (_k(s=300.0), (1226, 370), "skew"),
    (_k(k10=1.0), (1226, 370), "not [[fx, s, cx]"),
    (_k(k22=0.0), (1226, 370), "not [[fx, s, cx]"),
    (_k(fx=math.nan), (1226, 370), "NaN/inf"),
    (_k(), (0, 370), "image size 0x370"),
    (_k(), (10**9, 370), "not plausible"),
    (_k(), (30, 370), "fx = 707.091 px is not within"),  # the K of a larger image
])
def test_intrinsics_problem(K, size, fragment):
    got = intrinsics_problem(K, *size)
    if fragment is None:
        assert got is None
    else:
        assert got is not None and fragment in got, got


def test_camera_model_refuses_implausible_parameters():
    ok = CameraSettings(fx=707.0, fy=707.0, cx=600.0, cy=180.0, width=1226, height_px=370)
    camera_model(ok)
    with pytest.raises(ConfigError, match=r"not plausible: principal point \(600000"):
        camera_model(CameraSettings(fx=707.0, fy=707.0, cx=6e5, cy=180.0, width=1226, height_px=370))
    with pytest.raises(ConfigError, match="fx = 1e-300"):
        camera_model(ok, K=_k(fx=1e-300), width=1226, height_px=370)


# ------------------------------------------------------------------------------------------ stamps
def _feed(guard, stamps):
    return [guard.check(t, i) for i, t in enumerate(stamps)]


def test_lone_outliers_are_dropped_without_a_jump():
    g = TimeJumpGuard(max_back=1.0, max_forward=1.0, confirmations=3)
    stamps = [10.0, 10.01, 1e6, 10.02, 10.03, 0.0, 10.04, 5.0, 5.01, 10.05]  # a lone future, past, pair
    v = _feed(g, stamps)
    assert [x.accept for x in v] == [True, True, False, True, True, False, True, False, False, True]
    assert v[3].outliers == [2] and v[6].outliers == [5] and v[9].outliers == [7, 8]
    assert all(x.jump is None for x in v) and g.ref == 10.05
    # small steps back are the consumer's to drop; they are not jumps
    assert g.check(9.5).accept and g.ref == 10.05


@pytest.mark.parametrize("offset, direction", [(-100.0, "back"), (+100.0, "forward")])
def test_a_confirmed_jump_releases_every_held_message(offset, direction):
    g = TimeJumpGuard(max_back=1.0, max_forward=1.0, confirmations=3)
    v = _feed(g, [10.0, 10.01, 10.02] + [10.03 + offset + 0.01 * k for k in range(4)])
    assert [x.accept for x in v] == [True, True, True, False, False, False, True]
    assert v[5].jump == direction and v[5].release == [3, 4, 5] and v[5].jump_size == pytest.approx(abs(offset + 0.01))
    assert v[6].jump is None and not v[6].outliers
    assert g.ref == pytest.approx(10.06 + offset)


def test_a_second_wild_stamp_makes_the_first_an_outlier_and_one_confirmation_accepts_at_once():
    g = TimeJumpGuard(1.0, 1.0, 2)
    v = _feed(g, [0.0, 50.0, 900.0, 900.1])
    assert v[2].outliers == [1] and v[3].jump == "forward" and v[3].release == [2, 3]
    g1 = TimeJumpGuard(1.0, 1.0, 1)
    assert g1.check(0.0).accept and g1.check(-50.0).jump == "back"
    g.check(1000.0, "held")
    assert g.reset() == ["held"] and g.ref is None and g.check(-3.0).accept


def test_rebase_moves_a_stream_to_the_timeline_another_stream_confirmed():
    g = TimeJumpGuard(1.0, 1.0, 3)
    _feed(g, [100.0, 100.1, 50.0])  # 50.0: the start of a restarted bag, held
    g.held.append((7.0, "wild"))
    release, outliers = g.rebase(50.02)
    assert release == [2] and outliers == ["wild"] and g.ref == 50.02 and g.check(50.1).accept


# ------------------------------------------------------------------------------------------ YAML
def test_a_yaml_syntax_error_is_one_line_naming_the_file(tmp_path):
    bad = tmp_path / "learned.yaml"
    bad.write_text("format: bevo_learned_params/1\nprocess_noise_density: {pitch: 1e-4\n  roll: [\n")
    with pytest.raises(ConfigError) as info:
        read_yaml(bad, "learned-parameters file")
    text = str(info.value)
    assert "\n" not in text and str(bad) in text and "not valid YAML: line " in text, text
