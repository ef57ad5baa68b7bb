"""The car's own acceleration in the accelerometer, and its suspension's response to it.

The paper's DUKF measures attitude with the accelerometer as if it read gravity alone. A car
does not sit still: it brakes, accelerates and turns, and the accelerometer reads the specific
force ``f = R^T g + a_body``. With a forward speed ``v`` (no sideslip at the base origin, so the
body velocity is ``[v, 0, 0]``) and body rates ``w``, the body-frame acceleration is

    a_body = [dv/dt, 0, 0] + w x [v, 0, 0] = [dv/dt, v wz, -v wy]

(forward, centripetal, and the vertical part of pitching over a crest). On KITTI's OXTS that
is 5-6 deg RMS of accelerometer attitude error, up to 23 deg in a bend; removing it with the
unit's own speed leaves 0.3 / 0.9 deg (pitch / roll; issue 9). The speed and its rate come from
the vehicle motion filter (:mod:`bevo_ros.core.vehicle_filter`); their uncertainty becomes
measurement variance, so before a speed is known (start, reset, gap) the accelerometer counts
for little in a bend or when braking, and a residual ``| |f_c| - g |`` (acceleration the model
does not explain: bumps, a wrong speed) down-weights it further.

The suspension leans the body on the road by an amount proportional to the acceleration (the
"pitch gradient" and "roll gradient" of vehicle dynamics, ~0.1-0.5 deg per m/s^2). That lean is
real attitude relative to the road, which the BEV needs, but it lasts as long as the braking or
the bend: the road-tilt low-pass would absorb it as "road slope". :func:`suspension_attitude`
models it so the low-pass sees only what is left (road slope and camber).

The engine calls :func:`compensate_floats` once per IMU message; :func:`compensate_specific_force`
is the same arithmetic on batched, differentiable tensors (a test pins the two).
"""
from __future__ import annotations

import math

import torch

Tensor = torch.Tensor

GRAVITY = 9.80665

__all__ = [
    "GRAVITY",
    "vehicle_acceleration",
    "compensate_specific_force",
    "compensate_floats",
    "suspension_attitude",
]


def vehicle_acceleration(gyro: Tensor, speed: Tensor, accel_forward: Tensor) -> Tensor:
    """Body-frame acceleration of a car with forward speed ``speed`` and no sideslip.

    Args:
        gyro: ``(..., 3)`` body rates rad/s; speed, accel_forward: ``(...,)`` m/s and m/s^2.

    Returns:
        ``(..., 3)`` ``[dv/dt, v wz, -v wy]`` m/s^2.
    """
    s = speed.to(gyro.dtype)
    return torch.stack([accel_forward.to(gyro.dtype), s * gyro[..., 2], -s * gyro[..., 1]], dim=-1)


def compensate_specific_force(accel: Tensor, gyro: Tensor, speed: Tensor, accel_forward: Tensor,
                              speed_var: Tensor, accel_forward_var: Tensor) -> tuple[Tensor, Tensor]:
    """The accelerometer minus the car's own acceleration, and the extra measurement variance.

    The extra variance (rad^2, per [pitch, roll]) is what the compensation's own uncertainty does
    to the accelerometer angles (first order: an acceleration error ``e`` tilts the gravity
    direction by ``e / g``), plus the squared relative residual of the compensated norm
    ``(|f_c| / g - 1)^2``: acceleration nobody explained.

    Args:
        accel: ``(..., 3)`` specific force m/s^2; gyro: ``(..., 3)`` rad/s;
        speed, accel_forward: ``(...,)``; speed_var, accel_forward_var: ``(...,)`` their variances.

    Returns:
        compensated specific force ``(..., 3)``, extra variance ``(..., 2)`` rad^2.
    """
    f = accel - vehicle_acceleration(gyro, speed, accel_forward)
    g2 = GRAVITY * GRAVITY
    resid = (torch.linalg.vector_norm(f, dim=-1) / GRAVITY - 1.0) ** 2
    var_pitch = (accel_forward_var.to(f.dtype) + speed_var.to(f.dtype) * gyro[..., 1] ** 2) / g2 + resid
    var_roll = speed_var.to(f.dtype) * gyro[..., 2] ** 2 / g2 + resid
    return f, torch.stack([var_pitch, var_roll], dim=-1)


def compensate_floats(accel: list[float], gyro: list[float], speed: float, accel_forward: float,
                      speed_var: float, accel_forward_var: float) -> tuple[list[float], tuple[float, float]]:
    """:func:`compensate_specific_force` for one sample in plain floats (the engine's path)."""
    fx = accel[0] - accel_forward
    fy = accel[1] - speed * gyro[2]
    fz = accel[2] + speed * gyro[1]
    resid = (math.sqrt(fx * fx + fy * fy + fz * fz) / GRAVITY - 1.0) ** 2
    g2 = GRAVITY * GRAVITY
    var_pitch = (accel_forward_var + speed_var * gyro[1] ** 2) / g2 + resid
    var_roll = speed_var * gyro[2] ** 2 / g2 + resid
    return [fx, fy, fz], (var_pitch, var_roll)


def suspension_attitude(accel_forward: Tensor | float, lateral_accel: Tensor | float,
                        pitch_gradient: Tensor | float, roll_gradient: Tensor | float):
    """Body lean on the suspension (rad): braking dives the nose (positive pitch = nose down),
    a left turn (positive lateral acceleration ``v wz``) rolls the body out of the bend (left side
    up = positive roll). Gradients in rad per m/s^2. Floats in, floats out; tensors likewise.

    Returns:
        ``(pitch, roll)``.
    """
    return -pitch_gradient * accel_forward, roll_gradient * lateral_accel
