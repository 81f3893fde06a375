"""Figures: the sensor frames like Fig. 2c, and fab-study curves."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..plotting import pyplot, save_figure
from .sensor import SensorSpec, quadrant_slices

__all__ = ["case_label", "plot_frames", "plot_fab_study"]


def plot_frames(frames: np.ndarray, sensor: SensorSpec, out: str | Path, channels=None, title: str = "",
                beside: tuple | None = None, label: str = "") -> Path:
    """Two frames (x-pol, y-pol) with quadrant boundaries; row 0 at the top.  Each quadrant is scaled to
    its own peak (the 8 spots have different defocus and so peaks spanning an order of magnitude: on one
    linear scale only the sharpest show), and its peak relative to the brightest spot of the frame is
    written in it.  Axes in micrometres on the camera.  ``beside = (frames, channels, label)``: another
    device's frames on the same sensor, drawn as a second row (``label`` names the first)."""
    plt = pyplot()
    rows = [(frames, channels, label or title)] + ([beside] if beside is not None else [])
    fig, axes = plt.subplots(len(rows), 2, figsize=(13, 5.4 * len(rows)), constrained_layout=True, squeeze=False)
    for (fr, ch, label), ax_row in zip(rows, axes):
        _frame_pair(fig, ax_row, fr, sensor, ch, label if beside is not None else "")
    pitch_um = sensor.pixel_pitch * 1e6
    head = title + ": " if title else ""
    fig.suptitle(head + f"{sensor.width_px} x {sensor.height_px} pixels of {pitch_um:g} um; each quadrant on "
                 "its own scale")
    return save_figure(fig, out)


def _frame_pair(fig, axes, frames, sensor: SensorSpec, channels, label: str) -> None:
    pitch_um = sensor.pixel_pitch * 1e6
    extent = (-0.5 * pitch_um, (sensor.width_px - 0.5) * pitch_um, (sensor.height_px - 0.5) * pitch_um, -0.5 * pitch_um)
    for p, ax in enumerate(axes):
        f = np.asarray(frames[p], np.float64)
        top = max(float(f.max()), 1e-30)
        shown = np.zeros_like(f)
        peaks = []
        for k in range(1, 5):
            r, c = quadrant_slices(sensor, k)
            q = f[r, c]
            peaks.append(float(q.max()) / top)
            shown[r, c] = q / max(float(q.max()), 1e-30)
        im = ax.imshow(shown, cmap="inferno", origin="upper", interpolation="nearest", extent=extent, vmin=0, vmax=1)
        ax.axhline(sensor.height_px / 2 * pitch_um - 0.5 * pitch_um, color="w", lw=0.6, ls="--")
        ax.axvline(sensor.width_px / 2 * pitch_um - 0.5 * pitch_um, color="w", lw=0.6, ls="--")
        for k in range(1, 5):
            qx = 0.25 if k in (1, 3) else 0.75
            qy = 0.04 if k in (1, 2) else 0.54
            text = ["QI", "QII", "QIII", "QIV"][k - 1]
            if channels and channels[p]:
                text += f"  f = {channels[p][k - 1].focal_length * 1e3:.4g} mm"
            text += f"\npeak {peaks[k - 1]:.2f} of the frame's brightest"
            ax.text(qx * sensor.width_px * pitch_um, qy * sensor.height_px * pitch_um, text, color="w", ha="center",
                    va="top", fontsize=9)
        ax.set(title=(f"{label}: " if label else "") + ("x-pol (TE)" if p == 0 else "y-pol (TM)") + " frame",
               xlabel="x on the camera [um]", ylabel="y on the camera [um]")
        fig.colorbar(im, ax=ax, shrink=0.8, label="intensity / the quadrant's own peak")


def case_label(r: dict) -> str:
    """A perturbation case in words: "etch bias +10 nm", "jitter 5 nm", "etch depth -30 nm", "walls 88 deg",
    "nominal" ... (``r``: a fab-study row or a report; ``bias_nm`` a number or ``[x, y]``)."""
    b = r.get("bias_nm") or 0.0
    b = b[0] if isinstance(b, (list, tuple)) else b
    parts = []
    if b:
        parts.append(f"etch bias {b:+g} nm")
    if r.get("jitter_nm"):
        parts.append(f"jitter {r['jitter_nm']:g} nm")
    if r.get("corner_nm"):
        parts.append(f"corner radius {r['corner_nm']:g} nm")
    if r.get("height_nm"):
        parts.append(f"etch depth {r['height_nm']:+g} nm")
    if r.get("sidewall_deg", 90.0) != 90.0:
        parts.append(f"walls {r['sidewall_deg']:g} deg")
    return ", ".join(parts) or "nominal"


def plot_fab_study(rows: list[dict], out: str | Path) -> Path:
    """Efficiency, Strehl, focal shift and crosstalk per channel vs perturbation case: each case its own
    group of markers (the cases are separate devices: no line joins them), in %, um."""
    plt = pyplot()
    cases = sorted({r["case"] for r in rows})
    labels = {r["case"]: case_label(r) if "bias_nm" in r else r["label"] for r in rows}
    fig, axes = plt.subplots(2, 2, figsize=(12, 8), constrained_layout=True)
    keys = (("focusing_efficiency", "focusing efficiency [% of the incident power]", 100.0),
            ("strehl", "Strehl ratio at best focus", 1.0),
            ("focal_shift_mm", "best focus - design focal length [um]", 1e3),
            ("crosstalk", "crosstalk into the other quadrants [% of the spot]", 100.0))
    chans = sorted({(r["pol"], r["k"]) for r in rows})
    width = 0.7
    for ax, (key, name, scale) in zip(axes.ravel(), keys):
        for j, (pol, k) in enumerate(chans):
            dx = (j / max(len(chans) - 1, 1) - 0.5) * width
            ys = [scale * np.mean([r[key] for r in rows if r["case"] == c and r["pol"] == pol and r["k"] == k])
                  for c in cases]
            ax.plot(np.arange(len(cases)) + dx, ys, "o" if pol == "x" else "s", ms=5, ls="none",
                    color=f"C{k - 1}", mfc="none" if pol == "y" else None,
                    label=f"{pol}-pol {['QI', 'QII', 'QIII', 'QIV'][k - 1]}")
        for i in range(1, len(cases)):
            ax.axvline(i - 0.5, color="0.85", lw=0.8)
        ax.set_xticks(range(len(cases)), [labels[c] for c in cases], rotation=20, ha="right", fontsize=8)
        ax.set(ylabel=name)
        ax.grid(True, axis="y", lw=0.3)
    axes[0, 0].legend(fontsize=7, ncol=2, title="channel (x: filled, y: open)", title_fontsize=7)
    fig.suptitle("Fab study: the 8 spots of each as-fabricated device (one group per device)")
    return save_figure(fig, out)
