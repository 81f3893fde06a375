"""Co-design of the sensor's diversity with its reconstruction (issue #33): the U-Net reads the eight PSFs
that a learnable diversity (:class:`~metadesign.sensing.twin_diversity.DiversityTwin`) renders from the
dataset's stored received fields, and both are trained together on the end-to-end PiB loss (the usual
training loop, :func:`metadesign.reconstruction.train.train`, with a ``[codesign]`` recipe section).

* No dataset rebuild per step: the received fields are the dataset's; the PSFs are rendered each batch
  for the current diversity (normalised to sum 8 as the datasets are, then the sensor noise, a Gaussian
  level per sample drawn in the recipe's range, of each channel's peak: the datasets' noise model).
* Makeable: the diversity is a smooth phase on each channel's lens (defocus and low-order Zernike
  terms), which the 16 x 16 library realises like any lens phase (it covers every phase bin); the loss
  adds a penalty on the phase step between neighbouring pupil blocks above ``max_step_rad`` (a phase
  that varies within a block would leave the block model and the local-periodic approximation), and the
  learned design goes through the usual design -> layout -> as-fabricated path to be trained on
  (``design.recipe`` with ``zernike_rad`` per lens: :func:`diversity_design_recipe`).
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch
import torch.nn as nn

from ..sensing.detector import Detector
from ..sensing.diversity import DEFAULT_MODES, diversity_operators, focal_to_defocus, lens_table
from ..sensing.twin import normalise
from ..sensing.twin_diversity import DiversityTwin
from ..validation import ValidationError
from .dataset_store import load_device, open_dataset

__all__ = ["CodesignConfig", "CodesignNet", "build_codesign", "apply_diversity", "codesign_for_evaluation", "scaled_ladder",
           "diversity_record", "diversity_design_recipe"]


@dataclass(frozen=True)
class CodesignConfig:
    modes: tuple[int, ...] = DEFAULT_MODES  # Noll terms each channel may learn besides its defocus
    learn_defocus: bool = True
    lr: float = 1e-2  # the diversity's learning rate (its parameters are waves and radians)
    init: str = "paper"  # "paper" (the device as built) or "random"
    init_waves: float = 0.5  # "random": defocus std (waves) and Zernike std (rad)
    init_rad: float = 0.5
    max_step_rad: float = 0.5  # largest phase step between pupil blocks before the penalty
    penalty: float = 1.0
    rebin: int = 1  # the twin's approximations (1 / None: exact, as the dataset was rendered)
    samples: int | None = None
    seed: int = 0
    defocus_scale: float = 1.0  # "paper": the channels' optical powers spread about their mean times this


class CodesignNet(nn.Module):
    """The learnable sensor and its U-Net: received crops (B, A, A) complex -> phase (B, A, A).  Training
    mode draws each sample's Gaussian noise level in ``noise_percent`` (lo, hi) from the module's
    generator; evaluation mode uses a generator re-seeded on every ``eval()`` (the same noise every
    validation)."""

    input_key = "received"

    def __init__(self, twin: DiversityTwin, unet: nn.Module, cfg: CodesignConfig, noise_percent=(0.0, 0.0)):
        super().__init__()
        self.twin, self.unet, self.cfg = twin, unet, cfg
        self.noise_percent = (float(noise_percent[0]), float(noise_percent[1]))
        self._gen = torch.Generator().manual_seed(cfg.seed)

    @property
    def config(self):  # the U-Net's: what check_sizes and the evaluation read
        return self.unet.config

    def train(self, mode: bool = True):
        super().train(mode)
        if not mode:
            self._gen = torch.Generator().manual_seed(self.cfg.seed + 1)
        return self

    def seed_noise(self, seed: int) -> None:
        """Re-seed the training noise (per epoch, so a resumed run draws what an uninterrupted one did)."""
        self._gen = torch.Generator().manual_seed(int(seed))

    def render(self, received):
        """The normalised 8-channel tensor (B, 8, S, S) with the sensor noise of this mode.  The rendering
        runs in full precision even under autocast (CUDA's bfloat16 would cost the spots their dynamic
        range); the noise is drawn on the CPU generator (the same draws on any device), then moved."""
        with torch.autocast(received.device.type, enabled=False):
            x = normalise(self.twin(received).to(torch.float32))
        lo, hi = self.noise_percent
        if hi > 0:  # the detector's torch backend, at a level per sample drawn in the range
            lv = lo + (hi - lo) * torch.rand(x.shape[0], generator=self._gen, dtype=torch.float64)
            x = Detector().read_torch(x, self._gen, gaussian_sigma=lv.to(device=x.device, dtype=x.dtype) / 100.0)
        return x

    def forward(self, received):
        return self.unet(self.render(received))

    def penalty(self):
        """The makeability penalty: squared excess of the block-to-block diversity step over max_step_rad."""
        psi = self.twin.phases()
        ins = self.twin.inside
        dx = (psi[..., :, 1:] - psi[..., :, :-1]).abs() * (ins[:, 1:] & ins[:, :-1])
        dy = (psi[..., 1:, :] - psi[..., :-1, :]).abs() * (ins[1:, :] & ins[:-1, :])
        ex = torch.relu(dx - self.cfg.max_step_rad) ** 2
        ey = torch.relu(dy - self.cfg.max_step_rad) ** 2
        return self.cfg.penalty * (ex.sum() + ey.sum())


def build_codesign(unet: nn.Module, cfg: CodesignConfig, dataset: str | Path, noise_percent) -> CodesignNet:
    """The co-design module of ``unet`` on the device of ``dataset`` (its stored pupil, sensor and crop;
    its lenses from the layout's provenance)."""
    dev = load_device(dataset)
    lenses = lens_table(open_dataset(dataset).attrs["provenance"]["channels"])
    ops = diversity_operators(dev.pupil, dev.sensor, lenses, dev.geometry, cfg.rebin, cfg.samples, cfg.modes)
    twin = DiversityTwin(ops, persistent=False)  # the operators come from the dataset, not the checkpoint
    if cfg.init == "random":
        g = torch.Generator().manual_seed(cfg.seed)
        with torch.no_grad():
            if cfg.learn_defocus:
                twin.defocus_waves.copy_(cfg.init_waves * torch.randn(2, 4, generator=g, dtype=torch.float64))
            twin.zernike_rad.copy_(cfg.init_rad * torch.randn(twin.zernike_rad.shape, generator=g,
                                                              dtype=torch.float64))
    elif cfg.defocus_scale != 1.0:  # the paper's defocus ladder stretched (or shrunk) about its mean power
        with torch.no_grad():
            twin.defocus_waves.copy_(scaled_ladder(twin.f0, cfg.defocus_scale, twin.wavelength, twin.radius))
    twin.defocus_waves.requires_grad_(cfg.learn_defocus)
    return CodesignNet(twin, unet, cfg, noise_percent)


def scaled_ladder(f0, scale: float, wavelength: float, radius: float):
    """The defocus (waves) that scales the spread of the lenses' optical powers ``1 / f0`` about their mean
    by ``scale`` (1: none; 0: every lens at the mean power, no diversity; 2: twice the paper's ladder)."""
    p0 = 1.0 / f0
    pm = p0.mean()
    return focal_to_defocus(1.0 / (pm + scale * (p0 - pm)), f0, wavelength, radius)


def check_diversity(rec, where: str = "diversity") -> dict:
    """A recorded diversity (``diversity.json``, a card's ``codesign``) as a design recipe would take it: per
    polarisation four finite focal lengths in (0, 1e5] mm, distinct Noll indices 2..66, and a finite Zernike
    coefficient in [-1000, 1000] rad per lens and index; one line naming the field otherwise."""
    if not isinstance(rec, dict):
        raise ValidationError(f"{where}: expected a record with focal_length_mm, zernike_noll, zernike_rad")
    try:
        f = np.asarray(rec["focal_length_mm"], dtype=np.float64)
        noll = list(rec["zernike_noll"])
        a = np.asarray(rec["zernike_rad"], dtype=np.float64)
    except KeyError as exc:
        raise ValidationError(f"{where}: lacks {exc.args[0]}") from None
    except (TypeError, ValueError) as exc:
        raise ValidationError(f"{where}: expected numbers ({exc})") from None
    if f.shape != (2, 4) or not np.isfinite(f).all() or (f <= 0).any() or (f > 1e5).any():
        raise ValidationError(f"{where}: focal_length_mm must be 2 x 4 finite lengths in (0, 1e5] mm, got "
                              f"{f.tolist() if f.size <= 8 else f.shape}")
    if (not all(isinstance(j, int) and not isinstance(j, bool) and 2 <= j <= 66 for j in noll)
            or len(set(noll)) != len(noll)):
        raise ValidationError(f"{where}: zernike_noll must be distinct Noll indices (integers 2..66), got {noll}")
    if a.shape != (2, 4, len(noll)) or not np.isfinite(a).all() or (np.abs(a) > 1000).any():
        raise ValidationError(f"{where}: zernike_rad must be 2 x 4 x {len(noll)} finite coefficients in "
                              f"[-1000, 1000] rad, got shape {a.shape}")
    return rec


def apply_diversity(twin: DiversityTwin, rec: dict | None) -> DiversityTwin:
    """The twin at a recorded diversity (``diversity.json`` / a card's ``codesign``; None: the device as
    built)."""
    if rec is not None:
        check_diversity(rec)
    with torch.no_grad():
        twin.defocus_waves.zero_()
        twin.zernike_rad.zero_()
        if rec is not None:
            f = torch.tensor(rec["focal_length_mm"], dtype=torch.float64) * 1e-3
            twin.defocus_waves.copy_(focal_to_defocus(f, twin.f0, twin.wavelength, twin.radius))
            a = torch.tensor(rec["zernike_rad"], dtype=torch.float64)
            for i, j in enumerate(rec["zernike_noll"]):
                if j not in twin.modes:
                    raise ValidationError(f"diversity: Noll {j} is not among the twin's modes {list(twin.modes)}")
                twin.zernike_rad[..., twin.modes.index(j)] = a[..., i]
    return twin


def codesign_for_evaluation(unet: nn.Module, rec: dict, dataset: str | Path, device="cpu") -> CodesignNet:
    """A trained co-design U-Net with the diversity it was trained with (its card's ``codesign``), on the
    device of ``dataset``, in evaluation mode: received crops in, phases out; set ``noise_percent`` per
    noise level (the evaluation's Gaussian noise, drawn from the module's generator)."""
    c = rec.get("config", {})
    cfg = CodesignConfig(**{**c, "modes": tuple(c.get("modes", rec["zernike_noll"]))})
    net = build_codesign(unet, cfg, dataset, (0.0, 0.0))
    apply_diversity(net.twin, rec)
    return net.to(device).eval()


def diversity_record(net: CodesignNet, lenses: np.ndarray | None = None) -> dict:
    """The learned diversity as a record (``diversity.json``): per channel its focal length, the Zernike
    terms, and the largest block-to-block step (rad)."""
    d = net.twin.describe()
    with torch.no_grad():
        psi = net.twin.phases()
        ins = net.twin.inside
        sx = ((psi[..., :, 1:] - psi[..., :, :-1]).abs() * (ins[:, 1:] & ins[:, :-1])).amax()
        sy = ((psi[..., 1:, :] - psi[..., :-1, :]).abs() * (ins[1:, :] & ins[:-1, :])).amax()
    d["max_block_step_rad"] = float(max(sx, sy))
    d["config"] = asdict(net.cfg)
    d["aperture_radius_m"] = net.twin.radius
    d["convention"] = ("psi[p, k] = Eq.1 lens(f) - lens(f0) + sum_j a[p, k, j] Z_j(rho, theta); rho = r / "
                       "aperture_radius_m from the aperture centre, theta = atan2(y, x); Noll Z_j, unit RMS")
    return json.loads(json.dumps(d))


def diversity_design_recipe(base_recipe: dict, record: dict) -> dict:
    """A design recipe (TOML dict) of the co-designed device: the base design's, with each lens's learned
    focal length and its Zernike terms (``[x_pol] zernike_noll``, ``zernike_rad`` per lens)."""
    out = json.loads(json.dumps(base_recipe))
    for p, sec in enumerate(("x_pol", "y_pol")):
        out.setdefault(sec, {})
        out[sec]["focal_lengths_mm"] = [round(float(f), 9) for f in record["focal_length_mm"][p]]
        out[sec]["zernike_noll"] = list(record["zernike_noll"])
        out[sec]["zernike_rad"] = [[round(float(a), 9) for a in row] for row in record["zernike_rad"][p]]
    return out
