"""bevo convert on the real KITTI sample: round trip through both storages, error cases."""
from __future__ import annotations

import os
import re
import shutil
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from bevo_ros.io import bag
from bevo_ros.datasets import kitti
from bevo_ros.commands import convert as kitti_to_bag

REPO = Path(__file__).resolve().parents[1]

pytestmark = pytest.mark.kitti
DRIVE = "2011_09_30_drive_0020"
N_FRAMES = 51


def convert(*args: str) -> int:
    return kitti_to_bag.main([*map(str, args), "--quiet"])


@pytest.fixture(scope="module")
def bags(kitti_root, tmp_path_factory):
    """The whole sample converted once per storage."""
    out = tmp_path_factory.mktemp("bags")
    paths = {}
    for storage in bag.STORAGES:
        paths[storage] = out / f"seq06_{storage}"
        assert convert("--odometry", kitti_root / "odometry", "--sequence", "06", "-o", paths[storage],
                       "--storage", storage) == 0
    return paths


@pytest.fixture()
def layout(kitti_root, tmp_path):
    """A writable copy of the sample layout with 5 images (symlinked PNGs, copied OXTS)."""
    root = tmp_path / "kitti"
    seq = root / "odometry" / "sequences" / "06"
    (seq / "image_0").mkdir(parents=True)
    src_seq = kitti_root / "odometry" / "sequences" / "06"
    for i in range(5):
        os.symlink(src_seq / "image_0" / f"{i:06d}.png", seq / "image_0" / f"{i:06d}.png")
    shutil.copy(src_seq / "calib.txt", seq / "calib.txt")
    (root / "odometry" / "poses").mkdir()
    shutil.copy(kitti_root / "odometry" / "poses" / "06.txt", root / "odometry" / "poses" / "06.txt")
    shutil.copytree(kitti_root / "raw" / "2011_09_30" / f"{DRIVE}_sync" / "oxts",
                    root / "raw" / "2011_09_30" / f"{DRIVE}_sync" / "oxts")
    shutil.copytree(kitti_root / "raw" / "2011_09_26", root / "raw" / "2011_09_26")
    return root


def test_help_mentions_the_10_hz_imu(capsys):
    with pytest.raises(SystemExit) as exc:
        kitti_to_bag.main(["--help"])
    text = capsys.readouterr().out
    assert exc.value.code == 0 and "10 Hz" in text and "--raw-calib" in text


def test_roundtrip_is_exact(bags, kitti_root, capsys):
    oxts = kitti.read_oxts(kitti_root / "raw" / "2011_09_30" / f"{DRIVE}_sync" / "oxts").slice(0, N_FRAMES)
    poses = kitti.read_poses(kitti_root / "odometry" / "poses" / "06.txt")[:N_FRAMES]
    T_base_cam = kitti.invert_rigid(kitti.imu_to_camera_extrinsics(kitti_root / "raw" / "2011_09_26"))
    gt_base = kitti.base_poses(poses, T_base_cam)
    P0 = kitti.read_odometry_calib(kitti_root / "odometry" / "sequences" / "06" / "calib.txt")["P0"]
    pngs = kitti.list_images(kitti_root / "odometry" / "sequences" / "06" / "image_0")
    for storage, path in bags.items():
        rec = bag.read_recording(path)
        counts = {t: c for t, (_, c) in rec.topics.items()}
        size = sum(p.stat().st_size for p in path.rglob("*") if p.is_file())
        print(f"{storage}: {counts}, {size / 1e6:.2f} MB")
        assert counts == {bag.IMU_TOPIC: N_FRAMES, bag.IMAGE_TOPIC: N_FRAMES, bag.CAMERA_INFO_TOPIC: N_FRAMES,
                          bag.GT_ODOMETRY_TOPIC: N_FRAMES, bag.GT_IMU_TOPIC: N_FRAMES, bag.TF_STATIC_TOPIC: 1}
        # /tf_static: the rig (base = IMU, camera = the calibration chain), offered latched
        (_, _, tf), = bag.iter_messages(path, [bag.TF_STATIC_TOPIC])
        frames = {(t.header.frame_id, t.child_frame_id): t.transform for t in tf.transforms}
        assert set(frames) == {("base_link", "imu_link"), ("base_link", "camera_optical_frame")}
        from bevo_ros.io.static_tf import matrix_from_transform
        # the chain is a rotation (KITTI's 7-digit product taken to the nearest one): the quaternion gives it back
        assert np.allclose(matrix_from_transform(frames[("base_link", "camera_optical_frame")]), T_base_cam, atol=1e-12)
        assert np.allclose(matrix_from_transform(frames[("base_link", "imu_link")]), np.eye(4))
        # ... and the offline commands' lookup in it (read_recording's tree), as the node's
        assert np.allclose(rec.static_tf.lookup("base_link", rec.image_frame_id), T_base_cam, atol=1e-12)
        qos = bag.topic_qos(path)
        assert qos[bag.TF_STATIC_TOPIC].transient_local and not qos[bag.IMU_TOPIC].transient_local
        # IMU: exact values and exact nanosecond stamps; the rates of the records KITTI interpolated
        # (1-11) bridged by the unit's attitude change across them, those on /ground_truth/imu as written
        assert np.array_equal(rec.imu_stamps_ns, oxts.stamps_ns)
        interpolated = kitti.interpolated_oxts(oxts)
        assert np.flatnonzero(interpolated).tolist() == list(range(1, 12))
        assert np.array_equal(rec.gyro[~interpolated], oxts.gyro[~interpolated])
        assert np.array_equal(rec.accel[~interpolated], oxts.accel[~interpolated])
        gyro, accel, _ = kitti.bridged_imu(oxts, interpolated)
        assert np.array_equal(rec.gyro, gyro) and np.array_equal(rec.accel, accel)
        assert np.abs(rec.gyro[1:12] - oxts.gyro[1:12]).max() > np.radians(0.5)  # not the line
        gt_gyro = [(m.angular_velocity.x, m.angular_velocity.y, m.angular_velocity.z)
                   for _, _, m in bag.iter_messages(path, [bag.GT_IMU_TOPIC])]
        assert np.array_equal(np.array(gt_gyro), oxts.gyro)
        # Frames: no times.txt in the sample -> the OXTS stamps; images byte-exact.
        assert np.array_equal(rec.frame_stamps_ns, oxts.stamps_ns)
        assert rec.images.shape == (N_FRAMES, 370, 1226) and rec.image_encoding == "mono8"
        for i in (0, 17, N_FRAMES - 1):
            assert np.array_equal(rec.images[i], cv2.imread(str(pngs[i]), cv2.IMREAD_UNCHANGED))
        assert all(np.array_equal(rec.images[i], cv2.imread(str(p), cv2.IMREAD_UNCHANGED)) for i, p in enumerate(pngs))
        # Camera info: rectified, K/P from calib.txt.
        ci = rec.camera_info  # the message as read
        assert np.array_equal(np.reshape(ci.k, (3, 3)), P0[:, :3]) and np.array_equal(np.reshape(ci.p, (3, 4)), P0)
        assert (ci.width, ci.height, ci.distortion_model) == (1226, 370, "plumb_bob") and not np.any(ci.d)
        # Ground truth: base poses in odom, first = identity; OXTS attitude.
        pose_err = np.abs(rec.gt_poses - gt_base).max()
        att_err = max(np.abs(rec.gt_roll - oxts.roll).max(), np.abs(rec.gt_pitch - oxts.pitch).max())
        print(f"{storage}: GT pose max abs err {pose_err:.2e}, attitude max err {att_err:.2e} rad")
        # A quaternion is exactly orthonormal; KITTI's 7-digit rotations are not (~1e-7 off).
        assert pose_err < 1e-6 and att_err < 1e-9
        assert np.allclose(rec.gt_poses[0], np.eye(4), atol=1e-9)
        assert (rec.gt_frame_id, rec.gt_child_frame_id, rec.imu_frame_id) == ("odom", "base_link", "imu_link")


