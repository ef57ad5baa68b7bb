"""Vehicle motion filter over frames: forward speed, its rate and the yaw gyro's bias.

The paper composes each frame's phase-correlation result into the pose as it comes; on a car
that turns per-frame noise into drift and one bad correlation into a jump. A car's motion is
smooth (1 m/s^2 changes the motion by 1 cm per frame per frame) and its yaw is measured far
better by the gyro than by the BEVs (0.04 vs 0.3 deg per frame on KITTI). So:

* state ``[v, a, b]``: mean forward speed over the last frame interval (m/s), its rate (m/s^2)
  and the bias of the yaw rate about the road normal (rad/s); constant-acceleration model with
  a jerk density, bias random walk;
* measurements per frame, each a scalar Kalman update behind its own Mahalanobis gate: the
  correlation's forward motion ``dx / dt`` (variance from the correlation spread and the
  attitude uncertainty), and the gyro's yaw increment minus the correlation's rotation, which
  observes the bias;
* outputs: ``dx = v dt``, ``dyaw`` = gyro increment minus bias, ``dy`` = the correlation's lateral
  motion fused with the no-sideslip prior ``dx tan(dyaw / 2)`` (the chord of an arc).

A gated (or textureless) frame is carried by the prediction, never composed from a meaningless
peak. The speed and acceleration also feed the DUKF's acceleration compensation
(:mod:`bevo_ros.core.vehicle_dynamics`).

The arithmetic is written once for plain floats (the engine: microseconds per frame) and
``(B,)`` tensors (training: differentiable in the log-variances); a test pins the two. The
covariance is kept as its 6 unique entries.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import torch

Tensor = torch.Tensor

__all__ = ["VehicleNoise", "VehicleState", "VehicleFrame", "VehicleFilter", "initial_vehicle_state", "forget_speed",
           "forget_accel_bias"]


@dataclass
class VehicleNoise:
    """The motion filter's noise (learned like the DUKF's O and Q; floats or tensors).

    Attributes:
        jerk_density: m^2/s^5, white jerk of the forward motion (hard braking onsets are ~10 m/s^3).
        bias_walk_density: rad^2/s^3, random walk of the yaw gyro's bias.
        gyro_yaw_density: rad^2/s, the yaw increment's variance per second (angle random walk).
        slip_std: lateral motion not explained by the no-sideslip arc, per metre travelled.
        imu_accel_density: m^2/s^3, noise density of the accelerometer's forward acceleration
            (``f_x + g sin(pitch)``, vibration and bias); its mean over a frame interval measures
            ``a`` (the inertial speed input, fused item 16; 0 = off). The engine removes gravity at
            the gyro's pitch since the start (``odometry.INERTIAL_PULL_MEMORY``), whose constant
            error ``beta`` takes; with it on, the DUKF subtracts the filter's ``a`` from its
            accelerometer (fused item 17). 1.0 (2026-12-04, against off): per frame better on every set (KITTI
            sample 5.15 -> 4.45 cm, 1.72 -> 1.28 % drift; real-IMU 16 s clips 3.70 -> 3.33 cm; presets
            5.54 -> 4.76 %); drift better on the presets (1.80 -> 1.66 %) and with traffic (2.16 ->
            2.10 %), worse on the real-IMU clips' cold starts (16 s 1.63 -> 1.69 %, 5 s 2.31 -> 2.44 %).
        accel_bias_walk_density: m^2/s^5, random walk of ``beta``, the forward accelerometer bias
            (a pitch error of 0.1 deg is 0.017 m/s^2).
        image_rotation_std: rad, the images' rotation error beyond its correlation spread (an
            attitude error shears the BEV into a rotation): 1 deg took the 10 Hz curve preset's yaw
            from 0.10 to 0.06 deg per frame (KITTI sample 0.091 -> 0.066), the gyro bias still observed.
        min_quality: correlation peak quality in [0, 1] below which a frame carries no information
            (a black, covered or overexposed frame).
        gate: Mahalanobis distance (sigmas) beyond which a measurement is rejected.
        rotation_gate: rad; a frame whose image rotation differs from the bias-corrected gyro's
            increment by more than this plus (:data:`BIAS_RATE_BOUND` + 3 x the bias estimate's
            standard deviation) x ``dt`` is not used for the bias, and widens the bias's variance
            by :data:`ROTATION_REJECT_WIDEN` (a lasting disagreement is a bias after all). Set for
            10 Hz frames: per frame, so at 30 Hz a car turning under ~9 deg/s passes it. The bias
            changes slowly, so such a frame saw something else turn: a car ahead (synthetic
            ``urban`` with traffic: the drive's heading 9.4 -> 2.0 deg off, drift 6.7 -> 2.8 %).
            The Mahalanobis gate cannot catch it: ``image_rotation_std`` (1 deg per frame) is what
            weights the images against the gyro over many frames.
    """

    jerk_density: float = 10.0
    bias_walk_density: float = 1e-8
    gyro_yaw_density: float = 1e-6
    slip_std: float = 0.03
    imu_accel_density: float = 1.0
    accel_bias_walk_density: float = 1e-4
    image_rotation_std: float = 0.0175
    min_quality: float = 0.05
    gate: float = 5.0
    rotation_gate: float = 0.00524

    LEARNED = ("jerk_density", "bias_walk_density", "gyro_yaw_density", "slip_std", "imu_accel_density",
               "accel_bias_walk_density", "image_rotation_std")
    OFF_WHEN_ZERO = ("imu_accel_density",)  # 0 in a learned file switches that input off


N_STATE = 4  # v, a, b (yaw gyro bias), beta (forward accelerometer bias)

# At rest: the acceleration measured as zero with this standard deviation (m/s^2), and the
# frame's yaw change variance (rad^2: a car does not turn in place).
STANDSTILL_ACCEL_STD = 0.05
STANDSTILL_YAW_VAR = 1e-10
# rad/s: how far the yaw gyro's true bias may be from its estimate beyond the estimate's own
# 3 sigma, on top of ``rotation_gate`` (the images' per-frame error); x ``dt`` per frame.
BIAS_RATE_BOUND = math.radians(1.0)
# The bias variance's factor per frame the rotation gate rejects: a lasting disagreement (a bias that
# jumped, or larger than the prior said: 8 deg/s at 10 Hz, 5 deg/s at 5 Hz) opens the gate within
# frames instead of locking the images out for good; a car's turn of a second or two does not.
ROTATION_REJECT_WIDEN = 1.05


@dataclass
class VehicleState:
    """Belief ``x = [v, a, b, beta]`` and its covariance ``P`` (4x4 nested lists; floats or ``(B,)``
    tensors). ``beta``: the accelerometer's forward bias, gravity's share of a pitch error
    included, observed when the inertial speed input is on."""

    x: list
    P: list

    @property
    def v(self):
        return self.x[0]

    @property
    def a(self):
        return self.x[1]

    @property
    def b(self):
        return self.x[2]

    def var(self, i: int):
        return self.P[i][i]

    def speed_at(self, elapsed: float):
        """Extrapolated speed ``v + a t`` and its variance, for the accelerometer compensation."""
        P = self.P
        return self.v + self.a * elapsed, P[0][0] + 2 * P[0][1] * elapsed + P[1][1] * elapsed * elapsed


def initial_vehicle_state(speed_std: float = 30.0, accel_std: float = 3.0, bias_std: float = 0.01,
                          accel_bias_std: float = 0.3, like: Tensor | None = None) -> VehicleState:
    """Unknown speed (a start, a reset): zero means with wide variances. ``like (B,)`` for tensors."""
    var = [speed_std**2, accel_std**2, bias_std**2, accel_bias_std**2]
    z = 0.0 if like is None else torch.zeros_like(like)
    return VehicleState([z] * N_STATE, [[(z + var[i]) if i == j else z for j in range(N_STATE)] for i in range(N_STATE)])


def forget_accel_bias(s: VehicleState, accel_bias_std: float = 0.3) -> VehicleState:
    """``s`` with the forward accelerometer bias ``beta`` unknown again (zero mean, the start's
    variance, no correlation): the attitude it held the gravity error of started anew."""
    fresh = initial_vehicle_state(accel_bias_std=accel_bias_std, like=s.v if isinstance(s.v, Tensor) else None)
    x = list(s.x[:3]) + [fresh.x[3]]
    P = [[fresh.P[i][j] if i == 3 or j == 3 else s.P[i][j] for j in range(N_STATE)] for i in range(N_STATE)]
    return VehicleState(x, P)


def forget_speed(s: VehicleState, speed_std: float = 30.0, accel_std: float = 3.0) -> VehicleState:
    """``s`` with its speed and acceleration unknown again (zero means, wide variances, no
    correlation), the biases kept: the images showed the speed belief to be wrong."""
    fresh = initial_vehicle_state(speed_std, accel_std, like=s.v if isinstance(s.v, Tensor) else None)
    x = [fresh.x[0], fresh.x[1]] + list(s.x[2:])
    P = [[fresh.P[i][j] if i < 2 or j < 2 else s.P[i][j] for j in range(N_STATE)] for i in range(N_STATE)]
    return VehicleState(x, P)


@dataclass
class VehicleFrame:
    """One frame's output (floats or ``(B,)`` tensors).

    ``motion`` = (dx, dy, dyaw), ``variance`` = their variances; ``accepted`` = (translation, rotation)
    measurements used; ``mahalanobis`` = their distances (sigmas, before the gate).
    """

    motion: tuple
    variance: tuple
    accepted: tuple
    mahalanobis: tuple
    state: VehicleState = field(repr=False, default=None)
    speed_accepted: object = None  # the outside speed (``step``'s ``speed``) used; None without one


# The widening stops where the speed's / acceleration's standard deviation reaches 10 x a start's
# (300 m/s, 30 m/s^2): every measurement refused for good (a gate of 0) ran them to inf, and the
# DUKF's compensation on to NaN, within a minute.
MAX_WIDENED_VAR = (300.0**2, 30.0**2)


def _widen_speed_belief(P: list, widen, like) -> list:
    """``P`` with the speed/acceleration block (and only it) times 4 where ``widen`` (bool, or a bool
    tensor shaped as ``like``, the state's dtype): after a rejected speed measurement, so that a
    lasting disagreement opens the gate within a few frames instead of locking the filter out. Less
    than 4 (not below 1) where that would take a variance past :data:`MAX_WIDENED_VAR`."""
    if isinstance(widen, Tensor):
        room = torch.minimum(MAX_WIDENED_VAR[0] / P[0][0], MAX_WIDENED_VAR[1] / P[1][1]).clamp(1.0, 4.0)
        k = torch.where(widen, room, torch.ones_like(room)).to(like.dtype)
    else:
        k = max(1.0, min(4.0, MAX_WIDENED_VAR[0] / P[0][0], MAX_WIDENED_VAR[1] / P[1][1])) if widen else 1.0
    return [[P[i][j] * (k if i < 2 and j < 2 else 1.0) for j in range(N_STATE)] for i in range(N_STATE)]


def _where(cond, a, b):
    if isinstance(cond, Tensor):
        return torch.where(cond, a, b)
    return a if cond else b


def _sqrt(x):
    return x.clamp_min(0).sqrt() if isinstance(x, Tensor) else math.sqrt(max(x, 0.0))


def _tan(x):
    return torch.tan(x) if isinstance(x, Tensor) else math.tan(x)


def _scalar_update(x: list, p: list, k: int | tuple[int, ...], z, r, gate, enabled):
    """Sequential scalar Kalman update with measurement ``z`` of ``x[k]`` (or of the sum of the
    entries ``k``, a tuple), variance ``r``, behind a Mahalanobis ``gate`` (sigmas).

    ``x`` = the state list; ``p`` = its covariance, nested lists (symmetric). Returns
    (x, p, accepted, distance).
    """
    n = len(x)
    ks = (k,) if isinstance(k, int) else k
    hp = [sum(p[i][j] for j in ks) for i in range(n)]  # P H^T
    y = z - sum(x[j] for j in ks)
    s = sum(hp[j] for j in ks) + r
    d = _sqrt(y * y / s)
    ok = enabled & (d < gate) if isinstance(d, Tensor) else (enabled and d < gate)
    gain = [hp[i] / s for i in range(n)]
    new_x = [_where(ok, x[i] + gain[i] * y, x[i]) for i in range(n)]
    new_p = [[_where(ok, p[i][j] - gain[i] * hp[j], p[i][j]) for j in range(n)] for i in range(n)]
    return new_x, new_p, ok, d


class VehicleFilter:
    """Predict/update over frames; stateless apart from its noise (the state is passed around)."""

    def __init__(self, noise: VehicleNoise | None = None) -> None:
        self.noise = noise or VehicleNoise()

    def predict(self, s: VehicleState, dt) -> VehicleState:
        """Constant acceleration over ``dt``: ``v' = v + a dt`` (interval means); biases walk."""
        n = self.noise
        P = s.P
        q = n.jerk_density
        # F P F^T with F = I + dt e_v e_a^T, plus the jerk and the two bias walks.
        row_v = [P[0][j] + dt * P[1][j] for j in range(N_STATE)]
        new = [row[:] for row in P]
        new[0] = row_v
        for i in range(N_STATE):
            new[i][0] = row_v[i] if i != 0 else row_v[0] + dt * row_v[1]
        new[0][0] += q * dt**3 / 3
        new[0][1] = new[1][0] = new[0][1] + q * dt * dt / 2
        new[1][1] += q * dt
        new[2][2] += n.bias_walk_density * dt
        new[3][3] += n.accel_bias_walk_density * dt
        x = list(s.x)
        x[0] = s.v + s.a * dt
        return VehicleState(x, new)

    def inertial_update(self, s: VehicleState, dt, imu_accel=None, imu_accel_var=None) -> VehicleState:
        """``s`` updated with the accelerometer's mean forward acceleration over the coming ``dt``
        (``z = a + beta``, never gated; see :meth:`step`); ``s`` itself when ``imu_accel`` is None."""
        if imu_accel is None:
            return s
        x, P, _, _ = _scalar_update(s.x, s.P, (1, 3), imu_accel, imu_accel_var + self.noise.imu_accel_density / dt,
                                    math.inf, True)
        return VehicleState(x, P)

    def speed_update(self, s: VehicleState, speed, speed_var) -> VehicleState:
        """``s`` updated with an outside forward speed (see :meth:`step`'s ``speed``)."""
        x, P, _ = self._speed_update(s.x, s.P, speed, speed_var)
        return VehicleState(x, P)

    def _speed_update(self, x: list, P: list, speed, speed_var):
        x, P, accepted, _ = _scalar_update(x, P, 0, speed, speed_var, self.noise.gate, True)
        # rejected: the belief, not the sensor, may be wrong (widened as for the images' forward motion)
        return x, _widen_speed_belief(P, ~accepted if isinstance(accepted, Tensor) else not accepted, x[0]), accepted

    def step(self, s: VehicleState, dt, gyro_yaw, forward=None, forward_var=None, lateral=None,
             lateral_var=None, rotation=None, rotation_var=None, quality=None, imu_accel=None,
             imu_accel_var=None, rest_var=None, speed=None, speed_var=None) -> VehicleFrame:
        """One frame: predict by ``dt`` (s) and update with what the correlation gave.

        Args:
            s: the belief after the previous frame.
            gyro_yaw: yaw increment over the interval integrated from the gyro (rad, bias included).
            forward, lateral, rotation: the correlation's (dx, dy, dyaw) with their variances;
                None (or a quality below ``min_quality``) = no image information this frame.
            quality: the correlation peak quality in [0, 1].
            imu_accel: the accelerometer's mean forward acceleration over the interval (m/s^2,
                gravity removed at the gyro's pitch since the start, fused item 16; its constant
                error is ``beta``'s) and ``imu_accel_var`` the variance of its
                attitude part; it updates ``a`` before the prediction (inertial speed propagation:
                a braking onset is in the prediction, not a surprise for the gate).
            rest_var: > 0 when the vehicle stood still over the interval
                (:mod:`bevo_ros.core.standstill`): the variance (m^2) of the frame's forward and
                lateral motion at rest (what the standstill threshold leaves possible); None or 0
                when moving (a float or ``(B,)``). At rest the speed is measured as zero with
                ``rest_var / dt^2`` and its rate as zero, the gyro's whole yaw increment is its bias
                (the images' rotation is exactly zero), the correlation is not used, and the motion
                is exactly zero: a car at rest neither creeps on the correlation's noise nor turns on
                the gyro's bias.
            speed, speed_var: a forward speed that does not come from the images (wheel odometry,
                CAN, GNSS), its mean over the interval (m/s, signed) and that mean's variance: it
                measures ``v`` behind the gate before the correlation does (the correlation's gate
                then judges the images against it). None = none.
        """
        n = self.noise
        p = self.predict(self.inertial_update(s, dt, imu_accel, imu_accel_var), dt)
        x, P = p.x, p.P
        have = forward is not None
        if have and quality is not None:
            informative = quality >= n.min_quality
        else:
            informative = have
        if rest_var is None:
            rest_var = 0.0
        still = rest_var > 0
        if isinstance(still, Tensor) or still:
            # Zero velocity and acceleration (never gated: the images decided), and zero rotation:
            # the gyro's increment is its bias.
            x, P, _, _ = _scalar_update(x, P, 0, 0.0, _where(still, rest_var, 1.0) / (dt * dt), math.inf, still)
            x, P, _, _ = _scalar_update(x, P, 1, 0.0, STANDSTILL_ACCEL_STD**2, math.inf, still)
            x, P, _, _ = _scalar_update(x, P, 2, gyro_yaw / dt, n.gyro_yaw_density / dt, n.gate, still)
            informative = informative & ~still if isinstance(still, Tensor) else False
        acc_s = None
        if speed is not None:
            x, P, acc_s = self._speed_update(x, P, speed, speed_var)
        acc_t = acc_r = False
        d_t = d_r = float("nan")
        if have:
            x, P, acc_t, d_t = _scalar_update(x, P, 0, forward / dt, forward_var / (dt * dt), n.gate, informative)
            # A rejected informative measurement may be the model's fault (a braking onset harder
            # than the jerk noise allows): widen the speed/acceleration belief so that a lasting
            # disagreement opens the gate within a few frames instead of locking the filter out.
            P = _widen_speed_belief(P, informative & ~acc_t if isinstance(acc_t, Tensor) else informative and not acc_t,
                                    x[0])
        if have and rotation is not None:
            z_b = (gyro_yaw - rotation) / dt
            r_b = (rotation_var + n.gyro_yaw_density * dt) / (dt * dt)
            # widened by the bias estimate's own 3 sigma: a gyro whose bias is not known yet (a start)
            # may disagree with the images by more
            bound = n.rotation_gate + (BIAS_RATE_BOUND + 3.0 * _sqrt(P[2][2])) * dt
            residual = (z_b - x[2]) * dt  # the bias-corrected gyro's turn less the images', rad
            if isinstance(residual, Tensor):
                plausible = residual.abs() <= bound
                # (full_like: a Python 1.05 in torch.where would be rounded to float32)
                k = torch.where(informative & ~plausible, torch.full_like(residual, ROTATION_REJECT_WIDEN),
                                torch.ones_like(residual))
            else:
                plausible = abs(residual) <= bound
                k = ROTATION_REJECT_WIDEN if informative and not plausible else 1.0
            x, P, acc_r, d_r = _scalar_update(x, P, 2, z_b, r_b, n.gate, informative & plausible)
            if isinstance(k, Tensor) or k != 1.0:
                root = _sqrt(k)  # the bias's variance times k, its covariances times sqrt(k): P stays positive
                P = [[P[i][j] * (k if i == j == 2 else root if 2 in (i, j) else 1.0) for j in range(N_STATE)]
                     for i in range(N_STATE)]
        state = VehicleState(x, P)
        dx = x[0] * dt
        dyaw = gyro_yaw - x[2] * dt
        var_dx = P[0][0] * dt * dt
        var_dyaw = n.gyro_yaw_density * dt + P[2][2] * dt * dt
        prior = dx * _tan(dyaw / 2)
        var_prior = (n.slip_std * dx) ** 2 + 1e-6
        if have and lateral is not None:
            w = var_prior / (var_prior + lateral_var)
            use = acc_t  # a rejected frame's lateral motion is as meaningless as its forward one
            dy = _where(use, prior + w * (lateral - prior), prior)
            var_dy = _where(use, var_prior * (1 - w), var_prior)
        else:
            dy, var_dy = prior, var_prior
        if isinstance(still, Tensor) or still:
            zero = dx * 0.0
            dx, dy, dyaw = _where(still, zero, dx), _where(still, zero, dy), _where(still, zero, dyaw)
            var_dx = _where(still, zero + rest_var, var_dx)
            var_dy = _where(still, zero + rest_var, var_dy)
            var_dyaw = _where(still, zero + STANDSTILL_YAW_VAR, var_dyaw)
        return VehicleFrame((dx, dy, dyaw), (var_dx, var_dy, var_dyaw), (acc_t, acc_r), (d_t, d_r), state, acc_s)

