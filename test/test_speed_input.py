"""A vehicle speed from outside the images (wheel odometry, CAN, GNSS): ``speed_topic``.

* ``forward_speed_from_msg``: which number of which message, signed or not, its variance.
* The motion filter's speed measurement: float and tensor forms agree; a wrong speed is gated.
* The engine's mean over the frame interval (``BevoOdometry._external_speed``).
* ``bevo run --speed-topic`` on a synthetic drive: the per-frame error falls to the speed's, the
  scale follows the speed (a wheel 2 % long: 2 % long); a topic the bag lacks is refused.
(The node's ``speed_topic`` equals the offline core: ``test_node_inprocess``.)
"""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from bevo_ros.commands import run
from bevo_ros.config import REPO_ROOT, BevoConfig, build_odometry
from bevo_ros.core.vehicle_filter import VehicleFilter, VehicleNoise, initial_vehicle_state
from bevo_ros.datasets.rosbag import write_drive_bag
from bevo_ros.datasets.synthetic import kitti_like_camera, make_drive
from bevo_ros.io import bag
from bevo_ros.io.learned_params import LearnedParams
from bevo_ros.io.ros_conversions import forward_speed_from_msg

SYNTH_PARAMS = REPO_ROOT / "params" / "synthetic.yaml"


def test_the_speed_of_each_message_type():
    types = bag.typestore().types
    odom = bag.odometry_message(1.0, np.eye(4), "odom", "base_link", twist=(-2.5, 0.3, 0, 0, 0, 0))
    assert forward_speed_from_msg(odom, "base_link", 0.04) == (-2.5, 0.04, True)  # in the base: linear.x, signed
    assert forward_speed_from_msg(odom, "/base_link", 0.04) == (-2.5, 0.04, True)
    enu = bag.twist_stamped_message(1.0, (3.0, -4.0, 0.2), "enu")  # a GNSS velocity: the horizontal speed
    assert forward_speed_from_msg(enu, "base_link", 0.04) == (5.0, 0.04, False)  # unsigned
    cov = np.zeros(36)
    cov[0] = 0.09
    twc = types["geometry_msgs/msg/TwistWithCovarianceStamped"](
        header=enu.header, twist=types["geometry_msgs/msg/TwistWithCovariance"](twist=enu.twist, covariance=cov))
    assert forward_speed_from_msg(twc, "base_link", 0.04) == (5.0, 0.09, False)  # its own variance
    bad = bag.twist_stamped_message(1.0, (float("nan"), 0.0, 0.0), "base_link")
    with pytest.raises(ValueError, match="not a finite speed"):
        forward_speed_from_msg(bad, "base_link", 0.04)
    with pytest.raises(ValueError, match="variance"):
        forward_speed_from_msg(enu, "base_link", float("nan"))


def test_the_filter_takes_the_speed_in_float_and_tensor_form_and_gates_a_wrong_one():
    f = VehicleFilter(VehicleNoise())
    sf, st = initial_vehicle_state(), initial_vehicle_state(like=torch.zeros(2, dtype=torch.float64))
    rng = np.random.default_rng(1)
    for _ in range(15):  # 10 m/s; the images read 5 % long, the speed is right
        speed = 10.0 + float(rng.normal(0, 0.02))
        a = f.step(sf, 0.1, 0.0, forward=1.05, forward_var=4e-4, speed=speed, speed_var=1e-3)
        T = lambda v: torch.tensor(v, dtype=torch.float64).expand(2)  # noqa: E731
        b = f.step(st, 0.1, T(0.0), forward=T(1.05), forward_var=T(4e-4), speed=T(speed), speed_var=T(1e-3))
        for x, y in zip(a.motion + a.variance, b.motion + b.variance):
            assert float(y[0]) == pytest.approx(x, rel=1e-12, abs=1e-15)
        assert a.speed_accepted is True and bool(b.speed_accepted[0])
        sf, st = a.state, b.state
    assert a.motion[0] == pytest.approx(1.0, abs=0.01)  # the speed, not the images' 5 %
    wrong = f.step(sf, 0.1, 0.0, forward=1.0, forward_var=4e-4, speed=25.0, speed_var=1e-3)
    assert wrong.speed_accepted is False and wrong.motion[0] == pytest.approx(1.0, abs=0.01)
    assert f.step(sf, 0.1, 0.0, forward=1.0, forward_var=4e-4).speed_accepted is None  # no speed given


