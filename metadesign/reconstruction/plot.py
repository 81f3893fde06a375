"""Figures of a dataset: a few samples (8 PSFs, received phase and amplitude) and the Rytov histogram."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..plotting import pyplot, save_figure
from .data import PSFDataset
from .dataset_store import DatasetInfo

__all__ = ["plot_dataset"]

_NAMES = [f"{p}-pol Q{q}" for p in "xy" for q in ("I", "II", "III", "IV")]


def plot_dataset(info: DatasetInfo, out: str | Path, n_samples: int = 3) -> Path:
    plt = pyplot()
    ds = PSFDataset(info.path, "all")  # its reads check each sample (a damaged one is one line)
    test = info.indices("test")
    pick = (test if len(test) else np.arange(info.n))[:n_samples]
    fig = plt.figure(figsize=(17, 3.1 * len(pick) + 3.2), constrained_layout=True)
    gs = fig.add_gridspec(len(pick) + 1, 10)
    for row, i in enumerate(pick):
        s = ds.get(int(i))
        psf, rec = s["psf"], s["received"]
        for c in range(8):
            ax = fig.add_subplot(gs[row, c])
            ax.imshow(np.clip(psf[c], 0, None) ** 0.5, cmap="inferno", origin="upper")  # captures: < 0 after darks
            ax.set_xticks([])
            ax.set_yticks([])
            ax.set_title(_NAMES[c], fontsize=8)
            if c == 0:
                ax.set_ylabel(f"#{i}: Rytov {info.rytov[i]:.2f}\n(measured {info.rytov_measured[i]:.2f})", fontsize=8)
        amp = np.abs(rec)
        ax = fig.add_subplot(gs[row, 8])
        h = ax.imshow(np.where(amp > 0, np.angle(rec), np.nan), cmap="twilight", vmin=-np.pi, vmax=np.pi)
        ax.set_title("received phase [rad]", fontsize=8)
        ax.set_xticks([])
        ax.set_yticks([])
        fig.colorbar(h, ax=ax, shrink=0.7)
        ax = fig.add_subplot(gs[row, 9])
        h = ax.imshow(np.where(amp > 0, amp, np.nan), cmap="viridis")
        ax.set_title("received amplitude", fontsize=8)
        ax.set_xticks([])
        ax.set_yticks([])
        fig.colorbar(h, ax=ax, shrink=0.7)
    ax = fig.add_subplot(gs[-1, :5])
    top = np.nanmax(np.r_[info.rytov, info.rytov_measured, 0.0])  # NaN: unknown (imported captures)
    bins = np.linspace(0, max(float(top), 1e-3) * 1.05, 30)
    ax.hist(info.rytov, bins=bins, alpha=0.6, label="nominal (path model)")
    ax.hist(info.rytov_measured, bins=bins, alpha=0.6, label="measured (log-amplitude variance)")
    ax.set(xlabel="Rytov number", ylabel="samples", title=f"{info.n} samples")
    ax.legend(fontsize=8)
    ax = fig.add_subplot(gs[-1, 5:])
    ax.scatter(info.rytov, info.rytov_measured, s=3, alpha=0.5)
    lim = [0, bins[-1]]
    ax.plot(lim, lim, "k--", lw=0.8)
    ax.set(xlabel="nominal Rytov", ylabel="measured", title="per-sample log-amplitude variance vs nominal")
    fig.suptitle(f"dataset {info.attrs.get('name')}: 8 x {info.tensor_size}^2 PSF tensors (sqrt scale; Fig. 3a inputs)")
    return save_figure(fig, out)
