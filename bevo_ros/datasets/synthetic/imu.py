"""IMU errors of a synthetic drive: the error model (:class:`ImuNoise`) and its seeded draw (biases
with random walks, vibration, white noise) on top of the exact readings of :mod:`.motion`."""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

__all__ = ["ImuNoise", "noisy_imu"]


@dataclass(frozen=True)
class ImuNoise:
    """IMU error model (all seeded). Per-sample standard deviations; walks per sqrt(second)."""

    gyro_white: float = 0.005  # rad/s
    gyro_bias: float = 0.002  # rad/s, initial bias std per axis
    gyro_bias_walk: float = 2e-4  # rad/s/sqrt(s)
    accel_white: float = 0.05  # m/s^2
    accel_bias: float = 0.05  # m/s^2
    accel_bias_walk: float = 2e-3  # m/s^2/sqrt(s)
    accel_vibration: float = 0.5  # m/s^2 RMS per axis (engine harmonics + road, z 1.5x)

    def scaled(self, k: float) -> "ImuNoise":
        return ImuNoise(*(k * getattr(self, f) for f in self.__dataclass_fields__))


def noisy_imu(gyro_true: np.ndarray, accel_true: np.ndarray, t_imu: np.ndarray, speed: np.ndarray, v_ref: float,
              imu_rate: float, imu_noise: ImuNoise, seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The readings with errors, drawn from ``seed``: ``gyro_true``, ``accel_true`` ``(N, 3)`` at ``t_imu``
    ``(N,)`` s, ``speed`` ``(N,)`` m/s (the vibration grows with it, relative to ``v_ref``).
    -> ``(gyro, accel, gyro_bias, accel_bias)``, each ``(N, 3)``."""
    n_imu = len(t_imu)
    nrng = np.random.default_rng([int(seed), 2])
    dt = 1.0 / imu_rate
    gyro_bias = nrng.normal(0, imu_noise.gyro_bias, 3) + np.cumsum(
        nrng.normal(0, imu_noise.gyro_bias_walk * math.sqrt(dt), (n_imu, 3)), 0)
    accel_bias = nrng.normal(0, imu_noise.accel_bias, 3) + np.cumsum(
        nrng.normal(0, imu_noise.accel_bias_walk * math.sqrt(dt), (n_imu, 3)), 0)
    # Vibration: engine harmonics (speed-dependent amplitude) + broadband road roughness.
    vib = np.zeros((n_imu, 3))
    env = 0.5 + 0.5 * np.abs(speed) / max(v_ref, 1e-3)
    nyq = 0.5 * imu_rate
    for axis, gain in enumerate((0.7, 0.7, 1.5)):
        for _ in range(3):
            f = nrng.uniform(0.15, 0.9) * nyq
            vib[:, axis] += gain * math.sqrt(2.0) * np.sin(2 * math.pi * f * t_imu + nrng.uniform(0, 2 * math.pi)) / math.sqrt(3)
        vib[:, axis] = 0.8 * vib[:, axis] * env + 0.6 * gain * nrng.normal(0, 1, n_imu)
    vib *= imu_noise.accel_vibration
    gyro = gyro_true + gyro_bias + nrng.normal(0, imu_noise.gyro_white, (n_imu, 3))
    accel = accel_true + accel_bias + vib + nrng.normal(0, imu_noise.accel_white, (n_imu, 3))
    return gyro, accel, gyro_bias, accel_bias
