"""The sensor: frame geometry, quadrant windows, the 8-channel PSF tensor, noise.

Frame geometry: a ``width x height`` pixel frame (paper: 640 x 512, 15 um)
images the metasurface focal plane through a relay of magnification ``M``
(paper: 10x, no image inversion modelled).  Pixel ``(col, row)`` looks at the
focal-plane point ``X = (col - (width-1)/2) pitch / M``,
``Y = (row - (height-1)/2) pitch / M``: rows run along +y.  The frame splits
into four quadrants in reading order (row 0 drawn at the top): QI = low x /
low y (top-left), QII = high x / low y, QIII = low x / high y, QIV = high x /
high y, which is where design channels k = 1..4 land (their offsets
``((-1)^k dx, -dy for k < 3 else +dy)``).  The PSF tensor stacks the
quadrants as channels ``[x-pol QI..QIV, y-pol QI..QIV]`` = design channels
``(x, k=1..4), (y, k=1..4)``, each resampled to ``out x out`` pixels.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["SensorSpec", "NoiseSpec", "quadrant_slices", "psf_tensor", "add_noise"]


@dataclass(frozen=True)
class SensorSpec:
    width_px: int = 640
    height_px: int = 512
    pixel_pitch: float = 15e-6  # m, on the camera
    magnification: float = 10.0  # relay
    distance: float = 50e-3  # metasurface to focal (sensor-conjugate) plane, m
    tensor_size: int = 256  # network input: 8 x tensor_size x tensor_size

    def __post_init__(self) -> None:
        if self.width_px < 2 or self.height_px < 2 or self.width_px % 2 or self.height_px % 2:
            raise ValueError("sensor width and height must be even numbers of pixels >= 2")
        if self.pixel_pitch <= 0 or self.magnification <= 0 or self.distance <= 0 or self.tensor_size < 2:
            raise ValueError("pixel pitch, magnification, distance and tensor size must be positive")

    @property
    def focal_pitch(self) -> float:
        """Pixel pitch referred to the metasurface focal plane (m)."""
        return self.pixel_pitch / self.magnification

    def coords(self) -> tuple[np.ndarray, np.ndarray]:
        """Focal-plane coordinates of the pixel centres: (X of columns, Y of rows)."""
        p = self.focal_pitch
        return ((np.arange(self.width_px) - (self.width_px - 1) / 2) * p,
                (np.arange(self.height_px) - (self.height_px - 1) / 2) * p)

    def quadrant_centre(self, k: int) -> tuple[float, float]:
        """Focal-plane centre of quadrant k = 1..4 (reading order)."""
        qx = self.width_px // 4 * self.focal_pitch
        qy = self.height_px // 4 * self.focal_pitch
        return ((-qx if k in (1, 3) else qx), (-qy if k in (1, 2) else qy))


def quadrant_slices(sensor: SensorSpec, k: int) -> tuple[slice, slice]:
    """(rows, cols) of quadrant k = 1..4 in the frame."""
    h2, w2 = sensor.height_px // 2, sensor.width_px // 2
    rows = slice(0, h2) if k in (1, 2) else slice(h2, sensor.height_px)
    cols = slice(0, w2) if k in (1, 3) else slice(w2, sensor.width_px)
    return rows, cols


def _resample(img: np.ndarray, size: int) -> np.ndarray:
    """Area-weighted resampling of a 2D image to size x size (bilinear via zoom)."""
    from scipy.ndimage import zoom

    return zoom(img, (size / img.shape[0], size / img.shape[1]), order=1, prefilter=False)


def psf_tensor(frames: np.ndarray, sensor: SensorSpec) -> np.ndarray:
    """``frames`` (2, H, W) = [x-pol, y-pol] -> (8, S, S) float32, each channel one quadrant."""
    out = np.empty((8, sensor.tensor_size, sensor.tensor_size), np.float32)
    for p in range(2):
        for k in range(1, 5):
            r, c = quadrant_slices(sensor, k)
            out[4 * p + k - 1] = _resample(frames[p][r, c], sensor.tensor_size)
    return out


@dataclass(frozen=True)
class NoiseSpec:
    gaussian_sigma: float = 0.0  # additive Gaussian, sigma as a fraction of each frame's peak (paper: 0-0.1)
    photons_at_peak: float | None = None  # shot noise: Poisson with this many photo-electrons at the peak
    read_noise_e: float = 0.0  # read noise (electrons, Gaussian), needs photons_at_peak
    bit_depth: int | None = None  # ADC quantisation of [0, peak]
    seed: int = 0


def add_noise(frames: np.ndarray, noise: NoiseSpec, rng: np.random.Generator | None = None) -> np.ndarray:
    """Noisy copy of ``frames`` (..., H, W), each frame scaled by its own peak; seeded."""
    rng = rng or np.random.default_rng(noise.seed)
    f = np.asarray(frames, np.float64)
    peak = f.max(axis=(-2, -1), keepdims=True)
    peak = np.where(peak > 0, peak, 1.0)
    x = f / peak
    if noise.photons_at_peak:
        e = rng.poisson(x * noise.photons_at_peak).astype(np.float64)
        if noise.read_noise_e:
            e += rng.normal(0.0, noise.read_noise_e, e.shape)
        x = e / noise.photons_at_peak
    if noise.gaussian_sigma:
        x = x + rng.normal(0.0, noise.gaussian_sigma, x.shape)
    if noise.bit_depth:
        levels = 2**noise.bit_depth - 1
        x = np.round(np.clip(x, 0.0, 1.0) * levels) / levels
    return (x * peak).astype(np.float32)
