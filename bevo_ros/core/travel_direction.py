"""The camera's tilt to the road from the images alone: the direction of travel in the camera frame.

A car moves along the road, so the direction its camera translates in between two frames, which
the frames' epipolar geometry gives up to scale, lies in the road's plane (on average over a drive:
the body's pitching and the road's bumps average out). Its elevation below the optical axis is the
camera's tilt to the road, with no reference for the distance: no ground truth, no speed. This is
``bevo calibrate --from-images``. What it measures is the camera's physical tilt, so the BEV's scale
then rests on the camera height as well (``camera.mount_height``); the distance-matching fits
(:mod:`bevo_ros.training.mounting`) absorb a height error into the tilt instead.

Per frame pair: Shi-Tomasi corners tracked by pyramidal Lucas-Kanade (kept where the backward track
returns within 0.5 px), the essential matrix by RANSAC (5-point) and its decomposition
(``cv2.recoverPose``): the camera's motion direction. The pairs' median is robust to the few whose
matches lie on a moving car. The roll is not observable this way (a direction has two angles:
elevation and azimuth); the azimuth is reported as a check on the extrinsics' yaw.
"""
from __future__ import annotations

import math
import os
from concurrent.futures import ThreadPoolExecutor
from typing import NamedTuple

import cv2
import numpy as np

MAX_CORNERS = 2000  # Shi-Tomasi corners per frame
MIN_MATCHES = 30  # tracked corners for a pair's essential matrix
MIN_FLOW_PX = 1.0  # median track length (px) below which the pair is taken as standing still
MIN_PAIRS = 10  # pairs needed for a result
FB_TOLERANCE_PX = 0.5  # forward-backward track error kept
RANSAC_THRESHOLD_PX = 0.5  # epipolar distance of an inlier
DISTANCE_THRESHOLD = 1e4  # baselines: recoverPose's points in front of both cameras, however far


def usable_cores() -> int:
    """The CPU cores this process may run on (its affinity where the OS has one)."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)


def equalized(image: np.ndarray) -> np.ndarray:
    """``image (H, W)`` uint8 with its local contrast equalised (CLAHE, 8x8 tiles): the corners found in the
    shadows as in the sun and tracked through an exposure change. The KITTI sample's first 30 pairs
    darkened to dusk, noisier, JPEG'd and flickering +-15 % give 1.06-1.15 deg of tilt with it, 0.95-1.09
    deg as they come. A new CLAHE per call: OpenCV's algorithm objects are not for sharing between threads."""
    return cv2.createCLAHE(clipLimit=2.0, tileGridSize=(8, 8)).apply(np.ascontiguousarray(image))


STANDING = "standing"  # held_pair_motion: the pair's tracks moved less than MIN_FLOW_PX


