"""Separate the slowly varying road tilt (camber, slope) from the vehicle's own attitude.

The DUKF's pitch/roll are relative to *gravity*: an accelerometer cannot tell vehicle roll from
road camber. The BEV projection needs the attitude relative to the *road plane* (see
``geometry.camera_pose_on_road``); on KITTI the gravity-referenced roll holds ~2.6 deg of camber,
which projected into the BEV biases every yaw estimate by ~1 deg.

Road tilt changes slowly (time constants of many seconds at road speed); the attitude the paper
filters (suspension, bumps, braking) changes within a second or two. So the road tilt is
estimated by a first-order low-pass of the filtered gravity-referenced attitude and the
road-relative attitude is what remains:

    alpha_t = 1 - exp(-dt_t / tau)            (per-sample dt: any IMU/camera rate, gaps included)
    alpha_t = max(alpha_t, dt_t / elapsed_t)  (a running mean for the first ~tau seconds, so
                                               the first, noisy sample is not locked in)
    tilt_t  = tilt_{t-1} + alpha_t (x_t - tilt_{t-1}),   tilt_0 = x_0
    road_relative_t = x_t - tilt_t

Trade-offs of ``tau``: attitude changes lasting longer than ~tau (a long lean in a steady bend, a
long hill's start) are progressively absorbed into the tilt, and a change of camber/slope shows
up in the road-relative attitude until it decays with tau. The engine's default is 1 s: against
the road pitch derived from the unit's velocity on the four shared real OXTS drives (the unit's
pitch minus the slope ``atan(vu / v)``, heave smoothed out), fused mode's road pitch is 0.18 deg
RMS at 1 s, 0.21 at 1.5 s and 0.24 at 2 s (0.18 at 0.7 s; with a coarser reference 1 s is the
best); it also removes what the accelerometer gets wrong for seconds (braking, bends), and bumps
stay (the synthetic demo drive: 9 cm/frame at 2 s vs 31 cm/frame at 10 s). On a crest or sag the
low-pass lags the slope (by ~tau x the slope's rate) and the road ahead bends away from the plane
under the car: the KITTI sample's crest reads 4-11 cm short per frame, and 0.7 s helps it (1.72 ->
1.38 % drift), while the real-dynamics clips rendered over their own crests and sags lose per frame
what they gain in drift (README, "How well it does", ``--vertical-curves``: 59 16 s clips 3.91 -> 4.06 cm, 1.57 ->
1.52 %; 94 5 s clips 3.84 -> 4.03 cm, 2.33 -> 2.28 %): 1 s stays for now.

``time_constant <= 0``, ``inf`` or ``None`` disables the low-pass: the attitude is returned
unchanged. The rig's static attitude on the road (``filter.mounting_pitch/roll``, the engine's
``mounting_attitude``) is added back by the callers (:class:`~bevo_ros.core.odometry.BevoOdometry`,
:func:`~bevo_ros.core.sequence.frame_attitudes`), only with the low-pass on: it removes every
constant, while without it the gravity-referenced attitude holds the mounting already.
"""
from __future__ import annotations

import math
import torch

Tensor = torch.Tensor

__all__ = ["RoadTiltFilter", "road_relative_attitude", "lowpass_gain", "is_enabled"]


def is_enabled(time_constant: float | None) -> bool:
    """True if ``time_constant`` (s) switches the low-pass on: finite and > 0."""
    return time_constant is not None and math.isfinite(float(time_constant)) and float(time_constant) > 0


def lowpass_gain(dt: Tensor, time_constant: float | Tensor, elapsed: Tensor | None = None) -> Tensor:
    """``alpha = 1 - exp(-dt / tau)`` (via expm1: exact for dt << tau). ``(...,)`` -> ``(...,)``.

    With ``elapsed`` (seconds since the first sample, this one's dt included) the gain is at least
    ``dt / elapsed``: for the first ~tau seconds the tilt is the running mean of everything seen so
    far instead of staying pinned to the first, noisy sample (a bias-corrected start).
    """
    alpha = -torch.expm1(-dt / time_constant)
    if elapsed is not None:
        alpha = torch.maximum(alpha, torch.where(elapsed > 0, dt / elapsed.clamp_min(1e-12), torch.ones_like(dt)))
    return alpha


def _check_time_constant(time_constant: float | Tensor | None) -> float | Tensor | None:
    if time_constant is None:
        return None
    if isinstance(time_constant, Tensor):
        if time_constant.numel() != 1:
            raise ValueError(f"time_constant must be a scalar, got shape {tuple(time_constant.shape)}")
        value = float(time_constant.detach())
    else:
        value = float(time_constant)
    if math.isnan(value):
        raise ValueError("time_constant is NaN (use <= 0, inf or None to disable the road-tilt low-pass)")
    return time_constant if is_enabled(value) else None


def _check_attitude(x: Tensor, shape: tuple[int | str, ...], name: str) -> None:
    """ValueError unless ``x`` is a finite tensor of ``shape`` (a str entry = any size, named)."""
    ok = isinstance(x, Tensor) and x.dim() == len(shape)
    if not ok or any(isinstance(s, int) and s != xs for s, xs in zip(shape, x.shape)):
        got = tuple(x.shape) if isinstance(x, Tensor) else type(x).__name__
        want = "(" + ", ".join(str(s) for s in shape) + ("," if len(shape) == 1 else "") + ")"
        raise ValueError(f"{name} must be a tensor of shape {want}, got {got}")
    if not bool(torch.isfinite(x).all()):
        raise ValueError(f"{name} contains non-finite values (NaN or inf)")


