"""The sensor: frame geometry, quadrant windows, the 8-channel PSF tensor (its noise: :mod:`.detector`).

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

from ..conventions import centered
from ..validation import ConfigError, check_int, check_number  # noqa: F401

__all__ = ["QUADRANTS", "CHANNELS", "SensorSpec", "NoiseSpec", "quadrant_slices", "psf_tensor", "add_noise", "photo_electrons", "area_weights", "area_resample",
           "FrameTensor"]


#: the four quadrants of a frame, reading order (k = 1..4), and the 8 channels of the PSF tensor (channel
#: 4 p + k - 1: quadrant k of polarisation p's frame)
QUADRANTS = ("QI", "QII", "QIII", "QIV")
CHANNELS = tuple(f"{p}-pol {q}" for p in "xy" for q in QUADRANTS)


@dataclass(frozen=True)
class SensorSpec:
    width_px: int = 640
    height_px: int = 512
    pixel_pitch: float = 15e-6  # m, on the camera
    magnification: float = 10.0  # relay
    distance: float = 50e-3  # metasurface to focal (sensor-conjugate) plane, m
    tensor_size: int = 256  # network input: 8 x tensor_size x tensor_size

    def __post_init__(self) -> None:
        for name in ("width_px", "height_px"):
            v = check_int(f"sensor.{name}", getattr(self, name), 4, 100000)
            if v % 4:
                raise ConfigError(f"sensor.{name}", f"must be a multiple of 4 (four quadrants of even size), got {v}")
        check_number("sensor.pixel_pitch", self.pixel_pitch, 0, 1e-3, open_lo=True, unit="m")
        check_number("sensor.magnification", self.magnification, 0, 1e4, open_lo=True)
        check_number("sensor.distance", self.distance, 0, 10.0, open_lo=True, unit="m")
        check_int("sensor.tensor_size", self.tensor_size, 2, 4096)

    def to_dict(self) -> dict:
        return {"width_px": self.width_px, "height_px": self.height_px, "pixel_um": self.pixel_pitch * 1e6,
                "magnification": self.magnification, "distance_mm": self.distance * 1e3,
                "tensor_size": self.tensor_size}

    @property
    def focal_pitch(self) -> float:
        """Pixel pitch referred to the metasurface focal plane (m)."""
        return self.pixel_pitch / self.magnification

    def coords(self) -> tuple[np.ndarray, np.ndarray]:
        """Focal-plane coordinates of the pixel centres: (X of columns, Y of rows)."""
        p = self.focal_pitch
        return centered(self.width_px, p), centered(self.height_px, p)

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


def area_weights(n_in: int, n_out: int) -> np.ndarray:
    """``(n_out, n_in)`` overlap matrix of area-weighted resampling along one axis: output pixel ``i`` covers
    input coordinates ``[i, i + 1) n_in / n_out``; entry ``(i, j)`` is the fraction of input pixel ``j``
    inside it, so every column sums to 1 (power is conserved)."""
    edges = np.arange(n_out + 1) * (n_in / n_out)
    lo, hi = edges[:-1, None], edges[1:, None]
    j = np.arange(n_in)[None, :]
    return np.clip(np.minimum(hi, j + 1) - np.maximum(lo, j), 0.0, None)


def area_resample(img: np.ndarray, size: int) -> np.ndarray:
    """Area-weighted resampling of a 2D image of power per pixel to ``size x size`` pixels: each output
    pixel holds the power falling on it (the total is conserved)."""
    ry = area_weights(img.shape[0], size)
    rx = area_weights(img.shape[1], size)
    return (ry @ np.asarray(img, np.float64) @ rx.T).astype(np.float32)


def psf_tensor(frames: np.ndarray, sensor: SensorSpec) -> np.ndarray:
    """``frames`` (2, H, W) = [x-pol, y-pol] -> (8, S, S) float32, each channel one quadrant."""
    out = np.empty((8, sensor.tensor_size, sensor.tensor_size), np.float32)
    for p in range(2):
        for k in range(1, 5):
            r, c = quadrant_slices(sensor, k)
            out[4 * p + k - 1] = area_resample(frames[p][r, c], sensor.tensor_size)
    return out



def _strided_sum(v: np.ndarray, step: int, axis: int) -> np.ndarray:
    """``v`` summed over consecutive blocks of ``step`` samples along ``axis`` by strided adds (a multi-axis
    sum of a reshape is 3x slower); the adds run in sample order, so every caller rounds alike."""
    def part(i):
        return v[(slice(None),) * (axis % v.ndim) + (slice(i, None, step),)]

    if step == 1:
        return v
    x = part(0) + part(1)
    for i in range(2, step):
        x += part(i)
    return x


def _block_sums(v: np.ndarray, fy: int, fx: int, row_axis: int = -2) -> np.ndarray:
    """Block sums of ``fy`` rows (``row_axis``) by ``fx`` columns (the last axis): rows first, then columns."""
    return _strided_sum(_strided_sum(v, fy, row_axis), fx, -1)


class FrameTensor:
    """The camera's two frames -> the (8, S, S) float32 tensor of :func:`psf_tensor`, prepared once for a
    sensor: what a real-time loop runs per frame.  A quadrant window whose sides are whole multiples of S is
    area-resampled by block sums (a reshape and a sum: O(pixels)); any other by the precomputed float32
    overlap matrices.  ``normalised=True`` also divides by the total and multiplies by 8 (the datasets'
    normalisation).  Equals :func:`psf_tensor` to float32 rounding.

    ``window`` (0: the whole tensor): only the centred ``window x window`` square of each channel is computed
    and the rest of the ``(8, S, S)`` tensor is 0, reading only the quadrant pixels that square covers (a
    windowed real-time network reads nothing else: :class:`~metadesign.reconstruction.modal_net.ModalNet`);
    the square is the whole tensor's there (bit for bit with block sums); ``normalised=True`` divides by the
    window's total."""

    def __init__(self, sensor: SensorSpec, window: int = 0):
        self.size = s = sensor.tensor_size
        self.window = w = check_int("window", window, 0, s)
        if w and (s - w) % 2:
            raise ConfigError("window", f"expected a side of the same parity as the tensor's {s} (a centred "
                                        f"square), got {w}")
        self.offset = (s - w) // 2 if w else 0
        self.windows = []
        for k in range(1, 5):
            r, c = quadrant_slices(sensor, k)
            h, w = r.stop - r.start, c.stop - c.start
            block = (h // s, w // s) if h % s == 0 and w % s == 0 else None
            mats = None if block else (area_weights(h, s).astype(np.float32), area_weights(w, s).T.astype(np.float32))
            self.windows.append((r, c, block, mats))
        blocks = {w[2] for w in self.windows}
        # the four windows tile the frame with one block shape: both frames in one pass of strided adds
        self.whole = (next(iter(blocks)) if len(blocks) == 1 and None not in blocks
                      and 2 * (self.windows[0][0].stop) == sensor.height_px and 2 * self.windows[0][1].stop == sensor.width_px
                      else None)

    def __call__(self, frames: np.ndarray, normalised: bool = False) -> np.ndarray:
        s = self.size
        if self.window:
            return self._windowed(frames, normalised)
        if self.whole:
            y = _block_sums(np.asarray(frames, np.float32), *self.whole)
            out = np.ascontiguousarray(y.reshape(2, 2, s, 2, s).transpose(0, 1, 3, 2, 4).reshape(8, s, s))
            if normalised:
                out *= np.float32(8.0) / out.sum()
            return out
        out = np.empty((8, s, s), np.float32)
        for p in range(2):
            f = np.asarray(frames[p], np.float32)
            for k, (r, c, block, mats) in enumerate(self.windows):
                win = f[r, c]
                if block:
                    out[4 * p + k] = _block_sums(win, *block)
                else:
                    out[4 * p + k] = mats[0] @ win @ mats[1]
        if normalised:
            out *= np.float32(8.0) / out.sum()
        return out

    def _windowed(self, frames: np.ndarray, normalised: bool) -> np.ndarray:
        """The (8, S, S) tensor of :meth:`__call__` inside the centred window, 0 outside; only the window's
        pixels are read, and converted to float32 (the same strided adds as the whole tensor's, on views)."""
        s, w, a = self.size, self.window, self.offset
        out = np.zeros((8, s, s), np.float32)
        f = np.asarray(frames)

        def f32(v):
            return v if v.dtype == np.float32 else v.astype(np.float32)

        if self.whole:  # the four quadrants' windows of both frames as one strided view
            fy, fx = self.whole
            h2, w2 = self.windows[0][0].stop, self.windows[0][1].stop
            v = f32(f.reshape(2, 2, h2, 2, w2)[:, :, a * fy:(a + w) * fy, :, a * fx:(a + w) * fx])
            y = _block_sums(v, fy, fx, row_axis=2)
            out[:, a:a + w, a:a + w] = y.transpose(0, 1, 3, 2, 4).reshape(8, w, w)
        else:
            for p in range(2):
                for k, (r, c, block, mats) in enumerate(self.windows):
                    win = f[p][r, c]
                    if block:
                        fy, fx = block
                        win = f32(win[a * fy:(a + w) * fy, a * fx:(a + w) * fx])
                        out[4 * p + k, a:a + w, a:a + w] = _block_sums(win, fy, fx)
                    else:  # the overlap matrices' window rows and columns, on the pixels they touch
                        ry, rx = mats[0][a:a + w], mats[1][:, a:a + w]
                        i0, i1 = np.flatnonzero(ry.any(axis=0))[[0, -1]]
                        j0, j1 = np.flatnonzero(rx.any(axis=1))[[0, -1]]
                        out[4 * p + k, a:a + w, a:a + w] = (ry[:, i0:i1 + 1] @ f32(win[i0:i1 + 1, j0:j1 + 1])
                                                            @ rx[j0:j1 + 1])
        if normalised:
            out *= np.float32(8.0) / out.sum()
        return out


# the detector (noise on rendered frames) lives in .detector; its names stay importable from here
from .detector import NoiseSpec, add_noise, photo_electrons  # noqa: E402,F401
