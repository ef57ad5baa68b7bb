"""A gyro's rate over the latest sample interval, by what its samples are (``filter.gyro_sampling``).

* ``"interval_mean"`` (default): each sample is the mean rate over the interval since the previous
  one, as an IMU that integrates its rate (delta angles) reports it. The sample itself is then
  the interval's rate, exactly. The KITTI OXTS rates behave so: on the shared drives 0016, 0018,
  0020 and 0027 (10 Hz), the unit's own pitch change over an interval is the interval's end
  sample times its length to 0.017-0.022 deg RMS, while the trapezoid of the two end samples
  misses it by 0.049-0.072 deg (a least-squares fit weighs the end sample 1.10-1.16 and its
  neighbours -0.03 to -0.07).
* ``"instantaneous"``: each sample is the rate at its stamp. A 10 Hz IMU then samples a car's
  1-2 Hz suspension motion 5-10 times a period, and the trapezoid misses the rate's curvature
  (5 % of a pitch change at 1.5 Hz); the quadratic through the previous, the interval's start and
  its end samples (the two-step Adams-Moulton rule for equal steps, ``(5 r2 + 8 r1 - r0) / 12``)
  halves that and uses no sample from the future, so it adds no latency.
"""
from __future__ import annotations

from typing import Sequence

__all__ = ["GYRO_SAMPLING", "interval_rate"]

GYRO_SAMPLING = ("interval_mean", "instantaneous")


def interval_rate(sampling: str, r2: Sequence[float], r1: Sequence[float] | None, r0: Sequence[float] | None,
                  h2: float, h1: float | None, max_step_ratio: float = 2.0) -> list[float]:
    """The mean rate over ``[t1, t2]`` from samples at ``t0 < t1 < t2`` (floats per axis).

    Args:
        sampling: one of :data:`GYRO_SAMPLING`.
        r2, r1, r0: the samples at ``t2`` (the latest), ``t1`` and ``t0``; with ``"instantaneous"``,
            ``r0 = None`` gives the trapezoid (after a start or a restart).
        h2: ``t2 - t1`` > 0 s; h1: ``t1 - t0`` s, or None.
        max_step_ratio: ``"instantaneous"`` falls back to the trapezoid when the two intervals
            differ by more than this factor (a gap: the quadratic would extrapolate across it).

    Returns:
        the mean rate per axis over the interval (times ``h2``: the integral).
    """
    if sampling == "interval_mean":
        return [float(a) for a in r2]
    if sampling != "instantaneous":
        raise ValueError(f"gyro sampling must be one of {GYRO_SAMPLING}, got {sampling!r}")
    if r0 is None or h1 is None or not (h1 > 0) or max(h1 / h2, h2 / h1) > max_step_ratio:
        return [0.5 * (a + b) for a, b in zip(r2, r1)]
    # Integral of the interpolating quadratic over [t1, t2]: the trapezoid minus h2^2 / 12 times its
    # second derivative 2 ((r2 - r1) / h2 - (r1 - r0) / h1) / (h1 + h2).
    k = h2 * h2 / (6.0 * (h1 + h2))
    return [0.5 * (a + b) - k * ((a - b) / h2 - (b - c) / h1) for a, b, c in zip(r2, r1, r0)]
