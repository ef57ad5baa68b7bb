"""The pitch and roll gyro's biases while driving, from the DUKF's accelerometer innovations.

A bias beside the DUKF rather than in it: per axis a linear Kalman filter on ``[angle error,
bias]`` with ``angle' = angle + (rate - bias) dt``, measured by the accelerometer's angle with the
DUKF's own measurement variance (its ``Q`` plus the vehicle-acceleration uncertainty of that
sample). It shares the DUKF's innovation, so it never reads the accelerometer differently; its
angle book is the DUKF's angle as the DUKF corrects it (the DUKF's own gain, Joseph form: a bias
error's angle error left in the DUKF shows in later innovations, which an optimal angle gain here
would take for corrected and so overshoot the bias), and only its bias is used: the engine takes
it off the gyro's rates before the DUKF predicts. The DUKF's state, its sigma points, its training
and the paper mode stay two-dimensional. Near level the Euler kinematics make the pitch rate the y
rate and the roll rate the x rate; the bias is that of the base-frame y and x rates.

The accelerometer's angle error is not white: a sample's vibration and suspension motion last
~:data:`MEASUREMENT_CORRELATION_TIME`, so samples closer than that are not independent and the
measurement variance is scaled up to count once per that time (the bias learns as fast at 100 Hz
as at 10 Hz); a sample whose vehicle-acceleration uncertainty exceeds :data:`TRUST_RATIO` times the
accelerometer's own ``Q`` (the speed unknown in a bend, an acceleration the motion filter does not
know) teaches nothing: a
one-signed acceleration error lasting seconds would otherwise be integrated into the bias
(`make demo`'s 30 s before its held-out frames, no speed known: 0.42 deg/s read into the roll's
bias, the held-out drift 2.7 -> 6.3 %).

Why: a MEMS gyro's pitch bias (0.1-0.3 deg/s) ramps the DUKF's pitch, which the road-tilt low-pass
follows ~its time constant late (a BEV pitch error, read as scale) and which the pitch-change
correction takes for the car's own pitch change (a spurious forward shift). Stops observe the bias
directly (``BevoOdometry._observe_rest_bias`` weighs them here: :meth:`GyroBiasFilter.observe_rest`);
this estimate carries it between stops, where the accelerometer is trusted: an acceleration the
DUKF discounts (its measurement variance grows) teaches the bias proportionally less.

Floats, not tensors: one step per IMU message on the inference path, as ``DUKF.step_scalar``.
"""
from __future__ import annotations

import math
from typing import NamedTuple

__all__ = ["BiasAxis", "GyroBiasFilter", "predict_axis", "update_axis", "MEASUREMENT_CORRELATION_TIME", "TRUST_RATIO"]

# s: the accelerometer angle error's correlation time (vibration, the suspension's motion): the
# measurement variance counts once per this time, and a 10 Hz IMU (KITTI's) is used as it is.
MEASUREMENT_CORRELATION_TIME = 0.1
# A sample whose vehicle-acceleration variance is over this many times the DUKF's Q teaches the bias
# nothing. 1 kept the pitch's bias from ever learning with a wheel speed (its acceleration's variance
# is about Q); `make demo`'s held-out drift 2.68 / 2.78 / 2.85 % at 3 / 10 / 100 (6.3 % without), the
# 10 Hz presets 1.95 % at 3.
TRUST_RATIO = 3.0


class BiasAxis(NamedTuple):
    """One axis's belief: the bias (rad/s) and the covariance of ``[angle, bias]`` (a tuple: built
    four times per IMU message).

    Attributes:
        bias: rad/s, the gyro reads the true rate plus this.
        p_aa: rad^2, the angle's variance (this filter's own book, not the DUKF's).
        p_ab: rad^2/s, their covariance.
        p_bb: rad^2/s^2, the bias's variance.
    """

    bias: float
    p_aa: float
    p_ab: float
    p_bb: float


def predict_axis(axis: BiasAxis, dt: float, process_density: float, walk_density: float) -> BiasAxis:
    """``angle' = angle - bias dt`` (the rate's known part cancels), the angle's process noise and
    the bias's random walk over ``dt`` (s). Densities in rad^2/s and rad^2/s^3."""
    p_aa = axis.p_aa - 2.0 * dt * axis.p_ab + dt * dt * axis.p_bb + process_density * dt
    return BiasAxis(axis.bias, p_aa, axis.p_ab - dt * axis.p_bb, axis.p_bb + walk_density * dt)


