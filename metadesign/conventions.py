"""The conventions of metadesign, stated once (the README's "Conventions" section
says the same in prose), and the two grid helpers every module uses.

Units
    SI inside the physics code (m, rad, s).  Recipe keys and CLI options carry
    their unit in the name (``period_um``, ``--bias-nm``) and are converted once,
    at load.

Time and phase
    ``exp(-i omega t)``; a field is ``|E| exp(+i phi)``; a plane wave towards +z
    is ``exp(+i k z)``; a converging lens is Eq. 1,
    ``phi(r) = (2 pi / lambda) (f - sqrt(f^2 + r^2)) <= 0``.  A wavefront
    advanced by ``+W`` (metres of optical path) multiplies the field by
    ``exp(+i k W)``.

Grids (two centrings, on purpose)
    * **cell-centred** (:func:`centered`): sample ``i`` of ``n`` at
      ``(i - (n - 1) / 2) pitch``.  Metasurface cells (``[iy, ix]``, cell
      ``(ix, iy)`` at ``x = (ix - (n-1)/2) p``), sensor pixels, coarse-pupil
      blocks, propagation grids of :mod:`metadesign.optics`.  Symmetric about 0.
    * **FFT-centred** (:func:`fft_centered`): sample ``i`` at ``(i - n / 2) dx``.
      The turbulence grid (screens, split step, received field); the origin is
      sample ``n / 2``, as ``fftshift`` puts it.

Arrays
    Maps are ``[row, col] = [y, x]``; rows run along +y.  Unit-cell width
    arrays are ``[i_wx, i_wy]``; Jones matrices ``[out, in]`` with 0 = x, 1 = y.

Channels
    Polarisations ``x`` (paper: TE) and ``y`` (TM).  Lenses ``k = 1..4`` in the
    CLI, files and reports (cell ``(ix, iy)`` belongs to
    ``k = 1 + (ix mod 2) + 2 (iy mod 2)``; PSF of k in sensor quadrant k, QI..QIV
    in reading order of the frame); 0-based ``k - 1`` inside arrays.  The PSF
    tensor is ``8 x S x S``: ``[x k=1..4, y k=1..4]``.
"""

from __future__ import annotations

import numpy as np

__all__ = ["centered", "fft_centered"]


def centered(n: int, pitch: float) -> np.ndarray:
    """Cell-centred coordinates ``(i - (n - 1) / 2) pitch``, ``i = 0..n-1``."""
    return (np.arange(n) - (n - 1) / 2) * pitch


def fft_centered(n: int, dx: float) -> np.ndarray:
    """FFT-centred coordinates ``(i - n / 2) dx``, ``i = 0..n-1`` (origin at sample n/2)."""
    return (np.arange(n) - n / 2) * dx
