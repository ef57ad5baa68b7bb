"""KITTI readers: calibration sanity against the data README, OXTS parsing, poses, relative motion."""
from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest

from bevo_ros.datasets import kitti

DRIVE = "2011_09_30_drive_0020"


def _oxts_dir(root: Path) -> Path:
    return root / "raw" / "2011_09_30" / f"{DRIVE}_sync" / "oxts"


def _small_oxts_copy(root: Path, dst: Path, n: int = 5) -> Path:
    """The first ``n`` OXTS records in a writable tmp copy."""
    src = _oxts_dir(root)
    (dst / "data").mkdir(parents=True)
    lines = (src / "timestamps.txt").read_text().splitlines()[:n]
    (dst / "timestamps.txt").write_text("\n".join(lines) + "\n")
    for i in range(n):
        shutil.copy(src / "data" / f"{i:010d}.txt", dst / "data" / f"{i:010d}.txt")
    return dst


# ---------------------------------------------------------------------------------------------
# Pure parsing (no data needed)
# ---------------------------------------------------------------------------------------------
def test_timestamp_parsing_is_exact():
    ns = kitti.parse_timestamp_ns("2011-09-30 12:08:26.521831936")
    # 2011-09-30 00:00:00 UTC = 1317340800 s (days since epoch 15247 * 86400).
    assert ns == (1317340800 + 12 * 3600 + 8 * 60 + 26) * 10**9 + 521831936
    assert kitti.parse_timestamp_ns("2011-09-30 12:08:26.5") % 10**9 == 500_000_000
    with pytest.raises(ValueError, match="f.txt:7"):
        kitti.parse_timestamp_ns("2011-09-30 12:08", "f.txt", 7)


def test_pose_roundtrip_and_errors(tmp_path):
    rng = np.random.default_rng(0)
    poses = np.tile(np.eye(4), (4, 1, 1))
    for T in poses:
        q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
        T[:3, :3] = q * np.sign(np.linalg.det(q))
        T[:3, 3] = rng.normal(size=3) * 100
    path = tmp_path / "p.txt"
    kitti.write_poses(path, poses)
    back = kitti.read_poses(path)
    err = np.abs(back - poses).max()
    print(f"pose write/read max abs error {err:.2e}")
    assert err < 1e-6
    path.write_text(path.read_text() + "1 2 3\n")
    with pytest.raises(ValueError, match=r"p.txt:5: expected 12 numbers, found 3"):
        kitti.read_poses(path)
    with pytest.raises(FileNotFoundError, match="nope.txt"):
        kitti.read_poses(tmp_path / "nope.txt")


def test_relative_motion_of_a_known_base_trajectory():
    """A base moving on a circle (v, w) gives dx = R sin(w dt), dy = R (1 - cos(w dt)), dyaw = w dt."""
    T_base_cam = np.eye(4)
    # Optical camera: z forward (= base x), x right (= -base y), y down (= -base z), 0.7 m up.
    T_base_cam[:3, :3] = np.array([[0, 0, 1], [-1, 0, 0], [0, -1, 0]], dtype=float)
    T_base_cam[:3, 3] = [1.0, -0.3, 0.7]
    v, w, dt, n = 10.0, 0.2, 0.1, 20
    yaw = w * dt * np.arange(n)
    radius = v / w
    base = np.tile(np.eye(4), (n, 1, 1))
    base[:, 0, 0], base[:, 0, 1], base[:, 1, 0], base[:, 1, 1] = np.cos(yaw), -np.sin(yaw), np.sin(yaw), np.cos(yaw)
    base[:, 0, 3], base[:, 1, 3] = radius * np.sin(yaw), radius * (1 - np.cos(yaw))
    cam = base @ T_base_cam  # T_world_cam, world = odom
    cam = kitti.invert_rigid(cam[0]) @ cam  # KITTI style: the first camera pose is the identity
    motion = kitti.base_relative_motion(cam, T_base_cam)
    expected = np.array([radius * np.sin(w * dt), radius * (1 - np.cos(w * dt)), w * dt])
    err = np.abs(motion - expected).max()
    print(f"circle: motion[0] = {motion[0]}, expected {expected}, max err {err:.2e}")
    assert motion.shape == (n - 1, 3)
    assert err < 1e-9
    recovered = kitti.base_poses(cam, T_base_cam)
    assert np.abs(recovered - base).max() < 1e-9


