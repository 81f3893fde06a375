"""The co-designed sensor made into a device and explained (issue #33): from a co-design training run
(``metadesign train`` with a ``[codesign]`` section: ``diversity.json`` beside the U-Net) to

* a design recipe of the device with the learned diversity (``design.toml``: the base design's, each
  lens with its learned focal length and Zernike terms), which goes through design -> layout ->
  as-fabricated -> dataset like any other;
* the learned diversity per channel and the eight PSFs of a flat wavefront beside the paper's
  (``diversity.png``);
* the Fisher information of the frame for the first Zernike modes of the received wavefront, as
  Cramer-Rao bounds, for the paper's diversity, the learned one and random ones of the same parameter
  count (``fisher.png``, ``codesign.json``): why one diversity is better, whatever reads it.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np
import torch

from ..config import load_toml
from ..design.recipe import design_recipe_from_dict
from ..io import atomic_write_text
from ..outputs import RECIPE_HEADER
from ..plotting import pyplot, save_figure
from ..reconstruction.codesign import apply_diversity, check_diversity, diversity_design_recipe
from ..reconstruction.data import PSFDataset
from ..reconstruction.dataset import load_device, open_dataset
from ..sensing.diversity import defocus_to_power, diversity_operators, lens_table
from ..sensing.fisher import crb, crop_zernike_basis, zernike_fisher
from ..sensing.twin import normalise
from ..sensing.twin_diversity import DiversityTwin
from ..validation import InputError

__all__ = ["FisherSettings", "read_diversity", "random_diversity", "fisher_spectra", "run_codesign_report",
           "write_design_recipe", "toml_text"]


def read_diversity(path: str | Path) -> dict:
    """A learned diversity: ``diversity.json`` of a co-design run (or the run folder holding it)."""
    p = Path(path)
    if p.is_dir():
        p = p / "diversity.json"
    try:
        rec = json.loads(p.read_text())
        _ = rec["focal_length_mm"], rec["zernike_noll"], rec["zernike_rad"]
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise InputError(f"{path}: not a co-design run or diversity.json ({type(exc).__name__}: {exc})") from None
    return check_diversity(rec, str(p))


def random_diversity(tw: DiversityTwin, seed: int, waves: float, rad: float) -> dict:
    """A random diversity of the same parameter count (each channel's defocus and Zernike terms drawn
    with the given standard deviations), as a record."""
    rng = np.random.default_rng(seed)
    f0 = tw.f0.numpy()
    w = rng.normal(0.0, waves, (2, 4))
    f = 1 / (1 / f0 + defocus_to_power(w, tw.wavelength, tw.radius))
    return {"focal_length_mm": (f * 1e3).tolist(), "zernike_noll": list(tw.modes),
            "zernike_rad": rng.normal(0.0, rad, (2, 4, len(tw.modes))).tolist()}


def fisher_spectra(tw: DiversityTwin, fields: np.ndarray, basis: np.ndarray, diversities: dict, photons: float,
                   read_noise_e: float, progress: Callable[[int, int], None] | None = None) -> dict:
    """name -> Cramer-Rao bound per mode (rad^2) of the mean Fisher matrix over ``fields`` (the expected
    information over those wavefronts), frames normalised to a fixed sum (the network's input: the
    total flux tells it nothing)."""
    out = {}
    for i, (name, rec) in enumerate(diversities.items()):
        apply_diversity(tw, rec)
        F = zernike_fisher(tw, fields, basis, photons, read_noise_e, normalise_sum=True).mean(axis=0)
        out[name] = crb(F)
        if progress:
            progress(i + 1, len(diversities))
    return out


def toml_text(d: dict) -> str:
    """A recipe dict as TOML (tables of scalars, lists and lists of lists: what design recipes hold)."""
    def val(v):
        if isinstance(v, bool):
            return "true" if v else "false"
        if isinstance(v, (int, float)):
            return repr(v)
        if isinstance(v, str):
            return json.dumps(v)
        if isinstance(v, (list, tuple)):
            return "[" + ", ".join(val(x) for x in v) + "]"
        raise TypeError(type(v).__name__)

    lines = []
    for sec, body in d.items():
        lines.append(f"[{sec}]")
        lines += [f"{k} = {val(v)}" for k, v in body.items()]
        lines.append("")
    return "\n".join(lines)


def design_recipe_of(rec: dict, base: str | Path) -> tuple[dict, dict]:
    """(the co-designed device's design recipe as a dict, the base recipe's): ``base`` must be a design recipe
    and the result one that ``design build`` takes (checked here, before anything is written)."""
    base = Path(base)
    base_raw = load_toml(base)
    if not isinstance(base_raw.get("design"), dict):
        raise InputError(f"--base {base}: not a design recipe (no [design] section)")
    new = diversity_design_recipe(base_raw, rec)
    design_recipe_from_dict(new, base.stem, base)  # what design build would refuse, refused now
    return new, base_raw


def write_design_recipe(rec: dict, base: str | Path, path: Path, run: str | Path) -> Path:
    """The co-designed device's design recipe at ``path``: ``base`` with each lens's learned focal length
    and Zernike terms; its library named relative to ``path``'s folder (so it can be committed beside the
    other design recipes)."""
    base = Path(base)
    new, base_raw = design_recipe_of(rec, base)
    lib = base_raw.get("design", {}).get("library", "../library/paper.npz")
    lib_abs = (base.parent / lib).resolve() if not Path(lib).is_absolute() else Path(lib)
    new["design"]["library"] = os.path.relpath(lib_abs, path.parent.resolve())
    how = "held fixed" if rec.get("config", {}).get("lr", 1.0) == 0 else "learned"
    header = (f"{RECIPE_HEADER}\n# The co-designed sensor (issue #33): {base.name} with the diversity {how} in "
              f"{Path(run).name}\n# (each lens's focal length and its Zernike terms, rad, Noll-normalised over the "
              "aperture's disk; written by metadesign codesign).\n")
    atomic_write_text(path, header + toml_text(new))
    return path


@dataclass(frozen=True)
class FisherSettings:
    """The Fisher study of :func:`run_codesign_report`: ``modes`` Zernike modes 2..modes+1 of the received
    wavefront (tilt first), averaged over ``samples`` received fields of the test split (and a flat
    wavefront), at ``photons`` per frame with ``read_noise_e``, beside ``random`` random diversities."""

    modes: int = 21
    samples: int = 4
    photons: float = 1e6
    read_noise_e: float = 0.0
    random: int = 2


def run_codesign_report(run: str | Path, dataset: str | Path, base: str | Path, out: Path,
                        fisher: FisherSettings = FisherSettings(), recipe: Path | None = None,
                        log: Callable[[str], None] = print) -> dict:
    """See the module docstring; ``fisher``: the Fisher study's settings; ``recipe``: where the design recipe
    goes besides ``out/design.toml``."""
    modes, samples, photons, read_noise_e, random = (fisher.modes, fisher.samples, fisher.photons,
                                                     fisher.read_noise_e, fisher.random)
    rec = read_diversity(run)
    design_recipe_of(rec, base)  # every input checked before anything is written
    dev = load_device(dataset)
    out.mkdir(parents=True, exist_ok=True)
    # 1. the device recipe
    write_design_recipe(rec, base, out / "design.toml", run)
    if recipe is not None:
        write_design_recipe(rec, base, Path(recipe), run)
    # 2. the diversity and its PSFs
    lenses = lens_table(open_dataset(dataset).attrs["provenance"]["channels"])
    ops = diversity_operators(dev.pupil, dev.sensor, lenses, dev.geometry, modes=tuple(rec["zernike_noll"]))
    tw = DiversityTwin(ops)
    c0, a, n_grid, dx, d2 = dev.geometry
    flat_basis = crop_zernike_basis([1], c0, a, n_grid, dx, d2)
    flat = (flat_basis[0] != 0).astype(np.complex64)
    figs = [_plot_diversity(tw, rec, flat, out / "diversity.png")]
    # 3. Fisher spectra: paper, learned, random
    pd = PSFDataset(dataset, "test")
    n = min(samples, len(pd))
    fields = np.stack([flat] + [pd.get(i)["received"] for i in range(n)])
    basis = crop_zernike_basis(range(2, 2 + modes), c0, a, n_grid, dx, d2)
    divs = {"paper": None, "learned": rec}
    for k in range(random):
        divs[f"random {k + 1}"] = random_diversity(tw, k, rec.get("config", {}).get("init_waves", 0.5),
                                                   rec.get("config", {}).get("init_rad", 0.5))
    log(f"Fisher information of {len(divs)} diversities over {len(fields)} wavefronts, {modes} modes ...")
    spectra = fisher_spectra(tw, fields, basis, divs, photons, read_noise_e)
    figs.append(_plot_fisher(spectra, photons, out / "fisher.png"))
    summary = {"run": str(run), "dataset": str(dataset), "base_design": str(base),
               "design_recipe": str(recipe if recipe is not None else out / "design.toml"),
               "diversity": rec, "fisher": {"modes_noll": list(range(2, 2 + modes)), "photons": photons,
                                            "read_noise_e": read_noise_e, "wavefronts": len(fields),
                                            "crb_rad2": {k: [None if not np.isfinite(x) else float(x) for x in v]
                                                         for k, v in spectra.items()},
                                            "mean_crb_rad2": {k: float(np.mean(v[np.isfinite(v)])) for k, v in
                                                              spectra.items()}},
               "figures": [str(f) for f in figs]}
    atomic_write_text(out / "codesign.json", json.dumps(summary, indent=1))
    return summary


def _plot_diversity(tw: DiversityTwin, rec: dict, flat: np.ndarray, path: Path) -> Path:
    plt = pyplot()
    fig, ax = plt.subplots(3, 8, figsize=(17, 6.6), constrained_layout=True)
    x = torch.from_numpy(flat[None])
    with torch.no_grad():
        apply_diversity(tw, None)
        t_paper = normalise(tw(x))[0].numpy()
        apply_diversity(tw, rec)
        psi = tw.phases().numpy()
        t_learned = normalise(tw(x))[0].numpy()
    ins = tw.inside.numpy()
    lim = max(1e-3, float(np.abs(psi[:, :, ins]).max()))
    for c in range(8):
        p, k = divmod(c, 4)
        im = ax[0, c].imshow(np.where(ins, psi[p, k], np.nan), cmap="RdBu_r", vmin=-lim, vmax=lim)
        ax[0, c].set_title(f"{'xy'[p]}-pol lens {k + 1}: f {rec['focal_length_mm'][p][k]:.2f} mm", fontsize=8)
        ax[1, c].imshow(t_paper[c], cmap="magma")
        ax[2, c].imshow(t_learned[c], cmap="magma")
        for r in range(3):
            ax[r, c].set_xticks([])
            ax[r, c].set_yticks([])
    ax[0, 0].set_ylabel("learned diversity\n(rad, on top of the lens)")
    ax[1, 0].set_ylabel("paper: PSF of a\nflat wavefront")
    ax[2, 0].set_ylabel("learned: PSF of a\nflat wavefront")
    fig.colorbar(im, ax=ax[0, :], shrink=0.8, label="rad")
    fig.suptitle("Co-designed diversity per channel and the eight spots it makes, beside the paper's")
    return save_figure(fig, path)


def _plot_fisher(spectra: dict, photons: float, path: Path) -> Path:
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(8, 4.6), constrained_layout=True)
    for name, v in spectra.items():
        j = np.arange(2, 2 + len(v))
        ok = np.isfinite(v)
        ax.semilogy(j[ok], np.sqrt(v[ok]), "o-" if name in ("paper", "learned") else ".--", label=name,
                    lw=2 if name == "learned" else 1)
    ax.set(xlabel="Zernike mode of the received wavefront (Noll)", ylabel="Cramer-Rao bound, rms (rad)",
           title=f"What the eight spots can tell: the best any estimator can do at {photons:.0e} photons")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend()
    return save_figure(fig, path)
