"""Modified von Karman phase screens (Eq. S7): FFT method plus subharmonics.

``psd(f) = 0.023 r0^(-5/3) exp(-f^2 / fm^2) / (f^2 + f0^2)^(11/6)`` with
``fm = 5.92 / (2 pi l0)``, ``f0 = 1 / L0`` (ordinary frequency, cycles/m):
the phase PSD in rad^2 m^2.

Screens follow Schmidt (*Numerical Simulation of Optical Wave Propagation*,
Listings 9.2-9.3): complex Gaussian noise times ``sqrt(PSD) df`` through an
inverse FFT; both the real and the imaginary part are independent screens.
Subharmonics (five levels of 3 x 3 frequencies at ``df / 3^p``) restore the
low-frequency power a finite grid misses; their random draws come from a
generator of their own (never the high-frequency one).  The subharmonic sum
is separable, so it costs two small matrix products per level.
"""

from __future__ import annotations

import numpy as np
import scipy.fft as sfft
from scipy import integrate, special

from ..conventions import fft_centered
from ..determinism import single_thread_blas

__all__ = ["psd_mvk", "structure_function_theory", "log_amplitude_variance_theory", "screen_pair", "ScreenGrid",
           "screens"]


def psd_mvk(f: np.ndarray, r0: float, l0: float, L0: float) -> np.ndarray:
    """Modified von Karman phase PSD (rad^2 m^2) at ordinary frequency ``f`` (1/m)."""
    fm = 5.92 / (2 * np.pi * l0)
    f0 = 1.0 / L0
    return 0.023 * r0 ** (-5 / 3) * np.exp(-(f / fm) ** 2) / (f * f + f0 * f0) ** (11 / 6)


def _log_grid(L0: float, l0: float, n: int = 8001) -> np.ndarray:
    """Frequencies for integrals over f: log-spaced from far below 1/L0 to far above the inner-scale cut."""
    return np.geomspace(1e-4 / L0, 40 * 5.92 / (2 * np.pi * l0), n)


def structure_function_theory(r: np.ndarray, r0: float, l0: float, L0: float) -> np.ndarray:
    """Phase structure function of the same PSD: ``D(r) = 4 pi int f PSD(f) [1 - J0(2 pi f r)] df``
    (Simpson's rule in ln f; the part below the grid's first frequency is negligible)."""
    f = _log_grid(L0, l0)
    w = 4 * np.pi * f * f * psd_mvk(f, r0, l0, L0)  # d f = f d(ln f)
    r = np.atleast_1d(np.asarray(r, float))
    return np.array([integrate.simpson(w * (1 - special.j0(2 * np.pi * f * rr)), x=np.log(f)) for rr in r])


def _cell_psd(fx: np.ndarray, fy: np.ndarray, width: float, l0: float, L0: float, sub: int = 8) -> np.ndarray:
    """Effective PSD (r0 = 1 m) of square cells of side ``width`` centred on
    ``(fx, fy)``: ``int_cell PSD(f) |f|^2 d^2f / (|f_c|^2 width^2)``.  Near the
    origin the PSD is steep; one sample at the cell centre misjudges the cell.
    Weighting by ``|f|^2`` makes each mode carry exactly its cell's share of the
    small-separation structure function ``D(r) ~ 2 pi^2 int PSD (f.r)^2``."""
    s = ((np.arange(sub) + 0.5) / sub - 0.5) * width
    acc = np.zeros(np.broadcast(fx, fy).shape)
    for a in s:
        for b in s:
            f2 = (fx + a) ** 2 + (fy + b) ** 2
            acc += psd_mvk(np.sqrt(f2), 1.0, l0, L0) * f2
    fc2 = np.asarray(fx, float) ** 2 + np.asarray(fy, float) ** 2
    return acc / sub**2 / np.where(fc2 > 0, fc2, np.inf)


