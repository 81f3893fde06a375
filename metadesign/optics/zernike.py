"""Zernike polynomials, Noll-indexed (j = 1 piston, 2/3 tilts, 4 defocus, ...), normalised to unit RMS
over the unit disk (Noll 1976)."""

from __future__ import annotations

from math import factorial

import numpy as np

__all__ = ["noll_to_nm", "zernike", "zernike_basis", "modes_up_to_order"]


def noll_to_nm(j: int) -> tuple[int, int]:
    """Noll index j >= 1 -> (radial order n, azimuthal frequency m); m > 0 cosine, m < 0 sine."""
    if j < 1:
        raise ValueError(f"Noll index starts at 1, got {j}")
    n = 0
    while (n + 1) * (n + 2) // 2 < j:
        n += 1
    k = j - n * (n + 1) // 2 - 1  # position 0..n within the order
    mags = [0] + [m for m in range(2, n + 1, 2) for _ in (0, 1)] if n % 2 == 0 else \
        [m for m in range(1, n + 1, 2) for _ in (0, 1)]
    mabs = mags[k]
    if mabs == 0:
        return n, 0
    return n, (mabs if j % 2 == 0 else -mabs)


def _radial(n: int, m: int, r: np.ndarray) -> np.ndarray:
    out = np.zeros_like(r)
    for s in range((n - m) // 2 + 1):
        c = (-1) ** s * factorial(n - s) / (factorial(s) * factorial((n + m) // 2 - s) * factorial((n - m) // 2 - s))
        out += c * r ** (n - 2 * s)
    return out


def zernike(j: int, r: np.ndarray, theta: np.ndarray) -> np.ndarray:
    """Z_j at polar coordinates (r <= 1 inside the pupil)."""
    n, m = noll_to_nm(j)
    if m == 0:
        return np.sqrt(n + 1) * _radial(n, 0, r)
    norm = np.sqrt(2 * (n + 1))
    return norm * _radial(n, abs(m), r) * (np.cos(m * theta) if m > 0 else np.sin(-m * theta))


def modes_up_to_order(order: int) -> int:
    """Number of Noll modes with radial order <= ``order`` (piston included)."""
    return (order + 1) * (order + 2) // 2


def zernike_basis(n_modes: int, size: int, radius_px: float, first: int = 2) -> np.ndarray:
    """(n_modes, size, size) modes ``j = first .. first + n_modes - 1`` sampled at pixel centres of a grid
    whose centre pixel is ``(size - 1) / 2``, pupil radius ``radius_px`` (0 outside)."""
    c = (size - 1) / 2
    y, x = np.mgrid[0:size, 0:size] - c
    r = np.hypot(x, y) / radius_px
    th = np.arctan2(y, x)
    inside = r <= 1
    return np.stack([np.where(inside, zernike(j, r, th), 0.0) for j in range(first, first + n_modes)])