def test_sensor_imu_carries_no_orientation(bags):
    msgs = [m for _, _, m in bag.iter_messages(bags["sqlite3"], [bag.IMU_TOPIC])]
    assert len(msgs) == N_FRAMES
    assert all(m.orientation_covariance[0] == -1.0 for m in msgs)
    assert all(m.angular_velocity_covariance[0] > 0 and m.linear_acceleration_covariance[0] > 0 for m in msgs)
    gt = [m for _, _, m in bag.iter_messages(bags["sqlite3"], [bag.GT_IMU_TOPIC])]
    assert all(m.orientation_covariance[0] > 0 for m in gt)


def test_both_storages_hold_identical_messages(bags):
    a = list(bag.iter_raw_messages(bags["sqlite3"]))
    b = list(bag.iter_raw_messages(bags["mcap"]))
    print(f"{len(a)} messages per storage; first: {a[0].topic} at {a[0].stamp_ns}")
    assert len(a) == len(b) == 5 * N_FRAMES + 1  # + the one /tf_static
    assert [(m.topic, m.stamp_ns, m.data) for m in a] == [(m.topic, m.stamp_ns, m.data) for m in b]
    stamps = [m.stamp_ns for m in a]
    assert stamps == sorted(stamps)
    # At equal stamps the IMU sample precedes the image of the same frame.
    order = [m.topic for m in a if m.topic in (bag.IMU_TOPIC, bag.IMAGE_TOPIC)]
    assert order[:4] == [bag.IMU_TOPIC, bag.IMAGE_TOPIC, bag.IMU_TOPIC, bag.IMAGE_TOPIC]


def test_first_and_count(kitti_root, tmp_path, capsys):
    out = tmp_path / "short"
    assert kitti_to_bag.main(["--odometry", str(kitti_root / "odometry"), "-o", str(out), "--first", "10",
                              "--count", "5", "--storage", "mcap"]) == 0
    # records 10-11 are KITTI's interpolation over lost packets (judged with their neighbours 9, 12)
    assert "2 OXTS record(s) 10-11 are KITTI's linear interpolation" in capsys.readouterr().err
    rec = bag.read_recording(out)
    oxts = kitti.read_oxts(kitti_root / "raw" / "2011_09_30" / f"{DRIVE}_sync" / "oxts")
    assert len(rec.frame_stamps_ns) == 5 and np.array_equal(rec.imu_stamps_ns, oxts.stamps_ns[10:15])
    assert np.allclose(rec.gt_poses[0], np.eye(4), atol=1e-9)  # odom = base at the first written frame
    assert rec.gt_poses[-1][0, 3] > 4.0  # ~12 m/s over 0.4 s, along base x
    # bridged with the run's real ends, record 0 before the frames converted among them
    gyro, accel, _ = kitti.bridged_imu(oxts, kitti.interpolated_oxts(oxts))  # the drive's records, as convert
    assert np.array_equal(rec.gyro, gyro[10:15]) and not np.allclose(rec.gyro[:2], oxts.gyro[10:12])
    assert np.array_equal(rec.accel, accel[10:15])
    left_out = tmp_path / "left_out"
    assert kitti_to_bag.main(["--odometry", str(kitti_root / "odometry"), "-o", str(left_out), "--first", "10",
                              "--count", "5", "--interpolated-imu", "leave-out"]) == 0
    assert "left out of /imu/data" in capsys.readouterr().err
    short = bag.read_recording(left_out)
    assert np.array_equal(short.imu_stamps_ns, oxts.stamps_ns[12:15]) and len(short.gt_roll) == 5
    line = tmp_path / "line"
    assert kitti_to_bag.main(["--odometry", str(kitti_root / "odometry"), "-o", str(line), "--first", "10",
                              "--count", "5", "--interpolated-imu", "line"]) == 0
    assert "written to /imu/data as KITTI wrote them" in capsys.readouterr().err
    assert np.array_equal(bag.read_recording(line).gyro, oxts.gyro[10:15])
    assert np.array_equal(bag.read_recording(line).accel, oxts.accel[10:15])


def _expect_error(capsys, argv, *fragments) -> str:
    rc = kitti_to_bag.main([*map(str, argv), "-q"])
    err = capsys.readouterr().err
    print(err.strip())
    assert rc == 2, err
    for f in fragments:
        assert f in err, err
    assert "Traceback" not in err
    return err


def _no_partial(out: Path) -> bool:
    return not list(out.parent.glob(f".{out.name}.partial-*"))


