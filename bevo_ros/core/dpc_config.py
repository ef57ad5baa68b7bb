"""Phase-correlation settings (no torch: the settings tree in ``bevo_ros.config`` holds them as
its ``dpc`` section, read from the parameters file like every other setting)."""
from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class DpcConfig:
    """Phase-correlation settings (all hashable so derived grids can be cached).

    Attributes:
        angle_bins: ``A`` bins over 180 degrees for the rotation distribution.
        radial_range: Fourier radii used for rotation, cycles per pixel (excludes the lowest
            frequencies, dominated by shading, and the highest, aliased ones).
        radial_samples: number of radii sampled in ``radial_range``.
        rotation_padding: the rotation stage zero-pads the BEV to ``padding * S`` before its FFT so
            that the magnitude is sampled finely enough for bilinear polar resampling (the
            interpolation error is fixed to the pixel grid and would bias angles towards 0).
        window_alpha: radial Tukey window, fraction of the radius ``S/2`` that is tapered
            (1 = radial Hann).
        mask_blur: Gaussian sigma (pixels) of the mask's soft edge: the weight is
            ``smoothstep(2 * blur(mask) - 1)``, zero on the mask's border and rising to one about
            ``2 * mask_blur`` pixels inside, so invalid pixels never leak in and the fixed footprint
            has no sharp edge.
        rotation_sigma: width (bins) of the Gaussian correlation peak for rotation.
        rotation_lowcut: angular frequencies (cycles per 180 degrees) below ~this are suppressed.
        translation_sigma: width (pixels) of the Gaussian correlation peak for translation.
        translation_lowcut: spatial frequencies (cycles per pixel) below ~this are suppressed.
        rotation_temperature, translation_temperature: softmax temperatures on correlations
            normalised to 1 for a perfect match.
        whitening_floor: the translation's phase normalisation divides the cross-power spectrum by
            ``|C| + floor * mean|C|`` (0 = pure phase correlation); a floor keeps weak, leakage-
            dominated frequencies (smooth textures) from pulling the peak towards zero shift.
    """

    angle_bins: int = 360
    radial_range: tuple[float, float] = (0.05, 0.40)
    radial_samples: int = 36
    rotation_padding: int = 2
    window_alpha: float = 1.0
    mask_blur: float = 2.0
    rotation_sigma: float = 1.5
    rotation_lowcut: float = 0.0
    translation_sigma: float = 1.0
    translation_lowcut: float = 0.0
    rotation_temperature: float = 0.02
    translation_temperature: float = 0.02
    whitening_floor: float = 0.0

    def __post_init__(self) -> None:
        if self.angle_bins < 8 or self.angle_bins % 2:
            raise ValueError(f"angle_bins must be an even number >= 8, got {self.angle_bins}")
        lo, hi = self.radial_range
        if not 0.0 < lo < hi <= 0.5:
            raise ValueError(f"radial_range must satisfy 0 < lo < hi <= 0.5 cycles/pixel, got {self.radial_range}")
        if self.rotation_padding < 1:
            raise ValueError(f"rotation_padding must be >= 1, got {self.rotation_padding}")
        if self.radial_samples < 1:
            raise ValueError(f"radial_samples must be >= 1, got {self.radial_samples}")
        for name in ("rotation_temperature", "translation_temperature", "rotation_sigma", "translation_sigma"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be > 0, got {getattr(self, name)}")
        if not 0.0 < self.window_alpha <= 1.0:
            raise ValueError(f"window_alpha must be in (0, 1], got {self.window_alpha}")
        if self.mask_blur < 0:
            raise ValueError(f"mask_blur must be >= 0, got {self.mask_blur}")
