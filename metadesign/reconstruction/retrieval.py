"""Model-based phase-diversity retrieval on the same 8 PSFs the U-Net sees.

The unknown is the received field on the aperture crop, ``C = s exp(chi + i phi)`` (``s``: the receiver
aperture dilated by ``dilate`` pixels, which the cubic resampling onto the metasurface reaches), rendered
by the torch twin (:mod:`metadesign.sensing.twin`), normalised like the data (8 channels sum to 8), and
fitted to the measured tensor:

* **modal start**, coarse to fine: Zernike coefficients (Noll 2.., radial orders ``modal_orders`` in
  turn, each stage starting from the last) with ``starts`` initial points per sample (zero and random
  low-order draws); the best start per sample is kept.  The cheap twin (``coarse``) is used here.
* **zonal refinement**: per-pixel phase (and log-amplitude ``chi`` when ``amplitude``) from the modal
  result (or from a given start: the hybrid starts from the U-Net), on the finer twin (``fine``).

Misfits: ``amplitude`` (default; the robust one of phase retrieval, Yeh et al. 2015: squared difference of
the square roots of model and data, which weighs dim pixels up and tolerates the model's own error on
bright cores) or ``gaussian`` (the negative log-likelihood of the sensor's additive Gaussian noise,
``sigma = max(noise, floor) x channel peak``).  Adam throughout: its update is elementwise, so a batch
of samples is exactly as many independent retrievals (same result whatever the batch)."""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass
from typing import Callable

import numpy as np

from ..optics.zernike import modes_up_to_order, zernike
from ..sensing.device import Device
from ..sensing.twin import TorchTwin, normalise
from ..validation import ConfigError, check_int, check_number

__all__ = ["RetrievalConfig", "RetrievalContext", "retrieve", "misfit"]

MISFITS = ("amplitude", "gaussian")


@dataclass(frozen=True)
class RetrievalConfig:
    modal_orders: tuple[int, ...] = (2, 4, 6)
    modal_iterations: int = 30  # per order
    zonal_iterations: int = 100
    starts: int = 3
    lr_modal: float = 0.1  # rad (RMS of a mode) per step
    lr_zonal: float = 0.05  # rad per step
    amplitude: bool = True
    misfit: str = "amplitude"
    noise_percent: float = 0.0  # Gaussian noise of the data (the gaussian misfit's sigma)
    noise_floor_percent: float = 1.0
    coarse: tuple[int, int | None] = (4, 1)  # (pupil rebin, samples per tensor pixel) of the modal stage
    fine: tuple[int, int | None] = (2, 2)
    dilate: int = 2
    discrepancy: float = 0.0  # gaussian misfit: a sample stops when its chi^2 per pixel reaches this (0: never;
    # measured on the demo at 5 % noise: stopping at 1.0 lost 0.03 NPiB, fitting on past the noise level gains)
    seed: int = 0

    def __post_init__(self):
        for o in self.modal_orders:
            check_int("retrieval.modal_orders", o, 1, 20)
        check_int("retrieval.modal_iterations", self.modal_iterations, 0, 100000)
        check_int("retrieval.zonal_iterations", self.zonal_iterations, 0, 100000)
        check_int("retrieval.starts", self.starts, 1, 64)
        check_number("retrieval.lr_modal", self.lr_modal, 0, 10, open_lo=True)
        check_number("retrieval.lr_zonal", self.lr_zonal, 0, 10, open_lo=True)
        if self.misfit not in MISFITS:
            raise ConfigError("retrieval.misfit", f"expected one of {', '.join(MISFITS)}, got {self.misfit!r}")
        check_number("retrieval.noise_percent", self.noise_percent, 0, 100)
        check_number("retrieval.noise_floor_percent", self.noise_floor_percent, 0, 100, open_lo=True)
        check_int("retrieval.dilate", self.dilate, 0, 10)
        check_number("retrieval.discrepancy", self.discrepancy, 0, 100)

    @property
    def iterations(self) -> int:
        return self.modal_iterations * len(self.modal_orders) + self.zonal_iterations

    def to_dict(self) -> dict:
        return asdict(self)


@dataclass
class RetrievalContext:
    """Device-side pieces of a retrieval: the two twins, the support, the aperture and the Zernike modes."""

    coarse: object  # TorchTwin
    fine: object  # TorchTwin
    support: object  # (A, A) float tensor
    ap: object  # (A, A) bool numpy
    modes: object  # (M, A, A) float tensor, Noll 2..M+1, unit RMS on the aperture
    device: object = None

    @classmethod
    def build(cls, dev: Device, cfg: RetrievalConfig, device="cpu") -> "RetrievalContext":
        """The context for ``dev`` (:class:`~metadesign.sensing.device.Device`) on torch ``device``."""
        import torch
        from scipy.ndimage import binary_dilation

        coarse = TorchTwin.for_device(dev, *cfg.coarse, device=device)
        fine = TorchTwin.for_device(dev, *cfg.fine, device=device)
        d2 = dev.crop.aperture
        x = dev.crop.coords()
        r = np.hypot(x[None, :], x[:, None])
        ap = r <= d2 / 2
        support = binary_dilation(ap, iterations=cfg.dilate) if cfg.dilate else ap
        th = np.arctan2(x[:, None] + 0 * x[None, :], x[None, :] + 0 * x[:, None])
        n_modes = modes_up_to_order(max(cfg.modal_orders)) - 1
        Z = np.stack([zernike(j, r / (d2 / 2), th) for j in range(2, n_modes + 2)]) * support
        return cls(coarse, fine, torch.tensor(support, dtype=torch.float32, device=device), ap,
                   torch.tensor(Z, dtype=torch.float32, device=device), torch.device(device))