def _tracks(image0: np.ndarray, image1: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """Shi-Tomasi corners of ``image0`` tracked into ``image1`` (``(H, W)`` uint8) and back: ``(a, b)`` ``(M, 2)``
    px, the ones whose backward track returns within FB_TOLERANCE_PX; None with fewer than MIN_MATCHES."""
    p0 = cv2.goodFeaturesToTrack(image0, MAX_CORNERS, 0.01, 8)
    if p0 is None or len(p0) < MIN_MATCHES:
        return None
    lk = dict(winSize=(21, 21), maxLevel=3)
    p1, st, _ = cv2.calcOpticalFlowPyrLK(image0, image1, p0, None, **lk)
    back, st_back, _ = cv2.calcOpticalFlowPyrLK(image1, image0, p1, None, **lk)
    ok = (st[:, 0] == 1) & (st_back[:, 0] == 1) & (np.linalg.norm(back - p0, axis=2)[:, 0] < FB_TOLERANCE_PX)
    a, b = p0[ok, 0].astype(np.float64), p1[ok, 0].astype(np.float64)
    return (a, b) if len(a) >= MIN_MATCHES else None


def relative_pose(image0: np.ndarray, image1: np.ndarray, K: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """The camera's motion from ``image0`` to ``image1`` (``(H, W)`` uint8): ``R (3, 3)`` with ``x1 = R x0 + t``
    for a point's optical-frame coordinates, and the unit ``(3,)`` direction of the second camera's centre in
    the first camera's optical frame (x right, y down, z forward); None where the pair does not determine it
    (too few tracks, too little motion, no essential matrix)."""
    tracks = _tracks(image0, image1)
    if tracks is None or np.median(np.linalg.norm(tracks[1] - tracks[0], axis=1)) < MIN_FLOW_PX:
        return None
    return _pose_from_tracks(*tracks, K)


def _pose_from_tracks(a: np.ndarray, b: np.ndarray, K: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """:func:`relative_pose` from a pair's tracks ``a``, ``b`` ``(M, 2)``."""
    E, inliers = cv2.findEssentialMat(a, b, K, method=cv2.RANSAC, prob=0.999, threshold=RANSAC_THRESHOLD_PX)
    if E is None or E.shape != (3, 3):  # none, or several stacked solutions: ambiguous
        return None
    # distanceThresh: points up to that many baselines away count as in front (the default 50 dropped
    # most of a road scene's points at a slow speed or a high frame rate: 0.3 m per pair kept 41 of 325)
    good, R, t, _, _ = cv2.recoverPose(E, a, b, K, distanceThresh=DISTANCE_THRESHOLD, mask=inliers)
    if good < MIN_MATCHES:
        return None
    c = -(R.T @ t).ravel()  # x1 = R x0 + t: the second camera's centre in the first's frame
    return R, c / np.linalg.norm(c)


def motion_direction(image0: np.ndarray, image1: np.ndarray, K: np.ndarray) -> np.ndarray | None:
    """The camera's translation direction from ``image0`` to ``image1`` (:func:`relative_pose`'s), or None."""
    pose = relative_pose(image0, image1, K)
    return None if pose is None else pose[1]


def held_pair_motion(image0: np.ndarray, image1: np.ndarray, K: np.ndarray) -> np.ndarray | str | None:
    """:func:`motion_direction`, with :data:`STANDING` where the pair's tracks moved less than MIN_FLOW_PX (the
    camera stood still, or barely crept) instead of None: the engine's start runs such frames as they come
    (``core/start_tilt``)."""
    tracks = _tracks(image0, image1)
    if tracks is None:
        return None
    if np.median(np.linalg.norm(tracks[1] - tracks[0], axis=1)) < MIN_FLOW_PX:
        return STANDING
    pose = _pose_from_tracks(*tracks, K)
    return None if pose is None else pose[1]


class TravelDirection(NamedTuple):
    """:func:`travel_direction`'s result, the pairs' medians (rad) and how many pairs gave them."""

    elevation: float  # below the optical axis + (y down): the camera tilted up by that much
    azimuth: float  # right of the optical axis +
    elevation_sem: float  # the median's standard error (1.2533 std / sqrt(n))
    pairs: int  # pairs used
    pairs_skipped: int  # pairs that gave no direction (standing still, too few tracks)


def travel_direction(images, K) -> TravelDirection:
    """The direction of travel in the camera frame over consecutive ``images`` (``(F, H, W)`` uint8,
    rectified, intrinsics ``K (3, 3)``; each :func:`equalized` first). ValueError with fewer than MIN_PAIRS
    usable pairs."""
    K = np.asarray(K, dtype=np.float64)
    if len(images) < 2:
        raise ValueError(f"{len(images)} images: a direction of travel needs frame pairs")
    first = np.asarray(images[0])
    if first.ndim != 2 or first.dtype != np.uint8:
        raise ValueError(f"images must be grey (F, H, W) uint8, got frames {first.shape} {first.dtype}")
    # The pairs are independent and OpenCV releases the GIL: one thread per core (each pair's RANSAC seeds
    # its own generator, so the directions are those of one thread, in order).
    with ThreadPoolExecutor(max_workers=max(1, min(usable_cores(), 8))) as pool:
        found = list(pool.map(lambda k: motion_direction(equalized(images[k]), equalized(images[k + 1]), K),
                              range(len(images) - 1)))
    return direction_of_pairs(found)


def forward(direction: np.ndarray | None) -> bool:
    """A pair's direction counts toward the direction of travel: found, and forward (not reversing, not a
    degenerate decomposition)."""
    return isinstance(direction, np.ndarray) and direction[2] > 0


def direction_of_pairs(directions: list, body_pitch: list[float] | None = None) -> TravelDirection:
    """The direction of travel from consecutive pairs' :func:`motion_direction` results (None or
    :data:`STANDING`: the pair gave none): the medians of the forward ones. ``body_pitch`` (rad, nose down +, one per pair): the
    body's pitch on its suspension at each pair, whose direction is then the one at rest (a nose dived by
    ``b`` sees the road ``b`` higher: the elevation, below the axis +, gains ``b``). ValueError with fewer
    than MIN_PAIRS of them."""
    keep = [k for k, d in enumerate(directions) if forward(d)]
    if len(keep) < MIN_PAIRS:
        raise ValueError(f"only {len(keep)} of {len(directions)} frame pairs give a direction of travel (at least "
                         f"{MIN_PAIRS}: the car must move, forwards, past textured surroundings)")
    d = np.array([directions[k] for k in keep])
    elevation = np.arctan2(d[:, 1], d[:, 2])
    if body_pitch is not None:
        elevation = elevation + np.asarray(body_pitch, dtype=np.float64)[keep]
    azimuth = np.arctan2(d[:, 0], d[:, 2])
    sem = 1.2533 * float(np.std(elevation)) / math.sqrt(len(d))
    return TravelDirection(float(np.median(elevation)), float(np.median(azimuth)), sem, len(keep),
                           len(directions) - len(keep))


def mounting_pitch_from_travel(direction: TravelDirection, R_base_cam, roll: float) -> tuple[float, float]:
    """The base's pitch on the road (rad, nose down +, the ``filter.mounting_pitch`` convention) at
    which the direction of travel the images show, through the camera's extrinsics ``R_base_cam (3,
    3)``, lies in the road's plane, at the base's ``roll`` on the road; and that direction's azimuth
    on the road from the base's x axis (rad, left +: zero for extrinsics whose yaw is right, on a
    straight drive; a turn's chord and the camera's offset ahead of the base add to it). The base's
    attitude on the road is R = Ry(pitch) Rx(roll), as in ``core.geometry.camera_pose_on_road``."""
    e, a = direction.elevation, direction.azimuth
    b = np.asarray(R_base_cam, dtype=np.float64)[:3, :3] @ np.array([math.tan(a), math.tan(e), 1.0])
    # The direction of travel lies in the road's plane, whatever its azimuth: normal . b = 0 with the
    # road's normal in the base (-sin p, cos p sin r, cos p cos r).
    sr, cr = math.sin(roll), math.cos(roll)
    pitch = math.atan2(sr * b[1] + cr * b[2], b[0])
    sp, cp = math.sin(pitch), math.cos(pitch)
    # b in the road frame, Ry(p) Rx(r) b: its x and y give the azimuth
    y_road = cr * b[1] - sr * b[2]
    x_road = cp * b[0] + sp * (sr * b[1] + cr * b[2])
    return pitch, math.atan2(y_road, x_road)


__all__ = ["TravelDirection", "equalized", "relative_pose", "motion_direction", "held_pair_motion", "STANDING", "travel_direction", "direction_of_pairs", "forward",
           "mounting_pitch_from_travel", "usable_cores"]
