"""Learned unrolled refinement (deep unfolding, after Pinilla et al., IEEE Signal Processing Magazine
2023): the U-Net's estimate, then ``K`` steps, each of which renders the 8 PSFs of the current estimate
through the differentiable twin, forms the data-misfit gradient with respect to the phase, and lets a
small network map [measured PSFs, predicted PSFs, current estimate, gradient] to an update::

    phi_{k+1} = phi_k - alpha_k g_k / rms(g_k) + net_k(D, P(phi_k), phi_k, g_k / rms(g_k))

``g_k`` is the gradient of the amplitude misfit ``sum (sqrt(P + eps) - sqrt(D + eps))^2`` (the robust
misfit of the retrieval baseline) through the twin.  The twin is written here in real arithmetic with
its **explicit adjoint** (:class:`RealTwin`), not through autograd: the refinement is then one plain
feed-forward graph of matmuls, cos/sin and convolutions, so it runs without autograd at inference and
exports to ONNX whole; training differentiates through the adjoint like any other layer.  Each
``net_k``'s last layer starts at zero and ``alpha_k`` at ``step_init``: an untrained refiner is K
normalised gradient steps from the U-Net, and ``K = 0`` is the U-Net.

The twin's operators (fixed by the device; the approximate twin of :mod:`~metadesign.sensing.twin`, with
``rebin`` and ``samples``) are buffers of the module, so a saved refiner is self-contained but for the
U-Net, which it names by path and sha256 (it is not retrained: the refiner learns what the U-Net and the
twin's approximation leave).  Weights ship as safetensors with a JSON card (:func:`save_refiner`)."""

from __future__ import annotations

import json
import os
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F

from ..cards import has_format, load_into, load_weights, read_card, save_card_model
from ..sensing.device import Device
from ..sensing.twin import twin_operators
from ..sensing.twin_real import RealTwin, real_buffers
from ..tasks import file_key
from ..validation import ValidationError, check_int, check_number
from .model import aperture_mask, check_sizes, field_phase, load_model

__all__ = ["RefineConfig", "RealTwin", "real_twin", "build_refiner", "save_refiner", "load_refiner", "REFINER_FORMAT",
           "twin_support", "is_refiner", "load_network", "deepen_refiner"]

REFINER_FORMAT = "metadesign.refiner/1"


@dataclass(frozen=True)
class RefineConfig:
    steps: int = 3  # K
    rebin: int = 4  # the twin's pupil rebinning (sensing.twin)
    samples: int | None = 1  # the twin's intensity samples per tensor pixel (None: every camera pixel)
    width: int = 32  # channels of each step's network
    features: int = 16  # channels of the PSF-residual encoder
    step_init: float = 0.05  # rad: alpha_k at the start (the first step of the retrieval's Adam)
    eps: float = 1e-3  # the amplitude misfit's regulariser (normalised tensor units)
    dilate: int = 2  # the estimate's support: the aperture dilated by this many crop pixels
    output: str = "phase"  # "field": each step's update is the phase of exp(i phi') + a learned field

    def __post_init__(self):
        check_int("refine.steps", self.steps, 0, 32)
        check_int("refine.rebin", self.rebin, 1, 64)
        if self.samples is not None:
            check_int("refine.samples", self.samples, 1, 16)
        check_int("refine.width", self.width, 1, 512)
        check_int("refine.features", self.features, 1, 512)
        check_number("refine.step_init", self.step_init, 0, 10)
        check_number("refine.eps", self.eps, 0, 1, open_lo=True)
        check_int("refine.dilate", self.dilate, 0, 10)
        if self.output not in ("phase", "field"):
            raise ValidationError(f"refine.output: expected phase or field, got {self.output!r}")

    def to_dict(self) -> dict:
        return asdict(self)


def twin_support(a: int, dilate: int) -> np.ndarray:
    """The estimate's support on the A x A crop: the aperture disc dilated by ``dilate`` pixels (the cubic
    resampling onto the metasurface reaches that far)."""
    from scipy.ndimage import binary_dilation

    ap = aperture_mask(a)
    return binary_dilation(ap, iterations=dilate) if dilate else ap


def _twin_buffers(dev: Device, rebin: int, samples: int | None) -> dict[str, np.ndarray]:
    """The real twin's buffers for ``dev`` (the forward model's operators, :func:`real_buffers`)."""
    return real_buffers(twin_operators(dev.pupil, dev.sensor, dev.geometry, rebin, samples))


