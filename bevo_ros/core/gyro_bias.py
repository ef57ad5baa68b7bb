"""The pitch and roll gyro's biases while driving, from the DUKF's accelerometer innovations.

A bias beside the DUKF rather than in it (Friedland's separate-bias filter): per axis a linear
Kalman filter on ``[angle, bias]`` with ``angle' = angle + (rate - bias) dt``, measured by the
accelerometer's angle with the DUKF's own measurement variance (its ``Q`` plus the vehicle-
acceleration uncertainty of that sample). It shares the DUKF's innovation, so it never reads the
accelerometer differently, and only its bias is used: the engine takes it off the gyro's rates
before the DUKF predicts. The DUKF's state, its sigma points, its training and the paper mode stay
two-dimensional. Near level the Euler kinematics make the pitch rate the y rate and the roll rate
the x rate; the bias is that of the base-frame y and x rates.

Why: a MEMS gyro's pitch bias (0.1-0.3 deg/s) ramps the DUKF's pitch, which the road-tilt low-pass
follows ~its time constant late (a BEV pitch error, read as scale) and which the pitch-change
correction takes for the car's own pitch change (a spurious forward shift). Stops observe the bias
directly (``BevoOdometry._observe_rest_bias``, which sets it here: :meth:`GyroBiasFilter.set_at_rest`);
this estimate carries it between stops, where the accelerometer is trusted: an acceleration the
DUKF discounts (its measurement variance grows) teaches the bias proportionally less.

Floats, not tensors: one step per IMU message on the inference path, as ``DUKF.step_scalar``.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

__all__ = ["BiasAxis", "GyroBiasFilter", "predict_axis", "update_axis"]


@dataclass(frozen=True)
class BiasAxis:
    """One axis's belief: the bias (rad/s) and the covariance of ``[angle, bias]``.

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


def update_axis(axis: BiasAxis, innovation: float, measurement_var: float) -> BiasAxis:
    """The accelerometer's angle less the predicted one (rad), with its variance (rad^2).

    An innovation above zero says the angle integrated from the rates came out low: the rate less
    the bias was too small, the bias too large (``p_ab < 0`` after a predict makes the gain negative).
    """
    s = axis.p_aa + measurement_var
    k_a, k_b = axis.p_aa / s, axis.p_ab / s
    return BiasAxis(axis.bias + k_b * innovation, axis.p_aa - k_a * axis.p_aa, axis.p_ab - k_a * axis.p_ab,
                    axis.p_bb - k_b * axis.p_ab)


class GyroBiasFilter:
    """The x and y rate biases of a gyro (base frame), pitch's axis (y) and roll's (x).

    Args:
        bias_std: rad/s, the bias's prior standard deviation (a MEMS part's turn-on bias after its
            factory calibration, ~0.1 deg/s); 0: the bias is left to the stops alone.
        walk: rad/s/sqrt(s), the bias's random walk (its instability).
        attitude_std: rad, the angle's standard deviation at a (re)start (the DUKF's start).
    """

    def __init__(self, bias_std: float, walk: float, attitude_std: float) -> None:
        if not (bias_std >= 0 and walk >= 0 and attitude_std > 0):
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

    def restart(self) -> None:
        """The DUKF restarted (an IMU gap): its angles unknown again, the biases kept."""
        self._axes = [BiasAxis(a.bias, self.attitude_std**2, 0.0, a.p_bb) for a in self._axes]

    def step(self, dt: float, process_density: tuple[float, float], innovation: tuple[float, float],
             measurement_var: tuple[float, float]) -> None:
        """One DUKF message: ``dt`` (s), the DUKF's ``O`` (pitch, roll; rad^2/s), its innovation
        (pitch, roll; rad: the accelerometer's angles less the predicted ones) and measurement
        variance (its ``Q`` plus that sample's extra; rad^2)."""
        if not self.enabled:
            return
        walk_density = self.walk**2
        self._axes = [update_axis(predict_axis(a, dt, o, walk_density), nu, r)
                      for a, o, nu, r in zip(self._axes, process_density, innovation, measurement_var)]

    def set_at_rest(self, xy: tuple[float, float], share: float) -> None:
        """A stop observed the biases directly (their mean rates, ``xy``: x, y; rad/s): the
        estimate becomes that, and its variance ``share`` (0-1, the stop estimate's weight of its
        prior) of the prior's; the angles' link to the bias is cut (the stop measured it, not the
        accelerometer)."""
        prior = self.bias_std**2 * min(1.0, max(share, 0.0))
        self._axes = [BiasAxis(b, a.p_aa, 0.0, prior) for a, b in zip(self._axes, (xy[1], xy[0]))]
