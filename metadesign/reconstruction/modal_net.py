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
(diameter ``A - 1`` pixels, :func:`aperture_mask`, the U-Net's too).

The window (``window``, 0: the whole tensor): the network reads only the centred ``window x window`` square of
each channel (offset ``a = (S - window) / 2``, aligned with the convolutions' ``4 stride`` cells and the linear
path's bins), so a real-time camera stage reads only those pixels
(:class:`~metadesign.sensing.sensor.FrameTensor` ``window``); its input stays ``(B, 8, S, S)``.  The crop is
renormalised to sum 8 (what a camera stage that never reads the rest can compute: the network is independent of
the light outside its window, whatever the input's normalisation; on the datasets' tensors, whose channels sum
to 8 over the whole square, it is the crop times ``1 / (1 - f)``, ``f`` the fraction of light outside).
:func:`crop_to_window` starts a windowed network from a wider one."""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F

from ..optics.dm import DeformableMirror, ModalDM
from ..validation import ValidationError, check_int, check_number

__all__ = ["ModalNetConfig", "ModalNet", "modal_basis", "aperture_mask", "commands_record", "crop_to_window",
           "window_reconstructor"]


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
    window: int = 0           # the centred window x window square of each channel read (0: the whole S x S)

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
        check_int("model.window", self.window, 0, 4096)
        if self.window:
            s, w = self.input_size, self.window
            grid = 4 * self.stride if not self.bin else int(np.lcm(4 * self.stride, self.bin))
            if w >= s or (s - w) % 2 or ((s - w) // 2) % grid:
                raise ValidationError(f"model.window: expected 0 (the whole tensor) or a side below input_size {s} "
                                      f"whose offset (S - window) / 2 is a multiple of 4 x stride and of bin "
                                      f"({grid}), got {w}")

    @property
    def n_commands(self) -> int:
        return int(modal_basis(self).shape[0])

    @property
    def side(self) -> int:
        """The side of the square of each channel the network reads (``window``, else ``input_size``)."""
        return self.window or self.input_size

    @property
    def offset(self) -> int:
        """The window's first row and column in the S x S tensor (0 without a window)."""
        return (self.input_size - self.side) // 2


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
        side = cfg.side // (4 * s)
        self.fc = nn.Linear(4 * w * side * side, cfg.hidden)
        self.head = nn.Linear(cfg.hidden, n)
        nn.init.zeros_(self.head.weight)  # the non-linear path starts at 0
        nn.init.zeros_(self.head.bias)
        if cfg.bin:
            p = cfg.in_channels * (cfg.side // cfg.bin) ** 2
            self.linear = nn.Linear(p, n)
            nn.init.zeros_(self.linear.weight)
            nn.init.zeros_(self.linear.bias)
        self.register_buffer("basis", B.reshape(n, -1))
        self.register_buffer("mask", torch.tensor(aperture_mask(cfg.aperture_size), dtype=torch.float32))

    def commands(self, x):
        """The N commands (rad RMS per Zernike mode, or rad per actuator) of a PSF tensor batch (its 8
        channels summing to 8: a pixel's mean is 1 / S^2, so the convolutions see ``x S^2``, mean 1).  With a
        window: its centred square only, renormalised to sum 8."""
        x = self.read(x)
        c = self.head(F.relu(self.fc(self.features(x).flatten(1))))
        if self.config.bin:
            c = c + self.linear(F.avg_pool2d(x, self.config.bin).flatten(1))
        return c

    def features(self, x):
        """The convolutions' output (B, 4 width, side / (4 stride), side / (4 stride)) of the square read."""
        h = F.relu(self.stem(x * float(self.config.input_size ** 2)))
        h = F.relu(self.conv1(h))
        return F.relu(self.conv2(h))

    def read(self, x):
        """The square the network reads: ``x`` itself, or its centred ``window`` square renormalised to sum 8
        over the channels (a zero crop stays zero)."""
        w = self.config.window
        if not w:
            return x
        a = self.config.offset
        x = x[..., a:a + w, a:a + w]
        return x * (8.0 / x.sum(dim=(1, 2, 3), keepdim=True).clamp_min(1e-12))

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


def crop_to_window(net: ModalNet, window: int) -> ModalNet:
    """A network reading the centred ``window`` square, started from ``net`` (the same architecture reading the
    whole tensor or a wider window): the convolutions as they are; the hidden layer's weights on the window's
    cells (offset ``(side - window) / 2 / (4 stride)`` cells); the linear path's on the window's bins.

    The cells the window drops, and the window's edge cells (whose convolutions see zero padding where ``net``
    saw its neighbours), hold on a dark input the values ``net`` and the new network compute on an all-zero
    tensor; their difference through the hidden layer goes into its bias.  So, exactly (to float rounding), the
    two networks answer the same commands for every input whose 8 channels sum to 8 and which is zero outside
    the window and in its first ``4 stride`` and last ``3 stride`` rows and columns (the receptive field of
    the last convolution's cells that cross the window's edge: a ``3 x 3`` stride-2 convolution with padding 1
    reads one cell before its own and none past it); the linear path alone needs only the zeros outside."""
    src = net.config
    cfg = replace(src, window=window)
    if not window or window >= src.side:
        raise ValidationError(f"model.window: {window} cannot start from a network reading a {src.side} x "
                              f"{src.side} square (a windowed network starts from a wider one)")
    out = ModalNet(cfg)
    st = {k: v.detach().clone() for k, v in net.state_dict().items()}
    fc = st["fc.weight"]
    cells_src, cells = src.side // (4 * src.stride), cfg.side // (4 * cfg.stride)
    c = (src.side - cfg.side) // 2 // (4 * cfg.stride)
    st["fc.weight"] = fc.view(len(fc), -1, cells_src, cells_src)[:, :, c:c + cells, c:c + cells] \
        .reshape(len(fc), -1).contiguous()
    with torch.no_grad():  # the dark cells' values in each network, and their difference into the bias
        dark_src = net.features(torch.zeros(1, src.in_channels, src.side, src.side)).double().flatten()
        dark = net.features(torch.zeros(1, cfg.in_channels, cfg.side, cfg.side)).double().flatten()
        st["fc.bias"] = (st["fc.bias"].double() + fc.double() @ dark_src
                         - st["fc.weight"].double() @ dark).float()
    if cfg.bin:
        lw = st["linear.weight"]
        b_src, b = src.side // cfg.bin, cfg.side // cfg.bin
        o = (src.side - cfg.side) // 2 // cfg.bin
        st["linear.weight"] = lw.view(len(lw), -1, b_src, b_src)[:, :, o:o + b, o:o + b] \
            .reshape(len(lw), -1).contiguous()
    out.load_state_dict(st)
    return out.train(net.training)


def window_reconstructor(interaction: np.ndarray, reference: np.ndarray, cfg: ModalNetConfig,
                         regularisation: float) -> tuple[np.ndarray, np.ndarray]:
    """The linear path's reconstructor ``(R, reference)`` (:meth:`ModalNet.set_linear`) of a windowed network
    from the push-pull interaction matrix ``(P, M)`` and reference ``(P,)`` of the whole tensor binned
    ``cfg.bin`` (:class:`~.linear.LinearReconstructor`): the window's bins, renormalised as the network
    renormalises its crop (to first order about the reference ``I`` of window total ``s``:
    ``d(8 I / s) = 8 / s (dI - I ds / s)``), then the same Tikhonov-regularised least squares
    (``alpha = regularisation x mean diag(M^T M)``)."""
    n, nw, o = cfg.input_size // cfg.bin, cfg.side // cfg.bin, cfg.offset // cfg.bin
    sel = np.zeros((cfg.in_channels, n, n), bool)
    sel[:, o:o + nw, o:o + nw] = True
    sel = sel.ravel()
    ref = np.asarray(reference, np.float64)[sel]
    Mx = np.asarray(interaction, np.float64)[sel]
    tot = ref.sum()
    Mw = 8.0 / tot * (Mx - ref[:, None] * Mx.sum(axis=0)[None, :] / tot)
    mtm = Mw.T @ Mw
    alpha = regularisation * float(np.mean(np.diag(mtm)))
    R = np.linalg.solve(mtm + alpha * np.eye(mtm.shape[0]), Mw.T)
    return R.astype(np.float32), (8.0 * ref / tot).astype(np.float32)