# ---------------------------------------------------------------------------------------------
# The real sample
# ---------------------------------------------------------------------------------------------
@pytest.mark.kitti
def test_calibration_sanity(kitti_root):
    """README: camera centre ~0.73 m above the IMU, optical axis ~0.48 deg off the IMU x axis."""
    T_cam_imu = kitti.imu_to_camera_extrinsics(kitti_root / "raw" / "2011_09_26")
    T_base_cam = kitti.invert_rigid(T_cam_imu)
    R = T_base_cam[:3, :3]
    assert np.abs(R @ R.T - np.eye(3)).max() < 1e-12  # taken to the nearest rotation (KITTI's product: 5e-8)
    assert np.linalg.det(R) > 0
    axis = R[:, 2]  # optical axis in the base frame
    height = T_base_cam[2, 3]
    # geometry.py convention: positive pitch = nose down, so a downward-looking axis has pitch > 0.
    pitch_deg = np.degrees(np.arctan2(-axis[2], axis[0]))
    angle_deg = np.degrees(np.arccos(axis[0]))
    print(f"camera centre in base: {T_base_cam[:3, 3].round(4)} m; height above IMU {height:.4f} m; "
          f"optical-axis pitch {pitch_deg:+.3f} deg, angle to IMU x {angle_deg:.3f} deg")
    assert abs(height - 0.73) < 0.01
    assert abs(abs(pitch_deg) - 0.48) < 0.02
    assert angle_deg < 1.0  # the optical axis looks along the IMU x axis
    assert axis[0] > 0.99 and R[1, 0] < -0.99  # camera x (right) = -base y


@pytest.mark.kitti
def test_other_camera_differs_by_the_baseline(kitti_root):
    d = kitti_root / "raw" / "2011_09_26"
    T0, T1 = kitti.imu_to_camera_extrinsics(d, 0), kitti.imu_to_camera_extrinsics(d, 1)
    delta = T1 @ kitti.invert_rigid(T0)
    print(f"cam1 <- cam0 translation {delta[:3, 3].round(4)} m")
    assert np.allclose(delta[:3, :3], np.eye(3), atol=1e-5)  # calib R is rounded to 7 digits
    assert abs(delta[0, 3] + 0.537) < 0.01  # stereo baseline ~0.54 m


@pytest.mark.kitti
def test_odometry_calib_and_camera_model(kitti_root):
    seq = kitti_root / "odometry" / "sequences" / "06"
    calib = kitti.read_odometry_calib(seq / "calib.txt")
    assert set(calib) == {"P0", "P1"} and calib["P0"].shape == (3, 4)
    model = kitti.camera_model_from_kitti(seq / "calib.txt", kitti_root / "raw" / "2011_09_26", (1226, 370))
    print(f"K =\n{model.K}\nsize {model.width}x{model.height_px}, height {model.mount_height} m")
    assert model.K[0, 0].item() == pytest.approx(707.0912) and model.K[1, 2].item() == pytest.approx(183.1104)
    assert (model.width, model.height_px) == (1226, 370)
    assert model.T_base_cam[2, 3].item() == pytest.approx(0.7299, abs=1e-3)


