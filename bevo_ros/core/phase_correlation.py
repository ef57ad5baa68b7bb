"""Differentiable phase correlation (DPC) of two BEV images: rotation first, then translation.

Paper Section 2.3 (after Chen et al. 2020, "Deep Phase Correlation"), with the scale fixed at 1,
so a plain polar (not log-polar) resampling of the Fourier magnitude is enough.

Meaning of the result (pixel coordinates ``q = (row, col)``, BEV centre ``c = ((S-1)/2, (S-1)/2)``,
``R(a) = [[cos a, -sin a], [sin a, cos a]]`` acting on ``(row, col)``)::

    curr(q) = prev(c + R(-angle) (q - c) - shift)

i.e. ``curr`` is ``prev`` first shifted by ``shift = (d_row, d_col)`` pixels and then rotated by
``angle`` about the BEV centre. Positive ``angle`` turns the row axis towards the column axis,
which is counter-clockwise on the displayed BEV (row 0 at the top) and counter-clockwise about
the road's z axis (up). This order is what the pipeline measures: the Fourier magnitude gives
``angle`` regardless of any shift, and ``rotate_about_centre(curr, -angle)`` is exactly ``prev``
shifted by ``shift``. ``bevo_ros.core.motion`` turns it into vehicle motion.

Pipeline (all differentiable, batched, no Python loops over the batch, no ``.item()``):

1. :func:`prepare` (once per frame; each frame is ``curr`` once and ``prev`` once): subtract the
   weighted mean, multiply by a smooth weight = (soft mask edge) x (radial Tukey window). The
   window is radially symmetric, so rotating a weighted image equals weighting the rotated
   one, and tapered, so the BEV's fixed footprint (identical in every frame) has no edge that
   could pull the correlation towards zero motion. Then ``rfft2`` of the image, of the weight,
   and of the zero-padded image, whose compressed magnitude is resampled on a polar grid and
   normalised per radius.
2. :func:`estimate_rotation`: 1-D phase correlation along the angle axis (cross-power spectra
   summed over radii, phase-normalised, Gaussian band weight so the correlation peak is a
   Gaussian of ``rotation_sigma`` bins), softmax with a temperature over ``A`` angle bins.
3. :func:`rotate_about_centre` undoes the rotation of ``curr``; :func:`estimate_translation`
   does a 2-D phase correlation (same kind of band weight), softmax over the ``(S, S)`` shifts.
4. Point estimates: the argmax cell plus a sub-bin / sub-pixel log-parabola fit through the
   peak's neighbours (exact for the Gaussian peak the band weight produces). The translation fit divides out the overlap of the two weights
   first (:func:`overlap_envelope`), which otherwise drags the peak towards zero shift.
   The distributions (log-softmax, for the KL loss) are over the full grids.

Paper vs. this implementation: the paper takes the soft expectation over the whole softmax
distribution. With a sharp temperature that snaps to bin centres; with a soft one the noise
floor of ``S * S`` cells biases it towards the grid centre, so the point estimate here is local.

Rotation ambiguity: the Fourier magnitude of a real image is point symmetric, so only the
angle modulo 180 degrees is observable. We resolve it with the rule that a car turns far less
than 90 degrees between consecutive frames: angles live in ``[-90, 90)`` degrees.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F

from .device import constant_cache
from .dpc_config import DpcConfig

Tensor = torch.Tensor


class InvalidBevError(ValueError):
    """A BEV with no valid pixel (e.g. an attitude that puts the ground patch out of the image):
    bad input for this frame, not a bug (:class:`~bevo_ros.core.odometry.BevoOdometry` counts it
    as a drop)."""


@dataclass
class Prepared:
    """One BEV made ready for correlation (each frame is prepared once, used twice).

    Attributes:
        image: ``(B, S, S)`` weighted, zero-mean BEV.
        spectrum: ``(B, S, S // 2 + 1)`` complex ``rfft2(image)``.
        polar: ``(B, R, A // 2 + 1)`` complex ``rfft`` along the angle of the polar magnitude.
        weight_spectrum: ``(B, S, S // 2 + 1)`` complex ``rfft2`` of the weight (overlap envelope).
    """

    image: Tensor
    spectrum: Tensor
    polar: Tensor
    weight_spectrum: Tensor

    @property
    def size(self) -> int:
        return self.image.shape[-1]

    def __getitem__(self, index) -> "Prepared":
        """Batch slicing, e.g. ``p[:-1]`` / ``p[1:]`` to pair consecutive frames."""
        return Prepared(self.image[index], self.spectrum[index], self.polar[index], self.weight_spectrum[index])


@dataclass
class Registration:
    """Result of :func:`register` (see the module docstring for what angle and shift mean).

    Attributes:
        angle: ``(B,)`` radians in ``[-pi/2, pi/2)``.
        shift: ``(B, 2)`` pixels ``(d_row, d_col)``.
        rotation_log_prob: ``(B, A)`` log-softmax over ``rotation_bins``.
        rotation_bins: ``(A,)`` radians, ``(i - A/2) * pi / A``.
        translation_log_prob: ``(B, S, S)`` log-softmax over ``translation_bins``.
        translation_bins: ``(S, S, 2)`` the ``(d_row, d_col)`` of each cell, ``i - S // 2``.
        rotation_corr, translation_corr: the raw correlations (1 = perfect match).
        quality: ``(B,)`` translation peak height in [0, 1] (the normalised phase coherence).
        rotation_quality: ``(B,)`` rotation peak height in [0, 1].
        angle_std: ``(B,)`` radians, spread of the rotation distribution about ``angle``.
        shift_cov: ``(B, 2, 2)`` pixels^2, spread of the translation distribution about ``shift``.
    """

    angle: Tensor
    shift: Tensor
    rotation_log_prob: Tensor
    rotation_bins: Tensor
    translation_log_prob: Tensor
    translation_bins: Tensor
    rotation_corr: Tensor
    translation_corr: Tensor
    quality: Tensor
    rotation_quality: Tensor
    angle_std: Tensor
    shift_cov: Tensor
    rotation_estimate: Tensor | None = None  # (B,) the images' own rotation when ``angle`` was given
    rotation_estimate_std: Tensor | None = None  # (B,) its spread
    shift_gated: Tensor | None = None  # (B,) bool: the shift is the peak nearest the prior or in the direction, not the highest

    @property
    def rotation_prob(self) -> Tensor:
        """``(B, A)``."""
        return self.rotation_log_prob.exp()

    @property
    def translation_prob(self) -> Tensor:
        """``(B, S, S)``."""
        return self.translation_log_prob.exp()


# ------------------------------------------------------------------------------------------------
# Cached grids (depend only on size, config, device, dtype)
# ------------------------------------------------------------------------------------------------
@constant_cache(32)
def _radial_window(size: int, alpha: float, dtype: torch.dtype, device: torch.device) -> Tensor:
    """Radial Tukey window ``(S, S)``: 1 inside ``(1 - alpha) S/2``, cosine taper to 0 at ``S/2``."""
    c = (size - 1) / 2.0
    i = torch.arange(size, dtype=torch.float64) - c
    r = torch.sqrt(i[:, None] ** 2 + i[None, :] ** 2) / (size / 2.0)
    r0 = 1.0 - alpha
    t = ((r - r0) / alpha).clamp(0.0, 1.0)
    w = 0.5 * (1.0 + torch.cos(math.pi * t))
    return w.to(dtype=dtype, device=device)


@constant_cache(32)
def _polar_sampler(size: int, angle_bins: int, radial_range: tuple[float, float], radial_samples: int,
                   device: torch.device) -> tuple[Tensor, Tensor]:
    """Bilinear polar resampling of an ``rfft2`` magnitude (``S x (S // 2 + 1)``) as 4 gathers.

    Angles ``phi_j = j pi / A`` (``j < A``), measured from the row-frequency axis towards the
    column-frequency axis, so the column frequency ``r sin(phi) >= 0``: exactly the half plane
    ``rfft2`` keeps. Radii evenly spaced in ``radial_range`` (cycles/pixel).

    Returns:
        index ``(4 * R * A,)`` into the flattened ``S * (S // 2 + 1)`` spectrum and weights
        ``(4, R * A)`` (float64; cast by the caller).
    """
    S = size
    W = S // 2 + 1
    lo, hi = radial_range
    radii = torch.linspace(lo * S, hi * S, radial_samples, dtype=torch.float64)  # frequency bins
    phi = torch.arange(angle_bins, dtype=torch.float64) * math.pi / angle_bins
    kr = radii[:, None] * torch.cos(phi)[None, :]  # (R, A)
    kc = radii[:, None] * torch.sin(phi)[None, :]
    r0, c0 = torch.floor(kr), torch.floor(kc)
    fr, fc = kr - r0, kc - c0
    r0, c0 = r0.long(), c0.long()
    idx, wts = [], []
    for dr, dc, w in ((0, 0, (1 - fr) * (1 - fc)), (1, 0, fr * (1 - fc)), (0, 1, (1 - fr) * fc), (1, 1, fr * fc)):
        idx.append(((r0 + dr) % S) * W + (c0 + dc))  # 0 <= c0 + dc <= hi * S + 1 < W
        wts.append(w)
    return torch.stack(idx).reshape(-1).to(device), torch.stack(wts).reshape(4, -1).to(device)


@constant_cache(32)
def _polar_weights(size: int, angle_bins: int, radial_range: tuple[float, float], radial_samples: int,
                   dtype: torch.dtype, device: torch.device) -> tuple[Tensor, Tensor]:
    """:func:`_polar_sampler` with the weights in ``dtype``."""
    idx, w = _polar_sampler(size, angle_bins, radial_range, radial_samples, device)
    return idx, w.to(dtype)


@constant_cache(32)
def _rotation_band(angle_bins: int, sigma: float, lowcut: float, dtype: torch.dtype,
                   device: torch.device) -> tuple[Tensor, float]:
    """Weights ``(A // 2 + 1,)`` on the angular frequencies and the normaliser of ``irfft``.

    The Gaussian makes the correlation peak a Gaussian of ``sigma`` bins; the low-cut removes
    the slowly varying (in angle) common anisotropy of both spectra.
    """
    m = torch.arange(angle_bins // 2 + 1, dtype=torch.float64)
    g = torch.exp(-2.0 * (math.pi * sigma * m / angle_bins) ** 2)
    if lowcut > 0:
        g = g * (1.0 - torch.exp(-0.5 * (m / lowcut) ** 2))
    # irfft sums m and -m (except 0 and A/2): the peak of a perfect match is this / A.
    total = g[0] + 2.0 * g[1:-1].sum() + g[-1]
    return g.to(dtype=dtype, device=device), float(total) / angle_bins


@constant_cache(32)
def _translation_band(size: int, sigma: float, lowcut: float, dtype: torch.dtype,
                      device: torch.device) -> tuple[Tensor, Tensor]:
    """Weights ``(S, S // 2 + 1)`` on the ``rfft2`` frequencies, and the multiplicity of each
    column in the full spectrum (1 for the DC and Nyquist columns, 2 otherwise)."""
    kr = torch.fft.fftfreq(size, dtype=torch.float64)  # cycles per pixel
    kc = torch.fft.rfftfreq(size, dtype=torch.float64)
    k2 = kr[:, None] ** 2 + kc[None, :] ** 2
    g = torch.exp(-2.0 * math.pi**2 * sigma**2 * k2)
    if lowcut > 0:
        g = g * (1.0 - torch.exp(-0.5 * k2 / lowcut**2))
    mult = torch.full((kc.numel(),), 2.0, dtype=torch.float64)
    mult[0] = 1.0
    if size % 2 == 0:
        mult[-1] = 1.0
    return g.to(dtype=dtype, device=device), mult.to(dtype=dtype, device=device)


@constant_cache(32)
def _normalised_axis(size: int, dtype: torch.dtype, device: torch.device) -> Tensor:
    """Pixel centres in ``grid_sample(align_corners=False)`` units, ``(S,)``: ``(2 i + 1) / S - 1``."""
    return ((2.0 * torch.arange(size, dtype=torch.float64) + 1.0) / size - 1.0).to(dtype=dtype, device=device)


@constant_cache(32)
def _normalised_axes(size: int, dtype: torch.dtype, device: torch.device) -> tuple[Tensor, Tensor]:
    """:func:`_normalised_axis` as a column axis ``(1, 1, S)`` and a row axis ``(1, S, 1)``."""
    lin = _normalised_axis(size, dtype, device)
    return lin[None, None, :], lin[None, :, None]


@constant_cache(32)
def _angle_bins(A: int, dtype: torch.dtype, device: torch.device) -> Tensor:
    return (torch.arange(A, dtype=torch.float64) - A // 2).mul(math.pi / A).to(dtype=dtype, device=device)


@constant_cache(32)
def _shift_bins(size: int, dtype: torch.dtype, device: torch.device) -> Tensor:
    i = torch.arange(size, dtype=dtype, device=device) - size // 2
    rr, cc = torch.meshgrid(i, i, indexing="ij")
    return torch.stack([rr, cc], dim=-1)


@constant_cache(32)
def _shift_axis(size: int, dtype: torch.dtype, device: torch.device) -> Tensor:
    """``(1, S)`` the row (= column) offsets of :func:`shift_bins`, ``i - S // 2``."""
    return (torch.arange(size, dtype=dtype, device=device) - size // 2)[None, :]


def angle_bins(config: DpcConfig, dtype: torch.dtype = torch.float32, device=None) -> Tensor:
    """``(A,)`` bin centres in radians, ``[-pi/2, pi/2)``: ``(i - A/2) pi / A``. Do not modify in place."""
    return _angle_bins(config.angle_bins, dtype, torch.device(device or "cpu"))


def shift_bins(size: int, dtype: torch.dtype = torch.float32, device=None) -> Tensor:
    """``(S, S, 2)`` the ``(d_row, d_col)`` of each cell of the (fftshifted) translation grid,
    ``i - S // 2``. Do not modify in place."""
    return _shift_bins(size, dtype, torch.device(device or "cpu"))


# ------------------------------------------------------------------------------------------------
# Building blocks
# ------------------------------------------------------------------------------------------------
def _check_pair(bev: Tensor, mask: Tensor) -> None:
    if bev.ndim != 4 or bev.shape[1] != 1 or bev.shape[-1] != bev.shape[-2]:
        raise ValueError(f"bev must be (B, 1, S, S), got {tuple(bev.shape)}")
    if mask.shape != bev.shape:
        raise ValueError(f"mask must have the bev's shape {tuple(bev.shape)}, got {tuple(mask.shape)}")
    if not bev.is_floating_point():
        raise ValueError(f"bev must be floating point, got {bev.dtype}")


def _box_blur(x: Tensor, width: int) -> Tensor:
    """Mean over a ``width x width`` box, replicate padding (the BEV's outer border is not an
    invalid region). ``(B, 1, H, W)`` -> same. A sum of shifted slices per axis: equal to
    ``avg_pool2d`` but ~3x faster on CPU, and unlike ``conv2d`` the same for any batch size (the
    engine's one frame at a time and the batched training path must agree)."""
    p = width // 2
    H, W = x.shape[-2:]
    x = F.pad(x, (p, p, p, p), mode="replicate")
    rows = x[..., 0:H, :]
    for k in range(1, width):
        rows = rows + x[..., k : k + H, :]
    out = rows[..., 0:W]
    for k in range(1, width):
        out = out + rows[..., k : k + W]
    return out / (width * width)


def soft_weight(mask: Tensor, config: DpcConfig) -> Tensor:
    """Smooth weight ``(B, S, S)`` = (soft mask edge) x radial window. ``mask (B, 1, S, S)``.

    The soft edge is ``smoothstep(2 * blur(mask) - 1)``: 0 on and outside the mask's border
    (blur = 1/2 there), 1 well inside; cheaper than an erosion and C1-smooth.
    """
    m = mask.to(dtype=mask.dtype if mask.is_floating_point() else torch.float32)
    if config.mask_blur > 0:
        # Two box filters of width w have variance (w^2 - 1) / 6: a cheap near-Gaussian blur.
        w = max(3, 2 * round((math.sqrt(6.0 * config.mask_blur**2 + 1.0) - 1.0) / 2.0) + 1)
        b = _box_blur(_box_blur(m, w), w)
        t = (2.0 * b - 1.0).clamp(0.0, 1.0)
        m = t * t * (3.0 - 2.0 * t) * m
    S = mask.shape[-1]
    return m[:, 0] * _radial_window(S, config.window_alpha, m.dtype, m.device)


def _magnitude(z: Tensor) -> Tensor:
    """``|z|`` of a complex tensor, ~2.5x faster than ``z.abs()`` on CPU. Exactly 0 at 0 (a uniform
    BEV must stay "no information", not become a perfect match of rounding noise) with a zero,
    not NaN, gradient there (the DC term of a zero-mean image is 0): the double ``where``."""
    sq = z.real.square() + z.imag.square()
    if not (z.requires_grad and torch.is_grad_enabled()):
        return sq.sqrt_()  # the same values (sqrt(0) = 0); the wheres only guard the gradient
    nonzero = sq > 0
    return torch.where(nonzero, torch.where(nonzero, sq, torch.ones_like(sq)).sqrt(), torch.zeros_like(sq))


def _polar_spectrum(spectrum: Tensor, config: DpcConfig) -> Tensor:
    """Compressed magnitude in polar coordinates, zero mean and unit RMS per radius. -> ``(B, R, A)``."""
    B, S, W = spectrum.shape  # S here is the padded size; rfft2 layout
    mag = _magnitude(spectrum).reshape(B, S * W)
    idx, w = _polar_weights(S, config.angle_bins, config.radial_range, config.radial_samples, mag.dtype,
                            spectrum.device)
    if mag.requires_grad and torch.is_grad_enabled():
        mag = mag / (mag.mean(dim=1, keepdim=True) + 1e-12)  # brightness/contrast invariant
        polar = (torch.log1p(mag).index_select(1, idx).reshape(B, 4, -1) * w).sum(dim=1)
    else:  # the same operations in place (the engine: no gradient, fewer large temporaries)
        mag = mag.div_(mag.mean(dim=1, keepdim=True) + 1e-12).log1p_()
        polar = mag.index_select(1, idx).reshape(B, 4, -1).mul_(w).sum(dim=1)
    polar = polar.reshape(B, config.radial_samples, config.angle_bins)
    polar = polar - polar.mean(dim=-1, keepdim=True)
    return polar / (polar.pow(2).mean(dim=-1, keepdim=True).sqrt() + 1e-12)


@dataclass
class MaskWeight:
    """What :func:`prepare` derives from the mask alone (:func:`mask_weight`): a caller whose mask
    repeats (the engine: the BEV footprint rarely changes between frames) passes it back instead
    of recomputing it.

    Attributes:
        mask: ``(B, 1, S, S)`` the mask it was computed from.
        weight: ``(B, S, S)`` :func:`soft_weight` of the mask.
        total: ``(B, 1, 1)`` its sum.
        spectrum: ``(B, S, S // 2 + 1)`` complex ``rfft2(weight)``.
    """

    mask: Tensor
    weight: Tensor
    total: Tensor
    spectrum: Tensor


def mask_weight(mask: Tensor, config: DpcConfig, dtype: torch.dtype | None = None) -> MaskWeight:
    """:class:`MaskWeight` of ``mask (B, 1, S, S)`` in ``dtype`` (default: the mask's).

    Raises InvalidBevError when a BEV has no valid pixel after eroding its mask."""
    w = soft_weight(mask.to(dtype or mask.dtype), config)
    wsum = w.sum(dim=(-1, -2), keepdim=True)
    if bool((wsum <= 1e-6).any()):
        raise InvalidBevError("a BEV has no valid pixels after eroding its mask (camera model or BEV spec wrong?)")
    return MaskWeight(mask, w, wsum, torch.fft.rfft2(w))


def prepare(bev: Tensor, mask: Tensor, config: DpcConfig, weight: MaskWeight | None = None) -> Prepared:
    """Weight one batch of BEVs and compute the spectra both correlation stages need.

    Args:
        bev: ``(B, 1, S, S)`` float.
        mask: ``(B, 1, S, S)`` validity (1 valid, 0 not), same dtype family.
        weight: ``mask_weight(mask, config, bev.dtype)`` if the caller has it (not checked).

    Returns:
        :class:`Prepared`.
    """
    _check_pair(bev, mask)
    if weight is None:
        weight = mask_weight(mask, config, bev.dtype)
    w, wsum = weight.weight, weight.total
    x = bev[:, 0]
    mean = (w * x).sum(dim=(-1, -2), keepdim=True) / wsum
    image = w * (x - mean)
    spectrum = torch.fft.rfft2(image)
    p = config.rotation_padding
    padded = spectrum if p == 1 else torch.fft.rfft2(image, s=(p * image.shape[-2], p * image.shape[-1]))
    polar = torch.fft.rfft(_polar_spectrum(padded, config), dim=-1)
    return Prepared(image, spectrum, polar, weight.spectrum)


def rotate_about_centre(image: Tensor, angle: Tensor) -> Tensor:
    """Rotate images about their centre. ``image (B, C, S, S)``, ``angle (B,)`` -> ``(B, C, S, S)``.

    ``out(q) = image(c + R(-angle) (q - c))``: the content turns by ``+angle`` from the row axis
    towards the column axis (counter-clockwise on screen). Bilinear, zeros outside.
    """
    if image.ndim != 4 or angle.ndim != 1 or angle.shape[0] != image.shape[0]:
        raise ValueError(f"need image (B, C, H, W) and angle (B,), got {tuple(image.shape)} and {tuple(angle.shape)}")
    H, W = image.shape[-2:]
    if H != W:
        raise ValueError(f"image must be square, got {H}x{W}")
    # In grid_sample's normalised (x = col, y = row) coordinates the centre is 0 and both axes
    # share one scale (square image), so R(-angle) on (row, col) is [[c, -s], [s, c]] on (x, y):
    # an outer sum of two axes, built on planar (B, S, S) tensors (cheaper than affine_grid's matmul).
    x, y = _normalised_axes(H, image.dtype, image.device)  # (1, 1, S), (1, S, 1)
    a = angle.to(image.dtype)[:, None, None]
    c, s = torch.cos(a), torch.sin(a)
    grid = torch.stack([c * x - s * y, s * x + c * y], dim=-1)  # (B, S, S, 2)
    return F.grid_sample(image, grid, mode="bilinear", padding_mode="zeros", align_corners=False)


def _gaussian_offset(cm: Tensor, c0: Tensor, cp: Tensor) -> Tensor:
    """Sub-bin peak offset from three samples of a Gaussian-shaped peak (log-parabola vertex)."""
    floor = 1e-6 * c0.abs().clamp_min(1e-12)
    lm, l0, lp = (torch.log(torch.maximum(v, floor)) for v in (cm, c0, cp))
    den = lm - 2.0 * l0 + lp
    den = torch.where(den < -1e-9, den, torch.full_like(den, -1e-9))
    return (0.5 * (lm - lp) / den).clamp(-0.5, 0.5)


def _whitening_gain(mag: Tensor, floor: float, dims: tuple[int, ...]) -> Tensor:
    """Real gain ``1 / (|C| + floor * mean|C|)`` of the phase normalisation (pure phase for
    ``floor = 0``) from ``mag = |C|``; the whitened spectrum is ``C * gain``."""
    if floor > 0:
        return 1.0 / (mag + floor * mag.mean(dim=dims, keepdim=True) + 1e-12)
    return 1.0 / (mag + 1e-12)


def estimate_rotation(prev: Prepared, curr: Prepared, config: DpcConfig) -> tuple[Tensor, Tensor, Tensor]:
    """Rotation of ``curr`` relative to ``prev`` from the polar Fourier magnitudes.

    Returns:
        angle ``(B,)`` radians in ``[-pi/2, pi/2)``, correlation ``(B, A)`` over
        :func:`angle_bins` (1 = perfect match), log-probabilities ``(B, A)``.
    """
    A = config.angle_bins
    cross = (curr.polar * prev.polar.conj()).sum(dim=1)  # (B, A//2+1): pooled over radii
    band, norm = _rotation_band(A, config.rotation_sigma, config.rotation_lowcut, prev.image.dtype, prev.image.device)
    cross = cross * (band / (_magnitude(cross) + 1e-12))
    corr = torch.fft.irfft(cross, n=A, dim=-1) / norm  # index j <-> angle j pi / A
    corr = torch.roll(corr, A // 2, dims=-1)  # index i <-> (i - A/2) pi / A
    log_prob = F.log_softmax(corr / config.rotation_temperature, dim=-1)
    j = corr.argmax(dim=-1)
    cm, c0, cp = corr.gather(-1, (j[:, None] + _offsets(1, None, corr.device)) % A).unbind(-1)
    offset = _gaussian_offset(cm, c0, cp)
    angle = (j.to(corr.dtype) + offset - A // 2) * (math.pi / A)
    angle = torch.remainder(angle + math.pi / 2, math.pi) - math.pi / 2
    return angle, corr, log_prob


def overlap_envelope(prev_weight_spectrum: Tensor, curr_weight_spectrum: Tensor) -> Tensor:
    """Overlap of the two weights as a function of the shift, 1 at zero shift. -> ``(B, S, S)``
    over :func:`shift_bins` (fftshifted).

    The correlation of two weighted images is (correlation of the contents) x (correlation of
    the weights); the latter falls off with the shift and drags a sub-pixel peak towards zero.
    """
    S = curr_weight_spectrum.shape[-2]
    e = torch.fft.irfft2(curr_weight_spectrum * prev_weight_spectrum.conj(), s=(S, S))
    e = e / e[:, :1, :1].clamp_min(1e-12)
    return torch.fft.fftshift(e, dim=(-2, -1))


def translation_correlation(prev_spectrum: Tensor, curr_image: Tensor, config: DpcConfig) -> Tensor:
    """Whitened, band-passed cross-correlation over :func:`shift_bins` (fftshifted), 1 = perfect
    match. ``prev_spectrum (B, S, S // 2 + 1)`` complex ``rfft2``, ``curr_image (B, S, S)`` ->
    ``(B, S, S)``."""
    S = curr_image.shape[-1]
    cross = torch.fft.rfft2(curr_image) * prev_spectrum.conj()
    band, mult = _translation_band(S, config.translation_sigma, config.translation_lowcut, curr_image.dtype,
                                   curr_image.device)
    mag = _magnitude(cross)
    gain = _whitening_gain(mag, config.whitening_floor, dims=(-2, -1)) * band
    # Normalise so that a perfect match peaks at exactly 1 whatever the whitening (sum over the
    # full spectrum = half plane with the mirrored columns counted twice).
    norm = ((mag * gain * mult).sum(dim=(-2, -1)) / S**2)[:, None, None].clamp_min(1e-12)
    if cross.requires_grad and torch.is_grad_enabled():
        corr = torch.fft.irfft2(cross * gain, s=(S, S)) / norm  # index n <-> shift n (mod S)
    else:  # the same operations in place (the engine)
        corr = torch.fft.irfft2(cross.mul_(gain), s=(S, S)).div_(norm)
    return torch.fft.fftshift(corr, dim=(-2, -1))  # index i <-> shift i - S//2


def estimate_translation(prev_spectrum: Tensor, curr_image: Tensor, config: DpcConfig,
                         envelope: Tensor | None = None, prior: Tensor | None = None,
                         prior_std: Tensor | None = None,
                         peak_ratio: float = 0.5,
                         forward_range: Tensor | None = None) -> tuple[Tensor, Tensor, Tensor, Tensor | None]:
    """Shift of ``curr_image`` relative to the image whose ``rfft2`` is ``prev_spectrum``.

    ``curr(q) = prev(q - shift)``.

    Args:
        prev_spectrum: ``(B, S, S // 2 + 1)`` complex ``rfft2``.
        curr_image: ``(B, S, S)`` weighted image (already rotated back).
        envelope: optional :func:`overlap_envelope`; the sub-pixel fit then uses the correlation
            divided by it (the distribution is left as is: dividing amplifies far-off noise).
        prior, prior_std: optional ``(B, 2)`` pixels: where the shift is expected (e.g. a motion
            filter's prediction) and its standard deviation. A peak near the prior (at least
            ``peak_ratio`` x the highest, :func:`_nearest_strong_peak`) is taken over a highest one
            farther from it: a second motion in the view (the car ahead, its shadow) can outweigh
            the road's. Without a prior, or with no such peak, the highest.
        forward_range: optional ``(B, 2)`` px: the peak is taken among shifts whose row (forward)
            offset lies in ``[lo, hi]`` (``inf`` for none): the direction of travel (a car does
            not reverse without stopping; the car ahead pulling away reads as reversing), or the
            least motion the images' flow says (a car ahead moving with ours reads as a stop).

    Returns:
        shift ``(B, 2)`` pixels ``(d_row, d_col)``, correlation ``(B, S, S)`` over
        :func:`shift_bins` (fftshifted, 1 = perfect match), log-probabilities ``(B, S, S)``, and
        with a prior or a range ``(B,)`` bool: a peak other than the highest was taken, else None.
    """
    B, S, _ = curr_image.shape
    corr = translation_correlation(prev_spectrum, curr_image, config)
    flat = corr.reshape(B, S * S)
    log_prob = F.log_softmax(flat / config.translation_temperature, dim=-1).reshape(B, S, S)
    j = flat.argmax(dim=-1)
    gated = None
    if forward_range is not None:
        j, gated = _peak_in_range(corr, j, forward_range)
    jr, jc = j // S, j % S
    if prior is not None:
        jr, jc, near = _nearest_strong_peak(corr, jr, jc, prior, prior_std, peak_ratio, forward_range)
        gated = near if gated is None else gated | near
    index = _window_index(jr, jc, S, 1)
    win, _ = _window_2d(corr, jr, jc, 1, index)
    if envelope is not None:  # only the fit's 3x3 window is divided (the rest is never used)
        win = win / _window_2d(envelope, jr, jc, 1, index)[0].clamp_min(0.05)
    off, _ = _quadratic_peak_window(win, with_height=False)
    shift = torch.stack([jr, jc], dim=-1).to(corr.dtype) - S // 2 + off
    return shift, corr, log_prob, gated


@torch.compiler.disable  # decided on Python numbers: traced, each new range would be a recompilation
def _peak_in_range(corr: Tensor, j: Tensor, forward_range: Tensor) -> tuple[Tensor, Tensor]:
    """The flat index ``j (B,)`` of the highest cell if its row offset lies in ``forward_range
    (B, 2)``, else that of the highest peak (a 3x3 local maximum, cyclic) whose row does. -> ``(j,
    moved (B,) bool)``. Not merely the highest allowed cell: at the range's edge that is the flank
    of a peak outside it, and the sub-pixel fit would slide out to that peak. Python numbers per
    batch entry: in the common case (the highest is allowed) no tensor work at all."""
    B, S, _ = corr.shape
    out, moved = j.tolist(), [False] * B
    for b, (lo, hi) in enumerate(forward_range.tolist()):
        if lo <= out[b] // S - S // 2 <= hi:
            continue
        c = corr[b:b + 1]
        peaks = c >= F.max_pool2d(F.pad(c[:, None], (1, 1, 1, 1), mode="circular"), 3, 1)[:, 0]
        rows = _shift_axis(S, corr.dtype, corr.device)[0]
        wrong = (rows < lo) | (rows > hi)
        allowed = c.masked_fill(wrong[None, :, None] | ~peaks, float("-inf")).reshape(-1)
        k = int(allowed.argmax())
        if math.isfinite(float(allowed[k])):  # an allowed peak exists (else the highest stays)
            out[b], moved[b] = k, True
    return torch.tensor(out, dtype=j.dtype, device=j.device), torch.tensor(moved, device=j.device)


@torch.compiler.disable  # decided on Python numbers: traced, each new prior would be a recompilation
def _nearest_strong_peak(corr: Tensor, jr: Tensor, jc: Tensor, prior: Tensor, prior_std: Tensor,
                         ratio: float, forward_range: Tensor | None = None,
                         reach: int = 4) -> tuple[Tensor, Tensor, Tensor]:
    """The highest cell ``(jr, jc)``, or the highest within ``reach`` px of the prior where that is
    a peak (a 3x3 local maximum, cyclic) at least ``ratio`` x the highest and nearer the prior (in
    its standard deviations), and with its row offset in ``forward_range`` (if given).

    -> ``(jr, jc, gated)``, ``gated (B,)`` bool: the peak near the prior was taken. A few cells per
    batch entry, decided on Python numbers (the engine's batch of one: tensor ops would cost more)."""
    B, S, _ = corr.shape
    c = S // 2
    out_r, out_c, gated = jr.tolist(), jc.tolist(), [False] * B
    bounds = [(-math.inf, math.inf)] * B if forward_range is None else forward_range.tolist()
    for b, ((p_r, p_c), (s_r, s_c)) in enumerate(zip(prior.tolist(), prior_std.tolist())):
        r0, c0 = round(p_r) + c, round(p_c) + c
        near, _ = _window_2d(corr[b:b + 1], torch.tensor([r0], device=corr.device),
                             torch.tensor([c0], device=corr.device), reach)
        lo, hi = bounds[b]
        if not (lo <= r0 - c - reach and r0 - c + reach <= hi and 0 <= r0 - reach and r0 + reach < S):
            # the window reaches out of the range (or wraps round the grid): the rows' offsets, cyclic
            offsets = torch.remainder(_offsets(reach, corr.dtype, corr.device) + r0, S) - c
            near = near.masked_fill(((offsets < lo) | (offsets > hi))[None, :, None], float("-inf"))
        k = int(near.argmax())
        kr, kc = (r0 + k // (2 * reach + 1) - reach) % S, (c0 + k % (2 * reach + 1) - reach) % S
        if (kr, kc) == (out_r[b], out_c[b]) or not math.isfinite(float(near.reshape(-1)[k])):
            continue
        around, _ = _window_2d(corr[b:b + 1], torch.tensor([kr], device=corr.device),
                               torch.tensor([kc], device=corr.device), 1)
        peak, top = float(around[0, 1, 1]), float(corr[b, out_r[b], out_c[b]])
        s_r, s_c = max(s_r, 1e-6), max(s_c, 1e-6)

        def dist(r: int, q: int) -> float:
            return ((r - c - p_r) / s_r) ** 2 + ((q - c - p_c) / s_c) ** 2

        if peak >= float(around.max()) and peak >= ratio * top and dist(kr, kc) < dist(out_r[b], out_c[b]):
            out_r[b], out_c[b], gated[b] = kr, kc, True
    dev = jr.device
    return (torch.tensor(out_r, dtype=jr.dtype, device=dev), torch.tensor(out_c, dtype=jc.dtype, device=dev),
            torch.tensor(gated, device=dev))


@constant_cache(32)
def _offsets(h: int, dtype: torch.dtype | None, device: torch.device) -> Tensor:
    """``(2h+1,)`` the window offsets ``-h .. h`` (int64 for ``dtype`` None)."""
    return torch.arange(-h, h + 1, device=device).to(dtype or torch.int64)


def _window_index(jr: Tensor, jc: Tensor, size: int, h: int) -> Tensor:
    """Flat indices ``(B, (2h+1)^2)`` into ``(B, S * S)`` of the circular window around ``(jr, jc)``."""
    d = _offsets(h, None, jr.device)
    rows = (jr[:, None] + d) % size  # (B, n)
    cols = (jc[:, None] + d) % size
    return (rows[:, :, None] * size + cols[:, None, :]).reshape(jr.shape[0], -1)


def _window_2d(corr: Tensor, jr: Tensor, jc: Tensor, h: int, index: Tensor | None = None) -> tuple[Tensor, Tensor]:
    """Circular ``(2h+1)^2`` window around ``(jr, jc)``. -> values ``(B, 2h+1, 2h+1)``, offsets.
    ``index``: :func:`_window_index` if the caller has it."""
    B, S, _ = corr.shape
    n = 2 * h + 1
    index = _window_index(jr, jc, S, h) if index is None else index
    return corr.reshape(B, S * S).gather(1, index).reshape(B, n, n), _offsets(h, corr.dtype, corr.device)


@constant_cache(8)
def _quadratic_fit_3x3(dtype: torch.dtype, device: torch.device) -> Tensor:
    """``(9, 6)`` least-squares fit of ``a + b r + c k + d (r^2 - 2/3) + e (k^2 - 2/3) + f r k`` to
    the 3x3 stencil ``r, k in {-1, 0, 1}`` (closed form: the basis is orthogonal there)."""
    d = torch.tensor([-1.0, 0.0, 1.0], dtype=torch.float64)
    r, k = d[:, None].expand(3, 3).reshape(9), d[None, :].expand(3, 3).reshape(9)
    basis = torch.stack([torch.ones(9, dtype=torch.float64), r, k, r**2 - 2 / 3, k**2 - 2 / 3, r * k], dim=1)
    return (basis / (basis**2).sum(dim=0)).to(dtype=dtype, device=device)


def _quadratic_peak_2d(corr: Tensor, jr: Tensor, jc: Tensor) -> tuple[Tensor, Tensor]:
    """Vertex of a least-squares 2-D quadratic fit to ``log corr`` on the 3x3 around the peak.

    Exact for (possibly elongated, tilted) Gaussian peaks.

    Returns:
        offsets ``(B, 2)`` in [-1, 1] and the fitted log peak height ``(B,)``.
    """
    return _quadratic_peak_window(_window_2d(corr, jr, jc, 1)[0])


def _quadratic_peak_window(win: Tensor, with_height: bool = True) -> tuple[Tensor, Tensor | None]:
    """:func:`_quadratic_peak_2d` on the peak's 3x3 window ``(B, 3, 3)`` (the height None
    without ``with_height``)."""
    B = win.shape[0]
    peak = win[:, 1, 1].abs().clamp_min(1e-12)
    L = torch.log(torch.clamp(win.reshape(B, 9) / peak[:, None], min=1e-6))
    # Elementwise, not a matmul: BLAS sums in a batch-size dependent order (online == batched).
    coef = (L[:, :, None] * _quadratic_fit_3x3(L.dtype, L.device)).sum(dim=1)
    a0, b, c, dd, ee, ff = coef.unbind(-1)
    # Vertex: [2d f; f 2e] [r; k] = -[b; c]; the Hessian must be negative definite. Row and
    # column together as (B, 2) pairs: (b, c), (c, b), (h11, h22), (h22, h11).
    bc = coef[:, 1:3]
    h = (2.0 * coef[:, 3:5]).clamp_max(-1e-6)
    det = h[:, 0] * h[:, 1] - ff**2
    ok = det > 1e-9
    det = torch.where(ok, det, torch.ones_like(det))
    offset = torch.where(ok[:, None], (bc.flip(-1) * ff[:, None] - bc * h.flip(-1)) / det[:, None],
                         -bc / h).clamp(-1.0, 1.0)
    if not with_height:
        return offset, None
    orow, ocol = offset.unbind(-1)
    log_height = (a0 + b * orow + c * ocol + dd * (orow**2 - 2.0 / 3.0) + ee * (ocol**2 - 2.0 / 3.0)
                  + ff * orow * ocol + torch.log(peak))
    return torch.stack([orow, ocol], dim=-1), log_height


def _wrapped_spread(log_prob_a: Tensor, bins_a: Tensor, angle: Tensor) -> Tensor:
    diff = torch.remainder(bins_a[None, :] - angle[:, None] + math.pi / 2, math.pi) - math.pi / 2
    return (log_prob_a.exp() * diff**2).sum(dim=-1).sqrt()


def _shift_cov(log_prob_t: Tensor, shift: Tensor) -> Tensor:
    """Second moment ``(B, 2, 2)`` of the translation distribution about ``shift`` (cyclic).

    The grid is separable (row offset by row, column offset by column), so the moments are
    ``dr^T P dr``-type forms of the marginals: no ``(S, S)`` offset tensors."""
    S = log_prob_t.shape[-1]
    p = log_prob_t.exp()  # (B, S, S)
    axis = _shift_axis(S, log_prob_t.dtype, log_prob_t.device)  # the rows' and the columns' bins
    dr = torch.remainder(axis - shift[:, 0, None] + S / 2, S) - S / 2  # (B, S)
    dc = torch.remainder(axis - shift[:, 1, None] + S / 2, S) - S / 2  # (B, S)
    rr = (p.sum(dim=2) * dr**2).sum(dim=1)
    cc = (p.sum(dim=1) * dc**2).sum(dim=1)
    rc = (dr[:, None, :] @ p @ dc[:, :, None])[:, 0, 0]
    return torch.stack([rr, rc, rc, cc], -1).reshape(-1, 2, 2)


def motion_consistency_weight(prev_spectrum: Tensor, curr_image: Tensor, shift: Tensor, block: int = 5,
                              scale: float = 3.0) -> Tensor:
    """Where ``curr_image`` agrees with the previous image moved by ``shift``: 1, falling to 0
    where it does not. ``prev_spectrum (B, S, S // 2 + 1)``, ``curr_image (B, S, S)`` (derotated),
    ``shift (B, 2)`` px -> ``(B, S, S)``.

    The road moves by one shift; a car ahead, its shadow, a passing car move by their own. The
    absolute difference after the move (exact sub-pixel, in the Fourier domain), averaged over
    ``block x block`` px blocks (the last row and column of blocks partial where ``S`` is no multiple
    of ``block``: a 101 px BEV failed here), against ``scale`` x the road's level
    of it (the blocks' mean over the current image's support, then the mean of the blocks below
    twice that: the other motion left out): ``1 / (1 + x^4)`` per block.
    """
    S = curr_image.shape[-1]
    fr, fc = _shift_phase_axes(S, curr_image.dtype, curr_image.device)
    one = torch.ones((), dtype=curr_image.dtype, device=curr_image.device)
    # The shift theorem's phase is separable: exp(-2 pi i fr dr) exp(-2 pi i fc dc).
    phase = (torch.polar(one, (-2.0 * math.pi) * fr * shift[:, None, :1])
             * torch.polar(one, (-2.0 * math.pi) * fc * shift[:, None, 1:]))  # (B, S, S // 2 + 1)
    moved = torch.fft.irfft2(prev_spectrum * phase, s=(S, S))
    # (B, ceil(S / block), ceil(S / block)); a partial block is its own pixels' mean
    r = F.avg_pool2d((curr_image - moved).abs_()[:, None], block, ceil_mode=True)[:, 0]
    support = F.avg_pool2d((curr_image != 0).to(r.dtype)[:, None], block, ceil_mode=True)[:, 0] > 0.5
    level = torch.where(support, r, 0.0).sum(dim=(-2, -1)) / support.sum(dim=(-2, -1)).clamp_min(1)
    low = support & (r < 2.0 * level[:, None, None])
    level = torch.where(low, r, 0.0).sum(dim=(-2, -1)) / low.sum(dim=(-2, -1)).clamp_min(1)
    x = r / (scale * level.clamp_min(1e-12))[:, None, None]
    x = x * x
    w = 1.0 / (1.0 + x * x)
    return w.repeat_interleave(block, dim=-2).repeat_interleave(block, dim=-1)[..., :S, :S]


@constant_cache(8)
def _shift_phase_axes(size: int, dtype: torch.dtype, device: torch.device) -> tuple[Tensor, Tensor]:
    """``(S, 1)`` row and ``(1, S // 2 + 1)`` column frequencies (cycles per pixel) of an ``rfft2``."""
    return (torch.fft.fftfreq(size, dtype=dtype, device=device)[:, None],
            torch.fft.rfftfreq(size, dtype=dtype, device=device)[None, :])


@torch.compiler.disable  # sliced by Python numbers: traced, each new box would be a recompilation
def _gated_shift_cov(log_prob_t: Tensor, shift: Tensor, prior: Tensor, halfwidth: Tensor) -> Tensor:
    """:func:`_shift_cov` of the distribution inside the prior's box (``halfwidth (B, 2)`` px): the
    box's rows and columns sliced per batch entry (the engine's one; a mask over the grid costs more)."""
    B, S, _ = log_prob_t.shape
    c = S // 2
    out = []
    for b, ((p_r, p_c), (h_r, h_c)) in enumerate(zip(prior.tolist(), halfwidth.tolist())):
        r0, r1 = max(0, math.ceil(p_r - h_r) + c), min(S, math.floor(p_r + h_r) + c + 1)
        c0, c1 = max(0, math.ceil(p_c - h_c) + c), min(S, math.floor(p_c + h_c) + c + 1)
        if r1 <= r0 or c1 <= c0:  # the box is off the grid: the whole distribution
            out.append(_shift_cov(log_prob_t[b:b + 1], shift[b:b + 1])[0])
            continue
        win = log_prob_t[b, r0:r1, c0:c1]
        p = torch.softmax(win.reshape(-1), 0).reshape(win.shape)
        axis = _shift_axis(S, log_prob_t.dtype, log_prob_t.device)[0]
        dr, dc = axis[r0:r1] - shift[b, 0], axis[c0:c1] - shift[b, 1]
        rr, cc, rc = (p.sum(dim=1) * dr * dr).sum(), (p.sum(dim=0) * dc * dc).sum(), dr @ p @ dc
        out.append(torch.stack([rr, rc, rc, cc]).reshape(2, 2))
    return torch.stack(out)


def _range_shift_cov(log_prob_t: Tensor, shift: Tensor, forward_range: Tensor) -> Tensor:
    """:func:`_shift_cov` of the distribution inside the allowed rows ``forward_range (B, 2)`` px
    (all columns): the distribution given the range. Where the range excludes a stronger peak and
    the one allowed is the noise's, the spread is wide: such a reading counts for little."""
    half_grid = log_prob_t.shape[-1] / 2
    bounds = forward_range.to(log_prob_t.dtype).clamp(-half_grid, half_grid)
    centre = torch.stack([bounds.mean(dim=1), torch.zeros_like(bounds[:, 0])], dim=1)
    halfwidth = torch.stack([(bounds[:, 1] - bounds[:, 0]) / 2, torch.full_like(bounds[:, 0], half_grid)], dim=1)
    return _gated_shift_cov(log_prob_t, shift, centre, halfwidth)


def register_prepared(prev: Prepared, curr: Prepared, config: DpcConfig, angle: Tensor | None = None,
                      angle_std: Tensor | None = None, envelope: Tensor | None = None,
                      shift_prior: Tensor | None = None, shift_prior_std: Tensor | None = None,
                      peak_ratio: float = 0.5, forward_range: Tensor | None = None) -> Registration:
    """:func:`register` on already prepared BEVs (reuse ``curr`` as the next ``prev``).

    With ``angle (B,)`` (and its ``angle_std``), e.g. the gyro's rotation, the BEV is derotated by
    it instead of by the image estimate, which is still computed (``rotation_estimate``, its
    distribution kept for the loss) but not refined: the gyro measures a car's yaw over a frame
    better than the BEVs do, and a translation correlation of well-derotated images is sharper.
    ``envelope``: ``overlap_envelope(prev.weight_spectrum, curr.weight_spectrum)`` if the caller
    has it (the engine, while the BEV mask does not change; not checked). ``shift_prior``,
    ``shift_prior_std`` ``(B, 2)`` px, ``peak_ratio``: the expected shift; what moves unlike it is
    weighted out of the current BEV (:func:`motion_consistency_weight`), the peak is chosen with it
    (:func:`estimate_translation`), and ``shift_cov`` is the distribution's spread within 3
    standard deviations of it (the distribution given the prior); ``translation_log_prob`` stays
    the whole one. ``forward_range`` ``(B, 2)`` px: the rows the peak is taken in
    (:func:`estimate_translation`); without a prior ``shift_cov`` is the spread within them.
    """
    if prev.image.shape != curr.image.shape:
        raise ValueError(f"prepared BEVs differ in shape: {tuple(prev.image.shape)} vs {tuple(curr.image.shape)}")
    estimate, rcorr, rlog = estimate_rotation(prev, curr, config)
    if envelope is None:
        envelope = overlap_envelope(prev.weight_spectrum, curr.weight_spectrum)
    given = angle is not None
    angle = angle.to(estimate.dtype) if given else estimate
    derotated = rotate_about_centre(curr.image[:, None], -angle)[:, 0]
    weighted = derotated
    if shift_prior is not None:
        # What moves unlike the prior's motion (a car ahead, its shadow) is left out of the current
        # image (the previous one keeps it: no coherent peak of it remains).
        weighted = derotated * motion_consistency_weight(prev.spectrum, derotated, shift_prior)
    shift, tcorr, tlog, gated = estimate_translation(prev.spectrum, weighted, config, envelope, shift_prior,
                                                     shift_prior_std, peak_ratio, forward_range)
    if shift_prior is not None:  # the distribution given the prior (far peaks are the gate's business)
        shift_cov = _gated_shift_cov(tlog, shift, shift_prior, 3.0 * shift_prior_std)
    elif forward_range is not None:  # ... given the range
        shift_cov = _range_shift_cov(tlog, shift, forward_range)
    else:
        shift_cov = _shift_cov(tlog, shift)
    dtype, device = rcorr.dtype, rcorr.device
    abins = angle_bins(config, dtype, device)
    tbins = shift_bins(prev.size, dtype, device)
    spread = _wrapped_spread(rlog, abins, estimate if given else angle)
    return Registration(
        angle=angle,
        shift=shift,
        rotation_log_prob=rlog,
        rotation_bins=abins,
        translation_log_prob=tlog,
        translation_bins=tbins,
        rotation_corr=rcorr,
        translation_corr=tcorr,
        quality=tcorr.amax(dim=(-1, -2)).clamp(0.0, 1.0),
        rotation_quality=rcorr.amax(dim=-1).clamp(0.0, 1.0),
        angle_std=angle_std.to(dtype) if given and angle_std is not None else spread,
        shift_cov=shift_cov,
        rotation_estimate=estimate if given else None,
        rotation_estimate_std=spread if given else None,
        shift_gated=gated,
    )


def register(bev_prev: Tensor, bev_curr: Tensor, mask_prev: Tensor, mask_curr: Tensor,
             config: DpcConfig | None = None) -> Registration:
    """Rotation and translation of ``bev_curr`` relative to ``bev_prev`` (module docstring).

    Args:
        bev_prev, bev_curr: ``(B, 1, S, S)`` float.
        mask_prev, mask_curr: ``(B, 1, S, S)`` validity masks.
        config: :class:`DpcConfig` (defaults if None).
    """
    config = config or DpcConfig()
    if bev_prev.shape != bev_curr.shape:
        raise ValueError(f"bev_prev {tuple(bev_prev.shape)} and bev_curr {tuple(bev_curr.shape)} differ")
    return register_prepared(prepare(bev_prev, mask_prev, config), prepare(bev_curr, mask_curr, config), config)


__all__ = [
    "DpcConfig",
    "InvalidBevError",
    "Prepared",
    "Registration",
    "angle_bins",
    "shift_bins",
    "soft_weight",
    "MaskWeight",
    "mask_weight",
    "prepare",
    "rotate_about_centre",
    "estimate_rotation",
    "estimate_translation",
    "register_prepared",
    "register",
]
