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

from ..io import atomic_path, atomic_write_text
from ..library.locate import file_sha256
from ..sensing.device import Device
from ..sensing.twin import twin_operators
from ..validation import ValidationError, check_int, check_number
from .model import aperture_mask, check_sizes, load_model

__all__ = ["RefineConfig", "RealTwin", "build_refiner", "save_refiner", "load_refiner", "REFINER_FORMAT",
           "twin_support", "is_refiner", "load_network"]

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

    def to_dict(self) -> dict:
        return asdict(self)


def twin_support(a: int, dilate: int) -> np.ndarray:
    """The estimate's support on the A x A crop: the aperture disc dilated by ``dilate`` pixels (the cubic
    resampling onto the metasurface reaches that far)."""
    from scipy.ndimage import binary_dilation

    ap = aperture_mask(a)
    return binary_dilation(ap, iterations=dilate) if dilate else ap


def _nn():
    import torch
    import torch.nn as nn

    return torch, nn


def _twin_buffers(dev: Device, rebin: int, samples: int | None) -> dict[str, np.ndarray]:
    """The twin's operators as real arrays (real and imaginary parts apart)."""
    ops = twin_operators(dev.pupil, dev.sensor, dev.geometry, rebin, samples)
    out = {}
    for k in ("K", "Ay", "Ax"):
        a = getattr(ops, k)
        out[k + "r"], out[k + "i"] = a.real.astype(np.float32), a.imag.astype(np.float32)
    out["w"], out["Ry"], out["Rx"] = ops.w, ops.Ry, ops.Rx
    out["W"] = ops.W.astype(np.float32)  # real: the cubic interpolation
    return out


