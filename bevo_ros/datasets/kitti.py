"""KITTI readers: odometry and raw layouts, OXTS, calibration, ground-truth poses.

Pure numpy (torch only for :func:`camera_model_from_kitti`). Every parse error names the file
and the 1-based line number, because these files are edited and copied by hand.

Frames (see ``bevo_ros/core/geometry.py``):

* ``cam`` = the rectified camera-0 frame (optical axes), the frame of the odometry poses.
  ``poses/NN.txt`` line ``i`` is ``T_world_cam_i`` (3x4, row-major) with ``world`` = ``cam_0``.
* ``base`` = the OXTS IMU frame (x forward, y left, z up).
* Raw calibration chain: ``p_velo = T_velo_imu p_imu``, ``p_cam00 = T_cam00_velo p_velo`` (the
  unrectified camera 0), ``p_rect0 = R_rect_00 p_cam00``; for camera ``i`` the rectified frames
  differ by the translation in ``P_rect_0i`` only.
"""
from __future__ import annotations

import bisect
import calendar
import math
import re
from dataclasses import dataclass
from datetime import datetime
from pathlib import Path
from typing import Iterable

import numpy as np

from bevo_ros.io.ros_conversions import ns_to_seconds, out_of_order

PathLike = str | Path

# KITTI odometry devkit (readme.txt): sequence -> (raw drive, first raw frame, last raw frame).
# Odometry frame i is raw synced frame start + i; the pose files have end - start + 1 lines.
ODOMETRY_TO_RAW: dict[str, tuple[str, int, int]] = {
    "00": ("2011_10_03_drive_0027", 0, 4540),
    "01": ("2011_10_03_drive_0042", 0, 1100),
    "02": ("2011_10_03_drive_0034", 0, 4660),
    "03": ("2011_09_26_drive_0067", 0, 800),
    "04": ("2011_09_30_drive_0016", 0, 270),
    "05": ("2011_09_30_drive_0018", 0, 2760),
    "06": ("2011_09_30_drive_0020", 0, 1100),
    "07": ("2011_09_30_drive_0027", 0, 1100),
    "08": ("2011_09_30_drive_0028", 1100, 5170),
    "09": ("2011_09_30_drive_0033", 0, 1590),
    "10": ("2011_09_30_drive_0034", 0, 1200),
}

# The camera's tilt to the road differs between KITTI's recording days: the ground truth's mean
# direction of travel in camera 0's frame (poses/NN.txt, distance-weighted), deg below the optical axis.
# params/kitti.yaml's mounting was fitted on 2011_09_30 (the sample). Measured 2026-12-07: 04-07
# 1.18-1.20, 08 1.24; 00 0.96, 02 0.98; 03 (2011_09_26_drive_0067, public copy of poses/03.txt) -0.36.
# The engine's scale follows it: the sample with the tilt 0.22 / 1.55 deg too small drifts 5.3 / 36.8 %
# instead of 0.9 % (README, Limitations).
GROUND_TRUTH_CAMERA_TILT_DEG = {"2011_09_26": -0.36, "2011_09_30": 1.19, "2011_10_03": 0.97}
PARAMS_TILT_DAY = "2011_09_30"  # the day params/kitti.yaml's filter.mounting_pitch was fitted on


def day_tilt_note(date: str, bag: str = "BAG") -> str | None:
    """What ``bevo convert`` says about a ``date`` drive's camera tilt against params/kitti.yaml's, for
    its output ``bag`` (None for the day it was fitted on, or no day)."""
    if not re.fullmatch(r"\d{4}_\d{2}_\d{2}", date or "") or date == PARAMS_TILT_DAY:
        return None  # not a KITTI day (an --oxts folder elsewhere), or the params' own
    how = ("params/kitti.yaml's engine measures it from the drive's first 30 frame pairs (filter.tilt_from_images: "
           f"keep it on, node and `bevo run` alike), or over up to 600 frames: `bevo run {bag} --tilt-from-images` "
           f"(for bevo_node: `bevo calibrate {bag} --from-images` prints the params lines)")
    if date not in GROUND_TRUTH_CAMERA_TILT_DEG:
        return (f"params/kitti.yaml's camera tilt (filter.mounting_pitch) was fitted on {PARAMS_TILT_DAY} drives, and "
                f"KITTI's camera tilt changed between days by up to 1.5 deg (~2 % of scale per 0.1 deg); for this "
                f"{date} drive {how}")
    less = GROUND_TRUTH_CAMERA_TILT_DEG[PARAMS_TILT_DAY] - GROUND_TRUTH_CAMERA_TILT_DEG[date]
    return (f"params/kitti.yaml's camera tilt (filter.mounting_pitch) was fitted on {PARAMS_TILT_DAY} drives; "
            f"{date}'s ground truth has the camera {abs(less):.2f} deg {'less' if less > 0 else 'more'} tilted to the "
            f"road (its direction of travel), and the engine's scale follows the tilt (~2 % per 0.1 deg: with the "
            f"params' tilt as is this drive may read {'short' if less > 0 else 'long'}); {how}")


