"""Other vehicles in a synthetic drive: a car ahead in the lane, parked cars, oncoming traffic.

Real roads are not empty: in a city the BEV holds the car ahead (and its shadow) at every queue,
parked cars line the kerb and oncoming cars cross the left of the view. None of them lies on the
road plane the BEV assumes, and the moving ones move on their own: they are the outliers of the
phase correlation. Each vehicle is a box (length, width, height above a ground clearance) with a
textured skin and a soft shadow on the road under it, rendered by :func:`~.render.render_view`.

* **car ahead**: drives the ego's own path ``headway`` seconds ahead in time, ``standing_gap``
  metres further on (it does what the ego will do: it brakes first and pulls away first, and
  stands ``standing_gap`` ahead at a stop);
* **parked**: slots every ``parked_spacing`` metres along the right kerb (``parked_offset``), a
  share ``parked_fill`` occupied;
* **oncoming**: every ``oncoming_spacing`` metres in the left lane at ``oncoming_speed``.

Everything is deterministic by the drive's seed. Poses are world ``(x, y, yaw)`` at each frame.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

__all__ = ["TrafficOptions", "VEHICLE_FIELDS", "as_traffic_options", "traffic_at_frames"]

# Columns of a vehicle row: world x, y (box centre on the road), yaw, length, width, height, grey shade.
VEHICLE_FIELDS = ("x", "y", "yaw", "length", "width", "height", "shade")
GROUND_CLEARANCE = 0.3  # m: the road shows under a car body (in its shadow)


@dataclass(frozen=True)
class TrafficOptions:
    """What traffic a drive has. Distances in metres, times in seconds, speeds in m/s.

    ``lead``: a car ahead in the ego's lane. ``parked_spacing`` / ``oncoming_spacing`` 0 = none.
    """

    lead: bool = True
    headway: float = 0.8
    standing_gap: float = 6.5  # ego base -> the lead car's rear at a stop (KITTI base: ~2.5 m behind the front)
    parked_spacing: float = 6.0
    parked_fill: float = 0.6
    parked_offset: float = -3.3  # lateral, left positive: the right kerb's parking lane
    oncoming_spacing: float = 45.0
    oncoming_speed: float = 11.0
    oncoming_offset: float = 3.5
    view_behind: float = 5.0  # vehicles from this far behind the ego base ...
    view_ahead: float = 70.0  # ... to this far ahead are rendered (the rest are invisible or hazed)

    def __post_init__(self) -> None:
        for name in ("headway", "standing_gap", "parked_spacing", "oncoming_spacing", "oncoming_speed",
                     "view_behind", "view_ahead"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0):
                raise ValueError(f"traffic {name} must be a finite number >= 0, got {v!r}")
        if not 0.0 <= self.parked_fill <= 1.0:
            raise ValueError(f"traffic parked_fill must be in [0, 1], got {self.parked_fill!r}")


def as_traffic_options(traffic: "TrafficOptions | bool | None") -> "TrafficOptions | None":
    """A drive's ``traffic`` argument: True = the defaults, None/False = none, or the options."""
    if traffic is True:
        return TrafficOptions()
    if traffic is None or traffic is False:
        return None
    if not isinstance(traffic, TrafficOptions):
        raise ValueError(f"traffic must be a bool, None or a TrafficOptions, got {traffic!r}")
    return traffic


class _ArcPath:
    """The ego's path by arc length, extended straight beyond both ends."""

    def __init__(self, t: np.ndarray, xy: np.ndarray, yaw: np.ndarray) -> None:
        self.t = t
        seg = np.linalg.norm(np.diff(xy, axis=0), axis=1)
        # Strictly increasing arc (stops repeat positions; the tiny slope keeps interp well defined).
        self.s = np.concatenate([[0.0], np.cumsum(seg)]) + 1e-9 * np.arange(len(t))
        self.xy, self.yaw = xy, np.unwrap(yaw)

    def s_at(self, t: np.ndarray) -> np.ndarray:
        return np.interp(t, self.t, self.s)

    def pose_at(self, s: np.ndarray, lateral: float) -> np.ndarray:
        """World ``(x, y, yaw)`` at arc ``s (K,)`` and a lateral offset (left +). -> ``(K, 3)``."""
        s = np.asarray(s, dtype=np.float64)
        x = np.interp(s, self.s, self.xy[:, 0])
        y = np.interp(s, self.s, self.xy[:, 1])
        yaw = np.interp(s, self.s, self.yaw)
        for end, beyond in ((0, s < self.s[0]), (-1, s > self.s[-1])):  # straight extensions
            ds = s[beyond] - self.s[end]
            x[beyond] = self.xy[end, 0] + ds * math.cos(self.yaw[end])
            y[beyond] = self.xy[end, 1] + ds * math.sin(self.yaw[end])
            yaw[beyond] = self.yaw[end]
        x, y = x - lateral * np.sin(yaw), y + lateral * np.cos(yaw)
        return np.stack([x, y, yaw], 1)


