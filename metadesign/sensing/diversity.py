"""The sensor's diversity as parameters (issue #33): each of the eight channels' phase on top of its
focusing lens, so that the diversity can be chosen for the reconstruction.

A channel ``c = 4 p + k - 1`` (polarisation ``p``, lens/quadrant ``k``) of the device as built has the
Eq. 1 lens of focal length ``f0[p, k]`` centred on its spot offset.  Its diversity is

    psi[p, k](x, y) = lens(x, y; f[p, k]) - lens(x, y; f0[p, k]) + sum_j a[p, k, j] Z_j(rho, theta)

with ``1 / f = 1 / f0 + 2 lambda w / R^2`` (``w``: the defocus added, in waves of sag at the aperture edge
``R``, so ``w = 0`` is the device as built) and ``Z_j`` Noll-indexed Zernike terms (unit RMS over the
clear aperture's inscribed disk).  The paper's design is the point ``w = 0, a = 0`` of the device laid out
with Table S1's focal lengths; the 2 x 2 interleave, polarisation split, aperture and camera stay.

The phase is applied to each channel's block-averaged field (``CoarsePupil.G[p, k]``) at the block
centres, like :func:`~metadesign.sensing.forward.quadrant_fields`'s refocus: exact at ``w = 0, a = 0`` and
valid while ``psi`` changes by much less than a radian across a block (:func:`block_phase_step` measures
it).  :class:`DiversityOperators` holds the numpy arrays; the torch module is
:class:`metadesign.sensing.twin_diversity.DiversityTwin`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..optics.zernike import zernike
from .forward import CoarsePupil, _nonparaxial
from .sensor import SensorSpec
from .twin import rebin_pupil, twin_operators

__all__ = ["DiversityOperators", "diversity_operators", "lens_table", "lens_delta", "defocus_to_power",
           "focal_to_defocus",
           "block_phase_step", "DEFAULT_MODES"]

#: the low-order terms a channel may learn beyond its defocus: astigmatism (5, 6), coma (7, 8),
#: trefoil (9, 10), spherical (11)
DEFAULT_MODES = (5, 6, 7, 8, 9, 10, 11)


def lens_table(channels) -> np.ndarray:
    """``(2, 4, 3)`` float64 ``[f, offset_x, offset_y]`` (m) of each polarisation's four lenses, from a
    layout's or dataset's provenance (``[{"pol": "x"|"y", "k": 1..4, "focal_length_m", "offset_x_m",
    "offset_y_m"}, ...]``) or a :class:`~metadesign.design.phase.SupercellSpec`-like object with
    ``channels_x`` / ``channels_y``."""
    out = np.full((2, 4, 3), np.nan)
    if hasattr(channels, "channels_x"):
        for p, chans in enumerate((channels.channels_x, channels.channels_y)):
            for k, ch in enumerate(chans):
                out[p, k] = (ch.focal_length, ch.offset_x, ch.offset_y)
    else:
        for ch in channels:
            p = {"x": 0, "y": 1}[ch["pol"]]
            out[p, int(ch["k"]) - 1] = (ch["focal_length_m"], ch["offset_x_m"], ch["offset_y_m"])
    if not np.isfinite(out).all():
        raise ValueError("lens table: expected four lenses per polarisation")
    return out


def defocus_to_power(waves, wavelength: float, radius: float):
    """Change of optical power ``1/f - 1/f0`` (1/m) of ``waves`` of sag at the aperture edge ``radius``
    (works on numpy arrays and torch tensors)."""
    return waves * (2.0 * wavelength / radius**2)


def focal_to_defocus(f, f0, wavelength: float, radius: float):
    """The inverse of :func:`defocus_to_power`: the waves that take focal length ``f0`` to ``f``."""
    return (1.0 / f - 1.0 / f0) * radius**2 / (2.0 * wavelength)


def lens_delta(r2, f0, f, k0: float):
    """``lens(f) - lens(f0)`` of Eq. 1 at squared distance ``r2`` from the lens axis, written without the
    cancellation of two ~300 rad phases: ``k0 r2 (f + s - f0 - s0) / ((f0 + s0)(f + s))``, ``s = sqrt(f^2 +
    r2)`` (numpy or torch, float64 advised)."""
    s0 = (f0 * f0 + r2) ** 0.5
    s = (f * f + r2) ** 0.5
    return k0 * r2 * (f + s - f0 - s0) / ((f0 + s0) * (f + s))


@dataclass
class DiversityOperators:
    """numpy arrays of the diversity twin (channel-resolved, unlike the summed ``K`` of
    :class:`~metadesign.sensing.twin.TwinOperators`)."""

    G: np.ndarray  # (2, 4, N, N) complex64: each channel's block field x metasurface mask
    P: np.ndarray  # (8, N, N) complex64: the non-paraxial factor of quadrant c's spot
    Ay: np.ndarray  # (8, R, N) complex64
    Ax: np.ndarray  # (8, N, Q) complex64
    w: np.ndarray  # (8, R, Q) float32
    Ry: np.ndarray  # (S, R) float32
    Rx: np.ndarray  # (S, Q) float32
    W: np.ndarray  # (N, A) float32: crop -> pupil grid
    r2: np.ndarray  # (2, 4, N, N) float64: squared distance of each block centre from each lens's axis
    Z: np.ndarray  # (J, N, N) float64: Zernike terms at the block centres
    modes: tuple[int, ...]  # Noll indices of Z
    f0: np.ndarray  # (2, 4) float64: the device's focal lengths
    wavelength: float
    radius: float  # clear-aperture radius (m): the Zernike unit disk and the defocus's reference
    pitch: float  # block pitch (m)
    inside: np.ndarray  # (N, N) bool: block centres inside the clear aperture's disk


def diversity_operators(cp: CoarsePupil, sensor: SensorSpec, lenses: np.ndarray,
                        crop: tuple[int, int, int, float, float] | None = None, rebin: int = 1,
                        samples: int | None = None, modes=DEFAULT_MODES) -> DiversityOperators:
    """Operators for the device of pupil ``cp`` (whose lenses are ``lenses``, :func:`lens_table`) seen by
    ``sensor``, fed from received crops (``crop`` as in :func:`~metadesign.sensing.twin.twin_operators`)."""
    base = twin_operators(cp, sensor, crop, rebin, samples)
    n_fine = cp.G.shape[-1]
    if crop is not None:
        u = (np.arange(n_fine) + 0.5) / n_fine - 0.5
        mask = (u[None, :] ** 2 + u[:, None] ** 2) <= 0.25
    else:
        mask = np.ones((n_fine, n_fine), bool)
    g = rebin_pupil(CoarsePupil(cp.G * mask, cp.X, cp.block, cp.period, cp.wavelength, cp.z, 0), rebin)
    X = g.X.astype(np.float64)
    k0 = 2 * np.pi / cp.wavelength
    P = np.stack([_nonparaxial(X, sensor.quadrant_centre(k), k0, cp.z) for _ in range(2) for k in range(1, 5)])
    r2 = np.empty((2, 4, X.size, X.size))
    for p in range(2):
        for k in range(4):
            r2[p, k] = (X[None, :] - lenses[p, k, 1]) ** 2 + (X[:, None] - lenses[p, k, 2]) ** 2
    # the layout's aperture: CoarsePupil.X[0] = -(n_cells - 1) p / 2 + (block - 1) p / 2
    n_cells = int(round(cp.block - 2 * cp.X[0] / cp.period))
    radius = 0.5 * n_cells * cp.period
    rho = np.hypot(X[None, :], X[:, None]) / radius
    th = np.arctan2(np.broadcast_to(X[:, None], rho.shape), np.broadcast_to(X[None, :], rho.shape))
    Z = np.stack([zernike(j, rho, th) for j in modes]) if modes else np.zeros((0,) + rho.shape)
    return DiversityOperators(g.G.astype(np.complex64), P.astype(np.complex64), base.Ay, base.Ax, base.w,
                              base.Ry, base.Rx, base.W, r2, Z, tuple(int(j) for j in modes),
                              lenses[..., 0].astype(np.float64), float(cp.wavelength), float(radius), g.pitch,
                              rho <= 1)


def block_phase_step(ops: DiversityOperators, psi: np.ndarray) -> float:
    """Largest change of a diversity phase ``psi`` (..., N, N) between neighbouring blocks (rad), inside the
    aperture: the block-centre sampling of :mod:`this model <metadesign.sensing.diversity>` holds while it
    is well below 1."""
    ins = ops.inside
    dx = np.abs(np.diff(psi, axis=-1))[..., ins[:, 1:] & ins[:, :-1]]
    dy = np.abs(np.diff(psi, axis=-2))[..., ins[1:, :] & ins[:-1, :]]
    return float(max(dx.max(initial=0.0), dy.max(initial=0.0)))