def test_missing_directory(tmp_path, capsys):
    _expect_error(capsys, ["--odometry", tmp_path / "nope", "-o", tmp_path / "o"], "nope/sequences/06",
                  "not found")
    _expect_error(capsys, ["--raw", tmp_path / "nodrive", "-o", tmp_path / "o"], "nodrive", "not found")
    # one level off: the messages say which folder each option takes
    (tmp_path / "day" / "2011_10_03_drive_0042_sync").mkdir(parents=True)
    _expect_error(capsys, ["--raw", tmp_path / "day", "-o", tmp_path / "o"], "--raw takes one drive's folder",
                  "2011_10_03_drive_0042_sync")
    (tmp_path / "dataset" / "sequences" / "06" / "image_0").mkdir(parents=True)
    _expect_error(capsys, ["--odometry", tmp_path / "dataset" / "sequences" / "06", "-o", tmp_path / "o"],
                  "--odometry takes the folder that holds sequences/")
    # sequence 03's raw drive was never among the raw downloads: the message says so, other sequences' do not
    for seq, note in (("03", True), ("04", False)):
        images = tmp_path / "dataset" / "sequences" / seq / "image_0"
        images.mkdir(parents=True)
        cv2.imwrite(str(images / "000000.png"), np.zeros((4, 4), np.uint8))
        (images.parent / "calib.txt").write_text("P0: 1 0 2 0 0 1 2 0 0 0 1 0\n")
        args = ["--odometry", tmp_path / "dataset", "--sequence", seq, "-o", tmp_path / "o"]
        if note:
            _expect_error(capsys, args, "no OXTS directory for raw drive 2011_09_26_drive_0067",
                          "not among KITTI's raw downloads")
        else:
            err = _expect_error(capsys, args, "no OXTS directory for raw drive 2011_09_30_drive_0016")
            assert "raw downloads" not in err
    assert not (tmp_path / "o").exists()


def test_corrupt_oxts_line(layout, tmp_path, capsys):
    bad = layout / "raw" / "2011_09_30" / f"{DRIVE}_sync" / "oxts" / "data" / "0000000003.txt"
    bad.write_text(bad.read_text().replace(" ", " x", 1))
    out = tmp_path / "o"
    _expect_error(capsys, ["--odometry", layout / "odometry", "-o", out], "0000000003.txt:1", "cannot parse")
    assert not out.exists() and _no_partial(out)


def test_the_output_directory_is_created(layout, tmp_path, capsys):
    """The README's first command, `-o bags/kitti06` on a fresh machine: `bags/` is made, as `bevo run
    --out` makes its folder; a file in the way is a clear error."""
    out = tmp_path / "bags" / "kitti06"
    assert convert("--odometry", layout / "odometry", "-o", out, "--count", "2") == 0
    assert bag.bag_topics(out)[bag.IMAGE_TOPIC][1] == 2
    (tmp_path / "afile").write_text("x")
    _expect_error(capsys, ["--odometry", layout / "odometry", "-o", tmp_path / "afile" / "kitti06", "--count", "2"],
                  "afile: not a directory")


def test_a_missing_oxts_record_is_named(layout, tmp_path, capsys):
    """A gap in the OXTS file numbers (one file and one timestamp line gone) would pair every later
    record with another frame's time: refused, the record named."""
    oxts = layout / "raw" / "2011_09_30" / f"{DRIVE}_sync" / "oxts"
    (oxts / "data" / "0000000002.txt").unlink()
    lines = (oxts / "timestamps.txt").read_text().splitlines(True)
    (oxts / "timestamps.txt").write_text("".join(lines[:2] + lines[3:]))
    _expect_error(capsys, ["--odometry", layout / "odometry", "-o", tmp_path / "o"], "0000000003.txt",
                  "expected record 2")
    assert not (tmp_path / "o").exists()


def test_count_mismatches(layout, tmp_path, capsys):
    seq = layout / "odometry" / "sequences" / "06"
    (seq / "times.txt").write_text("0.0\n0.1\n0.2\n0.3\n")
    _expect_error(capsys, ["--odometry", layout / "odometry", "-o", tmp_path / "o"], "times.txt", "4 times but 5 images")
    (seq / "times.txt").unlink()
    (seq / "image_0" / "000002.png").unlink()
    _expect_error(capsys, ["--odometry", layout / "odometry", "-o", tmp_path / "o"], "000003.png",
                  "expected frame 2")
    assert not (tmp_path / "o").exists()


def test_times_txt_is_used_when_present(layout, tmp_path):
    seq = layout / "odometry" / "sequences" / "06"
    (seq / "times.txt").write_text("".join(f"{0.1 * i:.6e}\n" for i in range(5)))
    out = tmp_path / "o"
    assert convert("--odometry", layout / "odometry", "-o", out) == 0
    rec = bag.read_recording(out)
    dt = np.diff(rec.frame_stamps_ns)
    # on the OXTS clock where the records put the camera: the median of their offsets (a synced record is
    # the packet nearest the trigger), not record 0's alone
    offset = rec.imu_stamps_ns - rec.frame_stamps_ns
    assert np.all(dt == 100_000_000) and abs(np.median(offset)) <= 1 and np.ptp(offset) > 1_000_000


def test_existing_output_and_failed_overwrite_keep_the_old_bag(layout, tmp_path, capsys):
    out = tmp_path / "o"
    assert convert("--odometry", layout / "odometry", "-o", out, "--count", "2") == 0
    before = sorted((p.name, p.stat().st_size) for p in out.iterdir())
    _expect_error(capsys, ["--odometry", layout / "odometry", "-o", out], "exists", "--overwrite")
    # A failure half way (an unreadable image) with --overwrite: the old bag stays, nothing partial.
    img = layout / "odometry" / "sequences" / "06" / "image_0" / "000003.png"
    img.unlink()
    img.write_bytes(b"not a png")
    _expect_error(capsys, ["--odometry", layout / "odometry", "-o", out, "--overwrite"], "000003.png",
                  "cannot read image")
    assert sorted((p.name, p.stat().st_size) for p in out.iterdir()) == before
    assert _no_partial(out)
    # Without an old bag the same failure leaves nothing behind.
    out2 = tmp_path / "fresh"
    _expect_error(capsys, ["--odometry", layout / "odometry", "-o", out2], "000003.png")
    assert not out2.exists() and _no_partial(out2)
    # --overwrite replaces a good bag.
    assert convert("--odometry", layout / "odometry", "-o", out, "--overwrite", "--count", "3") == 0
    assert bag.bag_topics(out)[bag.IMAGE_TOPIC][1] == 3

    # The last rename failing (a full disk, a permission) after the old bag was moved aside: the old bag is
    # put back, not discarded with the partial (a read-only review)
    before = sorted((p.name, p.stat().st_size) for p in out.iterdir())
    real_replace = bag.os.replace

    def fail_into_place(src, dst):
        if Path(dst) == out and not str(src).endswith(".old"):
            raise OSError("no space left on device")
        real_replace(src, dst)

    import unittest.mock

    with unittest.mock.patch.object(bag.os, "replace", fail_into_place), pytest.raises(OSError, match="no space"):
        with bag.BagWriter(out, overwrite=True) as w:
            w.write_imu(1.0, (0.0, 0.0, 0.0), (0.0, 0.0, 9.81))
    assert sorted((p.name, p.stat().st_size) for p in out.iterdir()) == before and _no_partial(out)


