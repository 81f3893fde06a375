"""Figures: the sensor frames like Fig. 2c, and fab-study curves."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..plotting import pyplot, save_figure
from .sensor import SensorSpec

__all__ = ["plot_frames", "plot_fab_study"]


def plot_frames(frames: np.ndarray, sensor: SensorSpec, out: str | Path, channels=None, title: str = "") -> Path:
    """Two frames (x-pol, y-pol) with quadrant boundaries; row 0 at the top."""
    plt = pyplot()
    fig, axes = plt.subplots(1, 2, figsize=(13, 5.4), constrained_layout=True)
    for p, ax in enumerate(axes):
        f = frames[p]
        im = ax.imshow(f / max(f.max(), 1e-30), cmap="inferno", origin="upper", interpolation="nearest")
        ax.axhline(sensor.height_px / 2 - 0.5, color="w", lw=0.6, ls="--")
        ax.axvline(sensor.width_px / 2 - 0.5, color="w", lw=0.6, ls="--")
        for k in range(1, 5):
            qx = 0.25 if k in (1, 3) else 0.75
            qy = 0.04 if k in (1, 2) else 0.54
            label = ["QI", "QII", "QIII", "QIV"][k - 1]
            if channels and channels[p]:
                label += f"  f = {channels[p][k - 1].focal_length * 1e3:.4g} mm"
            ax.text(qx * sensor.width_px, qy * sensor.height_px, label, color="w", ha="center", va="top", fontsize=9)
        ax.set(title=("x-pol (TE)" if p == 0 else "y-pol (TM)") + " frame", xlabel="column [px]", ylabel="row [px]")
        fig.colorbar(im, ax=ax, shrink=0.8, label="intensity / frame peak")
    if title:
        fig.suptitle(title)
    return save_figure(fig, out)


def plot_fab_study(rows: list[dict], out: str | Path) -> Path:
    """Efficiency, Strehl, focal shift and crosstalk per channel vs perturbation case."""
    plt = pyplot()
    cases = sorted({r["case"] for r in rows})
    labels = {r["case"]: r["label"] for r in rows}
    fig, axes = plt.subplots(2, 2, figsize=(12, 8), constrained_layout=True)
    keys = (("focusing_efficiency", "focusing efficiency"), ("strehl", "Strehl ratio (best focus)"),
            ("focal_shift_mm", "focal shift [mm]"), ("crosstalk", "crosstalk"))
    chans = sorted({(r["pol"], r["k"]) for r in rows})
    for ax, (key, name) in zip(axes.ravel(), keys):
        for pol, k in chans:
            ys = [np.mean([r[key] for r in rows if r["case"] == c and r["pol"] == pol and r["k"] == k]) for c in cases]
            ax.plot(range(len(cases)), ys, "o-" if pol == "x" else "s--", label=f"{pol}-pol k={k}", ms=4)
        ax.set_xticks(range(len(cases)), [labels[c] for c in cases], rotation=30, ha="right", fontsize=8)
        ax.set(title=name)
        ax.grid(True, lw=0.3)
    axes[0, 0].legend(fontsize=7, ncol=2)
    return save_figure(fig, out)
