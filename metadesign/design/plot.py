"""Figure S2 equivalent: coverage with selected atoms, atom widths,
discretized phase maps and width maps (a central crop for large designs)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..conventions import centered
from ..library.store import UnitCellLibrary
from ..plotting import pyplot, save_figure
from .build import discretized_phase
from .store import Design

__all__ = ["plot_design"]


def plot_design(d: Design, out: str | Path, lib: UnitCellLibrary | None = None, crop: int = 400) -> Path:
    plt = pyplot()
    fig, ax = plt.subplots(2, 4, figsize=(18, 8.6), constrained_layout=True)
    a = d.atoms
    th = d.meta["discretizer"]["threshold"]
    # (a) coverage
    if lib is not None:
        keep = (lib.T0[..., 0] >= th) & (lib.T0[..., 1] >= th)
        ax[0, 0].scatter(lib.phase_x[keep], lib.phase_y[keep], s=2, c="tab:blue", label=f"library, T0 >= {th:g}")
    ax[0, 0].scatter(a.phase[:, 0], a.phase[:, 1], s=28, facecolors="none", edgecolors="tab:red",
                     label=f"selected atoms ({len(a)})")
    bins = d.meta["discretizer"]["bins"]
    for e in np.linspace(-np.pi, np.pi, bins + 1):
        ax[0, 0].axhline(e, color="0.85", lw=0.4, zorder=0)
        ax[0, 0].axvline(e, color="0.85", lw=0.4, zorder=0)
    ax[0, 0].set(xlim=(-np.pi, np.pi), ylim=(-np.pi, np.pi), xlabel="phase x-pol (TE) [rad]",
                 ylabel="phase y-pol (TM) [rad]", title="(a) phase coverage", aspect="equal")
    ax[0, 0].legend(loc="upper left", fontsize=7)
    # (b) width combinations
    sc = ax[1, 0].scatter(a.wx * 1e6, a.wy * 1e6, c=a.T0.min(axis=1), cmap="viridis", vmin=th, vmax=1, s=18)
    fig.colorbar(sc, ax=ax[1, 0], label="min(T0_x, T0_y)", shrink=0.8)
    ax[1, 0].set(xlabel="w_x [um]", ylabel="w_y [um]", title="(b) atom widths", aspect="equal")
    # (c, d) maps on a central crop
    n = d.spec.n_cells
    c = min(n, crop)
    s = (n - c) // 2
    s -= s % d.spec.supercell
    # one supercell lens: the m x m lenses of a polarisation interleave cell by cell, so a map of every
    # cell shows m^2 phases side by side (a moire once downsampled); every m-th cell is one lens (QI)
    m_sc = d.spec.supercell
    im = d.index_map[s:s + c:m_sc, s:s + c:m_sc]
    p = d.spec.period * 1e3
    lo = centered(n, p)[s] - p / 2  # lower edge of the crop
    ext = [lo, lo + c * p, lo, lo + c * p]
    crop_note = "" if c == n else f", central {c}x{c} of {n}x{n} cells"
    k = d.atom_indices()[s:s + c:m_sc, s:s + c:m_sc]
    wx_map = np.append(a.wx * 1e6, np.nan)[k]
    wy_map = np.append(a.wy * 1e6, np.nan)[k]
    lens = f" (lens QI: 1 cell in {m_sc}^2)" if m_sc > 1 else ""
    panels = [
        (discretized_phase(im, a, 0, d.empty), "twilight", (-np.pi, np.pi), f"(c) phase, x-pol [rad]{lens}"),
        (discretized_phase(im, a, 1, d.empty), "twilight", (-np.pi, np.pi), f"(d) phase, y-pol [rad]{lens}"),
        (wx_map, "magma", (a.wx.min() * 1e6, a.wx.max() * 1e6), f"(e) pillar width w_x [um]{lens}"),
        (wy_map, "magma", (a.wy.min() * 1e6, a.wy.max() * 1e6), f"(f) pillar width w_y [um]{lens}"),
    ]
    for axi, (data, cmap, lim, title) in zip([ax[0, 1], ax[0, 2], ax[1, 1], ax[1, 2]], panels):
        h = axi.imshow(data, origin="lower", extent=ext, cmap=cmap, vmin=lim[0], vmax=lim[1],
                       interpolation="antialiased")
        axi.set(xlabel="x [mm]", ylabel="y [mm]")
        axi.set_title(title, fontsize=10)
        fig.colorbar(h, ax=axi, shrink=0.8)
    # error histogram per polarisation and a text panel of metrics
    m = d.metrics
    ax[0, 3].axis("off")
    txt = (f"{d.meta['name']}\n{n:,} x {n:,} cells\n({n * d.spec.period * 1e3:.3f} mm square)\n\n"
           f"atoms       {m['n_atoms']} ({m['n_atoms_used']} used)\n"
           f"empty bins  {m['n_empty_bins']}\n"
           f"metric      {m['metric']}\n"
           f"offsets     x {m['phase_offsets_rad'][0]:+.3f} rad\n"
           f"            y {m['phase_offsets_rad'][1]:+.3f} rad\n"
           f"RMSE        x {m['rmse_rad'][0]:.3f} rad\n"
           f"            y {m['rmse_rad'][1]:.3f} rad\n"
           f"peak error  x {m['peak_error_rad'][0]:.3f} rad\n"
           f"            y {m['peak_error_rad'][1]:.3f} rad\n"
           f"mean T0     x {m['mean_T0'][0]:.3f}\n"
           f"            y {m['mean_T0'][1]:.3f}")
    ax[0, 3].text(0.0, 1.0, txt, va="top", family="monospace", fontsize=8.5, transform=ax[0, 3].transAxes)
    counts = np.bincount(d.atom_indices().ravel(), minlength=len(a) + 1)[:len(a)]
    ax[1, 3].bar(np.arange(len(a)), counts, width=1.0, color="tab:gray")
    ax[1, 3].set(title="(g) atom usage", xlabel="atom index", ylabel="cells", yscale="log")
    fig.suptitle(f"Design {d.meta['name']}: discretization (Fig. S2){crop_note}")
    return save_figure(fig, out)