def test_interpolated_oxts_records_are_found_exactly():
    """Records on the straight line through their neighbours in all six IMU channels (KITTI's fill
    over lost packets) are flagged; noisy records, the first and the last never are."""
    rng = np.random.default_rng(3)
    n = 40
    data = np.zeros((n, len(kitti.OXTS_FIELDS)))
    data[:, 11:14] = [0.3, -0.1, 9.8] + 0.05 * rng.standard_normal((n, 3))
    data[:, 17:20] = 0.01 * rng.standard_normal((n, 3))
    data[:, 11:20] += np.linspace(0.0, 0.5, n)[:, None]  # a smooth trend is still noisy: never flagged

    def fill(a, b):  # KITTI's linear fill between real records a and b
        w = np.linspace(0.0, 1.0, b - a + 1)[1:-1, None]
        data[a + 1:b] = (1 - w) * data[a] + w * data[b]

    fill(0, 6)    # a run from the very first record: records 1-5
    fill(20, 22)  # one lost packet: record 21
    fill(30, 39)  # a run up to the last record: records 31-38
    oxts = kitti.OxtsData(np.arange(n, dtype=np.int64) * 100_000_000, data)
    assert np.flatnonzero(kitti.interpolated_oxts(oxts)).tolist() == [1, 2, 3, 4, 5, 21, *range(31, 39)]
    one_channel = data.copy()
    one_channel[21, 19] += 1e-6  # five channels on the line, the sixth off it: a measurement
    assert 21 not in np.flatnonzero(kitti.interpolated_oxts(kitti.OxtsData(oxts.stamps_ns, one_channel)))
    assert not kitti.interpolated_oxts(oxts.slice(0, 2)).any()