# Column indices of the 30 OXTS fields (dataformat.txt).
OXTS_FIELDS = (
    "lat", "lon", "alt", "roll", "pitch", "yaw", "vn", "ve", "vf", "vl", "vu",
    "ax", "ay", "az", "af", "al", "au", "wx", "wy", "wz", "wf", "wl", "wu",
    "pos_accuracy", "vel_accuracy", "navstat", "numsats", "posmode", "velmode", "orimode",
)
OXTS_INDEX = {name: i for i, name in enumerate(OXTS_FIELDS)}

_STAMP_RE = re.compile(r"^(\d{4})-(\d{2})-(\d{2}) (\d{2}):(\d{2}):(\d{2})(?:\.(\d{1,9}))?$")


# ----------------------------------------------------------------------------------------------
# Small parsing helpers
# ----------------------------------------------------------------------------------------------
def _require_file(path: PathLike, what: str) -> Path:
    path = Path(path)
    if path.is_dir():
        raise FileNotFoundError(f"{path}: a directory, not the {what}")
    if not path.is_file():
        raise FileNotFoundError(f"{path}: {what} not found")
    return path


def _require_dir(path: PathLike, what: str) -> Path:
    path = Path(path)
    if not path.is_dir():
        raise FileNotFoundError(f"{path}: {what} directory not found")
    return path


def _parse_floats(text: str, path: Path, lineno: int, count: int | None = None) -> np.ndarray:
    """Whitespace-separated floats of one line; ``count`` checks their number."""
    try:
        values = np.array([float(tok) for tok in text.split()], dtype=np.float64)
    except ValueError as exc:
        raise ValueError(f"{path}:{lineno}: cannot parse numbers ({exc}): {text.strip()[:80]!r}") from None
    if count is not None and values.size != count:
        raise ValueError(f"{path}:{lineno}: expected {count} numbers, found {values.size}")
    if not np.all(np.isfinite(values)):
        raise ValueError(f"{path}:{lineno}: non-finite number: {text.strip()[:80]!r}")
    return values


def _content_lines(path: Path) -> Iterable[tuple[int, str]]:
    """(1-based line number, text) of the non-blank lines."""
    with open(path, "r", encoding="utf-8", errors="replace") as f:
        for lineno, line in enumerate(f, start=1):
            if line.strip():
                yield lineno, line


def parse_timestamp_ns(text: str, path: PathLike = "<string>", lineno: int = 0) -> int:
    """``'2011-09-30 12:08:26.521831936'`` -> integer nanoseconds since the epoch (read as UTC).

    Integer arithmetic keeps the nanoseconds exact (a float64 of ~1.3e9 s resolves ~0.2 us).
    """
    m = _STAMP_RE.match(text.strip())
    if m is None:
        raise ValueError(f"{path}:{lineno}: cannot parse timestamp {text.strip()[:80]!r} "
                         "(expected 'YYYY-MM-DD HH:MM:SS.fffffffff')")
    year, month, day, hour, minute, second = (int(g) for g in m.groups()[:6])
    frac = (m.group(7) or "").ljust(9, "0")
    try:
        seconds = calendar.timegm((year, month, day, hour, minute, second, 0, 0, 0))
    except (ValueError, OverflowError) as exc:
        raise ValueError(f"{path}:{lineno}: invalid date/time {text.strip()!r} ({exc})") from None
    if not (1 <= month <= 12 and 1 <= day <= 31 and hour < 24 and minute < 60 and second < 61):
        raise ValueError(f"{path}:{lineno}: invalid date/time {text.strip()!r}")
    return seconds * 1_000_000_000 + int(frac)


def read_timestamps_ns(path: PathLike, increasing: bool = True) -> np.ndarray:
    """A KITTI raw ``timestamps.txt`` -> ``(N,)`` int64 nanoseconds since the epoch.

    Blank lines are rejected: in raw data they mark dropped frames, which cannot be aligned.
    ``increasing``: stamps must be strictly increasing (else ValueError naming the line); False
    leaves that to the caller (an OXTS stamp out of order is one bad record, not a bad file).
    """
    path = _require_file(path, "timestamps file")
    stamps = []
    blank = None
    with open(path, "r", encoding="utf-8", errors="replace") as f:
        for lineno, line in enumerate(f, start=1):
            if not line.strip():
                blank = blank or lineno  # fine at the end of the file, an error before a stamp
                continue
            if blank is not None:
                raise ValueError(f"{path}:{blank}: empty timestamp line (dropped frame?)")
            stamps.append(parse_timestamp_ns(line, path, lineno))
    if not stamps:
        raise ValueError(f"{path}: no timestamps")
    out = np.asarray(stamps, dtype=np.int64)
    bad = np.flatnonzero(out_of_order(out))
    if bad.size and increasing:
        raise ValueError(f"{path}:{bad[0] + 1}: timestamps not strictly increasing")
    return out


