"""The reconstruction network: a U-Net after Ronneberger et al. (3x3 convolutions, 2x2 max-pooling,
transposed-convolution up-sampling, skip connections), 8-channel PSF tensor in, one phase map out,
resampled onto the receiver aperture of the turbulence grid and masked there.

The paper keeps Ronneberger's filter counts (base 64, depth 5: 64..1024).  Group normalisation after
each convolution (the paper does not say; per-sample normalisation keeps data-parallel training equal to
one process with the same global batch, which batch norm does not), zero-initialised output
layer: training starts at the flat (uncorrected) phase.  Weights ship as safetensors with a JSON card
(:func:`save_model`, :func:`load_model`); nothing is ever unpickled."""

from __future__ import annotations

from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F

from ..cards import load_into, load_weights, read_card, save_card_model
from ..validation import ValidationError, check_int
from .modal_net import ModalNet, ModalNetConfig, aperture_mask

__all__ = ["UNetConfig", "UNet", "build_unet", "save_model", "load_model", "MODEL_FORMAT", "aperture_mask", "check_fits",
           "check_sizes", "widen_unet", "field_phase", "build_network", "network_config"]

MODEL_FORMAT = "metadesign.unet/1"


@dataclass(frozen=True)
class UNetConfig:
    in_channels: int = 8
    base: int = 64  # filters of the first level (Ronneberger: 64)
    depth: int = 5  # levels including the bottleneck (Ronneberger: 5 -> 64..1024)
    input_size: int = 256  # S of the 8 x S x S tensor
    aperture_size: int = 41  # A: output grid (the receiver-aperture crop of the turbulence grid)
    norm: str = "group"  # "group" (GroupNorm, 8 groups), "batch" or "none"
    output: str = "phase"  # "phase": the head's phase; "field": the angle of exp(i phase) + a learned field

    def __post_init__(self) -> None:
        check_int("model.in_channels", self.in_channels, 1, 64)
        check_int("model.base", self.base, 1, 256)
        check_int("model.depth", self.depth, 2, 8)
        check_int("model.input_size", self.input_size, 8, 4096)
        check_int("model.aperture_size", self.aperture_size, 3, 4096)
        if self.norm not in ("group", "batch", "none"):
            raise ValidationError(f"model.norm: expected group, batch or none, got {self.norm!r}")
        if self.output not in ("phase", "field"):
            raise ValidationError(f"model.output: expected phase or field, got {self.output!r}")
        if self.input_size % 2 ** (self.depth - 1):
            raise ValidationError(f"model.input_size: {self.input_size} must be divisible by 2^(depth-1) = "
                                  f"{2 ** (self.depth - 1)}")


def _norm(cfg: "UNetConfig", c: int) -> list:
    if cfg.norm == "group":
        return [nn.GroupNorm(min(8, c), c)]
    return [nn.BatchNorm2d(c)] if cfg.norm == "batch" else []


def _block(cfg: "UNetConfig", cin: int, cout: int):
    bias = cfg.norm == "none"
    return nn.Sequential(nn.Conv2d(cin, cout, 3, padding=1, bias=bias), *_norm(cfg, cout), nn.ReLU(inplace=True),
                         nn.Conv2d(cout, cout, 3, padding=1, bias=bias), *_norm(cfg, cout), nn.ReLU(inplace=True))


class UNet(nn.Module):
    """The U-Net of :class:`UNetConfig`: (B, 8, S, S) -> (B, A, A) phase (rad), 0 outside the aperture.

    ``output = "field"``: the phase is the angle of ``exp(i phi) + c``, ``phi`` the phase head's and ``c``
    a complex field from a second head (both resampled onto the aperture before they are combined).  A
    continuous ``c`` can vanish where ``exp(i phi) + c`` does, so the output can hold the received
    phase's branch points (optical vortices), which a continuous phase cannot; the second head starts at
    zero, so a phase model loaded into it computes the same phase."""

    def __init__(self, cfg: "UNetConfig"):
        super().__init__()
        self.config = cfg
        ch = [cfg.base * 2**i for i in range(cfg.depth)]
        self.downs = nn.ModuleList([_block(cfg, cfg.in_channels, ch[0])] +
                                   [_block(cfg, ch[i - 1], ch[i]) for i in range(1, cfg.depth)])
        self.ups = nn.ModuleList([nn.ConvTranspose2d(ch[i], ch[i - 1], 2, stride=2)
                                  for i in range(cfg.depth - 1, 0, -1)])
        self.upblocks = nn.ModuleList([_block(cfg, 2 * ch[i - 1], ch[i - 1]) for i in range(cfg.depth - 1, 0, -1)])
        # no bias: a constant phase (piston) changes no loss, so its gradient is rounding noise, which
        # Adam would amplify into a random walk
        self.head = nn.Conv2d(ch[0], 1, 1, bias=False)
        nn.init.zeros_(self.head.weight)  # start at the flat phase: the uncorrected beam
        if cfg.output == "field":
            self.field_head = nn.Conv2d(ch[0], 2, 3, padding=1, bias=False)
            nn.init.zeros_(self.field_head.weight)
        self.register_buffer("mask", torch.tensor(aperture_mask(cfg.aperture_size), dtype=torch.float32))

    def forward(self, x):
        cfg = self.config
        skips = []
        for i, d in enumerate(self.downs):
            x = d(x)
            if i < cfg.depth - 1:
                skips.append(x)
                x = F.max_pool2d(x, 2)
        for up, blk in zip(self.ups, self.upblocks):
            x = up(x)
            x = blk(torch.cat([skips.pop(), x], dim=1))
        phi = self._on_aperture(self.head(x))[:, 0].float()
        if cfg.output == "field":
            c = self._on_aperture(self.field_head(x)).float()
            phi = field_phase(phi, c[:, 0], c[:, 1])
        return phi * self.mask

    def _on_aperture(self, y):
        a = self.config.aperture_size
        return y if y.shape[-1] == a else F.interpolate(y, size=(a, a), mode="bilinear", align_corners=True)


