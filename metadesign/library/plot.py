"""Figure S1 equivalent: phase, 0th-order and total transmission maps."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..plotting import pyplot, save_figure
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