def road_relative_attitude(
    pitch_roll: Tensor,
    dt: Tensor,
    time_constant: float | Tensor | None,
) -> Tensor:
    """Road-relative attitude of whole sequences (batched, differentiable).

    Args:
        pitch_roll: ``(B, T, 2)`` gravity-referenced ``[pitch, roll]`` (e.g. DUKF means), rad.
        dt: ``(B, T)`` seconds since the previous sample, >= 0; ``dt[:, 0]`` is unused (sample 0
            initialises the low-pass, so the output starts at 0).
        time_constant: tau in seconds; <= 0, inf or None disables the low-pass.

    Returns:
        ``(B, T, 2)`` attitude relative to the road plane; identical to feeding the samples one by
        one to :class:`RoadTiltFilter`.
    """
    _check_attitude(pitch_roll, ("B", "T", 2), "pitch_roll")
    b, t = pitch_roll.shape[:2]
    if not isinstance(dt, Tensor) or dt.shape != (b, t):
        raise ValueError(f"dt must be a tensor of shape ({b}, {t}), got {getattr(dt, 'shape', type(dt).__name__)}")
    tau = _check_time_constant(time_constant)
    if tau is None:
        return pitch_roll
    if t > 1:
        _check_attitude(dt[:, 1:], (b, t - 1), "dt[:, 1:]")
        if bool((dt[:, 1:] < 0).any()):
            raise ValueError("dt must be >= 0 (time must not run backwards)")
    dt = dt.to(pitch_roll)
    steps = dt.clone()
    steps[:, 0] = 0.0
    # elapsed time counts one sample period for the first sample (a running mean over samples).
    first = dt[:, 1:2] if t > 1 else torch.ones_like(dt[:, :1])
    alpha = lowpass_gain(dt, tau, elapsed=torch.cumsum(steps, dim=1) + first).unsqueeze(-1)  # (B, T, 1)
    tilt = pitch_roll[:, 0]
    tilts = [tilt]
    for i in range(1, t):
        tilt = tilt + alpha[:, i] * (pitch_roll[:, i] - tilt)
        tilts.append(tilt)
    return pitch_roll - torch.stack(tilts, dim=1)


class RoadTiltFilter:
    """Streaming road-tilt separation for one vehicle, in plain floats (the engine runs it on every
    IMU message: microseconds, where tensor ops cost tens). The recurrence is exactly that of
    :func:`road_relative_attitude`, which is the batched, differentiable form (training); a test
    pins the two together.

    Args:
        time_constant: tau in seconds; <= 0, inf or None disables the low-pass (see module doc).
    """

    def __init__(self, time_constant: float | None) -> None:
        tau = _check_time_constant(time_constant)
        # A tensor is read as its value: this streaming form is not differentiable.
        self.time_constant = None if tau is None else float(tau.detach() if isinstance(tau, Tensor) else tau)
        self.reset()

    @property
    def enabled(self) -> bool:
        """True if the low-pass is on."""
        return self.time_constant is not None

    @property
    def tilt(self) -> tuple[float, float] | None:
        """Current road tilt estimate [pitch, roll] (rad); None before the first sample."""
        return self._tilt

    def reset(self) -> None:
        """Forget the tilt; the next sample re-initialises it."""
        self._tilt: tuple[float, float] | None = None
        self._stamp: float | None = None
        self._elapsed: float | None = None

    def shift(self, pitch: float, roll: float) -> None:
        """Move the tilt by ``(pitch, roll)`` (rad): its input moved by that much for good."""
        if self._tilt is not None and self.enabled:
            self._tilt = (self._tilt[0] + pitch, self._tilt[1] + roll)

    def update(self, stamp: float, pitch: float, roll: float) -> tuple[float, float]:
        """Feed one sample: its stamp (s, not before the previous one) and the gravity-referenced
        pitch and roll (rad). Returns the (pitch, roll) relative to the road plane."""
        if not (math.isfinite(stamp) and math.isfinite(pitch) and math.isfinite(roll)):
            raise ValueError(f"stamp, pitch and roll must be finite, got {stamp!r}, {pitch!r}, {roll!r}")
        if not self.enabled:
            self._tilt = (0.0, 0.0)
        elif self._tilt is None:
            self._tilt = (pitch, roll)
        else:
            dt = stamp - self._stamp
            if dt < 0:
                raise ValueError(f"time ran backwards (dt = {dt:.6f} s); call reset() after a jump")
            # elapsed counts one sample period for the first sample (a running mean over samples).
            self._elapsed = 2.0 * dt if self._elapsed is None else self._elapsed + dt
            alpha = -math.expm1(-dt / self.time_constant)  # lowpass_gain, in floats
            alpha = max(alpha, dt / max(self._elapsed, 1e-12) if self._elapsed > 0 else 1.0)
            tp, tr = self._tilt
            self._tilt = (tp + alpha * (pitch - tp), tr + alpha * (roll - tr))
        self._stamp = stamp
        return pitch - self._tilt[0], roll - self._tilt[1]