def field_phase(phi, c_re, c_im):
    """The phase of ``exp(i phi) + c``, written ``phi + angle(1 + c exp(-i phi))``: ``phi`` itself (not
    wrapped) where ``c = 0``; where the sum passes through zero, a branch point."""
    cs, sn = torch.cos(phi), torch.sin(phi)
    return phi + torch.atan2(c_im * cs - c_re * sn, 1 + c_re * cs + c_im * sn)


def build_unet(cfg: "UNetConfig") -> UNet:
    """A ``torch.nn.Module``: (B, 8, S, S) -> (B, A, A) phase (rad), 0 outside the aperture."""
    return UNet(cfg)


def network_config(architecture: dict) -> "UNetConfig | ModalNetConfig":
    """The config of a card's ``architecture`` object: a U-Net, or (``kind = "modal"``) the real-time
    :class:`~.modal_net.ModalNet`."""
    if architecture.get("kind", "unet") == "modal":
        return ModalNetConfig(**architecture)
    return UNetConfig(**{k: v for k, v in architecture.items() if k != "kind"})


def build_network(cfg: "UNetConfig | ModalNetConfig"):
    """The network of a config: (B, 8, S, S) -> (B, A, A) phase (rad), 0 outside the aperture."""
    return ModalNet(cfg) if isinstance(cfg, ModalNetConfig) else UNet(cfg)




def widen_unet(model: UNet, factor: int = 2, noise: float = 0.0, seed: int = 0) -> UNet:
    """The same U-Net with ``factor`` x the filters at every level, computing the same function (Net2Net,
    Chen et al. 2016): every channel is repeated ``factor`` times side by side (so a group of the group norm
    holds its old group's channels, repeated: the same statistics) and the weights reading the repeated
    channels are divided by ``factor``.  ``noise``: Gaussian perturbation of the widened weights, relative
    to each tensor's RMS (repeated channels get the same gradients, so training from an exact copy never
    uses the new width)."""
    cfg = model.config
    wide = build_unet(replace(cfg, base=cfg.base * factor))
    kinds = {name: type(m) for name, m in model.named_modules()}
    old = model.state_dict()
    gen = torch.Generator().manual_seed(seed)
    new = {}
    for name, w_new in wide.state_dict().items():
        w = old[name].clone()
        kind = kinds.get(name.rsplit(".", 1)[0])
        if w.shape != w_new.shape:
            reads = 0 if kind is nn.ConvTranspose2d else 1  # the dim of a weight that reads channels
            for d in range(w.ndim):
                if w_new.shape[d] == factor * w.shape[d]:
                    w = w.repeat_interleave(factor, dim=d)
                    if d == reads and name.endswith("weight") and kind in (nn.Conv2d, nn.ConvTranspose2d):
                        w = w / factor
            if noise and w.is_floating_point():
                w = w + noise * w.pow(2).mean().sqrt() * torch.randn(w.shape, generator=gen)
        if w.shape != w_new.shape:
            raise ValueError(f"widen_unet: {name} {tuple(old[name].shape)} cannot become {tuple(w_new.shape)}")
        new[name] = w.to(w_new.dtype)
    wide.load_state_dict(new)
    return wide


def save_model(model, path: str | Path, card: dict) -> tuple[Path, Path]:
    """Weights as ``PATH`` (safetensors) and the card as ``PATH.json`` (:mod:`metadesign.cards`, both
    written atomically); ``card["dataset"]`` (when given) is what it was trained on."""
    return save_card_model(path, model.state_dict(), MODEL_FORMAT,
                           {"architecture": asdict(model.config), **card}, trained_on=card.get("dataset"))


def load_model(path: str | Path, device: str = "cpu"):
    """A model saved by :func:`save_model` (``PATH`` or ``PATH.json``), in eval mode, and its card.
    The weights file is checked against the card's sha256; nothing is unpickled."""
    path, card_path, card = read_card(path, MODEL_FORMAT, "model")
    try:
        if not isinstance(card.get("architecture"), dict):
            raise ValueError("no architecture object")
        cfg = network_config(card["architecture"])
    except (ValueError, KeyError, TypeError) as exc:
        raise ValidationError(f"{card_path}: not a metadesign model card ({exc})") from None
    state = load_weights(path, device, "model")
    model = build_network(cfg)
    load_into(model, state, path, "model")
    return model.to(device).eval(), card


def check_fits(model, info, what: str = "model") -> None:
    """Refuse a model whose input is not the dataset's tensor or whose output is not its received crop
    (``info``: a :class:`~metadesign.reconstruction.dataset.DatasetInfo`), in one line."""
    check_sizes(model.config, info.tensor_size, info.crop()[1], what)


def check_sizes(c: "UNetConfig", tensor_size: int, a: int, what: str = "model") -> None:
    """Refuse an architecture whose input is not ``tensor_size``^2 or whose output is not the ``a``^2 crop."""
    if c.input_size != tensor_size:
        raise ValidationError(f"{what}: model input {c.input_size}^2 does not match the dataset's tensors "
                              f"({tensor_size}^2)")
    if c.aperture_size != a:
        raise ValidationError(f"{what}: model output {c.aperture_size}^2 does not match the dataset's received "
                              f"crop ({a}^2: another turbulence grid or receiver aperture)")