def test_the_engine_takes_the_speeds_mean_over_the_frame_interval():
    odo = build_odometry(BevoConfig(), LearnedParams(), camera=kitti_like_camera(scale=0.5))
    assert odo._external_speed(0.0, 0.1) is None  # none given
    for k in range(11):  # 50 Hz, a speed rising 1 m/s per second from 10 m/s
        odo.add_speed(0.02 * k, 10.0 + 0.02 * k, 0.01 + 0.001 * k)
    mean, var = odo._external_speed(0.03, 0.13)  # between samples at both ends: linear between them
    assert mean == pytest.approx(10.08, abs=1e-9) and 0.01 < var < 0.02
    assert odo._external_speed(0.21, 0.3)[0] == pytest.approx(10.2)  # past the last: held for max_speed_age
    assert odo._external_speed(0.8, 0.9) is None  # older than max_speed_age: none
    with pytest.raises(Exception, match="not after"):
        odo.add_speed(0.1, 10.0)
    with pytest.raises(ValueError, match="finite"):
        odo.add_speed(0.3, float("inf"))
    odo.reset()
    assert odo._external_speed(0.03, 0.13) is None  # a reset forgets them


@pytest.fixture(scope="module")
def drive():
    return make_drive(seed=4, duration=6.0, render="lazy", camera=kitti_like_camera(), curvature=0.3)


def _motions(out_dir, name: str = "trajectory_kitti.txt") -> np.ndarray:
    """Each frame's translation in the previous camera frame, from ``bevo run``'s KITTI-format poses."""
    P = np.loadtxt(out_dir / name).reshape(-1, 3, 4)
    T = np.tile(np.eye(4), (len(P), 1, 1))
    T[:, :3] = P
    return np.array([(np.linalg.inv(a) @ b)[:3, 3] for a, b in zip(T[:-1], T[1:])])


def test_bevo_run_fuses_a_speed_topic(drive, tmp_path, capsys):
    exact = write_drive_bag(drive, tmp_path / "exact", wheel_odometry_topic="/wheel/odometry")
    long = write_drive_bag(drive, tmp_path / "long", wheel_odometry_topic="/wheel/odometry", wheel_speed_scale=1.02)
    gt, got = None, {}
    for name, path, extra in (("images", exact, []), ("speed", exact, ["--speed-topic", "/wheel/odometry"]),
                              ("speed 2 % long", long, ["--speed-topic", "/wheel/odometry"])):
        out = tmp_path / name.replace(" ", "_")
        assert run.main([str(path), "--out", str(out), "--params", str(SYNTH_PARAMS), "-q"] + extra) == 0
        printed = capsys.readouterr().out
        assert ("speed 0 (of /wheel/odometry)" in printed) == bool(extra), printed
        m = _motions(out)
        if gt is None:
            gt = _motions(out, "gt_kitti.txt")
        dist = np.linalg.norm(m, axis=1)
        true = np.linalg.norm(gt, axis=1)
        got[name] = (100 * math.sqrt(np.mean(np.sum((m - gt) ** 2, axis=1))), 100 * (dist.sum() / true.sum() - 1))
    with capsys.disabled():
        print("\n" + "; ".join(f"{k}: {v[0]:.2f} cm per frame, path {v[1]:+.2f} %" for k, v in got.items()))
    assert got["speed"][0] < 0.3 * got["images"][0]
    assert abs(got["speed"][1]) < 0.3 and 1.5 < got["speed 2 % long"][1] < 2.5
    assert run.main([str(exact), "--out", str(tmp_path / "x"), "--params", str(SYNTH_PARAMS), "-q",
                     "--speed-topic", "/imu/data"]) == 2
    assert "speed_topic /imu/data is not in the bag as one of" in capsys.readouterr().err


