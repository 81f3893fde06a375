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
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from ..execution import SERIAL, Execution
from ..plotting import pyplot, save_figure
from ..sensing.device import Device
from ..sensing.model import channel_metrics, spot_metrics
from ..sensing.plot import case_label
from ..sensing.sensor import SensorSpec
from ..sensing.transmission import Perturbation
from .certified import (  # noqa: F401  (re-exported: the certified case lived here)
    CERTIFIED_LABEL,
    SPOT_KEYS,
    CertifiedSettings,
    SampledDevice,
    _mean,
    _pillar_t,
    _sampled_metrics,
    certified_case,
)
from .lpa import Downstream, pupil_downstream

__all__ = ["CASES", "SPOT_KEYS", "SWEEP_AXES", "CertifiedCheck", "CertifiedSettings", "SampledDevice",
           "certified_case", "coupling_check", "plot_case_metrics", "plot_coupling_frames", "sweep_axis",
           "sweep_table", "plot_sweep"]

SPOT_TITLES = dict(zip(SPOT_KEYS, ("spot efficiency", "spot Strehl", "stray fraction", "|focal shift| (um)")))

CASES = {"lpa": "design, LPA", "coupled": "design, supercell coupling", "compensated": "compensated, coupling",
         "compensated_lpa": "compensated, LPA", "certified": CERTIFIED_LABEL,
         "compensated_certified": "compensated, certified (PEDS, sampled)",
         "certified_ring": "design, certified (PEDS, overlapping windows, sampled)",
         "compensated_certified_ring": "compensated, certified (PEDS, overlapping windows, sampled)",
         "certified_reoptimised": "design, atoms re-chosen under the certified model (sampled)",
         "compensated_certified_reoptimised": "compensated, atoms re-chosen under the certified model (sampled)"}


@dataclass(frozen=True)
class CertifiedCheck:
    """The certified cases of :func:`coupling_check`: how they are measured (``settings``), their resume
    folder ``partial`` (a folder per case inside it) and, to re-choose their atoms, each coupled case's
    :class:`~metadesign.design.store.Design` (``designs``: case name -> design)."""

    settings: CertifiedSettings
    partial: str | Path
    designs: Mapping[str, Any] = field(default_factory=dict)