def _steady_clock(stamps_ns: np.ndarray) -> np.ndarray:
    """The line through ``(N,)`` stamps (ns): a triggered camera's clock, which synced OXTS records jitter about."""
    i = np.arange(len(stamps_ns))
    fit = np.polyfit(i, (stamps_ns - stamps_ns[0]).astype(float), 1)
    return stamps_ns[0] + np.round(np.polyval(fit, i)).astype(np.int64)


def _frame_motions(T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(F, 4, 4)`` poses -> each frame-to-frame motion's length (m) and rotation angle (deg), ``(F-1,)`` each."""
    m = np.linalg.inv(T[:-1]) @ T[1:]
    cos = (np.trace(m[:, :3, :3], axis1=1, axis2=2) - 1) / 2
    return np.linalg.norm(m[:, :3, 3], axis=1), np.degrees(np.arccos(np.clip(cos, -1, 1)))


def _raw_drive(layout: Path, kitti_root: Path, frames: int = 5, steady_camera: bool = False) -> Path:
    """A raw ``<date>/<drive>_sync`` directory built from the sample: ``frames`` images in image_00, as many
    OXTS records (synced data pairs them one to one), camera stamps 5 ms after the OXTS ones (``steady_camera``:
    a steady camera clock, the line through the OXTS stamps, as a triggered camera's are)."""
    drive = layout / "raw" / "2011_09_30" / f"{DRIVE}_sync"
    cam = drive / "image_00"
    (cam / "data").mkdir(parents=True)
    for i in range(frames):
        os.symlink(kitti_root / "odometry" / "sequences" / "06" / "image_0" / f"{i:06d}.png", cam / "data" / f"{i:010d}.png")
    oxts = drive / "oxts"
    lines = (oxts / "timestamps.txt").read_text().splitlines()
    (oxts / "timestamps.txt").write_text("\n".join(lines[:frames]) + "\n")
    for p in sorted((oxts / "data").iterdir())[frames:]:
        p.unlink()
    stamps = kitti.read_timestamps_ns(oxts / "timestamps.txt") + 5_000_000
    if steady_camera:
        stamps = _steady_clock(stamps)
    (cam / "timestamps.txt").write_text("".join(
        f"2011-09-30 12:08:{(s // 10**9) % 60:02d}.{s % 10**9:09d}\n" for s in stamps))
    return drive


def _day_calibration(layout: Path, into: Path) -> None:
    """2011_09_30's own raw calibration in ``into``: 2011_09_26's chain with the sample's rectified
    camera (calib.txt's P0, 1226x370)."""
    for name in ("calib_imu_to_velo.txt", "calib_velo_to_cam.txt"):
        shutil.copy(layout / "raw" / "2011_09_26" / name, into / name)
    p0 = kitti.read_odometry_calib(layout / "odometry" / "sequences" / "06" / "calib.txt")["P0"].ravel()
    lines = []
    for line in (layout / "raw" / "2011_09_26" / "calib_cam_to_cam.txt").read_text().splitlines():
        if line.startswith("S_rect_00:"):
            line = "S_rect_00: 1.226000e+03 3.700000e+02"
        elif line.startswith("P_rect_00:"):
            line = "P_rect_00: " + " ".join(f"{v:.6e}" for v in p0)
        lines.append(line)
    (into / "calib_cam_to_cam.txt").write_text("\n".join(lines) + "\n")


def test_raw_layout(layout, kitti_root, tmp_path, capsys):
    """A raw ``<date>/<drive>_sync`` directory (built from the sample: image_00 + timestamps)."""
    drive = _raw_drive(layout, kitti_root)
    cam = drive / "image_00"
    stamps = kitti.read_timestamps_ns(cam / "timestamps.txt")
    # The camera matrix of a raw drive is its own day's: the layout has only 2011_09_26's calibration,
    # which the odometry layout borrows for the extrinsics but a raw drive may not (another day's P_rect
    # mis-scales it by percents: 17.6 % drift on the sample).
    _expect_error(capsys, ["--raw", drive, "-o", tmp_path / "no_day"], "no raw calibration of 2011_09_30",
                  "found 2011_09_26's", "--raw-calib")
    assert not (tmp_path / "no_day").exists()
    # Given explicitly, 2011_09_26's files are refused on their rectified size (1242x375 for 1226x370 images).
    _expect_error(capsys, ["--raw", drive, "-o", tmp_path / "o26", "--raw-calib", layout / "raw" / "2011_09_26"],
                  "S_rect_00 is 1242x375 but the images are 1226x370")
    # The day's own calibration.
    day = layout / "raw" / "2011_09_30"
    _day_calibration(layout, day)
    out = tmp_path / "raw_bag"
    rc = kitti_to_bag.main(["--raw", str(drive), "-o", str(out), "--poses",
                            str(layout / "odometry" / "poses" / "06.txt")])
    print(capsys.readouterr().out)
    assert rc == 0
    rec = bag.read_recording(out)
    assert np.array_equal(rec.frame_stamps_ns, stamps) and len(rec.imu_stamps_ns) == 5
    assert rec.camera_info.k[0] == pytest.approx(707.0912)  # P_rect_00 of the drive's own day
    assert rec.gt_poses.shape == (5, 4, 4)
    # with the IMU from a ~100 Hz extract of the drive (a stand-in: its synced records interpolated)
    fine, data = _fake_extract(drive / "oxts", slice(0, 5))
    fine, data = np.append(fine, fine[-1] + 9_500_000), np.vstack([data, data[-1:]])  # past the last image (5 ms on)
    extract = _write_oxts(tmp_path / "extract" / "oxts", fine, data)
    assert kitti_to_bag.main(["--raw", str(drive), "-o", str(tmp_path / "raw100"), "-q", "--imu-oxts", str(extract),
                              "--poses", str(layout / "odometry" / "poses" / "06.txt")]) == 0
    fast = bag.read_recording(tmp_path / "raw100")
    assert np.array_equal(fast.frame_stamps_ns, stamps) and np.array_equal(fast.gt_poses, rec.gt_poses)
    assert np.array_equal(fast.imu_stamps_ns, fine[(fine >= stamps[0] - 500_000_000) & (fine <= fine[fine >= stamps[-1]][0])])
    # The day comes from the drive folder's name: moved under a folder that is no date, or given as `.`,
    # it still finds its own day's calibration (2011_09_30, a sibling of the new folder's parent).
    moved = layout / "raw" / "drives" / drive.name
    moved.parent.mkdir()
    drive.rename(moved)
    shutil.rmtree(layout / "raw" / "2011_09_26")  # only the drive's own day is left to find
    shutil.move(str(day), str(layout / "raw" / "drives" / "2011_09_30"))
    assert kitti_to_bag.main(["--raw", str(moved), "-o", str(tmp_path / "moved"), "-q"]) == 0
    assert bag.read_recording(tmp_path / "moved").camera_info.k[0] == pytest.approx(707.0912)
    cwd = os.getcwd()
    try:
        os.chdir(moved)
        assert kitti_to_bag.main(["--raw", ".", "-o", str(tmp_path / "dot"), "-q"]) == 0
    finally:
        os.chdir(cwd)
    assert bag.read_recording(tmp_path / "dot").camera_info.k[0] == pytest.approx(707.0912)
    drive, cam = moved, moved / "image_00"
    # One timestamp short: a clear count error.
    (cam / "timestamps.txt").write_text("".join((cam / "timestamps.txt").read_text().splitlines(True)[:4]))
    _expect_error(capsys, ["--raw", drive, "-o", tmp_path / "o2"], "image_00/timestamps.txt",
                  "4 timestamps but 5 images")


def test_a_killed_conversion_leaves_nothing_after_the_next_run(kitti_root, tmp_path, capsys):
    """SIGKILL cannot be cleaned up after: the next run of the same output removes the partial."""
    import signal
    import subprocess
    import time

    out = tmp_path / "o"
    cmd = [sys.executable, "-m", "bevo_ros.cli", "convert", "--odometry", str(kitti_root / "odometry"),
           "-o", str(out), "--quiet"]
    proc = subprocess.Popen(cmd, env=dict(os.environ, PYTHONPATH=str(REPO)), stderr=subprocess.PIPE)
    deadline = time.monotonic() + 60
    while _no_partial(out) and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.01)
    assert proc.poll() is None, "the conversion ended before it could be killed"
    time.sleep(0.2)  # some frames written
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    assert not out.exists() and not _no_partial(out)  # what a kill leaves
    assert convert("--odometry", kitti_root / "odometry", "-o", out, "--count", "3") == 0
    assert "partial output of an interrupted run" in capsys.readouterr().err
    assert _no_partial(out) and bag.bag_topics(out)[bag.IMAGE_TOPIC][1] == 3
    assert [p.name for p in tmp_path.iterdir()] == ["o"]


