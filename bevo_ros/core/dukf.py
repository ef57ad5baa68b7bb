"""Differentiable unscented Kalman filter (DUKF) on the attitude ``[pitch, roll]`` (paper Sec. 2.1).

The gyroscope drives the motion model, the accelerometer's gravity direction is the measurement.
The four noise variances are the only learnable parameters, so gradients of any downstream loss
(BEV projection, phase correlation) reach them through every predict/update.

Conventions follow :mod:`bevo_ros.core.geometry` (REP-103): base = IMU frame, x forward, y left,
z up; ``R = Rz(yaw) Ry(pitch) Rx(roll)``; positive pitch = nose down, positive roll = left side up.
Pitch and roll here are relative to *gravity*; :mod:`bevo_ros.core.road_tilt` turns them into the
attitude relative to the road plane that the BEV needs.

Deviations from the paper (each also commented where it happens):

* Covariance update ``P = P_bar - K S K^T``; the paper's ``+ K S K^T`` is a sign slip (the
  posterior cannot be more uncertain than the prior).
* The process noise ``O`` is a continuous-time density (rad^2/s) scaled by each IMU message's
  own ``dt``, so one set of learned values works at any IMU rate; ``Q`` is per measurement (rad^2).
* The default motion model is the exact Z-Y-X Euler kinematics; the paper's additive model
  (``pitch += wy dt``, ``roll += wx dt``) is available as ``motion_model="additive"``.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import torch
from torch import nn

Tensor = torch.Tensor

__all__ = [
    "DukfState",
    "DUKF",
    "accel_to_pitch_roll",
    "remove_turn_acceleration",
    "steady_state_variance",
    "merwe_weights",
    "euler_motion",
    "additive_motion",
    "MOTION_MODELS",
]

# Defaults from a grid search (O, Q in log steps) over KITTI raw drives 2011_09_30_drive_0016,
# _0018 and _0027 (10 Hz OXTS, filtered angles vs. the unit's own roll/pitch); drive 0020, which
# the tests use, was held out. Q ~ (5.7 deg)^2 is the size of the raw accelerometer-angle error
# there (4-6 deg RMS: braking and centripetal acceleration, not white noise). Only O/Q shapes
# the mean; a ratio O/Q of 3e-5 /s is the roll optimum (0.60 deg RMS vs 4.4 raw) and within 0.1 deg of the pitch
# one (1.41 vs 5.4 raw), which keeps falling as the accelerometer is ignored altogether, i.e.
# pure gyro integration: too fragile against a MEMS gyro's bias to be a default. Q is per
# measurement, so at IMU rates far from 10 Hz the effective weighting changes: learn or retune.
DEFAULT_PROCESS_VAR = (3.0e-7, 3.0e-7)  # rad^2/s
DEFAULT_MEASUREMENT_VAR = (1.0e-2, 1.0e-2)  # rad^2

# Scaled sigma points for n = 2: alpha = 1, beta = 0, kappa = 3 - n = 1 (Julier's original UT).
# n + lambda = 3 matches the Gaussian's fourth moment along every sigma axis, and all weights are
# positive (1/3, 1/6 x 4), so the sigma covariance sum is PSD and float32-safe. The popular small
# alpha (1e-3) gives weights of about -1e6 that cancel catastrophically in float32 and buys
# nothing here: the state spans a few degrees, where the kinematics are nearly linear.
DEFAULT_ALPHA, DEFAULT_BETA, DEFAULT_KAPPA = 1.0, 0.0, 1.0


@dataclass
class DukfState:
    """Gaussian belief over ``[pitch, roll]`` (rad).

    Attributes:
        mean: ``(B, 2)``.
        cov: ``(B, 2, 2)``, symmetric positive definite.
    """

    mean: Tensor
    cov: Tensor

    def detach(self) -> "DukfState":
        """Cut the graph (e.g. between training windows)."""
        return DukfState(self.mean.detach(), self.cov.detach())

    def to(self, device: torch.device | str | None = None, dtype: torch.dtype | None = None) -> "DukfState":
        return DukfState(self.mean.to(device=device, dtype=dtype), self.cov.to(device=device, dtype=dtype))


def steady_state_variance(process_density: float, measurement_var: float, dt: float) -> float:
    """Posterior variance (rad^2) one axis of the filter settles to at a fixed IMU period ``dt``.

    Near level and at small rates the DUKF is a random walk (variance ``O dt`` per step) measured
    directly with variance ``Q``; the Riccati equation then has the closed-form fixed point
    ``P- = O dt / 2 + sqrt((O dt)^2 / 4 + O dt Q)``, ``P = P- Q / (P- + Q)``. This is the filter's
    long-run uncertainty, without the start transient (whose constant error the road-tilt
    high-pass removes from the attitude the BEV uses).
    """
    if not (process_density > 0 and measurement_var > 0 and dt > 0):
        raise ValueError(f"need O, Q, dt > 0, got {process_density}, {measurement_var}, {dt}")
    w = process_density * dt
    prior = 0.5 * w + math.sqrt(0.25 * w * w + w * measurement_var)
    return prior * measurement_var / (prior + measurement_var)


def accel_to_pitch_roll(accel: Tensor) -> Tensor:
    """Pitch and roll of the gravity direction seen by a resting accelerometer.

    ``pitch = -atan2(ax, sqrt(ay^2 + az^2))``, ``roll = atan2(ay, az)`` (the paper's formulas with
    ``atan2``). At rest the accelerometer reads ``R^T [0, 0, g]``, i.e. ``ax = -g sin(pitch)``,
    ``ay = g cos(pitch) sin(roll)``, ``az = g cos(pitch) cos(roll)``, which these formulas invert
    exactly in the REP-103 sign convention (nose down / left side up positive).

    Args:
        accel: ``(..., 3)`` specific force in the base frame, m/s^2.

    Returns:
        ``(..., 2)`` ``[pitch, roll]`` in radians.
    """
    if accel.shape[-1] != 3:
        raise ValueError(f"accel must have a last dimension of 3, got shape {tuple(accel.shape)}")
    ax, ay, az = accel.unbind(-1)
    pitch = -torch.atan2(ax, torch.hypot(ay, az))
    roll = torch.atan2(ay, az)
    return torch.stack([pitch, roll], dim=-1)


def remove_turn_acceleration(accel: Tensor, gyro: Tensor, speed: Tensor) -> Tensor:
    """Subtract the centripetal acceleration of a car turning at ``gyro[..., 2]`` with ``speed``.

    The paper's measurement model assumes the accelerometer sees only gravity. A car in a bend
    also feels ``speed x yaw rate`` sideways: 3 m/s^2 in a 0.2 rad/s bend at 15 m/s, a 17 deg
    error in the accelerometer roll (KITTI's OXTS ``ay`` correlates 0.985 with speed x yaw rate).
    A car's velocity turns with its heading (no sideslip), so this term is exact given the speed.
    Pitch and roll rates are not compensated: bumps rotate the body, not the velocity. ``dv/dt``
    is left in (a differentiated visual speed is too noisy): it shows up as pitch noise that the
    learned Q absorbs.

    Args:
        accel: ``(..., 3)`` specific force, m/s^2; gyro: ``(..., 3)`` rad/s; speed: ``(...,)`` m/s.

    Returns:
        ``(..., 3)`` the specific force without the centripetal part.
    """
    s = speed.to(accel.dtype)
    zero = torch.zeros_like(s)
    return accel - torch.stack([zero, s * gyro[..., 2], zero], dim=-1)


def merwe_weights(n: int, alpha: float, beta: float, kappa: float) -> tuple[float, list[float], list[float]]:
    """Van der Merwe's scaled sigma-point weights (identical to filterpy's ``MerweScaledSigmaPoints``).

    Returns:
        ``(lambda_, wm, wc)`` with ``2n + 1`` mean and covariance weights each.
    """
    lambda_ = alpha**2 * (n + kappa) - n
    if not n + lambda_ > 0:
        raise ValueError(f"alpha^2 (n + kappa) must be positive, got alpha={alpha}, kappa={kappa}, n={n}")
    w = 0.5 / (n + lambda_)
    wm = [lambda_ / (n + lambda_)] + [w] * (2 * n)
    wc = [lambda_ / (n + lambda_) + (1.0 - alpha**2 + beta)] + [w] * (2 * n)
    return lambda_, wm, wc


def _cholesky_2x2(cov: Tensor, floor: float = 1e-30) -> Tensor:
    """Lower Cholesky factor of ``(B, 2, 2)`` symmetric matrices that never fails.

    The closed form (three elementwise ops) is exact for 2x2 and several times faster than a
    LAPACK call on the tiny matrices this filter runs every IMU message; pivots are clamped to
    ``floor`` so a matrix that lost definiteness to rounding gets the factor of a nearby PSD
    matrix instead of NaN, which keeps gradients finite.
    """
    a, b, d = cov[:, 0, 0], cov[:, 1, 0], cov[:, 1, 1]
    l00 = a.clamp_min(floor).sqrt()
    l10 = b / l00
    l11 = (d - l10 * l10).clamp_min(floor).sqrt()
    return torch.stack([l00, torch.zeros_like(l00), l10, l11], dim=-1).reshape(-1, 2, 2)


def _sigma_points(mean: Tensor, cov: Tensor, sel: Tensor) -> Tensor:
    # sel (5, 2) @ L^T (B, 2, 2): row k + 1 of the product is c * column k of L.
    b = mean.shape[0]
    return mean.unsqueeze(1) + torch.bmm(sel.expand(b, 5, 2), _cholesky_2x2(cov).transpose(1, 2))


def additive_motion(sigmas: Tensor, gyro: Tensor, dt: Tensor) -> Tensor:
    """The paper's motion model: ``pitch += wy dt``, ``roll += wx dt``.

    Exact only at zero attitude: with roll != 0 a yaw rate leaks into pitch (see :func:`euler_motion`).

    Args:
        sigmas: ``(B, S, 2)`` ``[pitch, roll]``; gyro: ``(B, 3)`` body rates ``[wx, wy, wz]``; dt: ``(B,)``.

    Returns:
        ``(B, S, 2)``.
    """
    rate = torch.stack([gyro[:, 1], gyro[:, 0]], dim=-1)
    return sigmas + (rate * dt.unsqueeze(-1)).unsqueeze(1)


def euler_motion(sigmas: Tensor, gyro: Tensor, dt: Tensor) -> Tensor:
    """Exact Z-Y-X Euler kinematics (forward Euler step) for ``R = Rz(yaw) Ry(pitch) Rx(roll)``.

    ``pitch_dot = wy cos(roll) - wz sin(roll)``,
    ``roll_dot = wx + (wy sin(roll) + wz cos(roll)) tan(pitch)``.
    A car turning (large wz) while rolled on a cambered road sees ``-wz sin(roll)`` of pitch rate
    that the additive model misses; this is why it is the default. Singular at pitch = +-90 deg,
    far outside any road vehicle's range.

    Args:
        sigmas: ``(B, S, 2)`` ``[pitch, roll]``; gyro: ``(B, 3)`` body rates ``[wx, wy, wz]``; dt: ``(B,)``.

    Returns:
        ``(B, S, 2)``.
    """
    pitch, roll = sigmas.unbind(-1)
    wx, wy, wz = (gyro * dt.unsqueeze(-1)).unsqueeze(1).unbind(-1)  # (B, 1) each, already times dt
    cr, sr = torch.cos(roll), torch.sin(roll)
    d_pitch = wy * cr - wz * sr
    d_roll = wx + (wy * sr + wz * cr) * torch.tan(pitch)
    return sigmas + torch.stack([d_pitch, d_roll], dim=-1)


MOTION_MODELS = {"euler": euler_motion, "additive": additive_motion}


def _as_pair(value: float | Sequence[float] | Tensor, name: str) -> Tensor:
    t = torch.as_tensor(value, dtype=torch.float64).flatten()
    if t.numel() == 1:
        t = t.expand(2)
    if t.numel() != 2:
        raise ValueError(f"{name} must be a scalar or 2 values (pitch, roll), got {tuple(t.shape)}")
    if not bool(torch.isfinite(t).all()) or not bool((t > 0).all()):
        raise ValueError(f"{name} must be finite and > 0, got {t.tolist()}")
    return t


def _check_shape(x: Tensor, shape: tuple[int | None, ...], name: str) -> None:
    """ValueError unless ``x`` is a tensor of ``shape`` (``None`` = any size)."""
    if isinstance(x, Tensor) and x.dim() == len(shape):
        if all(s is None or s == xs for s, xs in zip(shape, x.shape)):
            return
    if not isinstance(x, Tensor):
        raise ValueError(f"{name} must be a torch.Tensor, got {type(x).__name__}")
    want = "(" + ", ".join("*" if s is None else str(s) for s in shape) + ("," if len(shape) == 1 else "") + ")"
    raise ValueError(f"{name} must have shape {want}, got {tuple(x.shape)}")


class DUKF(nn.Module):
    """Unscented Kalman filter on ``[pitch, roll]`` with learnable diagonal noise.

    Parameters (the only ones): ``log_process_var (2,)``: log of O, the continuous-time process
    noise density of [pitch, roll] in rad^2/s (multiplied by each IMU message's own dt);
    ``log_measurement_var (2,)``: log of Q, the variance of the accelerometer angles in rad^2.

    Args:
        process_var: O as plain variances (rad^2/s), scalar or (pitch, roll).
        measurement_var: Q as plain variances (rad^2), scalar or (pitch, roll).
        motion_model: ``"euler"`` (exact kinematics, default) or ``"additive"`` (paper).
        alpha, beta, kappa: scaled sigma-point parameters (see ``DEFAULT_ALPHA``).
        jitter: added to the covariance diagonals (rad^2) after every predict/update so they stay
            SPD in float32; 1e-12 rad^2 = (0.00006 deg)^2 is far below any real uncertainty.
    """

    def __init__(
        self,
        process_var: float | Sequence[float] = DEFAULT_PROCESS_VAR,
        measurement_var: float | Sequence[float] = DEFAULT_MEASUREMENT_VAR,
        motion_model: str = "euler",
        alpha: float = DEFAULT_ALPHA,
        beta: float = DEFAULT_BETA,
        kappa: float = DEFAULT_KAPPA,
        jitter: float = 1e-12,
    ) -> None:
        super().__init__()
        if motion_model not in MOTION_MODELS:
            raise ValueError(f"motion_model must be one of {sorted(MOTION_MODELS)}, got {motion_model!r}")
        if not (math.isfinite(jitter) and jitter >= 0):
            raise ValueError(f"jitter must be finite and >= 0, got {jitter}")
        self.motion_model = motion_model
        self._fx = MOTION_MODELS[motion_model]
        self.alpha, self.beta, self.kappa = float(alpha), float(beta), float(kappa)
        self.lambda_, self._wm, self._wc = merwe_weights(2, self.alpha, self.beta, self.kappa)
        self.jitter = float(jitter)
        self.log_process_var = nn.Parameter(_as_pair(process_var, "process_var").log().float())
        self.log_measurement_var = nn.Parameter(_as_pair(measurement_var, "measurement_var").log().float())
        self._const_cache: dict[tuple[torch.dtype, torch.device], tuple[Tensor, ...]] = {}

    # ----------------------------------------------------------------------------------- noise
    @property
    def process_var(self) -> Tensor:
        """O, ``(2,)`` rad^2/s."""
        return self.log_process_var.exp()

    @property
    def measurement_var(self) -> Tensor:
        """Q, ``(2,)`` rad^2."""
        return self.log_measurement_var.exp()

    def extra_repr(self) -> str:
        o = [f"{v:.3g}" for v in self.process_var.tolist()]
        q = [f"{v:.3g}" for v in self.measurement_var.tolist()]
        return f"motion_model={self.motion_model!r}, process_var={o}, measurement_var={q}"

    def _consts(self, dtype: torch.dtype, device: torch.device) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
        """Sigma selector ``(5, 2)``, ``wm (1, 5)``, ``wc (5, 1)``, I and jitter * I ``(2, 2)``, per dtype/device."""
        key = (dtype, device)
        c = self._const_cache.get(key)
        if c is None:
            s = math.sqrt(2 + self.lambda_)
            sel = torch.tensor([[0.0, 0.0], [s, 0.0], [0.0, s], [-s, 0.0], [0.0, -s]], dtype=dtype, device=device)
            wm = torch.tensor(self._wm, dtype=dtype, device=device).unsqueeze(0)
            wc = torch.tensor(self._wc, dtype=dtype, device=device).unsqueeze(-1)
            eye = torch.eye(2, dtype=dtype, device=device)
            c = self._const_cache[key] = (sel, wm, wc, eye, self.jitter * eye)
        return c

    # ----------------------------------------------------------------------------------- state
    def init_state(
        self,
        accel: Tensor | None = None,
        pitch_roll: Tensor | None = None,
        var: float | Sequence[float] | Tensor | None = None,
        batch_size: int = 1,
    ) -> DukfState:
        """Initial belief.

        Args:
            accel: ``(B, 3)``: start at the accelerometer angles (a vehicle at rest is best).
            pitch_roll: ``(B, 2)``: start at given angles (exclusive with ``accel``).
            var: initial variance (rad^2), scalar, (pitch, roll) or ``(B, 2)``. Default: Q when
                starting from ``accel``/``pitch_roll``, (0.1 rad)^2 when starting level.
            batch_size: B when neither ``accel`` nor ``pitch_roll`` is given (level start).

        Returns:
            ``DukfState`` with ``mean (B, 2)``, ``cov (B, 2, 2)`` diagonal.
        """
        if accel is not None and pitch_roll is not None:
            raise ValueError("give either accel or pitch_roll to init_state, not both")
        if accel is not None:
            _check_shape(accel, (None, 3), "accel")
            self._check_finite(accel=accel)
            mean = accel_to_pitch_roll(accel)
        elif pitch_roll is not None:
            _check_shape(pitch_roll, (None, 2), "pitch_roll")
            self._check_finite(pitch_roll=pitch_roll)
            mean = pitch_roll
        else:
            p = self.log_process_var
            mean = torch.zeros(batch_size, 2, dtype=p.dtype, device=p.device)
            if var is None:
                var = 0.01
        b = mean.shape[0]
        if var is None:
            v = self.measurement_var.to(mean).expand(b, 2)
        else:
            v = torch.as_tensor(var, dtype=mean.dtype, device=mean.device)
            try:
                v = torch.broadcast_to(v, (b, 2))
            except RuntimeError:
                v = None
            if v is None or not bool((torch.isfinite(v) & (v > 0)).all()):
                raise ValueError(f"var must be finite, > 0 and broadcast to ({b}, 2), got {var!r}")
        return DukfState(mean, torch.diag_embed(v))

    # ------------------------------------------------------------------------------ validation
    @staticmethod
    def _check_finite(**tensors: Tensor) -> None:
        for name, t in tensors.items():
            if not bool(torch.isfinite(t).all()):
                raise ValueError(f"{name} contains non-finite values (NaN or inf)")

    @staticmethod
    def _check_inputs(gyro: Tensor | None, accel: Tensor | None, dt: Tensor | None) -> None:
        """One host sync for the common (valid) case; names the culprit otherwise."""
        # A sum is non-finite iff an element is (inf - inf = nan); * 0 keeps only that fact, min
        # propagates NaN and "> 0" is False for NaN: one comparison tests finiteness and dt > 0.
        present = [t for t in (gyro, accel, dt) if t is not None and t.numel() > 0]
        if not present:
            return
        total = present[0].sum()
        for t in present[1:]:
            total = total + t.sum()
        if dt is not None and dt.numel() > 0:
            ok = (total * 0 + dt).min() > 0
        else:
            ok = total * 0 == 0
        if bool(ok):
            return
        for name, t in (("gyro", gyro), ("accel", accel), ("dt", dt)):
            if t is not None and not bool(torch.isfinite(t).all()):
                raise ValueError(f"{name} contains non-finite values (NaN or inf)")
        raise ValueError(f"dt must be > 0 seconds, got min {float(dt.min())}")

    @staticmethod
    def _check_state(state: DukfState) -> int:
        if not isinstance(state, DukfState):
            raise ValueError(f"state must be a DukfState, got {type(state).__name__}")
        _check_shape(state.mean, (None, 2), "state.mean")
        b = state.mean.shape[0]
        _check_shape(state.cov, (b, 2, 2), "state.cov")
        return b

    # ------------------------------------------------------------------------------- filtering
    def predict(self, state: DukfState, gyro: Tensor, dt: Tensor) -> DukfState:
        """Propagate the sigma points through the motion model and add ``O * dt``.

        Args:
            state: belief at t-1; gyro: ``(B, 3)`` body rates ``[wx, wy, wz]`` rad/s; dt: ``(B,)`` s.

        Returns:
            Prior belief at t.
        """
        b = self._check_state(state)
        _check_shape(gyro, (b, 3), "gyro")
        _check_shape(dt, (b,), "dt")
        self._check_inputs(gyro, None, dt)
        return self._predict(state, gyro, dt)

    def update(self, state: DukfState, accel: Tensor) -> DukfState:
        """Correct the prior with the accelerometer angles.

        Args:
            state: prior at t; accel: ``(B, 3)`` specific force, m/s^2.

        Returns:
            Posterior belief at t.
        """
        b = self._check_state(state)
        _check_shape(accel, (b, 3), "accel")
        self._check_inputs(None, accel, None)
        return self._update(state, accel)

    def noise_floats(self) -> tuple[tuple[float, float], tuple[float, float]]:
        """``(O, Q)`` as plain floats, for :meth:`step_scalar` (read once, not per message)."""
        o, q = self.process_var.tolist(), self.measurement_var.tolist()
        return (o[0], o[1]), (q[0], q[1])

    def step_scalar(
        self,
        mean: tuple[float, float],
        cov: tuple[float, float, float],
        gyro: Sequence[float],
        accel: Sequence[float],
        dt: float,
        noise: tuple[tuple[float, float], tuple[float, float]],
        extra_var: tuple[float, float] = (0.0, 0.0),
        return_pull: bool = False,
        return_innovation: bool = False,
    ) -> tuple:
        """:meth:`step` for one vehicle in plain float64 arithmetic: the inference path.

        The same math as ``_predict`` + ``_update`` (sigma points, motion model, closed-form
        identity update, ``- K S K^T``, symmetrisation, jitter), written out for 2x2 so that a
        message costs microseconds instead of ~45 tensor dispatches; test_dukf pins the two
        together to 1e-12. No autograd: training uses the tensor path.

        Args:
            mean: (pitch, roll); cov: (P00, P01, P11); gyro, accel: 3 floats; dt > 0 s;
            noise: ``noise_floats()``; extra_var: added to Q for this message (rad^2, pitch/roll):
            the fused engine's vehicle-acceleration uncertainty (0 reproduces the tensor path);
            return_pull: also return the update's share of the step, posterior minus predicted mean
            (the accelerometer's pull on (pitch, roll), rad); return_innovation: also return the
            accelerometer's (pitch, roll) less the predicted mean (rad) and the gain's diagonal
            (pitch from pitch, roll from roll): ``((ep, er), (k_pp, k_rr))`` (core/gyro_bias reads them).

        Returns:
            the posterior ``(mean, cov)`` in the same form, then the pull with ``return_pull``,
            then the innovation with ``return_innovation``.
        """
        (o0, o1), (q0, q1) = noise
        p, r = mean
        a, b, d = cov
        wx, wy, wz = (float(g) * dt for g in gyro)
        # sigma points from the clamped closed-form Cholesky (as _cholesky_2x2)
        l00 = math.sqrt(max(a, 1e-30))
        l10 = b / l00
        l11 = math.sqrt(max(d - l10 * l10, 1e-30))
        c = math.sqrt(2 + self.lambda_)
        pts = ((p, r), (p + c * l00, r + c * l10), (p, r + c * l11), (p - c * l00, r - c * l10), (p, r - c * l11))
        if self.motion_model == "euler":
            moved = []
            for pi, ri in pts:
                cr, sr = math.cos(ri), math.sin(ri)
                moved.append((pi + wy * cr - wz * sr, ri + wx + (wy * sr + wz * cr) * math.tan(pi)))
        else:
            moved = [(pi + wy, ri + wx) for pi, ri in pts]
        wm, wc = self._wm, self._wc
        mp = sum(w * x[0] for w, x in zip(wm, moved))
        mr = sum(w * x[1] for w, x in zip(wm, moved))
        pa = pb = pd = 0.0
        for w, (xp, xr) in zip(wc, moved):
            dp, dr = xp - mp, xr - mr
            pa += w * dp * dp
            pb += w * dp * dr
            pd += w * dr * dr
        jit = self.jitter
        pa, pd = pa + o0 * dt + jit, pd + o1 * dt + jit
        # update: z from the accelerometer, S = P + Q, K^T = S^-1 P
        ax, ay, az = (float(v) for v in accel)
        zp, zr = -math.atan2(ax, math.hypot(ay, az)), math.atan2(ay, az)
        s00, s11 = pa + q0 + extra_var[0], pd + q1 + extra_var[1]
        det = s00 * s11 - pb * pb
        k00, k01 = (s11 * pa - pb * pb) / det, (s11 * pb - pb * pd) / det  # K^T rows
        k10, k11 = (s00 * pb - pb * pa) / det, (s00 * pd - pb * pb) / det
        ep, er = zp - mp, zr - mr
        new_mean = (mp + ep * k00 + er * k10, mr + ep * k01 + er * k11)
        c00 = pa - (pa * k00 + pb * k10)
        c01 = pb - (pa * k01 + pb * k11)
        c10 = pb - (pb * k00 + pd * k10)
        c11 = pd - (pb * k01 + pd * k11)
        cov_out = (c00 + jit, 0.5 * (c01 + c10), c11 + jit)
        out: tuple = (new_mean, cov_out)
        if return_pull:
            out += ((new_mean[0] - mp, new_mean[1] - mr),)
        if return_innovation:
            out += (((ep, er), (k00, k11)),)
        return out

    def step(self, state: DukfState, gyro: Tensor, accel: Tensor, dt: Tensor) -> DukfState:
        """``predict`` then ``update`` for one IMU message.

        Args:
            state: belief at t-1; gyro: ``(B, 3)`` rad/s; accel: ``(B, 3)`` m/s^2; dt: ``(B,)`` s, > 0.

        Returns:
            Posterior belief at t. Raises ``ValueError`` on bad shapes, non-finite input or dt <= 0.
        """
        b = self._check_state(state)
        _check_shape(gyro, (b, 3), "gyro")
        _check_shape(accel, (b, 3), "accel")
        _check_shape(dt, (b,), "dt")
        self._check_inputs(gyro, accel, dt)
        return self._update(self._predict(state, gyro, dt), accel)

    def filter(
        self, gyro: Tensor, accel: Tensor, dt: Tensor, state: DukfState | None = None
    ) -> tuple[Tensor, Tensor, DukfState]:
        """Run over whole sequences (differentiable end to end).

        Args:
            gyro: ``(B, T, 3)`` rad/s; accel: ``(B, T, 3)`` m/s^2.
            dt: ``(B, T)`` s, > 0: the time from the previous sample (from ``state`` for sample 0).
            state: belief before sample 0. If None, sample 0 initialises the filter
                (``init_state(accel=accel[:, 0])``, so ``mean[:, 0]`` is its accelerometer angles
                with covariance Q) and ``dt[:, 0]`` is not used.

        Returns:
            ``mean (B, T, 2)``, ``cov (B, T, 2, 2)`` (posteriors after each sample), last state.
        """
        _check_shape(gyro, (None, None, 3), "gyro")
        b, t = gyro.shape[:2]
        _check_shape(accel, (b, t, 3), "accel")
        _check_shape(dt, (b, t), "dt")
        if t == 0:
            raise ValueError("filter needs at least one sample (T >= 1)")
        means, covs = [], []
        first = 0
        if state is None:
            self._check_inputs(gyro, accel, dt[:, 1:])
            state = self.init_state(accel=accel[:, 0])
            means.append(state.mean)
            covs.append(state.cov)
            first = 1
        else:
            self._check_inputs(gyro, accel, dt)
            if self._check_state(state) != b:
                raise ValueError(f"state batch {state.mean.shape[0]} != input batch {b}")
        for i in range(first, t):
            state = self._update(self._predict(state, gyro[:, i], dt[:, i]), accel[:, i])
            means.append(state.mean)
            covs.append(state.cov)
        return torch.stack(means, dim=1), torch.stack(covs, dim=1), state

    def forward(self, gyro: Tensor, accel: Tensor, dt: Tensor, state: DukfState | None = None):
        """Alias of :meth:`filter`."""
        return self.filter(gyro, accel, dt, state)

    # --------------------------------------------------------------------------- unchecked math
    # Tiny tensors: the cost is per kernel launch (~1 us), so these use few, batched ops (bmm
    # instead of broadcasting matmul, diagonal noise as vector * eye instead of diag_embed).
    def _predict(self, state: DukfState, gyro: Tensor, dt: Tensor) -> DukfState:
        mean, cov = state.mean, state.cov
        sel, wm, wc, eye, jit = self._consts(mean.dtype, mean.device)
        b = mean.shape[0]
        x = self._fx(_sigma_points(mean, cov, sel), gyro, dt)  # (B, 5, 2)
        mu = torch.bmm(wm.expand(b, 1, 5), x)  # (B, 1, 2)
        d = x - mu
        p = torch.bmm(d.transpose(1, 2), wc * d)
        # O is a density: the noise of one message grows with its own dt (rate independence).
        o = self.log_process_var.exp().to(mean) * eye
        p = p + o * dt.view(b, 1, 1)
        return DukfState(mu.squeeze(1), 0.5 * (p + p.transpose(1, 2)) + jit)

    def _update(self, state: DukfState, accel: Tensor) -> DukfState:
        mu, p = state.mean, state.cov
        eye, jit = self._consts(mu.dtype, mu.device)[3:]
        z = accel_to_pitch_roll(accel)
        # H is the identity on [pitch, roll], and the sigma points are redrawn from the prior
        # (paper: X_bar = Gamma(x_bar)). The unscented transform of redrawn points through the
        # identity is exact: M = mu, Sigma = P + Q, Sigma_XZ = P. These closed forms save a
        # Cholesky and ~15 kernel launches per step; the tests check them against filterpy's
        # full sigma-point update to 1e-9.
        s = p + self.log_measurement_var.exp().to(mu) * eye
        # K = Sigma_XZ S^-1 with S and Sigma_XZ = P symmetric, so K^T = solve(S, P).
        kt = torch.linalg.solve(s, p)
        mean = mu + torch.bmm((z - mu).unsqueeze(1), kt).squeeze(1)  # mu + K (z - M), row vectors
        # Paper: sigma = sigma_bar + K S K^T, a sign slip; the UKF subtracts it. K S K^T = P K^T
        # because K S = Sigma_XZ = P (one product fewer, same value to rounding).
        cov = p - torch.bmm(p, kt)
        return DukfState(mean, 0.5 * (cov + cov.transpose(1, 2)) + jit)