def _sizes(rng: np.random.Generator, k: int) -> np.ndarray:
    """Car-like boxes: length, width, height, shade. -> ``(k, 4)``."""
    return np.stack([rng.uniform(3.8, 5.0, k), rng.uniform(1.65, 1.9, k), rng.uniform(1.4, 1.65, k),
                     rng.uniform(0.15, 0.85, k)], 1)


def traffic_at_frames(options: TrafficOptions, t_dense: np.ndarray, xy_dense: np.ndarray, yaw_dense: np.ndarray,
                      frame_t: np.ndarray, seed: int) -> list[np.ndarray]:
    """The vehicles visible at each frame. -> ``F`` arrays ``(K_f, 7)`` (:data:`VEHICLE_FIELDS`).

    Args:
        options: the traffic.
        t_dense, xy_dense, yaw_dense: the ego's path, densely sampled ``(M,)``, ``(M, 2)``, ``(M,)``,
            covering every frame time plus ``options.headway``.
        frame_t: ``(F,)`` frame times on the same clock as ``t_dense``.
        seed: the drive's seed.
    """
    rng = np.random.default_rng([int(seed), 11])
    path = _ArcPath(t_dense, xy_dense, yaw_dense)
    s_ego = path.s_at(frame_t)
    s_lo, s_hi = float(s_ego.min()) - options.view_behind, float(s_ego.max()) + options.view_ahead
    out: list[list[np.ndarray]] = [[] for _ in frame_t]

    def add(s_centre: np.ndarray, lateral: float, size: np.ndarray, reverse: bool) -> None:
        # s_centre (F,) for one vehicle: kept at the frames where it is in view.
        rel = s_centre - s_ego
        seen = (rel > -options.view_behind - size[0]) & (rel < options.view_ahead)
        for f in np.nonzero(seen)[0]:
            pose = path.pose_at(s_centre[f:f + 1], lateral)[0]
            if reverse:
                pose[2] += math.pi
            out[f].append(np.concatenate([pose, size]))

    if options.lead:
        size = _sizes(rng, 1)[0]
        t_ahead = np.minimum(frame_t + options.headway, t_dense[-1])
        add(path.s_at(t_ahead) + options.standing_gap + size[0] / 2, 0.0, size, False)
    if options.parked_spacing > 0:
        slots = np.arange(s_lo, s_hi + options.parked_spacing, options.parked_spacing)
        slots = slots[rng.uniform(size=len(slots)) < options.parked_fill]
        sizes = _sizes(rng, len(slots))
        for s, size in zip(slots + rng.uniform(-0.5, 0.5, len(slots)), sizes):
            add(np.full(len(frame_t), s), options.parked_offset + rng.uniform(-0.2, 0.2), size, False)
    if options.oncoming_spacing > 0 and options.oncoming_speed > 0:
        travel = options.oncoming_speed * float(frame_t[-1] - frame_t[0])
        starts = np.arange(s_lo, s_hi + travel, options.oncoming_spacing) + rng.uniform(0, options.oncoming_spacing)
        sizes = _sizes(rng, len(starts))
        for s0, size in zip(starts, sizes):
            add(s0 - options.oncoming_speed * (frame_t - frame_t[0]), options.oncoming_offset, size, True)
    empty = np.zeros((0, len(VEHICLE_FIELDS)))
    return [np.stack(v) if v else empty for v in out]
