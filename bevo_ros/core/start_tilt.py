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
pair costs 40-140 ms of a core at 1226x370, measured in worker threads: the caller keeps up with its
camera). A car standing still at its start has its frames run as they come, 20 pairs at a time
(``BevoOdometry._release_standing``), and the tilt measured when it drives off. Too few textured pairs within
``max_frames`` images
keeps the configured tilt (:attr:`TiltMeasurement.measured` false, with the reason).
"""
from __future__ import annotations

import math
import weakref
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from .travel_direction import STANDING, equalized, forward, held_pair_motion, usable_cores


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
    failed: tuple[str, ...] = ()  # the errors of pairs whose measurement raised (counted as giving no direction)
    standing_frames: int = 0  # frames run at the configured tilt while the car stood still at its start

    def describe(self) -> str:
        """One line for a log."""
        failed = (f"; {len(self.failed)} pair(s) failed to measure, e.g. {self.failed[0]}" if self.failed else "")
        if self.standing_frames:
            failed += f"; after {self.standing_frames} frame(s) standing still, run as they came"
        if not self.measured:
            return f"the camera's tilt was not measured at the start ({self.reason}{failed}): the configured one kept"
        return (f"the camera's tilt from the images' direction of travel at the start ({self.pairs} frame pairs, "
                f"+- {math.degrees(self.sem):.2f} deg; the suspension's {math.degrees(self.body_pitch):+.2f} deg over "
                f"them taken out{failed}): {math.degrees(self.change):+.2f} deg from the configured "
                "filter.mounting_pitch (nose down +; ~2 % of scale per 0.1 deg at a 1.65 m camera height)")


PAIR_WORKERS = 4  # threads measuring the held pairs at most (OpenCV releases the GIL), one per core below that


@dataclass
class StartHold:
    """The inputs an engine holds until the camera's tilt is measured, in their order, and the frame pairs'
    directions of travel (``(3,)`` unit vectors in the camera's optical frame, or None), each measured in a
    worker thread as its second image comes: the caller only equalises the image, so a node keeps up with
    its camera while it holds (a pair costs 40-140 ms of a core at 1226x370, a 10 Hz camera gives 100 ms).
    What is measured does not depend on the threads' timing: the measurement takes the first ``pairs``
    forward pairs, with the pairs between them (:meth:`taken`), whenever they are done."""

    pairs: int  # forward pairs wanted
    max_frames: int  # images held at most: then the tilt is taken from what there is
    inputs: list[tuple[str, tuple]] = field(default_factory=list)  # ("imu" | "image" | "speed", arguments)
    images: int = 0
    stamps: list[float] = field(default_factory=list)  # the held images'
    last: dict[str, float] = field(default_factory=dict)  # the latest stamp held per kind (order checks)
    _found: list = field(default_factory=list)  # per pair: its direction, None, or the Future measuring it
    _image_inputs: list[int] = field(default_factory=list)  # per held image: its index in ``inputs``
    _previous: tuple[np.ndarray, np.ndarray] | None = None  # the latest image (equalised) and its K
    _pool: ThreadPoolExecutor | None = None
    _counted: int = 0  # pairs counted by forward_pairs, and the forward ones among them
    _forward: int = 0
    failed: list[str] = field(default_factory=list)  # the pairs whose measurement raised: their errors

    def _resolve(self, k: int) -> np.ndarray | None:
        """Pair ``k``'s direction, waiting for it if it is still being measured. A pair whose measurement
        raised gives none (its error kept in :attr:`failed`: in a worker it would otherwise be raised again
        at every later input), a pair dropped by :meth:`close` none either."""
        f = self._found[k]
        if isinstance(f, Future):
            if f.cancelled():
                f = None
            elif (error := f.exception()) is not None:
                self.failed.append(f"{type(error).__name__}: {error}")
                f = None
            else:
                f = f.result()
            self._found[k] = f
        return f

    def add_image(self, stamp: float, image: np.ndarray, tag: Any, K: np.ndarray) -> None:
        """Hold an image ``(H, W)`` (uint8, or float in [0, 1]) and start measuring its pair with the previous
        one (none across a camera change: another size or ``K (3, 3)``)."""
        grey = image if image.dtype == np.uint8 else np.clip(np.rint(image * 255.0), 0, 255).astype(np.uint8)
        grey = equalized(grey)
        K = np.array(K, dtype=np.float64)
        if self._previous is not None:
            same = self._previous[0].shape == grey.shape and np.array_equal(self._previous[1], K)
            if same and self._pool is None:
                self._pool = ThreadPoolExecutor(max_workers=max(1, min(usable_cores(), PAIR_WORKERS)),
                                                thread_name_prefix="bevo_start_tilt")
                # a hold dropped while measuring (its engine replaced) drops its queued pairs with it
                weakref.finalize(self, self._pool.shutdown, wait=False, cancel_futures=True)
            self._found.append(self._pool.submit(held_pair_motion, self._previous[0], grey, K) if same else None)
        self._previous = (grey, K)
        self.images += 1
        self.stamps.append(stamp)
        self._image_inputs.append(len(self.inputs))
        self.inputs.append(("image", (stamp, image, tag)))

    @property
    def forward_pairs(self) -> int:
        """Forward pairs among those measured so far, in order up to the first still being measured (checked
        at every input: what was counted stays counted)."""
        while self._counted < len(self._found):
            f = self._found[self._counted]
            if isinstance(f, Future) and not f.done():
                break
            self._forward += forward(self._resolve(self._counted))
            self._counted += 1
        return self._forward

    @property
    def measuring(self) -> bool:
        """A held pair is still being measured."""
        return any(isinstance(f, Future) and not f.done() for f in self._found)

    @property
    def ready(self) -> bool:
        """Enough forward pairs measured, or as many images as it may hold (then :meth:`taken` waits)."""
        return self.images >= self.max_frames or self.forward_pairs >= self.pairs

    @property
    def directions(self) -> list:
        """Every held pair's direction (None: none), waiting for those still being measured."""
        return [self._resolve(k) for k in range(len(self._found))]

    def taken(self) -> tuple[list, list[tuple[str, tuple]], list[float]]:
        """The pairs the measurement takes, waiting for them: the first ``pairs`` forward ones and those between,
        else (as many images as it may hold, or a flush) every pair. -> (their directions, the held inputs up to
        their last image, their first images' stamps); then the pairs after them are not measured."""
        directions, count, upto = [], 0, len(self.inputs)
        for k in range(len(self._found)):
            d = self._resolve(k)
            directions.append(d)
            count += forward(d)
            if count >= self.pairs:
                upto = self._image_inputs[k + 1] + 1  # the inputs up to the pair's second image
                break
        self.close()
        return directions, self.inputs[:upto], self.stamps[:len(directions)]

    def standing_prefix(self, pairs: int) -> bool:
        """The first ``pairs`` held pairs are measured and each stood still (:data:`STANDING`): a car waiting at
        its start, whose frames need no tilt (they move nothing) and need not wait for one."""
        if len(self._found) < pairs:
            return False
        for k in range(pairs):
            f = self._found[k]
            if isinstance(f, Future) and not f.done():
                return False
            if not (isinstance(d := self._resolve(k), str) and d == STANDING):
                return False
        return True

    def release_prefix(self, images: int) -> list[tuple[str, tuple]]:
        """Stop holding the first ``images`` images and every input before the next one: -> those inputs, in
        order. The pairs among them (and the one to the next image) go with them; the rest stay held."""
        cut = self._image_inputs[images] if images < self.images else len(self.inputs)
        released, self.inputs = self.inputs[:cut], self.inputs[cut:]
        self._found = self._found[images:]
        self.stamps = self.stamps[images:]
        self._image_inputs = [i - cut for i in self._image_inputs[images:]]
        self.images -= images
        self._counted, self._forward = 0, 0  # counted again from the held pairs (resolved ones stay resolved)
        return released

    def close(self) -> None:
        """Stop measuring: the pairs not started are dropped (a reset, or the measurement taken)."""
        if self._pool is not None:
            self._pool.shutdown(wait=False, cancel_futures=True)
            self._pool = None


def mean_offset(directions: list, body_pitch: list[float] | None) -> float:
    """The mean of ``body_pitch`` (one per pair) over the pairs that showed a direction."""
    if not body_pitch:
        return 0.0
    used = [b for d, b in zip(directions, body_pitch) if forward(d)]
    return float(np.mean(used)) if used else 0.0


__all__ = ["StartHold", "TiltMeasurement", "mean_offset"]