class Step(nn.Module):
    """One refinement step's network: a strided encoder of [D, P] onto the crop grid, then three 3x3
    convolutions over [phi, g, support, encoded]; the last one starts at zero.  ``output = "field"``: the
    last convolution also gives a complex field ``c`` and the step returns the phase of ``exp(i phi') + c``
    (``phi'`` the phase step's result), so a step can open or close branch points; ``c = 0`` at the start."""

    def __init__(self, cfg: RefineConfig, a: int):
        super().__init__()
        f, w = cfg.features, cfg.width
        self.a = a
        self.field = cfg.output == "field"
        self.enc = nn.Sequential(nn.Conv2d(16, f, 3, stride=2, padding=1), nn.ReLU(),
                                 nn.Conv2d(f, f, 3, stride=2, padding=1), nn.ReLU())
        self.body = nn.Sequential(nn.Conv2d(3 + f, w, 3, padding=1), nn.ReLU(),
                                  nn.Conv2d(w, w, 3, padding=1), nn.ReLU(),
                                  nn.Conv2d(w, 3 if self.field else 1, 3, padding=1))
        nn.init.zeros_(self.body[-1].weight)
        nn.init.zeros_(self.body[-1].bias)
        self.alpha = nn.Parameter(torch.tensor(float(cfg.step_init)))

    def forward(self, phi, g, data, pred, support):
        e = self.enc(torch.cat([data, pred], dim=1))
        e = F.interpolate(e, size=(self.a, self.a), mode="bilinear", align_corners=True)
        s = support.expand(phi.shape[0], 1, -1, -1)
        x = torch.cat([phi[:, None], g[:, None], s, e], dim=1)
        y = self.body(x)
        out = phi - self.alpha * g + y[:, 0]
        return field_phase(out, y[:, 1], y[:, 2]) if self.field else out

class Refiner(nn.Module):
    """U-Net estimate + ``K`` unrolled steps: (B, 8, S, S) PSFs -> (B, A, A) phase.  ``forward(x, k)``
    stops after ``k`` steps (default all); :meth:`trajectory` returns every step's estimate."""

    def __init__(self, unet, cfg: RefineConfig, buffers: dict[str, np.ndarray]):
        super().__init__()
        a = unet.config.aperture_size
        self.unet = unet
        self.cfg = cfg
        self.config = unet.config  # the input and output grids are the U-Net's
        self.twin = RealTwin(buffers, twin_support(a, cfg.dilate))
        self.register_buffer("mask", torch.tensor(aperture_mask(a), dtype=torch.float32))
        self.steps = nn.ModuleList([Step(cfg, a) for _ in range(cfg.steps)])
        for p in self.unet.parameters():
            p.requires_grad_(False)

    def train(self, mode: bool = True):
        super().train(mode)
        self.unet.eval()  # frozen (its normalisation statistics too)
        return self

    def iterate(self, x, k: int | None = None, start=None):
        """Yield the estimate before the first step (the U-Net's; ``start`` when already computed) and
        after each of the first ``k`` steps (default all), as each is computed."""
        data = x * (8.0 / x.sum(dim=(1, 2, 3), keepdim=True))  # the twin's normalisation
        if start is None:
            with torch.no_grad():
                phi = self.unet(x).float()
        else:
            phi = start.float()
        yield phi
        n = self.twin.support.sum()
        # the twin's products in float32 even under mixed precision (bf16 would lose the PSF's dim wings)
        with torch.autocast(x.device.type, enabled=False):
            data = data.float()
            for step in list(self.steps)[:k]:
                _, g, pred = self.twin.misfit_grad(phi, data, self.cfg.eps)
                rms = torch.sqrt((g * g).sum(dim=(1, 2), keepdim=True) / n + 1e-30)
                phi = step(phi, g / rms, data, pred, self.twin.support) * self.twin.support
                yield phi

    def trajectory(self, x, k: int | None = None, start=None) -> list:
        """Estimates after 0..k steps (on the support; ``* mask`` is what :meth:`forward` returns)."""
        return list(self.iterate(x, k, start))

    def forward(self, x, k: int | None = None, all_steps: bool = False):
        """The estimate after ``k`` steps (default all) on the aperture; ``all_steps``: every step's
        (K + 1, B, A, A), the U-Net's first (deep supervision in training)."""
        if all_steps:
            return torch.stack(self.trajectory(x, k)) * self.mask
        return self.trajectory(x, k)[-1] * self.mask




def real_twin(dev: Device, rebin: int = 4, samples: int | None = 1, dilate: int = 2):
    """The real-arithmetic twin of ``dev`` (:class:`~metadesign.sensing.twin_real.RealTwin`) on the
    refiner's support."""
    return RealTwin(_twin_buffers(dev, rebin, samples), twin_support(dev.crop.size, dilate))


def build_refiner(unet, cfg: RefineConfig, dev: Device | None = None, buffers: dict | None = None):
    """The refiner around a loaded ``unet`` for device ``dev`` (or given twin ``buffers``)."""
    if buffers is None:
        if dev is None:
            raise ValidationError("build_refiner: give the device (or the twin's buffers)")
        check_sizes(unet.config, dev.sensor.tensor_size, dev.crop.size, "refiner's U-Net")
        buffers = _twin_buffers(dev, cfg.rebin, cfg.samples)
    return Refiner(unet, cfg, buffers)