def test_bridged_imu_integrates_to_the_units_attitude_and_velocity_change():
    """A run of KITTI's interpolated records gets rates and accelerations that meet the real records
    at both ends and integrate to the unit's own change across the run (what its INS integrated over
    the lost packets): the rotation between its attitudes and its velocity change. On an S-bend's
    1.5 s the line's heading is 20 deg off, the bridge's records integrate to the unit's turn; the
    line's lateral acceleration's mean is 2.7 m/s^2 off, the bridge's 0.1; the same with the world
    turned so that the heading wraps at +-pi in the run; real records keep their values; a run with a
    misstamped end or an impossible turn keeps the line."""
    from scipy.spatial.transform import Rotation

    from bevo_ros.core.vehicle_dynamics import GRAVITY

    def rates(t):  # (..., 3) body rates of an S-bend with a little roll and pitch, rad/s
        return np.stack([0.05 * np.cos(2 * np.pi * 0.7 * t), 0.03 * np.sin(2 * np.pi * 0.5 * t),
                         0.3 * np.sin(2 * np.pi * 0.4 * t)], -1)

    speed = 12.0  # m/s along the body's x, constant: the specific force is w x v + gravity
    n, fine = 40, 100  # records at 10 Hz, integrated at 1 kHz
    # a start away from level and north: a nav-frame rotation vector would not pass for the body's
    R, attitude, velocity, force = Rotation.from_euler("ZYX", np.radians([90.0, 3.0, 5.0])), [], [], []
    for k in range(n):
        attitude.append(R)
        velocity.append(R.apply([speed, 0.0, 0.0]))
        w = rates(np.array(k * 0.1))
        force.append(np.cross(w, [speed, 0.0, 0.0]) + R.inv().apply([0.0, 0.0, GRAVITY]))
        t = k * 0.1 + (np.arange(fine) + 0.5) * 0.1 / fine  # midpoints
        for w in rates(t):
            R = R * Rotation.from_rotvec(w * 0.1 / fine)
    yaw, pitch, roll = np.array([a.as_euler("ZYX") for a in attitude]).T
    data = np.zeros((n, len(kitti.OXTS_FIELDS)))
    data[:, 3], data[:, 4], data[:, 5] = roll, pitch, yaw
    for name, column in zip(("ve", "vn", "vu"), np.array(velocity).T):
        data[:, kitti.OXTS_INDEX[name]] = column
    data[:, 11:14] = force
    data[:, 17:20] = rates(np.arange(n) * 0.1)
    truth = data[:, 11:20].copy()

    def fill(a, b):  # KITTI's linear fill of every channel between real records a and b
        w = np.linspace(0.0, 1.0, b - a + 1)[1:-1, None]
        data[a + 1:b] = (1 - w) * data[a] + w * data[b]

    fill(10, 25)  # records 11-24, through the bend's change of direction
    fill(30, 32)  # one lost packet
    stamps = np.arange(n, dtype=np.int64) * 100_000_000
    oxts = kitti.OxtsData(stamps, data)
    interpolated = kitti.interpolated_oxts(oxts)
    assert kitti.interpolated_runs(interpolated) == [(11, 25), (31, 32)]
    gyro, accel, bridged = kitti.bridged_imu(oxts, interpolated)
    assert bridged == [(11, 25), (31, 32)]
    assert np.array_equal(gyro[~interpolated], data[~interpolated, 17:20])  # real records as they are
    assert np.array_equal(accel[~interpolated], data[~interpolated, 11:14])
    t = stamps * 1e-9
    turn = (attitude[10].inv() * attitude[25]).as_rotvec()
    line_turn, bridged_turn = (np.trapezoid(g[10:26], t[10:26], axis=0) for g in (data[:, 17:20], gyro))
    print(f"turn over 10..25 (deg): unit {np.degrees(turn).round(3)}, line {np.degrees(line_turn).round(3)}, "
          f"bridged {np.degrees(bridged_turn).round(3)}")
    assert np.abs(line_turn - turn).max() > np.radians(2.0)
    assert np.abs(bridged_turn - turn).max() < np.radians(1e-6)  # the records' trapezoid has the unit's mean
    true_force, line_force, bridged_force = (np.trapezoid(a[10:26], t[10:26], axis=0) / 1.5
                                             for a in (truth[:, :3], data[:, 11:14], accel))
    print(f"mean specific force over 10..25 (m/s^2): truth {true_force.round(3)}, line {line_force.round(3)}, "
          f"bridged {bridged_force.round(3)}")
    assert np.abs(line_force - true_force).max() > 1.0
    # the body-frame mean rotated through KITTI's linear fill of the attitude, not the true path: ~0.1 m/s^2
    assert np.abs(bridged_force - true_force).max() < 0.2
    # and the values themselves nearer the truth than the line, sample by sample
    for channels, x in ((slice(0, 3), accel), (slice(6, 9), gyro)):
        line_err, bridged_err = (np.sqrt(np.mean((v[11:25] - truth[11:25, channels]) ** 2))
                                 for v in (data[:, 11:20][:, channels], x))
        assert bridged_err < 0.5 * line_err, (channels, bridged_err, line_err)
    # the same drive with the world turned so that the run's heading crosses +-pi (KITTI's linear fill
    # of the yaw field then sweeps the long way round): the body's rates and forces are the same
    turned = data.copy()
    turn_by = np.pi - yaw[18]
    turned[:, 5] = np.angle(np.exp(1j * (yaw + turn_by)))
    c, s_ = np.cos(turn_by), np.sin(turn_by)
    ve, vn = data[:, kitti.OXTS_INDEX["ve"]], data[:, kitti.OXTS_INDEX["vn"]]
    turned[:, kitti.OXTS_INDEX["ve"]], turned[:, kitti.OXTS_INDEX["vn"]] = c * ve - s_ * vn, s_ * ve + c * vn
    assert np.ptp(turned[10:26, 5]) > np.pi  # the fill wraps
    gyro_t, accel_t, bridged_t = kitti.bridged_imu(kitti.OxtsData(stamps, turned), interpolated)
    assert bridged_t == bridged
    np.testing.assert_allclose(gyro_t, gyro, atol=1e-9)
    np.testing.assert_allclose(accel_t, accel, atol=1e-9)
    # an end stamped out of order (a duplicate, a late one), or a turn no car makes in 1.5 s: the line stays
    for late_by in (-100_000_000, 300_000_000):
        late = stamps.copy()
        late[25] += late_by
        assert kitti.bridged_imu(kitti.OxtsData(late, data), interpolated)[2] == [(31, 32)], late_by
    spun = data.copy()
    spun[25:, 5] += np.radians(60.0)
    assert kitti.bridged_imu(kitti.OxtsData(stamps, spun), interpolated)[2] == [(31, 32)]