def read_timestamps(path: PathLike) -> np.ndarray:
    """A KITTI raw ``timestamps.txt`` -> ``(N,)`` float64 seconds since the epoch."""
    return ns_to_seconds(read_timestamps_ns(path))


# ----------------------------------------------------------------------------------------------
# OXTS
# ----------------------------------------------------------------------------------------------
@dataclass
class OxtsData:
    """Synced OXTS records of one raw drive.

    Attributes:
        stamps_ns: ``(N,)`` int64 nanoseconds since the epoch (exact).
        data: ``(N, 30)`` float64, the fields of ``OXTS_FIELDS``.
        directory: the ``oxts`` directory read.
    """

    stamps_ns: np.ndarray
    data: np.ndarray
    directory: Path | None = None

    def __len__(self) -> int:
        return int(self.data.shape[0])

    @property
    def stamps(self) -> np.ndarray:
        """``(N,)`` float64 seconds since the epoch."""
        return ns_to_seconds(self.stamps_ns)

    def field(self, name: str) -> np.ndarray:
        """One named column, ``(N,)``."""
        return self.data[:, OXTS_INDEX[name]]

    @property
    def accel(self) -> np.ndarray:
        """``(N, 3)`` ax, ay, az in the vehicle (base) frame, m/s^2, gravity included."""
        return self.data[:, 11:14]

    @property
    def gyro(self) -> np.ndarray:
        """``(N, 3)`` wx, wy, wz in the vehicle (base) frame, rad/s."""
        return self.data[:, 17:20]

    @property
    def roll(self) -> np.ndarray:
        return self.data[:, 3]

    @property
    def pitch(self) -> np.ndarray:
        return self.data[:, 4]

    @property
    def yaw(self) -> np.ndarray:
        return self.data[:, 5]

    def slice(self, start: int, stop: int) -> "OxtsData":
        """Records ``start:stop``."""
        return OxtsData(self.stamps_ns[start:stop].copy(), self.data[start:stop].copy(), self.directory)


EARTH_RADIUS = 6378137.0  # m, the KITTI devkit's Mercator sphere


def oxts_positions(lat_deg: np.ndarray, lon_deg: np.ndarray) -> np.ndarray:
    """East / north metres from the first record (Mercator scaled at the first latitude, as the
    KITTI devkit's ``convertOxtsToPose``). ``(N,)``, ``(N,)`` -> ``(N, 2)``."""
    scale = math.cos(math.radians(float(lat_deg[0])))
    x = scale * EARTH_RADIUS * np.radians(lon_deg)
    y = scale * EARTH_RADIUS * np.log(np.tan(np.radians(90.0 + np.asarray(lat_deg)) / 2.0))
    xy = np.stack([x, y], -1)
    return xy - xy[0]


def oxts_poses(oxts: "OxtsData", stamps_ns: np.ndarray | None = None) -> np.ndarray:
    """The OXTS unit's own GPS/INS poses, as the KITTI raw devkit's ``convertOxtsToPose``: position
    east / north (:func:`oxts_positions`) and altitude, attitude ``Rz(yaw) Ry(pitch) Rx(roll)``,
    relative to the first pose. The unit is the base (KITTI's IMU frame: x forward, y left, z up).

    ``stamps_ns (N,)``: record i's pose moved to stamp i (the camera's) by its own velocity and
    rates. A synced record is the unit's packet nearest the camera's trigger, up to ~10 ms away
    (drives 0016-0027: 3-13 ms RMS from a steady camera clock): at 12 m/s that moves a frame's
    motion by centimetres (its length against the odometry poses of 04-07: 3.3-6.9 cm RMS at the
    records' stamps, 0.25-0.40 cm at the camera's). -> ``(N, 4, 4)`` ``T_world_imu``, the first the identity."""
    from scipy.spatial.transform import Rotation

    T = np.tile(np.eye(4), (len(oxts), 1, 1))
    T[:, :2, 3] = oxts_positions(oxts.field("lat"), oxts.field("lon"))
    T[:, 2, 3] = oxts.field("alt") - oxts.field("alt")[0]
    rpy = np.stack([oxts.field("roll"), oxts.field("pitch"), oxts.field("yaw")], axis=1)
    rotation = Rotation.from_euler("ZYX", rpy[:, ::-1])  # intrinsic ZYX = Rz Ry Rx
    if stamps_ns is not None:
        dt = (np.asarray(stamps_ns, dtype=np.int64) - oxts.stamps_ns) * 1e-9  # (N,) s, exact in int64
        T[:, :3, 3] += np.stack([oxts.field("ve"), oxts.field("vn"), oxts.field("vu")], axis=1) * dt[:, None]
        rotation = rotation * Rotation.from_rotvec(oxts.gyro * dt[:, None])  # body rates
    T[:, :3, :3] = rotation.as_matrix()
    return np.linalg.inv(T[0]) @ T


