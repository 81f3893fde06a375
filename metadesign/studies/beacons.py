"""Fresh beacons through a device, estimated by a committed model: the pipeline's ``[beacons]`` stage.

No dataset is built: each beacon is drawn by the system's chain (the device as designed, its sensor and
the turbulence scenario), at a root seed of the recipe's (another than the model's training data), and
corrected by the model (a U-Net, or a refiner with its U-Net) at each sensor-noise level, against no
correction and the phase and complex conjugates (the oracles).  ``metadesign demo`` shows the committed
demo models this way on the paper design."""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from ..design.recipe import load_design_recipe
from ..design.store import run_design
from ..plotting import pyplot, save_figure
from ..reconstruction.data import apply_noise
from ..reconstruction.dataset import measured_rytov, normalise_psf, received_crop, sample_rytov
from ..reconstruction.losses import PiB
from ..reconstruction.metrics import captured_fraction, gain, npib_rows
from ..reconstruction.refine import load_network
from ..sensing.model import AsFabricated
from ..turbulence.system import build_system

if TYPE_CHECKING:
    from .pipeline_recipe import BeaconsSection

__all__ = ["fresh_beacons"]

LABELS = {"unet": "U-Net", "refine": "U-Net + learned refinement"}


def fresh_beacons(spec: BeaconsSection, turbulence: Path, work: Path, figure: Path,
                  library: Path | None = None) -> dict:
    """NPiB of ``spec.samples`` fresh beacons (root seed ``spec.seed``; Rytov numbers drawn in
    [``spec.rytov_min``, ``spec.rytov_max``]) through the device of the design recipe ``spec.design``
    (designed into ``work``; with the unit cells of ``library`` when given), seen by the sensor
    ``spec.sensor`` behind ``turbulence``, corrected by the model ``spec.model`` at each noise level of
    ``spec.noise_percent`` (% of each channel's peak); a refiner is also reported without its refinement
    (its U-Net).  Returns the mean NPiB per method, the captured fractions (``"unet@5"``, ``"refine@5"``,
    ...), the median gain of the best estimator at the highest noise level, and the Fig. 3b scatter at
    ``figure``.  ``spec``: the pipeline's ``[beacons]`` section (any object with its fields)."""
    import torch

    design, samples, root, rytov = Path(spec.design), spec.samples, spec.seed, (spec.rytov_min, spec.rytov_max)
    net, card = load_network(spec.model)
    refiner = net if hasattr(net, "trajectory") else None
    unet = refiner.unet if refiner is not None else net
    dr = load_design_recipe(design)
    d, _ = run_design(dr if library is None else dataclasses.replace(dr, library_path=Path(library)), work)
    chain = build_system(AsFabricated.from_design(d), spec.sensor, turbulence,
                         tensor_size=unet.config.input_size).chain()
    c0, a = received_crop(chain.turbulence.sc)
    pib = PiB(chain.turbulence.sc, c0, a)
    ap = chain.turbulence.aperture[c0:c0 + a, c0:c0 + a]
    methods = ("unet", "refine") if refiner is not None else ("unet",)
    levels = tuple(float(v) for v in spec.noise_percent)
    rows: dict = {k: [] for k in ("rytov", "none", "phase_conjugate", "complex_conjugate")}
    rows |= {f"{m}@{lv:g}": [] for m in methods for lv in levels}
    with torch.no_grad():
        for i in range(samples):
            r = sample_rytov(root, i, rytov, None)
            seed = 10_000 + i
            s = chain.sample(seed, r)
            tb = chain.at(r)
            scr = torch.from_numpy(tb.screens(seed))[None]
            rec = torch.from_numpy(s.received[c0:c0 + a, c0:c0 + a])[None]
            psf, _ = normalise_psf(s.tensor)
            rows["rytov"].append(measured_rytov(s.received[c0:c0 + a, c0:c0 + a], ap))
            ref = npib_rows(pib, torch.zeros(rec.shape), scr, rec, complex_conjugate=True)
            for k in ("none", "phase_conjugate", "complex_conjugate"):
                rows[k].append(float(ref[k]))
            for lv in levels:
                rng = np.random.default_rng(np.random.SeedSequence(root, spawn_key=(i, int(10 * lv))))
                x = torch.from_numpy(apply_noise(psf, rng, lv) if lv else psf)[None]
                phi = unet(x)
                rows[f"unet@{lv:g}"].append(float(pib.npib_phase(phi, scr)))
                if refiner is not None:
                    rows[f"refine@{lv:g}"].append(float(pib.npib_phase(refiner.trajectory(x, start=phi)[-1]
                                                                       * refiner.mask, scr)))
    m = {k: float(np.mean(v)) for k, v in rows.items()}
    cap = {k: captured_fraction(rows["none"], rows[k], rows["phase_conjugate"]) for k in rows if "@" in k}
    best = f"{methods[-1]}@{levels[-1]:g}"
    g = gain(rows["none"], rows[best])
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(7.5, 4.8), constrained_layout=True)
    series = [("complex_conjugate", "complex conjugate (oracle)", "^", "tab:olive"),
              ("phase_conjugate", "phase conjugate (oracle)", "s", "tab:green")]
    series += [(f"{k}@{levels[-1]:g}", f"{LABELS[k]}, {levels[-1]:g} % noise", "o" if k == "unet" else "P",
                "tab:blue" if k == "unet" else "tab:cyan") for k in methods]
    series += [("none", "uncorrected", "x", "k")]
    for k, name, mk, col in series:
        ax.scatter(rows["rytov"], rows[k], s=16, marker=mk, color=col, alpha=0.75, label=f"{name}: mean {m[k]:.3f}")
    ax.set(xlabel="Rytov number of the sample (measured)", ylabel="normalised power in bucket",
           title=f"Fig. 3b: {samples} fresh beacons through {Path(design).stem}")
    ax.legend(fontsize=8)
    fig_path = save_figure(fig, figure)
    per = "; ".join(f"{LABELS[k]} " + " / ".join(f"{m[f'{k}@{lv:g}']:.3f}" for lv in levels) + " (captured "
                    + " / ".join(f"{cap[f'{k}@{lv:g}']:.2f}" for lv in levels) + ")" for k in methods)
    at = " / ".join(f"{lv:g}" for lv in levels)
    line = (f"{samples} fresh beacons through {Path(design).stem}, mean NPiB at {at} % noise: {per}; "
            f"uncorrected {m['none']:.3f}, phase conjugate {m['phase_conjugate']:.3f}, complex conjugate "
            f"{m['complex_conjugate']:.3f}; gain median {np.median(g):.1f}x")
    return {"line": line, "npib": m, "captured_fraction": cap, "gain_median": float(np.median(g)),
            "noise_percent": list(levels), "model_card": card.get("metrics"), "figures": [str(fig_path)],
            "methods": list(methods)}