@pytest.mark.kitti
def test_interpolated_records_of_the_shared_drives(kitti_root):
    """The shared drives' synced OXTS: 0020 (the sample's drive) records 1-11 ramp the yaw rate
    linearly from 2.75 to 0.64 deg/s; 0018 has 14 at 1500 and one at 2162; 0016, 0027 none."""
    found = {}
    for drive in ("0016", "0018", "0020", "0027"):
        oxts = kitti.read_oxts(kitti_root / "raw" / "2011_09_30" / f"2011_09_30_drive_{drive}_sync" / "oxts")
        found[drive] = np.flatnonzero(kitti.interpolated_oxts(oxts)).tolist()
    print(found)
    assert found == {"0016": [], "0018": [*range(1500, 1514), 2162], "0020": list(range(1, 12)), "0027": []}


@pytest.mark.kitti
def test_read_oxts(kitti_root):
    oxts = kitti.read_oxts(_oxts_dir(kitti_root))
    dt = np.diff(oxts.stamps)
    print(f"{len(oxts)} OXTS records, dt {dt.mean():.4f} s (min {dt.min():.4f}, max {dt.max():.4f}); "
          f"roll0 {np.degrees(oxts.roll[0]):.3f} deg, pitch0 {np.degrees(oxts.pitch[0]):.3f} deg, "
          f"|a|0 {np.linalg.norm(oxts.accel[0]):.3f} m/s^2")
    assert oxts.data.shape == (1104, 30)
    assert oxts.accel.shape == (1104, 3) and oxts.gyro.shape == (1104, 3)
    assert oxts.stamps.dtype == np.float64
    # First record of the file, parsed exactly.
    assert oxts.stamps_ns[0] % 10**9 == 521831936
    assert oxts.accel[0] == pytest.approx([-0.24564946046682, 2.29976693059022, 9.60400659891081])
    assert oxts.gyro[0] == pytest.approx([-0.02776516775726, 0.00852361897934, 0.04793661907718])
    assert abs(np.degrees(oxts.roll[0]) - 2.6) < 0.1  # README: ~2.6 deg road camber at the start
    assert 0.09 < dt.mean() < 0.11
    assert 9.6 < np.linalg.norm(oxts.accel[0]) < 10.0


@pytest.mark.kitti
def test_corrupt_oxts_line_names_file_and_line(kitti_root, tmp_path):
    d = _small_oxts_copy(kitti_root, tmp_path / "oxts")
    assert len(kitti.read_oxts(d)) == 5
    bad = d / "data" / "0000000003.txt"
    bad.write_text(bad.read_text().replace("4.00000000000000", "4.0x", 1))
    with pytest.raises(ValueError, match=r"0000000003\.txt:1: cannot parse") as err:
        kitti.read_oxts(d)
    print(err.value)
    bad.write_text("1 2 3\n")
    with pytest.raises(ValueError, match=r"0000000003\.txt:1: expected 30 numbers, found 3"):
        kitti.read_oxts(d)
    (d / "timestamps.txt").write_text("2011-09-30 12:08:26.5\n\n2011-09-30 12:08:26.6\n")
    with pytest.raises(ValueError, match=r"timestamps\.txt:2: empty timestamp line"):
        kitti.read_oxts(d)
    (d / "timestamps.txt").write_text("2011-09-30 12:08:26.5\nnot a time\n")
    with pytest.raises(ValueError, match=r"timestamps\.txt:2: cannot parse timestamp"):
        kitti.read_oxts(d)