def misstamped(stamps_ns: np.ndarray) -> np.ndarray:
    """``(N,)`` bool: the records outside the longest run of strictly increasing stamps (on ties the
    earlier record stays), i.e. the fewest records whose stamps cannot be placed in time. Unlike
    :func:`~bevo_ros.io.ros_conversions.out_of_order` (each stamp against the highest before it), one
    record stamped too late leaves out that record, not the good ones after it (the raw extract's
    100 Hz OXTS has such jumps)."""
    t = np.asarray(stamps_ns)
    tails: list[int] = []  # tails[k]: index of the smallest last stamp of an increasing run of length k + 1
    tail_stamps: list[int] = []
    before = np.full(len(t), -1)
    for i, s in enumerate(t.tolist()):
        k = bisect.bisect_left(tail_stamps, s)
        if k < len(tail_stamps) and tail_stamps[k] == s:
            continue  # a stamp equal to a run's end: the earlier record keeps it
        before[i] = tails[k - 1] if k else -1
        if k == len(tails):
            tails.append(i)
            tail_stamps.append(s)
        else:
            tails[k], tail_stamps[k] = i, s
    bad = np.ones(len(t), dtype=bool)
    i = tails[-1] if tails else -1
    while i >= 0:
        bad[i] = False
        i = before[i]
    return bad


def interpolated_oxts(oxts: OxtsData, rtol: float = 1e-9) -> np.ndarray:
    """``(N,)`` bool: the records KITTI's synchronisation filled in where the unit's packets were
    lost, by linear interpolation between the real records on either side. Such a record's six
    IMU channels (``ax..az``, ``wx..wz``) all lie exactly on the straight line through its two
    neighbours (second difference below ``rtol`` of their size; the files' 1e-15 rounding), which
    a real sensor's noise never does. They are no measurement: drive 0020's records 1-11 ramp the
    yaw rate from 2.75 to 0.64 deg/s while the unit's own heading turns 0.36 deg/s (the KITTI
    sample's 1.3 deg of heading error), drive 0018 has 14 at record 1500. The first and last
    records cannot be judged (no neighbour on one side): False.
    """
    return linear_fill(np.concatenate([oxts.accel, oxts.gyro], 1), rtol)


# rad: a bridged run's attitude change above this is no car's between two packets a second or so apart:
# the run is left as KITTI wrote it (a wrong record at its end, not a lost stretch)
BRIDGE_MAX_ANGLE = math.radians(45.0)


def interpolated_runs(interpolated: np.ndarray) -> list[tuple[int, int]]:
    """``(N,)`` bool -> the ``[start, stop)`` index ranges of its runs of True."""
    x = np.concatenate([[False], np.asarray(interpolated, dtype=bool), [False]]).astype(np.int8)
    edges = np.flatnonzero(np.diff(x))
    return [(int(a), int(b)) for a, b in zip(edges[::2], edges[1::2])]


