"""Real drives' IMU and motion with a rendered camera (``datasets.synthetic.oxts_drive``), and the
engine's frame order: frames that arrive before the IMU sample after them (a bag played by stamp:
KITTI's 10 Hz OXTS beside frames on the camera clock) get the same attitude and gyro yaw as frames
delivered after it (a camera's latency; ``datasets.stamp_order``, the tests' feeding order)."""
from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
import torch

from bevo_ros.config import REPO_ROOT, BevoConfig, build_odometry
from bevo_ros.core.geometry import CameraModel
from bevo_ros.core.pose import integrate_motions
from bevo_ros.datasets.kitti import OXTS_FIELDS, OxtsData, read_oxts
from bevo_ros.datasets.rosbag import feed_engine
from bevo_ros.datasets.synthetic import kitti_like_camera, preset_drive, render_frame
from bevo_ros.datasets.kitti import EARTH_RADIUS, oxts_positions
from bevo_ros.datasets.synthetic.oxts_drive import _camera_clock, _hermite, drive_from_oxts
from bevo_ros.io.learned_params import load_learned_params

FUSED = load_learned_params(REPO_ROOT / "params" / "learned_default.yaml")
# the default with the inertial speed input (fused item 16, and so item 17) switched off
FUSED_NO_INERTIAL = replace(FUSED, vehicle={**FUSED.vehicle, "imu_accel_density": 0.0})
PAPER = load_learned_params(REPO_ROOT / "params" / "learned_paper.yaml")
CAMERA_PERIOD = 0.1037  # s, KITTI's camera (the OXTS runs at 100 Hz)


def small_camera() -> CameraModel:
    return kitti_like_camera(scale=0.5)


def _circle_oxts(n: int = 120, speed: float = 10.0, yaw_rate: float = 0.2, lat0: float = 49.0) -> tuple[OxtsData, np.ndarray]:
    """Synced OXTS of a car on a circle: records at the 100 Hz sample nearest each camera frame
    (``CAMERA_PERIOD``), as KITTI's sync picks them. -> (records, the camera's frame times)."""
    t_cam = 0.037 + CAMERA_PERIOD * np.arange(n)
    t = np.round(t_cam, 2)  # the nearest 10 ms sample
    yaw = 0.3 + yaw_rate * t
    r = speed / yaw_rate
    east, north = r * (np.sin(yaw) - np.sin(0.3)), -r * (np.cos(yaw) - np.cos(0.3))
    scale = math.cos(math.radians(lat0))
    y0 = scale * EARTH_RADIUS * math.log(math.tan(math.radians(90.0 + lat0) / 2.0))
    lat = np.degrees(2.0 * np.arctan(np.exp((y0 + north) / (scale * EARTH_RADIUS)))) - 90.0
    lon = np.degrees(east / (scale * EARTH_RADIUS)) + 8.4
    data = np.zeros((n, len(OXTS_FIELDS)))
    col = {name: i for i, name in enumerate(OXTS_FIELDS)}
    data[:, col["lat"]], data[:, col["lon"]], data[:, col["yaw"]] = lat, lon, yaw
    data[:, col["vn"]], data[:, col["ve"]] = speed * np.sin(yaw), speed * np.cos(yaw)
    data[:, col["vf"]] = speed
    data[:, col["ay"]], data[:, col["az"]] = speed * yaw_rate, 9.81
    data[:, col["wz"]] = yaw_rate
    stamps_ns = np.round((1.3e9 + t) * 1e9).astype(np.int64)
    return OxtsData(stamps_ns, data), t_cam


def test_camera_clock_and_hermite():
    t_cam = 5.0 + CAMERA_PERIOD * np.arange(200)
    clock = _camera_clock(np.round(t_cam, 2))
    assert np.abs(clock - t_cam).max() < 2e-3  # the +-5 ms of the 10 ms grid, averaged out
    assert abs(np.mean(np.diff(clock)) - CAMERA_PERIOD) < 1e-5
    t = np.array([0.0, 0.1, 0.25, 0.3])
    f = lambda x: 2 * x**3 - x**2 + 3 * x + 1  # noqa: E731 - a cubic is interpolated exactly
    df = lambda x: 6 * x**2 - 2 * x + 3  # noqa: E731
    q = np.linspace(0.0, 0.3, 17)
    out = _hermite(t, f(t)[:, None], df(t)[:, None], q)[:, 0]
    np.testing.assert_allclose(out, f(q), atol=1e-12)


def test_oxts_positions_are_metric():
    ox, _ = _circle_oxts()
    xy = oxts_positions(ox.field("lat"), ox.field("lon"))
    r = 10.0 / 0.2
    centre = xy[0] + r * np.array([-math.sin(0.3 + 0.2 * 0.04), math.cos(0.3 + 0.2 * 0.04)])
    np.testing.assert_allclose(np.linalg.norm(xy - centre, axis=1), r, atol=2e-3)