def test_a_negative_oxts_offset_is_refused(tmp_path):
    """--oxts-offset -5 sliced no OXTS record and failed with an IndexError deep in the conversion."""
    from bevo_ros.datasets.kitti_bag import ConversionError, ConversionOptions, load_source

    with pytest.raises(ConversionError, match="--oxts-offset -5: must be >= 0"):
        load_source(ConversionOptions(output=tmp_path / "b", odometry=tmp_path, oxts_offset=-5))
    with pytest.raises(ConversionError, match="--gyro-var -1.0: a variance must be >= 0"):
        load_source(ConversionOptions(output=tmp_path / "b", odometry=tmp_path, gyro_var=-1.0))


def test_raw_drive_past_its_sequence_converts_the_frames_with_ground_truth(layout, kitti_root, tmp_path, capsys):
    """A raw drive runs past its odometry sequence (0020: 1104 records, 1101 poses; 0028's poses start at
    frame 1100): converted whole, frames without a pose left bevo run with no gt_kitti.txt at all. By
    default the frames the poses cover; poses that cover none of the frames asked for are refused."""
    drive = _raw_drive(layout, kitti_root, frames=8)
    _day_calibration(layout, layout / "raw" / "2011_09_30")
    poses = tmp_path / "poses.txt"
    poses.write_text("".join((layout / "odometry" / "poses" / "06.txt").read_text().splitlines(True)[:6]))
    out = tmp_path / "o"
    assert kitti_to_bag.main(["--raw", str(drive), "-o", str(out), "--poses", str(poses)]) == 0
    assert "frames 0..5 of raw drive" in capsys.readouterr().err
    rec = bag.read_recording(out)
    assert len(rec.frame_stamps_ns) == 6 and rec.gt_poses.shape == (6, 4, 4)
    # asked for explicitly, the frames past the poses are converted (their ground truth left out)
    assert convert("--raw", drive, "-o", tmp_path / "all", "--poses", poses, "--count", "8") == 0
    rec = bag.read_recording(tmp_path / "all")
    assert len(rec.frame_stamps_ns) == 8 and rec.gt_poses.shape == (6, 4, 4)
    _expect_error(capsys, ["--raw", drive, "-o", tmp_path / "none", "--poses", poses, "--first", "6"],
                  "covers frames 0-5", "none of the frames 6..7")
    _expect_error(capsys, ["--raw", drive, "-o", tmp_path / "none", "--poses", poses, "--oxts-offset", "9"],
                  "first pose is frame 9", "8 frames")


def test_a_calibration_in_the_drives_folder_is_its_days_own(layout, kitti_root, tmp_path, capsys):
    """KITTI's layout names the day's folder by its date; the day's files inside the drive's own folder
    (or the folder holding it, under another name) are that day's too, not refused as another day's."""
    drive = _raw_drive(layout, kitti_root)
    _day_calibration(layout, drive)
    assert kitti_to_bag.main(["--raw", str(drive), "-o", str(tmp_path / "o"), "-q"]) == 0
    assert kitti_to_bag.main(["--raw", str(drive), "-o", str(tmp_path / "o2"), "-q", "--raw-calib", str(drive)]) == 0
    assert "another day" not in capsys.readouterr().err
    assert bag.read_recording(tmp_path / "o").camera_info.k[0] == pytest.approx(707.0912)