def coupling_check(fabs: dict, sensor: SensorSpec, grid: int, pert: Perturbation = Perturbation(),
                   downstream: Downstream | None = None, certified: CertifiedCheck | None = None,
                   run: Execution = SERIAL) -> tuple[dict, dict]:
    """``fabs``: case name -> :class:`~metadesign.sensing.model.AsFabricated` (its coupling set).  Returns
    the report and the flat-wavefront frames per case.  ``certified``: each coupled case (``coupled``,
    ``compensated``) also under the certified model, sampled (:func:`certified_case` with
    ``certified.settings``, on ``run``'s workers; no flat-wavefront frames; with ``downstream``, the NPiB from
    the sampled device's frames, with its jackknife error bar).  ``pert``: every device made with those
    widths (bias, jitter: the same pillars in every case and in the sample) and that global etch-depth error
    and wall angle (the devices' ``fab_lib`` gives the unit cells' change with height and angle; the
    certified model solves its supercells at that height, tapered in ``taper_slices`` slices, or vertical at
    mid-height widths with 0).  ``certified.settings.reoptimise = K`` with ``certified.designs``: each
    certified case also with its sampled supercells' atoms re-chosen under the certified model
    (:func:`certified_case`).  ``downstream``: the U-Net's NPiB through every case
    (:func:`~metadesign.studies.lpa.pupil_downstream`)."""
    log = run.log
    if pert.height_gradient or pert.sidewall_gradient_deg:
        raise ValueError("coupling_check: width errors and a global etch depth and wall angle only (no gradients "
                         "across the device)")
    pupils, frames = {}, {}
    rep = {"cases": {}, "sensor_distance_m": sensor.distance, "bias_nm": [pert.bias_x * 1e9, pert.bias_y * 1e9],
           "jitter_nm": pert.jitter * 1e9, "jitter_seed": pert.seed, "corner_nm": pert.corner_radius * 1e9,
           "height_nm": round(pert.height * 1e9, 6), "sidewall_deg": pert.sidewall_deg}
    for name, fab in fabs.items():
        t0 = time.perf_counter()
        log(f"  {CASES.get(name, name)}: pupil ...")
        cp = fab.pupil(sensor.distance, grid, pert)
        pupils[name] = cp
        frames[name] = Device(cp, sensor).frames()
        m = spot_metrics(cp, sensor, fab)
        sl = channel_metrics(cp, sensor, fab)
        rep["cases"][name] = {
            "label": CASES.get(name, name), "coupling": fab.coupling_name, "seconds": time.perf_counter() - t0,
            "channels": m, "mean": {k: _mean(m, k) for k in SPOT_KEYS},
            "sublattice_mean": {k: _mean(sl, k) for k in ("focusing_efficiency", "strehl", "crosstalk")},
            "power_on_sensor": [float(f.sum()) / (fab.n_cells * fab.period) ** 2 for f in frames[name]],
        }
    sampled = {}
    if certified and certified.settings.reoptimise and not all(n in certified.designs
                                                               for n in ("coupled", "compensated") if n in fabs):
        raise ValueError("coupling_check: re-optimising needs each coupled case's design (designs=)")
    if certified:
        for name, cert in (("coupled", "certified"), ("compensated", "compensated_certified")):
            if name in fabs:
                log(f"  {CASES[cert]}: {certified.settings.supercells} supercells through the certified model ...")
                device = SampledDevice(fabs[name], pupils[name], sensor, grid, pert, certified.designs.get(name))
                rep["cases"][cert], deltas, ring = certified_case(device, certified.settings,
                                                                  f"{certified.partial}/{name}", run=run,
                                                                  label=CASES[cert], return_deltas=True)
                if certified.settings.reoptimise:
                    rep["cases"][cert + "_reoptimised"] = {**rep["cases"][cert].pop("reoptimised"),
                                                           "label": CASES[cert + "_reoptimised"]}
                sampled[cert] = (name, deltas)
                if ring is not None:
                    rep["cases"][cert + "_ring"] = rep["cases"][cert].pop("with_ring")
                    sampled[cert + "_ring"] = (name, ring)
    base = rep["cases"].get("lpa", {}).get("mean")
    if base:
        for c in rep["cases"].values():
            c["relative_to_lpa"] = {k: (c["mean"][k] / base[k] if base[k] else None)
                                    for k in ("spot_efficiency", "spot_strehl", "stray")}
    if downstream is not None:
        rep["downstream"] = pupil_downstream(pupils, downstream, next(iter(fabs.values())), log, sampled=sampled)
    return rep, frames


def plot_case_metrics(rep: dict, out):
    """The mean spot metrics of every case side by side, sampled (certified) cases with their standard
    errors (2 sigma bars): what the certified model changes, and how sure the sampling is of it."""
    plt = pyplot()
    names = list(rep["cases"])
    fig, axs = plt.subplots(1, 4, figsize=(15, 3.6), constrained_layout=True)
    colours = {"lpa": "0.6", "compensated_lpa": "0.8", "coupled": "C0", "compensated": "C2", "certified": "C1",
               "compensated_certified": "C3", "certified_ring": "C4", "compensated_certified_ring": "C5",
               "certified_reoptimised": "C6", "compensated_certified_reoptimised": "C7"}
    for ax, (k, title) in zip(axs, SPOT_TITLES.items()):
        scale = 1e3 if k == "focal_shift_mm" else 1.0
        for i, n in enumerate(names):
            c = rep["cases"][n]
            se = c.get("stderr", {}).get(k, 0.0)
            ax.errorbar(i, c["mean"][k] * scale, yerr=2 * se * scale if se else None, fmt="o", ms=7, capsize=4,
                        color=colours.get(n, f"C{i}"))
        ax.axhline(rep["cases"][names[0]]["mean"][k] * scale, color="0.6", lw=0.8, ls=":")
        ax.set_xticks(range(len(names)), [c["label"] for c in rep["cases"].values()], rotation=35, ha="right",
                      fontsize=7)
        ax.set_xlim(-0.6, len(names) - 0.4)
        ax.set_title(title, fontsize=9)
        ax.tick_params(labelsize=7)
        ax.grid(axis="y", alpha=0.3)
    fig.suptitle(f"Spot metrics per device model, {case_label(rep)} device (mean of 8 channels; sampled cases: "
                 "+-2 standard errors)", fontsize=10)
    return save_figure(fig, out)


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


SWEEP_AXES = {"bias_nm": "width bias (nm)", "height_nm": "etch depth error (nm)",
              "sidewall_deg": "sidewall angle (deg)"}