def test_drive_from_oxts_puts_the_frames_on_the_camera_clock():
    """The records' stamps jitter by +-5 ms (7 cm at 14 m/s); the frames' truth does not."""
    ox, t_cam = _circle_oxts()
    d = drive_from_oxts(ox, render=False)
    assert len(d.imu_stamps) == len(ox)
    period = np.diff(d.frame_stamps)
    assert abs(period.mean() - CAMERA_PERIOD) < 1e-4 and period.std() < 1e-3
    # per frame the circle's exact motion: v T forward, (v T)(w T) / 2 sideways, w T of turn
    step = 10.0 * period
    np.testing.assert_allclose(d.relative_motion[:, 0], step, atol=2e-3)
    np.testing.assert_allclose(d.relative_motion[:, 1], step * 0.2 * period / 2, atol=2e-3)
    np.testing.assert_allclose(d.relative_motion[:, 2], 0.2 * period, atol=1e-5)
    # the IMU is the records', at their own stamps
    np.testing.assert_array_equal(d.gyro, ox.gyro)
    assert np.abs(d.imu_stamps[d.frame_imu_index] - d.frame_stamps).max() <= 0.006
    # flat road, no lean: the road-relative attitude is zero, the gravity one the records'
    np.testing.assert_allclose(d.pitch_roll_road[:, 0], 0.0, atol=1e-12)
    with pytest.raises(ValueError, match="at least 3"):
        drive_from_oxts(ox.slice(0, 2))
    # Traffic along the records' path: the car ahead on the circle, 6.5 m + 0.8 s of driving ahead.
    busy = drive_from_oxts(ox, render=False, traffic=True)
    np.testing.assert_array_equal(busy.relative_motion, d.relative_motion)
    lead = np.stack([v[0] for v in busy.traffic[:-10]])  # the last 0.8 s: the car ahead runs out of path
    gap = np.hypot(*(lead[:, :2] - busy.poses_xy_yaw[:-10, :2]).T) - lead[:, 3] / 2
    np.testing.assert_allclose(gap, 6.5 + 10.0 * 0.8, atol=0.3)  # a chord of the 50 m circle: a bit short
    with pytest.raises(ValueError, match="traffic"):
        drive_from_oxts(ox, render=False, traffic="busy")


def test_drive_from_oxts_bends_the_road_ahead_by_its_own_slope():
    """``vertical_curves``: the records climb at a rate that falls by k per metre (a crest of radius
    1/k); each frame's road ahead is then the parabola ``-k u^2 / 2`` under its plane (the drive's
    slope further along), the frames' distances are the path's, and the images show it."""
    ox, _ = _circle_oxts(n=200)
    col = {name: i for i, name in enumerate(OXTS_FIELDS)}
    t = (ox.stamps_ns - ox.stamps_ns[0]) * 1e-9
    k = 1.0 / 900.0
    ox.data[:, col["vu"]] = 10.0 * np.tan(math.radians(2.0) - k * 10.0 * t)  # climbing 2 deg, then less
    flat = drive_from_oxts(ox, render=False, camera=small_camera())
    d = drive_from_oxts(ox, render=False, camera=small_camera(), vertical_curves=True)
    assert flat.road_profile is None
    p = d.road_profile
    np.testing.assert_allclose(np.diff(p.frame_distance), np.linalg.norm(d.relative_motion[:, :2], axis=1), rtol=1e-3)
    # each frame's place on the profile: the slope there is the drive's slope at the frame
    np.testing.assert_allclose(np.interp(p.frame_distance, p.distance, p.slope)[20:-20],
                               d.road_slope_camber[20:-20, 0], atol=1e-4)
    u = np.array([7.5, 12.5, 17.5])
    for i in (60, 100, 140):  # away from the ends (the slope's smoothing)
        z, _ = p.height_ahead(float(p.frame_distance[i]))(u)
        np.testing.assert_allclose(z, -k * u**2 / 2, atol=2e-3)
    i = 100
    bent = render_frame(d, i).astype(float)
    plane = render_frame(flat, i).astype(float)
    assert np.abs(bent - plane)[100:].mean() > 5.0  # the ground rows differ
    with pytest.raises(ValueError, match="vertical_curves and traffic"):
        drive_from_oxts(ox, render=False, vertical_curves=True, traffic=True)


def test_frames_before_their_imu_sample_get_the_interpolated_attitude_and_yaw():
    """A 10 Hz IMU, frames 4 ms after or before its samples: frames delivered in stamp order (a
    node, ``bevo run``) give exactly what frames delivered after the next sample give, and the
    gyro's yaw per frame is the turn's. Before the fix the frames in stamp order took the attitude
    and yaw of the sample before them: per-frame gyro yaw 0, then twice the turn."""
    d = preset_drive("curve", seed=2, duration=4.0, imu_rate=10.0, render="lazy", camera=small_camera())
    frames = d.frame_stamps + np.where(np.arange(d.num_frames) % 2 == 0, 0.004, -0.004)
    images = [d.image(k) for k in range(d.num_frames)]
    runs = [feed_engine(build_odometry(BevoConfig(), FUSED, camera=small_camera()), d.imu_stamps, d.gyro, d.accel,
                        frames, lambda k: images[k], by_stamp=by_stamp) for by_stamp in (True, False)]
    a, b = runs
    assert len(a) == len(b) == d.num_frames
    np.testing.assert_array_equal(np.array([s.motion for s in a]), np.array([s.motion for s in b]))
    gyro_yaw = np.array([s.filter_inputs["gyro_yaw"] for s in a[1:]])
    true_yaw = d.relative_motion[:, 2]
    assert np.degrees(np.abs(gyro_yaw - true_yaw)).max() < 0.15  # 0.7-1.2 deg per frame: 0 or 2x before