def _module_classes():
    torch, nn = _nn()
    F = torch.nn.functional

    class RealTwin(nn.Module):
        """The torch twin (:class:`~metadesign.sensing.twin.TorchTwin`) in real arithmetic: phase on the
        crop (B, A, A) -> normalised tensor (B, 8, S, S), and the explicit adjoint of the amplitude
        misfit.  Buffers: ``Kr, Ki`` (8, N, N), ``Ayr, Ayi`` (8, R, N), ``Axr, Axi`` (8, N, Q), ``w`` (8, R,
        Q), ``Ry`` (S, R), ``Rx`` (S, Q), ``W`` (N, A), ``support`` (A, A)."""

        def __init__(self, buffers: dict[str, np.ndarray], support: np.ndarray):
            super().__init__()
            for k, v in buffers.items():
                self.register_buffer(k, torch.tensor(np.asarray(v, np.float32)))
            self.register_buffer("support", torch.tensor(np.asarray(support, np.float32)))

        def render(self, phi):
            """(normalised tensor P, its sum, and the intermediate fields the adjoint needs)."""
            Cr, Ci = self.support * torch.cos(phi), self.support * torch.sin(phi)
            Wt = self.W.transpose(0, 1)
            Er, Ei = (self.W @ Cr @ Wt)[:, None], (self.W @ Ci @ Wt)[:, None]  # (B, 1, N, N)
            vr, vi = self.Kr * Er - self.Ki * Ei, self.Kr * Ei + self.Ki * Er  # (B, 8, N, N)
            tr, ti = vr @ self.Axr - vi @ self.Axi, vr @ self.Axi + vi @ self.Axr  # (B, 8, N, Q)
            Ur, Ui = self.Ayr @ tr - self.Ayi @ ti, self.Ayr @ ti + self.Ayi @ tr  # (B, 8, R, Q)
            T = self.Ry @ ((Ur * Ur + Ui * Ui) * self.w) @ self.Rx.transpose(0, 1)  # (B, 8, S, S)
            total = T.sum(dim=(1, 2, 3), keepdim=True)
            return T * (8.0 / total), total, (Cr, Ci, Ur, Ui)

        def forward(self, phi):
            return self.render(phi)[0]

        def misfit_grad(self, phi, data, eps: float):
            """(per-sample amplitude misfit, its gradient with respect to ``phi`` (B, A, A), the prediction P).
            The adjoint runs the forward's products backwards (test: finite differences)."""
            P, total, (Cr, Ci, Ur, Ui) = self.render(phi)
            sp, sd = torch.sqrt(P + eps), torch.sqrt(torch.clamp(data, min=0) + eps)
            m = ((sp - sd) ** 2).sum(dim=(1, 2, 3))
            gP = 1.0 - sd / sp  # d m / d P
            gT = (8.0 / total) * (gP - (gP * P).sum(dim=(1, 2, 3), keepdim=True) / 8.0)
            gI = self.Ry.transpose(0, 1) @ gT @ self.Rx  # (B, 8, R, Q)
            a = 2.0 * self.w * gI
            gUr, gUi = a * Ur, a * Ui
            Ayrt, Ayit = self.Ayr.transpose(-1, -2), self.Ayi.transpose(-1, -2)
            gtr, gti = Ayrt @ gUr + Ayit @ gUi, Ayrt @ gUi - Ayit @ gUr  # Ay^H gU
            Axrt, Axit = self.Axr.transpose(-1, -2), self.Axi.transpose(-1, -2)
            gvr, gvi = gtr @ Axrt + gti @ Axit, gti @ Axrt - gtr @ Axit  # gt Ax^H
            gEr = (self.Kr * gvr + self.Ki * gvi).sum(dim=1)  # sum over channels of conj(K) gv
            gEi = (self.Kr * gvi - self.Ki * gvr).sum(dim=1)
            Wt = self.W.transpose(0, 1)
            gCr, gCi = Wt @ gEr @ self.W, Wt @ gEi @ self.W
            return m, Cr * gCi - Ci * gCr, P

    class Step(nn.Module):
        """One refinement step's network: a strided encoder of [D, P] onto the crop grid, then three 3x3
        convolutions over [phi, g, support, encoded]; the last one starts at zero."""

        def __init__(self, cfg: RefineConfig, a: int):
            super().__init__()
            f, w = cfg.features, cfg.width
            self.a = a
            self.enc = nn.Sequential(nn.Conv2d(16, f, 3, stride=2, padding=1), nn.ReLU(),
                                     nn.Conv2d(f, f, 3, stride=2, padding=1), nn.ReLU())
            self.body = nn.Sequential(nn.Conv2d(3 + f, w, 3, padding=1), nn.ReLU(),
                                      nn.Conv2d(w, w, 3, padding=1), nn.ReLU(),
                                      nn.Conv2d(w, 1, 3, padding=1))
            nn.init.zeros_(self.body[-1].weight)
            nn.init.zeros_(self.body[-1].bias)
            self.alpha = nn.Parameter(torch.tensor(float(cfg.step_init)))

        def forward(self, phi, g, data, pred, support):
            e = self.enc(torch.cat([data, pred], dim=1))
            e = F.interpolate(e, size=(self.a, self.a), mode="bilinear", align_corners=True)
            s = support.expand(phi.shape[0], 1, -1, -1)
            x = torch.cat([phi[:, None], g[:, None], s, e], dim=1)
            return phi - self.alpha * g + self.body(x)[:, 0]

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

    return RealTwin, Refiner


def RealTwin(dev: Device, rebin: int = 4, samples: int | None = 1, dilate: int = 2):
    """The real-arithmetic twin of ``dev`` (a ``torch.nn.Module``)."""
    cls, _ = _module_classes()
    return cls(_twin_buffers(dev, rebin, samples), twin_support(dev.crop.size, dilate))


def build_refiner(unet, cfg: RefineConfig, dev: Device | None = None, buffers: dict | None = None):
    """The refiner around a loaded ``unet`` for device ``dev`` (or given twin ``buffers``)."""
    if buffers is None:
        if dev is None:
            raise ValidationError("build_refiner: give the device (or the twin's buffers)")
        check_sizes(unet.config, dev.sensor.tensor_size, dev.crop.size, "refiner's U-Net")
        buffers = _twin_buffers(dev, cfg.rebin, cfg.samples)
    _, cls = _module_classes()
    return cls(unet, cfg, buffers)


