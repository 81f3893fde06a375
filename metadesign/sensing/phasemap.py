"""As-fabricated phase and amplitude maps of a layout (a product a user can hold against a measured map).

For each pillar the as-fabricated complex transmission ``tn`` (library look-up of the perturbed widths,
normalised so that ``|tn|^2`` is the transmitted power fraction) is compared with the design phase of
its lens (Eq. 1 of the channel its supercell site belongs to).  The design leaves one constant phase per
polarisation free (the library's phase origin); it is estimated as the angle of
``sum tn exp(-i phi_design)`` over the aperture and removed, so the residual is the fabrication (and
discretisation) error alone.

* **window** (full resolution): ``cells x cells`` pillars from ``(ix0, iy0)``: phase ``angle(tn)``,
  amplitude ``|tn|``, the wrapped design phase and the residual, per polarisation.
* **whole aperture** (supercell-averaged): per polarisation and channel, the residual phasor
  ``tn exp(-i phi_design)`` averaged over blocks of ``bin x bin`` supercells: its angle is the residual
  phase at that resolution, its modulus the amplitude times the coherence within the block.

Conventions: arrays are ``[row = iy (+y), col = ix (+x)]``; phases in rad, fields ``exp(+i phi)``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..design.phase import cell_coordinates, lens_phase, wrap
from ..io import json_array, write_npz
from ..plotting import pyplot, save_figure
from ..validation import ValidationError
from .transmission import Perturbation, pillar_transmission

__all__ = ["phase_maps", "save_phase_maps", "plot_phase_maps", "PHASEMAP_FORMAT"]

PHASEMAP_FORMAT = "metadesign.phasemap/1"


def _design_rows(fab, r0: int, r1: int) -> np.ndarray:
    """(r1 - r0, n, 2) unwrapped design phase of every pillar site of rows r0:r1, both polarisations."""
    n, m = fab.n_cells, fab.supercell
    x = cell_coordinates(n, fab.period)
    y = x[r0:r1]
    out = np.empty((r1 - r0, n, 2))
    rows = np.arange(r0, r1)
    for p in range(2):
        for b in range(m):
            rr = np.nonzero(rows % m == b)[0]
            for a in range(m):
                out[np.ix_(rr, np.arange(a, n, m), [p])] = lens_phase(
                    x[a::m][None, :], y[rr][:, None], fab.channels[p][a + m * b], fab.wavelength)[..., None]
    return out


def phase_maps(fab, pert: Perturbation = Perturbation(), window: tuple[int, int, int] | None = None,
               bin_supercells: int | None = None, max_bins: int = 512, tile_rows: int = 512, progress=None) -> dict:
    """The maps (see the module docstring); ``window = (ix0, iy0, cells)`` (default: the central 64 x 64)."""
    n, m = fab.n_cells, fab.supercell
    if window is None:
        c = min(64, n)
        window = ((n - c) // 2, (n - c) // 2, c)
    ix0, iy0, cells = window
    if not (0 <= ix0 and 0 <= iy0 and cells >= 1 and ix0 + cells <= n and iy0 + cells <= n):
        raise ValidationError(f"--window {ix0} {iy0} {cells}: must lie inside the {n} x {n} pillar array")
    ns = n // m  # supercells per side (a partial last supercell is dropped from the binned maps)
    b = bin_supercells or max(1, -(-ns // max_bins))
    nb = -(-ns // b)
    acc = np.zeros((2, m * m, nb, nb), np.complex128)
    cnt = np.zeros((nb, nb))
    rng = np.random.default_rng(pert.seed)  # one stream over the rows, as the coarse pupil
    scale = np.float32(fab.tn_scale)
    win_t = np.zeros((cells, cells, 2), np.complex64)
    win_d = np.zeros((cells, cells, 2))
    tile = max(m, tile_rows // m * m)
    for r0 in range(0, ns * m, tile):
        r1 = min(ns * m, r0 + tile)
        t, _ = pillar_transmission(fab.layout.index_map, fab.layout.atom_widths_nm, fab.lib, pert, slice(r0, r1), rng,
                                   fab.fab_lib, fab.coupling)
        t = t * scale
        mask = fab.aperture_mask_rows(r0, r1)
        if mask is not None:
            t[~mask] = 0
        d = _design_rows(fab, r0, r1)
        demod = t[:, :ns * m] * np.exp(-1j * d[:, :ns * m]).astype(np.complex64)
        sy = (np.arange(r0, r1) // m) // b  # bin row of each pillar row
        for bb in range(m):
            for a in range(m):
                sub = demod[bb::m, a::m]  # (rows/m, ns, 2)
                rows_bin = sy[bb::m]
                colsum = np.add.reduceat(sub, np.arange(0, ns, b), axis=1)  # (rows/m, nb, 2)
                np.add.at(acc[:, a + m * bb], (slice(None), rows_bin), np.moveaxis(colsum, -1, 0))
        ones = np.ones((r1 - r0) // m)
        np.add.at(cnt, sy[::m], np.add.reduceat(np.ones((len(ones), ns)), np.arange(0, ns, b), axis=1))
        lo, hi = max(r0, iy0), min(r1, iy0 + cells)
        if lo < hi:
            win_t[lo - iy0:hi - iy0] = t[lo - r0:hi - r0, ix0:ix0 + cells]
            win_d[lo - iy0:hi - iy0] = d[lo - r0:hi - r0, ix0:ix0 + cells]
        if progress:
            progress(r1, ns * m)
    offset = np.angle(acc.sum(axis=(1, 2, 3)))  # per polarisation
    binned = acc / np.maximum(cnt, 1)
    resid_binned = np.angle(binned * np.exp(-1j * offset)[:, None, None, None]).astype(np.float32)
    resid_win = wrap(np.angle(win_t) - win_d - offset[None, None, :]).astype(np.float32)
    return {
        "window": {"ix0": ix0, "iy0": iy0, "cells": cells,
                   "phase": np.moveaxis(np.angle(win_t), -1, 0).astype(np.float32),
                   "amplitude": np.moveaxis(np.abs(win_t), -1, 0).astype(np.float32),
                   "design_phase": np.moveaxis(wrap(win_d + offset[None, None, :]), -1, 0).astype(np.float32),
                   "residual": np.moveaxis(resid_win, -1, 0)},
        "binned": {"supercells_per_bin": b, "residual": resid_binned,
                   "amplitude": np.abs(binned).astype(np.float32)},
        "offset_rad": offset.tolist(),
        "stats": _stats(resid_binned, np.abs(binned), resid_win, np.abs(win_t)),
    }


def _stats(res_b, amp_b, res_w, amp_w) -> dict:
    lit = amp_b > 0.05 * amp_b.max()
    out = {"binned_residual_rms_rad": [[float(np.sqrt(np.mean(res_b[p, k][lit[p, k]] ** 2))) if lit[p, k].any()
                                        else None for k in range(res_b.shape[1])] for p in range(2)],
           "window_residual_rms_rad": [float(np.sqrt(np.mean(res_w[..., p][amp_w[..., p] > 0] ** 2)))
                                       if (amp_w[..., p] > 0).any() else None for p in range(2)],
           "window_mean_power": [float(np.mean(amp_w[..., p] ** 2)) for p in range(2)]}
    return out


def save_phase_maps(path: str | Path, maps: dict, meta: dict) -> Path:
    """``.npz`` readable with ``np.load(allow_pickle=False)``: ``window_phase``, ``window_amplitude``,
    ``window_design_phase``, ``window_residual`` (2, cells, cells); ``binned_residual``, ``binned_amplitude``
    (2, 4, nb, nb); ``meta`` (JSON)."""
    w, b = maps["window"], maps["binned"]
    meta = {"format": PHASEMAP_FORMAT, "window": {k: w[k] for k in ("ix0", "iy0", "cells")},
            "supercells_per_bin": b["supercells_per_bin"], "offset_rad": maps["offset_rad"], "stats": maps["stats"],
            "conventions": "arrays [pol (0 = x), row = iy, col = ix]; binned [pol, channel k-1, bin row, bin col]; "
                           "rad; fields exp(+i phi); residual = as-fabricated - design - per-pol offset"} | meta
    write_npz(path, {"window_phase": w["phase"], "window_amplitude": w["amplitude"],
                     "window_design_phase": w["design_phase"], "window_residual": w["residual"],
                     "binned_residual": b["residual"], "binned_amplitude": b["amplitude"], "meta": json_array(meta)})
    return Path(path)


def plot_phase_maps(maps: dict, out: str | Path, title: str = "") -> Path:
    plt = pyplot()
    w, b = maps["window"], maps["binned"]
    fig, axs = plt.subplots(3, 4, figsize=(15, 11), constrained_layout=True)
    for p in range(2):
        for j, (img, lab, cmap, lim) in enumerate(((w["phase"][p], "as-fabricated phase", "twilight", np.pi),
                                                   (w["residual"][p], "residual vs design", "RdBu_r", None))):
            ax = axs[0, 2 * p + j]
            vmax = lim or max(1e-3, float(np.percentile(np.abs(img), 99)))
            h = ax.imshow(img, cmap=cmap, vmin=-vmax, vmax=vmax, origin="lower")
            ax.set_title(f"{'xy'[p]}-pol {lab}\nwindow ({w['ix0']}, {w['iy0']}) {w['cells']}^2 cells", fontsize=8)
            fig.colorbar(h, ax=ax, shrink=0.7, label="rad")
        for k in range(4):
            ax = axs[1 + p, k]
            img = np.where(b["amplitude"][p, k] > 0.05 * b["amplitude"].max(), b["residual"][p, k], np.nan)
            vmax = max(1e-3, float(np.nanpercentile(np.abs(img), 99))) if np.isfinite(img).any() else 1
            h = ax.imshow(img, cmap="RdBu_r", vmin=-vmax, vmax=vmax, origin="lower")
            rms = maps["stats"]["binned_residual_rms_rad"][p][k]
            ax.set_title(f"{'xy'[p]}-pol channel {k + 1}: residual, {b['supercells_per_bin']}^2-supercell bins"
                         + (f" (RMS {rms:.3f} rad)" if rms is not None else ""), fontsize=8)
            fig.colorbar(h, ax=ax, shrink=0.7, label="rad")
    if title:
        fig.suptitle(title)
    return save_figure(fig, out)
