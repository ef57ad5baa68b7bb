"""The camera's frame interval, robust to jittered stamps.

The motion filter turns each frame's displacement into a speed with the frame interval, and the
speed back into the next displacement. Camera stamps often jitter while the frames themselves
come on a regular clock (a triggered or free-running camera stamped at reception; KITTI frames
timed by the OXTS clock, which is quantised to 10 ms: intervals of 0.09-0.11 s for a 0.104 s
camera). Taken as is, that jitter becomes +-10 % of the motion per frame although the car moved
the same: on the KITTI sample the fused per-frame error fell from 6.5 to 6.3 cm and the
frame-to-frame jitter of the estimate from 13.5 to 2.9 cm with this clock (docs/FUSED_ODOMETRY.md, item 6, has the
trade-off on that sample's odd first stamps).

So the interval used is the mean period over the last ``window`` frames times the whole number of
periods this interval spans (a dropped frame is two). An interval that fits no whole number of
periods within ``tolerance`` is a real change of the frame rate: it is used as is and the
history restarts from it. Exact stamps give back exactly their own mean period.
"""
from __future__ import annotations

from collections import deque

__all__ = ["FrameClock", "fast_camera_note"]

# s: frames closer than this come from a camera faster than the ~10 Hz the engine's per-frame constants
# were learned at (KITTI's OXTS-timed frames: 0.07-0.13 s apart, a 0.104 s mean)
FAST_CAMERA_PERIOD = 0.075


def fast_camera_note(period: float | None, min_frame_interval: float) -> str | None:
    """What to tell a user whose camera's mean frame ``period`` (s) is under
    :data:`FAST_CAMERA_PERIOD` while every frame is processed (``odometry.min_frame_interval`` 0), or None."""
    if period is None or not 0 < period < FAST_CAMERA_PERIOD or min_frame_interval > 0:
        return None
    return (f"frames come every {period * 1e3:.0f} ms ({1 / period:.0f} Hz), every one processed: the per-frame "
            f"constants were learned at 10 Hz and such a camera reads better thinned (synthetic 30 Hz: 5.86 -> 4.51 % "
            f"per 0.1 s on urban): set odometry.min_frame_interval to ~0.09 (README, Another car's rig)")


class FrameClock:
    """Regularised frame intervals (plain floats, one camera).

    Args:
        window: frames in the running mean period; 0 disables the clock (intervals as stamped).
        tolerance: the largest jitter, as a fraction of the period, still read as jitter.
    """

    def __init__(self, window: int = 20, tolerance: float = 0.25) -> None:
        if window < 0 or not 0.0 < tolerance < 0.5:
            raise ValueError(f"window must be >= 0 and tolerance in (0, 0.5), got {window}, {tolerance}")
        self.window = int(window)
        self.tolerance = float(tolerance)
        self._history: deque[tuple[float, int]] = deque(maxlen=max(self.window, 1))  # (interval, periods)

    def reset(self) -> None:
        self._history.clear()

    @property
    def period(self) -> float | None:
        """The current mean frame period (s), None before the first interval."""
        if not self._history:
            return None
        return sum(h[0] for h in self._history) / sum(h[1] for h in self._history)

    def interval(self, dt: float) -> float:
        """The interval to use for a stamped interval ``dt`` (s, > 0)."""
        if self.window == 0 or dt <= 0:
            return dt
        period = self.period
        n = max(1, round(dt / period)) if period else 1
        if period is None or abs(dt - n * period) > self.tolerance * period:
            self._history.clear()  # first interval, or a real change of the frame rate
            self._history.append((dt, 1))
            return dt
        self._history.append((dt, n))
        return n * self.period
