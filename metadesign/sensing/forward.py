"""From pillars to the 8 PSFs: the fast coarse-pupil path, the full-resolution
chunked path and the angular-spectrum reference.

Physics.  Each polarisation's field leaving the metasurface is the pillar
transmission ``tn = t sqrt(n_air / n_sub)`` (so ``|tn|^2 = T0``) times the
incident field.  Only spatial frequencies ``|f| < 1/lambda`` propagate; the
interleaved supercell's orders (period 1.4 um < 1550 nm) are evanescent, so
the light reaching the sensor is the supercell-averaged, band-limited field.

Fast path.  The Fresnel integral to a sensor point ``x2`` is the Fourier
transform, at ``f = x2 / (lambda z)``, of ``u(x1) exp(i k |x1|^2 / 2z)``.  For
light that lands on the sensor that demodulated field is slowly varying, so
it is represented exactly on a coarse pupil grid of ``B x B``-cell blocks by
its block averages (the block average multiplies the spectrum by
``sinc(f_x P) sinc(f_y P)``, ``P = B p``, which is divided out).  Block sums
are separable einsums over the pillar map, done once per design and distance
in row tiles (bounded memory).  Each sensor quadrant is then a matrix Fourier
transform of ``G(X) E_in(X)``; the non-paraxial part of the kernel,
``exp(i k [sqrt(z^2 + |c - x1|^2) - z - |c - x1|^2 / 2z])`` at the quadrant
centre ``c``, is applied on the coarse grid.  Per-channel pupils (one
sub-lattice at a time) give crosstalk and per-channel metrics.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

from .. import jit
from ..conventions import centered
from ..determinism import single_thread_blas
from ..optics.propagation import angular_spectrum, cexp, check_asm_sampling, mft
from .sensor import SensorSpec, quadrant_slices

__all__ = ["CoarsePupil", "coarse_pupil", "block_centres", "pupil_tiles", "quadrant_fields", "quadrant_transform", "sensor_frames",
           "full_resolution_frames", "asm_reference_intensity", "block_size_for"]


@dataclass
class CoarsePupil:
    """Block-averaged demodulated pupil fields.

    ``G[p, k]``: polarisation p (0 = x, 1 = y), channel k (0..m*m-1; the sum
    over k is the full field) on a ``N x N`` grid of blocks of ``B x B`` cells.
    """

    G: np.ndarray  # (2, m*m, N, N) complex64
    X: np.ndarray  # block-centre coordinates (m), both axes
    block: int  # B, cells per block side
    period: float
    wavelength: float
    z: float
    n_clamped: int  # pillars outside the library range (clamped)

    @property
    def pitch(self) -> float:
        return self.block * self.period


def block_size_for(n_cells: int, pupil_n: int, m: int) -> int:
    """Smallest multiple of the supercell ``m`` giving at most ``pupil_n`` blocks."""
    b = max(1, int(np.ceil(n_cells / pupil_n)))
    return int(np.ceil(b / m) * m)


#: transmission bytes per row tile of :func:`coarse_pupil` (the default tile: 16 block rows up to this)
TILE_BYTES = 1 << 28


def pupil_tiles(n_cells: int, block: int, tile_blocks: int | None = None,
                block_rows: tuple[int, int] | None = None):
    """``(B0, B1, r0, r1)`` per row tile, in the order :func:`coarse_pupil` asks for the pillar rows
    ``r0:r1`` (block rows ``B0:B1``): whoever replays a per-tile random stream (a jittered device's pillars)
    walks the same tiles."""
    nb = int(np.ceil(n_cells / block))
    first, last = block_rows if block_rows is not None else (0, nb)
    if tile_blocks is None:
        tile_blocks = int(max(1, min(16, TILE_BYTES // (block * nb * block * 2 * 8))))
    for B0 in range(first, last, tile_blocks):
        B1 = min(last, B0 + tile_blocks)
        yield B0, B1, B0 * block, min(n_cells, B1 * block)


def coarse_pupil(transmission_rows: Callable[[int, int], np.ndarray], n_cells: int, period: float,
                 wavelength: float, z: float, block: int, m: int = 2, tn_scale: float = 1.0,
                 tile_blocks: int | None = None, progress: Callable[[int, int], None] | None = None,
                 block_rows: tuple[int, int] | None = None) -> CoarsePupil:
    """Block-average ``tn * exp(i k |x|^2 / 2z)`` per polarisation and channel.

    ``transmission_rows(r0, r1)`` returns the pillar transmission of rows
    ``r0:r1`` as ``(r1 - r0, n_cells, 2)`` complex (index ``[iy, ix, pol]``)
    and the number of clamped pillars.  Rows are asked for ``tile_blocks`` block rows at a time (default:
    at most 16, and at most :data:`TILE_BYTES` of transmission: bounded memory at any aperture, 10 cm
    included; the sums are per block, so the tiling does not change the result).  ``block_rows = (B0, B1)``:
    only those block rows, and the returned ``G`` holds only them (``G[..., B0:B1, :]`` of the whole): a
    worker's share of a parallel pupil, in the memory of its share.
    """
    if block % m:
        raise ValueError(f"block {block} must be a multiple of the supercell {m}")
    k0 = 2 * np.pi / wavelength
    nb = int(np.ceil(n_cells / block))
    npad = nb * block
    x = centered(n_cells, period)[0] + np.arange(npad) * period  # cell-centred, padded past the aperture
    chirp = cexp(k0 * x**2 / (2 * z)).astype(np.complex64)
    chirp[n_cells:] = 0  # outside the aperture: no light
    first, last = block_rows if block_rows is not None else (0, nb)
    G = np.zeros((2, m * m, last - first, nb), np.complex64)
    s = block // m
    clamped = 0
    compiled = jit.enabled()
    for B0, B1, r0, r1 in pupil_tiles(n_cells, block, tile_blocks, block_rows):
        tt, c = transmission_rows(r0, r1)
        clamped += c
        cy = chirp[r0:B1 * block]
        if compiled:  # one pass over the tile, no padded copy: the twin's sums in another order (float32)
            _block_sums(np.ascontiguousarray(tt, np.complex64), np.float32(tn_scale), cy, chirp, block, m,
                        G[:, :, B0 - first:B1 - first])
        else:
            t = np.zeros((B1 * block - r0, npad, 2), np.complex64)
            t[: r1 - r0, :n_cells] = tt * np.float32(tn_scale)
            for b in range(m):
                for a in range(m):
                    sub = t[b::m, a::m]  # (rows/m, npad/m, 2)
                    sy = cy[b::m].reshape(B1 - B0, s)
                    sx = chirp[a::m].reshape(nb, s)
                    sub = sub.reshape(B1 - B0, s, nb, s, 2)
                    G[:, a + m * b, B0 - first:B1 - first] = np.einsum("IiJjp,Ii,Jj->pIJ", sub, sy, sx,
                                                                       optimize=True)
        if progress:
            progress(B1 - first, last - first)
    G /= np.float32(block * block)
    return CoarsePupil(G, block_centres(n_cells, period, block), block, period, wavelength, z, clamped)


def block_centres(n_cells: int, period: float, block: int) -> np.ndarray:
    """Coordinates (m) of the coarse pupil's block centres, both axes."""
    nb = int(np.ceil(n_cells / block))
    return centered(n_cells, period)[0] + (np.arange(nb) * block + (block - 1) / 2) * period


@jit.njit
def _block_sums(t, scale, cy, cx, block, m, G):
    """``G[p, a + m b, I, J] = sum tn * cy * cx`` over the pillars of block ``(I, J)`` on sub-lattice
    ``(b, a)`` (``t``: the tile's rows, ``G``: its block rows), each block summed in complex128 and stored
    once: the compiled twin of :func:`coarse_pupil`'s einsum (float32 rounding apart)."""
    R, C = t.shape[0], t.shape[1]
    nbr, nb = G.shape[2], G.shape[3]
    acc = np.zeros((2, m * m, nb), np.complex128)
    for I in range(nbr):
        acc[:] = 0
        for i in range(block):
            r = I * block + i
            if r >= R:
                break
            b = r % m
            wy = complex(cy[r])
            a, J, jj = 0, 0, 0
            for c in range(C):
                w = wy * complex(cx[c])
                k = a + m * b
                acc[0, k, J] += complex(t[r, c, 0]) * w
                acc[1, k, J] += complex(t[r, c, 1]) * w
                a += 1
                if a == m:
                    a = 0
                jj += 1
                if jj == block:
                    jj = 0
                    J += 1
        for p in range(2):
            for k in range(m * m):
                for J in range(nb):
                    G[p, k, I, J] = acc[p, k, J] * scale


def _nonparaxial(X: np.ndarray, c: tuple[float, float], k0: float, z: float) -> np.ndarray:
    dx2 = (c[0] - X[None, :]) ** 2
    dy2 = (c[1] - X[:, None]) ** 2
    r2 = dx2 + dy2
    # sqrt(z^2 + r2) - z - r2/2z without cancellation
    s = np.sqrt(z * z + r2)
    d = r2 / (s + z) - r2 / (2 * z)
    return cexp(k0 * d)


def quadrant_transform(cp: CoarsePupil, pol: int, xo: np.ndarray, yo: np.ndarray, centre: tuple[float, float],
                       e_in: np.ndarray | None = None, channels=None, z: float | None = None):
    """``(U, comp, scale)``: the complex focal-plane transform of the coarse pupil on ``xo x yo``, linear in
    ``cp.G``, with intensity ``|U|^2 / comp^2 * scale`` (:func:`quadrant_fields`, which documents the
    arguments).  Linear quantities (a sum of pupils, a sampled correction) combine here, before the square."""
    k0 = 2 * np.pi / cp.wavelength
    z = cp.z if z is None else z
    g = cp.G[pol].sum(axis=0) if channels is None else cp.G[pol, list(channels)].sum(axis=0)
    if e_in is not None:
        g = g * e_in.astype(np.complex64)
    if z != cp.z:
        r2 = cp.X[None, :] ** 2 + cp.X[:, None] ** 2
        g = g * cexp(k0 * r2 * (1 / z - 1 / cp.z) / 2)
    g = g * _nonparaxial(cp.X, centre, k0, z)
    fx, fy = xo / (cp.wavelength * z), yo / (cp.wavelength * z)
    U = mft(g, cp.X, cp.X, fx, fy)
    comp = (np.sinc(fy * cp.pitch)[:, None] * np.sinc(fx * cp.pitch)[None, :]).astype(np.float32)
    scale = (cp.pitch**2 / (cp.wavelength * z)) ** 2
    return U, comp, scale


def quadrant_fields(cp: CoarsePupil, pol: int, xo: np.ndarray, yo: np.ndarray, centre: tuple[float, float],
                    e_in: np.ndarray | None = None, channels=None, z: float | None = None) -> np.ndarray:
    """Focal-plane intensity (W/m^2 for unit incident intensity) on the grid
    ``xo x yo`` (``[y, x]``) from the coarse pupil; ``channels`` selects
    sub-lattices (default: all).  ``z`` other than the pupil's refocuses by
    the smooth factor ``exp(i k |X|^2 (1/z - 1/z0) / 2)`` on the coarse grid
    (valid for a few mm around z0 at f/10: < 0.02 rad per block)."""
    U, comp, scale = quadrant_transform(cp, pol, xo, yo, centre, e_in, channels, z)
    return (np.abs(U) ** 2 / comp**2 * scale).astype(np.float32)


def sensor_frames(cp: CoarsePupil, sensor: SensorSpec, e_in: np.ndarray | None = None,
                  channels: dict | None = None) -> np.ndarray:
    """(2, H, W) sensor frames (power per pixel, unit incident intensity).

    Each quadrant is evaluated with its own non-paraxial correction; light
    from all channels of a polarisation lands in every quadrant (crosstalk
    included) unless ``channels[(pol, k)]`` restricts the sub-lattices."""
    X, Y = sensor.coords()
    frames = np.zeros((2, sensor.height_px, sensor.width_px), np.float32)
    area = sensor.focal_pitch**2
    with single_thread_blas():  # the same bytes in every process (see metadesign.determinism)
        _fill_frames(frames, cp, sensor, X, Y, area, e_in, channels)
    return frames


def _fill_frames(frames, cp, sensor, X, Y, area, e_in, channels) -> None:
    for p in range(2):
        for k in range(1, 5):
            r, c = quadrant_slices(sensor, k)
            ch = None if channels is None else channels.get((p, k))
            frames[p, r, c] = quadrant_fields(cp, p, X[c], Y[r], sensor.quadrant_centre(k), e_in, ch) * area


def full_resolution_frames(transmission_rows, n_cells: int, period: float, wavelength: float,
                           sensor: SensorSpec, tn_scale: float = 1.0, tile_rows: int = 256,
                           window: int | None = None, progress=None) -> tuple[np.ndarray, int]:
    """Reference at pillar resolution, no block averaging: the Fresnel
    integral (with the same per-quadrant non-paraxial correction) summed over
    row tiles of the full pillar map (complex64, bounded memory).

    ``window`` restricts each quadrant to its central ``window x window``
    pixels (others left at 0) to bound the cost at paper scale."""
    k0 = 2 * np.pi / wavelength
    z = sensor.distance
    X, Y = sensor.coords()
    x = centered(n_cells, period)
    chirp = cexp(k0 * x**2 / (2 * z))
    frames = np.zeros((2, sensor.height_px, sensor.width_px), np.float32)
    sel = []
    for k in range(1, 5):
        r, c = quadrant_slices(sensor, k)
        rr, cc = np.arange(sensor.height_px)[r], np.arange(sensor.width_px)[c]
        if window:
            rr = rr[(len(rr) - window) // 2:(len(rr) + window) // 2]
            cc = cc[(len(cc) - window) // 2:(len(cc) + window) // 2]
        sel.append((k, rr, cc))
    acc = {(p, k): np.zeros((len(rr), len(cc)), np.complex64) for p in range(2) for k, rr, cc in sel}
    Ax = {k: cexp(-2 * np.pi * np.outer(x, X[cc] / (wavelength * z))) for k, rr, cc in sel}
    clamped = 0
    for r0 in range(0, n_cells, tile_rows):
        r1 = min(n_cells, r0 + tile_rows)
        t, c = transmission_rows(r0, r1)
        clamped += c
        base = t * (chirp[r0:r1, None, None] * chirp[None, :, None] * np.complex64(tn_scale))
        yy = x[r0:r1]
        for k, rr, cc in sel:
            cen = sensor.quadrant_centre(k)
            r2 = (cen[0] - x[None, :]) ** 2 + (cen[1] - yy[:, None]) ** 2
            s = np.sqrt(z * z + r2)
            corr = cexp(k0 * (r2 / (s + z) - r2 / (2 * z)))
            Ay = cexp(-2 * np.pi * np.outer(Y[rr] / (wavelength * z), yy))
            for p in range(2):
                acc[(p, k)] += Ay @ ((base[..., p] * corr) @ Ax[k])
        if progress:
            progress(r1, n_cells)
    scale = (period**2 / (wavelength * z)) ** 2 * sensor.focal_pitch**2
    for (p, k), U in acc.items():
        _, rr, cc = sel[k - 1]
        frames[p][np.ix_(rr, cc)] = np.abs(U) ** 2 * scale
    return frames, clamped


def asm_reference_intensity(tn_map: np.ndarray, period: float, wavelength: float, z: float,
                            pad_to: int) -> tuple[np.ndarray, np.ndarray]:
    """Band-limited angular spectrum at pillar pitch: the field ``tn_map``
    (``[iy, ix]``, the aperture) zero-padded to ``pad_to`` and propagated by z.
    Returns (intensity ``[y, x]``, coordinates of the padded grid)."""
    n = tn_map.shape[0]
    aperture = n * period
    check_asm_sampling(pad_to, period, wavelength, z, aperture, min(0.999, aperture / (2 * z)))
    u = np.zeros((pad_to, pad_to), np.complex64)
    s = (pad_to - n) // 2
    u[s:s + n, s:s + n] = tn_map
    U = angular_spectrum(u, period, wavelength, z)
    coords = centered(n, period)[0] + (np.arange(pad_to) - s) * period
    return (np.abs(U) ** 2).astype(np.float32), coords
