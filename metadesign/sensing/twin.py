"""The torch twin of the fast PSF path: received aperture field -> metasurface pupil -> 8 quadrant
matrix Fourier transforms -> area-resampled ``8 x S x S`` tensor, batched, differentiable, on CPU or
CUDA.  Model-based baselines (phase-diversity retrieval, the hybrid) fit pupil phases through it.

Exact mode (``rebin=1, samples=None``) runs the arithmetic of
:func:`~metadesign.sensing.forward.sensor_frames` + :func:`~metadesign.sensing.sensor.psf_tensor`
(same kernels, same order of products; test: 1e-5 relative).  Two documented approximations make it
cheap enough to iterate on: ``rebin`` block-averages the coarse pupil (the G of
:class:`~metadesign.sensing.forward.CoarsePupil`) by ``rebin x rebin``, and ``samples = q`` evaluates
the intensity at ``q x q`` points per tensor pixel instead of at every camera pixel (the midpoint rule of
the area resampling).  :func:`twin_error` measures what they cost on a given pupil.

The received field enters on the ``A x A`` crop of the turbulence grid (the dataset's ``received``);
:func:`crop_interpolator` is the cubic-spline resampling of
:meth:`~metadesign.turbulence.propagate.Turbulence.to_metasurface` written as two matrices (exact for a
field that is zero outside the crop).
"""

from __future__ import annotations

from dataclasses import dataclass
import numpy as np

from ..optics.propagation import cexp
from .forward import CoarsePupil, _nonparaxial
from .sensor import SensorSpec, area_weights, quadrant_slices

__all__ = ["rebin_pupil", "crop_interpolator", "crop_to_pupil", "TwinOperators", "twin_operators",
           "TorchTwin", "twin_error", "normalise", "render_tensor"]