def deepen_refiner(model: Refiner, state: dict, steps: int) -> None:
    """Load a trained refiner's ``state`` with ``steps`` steps into ``model`` (the same step architecture,
    ``steps`` <= its K): the trained steps come first and each appended step starts as the identity
    (``alpha`` 0, its last layer 0), so the deeper refiner computes exactly what the trained one did and
    training its new steps can only start from there (the Net2Net idea, in depth).  A phase refiner's
    steps go into a field refiner's with the field outputs at zero (the same corrections, wrapped)."""
    if not 0 < steps <= len(model.steps):
        raise ValidationError(f"deepen_refiner: {steps} trained steps do not fit a refiner of K = {len(model.steps)}")
    own = model.state_dict()
    missing = [k for k in own if k.startswith("steps.") and int(k.split(".")[1]) < steps and k not in state]
    if missing:
        raise ValidationError(f"deepen_refiner: the trained state lacks {missing[0]}")
    new = {}
    for k, v in state.items():
        if k not in own or (k.startswith("steps.") and int(k.split(".")[1]) >= steps):
            continue
        if v.shape != own[k].shape and ".body." in k and v.shape[1:] == own[k].shape[1:] and v.shape[0] == 1:
            v = torch.cat([v, torch.zeros((own[k].shape[0] - 1, *v.shape[1:]), dtype=v.dtype)])  # phase -> field
        new[k] = v
    model.load_state_dict({**own, **new})
    with torch.no_grad():
        for step in list(model.steps)[steps:]:
            step.alpha.zero_()
            step.body[-1].weight.zero_()
            step.body[-1].bias.zero_()


def save_refiner(refiner, path: str | Path, unet_path: str | Path, card: dict) -> tuple[Path, Path]:
    """The refiner's own weights and twin buffers as ``PATH`` (safetensors), the card as ``PATH.json``
    (:mod:`metadesign.cards`); the U-Net is named (path relative to the card when it can be, and sha256),
    not copied."""
    path, unet_path = Path(path), Path(unet_path)
    state = {k: v for k, v in refiner.state_dict().items() if not k.startswith("unet.")}
    try:
        rel = os.path.relpath(unet_path.resolve(), path.resolve().parent)
    except ValueError:
        rel = str(unet_path.resolve())
    return save_card_model(path, state, REFINER_FORMAT,
                           {"refine": refiner.cfg.to_dict(), "unet": {"path": rel, "weights_sha256": file_key(unet_path)},
                            **card}, trained_on=card.get("dataset"))


def is_refiner(path: str | Path) -> bool:
    """Whether ``path`` (weights or card) is a saved refiner (by its card's format)."""
    return has_format(path, REFINER_FORMAT)


def load_refiner(path: str | Path, device: str = "cpu"):
    """A refiner saved by :func:`save_refiner`, in eval mode, and its card.  Its U-Net (the card's path
    relative to the card, else the file of that name beside the card) is checked against the card's
    sha256; nothing is unpickled."""
    path, card_path, card = read_card(path, REFINER_FORMAT, "refiner")
    try:
        cfg = RefineConfig(**card["refine"])
        unet_ref = card["unet"]
        up = Path(unet_ref["path"])
    except (ValueError, KeyError, TypeError, ValidationError) as exc:
        raise ValidationError(f"{card_path}: not a metadesign refiner card ({exc})") from None
    up = up if up.is_absolute() else path.parent / up
    if not up.is_file() and (path.parent / up.name).is_file():  # copied beside the refiner (a wheel, a release)
        up = path.parent / up.name
    unet, _ = load_model(up, device)
    if file_key(up) != unet_ref.get("weights_sha256"):
        raise ValidationError(f"{path}: its U-Net {up} is not the one it was trained on (sha256 differs)")
    state = load_weights(path, device, "refiner")
    buffers = {k[len("twin."):]: v.numpy() for k, v in state.items()
               if k.startswith("twin.") and k != "twin.support"}
    try:
        ref = build_refiner(unet, cfg, buffers=buffers)
    except (RuntimeError, ValueError, KeyError) as exc:
        raise ValidationError(f"{path}: weights do not fit the card's refiner "
                              f"({str(exc).strip().splitlines()[-1].strip()[:160]})") from None
    load_into(ref, {**{k: v for k, v in ref.state_dict().items() if k.startswith("unet.")}, **state}, path,
              "refiner")
    return ref.to(device).eval(), card


def load_network(path: str | Path, device: str = "cpu"):
    """A U-Net or a refiner (by its card), in eval mode, and its card: both map (B, 8, S, S) PSFs to
    (B, A, A) phases and carry ``.config`` (the U-Net's grids)."""
    return load_refiner(path, device) if is_refiner(path) else load_model(path, device)