def bridged_imu(oxts: OxtsData, interpolated: np.ndarray) -> tuple[np.ndarray, np.ndarray, list[tuple[int, int]]]:
    """The IMU's rates and accelerations with each run of KITTI's interpolated records
    (:func:`interpolated_oxts`) replaced by what the unit itself measured across it.
    -> ``(N, 3)`` rad/s, ``(N, 3)`` m/s^2 and the runs bridged, ``[start, stop)``.

    KITTI filled the run with the line between the real records on either side (``i`` and ``j``),
    but the unit's state at those two real records holds the integrals of the lost packets: its INS
    integrated their rates into its attitude and their specific force into its velocity. On drive
    0020 (the KITTI sample's first 1.2 s) the line turns the heading by 1.9 deg where the unit's
    attitude turns 0.43 deg and the images' epipolar rotation ~0.0-0.1 deg (per pair ~0.09 deg
    scatter), and its lateral acceleration is 0.94 m/s^2 off the unit's velocity change (over real
    1.2 s windows of the shared drives the two agree to 0.03-0.05 m/s^2 std). Both are bridged: the
    rates alone, with the line's lateral acceleration no longer matching the turn, read as a 6 deg
    roll in the DUKF (the sample's gravity roll 1.15 -> 2.14 deg RMS; both: 0.65).

    Each run's channels become the smoothest profile (least squared change) that starts and ends at
    the real records and has the unit's mean over ``[t_i, t_j]``: the line plus a parabola
    ``s (1 - s)`` in the run's time fraction ``s``, scaled so that the records' trapezoid over the
    run (what an integrator of the samples sees; a single lost packet's parabola alone would give 75 %
    of it) has that mean. The rates' mean is the rotation vector of ``R_i^T R_j`` over the span
    (``R = Rz(yaw) Ry(pitch) Rx(roll)``, so the body's rates; a second's coning is negligible); the
    specific force's is the mean over the run of ``R(s)^T (dv/dt + g z)``, ``dv`` the east/north/up
    velocity change and ``R(s) = R_i exp(s log(R_i^T R_j))`` the shortest rotation between the real
    two (KITTI's own fill of the yaw goes the long way round where it wraps at +-pi). A run whose
    ends are missing or misstamped (:func:`misstamped`), or whose attitude turns by more than
    :data:`BRIDGE_MAX_ANGLE`, keeps the line.
    """
    from scipy.spatial.transform import Rotation

    from bevo_ros.core.vehicle_dynamics import GRAVITY
    from bevo_ros.rotations import rotation_vector, rotation_x, rotation_y, rotation_z

    gyro, accel = np.array(oxts.gyro, dtype=np.float64), np.array(oxts.accel, dtype=np.float64)
    t = np.asarray(oxts.stamps_ns, dtype=np.int64)
    bad_stamp = misstamped(t)
    R = rotation_z(oxts.yaw) @ rotation_y(oxts.pitch) @ rotation_x(oxts.roll)
    velocity = np.stack([oxts.field("ve"), oxts.field("vn"), oxts.field("vu")], 1)
    bridged = []
    for start, stop in interpolated_runs(interpolated):
        i, j = start - 1, stop
        if i < 0 or j >= len(gyro) or bad_stamp[i:j + 1].any():
            continue
        span = (t[j] - t[i]) * 1e-9
        theta = rotation_vector(R[i].T @ R[j])
        s = (t[i:j + 1] - t[i]) * 1e-9 / span  # (m + 1,) 0 .. 1
        along = R[i] @ Rotation.from_rotvec(s[:, None] * theta).as_matrix()  # (m + 1, 3, 3) geodesic
        force = (velocity[j] - velocity[i]) / span + np.array([0.0, 0.0, GRAVITY])  # nav frame
        mean_force = np.trapezoid(np.einsum("kji,j->ki", along, force), s, axis=0)  # into the body
        if not (np.isfinite(theta).all() and np.isfinite(mean_force).all()
                and np.linalg.norm(theta) <= BRIDGE_MAX_ANGLE):
            continue
        bump = (s * (1.0 - s))[:, None]
        bump = bump / np.trapezoid(bump, s, axis=0)  # its trapezoid over the run: 1
        for x, mean in ((gyro, theta / span), (accel, mean_force)):
            line = x[i] + (x[j] - x[i]) * s[:, None]
            missing = mean - np.trapezoid(line, s, axis=0)  # (3,) the mean the line lacks
            x[start:stop] = (line + missing * bump)[1:-1]
        bridged.append((start, stop))
    return gyro, accel, bridged


def linear_fill(samples: np.ndarray, rtol: float = 1e-9) -> np.ndarray:
    """``(N, C)`` evenly spaced samples -> ``(N,)`` bool: those that lie exactly on the straight line
    through their two neighbours in every channel (second difference below ``rtol`` of their size),
    a fill by linear interpolation (:func:`interpolated_oxts`); the first and last: False."""
    x = np.asarray(samples, dtype=np.float64)
    out = np.zeros(len(x), dtype=bool)
    if len(x) >= 3:
        d2 = np.abs(x[2:] - 2.0 * x[1:-1] + x[:-2])
        scale = 1.0 + np.abs(x[2:]) + np.abs(x[1:-1]) + np.abs(x[:-2])
        out[1:-1] = (d2 <= rtol * scale).all(axis=1)
    return out


def read_oxts(oxts_dir: PathLike, increasing: bool = True) -> OxtsData:
    """Read a raw ``<drive>_sync/oxts`` directory (``timestamps.txt`` + ``data/*.txt``);
    ``increasing``: as :func:`read_timestamps_ns` (False: :func:`out_of_order` finds the records).

    Raises:
        FileNotFoundError: missing directory or files.
        ValueError: unparseable line (file and line named), count mismatch.
    """
    oxts_dir = _require_dir(oxts_dir, "OXTS")
    stamps_ns = read_timestamps_ns(oxts_dir / "timestamps.txt", increasing)
    data_dir = _require_dir(oxts_dir / "data", "OXTS data")
    files = sorted(p for p in data_dir.iterdir() if p.suffix == ".txt")
    for i, p in enumerate(files):  # record i is timestamps.txt's line i: a gap would shift every later one
        if not p.stem.isdigit() or int(p.stem) != i:
            raise ValueError(f"{p}: expected record {i} here; OXTS data files must be numbered consecutively from 0 "
                             f"(a missing or extra file would pair every later record with another frame's time)")
    if len(files) != len(stamps_ns):
        raise ValueError(f"{data_dir}: {len(files)} OXTS data files but {len(stamps_ns)} lines in "
                         f"{oxts_dir / 'timestamps.txt'}")
    data = np.empty((len(files), len(OXTS_FIELDS)), dtype=np.float64)
    for i, path in enumerate(files):
        lines = list(_content_lines(path))
        if len(lines) != 1:
            raise ValueError(f"{path}: expected one line of {len(OXTS_FIELDS)} numbers, found {len(lines)} lines")
        lineno, text = lines[0]
        data[i] = _parse_floats(text, path, lineno, count=len(OXTS_FIELDS))
    return OxtsData(stamps_ns, data, oxts_dir)


