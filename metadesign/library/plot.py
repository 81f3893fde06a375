"""Figure S1 equivalent: phase, 0th-order and total transmission maps."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..plotting import save_figure, pyplot
from .store import UnitCellLibrary

__all__ = ["plot_library"]


def plot_library(lib: UnitCellLibrary, out: str | Path, threshold: float = 0.7) -> Path:
    plt = pyplot()
    ext = [lib.wx[0] * 1e6, lib.wx[-1] * 1e6, lib.wy[0] * 1e6, lib.wy[-1] * 1e6]
    fig, axes = plt.subplots(2, 3, figsize=(13, 8), constrained_layout=True)
    names = ("x-pol (TE)", "y-pol (TM)")
    for r, (name, t) in enumerate(zip(names, (lib.t_x, lib.t_y))):
        panels = (
            (np.angle(t), "twilight", (-np.pi, np.pi), "phase (rad)"),
            (lib.T0[..., r], "viridis", (0, 1), "0th-order transmission"),
            (lib.T_total[..., r], "viridis", (0, 1), "total transmission"),
        )
        for c, (data, cmap, lim, label) in enumerate(panels):
            ax = axes[r, c]
            # arrays are [i_wx, i_wy]: transpose so wx runs along the horizontal axis
            im = ax.imshow(data.T, origin="lower", extent=ext, cmap=cmap, vmin=lim[0], vmax=lim[1],
                           aspect="equal", interpolation="nearest")
            if c > 0:
                ax.contour(lib.wx * 1e6, lib.wy * 1e6, data.T, levels=[threshold], colors="w",
                           linewidths=0.6)
            ax.set_title(f"{name}: {label}")
            ax.set_xlabel("w_x (um)")
            ax.set_ylabel("w_y (um)")
            fig.colorbar(im, ax=ax, shrink=0.85)
    st = lib.meta.get("stack", {})
    fig.suptitle(
        f"Unit-cell library: period {st.get('period_m', 0)*1e6:.3g} um, height {st.get('height_m', 0)*1e6:.3g} um, "
        f"wavelength {st.get('wavelength_m', 0)*1e9:.0f} nm (white: T = {threshold:g})"
    )
    return save_figure(fig, out)


def plot_lpa(rep: dict, out):
    """LPA error: |eps| and phase histograms per polarisation, |eps| vs width contrast, downstream bars."""
    import numpy as np

    from ..plotting import pyplot, save_figure

    plt = pyplot()
    rows = rep["rows"]
    eps = np.array([[complex(*e) for e in r["eps"]] for r in rows])
    con = np.array([r["width_contrast_nm"] for r in rows])
    d = rep.get("downstream")
    fig, axs = plt.subplots(1, 4 if d else 3, figsize=(17 if d else 13, 3.8), constrained_layout=True)
    for p, c in enumerate(("C0", "C1")):
        axs[0].hist(np.abs(eps[:, p]), bins=20, alpha=0.6, color=c, label=f"{'xy'[p]}-pol")
        axs[1].hist(np.angle(1 + eps[:, p]), bins=20, alpha=0.6, color=c, label=f"{'xy'[p]}-pol")
        axs[2].plot(con[:, p], np.abs(eps[:, p]), "o", ms=4, color=c, label=f"{'xy'[p]}-pol")
    axs[0].set(xlabel="|t_supercell / t_LPA - 1|", ylabel="supercells",
               title=f"LPA error, {len(rows)} supercells (nG {rep['n_harmonics_supercell']})")
    axs[1].set(xlabel="arg(t_supercell / t_LPA) [rad]", title="phase error")
    axs[2].set(xlabel="width contrast in the supercell (RMS, nm)", ylabel="|eps|", title="error vs contrast")
    for ax in axs[:3]:
        ax.legend(fontsize=8)
    if d:
        names = ("nominal", "independent", "correlated")
        keys = ("focusing_efficiency", "strehl", "npib_unet")
        vals = np.array([[np.mean([c[k] for c in d[m]["channels"]]) if k != "npib_unet" else d[m][k]
                          for k in keys] for m in names])
        x = np.arange(len(keys))
        for i, m in enumerate(names):
            axs[3].bar(x + (i - 1) * 0.27, vals[i] / vals[0], 0.27, label=m)
        axs[3].set_xticks(x, ["focusing eff.", "Strehl", "U-Net NPiB"])
        rel = vals / vals[0]
        axs[3].set(ylabel="relative to the nominal LPA device", ylim=(0, max(1.1, rel.max() * 1.08)),
                   title="downstream (measured error on the pupil)")
        axs[3].legend(fontsize=8)
    return save_figure(fig, out)