def misfit(model, data, kind: str, sigma_frac: float):
    """Per-sample misfit of normalised model tensors (B, 8, S, S) against data of the same shape."""
    import torch

    if kind == "amplitude":
        eps = 1e-6
        return ((torch.sqrt(model + eps) - torch.sqrt(torch.clamp(data, min=0) + eps)) ** 2).sum(dim=(1, 2, 3))
    peak = data.amax(dim=(-2, -1), keepdim=True)
    return (((model - data) / (sigma_frac * peak)) ** 2).sum(dim=(1, 2, 3)) / 2


def _render(twin, support, phi, chi):
    import torch

    amp = support if chi is None else support * torch.exp(chi)
    return normalise(twin.from_crop(torch.polar(amp, phi)))


def retrieve(psf, ctx: RetrievalContext, cfg: RetrievalConfig, init=None, checkpoints=(),
             on_checkpoint: Callable[[int, object], None] | None = None) -> dict:
    """Retrieve the received phase (B, A, A) from normalised PSF tensors ``psf`` (B, 8, S, S) (torch).

    ``init``: a start phase (B, A, A) that skips the modal stage.  At each iteration count in
    ``checkpoints`` (0 = the start) ``on_checkpoint(it, phi)`` gets the current estimate.  Returns
    ``{"phi", "chi", "misfit" (history, per sample), "seconds"}``."""
    import torch

    t_start = time.perf_counter()
    data = psf.to(ctx.device, torch.float32)
    B = data.shape[0]
    sig = max(cfg.noise_percent, cfg.noise_floor_percent) / 100.0
    checkpoints = set(int(c) for c in checkpoints)
    history = []
    it = 0

    def mark(phi):
        if it in checkpoints and on_checkpoint is not None:
            on_checkpoint(it, phi.detach())

    if init is None:
        S = cfg.starts
        M = ctx.modes.shape[0]
        g = torch.Generator().manual_seed(cfg.seed)
        coef = torch.zeros((S, B, M))
        n0 = modes_up_to_order(min(cfg.modal_orders)) - 1
        if S > 1:
            coef[1:, :, :n0] = torch.randn((S - 1, B, n0), generator=g)
        coef = coef.reshape(S * B, M).to(ctx.device).requires_grad_(True)
        dS = data.repeat(S, 1, 1, 1)
        best = torch.zeros(B, dtype=torch.long, device=ctx.device)

        def phase_of(c):
            return torch.einsum("bm,mij->bij", c, ctx.modes)

        mark(torch.zeros((B,) + tuple(ctx.support.shape), device=ctx.device))
        for order in cfg.modal_orders:
            nm = modes_up_to_order(order) - 1
            active = torch.zeros(M, device=ctx.device)
            active[:nm] = 1
            opt = torch.optim.Adam([coef], lr=cfg.lr_modal)
            for _ in range(cfg.modal_iterations):
                opt.zero_grad(set_to_none=True)
                m = misfit(_render(ctx.coarse, ctx.support, phase_of(coef * active), None), dS, cfg.misfit, sig)
                m.sum().backward()
                opt.step()
                with torch.no_grad():
                    coef.mul_(active)
                    best = m.detach().reshape(S, B).argmin(dim=0)
                    history.append(m.detach().reshape(S, B).min(dim=0).values.cpu().numpy())
                it += 1
                if it in checkpoints:
                    with torch.no_grad():
                        c = coef.detach().reshape(S, B, M)[best, torch.arange(B)]
                        mark(phase_of(c))
        with torch.no_grad():
            c = coef.detach().reshape(S, B, M)
            m = misfit(_render(ctx.fine, ctx.support, phase_of(coef.detach()), None), dS, cfg.misfit, sig)
            best = m.reshape(S, B).argmin(dim=0)
            phi0 = phase_of(c[best, torch.arange(B)])
    else:
        phi0 = init.to(ctx.device, torch.float32) * ctx.support
        mark(phi0)
    phi = phi0.clone().requires_grad_(True)
    params = [phi]
    chi = None
    if cfg.amplitude:
        chi = torch.zeros_like(phi0, requires_grad=True)
        params.append(chi)
    opt = torch.optim.Adam(params, lr=cfg.lr_zonal)
    # Morozov's discrepancy principle: a sample whose misfit reaches the noise level stops (its parameters
    # are held), so the per-pixel freedom does not fit the noise
    target = cfg.discrepancy * data[0].numel() / 2 if (cfg.misfit == "gaussian" and cfg.discrepancy) else None
    done = torch.zeros(B, dtype=torch.bool, device=ctx.device)
    for _ in range(cfg.zonal_iterations):
        opt.zero_grad(set_to_none=True)
        m = misfit(_render(ctx.fine, ctx.support, phi, chi), data, cfg.misfit, sig)
        m.sum().backward()
        if target is not None:
            done |= m.detach() <= target
            held = [p.detach().clone() for p in params]
        opt.step()
        if target is not None and bool(done.any()):
            with torch.no_grad():
                for p, h in zip(params, held):
                    p[done] = h[done]
        history.append(m.detach().cpu().numpy())
        it += 1
        mark(phi)
    return {"phi": (phi.detach() * ctx.support), "chi": None if chi is None else chi.detach(),
            "misfit": np.array(history), "seconds": time.perf_counter() - t_start}
