"""The camera's tilt to the road, measured from the images at the start of a drive, before its first pose.

The BEV's scale follows the camera's tilt to the road (~2 % per 0.1 deg at KITTI's 1.65 m camera
height), and that tilt is not the rig's alone: the car's load pitches the body, and KITTI's camera sat
0.22 deg less tilted on 2011_10_03 and 1.55 deg less on 2011_09_26 than on 2011_09_30, the day
params/kitti.yaml was fitted on (README, Limitations). With ``filter.tilt_from_images: N`` the engine
(:class:`~bevo_ros.core.odometry.BevoOdometry`) holds its inputs from its start until ``N`` consecutive
frame pairs have shown the direction the camera travels in (their epipolar geometry,
:mod:`~bevo_ros.core.travel_direction`), takes the base's pitch on the road at which that direction lies
in the road's plane, and then runs the held inputs in their order. Every pose is at the measured tilt and
the node's are those of ``bevo run``; the first pose comes when the N-th pair has been measured (a
pair costs 40-140 ms of one core at 1226x370, so a node falls behind by that much per frame meanwhile and
catches up after). A start that stands still, or too few textured pairs within ``max_frames`` images,
keeps the configured tilt (:attr:`TiltMeasurement.measured` false, with the reason).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from .travel_direction import TravelDirection, direction_of_pairs, equalized, forward, motion_direction


@dataclass(frozen=True)
class TiltMeasurement:
    """What the start measured: the base's mounting pitch it runs with less the configured one
    (``change``, rad, nose down +; 0 when not measured), from how many pairs, and why not."""

    change: float
    pairs: int
    pairs_skipped: int
    sem: float  # the median elevation's standard error, rad
    measured: bool
    reason: str = ""  # why the configured tilt was kept
    body_pitch: float = 0.0  # the suspension's mean pitch over the pairs taken out (rad, nose down +)

    def describe(self) -> str:
        """One line for a log."""
        if not self.measured:
            return f"the camera's tilt was not measured at the start ({self.reason}): the configured one kept"
        return (f"the camera's tilt from the images' direction of travel at the start ({self.pairs} frame pairs, "
                f"+- {math.degrees(self.sem):.2f} deg; the suspension's {math.degrees(self.body_pitch):+.2f} deg over "
                f"them taken out): {math.degrees(self.change):+.2f} deg from the configured filter.mounting_pitch "
                "(nose down +; ~2 % of scale per 0.1 deg at a 1.65 m camera height)")


@dataclass
class StartHold:
    """The inputs an engine holds until the camera's tilt is measured, in their order, and the
    frame pairs' directions of travel (``(3,)`` unit vectors in the camera's optical frame, or None)."""

    pairs: int  # forward pairs wanted
    max_frames: int  # images held at most: then the tilt is taken from what there is
    inputs: list[tuple[str, tuple]] = field(default_factory=list)  # ("imu" | "image" | "speed", arguments)
    directions: list = field(default_factory=list)
    images: int = 0
    stamps: list[float] = field(default_factory=list)  # the held images'
    last: dict[str, float] = field(default_factory=dict)  # the latest stamp held per kind (order checks)
    _previous: tuple[np.ndarray, np.ndarray] | None = None  # the latest image (equalised) and its K

    def add_image(self, stamp: float, image: np.ndarray, tag: Any, K: np.ndarray) -> None:
        """Hold an image ``(H, W)`` (uint8, or float in [0, 1]) and measure its pair with the previous one
        (none across a camera change: another size or ``K (3, 3)``)."""
        grey = image if image.dtype == np.uint8 else np.clip(np.rint(image * 255.0), 0, 255).astype(np.uint8)
        grey = equalized(grey)
        if self._previous is not None:
            same = self._previous[0].shape == grey.shape and np.array_equal(self._previous[1], K)
            self.directions.append(motion_direction(self._previous[0], grey, K) if same else None)
        self._previous = (grey, np.array(K, dtype=np.float64))
        self.images += 1
        self.stamps.append(stamp)
        self.inputs.append(("image", (stamp, image, tag)))

    @property
    def forward_pairs(self) -> int:
        return sum(forward(d) for d in self.directions)

    @property
    def ready(self) -> bool:
        """Enough forward pairs, or as many images as it may hold."""
        return self.forward_pairs >= self.pairs or self.images >= self.max_frames

    def direction(self, body_pitch: list[float] | None = None) -> TravelDirection:
        """The pairs' direction of travel, each pair's elevation less the body's ``body_pitch`` (rad, nose
        down +, per pair: its first frame's) if given; ValueError with too few."""
        return direction_of_pairs(self.directions, body_pitch)

    def mean_offset(self, body_pitch: list[float] | None) -> float:
        """The mean of ``body_pitch`` over the pairs that showed a direction."""
        if not body_pitch:
            return 0.0
        used = [b for d, b in zip(self.directions, body_pitch) if forward(d)]
        return float(np.mean(used)) if used else 0.0


__all__ = ["StartHold", "TiltMeasurement"]