def rebin_pupil(cp: CoarsePupil, factor: int) -> CoarsePupil:
    """The coarse pupil with ``factor x factor`` blocks averaged into one (zero-padded to a multiple)."""
    if factor == 1:
        return cp
    n = cp.G.shape[-1]
    m = -(-n // factor) * factor
    G = np.zeros(cp.G.shape[:-2] + (m, m), np.complex64)
    G[..., :n, :n] = cp.G
    G = G.reshape(cp.G.shape[:-2] + (m // factor, factor, m // factor, factor)).mean(axis=(-3, -1))
    X = cp.X[0] + (np.arange(m) * cp.pitch)
    X = X.reshape(-1, factor).mean(axis=1)
    return CoarsePupil(G.astype(np.complex64), X, cp.block * factor, cp.period, cp.wavelength, cp.z, cp.n_clamped)


def crop_interpolator(n_grid: int, dx: float, receiver_aperture: float, crop_start: int, crop_size: int,
                      n_out: int) -> tuple[np.ndarray, np.ndarray]:
    """``(W, mask)``: the metasurface-grid field of a received crop ``C`` (A x A) is ``mask * (W C W^T)``,
    ``W`` (n_out, A) float64: the cubic spline of ``to_metasurface`` (``map_coordinates(order=3)``,
    separable) applied to a turbulence grid that is zero outside the crop; ``mask`` the inscribed circle."""
    from scipy.ndimage import map_coordinates

    u = (np.arange(n_out) + 0.5) / n_out - 0.5
    pos = u * receiver_aperture / dx + n_grid / 2
    W = np.empty((n_out, crop_size))
    grid = np.zeros((1, n_grid))
    zeros = np.zeros_like(pos)
    for j in range(crop_size):
        grid[:] = 0
        grid[0, crop_start + j] = 1.0
        W[:, j] = map_coordinates(grid, [zeros, pos], order=3)
    mask = (u[None, :] ** 2 + u[:, None] ** 2) <= 0.25
    return W, mask


def crop_to_pupil(crop: np.ndarray, n_grid: int, dx: float, receiver_aperture: float, crop_start: int,
                  n_out: int) -> np.ndarray:
    """numpy reference: the crop embedded in a zero turbulence grid, resampled as ``to_metasurface`` does."""
    from scipy.ndimage import map_coordinates

    a = crop.shape[-1]
    full = np.zeros((n_grid, n_grid), np.complex128)
    full[crop_start:crop_start + a, crop_start:crop_start + a] = crop
    u = (np.arange(n_out) + 0.5) / n_out - 0.5
    pos = u * receiver_aperture / dx + n_grid / 2
    yy, xx = np.meshgrid(pos, pos, indexing="ij")
    re = map_coordinates(full.real, [yy, xx], order=3)
    im = map_coordinates(full.imag, [yy, xx], order=3)
    mask = (u[None, :] ** 2 + u[:, None] ** 2) <= 0.25
    return np.where(mask, re + 1j * im, 0).astype(np.complex64)


@dataclass
class TwinOperators:
    """numpy arrays of the twin (device independent); ``K[c]`` = summed-channel pupil x non-paraxial
    factor x metasurface mask of channel ``c = 4 p + k - 1``."""

    K: np.ndarray  # (8, N, N) complex64
    Ay: np.ndarray  # (8, R, N) complex64: rows of the MFT (output y)
    Ax: np.ndarray  # (8, N, Q) complex64: columns of the MFT (output x)
    w: np.ndarray  # (8, R, Q) float32: 1/sinc^2 compensation x scale x pixel area
    Ry: np.ndarray  # (S, R) float32: resampling of the rows
    Rx: np.ndarray  # (S, Q) float32
    W: np.ndarray  # (N, A) float32: crop -> pupil grid interpolation
    rebin: int
    samples: int | None


def _sample_axis(n_px: int, size: int, q: int | None, pitch: float, origin: float) -> tuple[np.ndarray, np.ndarray]:
    """(coordinates of the evaluation points, resampling matrix) along one quadrant axis of ``n_px`` camera
    pixels; ``origin`` is the coordinate of pixel 0 of the quadrant."""
    if q is None:
        return origin + np.arange(n_px) * pitch, area_weights(n_px, size)
    span = n_px / size  # camera pixels per tensor pixel
    t = (np.arange(size)[:, None] + (np.arange(q)[None, :] + 0.5) / q) * span - 0.5  # pixel-index units
    R = np.kron(np.eye(size), np.full((1, q), span / q))
    return origin + t.ravel() * pitch, R


def twin_operators(cp: CoarsePupil, sensor: SensorSpec, crop: tuple[int, int, int, float, float] | None = None,
                   rebin: int = 1, samples: int | None = None) -> TwinOperators:
    """Operators of the twin for pupil ``cp`` and ``sensor``.  ``crop = (crop_start, crop_size, n_grid, dx,
    receiver_aperture)`` adds the crop interpolation (else ``W`` is empty and inputs are pupil fields)."""
    n_fine = cp.G.shape[-1]
    if crop is not None:
        c0, a, n_grid, dx, d2 = crop
        W, mask = crop_interpolator(n_grid, dx, d2, c0, a, n_fine)
    else:
        W, mask = np.zeros((n_fine, 0)), np.ones((n_fine, n_fine), bool)
    cpr = rebin_pupil(cp, rebin)
    g = rebin_pupil(CoarsePupil((cp.G.sum(axis=1) * mask)[:, None], cp.X, cp.block, cp.period, cp.wavelength,
                                cp.z, 0), rebin).G[:, 0]  # (2, N, N): channels summed, metasurface mask
    if rebin > 1:  # the crop interpolation averaged over the same blocks
        m = -(-n_fine // rebin) * rebin
        Wp = np.zeros((m, W.shape[1]))
        Wp[:n_fine] = W
        W = Wp.reshape(m // rebin, rebin, -1).mean(axis=1)
    k0 = 2 * np.pi / cp.wavelength
    X, Y = sensor.coords()
    p = sensor.focal_pitch
    K, Ay, Ax, w = [], [], [], []
    Ry = Rx = None
    for pol in range(2):
        for k in range(1, 5):
            r, c = quadrant_slices(sensor, k)
            yo, Ry = _sample_axis(r.stop - r.start, sensor.tensor_size, samples, p, Y[r][0])
            xo, Rx = _sample_axis(c.stop - c.start, sensor.tensor_size, samples, p, X[c][0])
            K.append(g[pol] * _nonparaxial(cpr.X, sensor.quadrant_centre(k), k0, cp.z))
            fx, fy = xo / (cp.wavelength * cp.z), yo / (cp.wavelength * cp.z)
            Ax.append(cexp(-2 * np.pi * np.outer(cpr.X, fx)))
            Ay.append(cexp(-2 * np.pi * np.outer(fy, cpr.X)))
            comp = (np.sinc(fy * cpr.pitch)[:, None] * np.sinc(fx * cpr.pitch)[None, :]).astype(np.float32)
            scale = (cpr.pitch**2 / (cp.wavelength * cp.z)) ** 2
            w.append(np.float32(scale) / comp**2 * np.float32(p * p))
    return TwinOperators(np.stack(K).astype(np.complex64), np.stack(Ay), np.stack(Ax), np.stack(w).astype(np.float32),
                         Ry.astype(np.float32), Rx.astype(np.float32), W.astype(np.float32), rebin, samples)


def render_tensor(K, e_in, Ay, Ax, w, Ry, Rx):
    """The twin's kernel (torch): pupil fields ``e_in`` (B, N, N) through the per-quadrant pupils ``K``
    (8, N, N), the matrix Fourier transforms ``Ay``, ``Ax``, the weights ``w`` and the area resampling
    ``Ry``, ``Rx`` -> (B, 8, S, S) PSF tensors.  One kernel for :class:`TorchTwin` and the learnable
    diversity's twin (:class:`~metadesign.sensing.twin_diversity.DiversityTwin`)."""
    v = K * e_in[:, None]  # (B, 8, N, N)
    U = Ay @ (v @ Ax)  # (B, 8, R, Q)
    inten = (U.real ** 2 + U.imag ** 2) * w
    return Ry @ inten @ Rx.transpose(-1, -2)


def normalise(tensor):
    """The dataset's input normalisation: the 8 channels of each sample sum to 8."""
    return tensor * (8.0 / tensor.sum(dim=(-3, -2, -1), keepdim=True))


class TorchTwin:
    """The torch backend of the forward-model contract (:mod:`metadesign.sensing.device`): :meth:`psfs` of
    pupil fields, :meth:`pupil_field` and :meth:`from_crop` of received crops."""

    @classmethod
    def for_device(cls, dev, rebin: int = 1, samples: int | None = None, device="cpu",
                   double: bool = False) -> "TorchTwin":
        """The twin of a :class:`~metadesign.sensing.device.Device` fed from its received-field crop."""
        return cls(twin_operators(dev.pupil, dev.sensor, dev.geometry, rebin, samples), device, double)

    def __init__(self, ops: TwinOperators, device="cpu", double: bool = False):
        import torch

        self.ops = ops
        self.device = torch.device(device)
        cd, rd = (torch.complex128, torch.float64) if double else (torch.complex64, torch.float32)
        self.cdtype, self.rdtype = cd, rd

        def t(a, dt):
            return torch.tensor(np.asarray(a), dtype=dt, device=self.device)

        self.K, self.Ay, self.Ax = t(ops.K, cd), t(ops.Ay, cd), t(ops.Ax, cd)
        self.w, self.Ry, self.Rx = t(ops.w, rd), t(ops.Ry, rd), t(ops.Rx, rd)
        self.W = t(ops.W, cd)

    @property
    def pupil_n(self) -> int:
        return self.K.shape[-1]

    def psfs(self, e_in):
        """``e_in`` (B, N, N) complex pupil fields -> (B, 8, S, S) PSF tensors (power, unit incident intensity)."""
        return render_tensor(self.K, e_in, self.Ay, self.Ax, self.w, self.Ry, self.Rx)

    tensor = psfs  # the name before the contract (metadesign.sensing.device)

    def pupil_field(self, crop):
        """Received crops (B, A, A) complex -> pupil fields (B, N, N) (the metasurface mask is in ``K``)."""
        return self.W @ crop.to(self.cdtype) @ self.W.transpose(-1, -2)

    def from_crop(self, crop):
        return self.psfs(self.pupil_field(crop))


def twin_error(cp: CoarsePupil, sensor: SensorSpec, crop_geometry, fields: np.ndarray, rebin: int,
               samples: int | None) -> float:
    """Mean relative L2 error of the normalised tensors of an approximate twin against the exact one on
    received ``fields`` (B, A, A)."""
    import torch

    exact = TorchTwin(twin_operators(cp, sensor, crop_geometry))
    fast = TorchTwin(twin_operators(cp, sensor, crop_geometry, rebin, samples))
    with torch.no_grad():
        f = torch.from_numpy(np.asarray(fields, np.complex64))
        a, b = normalise(exact.from_crop(f)), normalise(fast.from_crop(f))
        err = torch.linalg.vector_norm(a - b, dim=(1, 2, 3)) / torch.linalg.vector_norm(a, dim=(1, 2, 3))
    return float(err.mean())