# ----------------------------------------------------------------------------------------------
# Calibration
# ----------------------------------------------------------------------------------------------
def _read_key_values(path: PathLike, what: str) -> dict[str, tuple[int, str]]:
    """``key: values`` lines -> {key: (line number, value text)}."""
    path = _require_file(path, what)
    out: dict[str, tuple[int, str]] = {}
    for lineno, line in _content_lines(path):
        key, sep, value = line.partition(":")
        if not sep or not key.strip() or " " in key.strip():
            raise ValueError(f"{path}:{lineno}: expected 'KEY: numbers', got {line.strip()[:80]!r}")
        out[key.strip()] = (lineno, value)
    return out


def read_odometry_calib(calib_txt: PathLike) -> dict[str, np.ndarray]:
    """Odometry ``sequences/NN/calib.txt`` -> {``P0``..``P3``, ``Tr``: ``(3, 4)``} (those present).

    ``P0`` is required (it holds the camera-0 intrinsics).
    """
    path = Path(calib_txt)
    out = {}
    for key, (lineno, value) in _read_key_values(path, "odometry calibration").items():
        out[key] = _parse_floats(value, path, lineno, count=12).reshape(3, 4)
    if "P0" not in out:
        raise ValueError(f"{path}: no 'P0:' line")
    return out


# Keys of the raw calibration files that are not numeric matrices.
_RAW_TEXT_KEYS = {"calib_time"}


def read_raw_calib(path: PathLike) -> dict[str, np.ndarray]:
    """A raw ``calib_*.txt`` -> {key: float64 array} (``calib_time`` skipped).

    Shapes as stored (flat); use :func:`raw_rigid_transform` for ``R``/``T`` pairs.
    """
    path = Path(path)
    out = {}
    for key, (lineno, value) in _read_key_values(path, "raw calibration").items():
        if key in _RAW_TEXT_KEYS:
            continue
        out[key] = _parse_floats(value, path, lineno)
    return out


def _matrix(calib: dict[str, np.ndarray], key: str, shape: tuple[int, int], path: PathLike) -> np.ndarray:
    if key not in calib:
        raise ValueError(f"{path}: missing '{key}:' line")
    value = calib[key]
    if value.size != shape[0] * shape[1]:
        raise ValueError(f"{path}: '{key}' has {value.size} numbers, expected {shape[0] * shape[1]}")
    return value.reshape(shape)


def raw_rigid_transform(path: PathLike) -> np.ndarray:
    """``R`` (3x3) and ``T`` (3,) of a raw ``calib_*_to_*.txt`` -> ``(4, 4)`` (maps *from* -> *to*)."""
    calib = read_raw_calib(path)
    T = np.eye(4)
    T[:3, :3] = _matrix(calib, "R", (3, 3), path)
    T[:3, 3] = _matrix(calib, "T", (3, 1), path)[:, 0]
    return T


def find_raw_calib_dir(start: PathLike, date: str | None = None) -> Path | None:
    """Search ``start`` and its parents for a directory holding ``calib_imu_to_velo.txt``.

    Looks in ``X``, ``X/<date>`` and ``X/<any date>`` for ``X`` = ``start`` and each parent (the
    sample's 2011_09_30 drives have no calibration; the 2011_09_26 files describe the same rig).
    Prefers ``date``, then the nearest other date (the earlier on a tie; the newest without a
    ``date``). Returns None when nothing is found.
    """
    start = Path(start).resolve()

    try:
        day = datetime.strptime(date, "%Y_%m_%d") if date else None
    except ValueError:
        day = None

    def order(p: Path) -> tuple:
        """Sort key: the drive's own day, then the nearest (the earlier on a tie), a date-like name
        that is no date last; without a ``date``, the newest first."""
        if day is None:
            return (True, [-ord(c) for c in p.name])
        try:
            distance = abs((datetime.strptime(p.name, "%Y_%m_%d") - day).days)
        except ValueError:
            distance = math.inf
        return (p.name != date, distance, p.name)

    for base in [start, *start.parents]:
        candidates = [base]
        if date:
            candidates.append(base / date)
        for root in (base, base / "raw"):
            if root.is_dir():
                try:
                    dated = sorted((p for p in root.iterdir() if p.is_dir() and re.fullmatch(r"\d{4}_\d{2}_\d{2}", p.name)),
                                   key=order)
                except OSError:
                    dated = []
                candidates.extend(dated)
        for cand in candidates:
            if (cand / "calib_imu_to_velo.txt").is_file() and (cand / "calib_velo_to_cam.txt").is_file() \
                    and (cand / "calib_cam_to_cam.txt").is_file():
                return cand
    return None


