"""PNG previews of a layout read back from the file: a window with every
pillar drawn to scale, and a thumbnail of the whole aperture (w_x map)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..plotting import pyplot, save_figure
from .reader import LayoutContents

__all__ = ["preview_layout"]


def preview_layout(lc: LayoutContents, out: str | Path, window: tuple[int, int, int] | None = None) -> Path:
    """``window = (ix0, iy0, cells)``; default: ``16 x 16`` cells at the centre."""
    from matplotlib.collections import PatchCollection
    from matplotlib.patches import Rectangle

    plt = pyplot()
    n = lc.index_map.shape[0]
    if window is None:
        c = min(16, n)
        window = ((n - c) // 2, (n - c) // 2, c)
    ix0, iy0, c = window
    ix0, iy0 = max(0, min(ix0, n - 1)), max(0, min(iy0, n - 1))
    c = max(1, min(c, n - ix0, n - iy0))
    p, x0 = lc.period_nm, lc.origin_nm
    fig, (a1, a2) = plt.subplots(1, 2, figsize=(14, 6.6), constrained_layout=True)
    rects = []
    sub = lc.index_map[iy0:iy0 + c, ix0:ix0 + c]
    for j in range(c):
        for i in range(c):
            a = sub[j, i]
            if a < 0:
                continue
            w, h = lc.atom_widths_nm[a]
            cx = (ix0 + i) * p + x0 + lc.atom_centres_nm[a, 0] / 2
            cy = (iy0 + j) * p + x0 + lc.atom_centres_nm[a, 1] / 2
            rects.append(Rectangle(((cx - w / 2) / 1e3, (cy - h / 2) / 1e3), w / 1e3, h / 1e3))
    a1.add_collection(PatchCollection(rects, facecolor="tab:blue", edgecolor="k", linewidth=0.3))
    lo = ((ix0 * p + x0 - p / 2) / 1e3, (iy0 * p + x0 - p / 2) / 1e3)
    a1.set(xlim=(lo[0], lo[0] + c * p / 1e3), ylim=(lo[1], lo[1] + c * p / 1e3), aspect="equal",
           xlabel="x [um]", ylabel="y [um]", title=f"pillars: cells ({ix0}..{ix0 + c - 1}, {iy0}..{iy0 + c - 1}), "
                                                   f"period {p} nm")
    a1.set_xticks(np.round((np.arange(ix0, ix0 + c + 1, max(1, c // 8)) * p + x0 - p / 2) / 1e3, 3))
    a1.grid(True, lw=0.3, color="0.8")
    # thumbnail: block mean of w_x over <= 800 x 800 blocks
    f = max(1, int(np.ceil(n / 800)))
    wx = np.append(lc.atom_widths_nm[:, 0].astype(float), np.nan)[np.where(lc.index_map < 0, len(lc.atom_widths_nm),
                                                                             lc.index_map)]
    m = (n // f) * f
    thumb = np.nanmean(wx[:m, :m].reshape(m // f, f, m // f, f), axis=(1, 3)) if f > 1 else wx
    ext = [x0 / 1e6 - p / 2e6, (x0 + n * p) / 1e6 - p / 2e6] * 2
    h = a2.imshow(thumb, origin="lower", extent=ext, cmap="magma", interpolation="nearest")
    a2.add_patch(Rectangle((lo[0] / 1e3, lo[1] / 1e3), c * p / 1e6, c * p / 1e6, fill=False, ec="cyan", lw=1))
    a2.set(title=f"whole aperture: w_x (block mean {f}x{f})", xlabel="x [mm]", ylabel="y [mm]")
    fig.colorbar(h, ax=a2, label="w_x [nm]", shrink=0.8)
    return save_figure(fig, out)