def _feed_clip(odo, d, f0: int, f1: int, by_stamp: bool = False) -> list:
    """The engine ``odo`` started cold at frame ``f0`` of a drive through ``f1 - 1`` (frames rendered
    as needed, the IMU from 0.15 s around them). -> its steps."""
    sel = (d.imu_stamps >= d.frame_stamps[f0] - 0.15) & (d.imu_stamps <= d.frame_stamps[f1 - 1] + 0.15)
    return feed_engine(odo, d.imu_stamps[sel], d.gyro[sel], d.accel[sel], d.frame_stamps[f0:f1],
                       lambda k: d.image(f0 + k), by_stamp=by_stamp)


def _clip_scores(d, f0: int, f1: int, mode: str) -> tuple[float, float]:
    """(endpoint drift %, yaw RMSE deg) of the engine over frames f0..f1 of a drive."""
    config = BevoConfig()
    config.odometry.mode = mode
    steps = _feed_clip(build_odometry(config, FUSED if mode == "fused" else PAPER, camera=d.camera), d, f0, f1)
    est, gt = np.array([s.motion for s in steps[1:]]), d.relative_motion[f0:f1 - 1]
    assert len(est) == len(gt)
    end_e = integrate_motions(torch.tensor(est))[-1].numpy()
    end_g = integrate_motions(torch.tensor(gt))[-1].numpy()
    drift = float(np.linalg.norm(end_e[:2] - end_g[:2]) / np.linalg.norm(gt[:, :2], axis=1).sum() * 100)
    return drift, float(np.degrees(np.sqrt(np.mean((est[:, 2] - gt[:, 2]) ** 2))))


@pytest.mark.kitti
@pytest.mark.parametrize("drive, first", [("0027", 0), ("0020", 640), ("0018", 2320)])
def test_fused_holds_on_real_imu_clips(kitti_root, drive, first):
    """16 s clips of the shared drives' real IMU and motion, camera rendered: a start in a
    bend that ends in a stop (0027), two right-angle turns at 5 m/s (0020), a stop and a start
    (0018). Fused drift within 5 % (docs/FUSED_ODOMETRY.md: 160-frame clips of all four drives), and far below
    paper mode's (20-60 %). 0018 @ 2320 reads 4.58 % (3.14 % with the suspension pitch gradient
    0.003 before): pulling away in a 28 deg/s turn, the road's slope changes by 1.4 deg in 2.5 s
    and the pitch-change correction, which assumes a constant slope, adds 0.05-0.12 m per pair;
    the lean that now matches the truth no longer offsets part of it (docs/FUSED_ODOMETRY.md, "The suspension's
    pitch gradient")."""
    ox = read_oxts(kitti_root / "raw" / "2011_09_30" / f"2011_09_30_drive_{drive}_sync" / "oxts")
    d = drive_from_oxts(ox.slice(first, first + 175), seed=1, camera=small_camera())
    fused, fused_yaw = _clip_scores(d, 0, 160, "fused")
    paper, paper_yaw = _clip_scores(d, 0, 160, "paper")
    print(f"\n{drive}@{first}: fused drift {fused:.2f} %, yaw {fused_yaw:.3f} deg; paper {paper:.2f} %, {paper_yaw:.3f} deg")
    assert fused <= 5.0 and fused < 0.2 * paper
    assert fused_yaw <= 0.06 and fused_yaw < 0.5 * paper_yaw


@pytest.mark.kitti
def test_a_stop_rocking_on_its_suspension_gives_no_gyro_bias(kitti_root, monkeypatch):
    """0018 braking to a 6 s stop (real IMU and motion, rendered frames, fed by stamp): the car
    rocks back on its suspension as it stops, which the rest intervals' gyro-bias estimate must
    not take for a bias (engine REST_BIAS_SETTLE, REST_BIAS_PRIOR). Measured: 62 of 63 frames at
    rest found, 4.6 cm of creep over the stop, pitch-rate bias -0.017 deg/s. Taken from the first
    still frames with no prior it read -1.25 deg/s: the DUKF's pitch ran off, the BEVs moved, the
    standstill was lost after 3 frames and the stop crept 9.9 m. The inertial speed input (fused
    item 16) now holds that stop by itself (the accelerometer says the car does not move: 61 of 63,
    5 cm), so the rest-bias settings are checked with it off too, where they are all that holds it
    (the test can fail: checked with those settings below). As the OXTS is run (params/kitti.yaml),
    without the pitch/roll gyro bias estimate between stops (``filter.gyro_bias_std`` 0); with it
    (the default, a MEMS IMU's) the stop holds as well, and also without the settling and the prior
    on this clip (61 of 63 frames), so those are checked without it."""
    import bevo_ros.core.odometry as engine_module

    ox = read_oxts(kitti_root / "raw" / "2011_09_30" / "2011_09_30_drive_0018_sync" / "oxts")
    d = drive_from_oxts(ox.slice(2240, 2240 + 175), seed=1, camera=small_camera())
    rest = d.relative_motion[:159, 0] < 0.005
    assert rest.sum() > 50

    def run(learned, gyro_bias_std: float | None = 0.0) -> tuple[int, float, tuple]:
        config = BevoConfig()
        if gyro_bias_std is not None:
            config.filter.gyro_bias_std = gyro_bias_std
        odo = build_odometry(config, learned, camera=d.camera)
        steps = _feed_clip(odo, d, 0, 160, by_stamp=True)
        est = np.array([s.motion for s in steps[1:]])
        return sum(s.standstill for s in steps[1:]), float(np.abs(est[rest, 0]).sum()), odo.gyro_bias

    for name, learned, bias_std in (("default", FUSED, 0.0), ("inertial input off", FUSED_NO_INERTIAL, 0.0),
                                    ("the bias between stops too", FUSED, None)):
        still, creep, bias = run(learned, bias_std)
        print(f"\n{name}: found {still} frames at rest of {rest.sum()}; creep {creep * 100:.1f} cm; gyro bias "
              f"{np.degrees(bias)} deg/s")
        assert still >= 0.9 * rest.sum() and creep < 0.2 and max(abs(b) for b in bias[:2]) < math.radians(0.1)
    monkeypatch.setattr(engine_module, "REST_BIAS_SETTLE", 0.0)
    monkeypatch.setattr(engine_module, "REST_BIAS_PRIOR", 1e-9)
    monkeypatch.setattr(engine_module, "REST_BIAS_MAX", 0.05)
    still, creep, bias = run(FUSED_NO_INERTIAL)
    print(f"without the settling and the prior: {still} frames at rest; creep {creep:.2f} m; gyro bias {np.degrees(bias)} deg/s")
    assert still < 0.5 * rest.sum() and creep > 1.0