def test_other_cameras_ground_truth_is_camera_0s_poses(layout, kitti_root, tmp_path):
    """poses/NN.txt are camera 0's: converted for camera 1, the base's ground truth must be the same
    (through camera 1's extrinsics it moved by the lever arm between the cameras, 1.07 m over 06)."""
    seq = layout / "odometry" / "sequences" / "06"
    (seq / "image_1").mkdir()
    for i in range(5):
        os.symlink(kitti_root / "odometry" / "sequences" / "06" / "image_0" / f"{i:06d}.png", seq / "image_1" / f"{i:06d}.png")
    for cam in (0, 1):
        assert convert("--odometry", layout / "odometry", "-o", tmp_path / f"c{cam}", "--camera", cam) == 0
    gt0, gt1 = (bag.read_recording(tmp_path / f"c{cam}").gt_poses for cam in (0, 1))
    assert np.abs(gt0[-1][:3, 3]).max() > 4.0 and np.allclose(gt0, gt1, atol=1e-9)
    tf0, tf1 = (bag.read_recording(tmp_path / f"c{cam}") for cam in (0, 1))
    assert tf0.camera_info.p[3] == 0.0 and tf1.camera_info.p[3] != 0.0  # the bags are each camera's


def test_a_partial_download_with_the_whole_times_txt(layout, tmp_path):
    """The odometry zips hold the sequence's whole times.txt: the first n images take its first n times."""
    seq = layout / "odometry" / "sequences" / "06"
    (seq / "times.txt").write_text("".join(f"{0.1 * i:.6e}\n" for i in range(1101)))
    assert convert("--odometry", layout / "odometry", "-o", tmp_path / "o") == 0
    assert np.all(np.diff(bag.read_recording(tmp_path / "o").frame_stamps_ns) == 100_000_000)


def test_an_oxts_stamp_out_of_order_leaves_that_record_out(layout, tmp_path, capsys):
    """One OXTS stamp at or before the record before it refused the whole drive, even a record outside
    the frames converted: now that record alone is left out of the IMU topics, and said."""
    oxts = layout / "raw" / "2011_09_30" / f"{DRIVE}_sync" / "oxts"
    lines = (oxts / "timestamps.txt").read_text().splitlines(True)
    lines[3] = lines[2]  # record 3 repeats record 2's stamp
    lines[900] = lines[899]  # far outside the 5 frames
    (oxts / "timestamps.txt").write_text("".join(lines))
    seq = layout / "odometry" / "sequences" / "06"
    (seq / "times.txt").write_text("".join(f"{0.1 * i:.6e}\n" for i in range(5)))
    out = tmp_path / "o"
    assert kitti_to_bag.main(["--odometry", str(layout / "odometry"), "-o", str(out), "--quiet"]) == 0
    assert "1 OXTS record(s) 3 stamped out of order with the others" in capsys.readouterr().err
    rec = bag.read_recording(out)
    stamps = kitti.read_timestamps_ns(oxts / "timestamps.txt", increasing=False)
    assert np.array_equal(rec.imu_stamps_ns, stamps[[0, 1, 2, 4]]) and len(rec.frame_stamps_ns) == 5
    assert np.all(np.diff(rec.imu_stamps_ns) > 0)


def test_interpolated_records_are_named_by_the_drives_record_numbers(layout, tmp_path, capsys):
    """Records are the drive's oxts/data file numbers, not the frames of a sequence that starts later;
    they are judged and bridged over the drive's records, so the sequence's first and last records,
    inside the drive's run 1-11, are found too (judged on the sequence's alone they were not)."""
    assert kitti_to_bag.main(["--odometry", str(layout / "odometry"), "-o", str(tmp_path / "o"),
                              "--oxts-offset", "3"]) == 0
    err = capsys.readouterr().err
    assert "5 OXTS record(s) 3-7 are KITTI's linear interpolation" in err and "bridged" in err  # frames 0-4
    assert " not (no real record" not in err  # the run's real ends, records 0 and 12, lie outside the sequence
    oxts = kitti.read_oxts(layout / "raw" / "2011_09_30" / f"{DRIVE}_sync" / "oxts")
    gyro, accel, _ = kitti.bridged_imu(oxts, kitti.interpolated_oxts(oxts))
    rec = bag.read_recording(tmp_path / "o")
    assert np.array_equal(rec.gyro, gyro[3:3 + len(rec.gyro)]) and np.array_equal(rec.accel, accel[3:3 + len(rec.gyro)])


def test_overwrite_replaces_only_a_bag(layout, tmp_path, capsys):
    """--overwrite under a mistyped -o deleted a folder of the user's data."""
    mine = tmp_path / "mydata"
    mine.mkdir()
    (mine / "notes.txt").write_text("precious")
    _expect_error(capsys, ["--odometry", layout / "odometry", "-o", mine, "--overwrite", "--count", "2"],
                  "not a rosbag2 folder")
    assert (mine / "notes.txt").read_text() == "precious" and _no_partial(mine)
    empty = tmp_path / "empty"
    empty.mkdir()
    assert convert("--odometry", layout / "odometry", "-o", empty, "--overwrite", "--count", "2") == 0
    assert bag.bag_topics(empty)[bag.IMAGE_TOPIC][1] == 2


