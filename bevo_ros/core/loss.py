"""KL loss between the DPC distributions and Gaussian-blurred one-hot targets (paper 2.4).

Direction: ``KL(target || predicted) = sum_i t_i (log t_i - log p_i)``. This is the usual
"soft cross-entropy" direction: the target has full support (a Gaussian), so the loss is finite
and well-behaved even when the prediction puts (numerically) zero mass somewhere, it needs only
``log p`` (from ``log_softmax``, never ``log(0)``), and its gradient w.r.t. the logits is simply
``p - t``. The reverse direction ``KL(p || t)`` is mode-seeking and lets the prediction collapse
onto any single cell inside the target's bump, rewarding over-confident, shifted peaks.
"""
from __future__ import annotations

import math

import torch

Tensor = torch.Tensor


def gaussian_target_1d(centre: Tensor, bins: Tensor, sigma: float, period: float | None = None) -> Tensor:
    """Gaussian-blurred one-hot over 1-D bins, normalised to sum 1.

    Args:
        centre: ``(B,)`` target values (same unit as ``bins``).
        bins: ``(A,)`` bin centres.
        sigma: blur, same unit (> 0).
        period: if given, distances wrap with this period (angles: ``pi`` for DPC rotation bins).

    Returns:
        ``(B, A)``.
    """
    if sigma <= 0:
        raise ValueError(f"sigma must be > 0, got {sigma}")
    if centre.ndim != 1 or bins.ndim != 1:
        raise ValueError(f"need centre (B,) and bins (A,), got {tuple(centre.shape)} and {tuple(bins.shape)}")
    d = bins[None, :].to(centre.dtype) - centre[:, None]
    if period is not None:
        d = torch.remainder(d + period / 2, period) - period / 2
    logits = -0.5 * (d / sigma) ** 2
    return torch.softmax(logits, dim=-1)


def gaussian_target_2d(centre: Tensor, grid: Tensor, sigma: float, period: float | None = None) -> Tensor:
    """Gaussian-blurred one-hot over a 2-D grid of bins, normalised to sum 1.

    Args:
        centre: ``(B, 2)`` target, e.g. ``(d_row, d_col)`` pixels.
        grid: ``(S, S, 2)`` bin coordinates (``Registration.translation_bins``).
        sigma: blur (> 0).
        period: if given, distances wrap with this period (the phase-correlation shift grid is
            cyclic with period ``S``).

    Returns:
        ``(B, S, S)``.
    """
    if sigma <= 0:
        raise ValueError(f"sigma must be > 0, got {sigma}")
    if centre.ndim != 2 or centre.shape[-1] != 2 or grid.ndim != 3 or grid.shape[-1] != 2:
        raise ValueError(f"need centre (B, 2) and grid (S, S, 2), got {tuple(centre.shape)} and {tuple(grid.shape)}")
    d = grid[None].to(centre.dtype) - centre[:, None, None, :]
    if period is not None:
        d = torch.remainder(d + period / 2, period) - period / 2
    logits = -0.5 * (d**2).sum(dim=-1) / sigma**2
    B = centre.shape[0]
    return torch.softmax(logits.reshape(B, -1), dim=-1).reshape(logits.shape)


def kl_target_predicted(target: Tensor, log_prob: Tensor) -> Tensor:
    """``KL(target || p)`` per item, summed over all but the batch dimension. -> ``(B,)``."""
    t = target.reshape(target.shape[0], -1)
    lp = log_prob.reshape(log_prob.shape[0], -1)
    # Cells without target mass contribute nothing (0 log 0 = 0); masking log p there as well keeps
    # a -inf log-probability from turning into 0 * inf = nan, forward and backward.
    pos = t > 0
    log_t = torch.log(torch.where(pos, t, torch.ones_like(t)))
    lp = torch.where(pos, lp, torch.zeros_like(lp))
    return (t * (log_t - lp)).sum(dim=-1)


def registration_kl_loss(registration, target_angle: Tensor, target_shift: Tensor,
                         sigma_angle: float = math.radians(1.0), sigma_shift: float = 1.0) -> Tensor:
    """``KL(rotation target || rotation distribution) + KL(translation target || translation
    distribution)``, mean over the batch. -> scalar.

    Args:
        registration: a ``phase_correlation.Registration`` (uses its log-probabilities and bins).
        target_angle: ``(B,)`` radians (wrapped to the bins' 180-degree period).
        target_shift: ``(B, 2)`` pixels ``(d_row, d_col)``.
        sigma_angle: target blur in radians.
        sigma_shift: target blur in pixels.
    """
    rl, tl = registration.rotation_log_prob, registration.translation_log_prob
    B = rl.shape[0]
    if target_angle.shape != (B,) or target_shift.shape != (B, 2):
        raise ValueError(f"need target_angle ({B},) and target_shift ({B}, 2), got "
                         f"{tuple(target_angle.shape)} and {tuple(target_shift.shape)}")
    t_rot = gaussian_target_1d(target_angle.to(rl.dtype), registration.rotation_bins, sigma_angle, period=math.pi)
    S = tl.shape[-1]
    t_tr = gaussian_target_2d(target_shift.to(tl.dtype), registration.translation_bins, sigma_shift, period=float(S))
    return (kl_target_predicted(t_rot, rl) + kl_target_predicted(t_tr, tl)).mean()


__all__ = ["gaussian_target_1d", "gaussian_target_2d", "kl_target_predicted", "registration_kl_loss"]