def update_axis(axis: BiasAxis, innovation: float, measurement_var: float, angle_gain: float,
                learn: bool = True) -> BiasAxis:
    """The accelerometer's angle less the predicted one (rad), with its variance (rad^2).

    ``angle_gain``: the gain the angle was actually corrected with (the DUKF's). The bias's gain ``p_ab / S`` is optimal whatever the angle's; the covariance is
    the Joseph form for that pair of gains. An innovation above zero says the angle integrated from
    the rates came out low: the rate less the bias was too small, the bias too large (``p_ab < 0``
    after a predict makes the gain negative). ``learn`` False (a sample not trusted to teach the
    bias): the bias's gain is 0, but the DUKF corrected its angle all the same, so the book still
    takes that correction's share of the measurement's error (before 2026-12-06 such a sample left the
    book untouched: its angle variance and the angle-bias covariance no longer the DUKF's). An
    infinite variance: nothing learnt, nothing corrected.
    """
    if not math.isfinite(measurement_var):
        return axis
    s = axis.p_aa + measurement_var
    k_a, k_b = angle_gain, (axis.p_ab / s if learn else 0.0)
    p_aa = (1.0 - k_a) ** 2 * axis.p_aa + k_a * k_a * measurement_var
    p_ab = (1.0 - k_a) * (axis.p_ab - k_b * axis.p_aa) + k_a * k_b * measurement_var
    p_bb = axis.p_bb - k_b * axis.p_ab
    return BiasAxis(axis.bias + k_b * innovation, p_aa, p_ab, p_bb)


class GyroBiasFilter:
    """The x and y rate biases of a gyro (base frame), pitch's axis (y) and roll's (x).

    Args:
        bias_std: rad/s, the bias's prior standard deviation (a MEMS part's turn-on bias after its
            factory calibration, ~0.1 deg/s); 0: the bias is left to the stops alone.
        walk: rad/s/sqrt(s), the bias's random walk (its instability).
        attitude_std: rad, the angle's standard deviation at a (re)start (the DUKF's start).
    """

    def __init__(self, bias_std: float, walk: float, attitude_std: float) -> None:
        if not (0 <= bias_std < math.inf and 0 <= walk < math.inf and 0 < attitude_std < math.inf):
            raise ValueError(f"need bias_std, walk >= 0 and attitude_std > 0, got {bias_std}, {walk}, {attitude_std}")
        self.bias_std, self.walk, self.attitude_std = float(bias_std), float(walk), float(attitude_std)
        self.reset()

    @property
    def enabled(self) -> bool:
        return self.bias_std > 0

    def reset(self) -> None:
        """Bias zero with its prior variance; angles unknown."""
        prior = self.bias_std**2
        self._axes = [BiasAxis(0.0, self.attitude_std**2, 0.0, prior) for _ in range(2)]  # (pitch/y, roll/x)

    @property
    def xy(self) -> tuple[float, float]:
        """The x (roll) and y (pitch) rate biases, rad/s."""
        return self._axes[1].bias, self._axes[0].bias

    @property
    def xy_std(self) -> tuple[float, float]:
        """Their standard deviations, rad/s."""
        return math.sqrt(max(self._axes[1].p_bb, 0.0)), math.sqrt(max(self._axes[0].p_bb, 0.0))

    def restart(self, gap: float = 0.0) -> None:
        """The DUKF restarted after an IMU gap of ``gap`` seconds: its angles unknown again, the
        biases kept, walked over the gap."""
        walked = self.walk**2 * max(gap, 0.0)
        self._axes = [BiasAxis(a.bias, self.attitude_std**2, 0.0, a.p_bb + walked) for a in self._axes]

    def step(self, dt: float, process_density: tuple[float, float], innovation: tuple[float, float],
             measurement_var: tuple[float, float], extra_var: tuple[float, float],
             angle_gain: tuple[float, float]) -> None:
        """One DUKF message: ``dt`` (s), the DUKF's ``O`` (pitch, roll; rad^2/s), its innovation
        (pitch, roll; rad: the accelerometer's angles less the predicted ones), its ``Q`` and that
        sample's vehicle-acceleration variance (rad^2; the measurement's variance is their sum), and
        the gain the DUKF corrected each angle with."""
        if not self.enabled:
            return
        walk_density = self.walk**2
        per = max(1.0, MEASUREMENT_CORRELATION_TIME / dt) if dt > 0 else 1.0
        self._axes = [update_axis(predict_axis(a, dt, o, walk_density), nu, (q + e) * per, k, learn=e <= TRUST_RATIO * q)
                      for a, o, nu, q, e, k in zip(self._axes, process_density, innovation, measurement_var, extra_var,
                                                   angle_gain)]

    def observe_rest(self, xy: tuple[float, float], span: float, prior_seconds: float) -> None:
        """A stop observed the biases directly: the gyro's mean x and y rates (rad/s) over ``span``
        seconds of rest, weighted against the prior as ``span`` seconds against ``prior_seconds``
        (the stops' own shrinkage, ``REST_BIAS_PRIOR``); the estimate carried by the accelerometer
        and the earlier stops counts by its variance (a direct measurement of the bias: the angle's
        book keeps what it says of the angle)."""
        r = self.bias_std**2 * prior_seconds / max(span, 1e-9)
        axes = []
        for a, m in zip(self._axes, (xy[1], xy[0])):
            s = a.p_bb + r
            k = a.p_bb / s
            axes.append(BiasAxis(a.bias + k * (m - a.bias), a.p_aa - a.p_ab * a.p_ab / s, a.p_ab * r / s, a.p_bb * r / s))
        self._axes = axes

    def set_xy(self, xy: tuple[float, float]) -> None:
        """The biases as the stops alone estimate them (``bias_std`` 0: no state between stops)."""
        self._axes = [BiasAxis(b, a.p_aa, a.p_ab, a.p_bb) for a, b in zip(self._axes, (xy[1], xy[0]))]
