"""The drive's analytic motion: speed and yaw-rate profiles, suspension, road tilt, named presets.

Model of the drive (all signals are smooth analytic functions of time, so the IMU is exact to
~1e-8):

* the base (IMU) origin moves on the road with speed ``v(t)`` and heading ``yaw(t)``;
  its road-relative attitude is ``R_road_base = Ry(pitch_rel) @ Rx(roll_rel)`` (suspension:
  sinusoids and bump events driven by the road, so fading out below ~3 m/s and gone at rest, and
  load transfer from the longitudinal/lateral acceleration) and its
  height follows from the fixed camera height (the geometry module's constant-elevation model);
* the road is tilted against gravity by a slowly varying slope and camber, defined relative to
  the heading (a banked, graded road the car follows); they vary with the road's own clock,
  which runs with the suspension's excitation (``_RoadClock``), so under a car at rest the road
  does not tilt:
  ``R_grav_base = Rz(yaw) @ Ry(slope) @ Rx(camber) @ Ry(pitch_rel) @ Rx(roll_rel)``;
* the velocity in the gravity frame is the road-frame velocity carried by the local road tilt,
  ``v_grav = Rz(yaw) Ry(slope) Rx(camber) [v, 0, dz/dt]``; its time derivative is the kinematic
  acceleration of the accelerometer model (rotating the whole world plane by the tilt instead would
  create huge spurious accelerations far from the origin);
* speed and yaw rate are seeded random (sines, curve events) or a named preset (:data:`PRESETS`:
  sustained curve, hard braking, start inside a bend, stop-and-go, bumpy road, on-ramp, urban,
  traffic light, highway, parking: the one that reverses) built from C4 smooth steps with
  closed-form integrals; the suspension, road tilt and noise stay seeded either way;
* gyro = body angular velocity of ``R_grav_base`` (5-point central differences of the analytic
  rotation, error ~1e-9 rad/s), accel = specific force ``R_grav_base^T (a_grav + [0, 0, g])``
  (error ~3e-8 m/s^2).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Protocol, Sequence

import numpy as np

from bevo_ros.core.geometry import CameraModel
from bevo_ros.rotations import rotation_vector, rotation_x, rotation_y, rotation_z

__all__ = ["GRAVITY", "PRESETS", "REVERSING_PRESETS"]

GRAVITY = 9.80665

# ---------------------------------------------------------------------------------------------
# Drive: analytic motion model
# ---------------------------------------------------------------------------------------------


def _d5(f, t: np.ndarray, h: float = 1e-3) -> np.ndarray:
    """5-point central derivative of a vectorised ``f(t) -> (N, ...)`` (truncation ~h^4)."""
    return (f(t - 2 * h) - 8 * f(t - h) + 8 * f(t + h) - f(t + 2 * h)) / (12 * h)


@dataclass
class _Sines:
    """``sum a_i sin(2 pi f_i t + p_i)``."""

    a: np.ndarray
    f: np.ndarray
    p: np.ndarray

    @staticmethod
    def random(rng: np.random.Generator, n: int, f_lo: float, f_hi: float, total: float) -> "_Sines":
        a = rng.uniform(0.5, 1.0, n)
        return _Sines(a * (total / a.sum()), rng.uniform(f_lo, f_hi, n), rng.uniform(0, 2 * math.pi, n))

    def __call__(self, t: np.ndarray) -> np.ndarray:
        w = 2 * math.pi * self.f
        return (self.a * np.sin(w * t[..., None] + self.p)).sum(-1)

    def deriv(self, t: np.ndarray) -> np.ndarray:
        w = 2 * math.pi * self.f
        return (self.a * w * np.cos(w * t[..., None] + self.p)).sum(-1)

    def integral(self, t: np.ndarray) -> np.ndarray:
        """Integral from 0 to t."""
        w = 2 * math.pi * self.f
        return (self.a / w * (np.cos(self.p) - np.cos(w * t[..., None] + self.p))).sum(-1)


def _window(t: np.ndarray, lo: float, hi: float) -> slice | np.ndarray:
    """Indices of ``t`` in ``[lo, hi]``: a slice for sorted 1-D ``t`` (cheap), else a mask."""
    if t.ndim == 1 and (len(t) < 2 or t[-1] >= t[0]):
        return slice(int(np.searchsorted(t, lo)), int(np.searchsorted(t, hi, side="right")))
    return (t >= lo) & (t <= hi)


_SUPPORT = 9.0  # events are evaluated within +-9 sigma (exp(-40) ~ 4e-18: exact in float64)


@dataclass
class _Bumps:
    """``sum a_k (1 - u^2)^4`` for ``|u| < 1``, ``u = (t - c_k) / w_k``: C3 bumps (the curves of the
    yaw rate) whose integral is a polynomial, so yaw is exact and cheap."""

    a: np.ndarray
    c: np.ndarray
    w: np.ndarray

    def __call__(self, t: np.ndarray) -> np.ndarray:
        t = np.asarray(t, dtype=np.float64)
        out = np.zeros(t.shape)
        for a, c, w in zip(self.a, self.c, self.w):
            sl = _window(t, c - w, c + w)
            u = (t[sl] - c) / w
            out[sl] += a * (1.0 - u * u) ** 4
        return out

    def deriv(self, t: np.ndarray) -> np.ndarray:
        t = np.asarray(t, dtype=np.float64)
        out = np.zeros(t.shape)
        for a, c, w in zip(self.a, self.c, self.w):
            sl = _window(t, c - w, c + w)
            u = (t[sl] - c) / w
            out[sl] += a * -8.0 * u * (1.0 - u * u) ** 3 / w
        return out

    @staticmethod
    def _antideriv(u: np.ndarray) -> np.ndarray:
        u = np.clip(u, -1.0, 1.0)
        u2 = u * u
        return u * (1.0 + u2 * (-4.0 / 3.0 + u2 * (6.0 / 5.0 + u2 * (-4.0 / 7.0 + u2 / 9.0))))

    def integral(self, t: np.ndarray) -> np.ndarray:
        """Integral from 0 to t."""
        t = np.asarray(t, dtype=np.float64)
        out = np.zeros(t.shape)
        for a, c, w in zip(self.a, self.c, self.w):
            out += a * w * (self._antideriv((t - c) / w) - self._antideriv(np.asarray(-c / w)))
        return out


@dataclass
class _Gabors:
    """``sum a_k exp(-(t - c_k)^2 / (2 s_k^2)) sin(2 pi f_k (t - c_k) + p_k)``: smooth bump events."""

    a: np.ndarray
    c: np.ndarray
    s: np.ndarray
    f: np.ndarray
    p: np.ndarray

    def __call__(self, t: np.ndarray) -> np.ndarray:
        t = np.asarray(t, dtype=np.float64)
        out = np.zeros(t.shape)
        for a, c, s, f, p in zip(self.a, self.c, self.s, self.f, self.p):
            w = _window(t, c - _SUPPORT * s, c + _SUPPORT * s)
            dt = t[w] - c
            out[w] += a * np.exp(-0.5 * (dt / s) ** 2) * np.sin(2 * math.pi * f * dt + p)
        return out


# Profiles: speed and yaw rate of a drive, exact in closed form (the IMU and poses stay consistent).


class _Profile(Protocol):
    """A signal of relative time ``t (N,)``: value, time derivative, ``start + integral from 0 to t``."""

    def __call__(self, t: np.ndarray) -> np.ndarray: ...

    def deriv(self, t: np.ndarray) -> np.ndarray: ...

    def integral(self, t: np.ndarray, start: float = 0.0) -> np.ndarray: ...


@dataclass
class _Affine:
    """``mid + half * f(t)`` of a profile ``f`` (the random drive's speed)."""

    mid: float
    half: float
    f: _Sines

    def __call__(self, t):
        return self.mid + self.half * self.f(t)

    def deriv(self, t):
        return self.half * self.f.deriv(t)

    def integral(self, t, start: float = 0.0):
        return start + self.mid * np.asarray(t, dtype=np.float64) + self.half * self.f.integral(t)


@dataclass
class _Sum:
    """The sum of profiles (the random drive's yaw rate: curves + wander)."""

    parts: tuple

    def __call__(self, t):
        out = self.parts[0](t)
        for p in self.parts[1:]:
            out = out + p(t)
        return out

    def deriv(self, t):
        out = self.parts[0].deriv(t)
        for p in self.parts[1:]:
            out = out + p.deriv(t)
        return out

    def integral(self, t, start: float = 0.0):
        out = start
        for p in self.parts:
            out = out + p.integral(t)
        return out


def _smoothstep_antiderivs() -> list[np.polynomial.Polynomial]:
    """``[S', S, int S, int int S]`` on ``[0, 1]`` of the C4 smooth step ``S' = 630 u^4 (1 - u)^4``."""
    u = np.polynomial.Polynomial([0.0, 1.0])
    out = [630.0 * u**4 * (1.0 - u) ** 4]
    for _ in range(3):
        out.append(out[-1].integ())  # lower bound 0: zero at u = 0
    return out


_STEP = _smoothstep_antiderivs()


_STEP_AT1 = [1.0] + [float(p(1.0)) for p in _STEP[2:]]  # Phi_0(1) = 1 (exactly), Phi_1(1), Phi_2(1)


def _step_phi(j: int, u: np.ndarray) -> np.ndarray:
    """``Phi_j(u)``: ``j = -1, 0, 1, 2`` -> the smooth step's derivative, itself, its first and second
    antiderivatives; 0 before ``u = 0``, continued exactly after ``u = 1`` (where ``S = 1``)."""
    u = np.asarray(u, dtype=np.float64)
    uc = np.clip(u, 0.0, 1.0)
    if j == 0:  # S(u) = 1 - S(1 - u): accurate near both ends, so 0 <= S <= 1 (no reversing speed)
        return np.where(uc > 0.5, 1.0 - _STEP[1](1.0 - uc), _STEP[1](uc))
    inside = _STEP[j + 1](uc)
    if j < 0:
        return inside  # S' vanishes at both ends
    e = np.maximum(u - 1.0, 0.0)
    beyond = sum(_STEP_AT1[j - i] * e**i / math.factorial(i) for i in range(j + 1))
    return np.where(u > 1.0, beyond, inside)


@dataclass
class _Ramps:
    """A piecewise-smooth profile: holds joined by C4 smooth steps (closed-form derivative and integral).

    ``order = 0``: the value steps, ``f = base + sum_k delta_k S((t - t_k) / d_k)`` (speed changes, curve
    entries). ``order = 1``: the derivative steps, ``f' = sum_k delta_k S(...)``, ``f(-inf) = base``
    (acceleration held at a level: braking). Constant before the first step.
    """

    base: float
    t: np.ndarray  # (K,) step starts, s
    d: np.ndarray  # (K,) step durations, s
    delta: np.ndarray  # (K,) step heights
    order: int = 0

    def _terms(self, j: int, t) -> np.ndarray:
        t = np.asarray(t, dtype=np.float64)
        out = np.zeros(t.shape)
        for tk, dk, ak in zip(self.t, self.d, self.delta):
            out += ak * dk ** (self.order + j) * _step_phi(self.order + j, (t - tk) / dk)
        return out

    def __call__(self, t):
        return self.base + self._terms(0, t)

    def deriv(self, t):
        return self._terms(-1, t)

    def integral(self, t, start: float = 0.0):
        t = np.asarray(t, dtype=np.float64)
        return start + self.base * t + self._terms(1, t) - self._terms(1, np.zeros(()))


def _levels(start: float, changes: Sequence[tuple[float, float, float]]) -> _Ramps:
    """Value steps from ``start``: ``changes = [(t_start, duration, new_level), ...]`` in time order."""
    lv = [start] + [c[2] for c in changes]
    return _Ramps(float(start), np.array([c[0] for c in changes], float), np.array([c[1] for c in changes], float),
                  np.diff(np.asarray(lv, float)), 0)


def _accel_levels(v0: float, changes: Sequence[tuple[float, float, float]]) -> _Ramps:
    """Speed from acceleration steps: ``changes = [(t_start, duration, new_acceleration), ...]``, speed ``v0``
    before the first."""
    lv = [0.0] + [c[2] for c in changes]
    return _Ramps(float(v0), np.array([c[0] for c in changes], float), np.array([c[1] for c in changes], float),
                  np.diff(np.asarray(lv, float)), 1)


_DEG = math.pi / 180.0


@dataclass
class _Motion:
    """Analytic drive signals of relative time ``t`` (seconds from the first stamp)."""

    speed_profile: _Profile  # v(t) m/s, negative reversing (only the ``parking`` preset)
    yaw0: float
    yaw_rate_profile: _Profile  # rad/s; yaw = yaw0 + its integral
    pitch_sines: _Sines
    roll_sines: _Sines
    pitch_bumps: _Gabors
    roll_bumps: _Gabors
    load_pitch: float  # rad per m/s^2 of longitudinal acceleration (braking -> nose down)
    load_roll: float  # rad per m/s^2 of lateral acceleration (body leans out of the curve)
    slope0: float
    camber0: float
    slope_sines: _Sines
    camber_sines: _Sines
    t_base_cam: np.ndarray  # (3,)
    cam_height: float
    # The road drives the body's oscillation and bumps: full above this speed (m/s), fading to
    # nothing at rest (a car standing at a light does not pitch by a degree between frames).
    excitation_speed: float = 3.0
    # Crests and sags: slope steps as a function of the distance travelled (m -> rad), a road's
    # vertical curves; the renderer bends the road ahead with them (the drive's ``road_profile``).
    hills: _Ramps | None = None
    # The clock the slope's and camber's sines run on (None: time itself, a drive never slower
    # than excitation_speed): it stops with the car.
    road_clock: "_RoadClock | None" = None

    def excitation(self, t):
        """Road excitation of the suspension in [0, 1]: a C2 smoothstep of ``|speed| / excitation_speed``."""
        u = np.clip(np.abs(self.speed(t)) / self.excitation_speed, 0.0, 1.0)
        return u * u * u * (10.0 - 15.0 * u + 6.0 * u * u)

    def speed(self, t):
        return self.speed_profile(t)

    def speed_dot(self, t):
        return self.speed_profile.deriv(t)

    def yaw_rate(self, t):
        return self.yaw_rate_profile(t)

    def yaw(self, t):
        return self.yaw_rate_profile.integral(t, self.yaw0)

    def pitch_rel(self, t):
        return self.excitation(t) * (self.pitch_sines(t) + self.pitch_bumps(t)) - self.load_pitch * self.speed_dot(t)

    def roll_rel(self, t):
        return (self.excitation(t) * (self.roll_sines(t) + self.roll_bumps(t))
                + self.load_roll * self.speed(t) * self.yaw_rate(t))

    def distance(self, t):
        """Distance travelled since ``t = 0`` (negative before), m."""
        return self.speed_profile.integral(np.asarray(t, dtype=np.float64), 0.0)

    def road_time(self, t):
        """The road's clock (s): ``t`` while the car moves faster than ``excitation_speed``, slower
        below it, standing still with the car."""
        return t if self.road_clock is None else self.road_clock(t)

    def slope(self, t):
        out = self.slope0 + self.slope_sines(self.road_time(t))
        return out if self.hills is None else out + self.hills(self.distance(t))

    def camber(self, t):
        return self.camber0 + self.camber_sines(self.road_time(t))

    def r_road_base(self, t):
        return rotation_y(self.pitch_rel(t)) @ rotation_x(self.roll_rel(t))

    def r_grav_base(self, t):
        return rotation_z(self.yaw(t)) @ rotation_y(self.slope(t)) @ rotation_x(self.camber(t)) @ self.r_road_base(t)

    def z_base(self, t):
        """Base origin height above the road (the camera centre stays at ``cam_height``)."""
        return self.cam_height - (self.r_road_base(t) @ self.t_base_cam)[..., 2]

    def vel_grav(self, t):
        """Base velocity in the gravity frame, ``(N, 3)``."""
        v = np.stack([self.speed(t), np.zeros_like(t), _d5(self.z_base, t)], -1)
        r = rotation_z(self.yaw(t)) @ rotation_y(self.slope(t)) @ rotation_x(self.camber(t))
        return (r @ v[..., None])[..., 0]

    def gyro(self, t):
        """Body angular velocity of ``R_grav_base``, ``(N, 3)`` rad/s."""
        r = self.r_grav_base(t)
        omega = np.swapaxes(r, -1, -2) @ _d5(self.r_grav_base, t)
        return 0.5 * np.stack([omega[..., 2, 1] - omega[..., 1, 2], omega[..., 0, 2] - omega[..., 2, 0],
                               omega[..., 1, 0] - omega[..., 0, 1]], -1)

    def gyro_interval_mean(self, t, dt: float):
        """Mean body angular velocity over ``(t - dt, t]``, ``(N, 3)`` rad/s: the rotation between
        the two attitudes as a rotation vector over ``dt``, what an IMU reporting its integrated
        rate (delta angle) over each sample interval gives."""
        rel = np.swapaxes(self.r_grav_base(t - dt), -1, -2) @ self.r_grav_base(t)
        return rotation_vector(rel) / dt

    def specific_force(self, t):
        """Accelerometer reading without noise, ``(N, 3)`` m/s^2 in the base frame."""
        a = _d5(self.vel_grav, t) + np.array([0.0, 0.0, GRAVITY])
        return (np.swapaxes(self.r_grav_base(t), -1, -2) @ a[..., None])[..., 0]


@dataclass(frozen=True)
class _RoadClock:
    """``tau(t) = integral of excitation(t) dt`` from ``tau(0) = 0``: the slope and camber (seeded
    sines of time, as a road's grade and banking pass under a car at a steady speed) stand still
    while the car does. A cubic Hermite spline through the integral on a 1 ms grid, its slope the
    excitation itself at each node, so the IMU's finite differences see a smooth clock."""

    spline: object  # scipy.interpolate.CubicHermiteSpline

    @staticmethod
    def of(m: "_Motion", t_lo: float, t_hi: float) -> "_RoadClock | None":
        """The clock over ``[t_lo, t_hi]`` (s; evaluated beyond it the spline extrapolates), or None
        where the car never drops below ``excitation_speed`` there (then it is time itself)."""
        from scipy.interpolate import CubicHermiteSpline

        n = int(math.ceil((t_hi - t_lo) / 1e-3))
        grid = np.linspace(t_lo, t_hi, n + 1)
        rate = m.excitation(grid)
        if rate.min() >= 1.0:
            return None
        tau = np.concatenate([[0.0], np.cumsum(0.5 * (rate[1:] + rate[:-1]) * np.diff(grid))])
        tau -= np.interp(0.0, grid, tau)
        return _RoadClock(CubicHermiteSpline(grid, tau, rate))

    def __call__(self, t):
        return self.spline(t)


def _random_motion(rng: np.random.Generator, t_lo: float, t_hi: float, *, speed_range, speed_variation,
                   curvature, max_yaw_rate, max_lateral_accel, bumps, road_tilt, camera: CameraModel,
                   start_yaw: float) -> _Motion:
    vmin, vmax = speed_range
    speed_sines = _Sines.random(rng, 3, 0.015, 0.06, 1.0)
    mid, half = 0.5 * (vmin + vmax), 0.5 * (vmax - vmin) * speed_variation
    # Curves: smooth yaw-rate bumps every 4-10 s, limited by yaw rate and lateral acceleration.
    centres = []
    c = t_lo + rng.uniform(0.0, 4.0)
    while c < t_hi:
        centres.append(c)
        c += rng.uniform(4.0, 10.0)
    centres = np.asarray(centres)
    half_width = rng.uniform(2.0, 6.0, len(centres))
    v_at = mid + half * speed_sines(centres) if len(centres) else centres
    amp = rng.choice([-1.0, 1.0], len(centres)) * rng.uniform(0.25, 1.0, len(centres))
    amp = amp * np.minimum(max_yaw_rate, max_lateral_accel / np.maximum(v_at, 1e-3)) * curvature
    curves = _Bumps(amp, centres, half_width)
    wander = _Sines.random(rng, 2, 0.01, 0.04, 0.012 * curvature)
    # Keep the yaw rate (overlapping events add up) within max_yaw_rate.
    tt = np.linspace(t_lo, t_hi, max(200, int((t_hi - t_lo) * 20)))
    peak = np.abs(curves(tt) + wander(tt)).max() if curvature > 0 else 0.0
    if peak > max_yaw_rate:
        curves = _Bumps(curves.a * (max_yaw_rate / peak), curves.c, curves.w)
        wander = _Sines(wander.a * (max_yaw_rate / peak), wander.f, wander.p)
    # Suspension: continuous oscillation 0.5-3 Hz plus bump events (about one per 3 s).
    n_b = max(1, int((t_hi - t_lo) / 3.0))
    bc = rng.uniform(t_lo, t_hi, n_b)
    bs = rng.uniform(0.15, 0.4, n_b)
    bf = rng.uniform(0.8, 2.0, n_b)
    pitch_bumps = _Gabors(rng.choice([-1.0, 1.0], n_b) * rng.uniform(0.7, 2.0, n_b) * _DEG * bumps, bc, bs, bf,
                          rng.uniform(0, 2 * math.pi, n_b))
    roll_bumps = _Gabors(rng.choice([-1.0, 1.0], n_b) * rng.uniform(0.4, 1.5, n_b) * _DEG * bumps, bc, bs,
                         bf * rng.uniform(0.8, 1.2, n_b), rng.uniform(0, 2 * math.pi, n_b))
    pitch_sines = _Sines.random(rng, 4, 0.5, 3.0, 0.6 * _DEG * bumps)
    roll_sines = _Sines.random(rng, 4, 0.5, 3.0, 0.5 * _DEG * bumps)
    if road_tilt is True:
        slope0, camber0 = rng.uniform(-0.5, 1.5) * _DEG, rng.uniform(1.8, 2.8) * _DEG
        slope_s = _Sines.random(rng, 2, 0.005, 0.03, 0.7 * _DEG)
        camber_s = _Sines.random(rng, 2, 0.005, 0.03, 0.4 * _DEG)
    else:
        slope0, camber0 = (0.0, 0.0) if road_tilt is False else (float(road_tilt[0]), float(road_tilt[1]))
        slope_s = camber_s = _Sines(np.zeros(1), np.ones(1), np.zeros(1))
    return _Motion(
        speed_profile=_Affine(mid, half, speed_sines), yaw0=start_yaw, yaw_rate_profile=_Sum((curves, wander)),
        pitch_sines=pitch_sines, roll_sines=roll_sines, pitch_bumps=pitch_bumps,
        roll_bumps=roll_bumps, load_pitch=0.3 * _DEG * bumps, load_roll=0.5 * _DEG * bumps,
        slope0=slope0, camber0=camber0, slope_sines=slope_s, camber_sines=camber_s,
        t_base_cam=camera.T_base_cam[:3, 3].detach().cpu().double().numpy(), cam_height=float(camera.mount_height),
    )


def _integrate_xy(m: _Motion, t: np.ndarray, start_xy: tuple[float, float], i0: int) -> np.ndarray:
    """Planar position on the uniform grid ``t`` (``t[i0] == 0``): corrected trapezoid, error ~h^4."""
    h = t[1] - t[0]
    v, vd, yaw, w = m.speed(t), m.speed_dot(t), m.yaw(t), m.yaw_rate(t)
    c, s = np.cos(yaw), np.sin(yaw)
    f = np.stack([v * c, v * s], -1)
    fd = np.stack([vd * c - v * w * s, vd * s + v * w * c], -1)
    inc = 0.5 * h * (f[1:] + f[:-1]) + (h * h / 12.0) * (fd[:-1] - fd[1:])
    xy = np.concatenate([np.zeros((1, 2)), np.cumsum(inc, 0)], 0)
    return xy - xy[i0] + np.asarray(start_xy)


# ---------------------------------------------------------------------------------------------
# Named drives (presets)
# ---------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class _Preset:
    """A named drive: fixed speed and yaw-rate profiles; suspension, road tilt, noise stay seeded."""

    description: str
    duration: float  # s, the whole manoeuvre (a longer drive holds the last state)
    speed: _Ramps
    yaw_rate: _Ramps
    bumps_gain: float = 1.0  # times the ``bumps`` argument
    vibration_gain: float = 1.0  # times ImuNoise.accel_vibration
    bump_rate: float = 0.0  # extra short bump events per second (potholes, joints)
    reverses: bool = False  # the speed goes negative (only then may it)


def _stop_and_go_speed() -> _Ramps:
    # 9 m/s <-> 1 m/s (0.1 m per 10 Hz frame) in 6 s (peak 3.3 m/s^2), the second dip a full stop.
    changes, t = [], 1.0
    for low, hold in ((1.0, 1.5), (0.0, 2.0), (1.0, 1.5)):
        changes += [(t, 6.0, low), (t + 6.0 + hold, 6.0, 9.0)]
        t += 12.0 + hold + 1.5
    return _levels(9.0, changes)


_PRESETS: dict[str, _Preset] = {
    "curve": _Preset(
        "sustained left curve of 100 m radius at 15 m/s (2.25 m/s^2 lateral, 0.15 rad/s = 8.6 deg/s) "
        "from t = 4 s to 12 s; straight 2 s, 2 s smooth entry and exit, straight to 16 s",
        16.0, _levels(15.0, []), _levels(0.0, [(2.0, 2.0, 0.15), (12.0, 2.0, 0.0)])),
    "braking": _Preset(
        "straight, 15 m/s until t = 2 s, then -5 m/s^2 braking (0.5 s smooth onset and release) down to "
        "2 m/s at t = 5.1 s, held to 8 s",
        8.0, _accel_levels(15.0, [(2.0, 0.5, -5.0), (4.6, 0.5, 0.0)]), _levels(0.0, [])),
    "bend_start": _Preset(
        "starts inside a left bend: 12 m/s at 0.18 rad/s (2.16 m/s^2 centripetal at the first sample); "
        "leaves it over t = 3..5 s while speeding up to 14 m/s by t = 7 s; 10 s",
        10.0, _levels(12.0, [(3.0, 4.0, 14.0)]), _levels(0.18, [(3.0, 2.0, 0.0)])),
    "stop_and_go": _Preset(
        "stop-and-go: 9 m/s down to 1 m/s (0.1 m per 10 Hz frame), to a full 2 s stop, and to 1 m/s "
        "again, 6 s ramps (<= 3.7 m/s^2), two gentle turns; 46 s",
        46.0, _stop_and_go_speed(), _levels(0.0, [(9.0, 3.0, 0.1), (13.0, 3.0, 0.0), (25.0, 3.0, -0.08),
                                                  (29.0, 3.0, 0.0)])),
    "bumpy": _Preset(
        "bumpy road: suspension 2.5x, extra short bumps (1 per s), vibration 2x; 7-10 m/s with gentle "
        "curves (<= 0.06 rad/s); 20 s",
        20.0, _levels(8.0, [(4.0, 4.0, 10.0), (12.0, 4.0, 7.0), (17.0, 3.0, 8.0)]),
        _levels(0.0, [(2.0, 3.0, 0.06), (7.0, 3.0, -0.05), (13.0, 3.0, 0.04), (17.0, 3.0, 0.0)]),
        bumps_gain=2.5, vibration_gain=2.0, bump_rate=1.0),
    "on_ramp": _Preset(
        "highway on-ramp: 10.5 m/s into a 30 m radius bend at t = 0.5 s (0.35 rad/s = 20 deg/s, 3.7 m/s^2 "
        "centripetal) for 98 deg of turn, out of it at t = 5.9 s while speeding up to 15 m/s by t = 9 s; 12 s",
        12.0, _levels(10.5, [(6.0, 3.0, 15.0)]), _levels(0.0, [(0.5, 1.0, 0.35), (5.4, 1.0, 0.0)])),
    "urban": _Preset(
        "urban: 8 m/s, braking to 3 m/s for a 90 deg right turn (0.3 rad/s), on at 8 m/s, braking to "
        "1 m/s (0.1 m per 10 Hz frame) and a 90 deg left turn while pulling away to 6 m/s; 26 s",
        26.0, _levels(8.0, [(1.0, 3.0, 3.0), (9.5, 3.0, 8.0), (13.0, 3.0, 1.0), (17.0, 3.0, 6.0)]),
        _levels(0.0, [(3.5, 1.0, -0.3), (8.736, 1.0, 0.0), (16.0, 1.0, 0.25), (22.283, 1.0, 0.0)])),
    "traffic_light": _Preset(
        "traffic light: 10 m/s with a gentle curve, braking (<= 3.1 m/s^2) to a full stop at t = 9 s, 15 s at rest, "
        "pulling away to 8 m/s by t = 30 s and turning right; 32 s",
        32.0, _levels(10.0, [(1.0, 8.0, 0.0), (24.0, 6.0, 8.0)]),
        _levels(0.0, [(2.0, 2.0, 0.03), (5.0, 2.0, 0.0), (27.0, 2.0, -0.08), (30.0, 2.0, 0.0)])),
    "parking": _Preset(
        "parking: 4 m/s braking to a stop at t = 4 s, 2 s at rest, reversing at 1.5 m/s from t = 6 s with a 29 deg "
        "turn into a bay (7.5 m radius, t = 7.5..11 s), stopping at t = 13 s, 2 s at rest, pulling away "
        "forward to 3 m/s by t = 18 s; 22 s",
        22.0, _levels(4.0, [(1.0, 3.0, 0.0), (6.0, 2.0, -1.5), (11.0, 2.0, 0.0), (15.0, 3.0, 3.0)]),
        _levels(0.0, [(7.5, 1.0, -0.2), (10.0, 1.0, 0.0)]), reverses=True),
    "highway": _Preset(
        "highway: 28 m/s (100 km/h) into a 1000 m radius left curve (0.028 rad/s) at t = 2 s, a gentle right one "
        "at t = 7 s, slowing to 25 m/s over t = 6..10 s; 12 s",
        12.0, _levels(28.0, [(6.0, 4.0, 25.0)]),
        _levels(0.0, [(2.0, 2.0, 0.028), (7.0, 2.0, -0.02), (10.0, 1.5, 0.0)])),
}

PRESETS: dict[str, str] = {name: p.description for name, p in _PRESETS.items()}
"""Named deterministic drives for :func:`make_drive` ``(preset=...)``: name -> description."""
REVERSING_PRESETS: frozenset[str] = frozenset(name for name, p in _PRESETS.items() if p.reverses)
"""The presets whose car reverses (no traffic with them: other cars follow the path forwards)."""


def _random_hills(rng: np.random.Generator, s_lo: float, s_hi: float, v_max: float) -> _Ramps:
    """Crests and sags over the distance ``[s_lo, s_hi]`` (m): the slope moves by 0.7-2.5 deg over
    25-70 m (vertical curve radii from ~600 m; the KITTI sample's crest is ~900 m), longer where
    ``v_max`` (m/s) would make the vertical acceleration exceed 0.4 m/s^2 (roads are designed for
    their speed: a 100 km/h road's crests are kilometres long), then holds for 15-95 m; it stays
    within 3 deg of level."""
    changes, s, level = [], s_lo + rng.uniform(0.0, 40.0), 0.0
    while s < s_hi:
        step = rng.choice([-1.0, 1.0]) * rng.uniform(0.7, 2.5) * _DEG
        # the smooth step's peak curvature is 2.46 step / length (630 / 2^8 at its middle)
        length = max(rng.uniform(25.0, 70.0), 2.46 * abs(step) * v_max**2 / 0.4)
        if abs(level + step) > 3.0 * _DEG:
            step = -step
        level += step
        changes.append((s, length, level))
        s += length + rng.uniform(15.0, 95.0)
    return _levels(0.0, changes)


def _with_preset(m: _Motion, p: _Preset, rng: np.random.Generator, t_lo: float, t_hi: float, bumps: float) -> _Motion:
    """The seeded random motion with the preset's speed and yaw rate (and its extra short bumps)."""
    out = replace(m, speed_profile=p.speed, yaw_rate_profile=p.yaw_rate)
    n = int(round(p.bump_rate * (t_hi - t_lo)))
    if not n:
        return out
    c, s, f = rng.uniform(t_lo, t_hi, n), rng.uniform(0.1, 0.25, n), rng.uniform(1.0, 2.5, n)
    pitch_a = rng.choice([-1.0, 1.0], n) * rng.uniform(0.2, 0.6, n) * _DEG * bumps
    roll_a = rng.choice([-1.0, 1.0], n) * rng.uniform(0.2, 0.5, n) * _DEG * bumps
    phase = rng.uniform(0, 2 * math.pi, (2, n))

    def more(g: _Gabors, a: np.ndarray, ph: np.ndarray) -> _Gabors:
        return _Gabors(*(np.concatenate([x, y]) for x, y in zip((g.a, g.c, g.s, g.f, g.p), (a, c, s, f, ph))))

    return replace(out, pitch_bumps=more(m.pitch_bumps, pitch_a, phase[0]), roll_bumps=more(m.roll_bumps, roll_a, phase[1]))