def imu_to_camera_extrinsics(raw_calib_dir: PathLike, cam: int = 0) -> np.ndarray:
    """``T_cam_imu (4, 4)``: IMU points -> rectified camera ``cam`` frame.

    ``T_rect0_imu = R_rect_00 @ T_cam00_velo @ T_velo_imu``; for ``cam > 0`` the rectified
    cameras share ``R_rect_00`` and are offset by ``P_rect_0i``'s translation
    (``t = K^-1 P[:, 3]``). Camera 0 is the frame of the odometry poses.
    ``T_base_cam = inv(T_cam_imu)`` (base = IMU).

    The product of KITTI's matrices (7 digits) is orthonormal only to ~5e-8: its rotation is taken
    to the nearest one, so that the chain is rigid (``invert_rigid`` exact) and equals what a bag's
    ``/tf_static`` quaternion of it gives back (``bevo run`` and bevo_node take the rig from there;
    otherwise the ground truth converted through it moves by ~3e-6 m on the way back).
    """
    d = _require_dir(raw_calib_dir, "raw calibration")
    T_velo_imu = raw_rigid_transform(d / "calib_imu_to_velo.txt")
    T_cam00_velo = raw_rigid_transform(d / "calib_velo_to_cam.txt")
    cam_path = d / "calib_cam_to_cam.txt"
    cam_calib = read_raw_calib(cam_path)
    R_rect = np.eye(4)
    R_rect[:3, :3] = _matrix(cam_calib, "R_rect_00", (3, 3), cam_path)
    T = R_rect @ T_cam00_velo @ T_velo_imu
    if cam != 0:
        P = _matrix(cam_calib, f"P_rect_{cam:02d}", (3, 4), cam_path)
        shift = np.eye(4)
        shift[:3, 3] = np.linalg.solve(P[:, :3], P[:, 3])
        T = shift @ T
    U, _, Vt = np.linalg.svd(T[:3, :3])
    R = U @ Vt  # the nearest orthonormal matrix
    if np.linalg.det(R) < 0 or np.abs(R - T[:3, :3]).max() > 1e-4:
        raise ValueError(f"{d}: the calibration chain's rotation is no rotation (det {np.linalg.det(T[:3, :3]):.6f}, "
                         f"{np.abs(R - T[:3, :3]).max():.1e} off the nearest orthonormal matrix): a broken file?")
    T[:3, :3] = R
    return T


def invert_rigid(T: np.ndarray) -> np.ndarray:
    """Inverse of rigid transforms ``(..., 4, 4)``, exact for orthonormal R."""
    R = T[..., :3, :3]
    t = T[..., :3, 3]
    out = np.zeros_like(T)
    Rt = np.swapaxes(R, -1, -2)
    out[..., :3, :3] = Rt
    out[..., :3, 3] = -(Rt @ t[..., None])[..., 0]
    out[..., 3, 3] = 1.0
    return out


def camera_model_from_kitti(odometry_calib_txt: PathLike, raw_calib_dir: PathLike, image_size: tuple[int, int],
                            mount_height: float = 1.65, cam: int = 0, dtype=None):
    """Build a :class:`bevo_ros.core.geometry.CameraModel` for camera ``cam`` of a sequence.

    Args:
        odometry_calib_txt: ``sequences/NN/calib.txt`` (``P{cam}`` gives K for the odometry images).
        raw_calib_dir: directory with the raw ``calib_*.txt`` of the same rig (extrinsics).
        image_size: ``(W, H)`` of the images in pixels.
        mount_height: camera centre height above the road, metres (KITTI: 1.65).
        dtype: torch dtype of the tensors (default float32).
    """
    import torch

    from bevo_ros.core.geometry import CameraModel

    dtype = dtype or torch.float32
    calib = read_odometry_calib(odometry_calib_txt)
    key = f"P{cam}"
    if key not in calib:
        raise ValueError(f"{odometry_calib_txt}: no '{key}:' line")
    K = calib[key][:, :3]
    T_base_cam = invert_rigid(imu_to_camera_extrinsics(raw_calib_dir, cam))
    width, height_px = (int(v) for v in image_size)
    return CameraModel(torch.as_tensor(K, dtype=dtype), width, height_px,
                       torch.as_tensor(T_base_cam, dtype=dtype), float(mount_height))