def test_read_speed_reads_a_bag_as_the_node_does_and_a_reversing_stretch_counts_back(tmp_path):
    """``bevo calibrate --speed-topic`` reads a bag's speeds with the node's rule: in base_frame signed,
    else the horizontal speed, unsigned (and the command says so). On the parking drive's reversing stretch the
    signed wheel speed gives the ground truth's distance (negative), the distance the calibration matches
    the BEV's to; read unsigned, as before, it was the opposite one."""
    from bevo_ros.datasets.rosbag import RigSettings, load_sequence
    from bevo_ros.config import load_config
    from bevo_ros.training.mounting import reference_from_ground_truth, reference_from_speed

    path = tmp_path / "speeds"
    with bag.BagWriter(path) as w:
        for k, v in enumerate((1.0, 0.0, -1.5)):
            w.write("/wheel", bag.ODOMETRY_MSG, bag.odometry_message(
                1.0 + k, np.eye(4), "odom", "base_link", twist=(v, 0.2, 0, 0, 0, 0)), 1.0 + k)
            w.write("/gnss", bag.TWIST_STAMPED_MSG, bag.twist_stamped_message(1.0 + k, (3.0 * v, 4.0, 0.0), "enu"),
                    1.0 + k)
        w.write("/bad", bag.TWIST_STAMPED_MSG, bag.twist_stamped_message(1.0, (math.nan, 0.0, 0.0), "base_link"), 1.0)
        w.write("/mixed", bag.ODOMETRY_MSG, bag.odometry_message(1.0, np.eye(4), "odom", "base_link",
                                                                 twist=(1.0, 0, 0, 0, 0, 0)), 1.0)
        w.write("/mixed", bag.ODOMETRY_MSG, bag.odometry_message(2.0, np.eye(4), "odom", "gps",
                                                                 twist=(1.0, 0, 0, 0, 0, 0)), 2.0)
        twc = bag.typestore().types["geometry_msgs/msg/TwistWithCovarianceStamped"]
        cov = np.zeros(36)
        cov[0] = math.inf  # a speed whose variance no one knows: read, the variance is not
        for k in range(2):
            w.write("/cov", "geometry_msgs/msg/TwistWithCovarianceStamped", twc(
                header=bag.twist_stamped_message(1.0 + k, (0, 0, 0), "base_link").header,
                twist=bag.typestore().types["geometry_msgs/msg/TwistWithCovariance"](
                    twist=bag.twist_stamped_message(1.0, (-2.0, 0.0, 0.0), "base_link").twist, covariance=cov)), 1.0 + k)
    t, v, signed = bag.read_speed(path, "/wheel")
    assert signed and t.tolist() == [1.0, 2.0, 3.0] and v.tolist() == [1.0, 0.0, -1.5]
    t, v, signed = bag.read_speed(path, "/gnss")
    assert not signed and v == pytest.approx([5.0, 4.0, math.hypot(4.5, 4.0)], abs=1e-12)
    t, v, signed = bag.read_speed(path, "/wheel", base_frame="vehicle")  # another base: not its frame
    assert not signed and v == pytest.approx([math.hypot(1.0, 0.2), 0.2, math.hypot(1.5, 0.2)], abs=1e-12)
    with pytest.raises(bag.BagError, match=r"topic /bad holds a speed that is not finite \(nan m/s at 1\.000000 s\)"):
        bag.read_speed(path, "/bad")
    with pytest.raises(bag.BagError, match="mixes twists in base_frame 'base_link' with twists in 'gps'"):
        bag.read_speed(path, "/mixed")
    t, v, signed = bag.read_speed(path, "/cov")
    assert signed and v.tolist() == [-2.0, -2.0]

    drive = make_drive(seed=1, preset="parking", render="lazy", noise=False, camera=kitti_like_camera())
    reverse = write_drive_bag(drive, tmp_path / "reverse", frame_range=(64, 106), wheel_odometry_topic="/wheel/odometry")
    config, _ = load_config(SYNTH_PARAMS)
    seq = load_sequence(reverse, config, rig=RigSettings(extrinsics_from_tf=False))
    truth = reference_from_ground_truth(seq)
    t, v, signed = bag.read_speed(reverse, "/wheel/odometry")
    assert signed and v.min() < -1.4 and truth[0] < -3.0
    by_speed = reference_from_speed(seq, t, v)
    assert by_speed.distance == pytest.approx(truth[0], rel=3e-3), (by_speed.distance, truth[0])
    assert reference_from_speed(seq, t, np.abs(v)).distance == pytest.approx(-truth[0], rel=3e-3)  # the old reading
