"""A device under a forward model too costly to run on every supercell: the cheap model everywhere, the
costly one's correction estimated from a random sample of supercells, with error bars.

The field on the sensor is linear in the pillars' transmissions, so a device under model B is the device
under model A plus the field of the corrections ``delta_s = t_B(s) - t_A(s)`` summed over its supercells.
Drawing ``m`` supercells uniformly (with replacement) from the ``N`` the device has and giving each the
weight ``N / m`` estimates that sum without bias (Hansen-Hurwitz).  Intensities are quadratic, so one
sample's ``|U_A + dU|^2`` is biased up by the sample's noise power; ``R`` independent replicates give the
unbiased U-statistic ``(|sum_r U_r|^2 - sum_r |U_r|^2) / (R (R - 1))`` per focal point
(:class:`SampledIntensity`), and the replicates, left out one at a time, the jackknife's standard error of
any metric computed from it (:func:`sampled_spot_metrics`).

What it can and cannot measure: near a focus the device's light adds up coherently over ~N supercells and
a sample's noise over ~m, so the spot's power, peak and best focus come out to ~``rms|delta| /
(|t| sqrt(m))``; the light scattered over a whole quadrant (its stray fraction, and the Strehl's
normalisation by the quadrant's power) is estimated without bias but with a wider error bar (paper
device, 4,000 of 12.75 M supercells: 0.8 % on the spot's power, 0.5 % on the stray fraction)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..conventions import centered
from ..determinism import single_thread_blas
from ..optics.propagation import cexp
from .forward import CoarsePupil, block_centres, pupil_tiles, quadrant_transform
from .model import spot_metrics
from .sensor import quadrant_slices
from .transmission import Perturbation, perturb_widths

__all__ = [
    "SampledIntensity",
    "delta_pupil",
    "device_widths_rows",
    "eligible_supercells",
    "jackknife_bias",
    "jackknife_se",
    "sampled_frames",
    "sampled_spot_metrics",
    "supercell_widths",
]

_TILE_ROWS = 1024  # pillar rows read at a time (even: tiles start on a supercell row)


def _tiles(fab):
    n = fab.n_cells
    for r0 in range(0, n - n % 2, _TILE_ROWS):
        yield r0, min(r0 + _TILE_ROWS, n - n % 2)


def eligible_supercells(fab) -> np.ndarray:
    """Flat ids ``I * (n // 2) + J`` of the device's complete 2 x 2 supercells (rows 2I, 2I+1; columns 2J,
    2J+1): four pillars, all inside the clear aperture (the ones a supercell coupling model changes), read
    in row tiles (a layout of any size)."""
    if fab.supercell != 2:
        raise ValueError("sampled supercells need the 2 x 2 interleave")
    C2 = fab.n_cells // 2
    out = []
    for r0, r1 in _tiles(fab):
        has = np.asarray(fab.layout.index_map[r0:r1])[:, :2 * C2] >= 0
        mask = fab.aperture_mask_rows(r0, r1)
        if mask is not None:
            has &= mask[:, :2 * C2]
        full = has.reshape((r1 - r0) // 2, 2, C2, 2).all((1, 3))
        out.append(np.flatnonzero(full.ravel()) + (r0 // 2) * C2)
    return np.concatenate(out).astype(np.int64) if out else np.zeros(0, np.int64)


def device_widths_rows(fab, pupil_grid: int, pert: Perturbation = Perturbation()):
    """``(r0, r1, widths (r1 - r0, n, 2) m, has (r1 - r0, n) bool)`` per row tile: the perturbed widths of
    every pillar, drawn from the same random stream, tile by tile in the same order, as
    :meth:`AsFabricated.pupil` draws them on a grid of ``pupil_grid`` (a jittered device is one device in
    the pupil and here: test); empty cells have width 0."""
    if pert.has_fab_axes:
        raise ValueError("device_widths_rows: widths only (height and sidewall perturbations go elsewhere)")
    rng = np.random.default_rng(pert.seed)
    w = np.asarray(fab.layout.atom_widths_nm, np.float64) * 1e-9
    for _, _, r0, r1 in pupil_tiles(fab.n_cells, fab.pupil_block(pupil_grid)):
        im = np.asarray(fab.layout.index_map[r0:r1])
        has = im >= 0
        k = np.where(has, im, 0)
        wx, wy = perturb_widths(w[k, 0], w[k, 1], pert, rng)  # the draw of the pupil's transmission rows
        yield r0, r1, np.where(has[..., None], np.stack([wx, wy], -1), 0.0), has


def supercell_widths(fab, ids: np.ndarray, pert: Perturbation = Perturbation(),
                     pupil_grid: int | None = None) -> np.ndarray:
    """(n, 2, 2, 2) widths (m; ``[supercell, row, column, (wx, wy)]``) of supercells ``ids`` as made with
    ``pert`` (nominal, biased, rounded, jittered): the pillars of the device :meth:`AsFabricated.pupil`
    makes on a grid of ``pupil_grid`` (:func:`device_widths_rows`; needed with jitter, whose draws follow
    the pupil's row tiles; without it any tiling gives the same widths)."""
    if pert.jitter and pupil_grid is None:
        raise ValueError("supercell_widths: a jittered device's widths depend on its pupil grid (tiles)")
    ids = np.asarray(ids, np.int64)
    C2 = fab.n_cells // 2
    I, J = ids // C2, ids % C2
    out = np.full((len(ids), 2, 2, 2), np.nan)
    for r0, r1, w, has in device_widths_rows(fab, pupil_grid or fab.n_cells // 2, pert):
        sel = np.flatnonzero((2 * I >= r0) & (2 * I + 1 < r1))
        for r in range(2):
            for c in range(2):
                rows, cols = 2 * I[sel] + r - r0, 2 * J[sel] + c
                if not has[rows, cols].all():
                    raise ValueError("supercell_widths: a supercell without its four pillars")
                out[sel, r, c] = w[rows, cols]
    return out


def delta_pupil(fab, z: float, pupil_grid: int, ids: np.ndarray, delta: np.ndarray, weight: float) -> CoarsePupil:
    """The coarse pupil of corrections only: ``weight * delta[s]`` (n, 2 pol) complex added to each of the
    four pillars of supercell ``ids[s]`` (so the supercell's ``t``, the mean of its four, moves by that),
    or ``delta`` (n, 2, 2, 2 pol) one per pillar (``[s, row, column]``), nothing elsewhere; each pillar summed into its block with the demodulating chirp and ``tn`` scale, as
    :func:`~metadesign.sensing.forward.coarse_pupil` sums a device (so it adds to a device's pupil), but
    touching only the sampled pillars (not a pass over the whole device per replicate)."""
    ids = np.asarray(ids, np.int64)
    n, p, B = fab.n_cells, fab.period, fab.pupil_block(pupil_grid)
    nb = int(np.ceil(n / B))
    I, J = ids // (n // 2), ids % (n // 2)
    d = np.asarray(delta, np.complex128) * (weight * fab.tn_scale)
    x0, k0 = centered(n, p)[0], 2 * np.pi / fab.wavelength
    G = np.zeros((2, 4, nb, nb), np.complex128)
    for b in range(2):
        for a in range(2):
            row, col = 2 * I + b, 2 * J + a
            w = (d[:, b, a] if d.ndim == 4 else d) * cexp(k0 * ((x0 + row * p) ** 2 + (x0 + col * p) ** 2)
                                                           / (2 * z))[:, None]
            for pol in range(2):
                np.add.at(G[pol, a + 2 * b], (row // B, col // B), w[:, pol])
    G /= B * B
    return CoarsePupil(G.astype(np.complex64), block_centres(n, p, B), B, p, fab.wavelength, z, 0)


@dataclass
class SampledIntensity:
    """Focal intensity of ``cp`` plus an estimated correction given by ``R >= 2`` independent replicate
    pupils (:func:`delta_pupil`): the U-statistic over the replicates in ``active`` (default all), unbiased
    for the intensity of ``cp`` plus the true correction.  Called as ``spot_metrics``' ``intensity``; the
    complex transforms are cached, so switching ``active`` (the jackknife) only recombines them."""

    cp: CoarsePupil
    deltas: list
    active: tuple = ()
    _cache: dict = field(default_factory=dict, repr=False)

    def __post_init__(self):
        if len(self.deltas) < 2:
            raise ValueError("a sampled intensity needs at least two replicates")
        self.active = tuple(self.active) or tuple(range(len(self.deltas)))

    def __call__(self, pol, xo, yo, centre, z=None):
        key = (pol, np.asarray(xo).tobytes(), np.asarray(yo).tobytes(), tuple(centre), z)
        if key not in self._cache:
            u0, comp, scale = quadrant_transform(self.cp, pol, xo, yo, centre, z=z)
            du = np.stack([quadrant_transform(d, pol, xo, yo, centre, z=z)[0] for d in self.deltas])
            self._cache[key] = (u0.astype(np.complex128), du.astype(np.complex128), comp, scale)
        u0, du, comp, scale = self._cache[key]
        return _u_statistic(u0, du, self.active) / comp.astype(np.float64) ** 2 * scale


def _u_statistic(u0: np.ndarray, du: np.ndarray, active) -> np.ndarray:
    """``|u0 + true correction|^2`` estimated without bias from the replicates ``du[active]``: the mean of
    ``Re conj(U_r) U_s`` over ordered pairs ``r != s`` of ``U_r = u0 + du_r``."""
    U = u0[None] + du[list(active)]
    R = len(active)
    return (np.abs(U.sum(0)) ** 2 - (np.abs(U) ** 2).sum(0)) / (R * (R - 1))


def sampled_frames(cp: CoarsePupil, deltas: list, sensor, e_in: np.ndarray | None = None):
    """``(frames (2, H, W), leave_one_out (R, 2, H, W))`` float32: the sensor frames
    (:func:`~metadesign.sensing.forward.sensor_frames`, with the received field ``e_in``) of ``cp`` plus the
    sampled correction, by the U-statistic over the replicate pupils ``deltas``, and the same with each
    replicate left out (the jackknife of anything computed from the frames, a reconstruction's NPiB
    included).  Unbiased per pixel; a pixel's estimate can dip below zero where the light is faint."""
    R = len(deltas)
    if R < 3:
        raise ValueError("sampled frames need at least three replicates (the jackknife)")
    X, Y = sensor.coords()
    area = sensor.focal_pitch**2
    frames = np.zeros((2, sensor.height_px, sensor.width_px), np.float32)
    loo = np.zeros((R, *frames.shape), np.float32)
    with single_thread_blas():
        for p in range(2):
            for k in range(1, 5):
                r, c = quadrant_slices(sensor, k)
                centre = sensor.quadrant_centre(k)
                u0, comp, scale = quadrant_transform(cp, p, X[c], Y[r], centre, e_in)
                du = np.stack([quadrant_transform(d, p, X[c], Y[r], centre, e_in)[0] for d in deltas])
                U = u0.astype(np.complex128)[None] + du.astype(np.complex128)
                norm = area * scale / comp.astype(np.float64) ** 2
                S, Q = U.sum(0), (np.abs(U) ** 2).sum(0)  # every subset's U-statistic from these two sums
                frames[p, r, c] = (np.abs(S) ** 2 - Q) / (R * (R - 1)) * norm
                loo[:, p, r, c] = (np.abs(S - U) ** 2 - (Q - np.abs(U) ** 2)) / ((R - 1) * (R - 2)) * norm
    return frames, loo


def jackknife_bias(estimate: float, leave_one_out) -> float:
    """The jackknife's estimate of an estimate's bias from its leave-one-replicate-out values (subtract it
    to correct)."""
    v = np.asarray(leave_one_out, np.float64)
    return float((len(v) - 1) * (v.mean() - estimate))


def jackknife_se(leave_one_out) -> float:
    """Jackknife standard error of an estimate from its leave-one-replicate-out values."""
    v = np.asarray(leave_one_out, np.float64)
    R = len(v)
    return float(np.sqrt((R - 1) / R * np.sum((v - v.mean()) ** 2)))


def sampled_spot_metrics(cp: CoarsePupil, deltas: list, sensor, fab, **kw):
    """``(rows, leave_one_out)``: :func:`~metadesign.sensing.model.spot_metrics` of ``cp`` plus the sampled
    correction, and the same with each replicate left out in turn (for :func:`jackknife_se`)."""
    if len(deltas) < 3:
        raise ValueError("the jackknife needs at least three replicates")
    si = SampledIntensity(cp, deltas)
    rows = spot_metrics(cp, sensor, fab, intensity=si, **kw)
    loo = []
    for r in range(len(deltas)):
        si.active = tuple(i for i in range(len(deltas)) if i != r)
        loo.append(spot_metrics(cp, sensor, fab, intensity=si, **kw))
    si.active = tuple(range(len(deltas)))
    return rows, loo