# ----------------------------------------------------------------------------------------------
# Poses and times
# ----------------------------------------------------------------------------------------------
def read_poses(poses_txt: PathLike) -> np.ndarray:
    """KITTI pose file (3x4 row-major per line) -> ``(F, 4, 4)`` float64 (camera-0 poses)."""
    path = _require_file(poses_txt, "pose file")
    poses = []
    for lineno, line in _content_lines(path):
        T = np.eye(4)
        T[:3, :] = _parse_floats(line, path, lineno, count=12).reshape(3, 4)
        poses.append(T)
    if not poses:
        raise ValueError(f"{path}: no poses")
    return np.stack(poses)


def write_poses(path: PathLike, poses: np.ndarray) -> None:
    """``(F, 4, 4)`` or ``(F, 3, 4)`` -> KITTI pose file, atomically (temp file + os.replace)."""
    from bevo_ros.io.files import atomic_write_text

    poses = np.asarray(poses, dtype=np.float64)
    if poses.ndim != 3 or poses.shape[1:] not in ((4, 4), (3, 4)):
        raise ValueError(f"poses must be (F, 4, 4) or (F, 3, 4), got {poses.shape}")
    path = Path(path)
    atomic_write_text(path, "".join(" ".join(f"{v:.9e}" for v in T[:3, :].ravel()) + "\n" for T in poses))


def read_times(times_txt: PathLike) -> np.ndarray:
    """Odometry ``times.txt`` (seconds since the sequence start, one per line) -> ``(F,)`` float64."""
    path = _require_file(times_txt, "times file")
    times = [float(_parse_floats(line, path, lineno, count=1)[0]) for lineno, line in _content_lines(path)]
    if not times:
        raise ValueError(f"{path}: no times")
    return np.asarray(times, dtype=np.float64)


def base_poses(camera_poses: np.ndarray, T_base_cam: np.ndarray) -> np.ndarray:
    """Camera-0 poses -> base (IMU) poses in the ``odom`` frame = the base frame at frame 0.

    ``T_world_base_i = T_world_cam_i @ T_cam_base``; re-anchored so that the first pose is the
    identity: ``T_odom_base_i = inv(T_world_base_0) @ T_world_base_i`` (z up, x forward at start).

    Args:
        camera_poses: ``(F, 4, 4)`` ``T_world_cam_i``.
        T_base_cam: ``(4, 4)`` camera pose in the base frame.

    Returns:
        ``(F, 4, 4)``.
    """
    camera_poses = np.asarray(camera_poses, dtype=np.float64)
    T_cam_base = invert_rigid(np.asarray(T_base_cam, dtype=np.float64))
    world_base = camera_poses @ T_cam_base
    return invert_rigid(world_base[0]) @ world_base


def relative_poses(poses: np.ndarray) -> np.ndarray:
    """``(F, 4, 4)`` -> ``(F-1, 4, 4)`` with ``inv(T_{i-1}) @ T_i``."""
    return invert_rigid(poses[:-1]) @ poses[1:]


def base_relative_motion(camera_poses: np.ndarray, T_base_cam: np.ndarray) -> np.ndarray:
    """Planar motion of the base between consecutive frames, in the base frame at frame i-1.

    Args:
        camera_poses: ``(F, 4, 4)`` ``T_world_cam_i``.
        T_base_cam: ``(4, 4)``.

    Returns:
        ``(F-1, 3)`` ``(dx, dy, dyaw)`` (metres, radians, REP-103) of
        ``inv(T_base_{i-1}) @ T_base_i``; ``dyaw = atan2(R[1, 0], R[0, 0])``.
    """
    rel = relative_poses(base_poses(camera_poses, T_base_cam))
    return np.stack([rel[:, 0, 3], rel[:, 1, 3], np.arctan2(rel[:, 1, 0], rel[:, 0, 0])], axis=-1)


# ----------------------------------------------------------------------------------------------
# Layout helpers
# ----------------------------------------------------------------------------------------------
def raw_drive_for_sequence(sequence: str | int) -> tuple[str, str, int, int]:
    """``'06'`` -> ``(date, drive, start, end)`` e.g. ``('2011_09_30', '2011_09_30_drive_0020', 0, 1100)``."""
    key = f"{int(sequence):02d}" if str(sequence).isdigit() else str(sequence)
    if key not in ODOMETRY_TO_RAW:
        raise ValueError(f"sequence {sequence!r} has no raw drive (only 00..10 do)")
    drive, start, end = ODOMETRY_TO_RAW[key]
    return drive[:10], drive, start, end


def list_images(image_dir: PathLike) -> list[Path]:
    """Sorted ``*.png`` of an image directory (raises when missing or empty)."""
    image_dir = _require_dir(image_dir, "image")
    files = sorted(p for p in image_dir.iterdir() if p.suffix.lower() == ".png")
    if not files:
        raise FileNotFoundError(f"{image_dir}: no .png images")
    return files