@pytest.mark.kitti
def test_render_oxts_bag_through_bevo_run(kitti_root, tmp_path, capsys):
    """``bevo convert --render-oxts`` writes the drive as a bag (frames on the camera clock, the
    10 Hz OXTS at its own stamps, played by stamp); ``run_bag`` (``bevo run``) reads the turn's
    yaw per frame to within 0.05 deg: it read 0 and then twice the turn before the engine fused
    a sample before releasing the frames that wait for it."""
    from bevo_ros import cli
    from bevo_ros.config import load_config
    from bevo_ros.pipeline import run_bag

    oxts = kitti_root / "raw" / "2011_09_30" / "2011_09_30_drive_0027_sync" / "oxts"
    out = tmp_path / "bag"
    assert cli.main(["convert", "--render-oxts", str(oxts), "--first", "0", "--count", "40", "-o", str(out)]) == 0
    assert "rendered camera, frames 0..39" in capsys.readouterr().out
    assert cli.main(["convert", "--render-oxts", str(oxts), "--first", "0", "--count", "40", "-o", str(out)]) == 2
    assert "exists" in capsys.readouterr().err
    config, _ = load_config(REPO_ROOT / "params" / "synthetic.yaml")
    steps, _, odo = run_bag(out, config, config.learned_params_file)
    truth = drive_from_oxts(read_oxts(oxts), render=False)
    est = np.array([s.motion for s in steps[1:]])
    assert len(steps) == 40 and odo.counters.dropped_no_imu == 0
    yaw_err = np.degrees(np.abs(est[:, 2] - truth.relative_motion[:39, 2]))
    print(f"\nyaw per frame: truth {np.degrees(truth.relative_motion[:39, 2]).mean():.2f} deg, error max {yaw_err.max():.3f}")
    assert yaw_err.max() < 0.05


@pytest.mark.kitti
def test_a_creeping_start_is_no_standstill(kitti_root):
    """0018 pulling away from a stop (real motion, rendered frames): around 14 cm per frame, under
    the correlation's CHECK_BELOW, the fine small-motion estimate left its linear range and read
    ~0, a false stop whose zero-rotation update took the frame's 0.7 deg of turn out of the heading.
    The detector's coarse scale reads the motion; the frames at rest before still read as rest."""
    from bevo_ros.core.standstill import StandstillDetector

    ox = read_oxts(kitti_root / "raw" / "2011_09_30" / "2011_09_30_drive_0018_sync" / "oxts")
    d = drive_from_oxts(ox, seed=1, camera=small_camera())
    det = StandstillDetector(d.camera, (0.0, 0.0), 0.1)
    frames = range(2370, 2420)
    moving = np.linalg.norm(d.relative_motion[frames.start:frames.stop - 1, :2], axis=1)
    flagged = []
    for k in frames:
        image = torch.as_tensor(d.image(k))
        if k > frames.start:
            flagged.append(det.at_rest(det.measure(image), float(d.frame_stamps[k] - d.frame_stamps[k - 1])))
        det.remember(image)
    flagged = np.array(flagged)
    print(f"\nat rest: {flagged.sum()} of {len(flagged)}; truth under 1 cm: {(moving < 0.01).sum()}; "
          f"flagged motions up to {moving[flagged].max() * 100:.1f} cm")
    assert not flagged[moving > 0.03].any()
    assert flagged[moving < 0.002].mean() > 0.9