class ScreenGrid:
    """Precomputed pieces for ``n x n`` screens of spacing ``dx`` (r0 = 1 m templates;
    a screen of Fried parameter r0 scales by ``r0^(-5/6)``).

    Cells near the origin of the FFT grid, and the subharmonic cells, carry
    their cell-integrated PSD (not the PSD at the cell centre); ``levels``
    subharmonic levels of 3 x 3 cells each, down to ``df / 3^levels``."""

    def __init__(self, n: int, dx: float, l0: float, L0: float, subharmonics: bool = True, levels: int = 5):
        self.n, self.dx, self.l0, self.L0 = n, dx, l0, L0
        df = 1.0 / (n * dx)
        fx = np.fft.fftfreq(n, dx)
        FX, FY = np.meshgrid(fx, fx)
        f = np.hypot(FX, FY)
        psd = psd_mvk(np.where(f == 0, 1.0, f), 1.0, l0, L0)
        near = (np.abs(FX) <= 4.5 * df) & (np.abs(FY) <= 4.5 * df)
        psd[near] = _cell_psd(FX[near], FY[near], df, l0, L0)
        amp = np.sqrt(psd) * df
        amp[0, 0] = 0.0  # the central cell is covered by the subharmonics (or is piston)
        self.amp = (amp * n * n).astype(np.float32)  # ifft2 divides by n^2
        self.subharmonics = subharmonics
        x = fft_centered(n, dx)
        self.levels = []
        for p in range(1, levels + 1):
            dfp = df / 3**p
            fs = np.array([-1.0, 0.0, 1.0]) * dfp
            ex = np.exp(2j * np.pi * np.outer(fs, x))  # (3, n)
            GX, GY = np.meshgrid(fs, fs)
            a = np.sqrt(_cell_psd(GX, GY, dfp, l0, L0)) * dfp
            a[1, 1] = 0.0  # covered by the next level (or piston at the last)
            self.levels.append((ex.astype(np.complex64), a))  # a[iy, ix]
        E = np.concatenate([ex for ex, _ in self.levels]) if self.levels else np.zeros((0, n), np.complex64)
        self._Er = np.ascontiguousarray(E.real, np.float32)
        self._Ei = np.ascontiguousarray(E.imag, np.float32)
        self._EE = np.concatenate([self._Er, -self._Ei])

    def low_frequency(self, rng: np.random.Generator) -> np.ndarray:
        """Subharmonic screen (r0 = 1 m), piston removed, shape (n, n): all
        levels in one product ``Re(E^T C E)`` with block-diagonal C."""
        L = len(self.levels)
        C = np.zeros((3 * L, 3 * L), np.complex128)
        for i, (_, a) in enumerate(self.levels):
            C[3 * i:3 * i + 3, 3 * i:3 * i + 3] = (rng.standard_normal((3, 3)) + 1j * rng.standard_normal((3, 3))) * a
        # Re(E^T C E) = [Er; -Ei]^T [Cr Er - Ci Ei; Ci Er + Cr Ei], one real float32 product
        Er, Ei = self._Er, self._Ei
        Cr, Ci = C.real.astype(np.float32), C.imag.astype(np.float32)
        lo = self._EE.T @ np.concatenate([Cr @ Er - Ci @ Ei, Ci @ Er + Cr @ Ei])
        lo -= np.float32(lo.mean(dtype=np.float64))
        return lo


def screen_pair(grid: ScreenGrid, r0s: tuple[float, float], rng_hf: np.random.Generator,
                rng_sh: np.random.Generator | None) -> tuple[np.ndarray, np.ndarray]:
    """Two independent screens (rad, float32) from one complex FFT: the real
    part scaled to ``r0s[0]`` and the imaginary part to ``r0s[1]``."""
    n = grid.n
    cn = np.empty((n, n), np.complex64)
    # draw straight into the interleaved (re, im) memory: no temporaries
    rng_hf.standard_normal(out=cn.view(np.float32), dtype=np.float32)
    cn *= grid.amp
    hf = sfft.ifft2(cn, overwrite_x=True)
    a, b = hf.real, hf.imag  # views: the sums below happen in place
    if grid.subharmonics and rng_sh is not None:
        a += grid.low_frequency(rng_sh)
        b += grid.low_frequency(rng_sh)
    a *= np.float32(r0s[0] ** (-5 / 6))
    b *= np.float32(r0s[1] ** (-5 / 6))
    return a, b


def screens(grid: ScreenGrid, r0s, seed) -> np.ndarray:
    """All screens of one sample, (len(r0s), n, n) float32; ``seed`` is an int or
    a SeedSequence: it spawns one generator for the high-frequency parts and
    one for the subharmonics."""
    with single_thread_blas():  # the same bytes in every process (see metadesign.determinism)
        return _screens(grid, r0s, seed)


def _screens(grid: ScreenGrid, r0s, seed) -> np.ndarray:
    ss = seed if isinstance(seed, np.random.SeedSequence) else np.random.SeedSequence(seed)
    hf_ss, sh_ss = ss.spawn(2)
    rng_hf, rng_sh = np.random.default_rng(hf_ss), np.random.default_rng(sh_ss)
    r0s = list(r0s)
    out = np.zeros((len(r0s), grid.n, grid.n), np.float32)
    live = [i for i, r in enumerate(r0s) if np.isfinite(r)]  # r0 = inf: no turbulence, nothing drawn
    for j in range(0, len(live), 2):
        i0 = live[j]
        i1 = live[j + 1] if j + 1 < len(live) else None
        a, b = screen_pair(grid, (r0s[i0], r0s[i1] if i1 is not None else r0s[i0]), rng_hf, rng_sh)
        out[i0] = a
        if i1 is not None:
            out[i1] = b
    return out


def log_amplitude_variance_theory(r0_screens, distances, wavelength: float, l0: float, L0: float) -> float:
    """Weak-fluctuation (Rytov) log-amplitude variance of a spherical wave
    behind thin screens of this PSD: ``sum_i 2 pi int f PSD_i(f)
    sin^2(pi lambda f^2 d_i) df`` with ``d_i = z_i (1 - z_i / L)`` (z from the
    source).  For Kolmogorov screens this is Eq. S5; with an inner scale it is
    lower (the Fresnel zone sqrt(lambda L) is only a few l0)."""
    f = _log_grid(L0, l0, 20001)
    total = 0.0
    for r0, d in zip(r0_screens, distances):
        if not np.isfinite(r0) or d <= 0:
            continue
        g = 2 * np.pi * f * f * psd_mvk(f, r0, l0, L0) * np.sin(np.pi * wavelength * f * f * d) ** 2
        total += integrate.simpson(g, x=np.log(f))
    return float(total)
