"""A simulated Shack-Hartmann sensor on the received field.

Geometry.  ``L x L`` square lenslets tile the receiver aperture's bounding square (pitch ``d = D / L``);
each pixel of the received crop (pitch ``dx``) belongs to the lenslet holding its centre.  A lenslet
focuses its part of the field onto ``K x K`` detector pixels of angular pitch ``lambda / (s d)``
(``s`` pixels per ``lambda / d``, 2 = Nyquist): the spot is ``|sum_pix u exp(-i k theta . (x - x_c))|^2``
(the Fraunhofer pattern of the sub-aperture, a matrix Fourier transform).  ``K = s d / dx`` makes the
lenslet's field of view one period of that pattern, ``lambda / dx``: the field is sampled at ``dx`` and
has no tilt beyond it, so no spot can be lost or aliased by the simulation itself.  Scintillation
(dark and bright sub-apertures, speckled spots when ``d > r0``) and branch points (a curl the gradient
cannot carry) are in the field, so their effect on the sensor comes by construction.

Detection: the whole frame is scaled by its brightest pixel and gets the same Gaussian noise as the
metasurface sensor (% of the peak, :func:`metadesign.reconstruction.data.apply_noise`).  Centroids:
thresholded centre of gravity (``threshold`` x the lenslet's own peak subtracted); sub-apertures with
less than ``min_flux`` of the mean flux, or less than half inside the aperture, are dropped.

Calibration: each lenslet's slope gain is measured with a small push-pull tilt of a flat beam and
divided out (the thresholded centre of gravity of a truncated, pixelated spot reads a few % off, more on
partial lenslets at the aperture's edge).

Reconstruction: slopes are phase gradients ``k theta``.  ``zonal``: Southwell geometry (phase at the
lenslet centres, neighbours' mean slope times the pitch equals their phase difference; at the edge and
next to dropped lenslets the valid neighbour's slope carries the phase one pitch out), least squares
with a weak Laplacian for nodes no equation reaches, then cubic interpolation to the crop pixels.
``modal``: Zernike coefficients by least squares against an interaction matrix calibrated as an AO
user does, by pushing and pulling each mode (noise-free, flat amplitude) through this same sensor.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from ..optics.propagation import cexp
from ..optics.zernike import zernike
from ..sensing.device import Device, ReceiverCrop
from ..validation import ConfigError, check_int, check_number
from .data import apply_noise

__all__ = ["SHConfig", "ShackHartmann"]


@dataclass(frozen=True)
class SHConfig:
    lenslets: int = 8  # across the aperture
    pixels_per_lambda_over_d: float = 2.0
    threshold: float = 0.1  # x the lenslet's own peak, subtracted before centroiding
    noise_sigmas: float = 3.0  # ... or this many noise sigmas (of the frame), whichever is larger
    min_flux: float = 0.1
    reconstructor: str = "zonal"
    modes: int = 0  # modal: Noll 2 .. modes+1; 0: as many as 3/4 of the lenslets inside the aperture
    smoothing: float = 0.05  # zonal: weight of the Laplacian fill
    noise_percent: float = 0.0  # the frames' expected Gaussian noise (% of the peak): sets the centroid threshold

    def __post_init__(self):
        check_int("sh.lenslets", self.lenslets, 2, 64)
        check_number("sh.pixels_per_lambda_over_d", self.pixels_per_lambda_over_d, 1, 8)
        check_number("sh.threshold", self.threshold, 0, 0.99)
        check_number("sh.noise_sigmas", self.noise_sigmas, 0, 100)
        check_number("sh.min_flux", self.min_flux, 0, 1)
        if self.reconstructor not in ("zonal", "modal"):
            raise ConfigError("sh.reconstructor", f"expected zonal or modal, got {self.reconstructor!r}")
        check_int("sh.modes", self.modes, 0, 300)
        check_number("sh.smoothing", self.smoothing, 0, 100)
        check_number("sh.noise_percent", self.noise_percent, 0, 100)

    def to_dict(self) -> dict:
        """The sensor's settings (the expected noise is the study's, reported with it)."""
        d = asdict(self)
        d.pop("noise_percent")
        return d


class ShackHartmann:
    """The sensor for one crop geometry: :meth:`frames` of received crops, :meth:`centroids`,
    :meth:`reconstruct` (phase on the crop), :meth:`__call__` = all three."""

    @classmethod
    def for_crop(cls, cfg: SHConfig, crop: ReceiverCrop, wavelength: float) -> "ShackHartmann":
        """The sensor on a received-field crop (:class:`~metadesign.sensing.device.ReceiverCrop`)."""
        return cls(cfg, crop.size, crop.start, crop.n_grid, crop.dx, crop.aperture, wavelength)

    @classmethod
    def for_device(cls, cfg: SHConfig, dev: Device) -> "ShackHartmann":
        """The sensor in place of ``dev``: same received-field crop, same wavelength."""
        return cls.for_crop(cfg, dev.crop, dev.wavelength)

    def __init__(self, cfg: SHConfig, crop_size: int, crop_start: int, n_grid: int, dx: float,
                 receiver_aperture: float, wavelength: float):
        self.cfg = cfg
        a, L = crop_size, cfg.lenslets
        self.a, self.dx, self.wavelength = a, dx, wavelength
        x = (np.arange(a) + crop_start - n_grid / 2) * dx  # crop coordinates (m)
        R = receiver_aperture / 2
        self.ap = np.hypot(x[None, :], x[:, None]) <= R
        self.d = receiver_aperture / L
        idx = np.clip(np.floor((x + R) / self.d).astype(int), 0, L - 1)
        self.lens_of = idx  # lenslet index of each crop row/column
        self.centres = -R + (np.arange(L) + 0.5) * self.d
        s = cfg.pixels_per_lambda_over_d
        self.K = max(4, int(round(s * self.d / dx)))
        self.dtheta = wavelength / (s * self.d)
        th = (np.arange(self.K) - (self.K - 1) / 2) * self.dtheta
        k = 2 * np.pi / wavelength
        # E[i] (K, a): Fourier kernel of lenslet i's rows (zero on others' rows)
        E = np.zeros((L, self.K, a), np.complex64)
        for i in range(L):
            sel = idx == i
            E[i][:, sel] = cexp(-k * np.outer(th, x[sel] - self.centres[i]))
        self.E = E
        self.theta = th
        # aperture fill of each lenslet
        fill = np.zeros((L, L))
        np.add.at(fill, (idx[:, None].repeat(a, 1), idx[None, :].repeat(a, 0)), self.ap.astype(float))
        full = np.zeros((L, L))
        np.add.at(full, (idx[:, None].repeat(a, 1), idx[None, :].repeat(a, 0)), 1.0)
        self.fill = fill / np.maximum(full, 1)
        self.inside = self.fill >= 0.5
        self._modal = None
        self._zonal_cache = None
        self.gain = np.ones((L, L, 2))
        self.gain = self._calibrate_gain()

    # -- detection ---------------------------------------------------------------------------------
    def frames(self, crops: np.ndarray) -> np.ndarray:
        """(B, L, L, K, K) spot images (arbitrary units) of received crops (B, a, a)."""
        u = np.asarray(crops, np.complex64) * self.ap
        # U[b, i, j] = E[i] u E[j]^T
        t = np.einsum("iua,bac->biuc", self.E, u, optimize=True)
        U = np.einsum("biuc,jvc->bijuv", t, self.E, optimize=True)
        return (U.real ** 2 + U.imag ** 2).astype(np.float32)

    def add_noise(self, spots: np.ndarray, gaussian_percent: float, rng: np.random.Generator) -> np.ndarray:
        """The metasurface sensor's noise model on the whole frame (scaled by the frame's peak)."""
        if not gaussian_percent:
            return spots
        B, L, _, K, _ = spots.shape
        frame = spots.transpose(0, 1, 3, 2, 4).reshape(B, L * K, L * K)
        noisy = np.stack([apply_noise(f[None], rng, gaussian_percent)[0] for f in frame])
        return noisy.reshape(B, L, K, L, K).transpose(0, 1, 3, 2, 4)

    def centroids(self, spots: np.ndarray, gaussian_percent: float = 0.0,
                  calibrated: bool = True) -> tuple[np.ndarray, np.ndarray]:
        """(slopes (B, L, L, 2) rad/m as (d phi/dx, d phi/dy), valid (B, L, L) bool) of spot images with
        the frame's Gaussian noise level ``gaussian_percent`` (% of the frame's peak; sets the threshold)."""
        cfg = self.cfg
        s = np.asarray(spots, np.float64)
        peak = s.max(axis=(-2, -1), keepdims=True)
        sigma = gaussian_percent / 100 * s.max(axis=(1, 2, 3, 4), keepdims=True)
        w = np.clip(s - np.maximum(cfg.threshold * peak, cfg.noise_sigmas * sigma), 0, None)
        tot = w.sum(axis=(-2, -1))
        th = self.theta
        cx = (w.sum(axis=-2) * th).sum(axis=-1) / np.maximum(tot, 1e-300)
        cy = (w.sum(axis=-1) * th).sum(axis=-1) / np.maximum(tot, 1e-300)
        flux = s.sum(axis=(-2, -1))
        mean_flux = (flux * self.inside).sum(axis=(-2, -1), keepdims=True) / max(self.inside.sum(), 1)
        valid = self.inside & (flux >= cfg.min_flux * mean_flux) & (tot > 0)
        k = 2 * np.pi / self.wavelength
        slopes = np.stack([k * cx, k * cy], -1)
        return (slopes / self.gain if calibrated else slopes), valid

    def _calibrate_gain(self, tilt_rad_per_lenslet: float = 0.2) -> np.ndarray:
        """Per-lenslet slope gain (x, y): measured over applied for a small push-pull tilt of a flat beam,
        as an AO user calibrates a sensor (the centre of gravity of a truncated, pixelated spot reads
        partial lenslets low and full ones a few % high); 1 where a lenslet sees no light."""
        x = (np.arange(self.a) - (self.a - 1) / 2) * self.dx
        g = tilt_rad_per_lenslet / self.d
        out = np.ones((self.cfg.lenslets, self.cfg.lenslets, 2))
        for ax, ramp in enumerate((x[None, :] + 0 * x[:, None], x[:, None] + 0 * x[None, :])):
            plus, v = self.centroids(self.frames(np.exp(1j * g * ramp)[None] * self.ap), calibrated=False)
            minus, _ = self.centroids(self.frames(np.exp(-1j * g * ramp)[None] * self.ap), calibrated=False)
            gain = (plus[0, ..., ax] - minus[0, ..., ax]) / (2 * g)
            out[..., ax] = np.where(v[0] & (gain > 0.2), gain, 1.0)
        return out

    # -- reconstruction ----------------------------------------------------------------------------
    def _zonal_system(self):
        """Pairs of neighbours and the Laplacian on the lenslet grid padded by one ring of virtual nodes."""
        if self._zonal_cache is None:
            n = self.cfg.lenslets + 2
            pairs = []  # (a, b, axis): phase[b] - phase[a] along +axis
            lap = np.zeros((n * n, n * n))
            for i in range(n):
                for j in range(n):
                    if j + 1 < n:
                        pairs.append((i * n + j, i * n + j + 1, 0))
                    if i + 1 < n:
                        pairs.append((i * n + j, (i + 1) * n + j, 1))
                    nb = [(i + di, j + dj) for di, dj in ((1, 0), (-1, 0), (0, 1), (0, -1))
                          if 0 <= i + di < n and 0 <= j + dj < n]
                    lap[i * n + j, i * n + j] = -len(nb)
                    for p, q in nb:
                        lap[i * n + j, p * n + q] = 1
            self._zonal_cache = (pairs, lap)
        return self._zonal_cache

    def _interp(self, grid: np.ndarray) -> np.ndarray:
        """Cubic interpolation of the padded lenslet-grid phase to the crop pixels."""
        from scipy.ndimage import map_coordinates

        x = (np.arange(self.a) - (self.a - 1) / 2) * self.dx  # crop coordinates relative to its centre
        pos = (x + self.cfg.lenslets * self.d / 2) / self.d - 0.5 + 1
        yy, xx = np.meshgrid(pos, pos, indexing="ij")
        return map_coordinates(grid, [yy, xx], order=3, mode="nearest") * self.ap

    def _zonal(self, slopes, valid):
        """Southwell least squares: neighbours both valid, ``phi_b - phi_a = d (s_a + s_b) / 2``; one valid
        (the aperture's edge, a dark lenslet), ``d s_valid``: the phase is carried out by the measured
        tilt, so the cubic interpolation has support beyond the outer lenslet centres; a weak Laplacian
        fixes nodes no equation reaches; zero mean."""
        pairs, lap = self._zonal_system()
        L = self.cfg.lenslets
        n = L + 2
        v = np.zeros((n, n), bool)
        v[1:-1, 1:-1] = valid
        sl = np.zeros((n, n, 2))
        sl[1:-1, 1:-1] = slopes
        v, sl = v.ravel(), sl.reshape(-1, 2)
        rows, rhs = [], []
        for a_, b_, ax in pairs:
            if v[a_] or v[b_]:
                r = np.zeros(n * n)
                r[b_], r[a_] = 1, -1
                rows.append(r)
                s = (sl[a_, ax] + sl[b_, ax]) / 2 if (v[a_] and v[b_]) else (sl[a_, ax] if v[a_] else sl[b_, ax])
                rhs.append(self.d * s)
        A = np.vstack(rows + [self.cfg.smoothing * lap, np.ones((1, n * n))])
        y = np.concatenate([rhs, np.zeros(n * n), [0.0]])
        phi = np.linalg.lstsq(A, y, rcond=None)[0]
        return self._interp(phi.reshape(n, n))

    def _modal_matrix(self):
        if self._modal is None:
            x = (np.arange(self.a) - (self.a - 1) / 2) * self.dx
            R = self.cfg.lenslets * self.d / 2
            r = np.hypot(x[None, :], x[:, None]) / R
            th = np.arctan2(x[:, None] + 0 * x[None, :], x[None, :] + 0 * x[:, None])
            n = self.cfg.modes or max(2, int(0.75 * self.inside.sum()))
            Z = np.stack([zernike(j, r, th) * self.ap for j in range(2, n + 2)])
            amp = 0.1  # rad RMS: push-pull well inside the linear range, with the sensor's own settings
            plus, _ = self.centroids(self.frames(np.exp(1j * amp * Z) * self.ap))  # gain-calibrated slopes
            minus, _ = self.centroids(self.frames(np.exp(-1j * amp * Z) * self.ap))
            D = ((plus - minus) / (2 * amp)).reshape(len(Z), -1, 2)  # (modes, L*L, 2)
            self._modal = (Z, D)
        return self._modal

    def _modal_fit(self, slopes, valid):
        Z, D = self._modal_matrix()
        v = valid.ravel()
        M = D[:, v].reshape(len(Z), -1).T  # (2 n_valid, modes)
        y = slopes.reshape(-1, 2)[v].ravel()
        if M.shape[0] == 0:
            return np.zeros((self.a, self.a))
        c = np.linalg.lstsq(M, y, rcond=1e-3)[0]
        return np.tensordot(c, Z, axes=1)

    def reconstruct(self, slopes: np.ndarray, valid: np.ndarray) -> np.ndarray:
        """(B, a, a) phase on the crop (0 outside the aperture) from slopes and validity."""
        f = self._zonal if self.cfg.reconstructor == "zonal" else self._modal_fit
        return np.stack([f(s, v) for s, v in zip(slopes, valid)]).astype(np.float32)

    def __call__(self, crops: np.ndarray, gaussian_percent: float = 0.0,
                 rng: np.random.Generator | None = None) -> np.ndarray:
        spots = self.frames(crops)
        if gaussian_percent:
            spots = self.add_noise(spots, gaussian_percent, rng or np.random.default_rng(0))
        return self.reconstruct(*self.centroids(spots, gaussian_percent))
