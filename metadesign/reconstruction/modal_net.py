"""The real-time estimator (issue #51): a small network whose output is N modal or actuator commands, not a
full-resolution phase map.

A U-Net answers a phase on every one of the A x A crop's pixels and costs ~9 ms on one core; a deformable
mirror takes N commands.  :class:`ModalNet` reads the 8 PSFs and answers the N commands directly
(:meth:`ModalNet.commands`); its phase (``forward``, what training, evaluation and export see) is the
commands through a fixed basis ``B`` (N, A, A) on the crop, so the captured fraction is measured through the
same fit as every other estimator.

Two paths add (Landman and Haffert, Opt. Express 28, 16644, 2020: a network that corrects only the
non-linear part of a linear reconstructor did better in closed loop than a network alone):

* the **linear path**: each channel summed over ``bin x bin`` pixel blocks, one matrix (``linear``), which
  ``linear_init`` sets to the regularised least-squares reconstructor measured by push-pull on the device
  around the flat wavefront (:class:`~.linear.LinearReconstructor`: the network then starts as the classic
  AO reconstructor, exactly);
* the **non-linear path**: a strided convolution stem (``stride`` x ``stride`` patches, no overlap), two
  3 x 3 stride-2 convolutions, a hidden layer and the commands layer, zero-initialised (it starts at 0).

The basis (``basis``): ``"zernike"``, Noll modes 2..``modes`` + 1 (the modal corrector of
:class:`~metadesign.optics.dm.ModalDM`, no piston) made orthonormal on the sampled disc (unit RMS each), or ``"dm"``, the Gaussian influence functions
of a zonal mirror with ``actuators`` across the disc and ``coupling`` at the neighbour
(:class:`~metadesign.optics.dm.DeformableMirror`).  The disc is the crop's inscribed aperture
(diameter ``A - 1`` pixels, :func:`aperture_mask`, the U-Net's too)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F

from ..optics.dm import DeformableMirror, ModalDM
from ..validation import ValidationError, check_int, check_number

__all__ = ["ModalNetConfig", "ModalNet", "modal_basis", "aperture_mask", "commands_record"]


def aperture_mask(a: int) -> np.ndarray:
    """The receiver aperture on the A x A crop: the inscribed disc (A = 2 floor(R/dx) + 1), every network's
    output mask (:mod:`.model` re-exports it)."""
    r = np.arange(a) - (a - 1) / 2
    return (r[None, :] ** 2 + r[:, None] ** 2) <= ((a - 1) / 2) ** 2 + 1e-9


@dataclass(frozen=True)
class ModalNetConfig:
    kind: str = "modal"
    in_channels: int = 8
    input_size: int = 64      # S of the 8 x S x S tensor
    aperture_size: int = 41   # A: the crop the basis lives on
    basis: str = "zernike"    # "zernike" | "dm"
    modes: int = 100          # zernike: Noll 2 .. modes + 1
    actuators: int = 12       # dm: actuators across the disc
    coupling: float = 0.15    # dm: influence at the neighbouring actuator
    stride: int = 4           # the stem's patch size
    width: int = 32           # the stem's filters (then 2x, 4x)
    hidden: int = 256         # the hidden layer
    bin: int = 8              # the linear path's pixel blocks (0: no linear path)

    def __post_init__(self) -> None:
        if self.kind != "modal":
            raise ValidationError(f"model.kind: expected modal, got {self.kind!r}")
        check_int("model.in_channels", self.in_channels, 1, 64)
        check_int("model.input_size", self.input_size, 8, 4096)
        check_int("model.aperture_size", self.aperture_size, 3, 4096)
        if self.basis not in ("zernike", "dm"):
            raise ValidationError(f"model.basis: expected zernike or dm, got {self.basis!r}")
        check_int("model.modes", self.modes, 1, 2000)
        check_int("model.actuators", self.actuators, 2, 128)
        check_number("model.coupling", self.coupling, 0, 1, open_lo=True, open_hi=True)
        check_int("model.stride", self.stride, 1, 64)
        check_int("model.width", self.width, 1, 1024)
        check_int("model.hidden", self.hidden, 1, 8192)
        check_int("model.bin", self.bin, 0, 4096)
        if self.input_size % (4 * self.stride):
            raise ValidationError(f"model.stride: input_size {self.input_size} must be divisible by 4 x stride "
                                  f"= {4 * self.stride}")
        if self.bin and self.input_size % self.bin:
            raise ValidationError(f"model.bin: input_size {self.input_size} must be divisible by bin {self.bin}")

    @property
    def n_commands(self) -> int:
        return int(modal_basis(self).shape[0])


def modal_basis(cfg: ModalNetConfig) -> np.ndarray:
    """The basis (N, A, A) float32 of ``cfg`` on the crop (zero outside the disc), rad per unit command."""
    a = cfg.aperture_size
    x = np.arange(a) - (a - 1) / 2
    m = aperture_mask(a)
    if cfg.basis == "dm":
        B = DeformableMirror(x, a - 1 + 1e-9, n_act=cfg.actuators, coupling=cfg.coupling).influence
        return (np.asarray(B, np.float32) * m).astype(np.float32)
    # Zernikes sampled on a 41-pixel disc are not orthogonal at high order (~20 % cross-talk at Noll 100):
    # Gram-Schmidt in Noll order (QR, signs kept) makes each command the RMS of its own mode on the disc
    Z = np.asarray(ModalDM(x, a - 1 + 1e-9, n_modes=cfg.modes).influence, np.float64)[:, m]  # (N, npix)
    q, r = np.linalg.qr(Z.T)
    q = q * np.sign(np.diag(r))[None, :] * np.sqrt(m.sum())
    out = np.zeros((cfg.modes, a, a), np.float32)
    out[:, m] = q.T
    return out


class ModalNet(nn.Module):
    """(B, 8, S, S) -> commands (B, N) (:meth:`commands`) and their phase (B, A, A) rad (``forward``)."""

    def __init__(self, cfg: ModalNetConfig):
        super().__init__()
        self.config = cfg
        B = torch.from_numpy(modal_basis(cfg))
        n = B.shape[0]
        w, s = cfg.width, cfg.stride
        self.stem = nn.Conv2d(cfg.in_channels, w, s, stride=s)
        self.conv1 = nn.Conv2d(w, 2 * w, 3, stride=2, padding=1)
        self.conv2 = nn.Conv2d(2 * w, 4 * w, 3, stride=2, padding=1)
        side = cfg.input_size // (4 * s)
        self.fc = nn.Linear(4 * w * side * side, cfg.hidden)
        self.head = nn.Linear(cfg.hidden, n)
        nn.init.zeros_(self.head.weight)  # the non-linear path starts at 0
        nn.init.zeros_(self.head.bias)
        if cfg.bin:
            p = cfg.in_channels * (cfg.input_size // cfg.bin) ** 2
            self.linear = nn.Linear(p, n)
            nn.init.zeros_(self.linear.weight)
            nn.init.zeros_(self.linear.bias)
        self.register_buffer("basis", B.reshape(n, -1))
        self.register_buffer("mask", torch.tensor(aperture_mask(cfg.aperture_size), dtype=torch.float32))

    def commands(self, x):
        """The N commands (rad RMS per Zernike mode, or rad per actuator) of a PSF tensor batch (its 8
        channels summing to 8: a pixel's mean is 1 / S^2, so the convolutions see ``x S^2``, mean 1)."""
        h = F.relu(self.stem(x * float(self.config.input_size ** 2)))
        h = F.relu(self.conv1(h))
        h = F.relu(self.conv2(h))
        c = self.head(F.relu(self.fc(h.flatten(1))))
        if self.config.bin:
            c = c + self.linear(F.avg_pool2d(x, self.config.bin).flatten(1))
        return c

    def phase(self, c):
        a = self.config.aperture_size
        return (c @ self.basis).view(-1, a, a)

    def forward(self, x):
        return self.phase(self.commands(x))

    def set_linear(self, R: np.ndarray, reference: np.ndarray) -> None:
        """The linear path from a reconstructor ``c = R @ (sum-binned psf - reference)`` with this network's
        basis and bin (:class:`~.linear.LinearReconstructor`): the average pool is the sum / bin^2."""
        b = self.config.bin
        if not b:
            raise ValidationError("model.bin: 0 (no linear path) cannot take a linear reconstructor")
        R = torch.as_tensor(np.asarray(R, np.float32))
        ref = torch.as_tensor(np.asarray(reference, np.float32))
        if tuple(R.shape) != tuple(self.linear.weight.shape):
            raise ValidationError(f"linear reconstructor: shape {tuple(R.shape)} does not match the network's "
                                  f"{tuple(self.linear.weight.shape)} (another basis or bin)")
        with torch.no_grad():
            self.linear.weight.copy_(R * b * b)
            self.linear.bias.copy_(-(R @ ref))


def commands_record(cfg: ModalNetConfig) -> dict:
    """What a modal network's commands are, for its card and its deployment contract."""
    a = cfg.aperture_size
    if cfg.basis == "zernike":
        what = (f"rad RMS of each of Noll Zernikes 2..{cfg.modes + 1} made orthonormal (Gram-Schmidt in Noll order) "
                f"on the disc of diameter {a - 1} samples inscribed in the {a} x {a} crop")
    else:
        what = (f"rad at each actuator of a zonal mirror, {cfg.actuators} actuators across the disc of diameter "
                f"{a - 1} samples (Fried geometry), Gaussian influence {cfg.coupling:g} at the neighbour")
    return {"count": cfg.n_commands, "basis": cfg.basis, "meaning": what,
            "phase": "phase = commands @ basis (the network's phase output); the correction is its conjugate"}
