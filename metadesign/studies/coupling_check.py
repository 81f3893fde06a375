"""What the supercell coupling does to a device, and what the compensating discretizer gives back.

Four devices on the same sensor: the design under the LPA (what every earlier figure assumed), the same
design under the coupling model (what the fab would make, as far as the model knows), and the compensated
design (:mod:`metadesign.design.compensate`) under the coupling model (and under the LPA, for reference).
Per channel, on the total field as the camera sees it (:func:`metadesign.sensing.model.spot_metrics`: under
coupling a pillar's light is not its own, so the sub-lattice metrics of the LPA studies are kept only as a
second column): spot efficiency, spot Strehl, stray light in the quadrant, focal shift; the 8-PSF frames side by side; with a
dataset and a U-Net, the U-Net's NPiB on its test samples re-rendered through each device."""

from __future__ import annotations

import time

import numpy as np

from ..plotting import pyplot, save_figure
from ..sensing.forward import sensor_frames
from ..sensing.model import channel_metrics, spot_metrics
from ..sensing.sensor import SensorSpec
from .lpa import pupil_downstream

__all__ = ["coupling_check", "plot_coupling_frames", "CASES", "SPOT_KEYS"]

SPOT_KEYS = ("spot_efficiency", "spot_strehl", "stray", "focal_shift_mm")

CASES = {"lpa": "design, LPA", "coupled": "design, supercell coupling", "compensated": "compensated, coupling",
         "compensated_lpa": "compensated, LPA"}


def _mean(rows, key):
    return float(np.mean([abs(r[key]) if key == "focal_shift_mm" else r[key] for r in rows]))


def coupling_check(fabs: dict, sensor: SensorSpec, grid: int, dataset=None, model=None, samples: int = 64,
                   noise_percent: float = 5.0, seed: int = 0, log=lambda s: None) -> tuple[dict, dict]:
    """``fabs``: case name -> :class:`~metadesign.sensing.model.AsFabricated` (its coupling set).  Returns
    the report and the flat-wavefront frames per case."""
    pupils, frames, rep = {}, {}, {"cases": {}, "sensor_distance_m": sensor.distance}
    for name, fab in fabs.items():
        t0 = time.perf_counter()
        log(f"  {CASES.get(name, name)}: pupil ...")
        cp = fab.pupil(sensor.distance, grid)
        pupils[name] = cp
        frames[name] = sensor_frames(cp, sensor)
        m = spot_metrics(cp, sensor, fab)
        sl = channel_metrics(cp, sensor, fab)
        rep["cases"][name] = {
            "label": CASES.get(name, name), "coupling": fab.coupling_name, "seconds": time.perf_counter() - t0,
            "channels": m, "mean": {k: _mean(m, k) for k in SPOT_KEYS},
            "sublattice_mean": {k: _mean(sl, k) for k in ("focusing_efficiency", "strehl", "crosstalk")},
            "power_on_sensor": [float(f.sum()) / (fab.n_cells * fab.period) ** 2 for f in frames[name]],
        }
    base = rep["cases"].get("lpa", {}).get("mean")
    if base:
        for c in rep["cases"].values():
            c["relative_to_lpa"] = {k: (c["mean"][k] / base[k] if base[k] else None)
                                    for k in ("spot_efficiency", "spot_strehl", "stray")}
    if dataset is not None and model is not None:
        any_fab = next(iter(fabs.values()))
        rep["downstream"] = pupil_downstream(pupils, dataset, model, any_fab, samples, noise_percent, seed, log)
    return rep, frames


def plot_coupling_frames(frames: dict, sensor: SensorSpec, out, labels=CASES):
    """The 8-PSF frames (x-pol top, y-pol bottom) of each case side by side, each quadrant scaled to the
    brightest quadrant of the LPA frame of its polarisation, so a dimmer or spread spot reads as such."""
    plt = pyplot()
    names = list(frames)
    fig, axs = plt.subplots(2, len(names), figsize=(3.6 * len(names), 5.6), constrained_layout=True, squeeze=False)
    X, Y = sensor.coords()
    ext = np.array([X.min(), X.max(), Y.min(), Y.max()]) * 1e6
    for p in range(2):
        ref = frames[names[0]][p].max()
        for j, n in enumerate(names):
            ax = axs[p, j]
            ax.imshow(np.sqrt(frames[n][p] / ref), origin="lower", extent=ext, cmap="inferno", vmin=0, vmax=1)
            ax.set_title(f"{labels.get(n, n)}\n{'xy'[p]}-pol, peak {frames[n][p].max() / ref:.2f}", fontsize=9)
            ax.set_xlabel("x in the focal plane (um)", fontsize=8)
            if j == 0:
                ax.set_ylabel("y (um)", fontsize=8)
            ax.tick_params(labelsize=7)
    fig.suptitle("8-PSF frames (sqrt of intensity, relative to the LPA design's peak)", fontsize=10)
    return save_figure(fig, out)