def _bias(r: dict) -> float:
    return (r.get("bias_nm") or [0.0])[0]


def _axis_values(reports: list[dict]) -> dict:
    return {"bias_nm": [_bias(r) for r in reports], "height_nm": [r.get("height_nm", 0.0) for r in reports],
            "sidewall_deg": [r.get("sidewall_deg", 90.0) for r in reports]}


def sweep_axis(reports: list[dict]) -> str:
    """The one perturbation that varies across coupling-check reports (a key of :data:`SWEEP_AXES`: width
    bias, etch depth or sidewall angle); ValueError when several vary, or none does (a repeated device)."""
    values = _axis_values(reports)
    varying = [k for k, v in values.items() if len(set(v)) > 1]
    if len(varying) > 1:
        raise ValueError(f"the reports differ in {' and '.join(SWEEP_AXES[k].split(' (')[0] for k in varying)}: "
                         "one perturbation per sweep")
    if not varying:
        raise ValueError(f"the reports repeat one device (width bias {values['bias_nm'][0]:g} nm, etch depth "
                         f"{values['height_nm'][0]:g} nm, wall {values['sidewall_deg'][0]:g} deg): one report "
                         "per value")
    v = values[varying[0]]
    if len(set(v)) != len(v):
        raise ValueError(f"the reports' {SWEEP_AXES[varying[0]].split(' (')[0]}s repeat "
                         f"({', '.join(f'{x:g}' for x in v)}): one report per value")
    return varying[0]


def sweep_table(reports: list[dict]) -> dict:
    """Coupling-check reports of one design made with different width biases (or etch depths, or wall
    angles: :func:`sweep_axis`) -> per case, per metric, the values (and standard errors) in order of that
    axis: ``{"axis": "bias_nm", "bias_nm": [...], "height_nm": [...], "sidewall_deg": [...], "cases": {name:
    {"label", key: [...], key + "_se": [...]}}}`` (cases present in every report)."""
    axis = sweep_axis(reports) if len(reports) > 1 else "bias_nm"
    order = np.argsort(_axis_values(reports)[axis], kind="stable")
    reps = [reports[i] for i in order]
    names = [n for n in reps[0]["cases"] if all(n in r["cases"] for r in reps)]
    out = {"axis": axis, **_axis_values(reps), "jitter_nm": [r.get("jitter_nm", 0.0) for r in reps], "cases": {}}
    for n in names:
        row = {"label": reps[0]["cases"][n]["label"]}
        for k in SPOT_KEYS:
            row[k] = [r["cases"][n]["mean"][k] for r in reps]
            row[k + "_se"] = [r["cases"][n].get("stderr", {}).get(k, 0.0) for r in reps]
        out["cases"][n] = row
    return out


def plot_sweep(table: dict, out):
    """Spot efficiency, Strehl, stray light and |focal shift| against the width bias (or the etch depth: the
    table's ``axis``), one line per device model; the sampled (certified) ones with +-2 standard-error bars:
    a fab-tolerance curve per model."""
    plt = pyplot()
    fig, axs = plt.subplots(1, 4, figsize=(15, 3.6), constrained_layout=True)
    axis = table.get("axis", "bias_nm")
    b = np.asarray(table[axis])
    styles = {"lpa": dict(color="0.5", ls="--", marker="s"), "coupled": dict(color="C0", marker="o"),
              "certified": dict(color="C1", marker="D", lw=2)}
    for ax, (k, title) in zip(axs, SPOT_TITLES.items()):
        scale = 1e3 if k == "focal_shift_mm" else 1.0
        for i, (n, row) in enumerate(table["cases"].items()):
            v = np.abs(row[k]) * scale if k == "focal_shift_mm" else np.asarray(row[k])
            se = np.asarray(row[k + "_se"]) * scale
            ax.errorbar(b, v, yerr=2 * se if se.any() else None, capsize=3, label=row["label"],
                        **styles.get(n, dict(color=f"C{i + 2}", marker="^")))
        ax.set_xlabel(SWEEP_AXES[axis], fontsize=8)
        ax.set_title(title, fontsize=9)
        ax.tick_params(labelsize=7)
        ax.grid(alpha=0.3)
    axs[0].legend(fontsize=7)
    fig.suptitle("Fab tolerance of the spots under each device model (mean of 8 channels; sampled: +-2 standard "
                 "errors)", fontsize=10)
    return save_figure(fig, out)