def test_render_oxts_reports_bad_input(tmp_path, capsys):
    """A missing OXTS directory or a frame range outside the drive: a clear error, exit code 2, no bag;
    ``--vertical-curves`` renders, and with real images it is an error."""
    from bevo_ros import cli

    out = tmp_path / "bag"
    assert cli.main(["convert", "--render-oxts", str(tmp_path / "nowhere"), "-o", str(out)]) == 2
    assert "nowhere" in capsys.readouterr().err and not out.exists()
    ox, _ = _circle_oxts(n=30)
    oxts = tmp_path / "oxts"
    (oxts / "data").mkdir(parents=True)
    stamps = [f"2011-09-30 12:00:{(t / 1e9) % 60:012.9f}" for t in ox.stamps_ns]
    (oxts / "timestamps.txt").write_text("\n".join(stamps) + "\n")
    for i, row in enumerate(ox.data):
        (oxts / "data" / f"{i:010d}.txt").write_text(" ".join(f"{v:.12g}" for v in row) + "\n")
    assert cli.main(["convert", "--render-oxts", str(oxts), "--first", "20", "--count", "50", "-o", str(out)]) == 2
    assert "the drive has" in capsys.readouterr().err and not out.exists()
    # --vertical-curves bends the rendered road; real images are what they are
    assert cli.main(["convert", "--render-oxts", str(oxts), "--vertical-curves", "--count", "2", "-o", str(out)]) == 0
    assert "wrote" in capsys.readouterr().out and out.exists()
    assert cli.main(["convert", "--odometry", str(tmp_path), "--vertical-curves", "-o", str(tmp_path / "b2")]) == 2
    assert "--render-oxts only" in capsys.readouterr().err and not (tmp_path / "b2").exists()


