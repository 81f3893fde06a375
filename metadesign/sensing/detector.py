"""The detector: what the camera does to a rendered frame (hcipy's ``NoisyDetector`` in spirit).

Rendering (:meth:`metadesign.sensing.device.Device.render`, the twins) gives the power on each pixel for a
noise-free exposure; the detector alone adds noise, after rendering, in one unit (each frame's peak):
shot noise (Poisson, ``photons_at_peak`` photo-electrons at the peak) with Gaussian read noise
(electrons), additive Gaussian noise of ``gaussian_sigma`` x peak, and an optional ADC quantisation of
[0, peak].  One kernel per backend: :func:`add_noise` (numpy) and :func:`add_noise_torch` (torch, the
same model; differentiable in the frame for the Gaussian part, as the co-design training needs).
Estimators never see these settings: they receive frames.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..validation import ConfigError, check_int, check_number

__all__ = ["NoiseSpec", "Detector", "add_noise", "add_noise_torch", "photo_electrons", "NOISELESS"]


@dataclass(frozen=True)
class NoiseSpec:
    gaussian_sigma: float = 0.0  # additive Gaussian, sigma as a fraction of each frame's peak (paper: 0-0.1)
    photons_at_peak: float | None = None  # shot noise: Poisson with this many photo-electrons at the peak
    read_noise_e: float = 0.0  # read noise (electrons, Gaussian), needs photons_at_peak
    bit_depth: int | None = None  # ADC quantisation of [0, peak]
    seed: int = 0

    def __post_init__(self) -> None:
        check_number("noise.gaussian_sigma", self.gaussian_sigma, 0, 1)
        if self.photons_at_peak is not None:
            # Poisson sampling needs lam < ~1e18; beyond ~1e15 photo-electrons shot noise is < 3e-8 of the peak
            check_number("noise.photons_at_peak", self.photons_at_peak, 0, 1e15, open_lo=True)
        check_number("noise.read_noise_e", self.read_noise_e, 0, 1e6)
        if self.read_noise_e and not self.photons_at_peak:
            raise ConfigError("noise.read_noise_e", "needs noise.photons_at_peak > 0 (read noise is counted in "
                                                    "photo-electrons)")
        if self.bit_depth is not None:
            check_int("noise.bit_depth", self.bit_depth, 1, 32)
        check_int("noise.seed", self.seed, 0, 2**63 - 1)

    @property
    def active(self) -> bool:
        return bool(self.gaussian_sigma or self.photons_at_peak or self.bit_depth)

    def to_dict(self) -> dict:
        return {"gaussian_percent": self.gaussian_sigma * 100, "photons_at_peak": self.photons_at_peak or 0.0,
                "read_noise_e": self.read_noise_e, "bit_depth": self.bit_depth or 0, "seed": self.seed}


def photo_electrons(mean_e: np.ndarray, read_noise_e: float, rng: np.random.Generator) -> np.ndarray:
    """The detector's one noise kernel: expected photo-electrons per pixel -> detected electrons (float64):
    Poisson shot noise plus Gaussian read noise (electrons).  :func:`add_noise` (sensing, datasets,
    evaluation, estimators) and :func:`metadesign.sensing.camera.expose` (the capture synthesiser's
    counts) both draw through it."""
    e = rng.poisson(mean_e).astype(np.float64)
    if read_noise_e:
        e += rng.normal(0.0, read_noise_e, e.shape)
    return e


def add_noise(frames: np.ndarray, noise: NoiseSpec, rng: np.random.Generator | None = None) -> np.ndarray:
    """Noisy copy of ``frames`` (..., H, W), each frame scaled by its own peak; seeded.

    The one detector model (hcipy's ``NoisyDetector`` in spirit), in one unit, the frame's peak: the
    irradiance is clipped at zero (a detector sees no negative power), then shot + read noise
    (:func:`photo_electrons`), additive Gaussian noise of ``gaussian_sigma`` x peak, and an optional ADC
    quantisation of [0, peak].  Noise may take a pixel below zero; only the ADC clips the result."""
    rng = rng or np.random.default_rng(noise.seed)
    f = np.asarray(frames, np.float64)
    peak = f.max(axis=(-2, -1), keepdims=True)
    peak = np.where(peak > 0, peak, 1.0)
    x = np.clip(f / peak, 0.0, None)
    if noise.photons_at_peak:
        x = photo_electrons(x * noise.photons_at_peak, noise.read_noise_e, rng) / noise.photons_at_peak
    if noise.gaussian_sigma:
        x = x + rng.normal(0.0, noise.gaussian_sigma, x.shape)
    if noise.bit_depth:
        levels = 2**noise.bit_depth - 1
        x = np.round(np.clip(x, 0.0, 1.0) * levels) / levels
    return (x * peak).astype(np.float32)


#: a detector that adds nothing
NOISELESS = NoiseSpec()


@dataclass(frozen=True)
class Detector:
    """The camera's detector: :meth:`read` turns rendered frames (power per pixel) into what the camera
    records.  ``noise``: its :class:`NoiseSpec` (the seed is the default stream's)."""

    noise: NoiseSpec = NOISELESS

    @classmethod
    def gaussian(cls, percent: float, seed: int = 0) -> "Detector":
        """Additive Gaussian noise of ``percent`` % of each frame's peak (the paper's noise levels)."""
        return cls(NoiseSpec(gaussian_sigma=float(percent) / 100.0, seed=int(seed)))

    @property
    def active(self) -> bool:
        return self.noise.active

    def read(self, frames: np.ndarray, rng: np.random.Generator | None = None) -> np.ndarray:
        """numpy: noisy copy of ``frames`` (..., H, W) (the input unchanged when the detector is noiseless)."""
        return add_noise(frames, self.noise, rng) if self.noise.active else frames

    def read_torch(self, frames, generator=None, gaussian_sigma=None):
        """torch: noisy ``frames`` (..., H, W) drawn on ``generator`` (CPU; the same draws on any device).
        ``gaussian_sigma``: a per-sample level (B,) overriding the spec's (a training range)."""
        if not self.noise.active and gaussian_sigma is None:
            return frames
        return add_noise_torch(frames, self.noise, generator, gaussian_sigma)


def add_noise_torch(frames, noise: NoiseSpec, generator=None, gaussian_sigma=None):
    """The torch backend of :func:`add_noise` (same model and unit: each frame's peak).  ``frames``
    (..., H, W) real; ``gaussian_sigma``: None (the spec's level) or a tensor of per-sample levels over the
    leading axis.  The draws are made on the CPU ``generator`` in float32 (Gaussian) and moved to the
    frames' device.  Shot and read noise and the ADC are not differentiable (sampled on detached values);
    the Gaussian part is additive, so gradients pass to the frame."""
    import torch

    x = frames
    peak = x.detach().amax(dim=(-2, -1), keepdim=True)
    peak = torch.where(peak > 0, peak, torch.ones_like(peak))
    if noise.photons_at_peak:
        lam = (torch.clamp(x.detach(), min=0) / peak * noise.photons_at_peak).to("cpu", torch.float64)
        e = torch.poisson(lam, generator=generator)
        if noise.read_noise_e:
            e = e + noise.read_noise_e * torch.randn(e.shape, generator=generator, dtype=torch.float64)
        shot = (e / noise.photons_at_peak).to(device=x.device, dtype=x.dtype) * peak
        x = x + (shot - x.detach())  # the sampled value, the frame's gradient
    sigma = noise.gaussian_sigma if gaussian_sigma is None else gaussian_sigma
    if gaussian_sigma is not None or sigma:
        z = torch.randn(x.shape, generator=generator, dtype=torch.float32).to(x.device)
        if torch.is_tensor(sigma):
            sigma = sigma.to(device=x.device, dtype=x.dtype).reshape(sigma.shape + (1,) * (x.ndim - sigma.ndim))
        x = x + sigma * peak * z
    if noise.bit_depth:
        levels = 2**noise.bit_depth - 1
        q = torch.round(torch.clamp(x.detach() / peak, 0.0, 1.0) * levels) / levels * peak
        x = x + (q - x.detach())
    return x