def save_refiner(refiner, path: str | Path, unet_path: str | Path, card: dict) -> tuple[Path, Path]:
    """The refiner's own weights and twin buffers as ``PATH`` (safetensors), the card as ``PATH.json``; the
    U-Net is named (path relative to the card when it can be, and sha256), not copied."""
    from safetensors.torch import save_file

    path, unet_path = Path(path), Path(unet_path)
    state = {k: v.detach().cpu().contiguous() for k, v in refiner.state_dict().items() if not k.startswith("unet.")}
    with atomic_path(path) as tmp:
        save_file(state, str(tmp), metadata={"format": REFINER_FORMAT})
    try:
        rel = os.path.relpath(unet_path.resolve(), path.resolve().parent)
    except ValueError:
        rel = str(unet_path.resolve())
    card = {"format": REFINER_FORMAT, "refine": refiner.cfg.to_dict(), "weights_sha256": file_sha256(path),
            "unet": {"path": rel, "weights_sha256": file_sha256(unet_path)}, **card}
    card_path = path.with_name(path.name + ".json")
    atomic_write_text(card_path, json.dumps(card, indent=2, sort_keys=True, default=float))
    return path, card_path


def is_refiner(path: str | Path) -> bool:
    """Whether ``path`` (weights or card) is a saved refiner (by its card's format)."""
    path = Path(path)
    card = path if path.suffix == ".json" else path.with_name(path.name + ".json")
    try:
        return json.loads(card.read_text()).get("format") == REFINER_FORMAT
    except (OSError, ValueError, AttributeError):
        return False


def load_refiner(path: str | Path, device: str = "cpu"):
    """A refiner saved by :func:`save_refiner`, in eval mode, and its card.  Its U-Net (the card's path
    relative to the card, else the file of that name beside the card) is checked against the card's
    sha256; nothing is unpickled."""
    from safetensors import SafetensorError
    from safetensors.torch import load_file

    path = Path(path)
    if path.suffix == ".json":
        path = path.with_suffix("")
    card_path = path.with_name(path.name + ".json")
    if not path.is_file() or not card_path.is_file():
        raise ValidationError(f"{path}: no such refiner (expected the weights and {card_path.name} beside them)")
    try:
        card = json.loads(card_path.read_text())
        if not isinstance(card, dict) or card.get("format") != REFINER_FORMAT:
            raise ValueError(f"format {card.get('format') if isinstance(card, dict) else card!r}")
        cfg = RefineConfig(**card["refine"])
        unet_ref = card["unet"]
    except (ValueError, KeyError, TypeError, UnicodeDecodeError, ValidationError) as exc:
        raise ValidationError(f"{card_path}: not a metadesign refiner card ({exc})") from None
    if file_sha256(path) != card.get("weights_sha256"):
        raise ValidationError(f"{path}: weights do not match the card's sha256 (truncated or replaced)")
    up = Path(unet_ref["path"])
    up = up if up.is_absolute() else path.parent / up
    if not up.is_file() and (path.parent / up.name).is_file():  # copied beside the refiner (a wheel, a release)
        up = path.parent / up.name
    unet, _ = load_model(up, device)
    if file_sha256(up) != unet_ref.get("weights_sha256"):
        raise ValidationError(f"{path}: its U-Net {up} is not the one it was trained on (sha256 differs)")
    try:
        state = load_file(str(path), device=device)
    except (SafetensorError, OSError, ValueError) as exc:
        raise ValidationError(f"{path}: unreadable safetensors ({exc})") from None
    buffers = {k[len("twin."):]: v.numpy() for k, v in state.items()
               if k.startswith("twin.") and k != "twin.support"}
    try:
        ref = build_refiner(unet, cfg, buffers=buffers)
        missing, unexpected = ref.load_state_dict(state, strict=False)
    except (RuntimeError, ValueError, KeyError) as exc:
        raise ValidationError(f"{path}: weights do not fit the card's refiner "
                              f"({str(exc).strip().splitlines()[-1].strip()[:160]})") from None
    missing = [k for k in missing if not k.startswith("unet.")]
    if missing or unexpected:
        raise ValidationError(f"{path}: weights do not fit the card's refiner (missing {missing[:3]}, "
                              f"unexpected {unexpected[:3]})")
    return ref.to(device).eval(), card


def load_network(path: str | Path, device: str = "cpu"):
    """A U-Net or a refiner (by its card), in eval mode, and its card: both map (B, 8, S, S) PSFs to
    (B, A, A) phases and carry ``.config`` (the U-Net's grids)."""
    return load_refiner(path, device) if is_refiner(path) else load_model(path, device)