@pytest.mark.kitti
def test_poses_and_motion_consistent_with_oxts(kitti_root):
    """GT base motion vs the OXTS over the whole drive: path length vs the integral of vf, GT yaw
    vs the OXTS heading. (Per-step speeds differ by a few %: the OXTS stamps jitter by +-25 ms
    while the GT is sampled at the camera triggers, so only integrals are compared.)"""
    poses = kitti.read_poses(kitti_root / "odometry" / "poses" / "06.txt")
    _, drive, start, end = kitti.raw_drive_for_sequence("06")
    assert drive == DRIVE and poses.shape == (end - start + 1, 4, 4)
    assert np.allclose(poses[0], np.eye(4), atol=1e-9)
    T_base_cam = kitti.invert_rigid(kitti.imu_to_camera_extrinsics(kitti_root / "raw" / "2011_09_26"))
    motion = kitti.base_relative_motion(poses, T_base_cam)
    base = kitti.base_poses(poses, T_base_cam)
    oxts = kitti.read_oxts(_oxts_dir(kitti_root)).slice(start, end + 1)
    dt = np.diff(oxts.stamps)
    vf = oxts.field("vf")
    path_gt = np.hypot(motion[:, 0], motion[:, 1]).sum()
    path_oxts = np.sum(0.5 * (vf[1:] + vf[:-1]) * dt)
    yaw_gt = np.unwrap(np.arctan2(base[:, 1, 0], base[:, 0, 0]))
    yaw_oxts = np.unwrap(oxts.yaw - oxts.yaw[0])
    yaw_err = np.degrees(np.abs(yaw_gt - yaw_oxts)).max()
    sum_err = np.degrees(np.abs(np.cumsum(motion[:, 2]) - yaw_gt[1:])).max()
    lateral = np.median(np.abs(motion[:, 1]) / np.maximum(np.abs(motion[:, 0]), 1e-6))
    print(f"seq 06: {len(motion)} steps, GT path {path_gt:.1f} m vs OXTS integral {path_oxts:.1f} m "
          f"(ratio {path_gt / path_oxts:.4f}); total yaw {np.degrees(yaw_gt[-1]):.1f} deg, "
          f"max |GT yaw - OXTS yaw| {yaw_err:.3f} deg, max |cumsum(dyaw) - yaw| {sum_err:.3f} deg; "
          f"median |dy/dx| {lateral:.4f}")
    assert abs(path_gt / path_oxts - 1.0) < 0.01
    assert yaw_err < 1.0
    assert sum_err < 1.0  # dyaw of a slightly tilted base only approximates the heading change
    assert lateral < 0.02  # the base moves along its own x axis: the extrinsics are right


def test_raw_calibration_search_prefers_the_day_then_the_nearest(tmp_path):
    """find_raw_calib_dir: the drive's own day, else the nearest other day (the earlier on a tie; a
    date-like name that is no date last), else without a date the newest. No data needed."""
    for day in ("2011_09_26", "2011_09_29", "2011_10_03", "2011_99_99"):
        (tmp_path / day).mkdir()
        for name in ("calib_imu_to_velo.txt", "calib_velo_to_cam.txt", "calib_cam_to_cam.txt"):
            (tmp_path / day / name).write_text("x\n")
    drive = tmp_path / "2011_09_30" / "2011_09_30_drive_0020_sync"
    drive.mkdir(parents=True)
    assert kitti.find_raw_calib_dir(drive, "2011_09_30").name == "2011_09_29"
    assert kitti.find_raw_calib_dir(drive, "2011_10_01").name == "2011_09_29"  # 2 days either way: the earlier
    assert kitti.find_raw_calib_dir(drive, "2011_10_03").name == "2011_10_03"
    assert kitti.find_raw_calib_dir(drive, None).name == "2011_99_99"  # no date: the newest name
    (tmp_path / "2011_09_30" / "calib_imu_to_velo.txt").write_text("x\n")  # a partial set is no calibration
    assert kitti.find_raw_calib_dir(drive, "2011_09_30").name == "2011_09_29"


def test_misstamped_leaves_out_the_fewest_records():
    """The records outside the longest strictly increasing run of stamps: one late stamp is that record
    alone (a running maximum would take every good record after it), a duplicate is the later one."""
    from bevo_ros.datasets.kitti import misstamped

    cases = {(0, 1, 2, 2, 4): [3], (0, 1, 2, 30, 4, 5, 6): [3], (0, 1, -5, 3, 4): [2], (0, 10, 20, 15, 16, 17, 30): [2],
             (5,): [], (): [], (0, 1, 2): []}
    for stamps, bad in cases.items():
        assert np.flatnonzero(misstamped(np.array(stamps, dtype=np.int64))).tolist() == bad, stamps