@pytest.mark.kitti
def test_eval_real_imu_tool_prints_the_clip_table(kitti_root, tmp_path):
    """tools/eval_real_imu.py (the README's clip table) on drive 0016, 10 s clips: it runs from a
    fresh cache and says what it measured."""
    import re
    import subprocess
    import sys

    out = subprocess.run([sys.executable, str(REPO_ROOT / "tools" / "eval_real_imu.py"), "--drives", "0016",
                          "--raw", str(kitti_root / "raw" / "2011_09_30"), "--length", "100", "--step", "150",
                          "--modes", "fused", "--cache", str(tmp_path)], capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stderr
    m = re.search(r"fused \((\d+) clips of 100 frames\): drift mean ([\d.]+) %", out.stdout)
    assert m and int(m.group(1)) == 2 and float(m.group(2)) < 5.0, out.stdout
    assert (tmp_path / "0016_seed1_620x188.npy").exists()


def test_eval_real_imu_tool_on_synthetic_presets(tmp_path):
    """``--presets``: the same cold-start clip table on synthetic drives (exact truth, no shared
    data), with the first frame pairs' forward error apart and the BEV's road pitch error the
    scale error follows; an unknown preset is a clear error."""
    import re
    import subprocess
    import sys

    tool = str(REPO_ROOT / "tools" / "eval_real_imu.py")
    out = subprocess.run([sys.executable, tool, "--presets", "curve", "--length", "40", "--step", "60",
                          "--modes", "fused", "--cache", str(tmp_path)], capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stderr
    m = re.search(r"fused \((\d+) clips of 40 frames\): drift mean ([\d.]+) %", out.stdout)
    assert m and int(m.group(1)) == 3 and float(m.group(2)) < 10.0, out.stdout  # a 16 s preset: clips at 0, 60, 120
    first = re.search(r"first 5 frame pairs .*?\) ([\d. /]+) cm, later pairs ([\d.]+) cm", out.stdout)
    assert first, out.stdout
    pairs = [float(v) for v in first.group(1).split("/")]
    assert len(pairs) == 5 and all(0.0 < v < 100.0 for v in pairs) and 0.0 < float(first.group(2)) < 50.0
    # the scale error's attribution: the BEV's road pitch error while moving against the exact truth
    pitch = re.search(r"fused: the BEV's road pitch error while moving .*? RMS ([\d.]+) deg; the clips' scale error "
                      r"follows it at ([-+\d.]+) % per 0.1 deg \(correlation ([-+\d.]+)\)", out.stdout)
    assert pitch, out.stdout
    assert 0.0 < float(pitch.group(1)) < 0.3 and -1.0 <= float(pitch.group(3)) <= 1.0
    # the published gravity attitude after each clip's first second, against the exact truth
    gravity = re.search(r"fused: the published gravity attitude \(after each clip's first 1 s\) pitch / roll RMS "
                        r"([\d.]+) / ([\d.]+) deg", out.stdout)
    assert gravity and all(0.0 < float(v) < 5.0 for v in gravity.groups()), out.stdout
    assert (tmp_path / "preset_curve_seed1_10hz_620x188.npy").exists()
    # --starts picks one clip, --pairs prints its frame pairs: error = engine - truth, and the
    # correlation's own reading less the pitch-change shift is what the filter was given
    one = subprocess.run([sys.executable, tool, "--presets", "curve", "--length", "40", "--starts", "60", "--pairs",
                          "--modes", "fused", "--cache", str(tmp_path)], capture_output=True, text=True, timeout=600)
    assert one.returncode == 0, one.stderr
    assert "fused (1 clips of 40 frames)" in one.stdout and "curve/1 60 fused: pair;" in one.stdout, one.stdout
    rows = [line.split() for line in one.stdout.splitlines() if re.match(r"^\s+\d+\s+[-\d.]+\s", line)]
    assert [int(r[0]) for r in rows] == list(range(1, 40)), one.stdout
    for r in rows:
        truth, engine, error = float(r[1]), float(r[2]), float(r[3])
        assert abs(engine - truth - error) <= 0.0015 and 0.5 < truth < 2.5 and r[-1] in ("yy", "yn", "ny", "nn")
    assert np.sqrt(np.mean([float(r[3]) ** 2 for r in rows])) < 0.2  # a 15 m/s bend read to well under 20 cm
    bad = subprocess.run([sys.executable, tool, "--presets", "curve,nope", "--cache", str(tmp_path)],
                         capture_output=True, text=True, timeout=120)
    assert bad.returncode == 2 and "unknown presets ['nope']" in bad.stderr
    bad = subprocess.run([sys.executable, tool, "--presets", "curve", "--starts", "60,x"],
                         capture_output=True, text=True, timeout=120)
    assert bad.returncode == 2 and "expected comma-separated frame numbers" in bad.stderr
    # The same clips from the same cached frames with the IMU changed, each refused without --presets:
    # --gyro-bias, an uncalibrated MEMS gyro's 1 deg/s, whose pitch bias passes the road-tilt high-pass into
    # the BEV (measured 1.8 -> 5.6 % drift); --grade, a 5 deg hill under every cold start, whose slope the
    # DUKF's start converges to over seconds (1.8 -> 5.5 %).
    for option, value in (("--gyro-bias", "1.0"), ("--grade", "5")):
        varied = subprocess.run([sys.executable, tool, "--presets", "curve", "--length", "40", "--step", "60",
                                 "--modes", "fused", "--cache", str(tmp_path), option, value],
                                capture_output=True, text=True, timeout=600)
        assert varied.returncode == 0, varied.stderr
        mv = re.search(r"fused \((\d+) clips of 40 frames\): drift mean ([\d.]+) %", varied.stdout)
        assert mv and int(mv.group(1)) == 3 and float(mv.group(2)) > float(m.group(2)) + 2.0, (out.stdout, varied.stdout)
        bad = subprocess.run([sys.executable, tool, option, value], capture_output=True, text=True, timeout=120)
        assert bad.returncode == 2 and f"{option} needs --presets" in bad.stderr
    # --true-road-pitch: the same clips with the BEV at the truth's road pitch, the ceiling a perfect road pitch
    # reaches (measured 1.8 -> 0.3 % drift); paper mode has no road pitch to replace
    ideal = subprocess.run([sys.executable, tool, "--presets", "curve", "--length", "40", "--step", "60",
                            "--modes", "fused", "--cache", str(tmp_path), "--true-road-pitch"],
                           capture_output=True, text=True, timeout=600)
    assert ideal.returncode == 0, ideal.stderr
    mi = re.search(r"fused \((\d+) clips of 40 frames\): drift mean ([\d.]+) %", ideal.stdout)
    assert mi and int(mi.group(1)) == 3 and float(mi.group(2)) < 0.5 * float(m.group(2)), (out.stdout, ideal.stdout)
    assert "the BEV at the true road pitch" in ideal.stdout and "follows it at" not in ideal.stdout
    bad = subprocess.run([sys.executable, tool, "--presets", "curve", "--modes", "fused,paper", "--true-road-pitch"],
                         capture_output=True, text=True, timeout=120)
    assert bad.returncode == 2 and "--true-road-pitch needs --modes fused" in bad.stderr


def test_eval_real_imu_acceptance_table(tmp_path):
    """``--presets ... --acceptance``: issue 9's table, each drive whole in both modes, each figure
    against its target, and whether fused beats paper; ``--vertical-curves`` the same over crests and
    sags; without ``--presets`` a clear error."""
    import re
    import subprocess
    import sys

    tool = str(REPO_ROOT / "tools" / "eval_real_imu.py")
    out = subprocess.run([sys.executable, tool, "--presets", "braking", "--acceptance", "--cache", str(tmp_path)],
                         capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stderr
    rows = {m.group(1): [float(v) for v in m.groups()[1:]] for m in re.finditer(
        r"braking/1 +(fused|paper) +([\d.]+) / +([\d.]+) \w+ +([\d.]+) \w+ +([\d.]+) \w+ +([\d.]+) \w+ +[-+\d.]+",
        out.stdout)}
    assert set(rows) == {"fused", "paper"}, out.stdout
    fused, paper = rows["fused"], rows["paper"]  # pitch, roll (deg), per frame (%), yaw (deg), drift (%)
    assert all(0.0 < v for v in fused) and fused[2] < paper[2] and fused[3] < paper[3], out.stdout
    assert re.search(r"fused: targets met \(of 1 drives\): attitude <= 0.3 deg [01], per frame <= 3.0 % [01], "
                     r"yaw <= 0.05 deg [01], drift <= 1.0 % [01]", out.stdout), out.stdout
    assert "fused beats paper on every metric in 1 of 1 drives" in out.stdout, out.stdout
    # the published gravity attitude (OdometryStep.rpy, after the first second): paper mode reads the
    # -5 m/s^2 braking as ~30 deg of tilt in the accelerometer (measured 9.9 deg RMS), fused mode subtracts
    # the car's acceleration (1.1 deg)
    gravity = {m.group(1): (float(m.group(2)), float(m.group(3))) for m in re.finditer(
        r"(fused|paper): the published gravity attitude \(after the first 1 s\), pitch / roll RMS, mean of the "
        r"drives ([\d.]+) / ([\d.]+) deg", out.stdout)}
    assert set(gravity) == {"fused", "paper"}, out.stdout
    assert 0.0 < gravity["fused"][0] < 0.5 * gravity["paper"][0] and 0.0 < gravity["fused"][1] < 3.0, out.stdout
    # over crests and sags: its own frames (a cache of their own), the same table
    hills = subprocess.run([sys.executable, tool, "--presets", "braking", "--acceptance", "--vertical-curves", "--modes",
                            "fused", "--cache", str(tmp_path)], capture_output=True, text=True, timeout=600)
    assert hills.returncode == 0, hills.stderr
    assert "whole drives over crests and sags:" in hills.stdout, hills.stdout
    assert len(list(tmp_path.glob("*_hills.npy"))) == 1
    bent = re.search(r"braking/1 +fused +[\d.]+ / +[\d.]+ \w+ +([\d.]+) ", hills.stdout)
    assert bent and float(bent.group(1)) != fused[2], hills.stdout  # other images, another per-frame error
    # --learned: a candidate learned file for fused mode (the inertial speed input off), on the same frames
    candidate = tmp_path / "candidate.yaml"
    default = (REPO_ROOT / "params" / "learned_default.yaml").read_text()
    assert "  imu_accel_density: 1.0\n" in default
    candidate.write_text(default.replace("  imu_accel_density: 1.0\n", "  imu_accel_density: 0.0\n"))
    other = subprocess.run([sys.executable, tool, "--presets", "braking", "--acceptance", "--modes", "fused",
                            "--cache", str(tmp_path), "--learned", str(candidate)], capture_output=True, text=True,
                           timeout=600)
    assert other.returncode == 0, other.stderr
    moved = re.search(r"braking/1 +fused +[\d.]+ / +[\d.]+ \w+ +([\d.]+) ", other.stdout)
    assert moved and float(moved.group(1)) != fused[2], other.stdout
    bad = subprocess.run([sys.executable, tool, "--presets", "braking", "--learned", str(tmp_path / "none.yaml")],
                         capture_output=True, text=True, timeout=60)
    assert bad.returncode != 0 and "none.yaml" in bad.stderr
    # tools/eval_set.py reads this table into its one-line summary
    import importlib.util

    spec = importlib.util.spec_from_file_location("eval_set", REPO_ROOT / "tools" / "eval_set.py")
    eval_set = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(eval_set)
    line = eval_set.clips(["--presets", "braking", "--acceptance", "--cache", str(tmp_path)], None)
    assert line == (f"road pitch / roll {fused[0]:.2f} / {fused[1]:.2f} deg, per frame {fused[2]:.2f} %, "
                    f"yaw {fused[3]:.3f} deg, drift {fused[4]:.2f} %; gravity pitch / roll "
                    f"{gravity['fused'][0]:.2f} / {gravity['fused'][1]:.2f} deg"), line
    bad = subprocess.run([sys.executable, tool, "--acceptance"], capture_output=True, text=True, timeout=60)
    assert bad.returncode == 2 and "--acceptance needs --presets" in bad.stderr
    bad = subprocess.run([sys.executable, tool, "--presets", "braking", "--vertical-curves", "--traffic"],
                         capture_output=True, text=True, timeout=60)
    assert bad.returncode == 2 and "--vertical-curves and --traffic cannot be combined" in bad.stderr


@pytest.mark.kitti
def test_a_cold_start_behind_a_car_keeps_the_first_pairs_speed(kitti_root, monkeypatch):
    """0027 with traffic, started cold at frame 480 (4.7 m/s behind a car moving with ours): the
    first pair reads the road (0.55 m for 0.47 m), its variance wide with the spread of the
    road's and the car's peaks (0.56 m std; 0.064 m without traffic). With a prediction that wide
    taken as no prediction (the peak prior's limit at
    0.5 m, before), the second pair took the highest peak, the car's at ~0, and the motion filter
    followed it to a stop for four frames (-49 cm each); with the limit at 1 m the prediction picks
    the road's peak (read 14-20 cm long in those pairs, 8-11 cm without traffic: the cold start's
    attitude; found, not fixed)."""
    import bevo_ros.core.odometry as odometry

    d = drive_from_oxts(read_oxts(kitti_root / "raw" / "2011_09_30" / "2011_09_30_drive_0027_sync" / "oxts"),
                        seed=1, camera=small_camera(), traffic=True)
    f0, f1 = 480, 488

    def forward_errors() -> np.ndarray:
        steps = _feed_clip(build_odometry(BevoConfig(), FUSED, camera=d.camera), d, f0, f1, by_stamp=True)
        return np.array([s.motion[0] for s in steps[1:]]) - d.relative_motion[f0:f1 - 1, 0]

    err = forward_errors()
    monkeypatch.setattr(odometry, "PEAK_PRIOR_MAX_STD", 0.5)
    before = forward_errors()
    print(f"\nforward error per pair (cm): {np.round(err * 100, 1)}; with the 0.5 m limit {np.round(before * 100, 1)}")
    assert np.abs(err).max() < 0.25
    assert before[1:5].min() < -0.3


@pytest.mark.kitti
def test_a_cold_start_in_an_acceleration_keeps_the_suspensions_input(kitti_root):
    """0027 started cold at frame 480, accelerating 0.5 -> 1.7 m/s^2 over 2 s.

    - With the inertial speed input off, the DUKF only widens its accelerometer variance by the
      acceleration's size and reads the acceleration as tilt: its pitch 3.5 deg off within 2 s (its
      variance marks those updates as unconverged). The suspension's input, the forward
      acceleration ``a_x + g sin(pitch)``, takes the DUKF's pitch less those updates over the last
      ``KEPT_OUT_MEMORY``: 0.26 m/s^2 RMS from the true one over 0.5-2 s (with the DUKF's pitch as it
      is, measured when this came: 0.57 m/s^2, half the acceleration missing by 2 s).
    - By default (fused item 17) the DUKF subtracts the motion filter's acceleration at its
      variance: 0.8 deg off at most, the suspension's input 0.17 m/s^2 RMS from the truth.
    """
    d = drive_from_oxts(read_oxts(kitti_root / "raw" / "2011_09_30" / "2011_09_30_drive_0027_sync" / "oxts"),
                        seed=1, camera=small_camera())
    f0, f1 = 480, 501
    for name, learned, pitch_bound in (("inertial input off", FUSED_NO_INERTIAL, None), ("default", FUSED, 1.5)):
        odo = build_odometry(BevoConfig(), learned, camera=d.camera)
        seen: list[tuple[float, float, float]] = []
        fuse = odo._fuse_imu

        def recording(stamp, g, a, fuse=fuse, odo=odo, seen=seen):
            fuse(stamp, g, a)
            seen.append((stamp, math.nan if odo._acc_fx is None else odo._acc_fx, odo._state[0][0]))

        odo._fuse_imu = recording
        _feed_clip(odo, d, f0, f1, by_stamp=True)
        t, acc, pitch = (np.array(v) for v in zip(*seen))
        true_acc = np.interp(t, d.frame_stamps[1:], np.diff(d.speed) / np.diff(d.frame_stamps))
        true_pitch = np.interp(t, d.imu_stamps, d.imu_pitch_roll_gravity[:, 0])
        window = (t - t[0] >= 0.5) & (t - t[0] <= 2.0)
        err = float(np.sqrt(np.mean((acc - true_acc)[window] ** 2)))
        pitch_err = float(np.degrees(np.abs(pitch - true_pitch)[window]).max())
        print(f"\n{name}: forward acceleration error {err:.2f} m/s^2 RMS; the DUKF's pitch off by up to "
              f"{pitch_err:.1f} deg")
        if pitch_bound is None:
            assert pitch_err > 2.0  # the case: the DUKF misreads the acceleration
        else:
            assert pitch_err < pitch_bound  # measured 0.8 (3.5 with the input off)
        assert err < 0.4


@pytest.mark.kitti
def test_a_corner_after_a_braking_start_keeps_the_pitch_change_correction_off(kitti_root, monkeypatch):
    """0018 started cold at frame 102: a 2.4 m/s^2 braking leaves the DUKF's pitch ~2.5 deg off
    (kept out of the BEV), then a 32 deg/s corner at 3.7 m/s rotates that error into roll, and
    the roll error back into a ~1 deg/s pitch drift (Euler kinematics) that is neither the car's
    nor the road's. Taken as the car's by the pitch-change correction, it came off the forward
    motion (+0.1..+0.2 m of 0.37 m per pair: scale -19 % over the 5 s); with the correction off
    while yaw rate x sqrt(the DUKF's roll variance above steady state) is over
    TURN_ROLL_RATE_GATE, about half that. Measured with the inertial speed input (fused item 16):
    -21.5 % without the gate, -11.6 % with it (-10.7 % with the input off: a braking start's
    gravity error is what the input's bias state has not learnt yet). With the DUKF subtracting the
    motion filter's acceleration (fused item 17) the start's error stays longer (the accelerometer
    counts little while the acceleration is unknown): -17.8 % without the gate, -14.6 % with it."""
    import bevo_ros.core.odometry as odometry

    d = drive_from_oxts(read_oxts(kitti_root / "raw" / "2011_09_30" / "2011_09_30_drive_0018_sync" / "oxts"),
                        seed=1, camera=small_camera())
    f0, f1 = 102, 153
    gt = d.relative_motion[f0:f1 - 1]

    def run() -> tuple[float, np.ndarray, int]:
        odo = build_odometry(BevoConfig(), FUSED, camera=d.camera)
        steps = _feed_clip(odo, d, f0, f1, by_stamp=True)
        est = np.array([s.motion for s in steps[1:]])
        assert len(est) == len(gt)
        return (float((est[:, 0].sum() - gt[:, 0].sum()) / gt[:, 0].sum() * 100),
                np.array([s.pitch_shift for s in steps[1:]]), odo.counters.pitch_correction_off)

    gated, shifts, off = run()
    monkeypatch.setattr(odometry, "TURN_ROLL_RATE_GATE", math.inf)
    ungated, shifts_ungated, off_ungated = run()
    turning = np.abs(gt[:, 2]) > math.radians(2.0)  # > ~20 deg/s at 10 Hz
    by_the_gate = turning & (shifts == 0) & (shifts_ungated != 0)  # not the pull gate's doing
    print(f"\nscale error {ungated:+.1f} % without the turn gate, {gated:+.1f} % with it; the turn gate took the "
          f"correction off in {int(by_the_gate.sum())} of {int(turning.sum())} turning pairs")
    assert turning.sum() >= 15 and by_the_gate.sum() >= turning.sum() // 2
    assert off >= by_the_gate.sum() + off_ungated // 2 and off > off_ungated  # counted (Counters, /diagnostics)
    assert ungated < -14.0  # the case
    assert gated > -16.0 and gated > ungated + 2.0