def test_a_raw_drive_without_poses_has_the_oxts_ground_truth_at_the_image_stamps(layout, kitti_root, tmp_path, capsys):
    """Most raw drives have no odometry sequence: their ground truth is the OXTS unit's GPS/INS poses (the
    devkit's convertOxtsToPose), moved from each synced record's stamp to its image's. Against the odometry
    poses of the sample's 51 frames, each frame's motion (its length and angle: the comparison does not
    hang on the calibration chain, whose 2011_09_26 stand-in pitches the poses' base by 0.97 deg): 1.9 cm
    at the images' stamps, 7.3 cm at the records' own (a synced record is the packet nearest the
    trigger, up to ~10 ms off); whole drives 0016-0027 0.06-0.4 cm against 1.6-7.3."""
    drive = _raw_drive(layout, kitti_root, frames=51, steady_camera=True)
    _day_calibration(layout, layout / "raw" / "2011_09_30")
    assert kitti_to_bag.main(["--raw", str(drive), "-o", str(tmp_path / "oxts")]) == 0
    assert "ground truth from the OXTS unit's GPS/INS poses" in capsys.readouterr().err
    assert convert("--raw", drive, "-o", tmp_path / "poses", "--poses", layout / "odometry" / "poses" / "06.txt") == 0
    assert convert("--raw", drive, "-o", tmp_path / "none", "--no-oxts-ground-truth") == 0
    assert bag.read_recording(tmp_path / "none").gt_poses is None
    ours, official = (bag.read_recording(tmp_path / name) for name in ("oxts", "poses"))
    assert np.array_equal(ours.gt_stamps_ns, official.gt_stamps_ns) and np.allclose(ours.gt_poses[0], np.eye(4))

    def per_frame(a, b):  # RMS differences of the frame-to-frame motions' lengths (m) and angles (deg)
        (la, aa), (lb, ab) = _frame_motions(a), _frame_motions(b)
        return float(np.sqrt(np.mean((la - lb) ** 2))), float(np.sqrt(np.mean((aa - ab) ** 2)))

    length, angle = per_frame(ours.gt_poses, official.gt_poses)
    oxts = kitti.read_oxts(drive / "oxts")
    at_records = per_frame(kitti.oxts_poses(oxts), official.gt_poses)[0]
    print(f"\nOXTS ground truth against the odometry poses, per frame: {length * 100:.2f} cm, {angle:.4f} deg at the "
          f"images' stamps; {at_records * 100:.2f} cm at the records'")
    assert length < 0.025 and angle < 0.02 and at_records > 0.05


@pytest.mark.parametrize("drive, sequence", [("0016", "04"), ("0027", "07")])
def test_oxts_poses_at_a_steady_camera_clock_are_the_odometry_ground_truths_motions(kitti_root, drive, sequence):
    """Whole drives: at a steady camera clock (the line through the records' stamps, as a triggered
    camera runs) the OXTS poses' frame-to-frame motions have the odometry poses' lengths to millimetres
    (at the records' own stamps: centimetres)."""
    oxts = kitti.read_oxts(kitti_root / "raw" / "2011_09_30" / f"2011_09_30_drive_{drive}_sync" / "oxts")
    poses = kitti.read_poses(kitti_root / "odometry" / "poses" / f"{sequence}.txt")
    oxts = oxts.slice(0, len(poses))
    truth, angle = _frame_motions(poses)  # camera 0's motions: as long as the base's but for the turns' lever arm
    straight = angle < 0.5
    at_camera = np.sqrt(np.mean((_frame_motions(kitti.oxts_poses(oxts, _steady_clock(oxts.stamps_ns)))[0] - truth)[straight] ** 2))
    at_records = np.sqrt(np.mean((_frame_motions(kitti.oxts_poses(oxts))[0] - truth)[straight] ** 2))
    print(f"\n{drive}: frame motions' lengths against the odometry poses: {at_camera * 100:.2f} cm at the camera's "
          f"clock, {at_records * 100:.2f} cm at the records' stamps")
    assert at_camera < 0.008 and at_records > 0.015


