"""Tip and tilt from the far field's peak (issue #50): the tilt a closed loop's power in the bucket rewards.

The tilt that best corrects a received field ``u`` is the one that maximises the corrected beam's overlap
with it, ``|sum_aperture u exp(-i (a Z2 + b Z3))|^2``: the position of ``u``'s far-field peak.  Under
scintillation that is neither the phase's mean gradient nor its intensity-weighted mean gradient (the
far field's centroid): on the closed-loop residuals of ``sensing/dataset-loop`` both lie 0.3-0.5 rad rms
from it (``benchmarks/crosscheck_realtime_tilt.py``).  A metasurface channel that focuses on the sensor
images the far field, so its peak is that tilt.

:class:`PeakTipTilt` finds the channel whose flat-wavefront PSF has the highest peak (the in-focus one),
locates the peak of that channel to a fraction of a pixel (a three-point parabola through the brightest
pixel and its neighbours along each axis) and reads it through a push-pull calibration on the device: the
peak's shift for ``+/- amplitude`` rad of each tilt mode around the flat wavefront, a 2 x 2 matrix,
inverted.  One frame: one argmax over the channel's pixels and five reads.  It reads what
:class:`~metadesign.reconstruction.linear.TipTiltSplitEstimator` swaps in (``estimate(psf) -> (B, 2)``,
``basis``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..validation import InputError
from .linear import render_phase

__all__ = ["PeakTipTilt", "peak_position"]

#: pixels: the least peak shift a calibration push may give (below it the parabola's error dominates)
MIN_SHIFT_PX = 0.2


def peak_position(img: np.ndarray) -> np.ndarray:
    """``(..., S, S)`` -> ``(..., 2)``: the (x, y) position of each image's peak in pixels from the image's
    centre ``(S - 1) / 2``: the brightest pixel moved by the vertex of the parabola through it and its two
    neighbours along each axis (no move along an axis where the three do not curve downwards or the pixel
    lies on that border).  NaN for an image with no light or a non-finite pixel."""
    a = np.asarray(img, np.float64)
    *lead, s, s2 = a.shape
    if s != s2 or s < 3:
        raise InputError(f"psf: expected square images of at least 3 x 3 pixels, got {a.shape}")
    f = a.reshape(-1, s, s)
    flat = f.reshape(len(f), -1)
    ok = np.all(np.isfinite(flat), axis=1)
    k = np.where(ok, np.where(ok[:, None], flat, 0.0).argmax(axis=1), 0)
    ok &= flat[np.arange(len(f)), k] > 0
    iy, ix = np.divmod(k, s)
    b = np.arange(len(f))
    v0 = f[b, iy, ix]

    def vertex(i, vm, vp):
        d = vm - 2 * v0 + vp
        inner = (i >= 1) & (i <= s - 2) & (d < 0)
        return np.where(inner, 0.5 * (vm - vp) / np.where(inner, d, -1.0), 0.0)

    lo_x, hi_x = np.clip(ix - 1, 0, s - 1), np.clip(ix + 1, 0, s - 1)
    lo_y, hi_y = np.clip(iy - 1, 0, s - 1), np.clip(iy + 1, 0, s - 1)
    x = ix + vertex(ix, f[b, iy, lo_x], f[b, iy, hi_x]) - (s - 1) / 2
    y = iy + vertex(iy, f[b, lo_y, ix], f[b, hi_y, ix]) - (s - 1) / 2
    out = np.stack([np.where(ok, x, np.nan), np.where(ok, y, np.nan)], axis=-1)
    return out.reshape(*lead, 2)


@dataclass
class PeakTipTilt:
    """``estimate(psf) = R @ (peak(psf[channel]) - reference)``: the tip and tilt (rad rms of each basis
    mode) of a normalised PSF tensor ``(C, S, S)`` (or a batch ``(B, C, S, S)``)."""

    R: np.ndarray            # (2, 2): the inverse of the calibration
    reference: np.ndarray    # (2,): the flat wavefront's peak (pixels from the centre)
    basis: np.ndarray        # (2, A, A) float32: the tilt modes on the crop
    channel: int             # the in-focus channel
    interaction: np.ndarray  # (2, 2): peak shift (pixels) per rad of each mode
    amplitude: float

    @classmethod
    def build(cls, device, basis: np.ndarray, amplitude: float = 1.0) -> PeakTipTilt:
        """Calibrate on ``device`` (a :class:`~metadesign.sensing.device.Device` with a receiver crop) for the
        two tilt modes ``basis`` (2, A, A) on the crop, pushed by ``+/- amplitude`` rad."""
        basis = np.asarray(basis, np.float64)
        if basis.shape != (2, device.crop.size, device.crop.size):
            raise InputError(f"basis: expected (2, {device.crop.size}, {device.crop.size}) tilt modes on the crop, "
                             f"got {basis.shape}")
        if not (np.isfinite(amplitude) and amplitude > 0):
            raise InputError(f"peak tilt: expected amplitude > 0 rad, got {amplitude!r}")

        flat = render_phase(device, np.zeros(basis.shape[1:]))
        channel = int(np.argmax(flat.reshape(len(flat), -1).max(axis=1)))
        ref = peak_position(flat[channel])
        def peak(phase):
            return peak_position(render_phase(device, phase)[channel])

        M = np.stack([(peak(amplitude * z) - peak(-amplitude * z)) / (2 * amplitude) for z in basis], axis=1)
        shift = np.abs(M).max(axis=0) * amplitude
        if not np.all(np.isfinite(M)) or np.any(shift < MIN_SHIFT_PX) or np.linalg.cond(M) > 1e3:
            raise InputError(f"peak tilt: channel {channel}'s peak moves {np.round(shift, 2).tolist()} px for "
                             f"{amplitude:g} rad of tip and tilt (at least {MIN_SHIFT_PX} px needed): push harder")
        return cls(np.linalg.inv(M), ref, basis.astype(np.float32), channel, M, float(amplitude))

    def estimate(self, psf: np.ndarray) -> np.ndarray:
        """Tip and tilt ``(2,)`` (or ``(B, 2)``) of a normalised PSF tensor ``(C, S, S)`` (or a batch); zero
        (no correction) for a frame whose channel has no light or a non-finite pixel."""
        p = np.asarray(psf)
        if p.ndim < 3 or p.shape[-3] <= self.channel:
            raise InputError(f"psf: expected (..., C, S, S) with at least {self.channel + 1} channels, got {p.shape}")
        t = (peak_position(p[..., self.channel, :, :]) - self.reference) @ self.R.T
        return np.where(np.isfinite(t), t, 0.0)