def _fake_extract(synced: Path, records: slice, factor: int = 10) -> tuple[np.ndarray, np.ndarray]:
    """A raw extract's unsynced OXTS stand-in: the synced records ``records`` linearly interpolated
    ``factor`` x denser (~100 Hz from KITTI's 10 Hz), on the same clock, so that its records at the synced
    stamps are the synced records. -> ``(stamps_ns (M,), data (M, 30))``."""
    ox = kitti.read_oxts(synced)
    t, d = ox.stamps_ns[records], ox.data[records]
    fine = np.concatenate([t[i] + (t[i + 1] - t[i]) * np.arange(factor) // factor for i in range(len(t) - 1)] + [t[-1:]])
    return fine, np.stack([np.interp(fine.astype(np.float64), t.astype(np.float64), d[:, k]) for k in range(d.shape[1])], 1)


def _write_oxts(into: Path, stamps_ns: np.ndarray, data: np.ndarray) -> Path:
    """An OXTS directory (``timestamps.txt``, ``data/NNNNNNNNNN.txt``) as KITTI's raw downloads lay it out."""
    (into / "data").mkdir(parents=True)
    for i, row in enumerate(data):
        (into / "data" / f"{i:010d}.txt").write_text(" ".join(repr(float(v)) for v in row) + "\n")
    day = np.datetime64("1970-01-01T00:00:00", "ns")
    (into / "timestamps.txt").write_text("".join(str(day + np.timedelta64(int(s), "ns")).replace("T", " ") + "\n"
                                                 for s in stamps_ns))
    return into


def test_the_imu_topic_from_the_raw_extracts_100_hz_oxts(layout, kitti_root, tmp_path, capsys):
    """``--imu-oxts``: /imu/data from another OXTS directory of the drive (the raw extract's unsynced
    ~100 Hz records, the paper's IMU rate), from 0.5 s before the first frame to the first record at or
    after the last; the synced records still give the ground truth and /ground_truth/imu; bevo run takes
    the stream. A record stamped out of order is left out alone (not the good ones after it), a gap
    (lost packets) is said, and so is a stream that does not hold the synced records; one that does not
    cover the frames is refused, and so are --render-oxts and --interpolated-imu other than bridge with it."""
    from bevo_ros.commands import run

    synced = layout / "raw" / "2011_09_30" / f"{DRIVE}_sync" / "oxts"
    images = layout / "odometry" / "sequences" / "06" / "image_0"
    for i in range(5, 19):  # the layout's 5 frames and 14 more (records 1-11 are KITTI's interpolation)
        os.symlink(kitti_root / "odometry" / "sequences" / "06" / "image_0" / f"{i:06d}.png", images / f"{i:06d}.png")
    frames10 = kitti.read_oxts(synced).stamps_ns  # this layout has no times.txt: the frames are at the records
    t, d = _fake_extract(synced, slice(0, 25))
    late = int(np.searchsorted(t, frames10[14])) + 5  # between frames 14 and 15
    t[late] += 300_000_000  # stamped 0.3 s late: only it is out of order
    gap = slice(int(np.searchsorted(t, frames10[16])) + 1, int(np.searchsorted(t, frames10[16])) + 8)  # 7 packets lost
    at_last = int(np.searchsorted(t, frames10[17]))  # the record at the last frame's stamp lost too
    drop = np.zeros(len(t), dtype=bool)
    drop[gap], drop[at_last] = True, True
    t, d = t[~drop], d[~drop]
    extract = _write_oxts(tmp_path / "extract" / "oxts", t, d)
    base = ["--odometry", str(layout / "odometry"), "--sequence", "06", "--raw-root", str(layout / "raw"),
            "--first", "13", "--count", "5"]
    assert kitti_to_bag.main(base + ["-o", str(tmp_path / "b10"), "-q"]) == 0
    assert kitti_to_bag.main(base + ["-o", str(tmp_path / "b100"), "--imu-oxts", str(extract)]) == 0
    err = capsys.readouterr().err
    assert re.search(r"/imu/data from \S+extract/oxts \(\d+ records, 1\d\d Hz\); the synced records give /ground_truth/imu",
                     err), err
    assert f"1 record(s) of --imu-oxts {late} stamped out of order with the others" in err, err
    assert re.search(r"1 gap\(s\) over 2.5 periods \(lost packets\) over the frames, the longest 0\.0[789]\d s after record 160: ", err), err
    assert "synced OXTS records are among" not in err
    slow, quick = bag.read_recording(tmp_path / "b10"), bag.read_recording(tmp_path / "b100")
    frames = quick.frame_stamps_ns
    assert np.array_equal(frames, frames10[13:18]) and np.array_equal(frames, slow.frame_stamps_ns)
    ok = np.ones(len(t), dtype=bool)
    ok[late] = False
    end = t[ok][np.searchsorted(t[ok], frames[-1])]  # the first record after the last frame (its own is lost)
    want = ok & (t >= frames[0] - 500_000_000) & (t <= end)
    assert end > frames[-1] and t[want][0] < frames[0] - 400_000_000  # a lead-in and a record past the last frame
    assert np.array_equal(quick.imu_stamps_ns, t[want])
    assert bag.bag_topics(tmp_path / "b100")[bag.IMU_TOPIC][1] == want.sum()  # nothing else on the IMU topic
    assert np.array_equal(quick.gyro, kitti.OxtsData(t, d).gyro[want])
    assert np.array_equal(quick.gt_poses, slow.gt_poses) and np.array_equal(quick.gt_att_stamps_ns, slow.gt_att_stamps_ns)
    assert run.main([str(tmp_path / "b100"), "--out", str(tmp_path / "run100"), "-q"]) == 0
    assert len(kitti.read_poses(tmp_path / "run100" / "trajectory_kitti.txt")) == 5

    # 3 ms later: none of the synced records is among its records (another drive's, or shifted): said
    t2, d2 = _fake_extract(synced, slice(0, 25))
    shifted = _write_oxts(tmp_path / "shifted" / "oxts", t2 + 3_000_000, d2)
    assert kitti_to_bag.main(base + ["-o", str(tmp_path / "bshift"), "--imu-oxts", str(shifted), "-q"]) == 0
    assert "only 0 of the 5 synced OXTS records are among --imu-oxts's" in capsys.readouterr().err
    # a directory that ends before the frames do: refused, nothing written
    short = _write_oxts(tmp_path / "short" / "oxts", *_fake_extract(synced, slice(0, 16)))
    assert kitti_to_bag.main(base + ["-o", str(tmp_path / "bshort"), "--imu-oxts", str(short)]) == 2
    assert "do not cover the frames converted" in capsys.readouterr().err and not (tmp_path / "bshort").exists()
    assert kitti_to_bag.main(base + ["-o", str(tmp_path / "bnone"), "--imu-oxts", str(tmp_path / "nothing")]) == 2
    assert "--imu-oxts" in capsys.readouterr().err
    assert kitti_to_bag.main(base + ["-o", str(tmp_path / "bi"), "--imu-oxts", str(extract),
                                     "--interpolated-imu", "leave-out"]) == 2
    assert "--interpolated-imu applies to the synced records" in capsys.readouterr().err
    assert kitti_to_bag.main(["--render-oxts", str(synced), "--imu-oxts", str(synced), "-o", str(tmp_path / "r")]) == 2
    assert "--imu-oxts applies to a drive's real images" in capsys.readouterr().err


def test_a_drive_of_another_day_is_told_its_camera_tilt(layout, kitti_root, tmp_path, capsys):
    """params/kitti.yaml's camera tilt was fitted on 2011_09_30, and KITTI's differed between days (the
    ground truth's direction of travel: 2011_10_03 0.22 deg less, 2011_09_26 1.55 deg less): a drive of
    another day is told so by convert (even with ``--quiet``: the scale hangs on it), naming ``bevo run
    <bag> --tilt-from-images``; the fitted day's drive is told nothing."""
    drive = _raw_drive(layout, kitti_root)
    _day_calibration(layout, layout / "raw" / "2011_09_30")
    other = layout / "raw" / "2011_10_03" / "2011_10_03_drive_0042_sync"
    shutil.copytree(drive, other, symlinks=True)
    for name in ("calib_imu_to_velo.txt", "calib_velo_to_cam.txt", "calib_cam_to_cam.txt"):
        shutil.copy(layout / "raw" / "2011_09_30" / name, other.parent / name)
    for src, told in ((drive, False), (other, True)):
        capsys.readouterr()
        out = tmp_path / src.name
        assert kitti_to_bag.main(["--raw", str(src), "-o", str(out)]) == 0
        err = capsys.readouterr().err
        assert ("--tilt-from-images" in err) == told, err
        if told:
            assert "2011_10_03's ground truth has the camera 0.22 deg less tilted" in err, err
            assert f"bevo run {out} --tilt-from-images" in err, err
    assert kitti_to_bag.main(["--raw", str(other), "-o", str(tmp_path / "quiet"), "-q"]) == 0
    assert "warning: params/kitti.yaml's camera tilt" in capsys.readouterr().err  # said even with --quiet
    assert "1.55 deg less tilted" in kitti.day_tilt_note("2011_09_26")
    assert "changed between days by up to 1.5 deg" in kitti.day_tilt_note("2011_09_28")  # no ground truth of it
    assert kitti.day_tilt_note("2011_09_30") is None and kitti.day_tilt_note("oxts") is None
