"""Training losses (torch).

* ``pib`` (end to end, the paper's): the predicted phase's conjugate plus the focusing phase (the
  conjugate of the vacuum wavefront) on the receiver aperture is back-propagated through the sample's
  13 screens (regenerated from its seed) in reverse order with the torch split step of the turbulence
  stage; NPiB is the power in the bucket (diameter: the FWHM of the diffraction-limited Airy disk) over
  that of the ideal beam through vacuum, exactly as :meth:`Turbulence.power_in_bucket`.  We minimise
  ``-log NPiB``: NPiB spans 0.01-0.9 across samples, and the log gives every sample the same relative
  weight (1 - NPiB lets the already-easy samples dominate the gradient).
* ``phase``: ``1 - |mean_aperture exp(i (phi_pred - phi_true))|^2``: piston-free and blind to 2 pi
  wraps (branch points make the true phase unwrappable); it is the Strehl-like overlap of the residual.
* ``mse`` (the paper's baseline): mean over the aperture of ``(phi_pred - phi_true - piston)^2``, with
  the wrapped received phase as the target and the mean difference (piston) removed.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

from ..optics.phase import irrotational_phase, wrap
from ..turbulence.propagate import Turbulence, split_step_torch

__all__ = ["PiB", "phase_loss", "mse_loss", "unwrap_ls", "LOSSES", "Loss", "register_loss"]

@dataclass(frozen=True)
class Loss:
    """A training loss: ``fn(ctx, phi, batch, received) -> (loss, per-sample NPiB or None)``; ``ctx`` holds
    the batch's :class:`PiB` (``ctx.pib``) and, for the end-to-end loss, how it meets the screens (the
    training loop's :class:`~metadesign.reconstruction.train` batch context).  ``end_to_end``: the loss
    needs each sample's screens or bucket operators."""

    name: str
    description: str
    fn: Callable
    end_to_end: bool = False


#: the training losses, by the name recipes use (``train.loss``, ``train.pretrain_loss``): one registry,
#: as the estimators' (:func:`register_loss` adds one)
LOSSES: dict[str, Loss] = {}


def register_loss(name: str, description: str, end_to_end: bool = False):
    """Decorator: register ``fn(ctx, phi, batch, received)`` as the loss ``name``."""
    if not name or name in LOSSES:
        raise ValueError(f"loss {name!r}: empty or registered already")

    def deco(fn):
        LOSSES[name] = Loss(name, description, fn, end_to_end)
        return fn

    return deco

# The end-to-end loss is a quadratic form.  Back-propagation through a sample's fixed screens is linear
# in the aperture correction u, so the power in the bucket is ||A u||^2 with A the bucket pixels' rows of
# that operator restricted to the aperture pixels (PiB.bucket_operator: one adjoint propagation per
# bucket pixel).  Then the loss is a small matrix product instead of 12 FFT pairs forward and back.


class PiB:
    """Normalised power in bucket of corrections on the receiver aperture, batched and differentiable."""

    def __init__(self, scenario, crop_start: int, crop_size: int, device="cpu", double: bool = False):
        import torch

        tb = Turbulence(scenario, check=False)
        self.tb = tb
        self.c0, self.a = int(crop_start), int(crop_size)
        sl = slice(self.c0, self.c0 + self.a)
        ap = tb.aperture[sl, sl]
        self.device = torch.device(device)
        vac = np.exp(-1j * np.angle(tb.vacuum[sl, sl])) * ap  # the focusing phase (conjugate of vacuum)
        self.cdtype = torch.complex128 if double else torch.complex64  # double: for gradient checks
        cd, rd = (np.complex128, np.float64) if double else (np.complex64, np.float32)
        self.focus = torch.tensor(vac.astype(cd), device=self.device)
        self.vacuum_conj = torch.tensor((np.conj(tb.vacuum[sl, sl]) * ap).astype(cd), device=self.device)
        self.ap = torch.tensor(ap, device=self.device)
        self.H = torch.tensor(tb.H.astype(cd), device=self.device)
        self.absorber = torch.tensor(tb.absorber.astype(rd), device=self.device)
        bucket, ideal = tb._vacuum_bucket()
        self.bucket = torch.tensor(np.nonzero(bucket.ravel())[0], device=self.device)
        self.ideal = float(ideal)
        self.n = scenario.n_grid

    def npib_field(self, corr, screens):
        """NPiB of aperture corrections ``corr`` (B, A, A) complex (already conjugated): normalised to
        unit power, back-propagated through ``screens`` (B, n_s, n, n)."""
        import torch

        B = corr.shape[0]
        corr = corr * self.ap
        corr = corr / torch.sqrt((corr.abs() ** 2).sum(dim=(-2, -1), keepdim=True))
        u = torch.zeros((B, self.n, self.n), dtype=self.cdtype, device=corr.device)
        u[:, self.c0:self.c0 + self.a, self.c0:self.c0 + self.a] = corr
        back = split_step_torch(u, screens, self.H, self.absorber, reverse=True)
        p = (back.reshape(B, -1)[:, self.bucket].abs() ** 2).sum(dim=1)
        return p / self.ideal

    def npib_phase(self, phi, screens):
        """NPiB of the phase-only correction that conjugates ``phi`` (B, A, A) (the predicted received
        phase, vacuum removed), plus the focusing phase."""
        import torch

        return self.npib_field(torch.polar(torch.ones_like(phi), -phi) * self.focus, screens)

    def npib_complex(self, received, screens):
        """NPiB of the complex conjugate of the received field (amplitude and phase; ``received`` is the
        collimated field: the vacuum field is multiplied back, as the turbulence stage does)."""
        import torch

        return self.npib_field(torch.conj(received) * self.vacuum_conj, screens)

    def bucket_operator(self, screens):
        """``A`` (B, n_bucket, n_aperture) complex: ``bucket(back-propagate(u)) = A @ u[aperture]``.

        The reverse split step is ``P = D_0 T D_1 ... T D_{s-1}`` (``D_i``: absorber x screen i, ``T``:
        the angular-spectrum step); row j of ``A`` is ``(P^H e_j)^H`` on the aperture, and
        ``P^H = D_{s-1}^* T^H ... T^H D_0^*`` with ``T^H`` the step with ``conj(H)``: one forward split
        step with conjugated factors per bucket pixel, all bucket pixels in one batch."""
        import torch

        B = screens.shape[0]
        nb = len(self.bucket)
        out = []
        Hc = torch.conj(self.H)
        ap_idx = torch.nonzero(self.ap.reshape(-1)).reshape(-1)
        rows = torch.arange(self.c0, self.c0 + self.a, device=self.device)
        full_idx = (rows[:, None] * self.n + rows[None, :]).reshape(-1)[ap_idx]
        for b in range(B):
            e = torch.zeros((nb, self.n * self.n), dtype=self.cdtype, device=self.device)
            e[torch.arange(nb), self.bucket] = 1
            v = e.reshape(nb, self.n, self.n)
            # the adjoint of the backward pass: D_0^* first, then T^H, D_1^*, ... (a forward pass through the
            # conjugate screens with the conjugate step)
            v = split_step_torch(v, -screens[b], Hc, self.absorber, reverse=False)
            out.append(torch.conj(v.reshape(nb, -1)[:, full_idx]))
        return torch.stack(out)

    def npib_quadratic(self, A, phi):
        """NPiB of the phase-only correction of ``phi`` from the bucket operators ``A``: ``||A u||^2``."""
        import torch

        ap_idx = torch.nonzero(self.ap.reshape(-1)).reshape(-1)
        corr = (torch.polar(torch.ones_like(phi), -phi) * self.focus).reshape(phi.shape[0], -1)[:, ap_idx]
        corr = corr / torch.sqrt((corr.abs() ** 2).sum(dim=1, keepdim=True))
        return ((A @ corr[..., None])[..., 0].abs() ** 2).sum(dim=1) / self.ideal

    def loss(self, phi, screens=None, A=None):
        """``-log NPiB`` averaged over the batch, and the per-sample NPiB: through the split step over
        ``screens``, or from the samples' bucket operators ``A`` (the quadratic form) when given."""
        npib = self.npib_quadratic(A, phi) if A is not None else self.npib_phase(phi, screens)
        return -torch_log(npib).mean(), npib


def torch_log(x):
    import torch

    return torch.log(torch.clamp(x, min=1e-12))


def phase_loss(phi, received, ap):
    """``1 - |mean_ap exp(i (phi - angle(received)))|^2`` per batch (mean)."""
    import torch

    d = torch.polar(torch.ones_like(phi), phi) * torch.conj(received) / torch.clamp(received.abs(), min=1e-12)
    m = (d * ap).sum(dim=(-2, -1)) / ap.sum()
    return (1 - m.abs() ** 2).mean()


def unwrap_ls(wrapped, mask):
    """Unwrapped phase on ``mask`` (leading batch axes allowed): least-squares integration of the wrapped
    phase differences between mask pixels (Ghiglia & Romero 1994: a Neumann Poisson solve by DCT,
    :func:`~metadesign.optics.phase.irrotational_phase`), then made congruent with the data (``phi +
    wrap(wrapped - phi)``), so a phase whose least-squares estimate is within pi of the truth is recovered
    exactly; piston removed on the mask, zero outside."""
    wrapped = np.asarray(wrapped, np.float64)
    m = np.asarray(mask, bool)
    phi = irrotational_phase(wrapped, m)
    phi = phi + wrap(wrapped - phi)
    piston = (phi * m).sum(axis=(-2, -1), keepdims=True) / m.sum()
    return (phi - piston) * m


def mse_loss(phi, received, ap):
    """The paper's baseline: mean over the aperture of ``(phi - phi_true - piston)^2``, with ``phi_true``
    the received phase unwrapped on the aperture (``unwrap_ls``); piston removed.  Against the wrapped
    phase the MSE is ill-posed (a 2 pi jump costs 4 pi^2 where the field is unchanged) and did not learn
    at all (Table S2 run: captured fraction ~0)."""
    import torch

    mask = ap.detach().cpu().numpy() > 0.5
    true = torch.from_numpy(unwrap_ls(torch.angle(received).detach().cpu().numpy(), mask).astype(np.float32))
    d = (phi - true.to(phi.device)) * ap
    piston = d.sum(dim=(-2, -1), keepdim=True) / ap.sum()
    return ((((d - piston) * ap) ** 2).sum(dim=(-2, -1)) / ap.sum()).mean()


@register_loss("pib", "end to end: -log NPiB of the corrected beam through the sample's own turbulence (PiB)",
               end_to_end=True)
def _pib(ctx, phi, b, rec):
    """Through the stored bucket operators, the per-sample operators computed once (quadratic form), or the
    split step over the sample's screens (``ctx.mode``)."""
    import torch

    pib, device = ctx.pib, ctx.device
    if "mirror" in b:  # a closed-loop residual's correction: the mirror's phase plus the estimate
        phi = phi + b["mirror"].to(phi.device)
    if ctx.stored:
        return pib.loss(phi, A=b["A"].to(device))
    if ctx.quadratic:
        idx = [int(i) for i in b["index"]]
        miss = [k for k, i in enumerate(idx) if i not in ctx.ops]
        if miss:
            with torch.no_grad():
                for k, A in zip(miss, pib.bucket_operator(b["screens"][miss].to(device))):
                    ctx.ops[idx[k]] = A.cpu()
        return pib.loss(phi, A=torch.stack([ctx.ops[i] for i in idx]).to(device))
    return pib.loss(phi, b["screens"].to(device))


@register_loss("phase", "piston-free MSE against the received phase, on the aperture (phase_loss)")
def _phase(ctx, phi, b, rec):
    return phase_loss(phi, rec, ctx.pib.ap), None


@register_loss("mse", "MSE against the least-squares unwrapped received phase (mse_loss; Table S2's baseline)")
def _mse(ctx, phi, b, rec):
    return mse_loss(phi, rec, ctx.pib.ap), None


@register_loss("distill", "piston-free MSE against a teacher network's estimate on the same frames (train.teacher): "
                          "a student of the U-Net or the learned refinement")
def _distill(ctx, phi, b, rec):
    """The teacher's estimate is computed the first time a sample is drawn and kept (per sample index: a later
    epoch's noise draw meets the same target); both are continuous phases, so the MSE is well posed.  A
    closed-loop residual beacon (``loop_gain`` > 0, a ``[closed_loop]`` dataset) lies outside what the teacher
    was trained on: its target is its own least-squares unwrapped received phase (``mse``'s)."""
    import torch

    idx = [int(i) for i in b["index"]]
    lg = b.get("loop_gain")
    own = {k for k in range(len(idx)) if lg is not None and float(lg[k]) > 0}
    miss = [k for k, i in enumerate(idx) if i not in ctx.targets and k not in own]
    if miss:
        with torch.no_grad():
            t = ctx.teacher(b["psf"][miss].to(ctx.device)).float()
        for k, v in zip(miss, t):
            ctx.targets[idx[k]] = v.cpu()
    mine = [k for k in sorted(own) if idx[k] not in ctx.targets]
    if mine:
        mask = ctx.pib.ap.detach().cpu().numpy() > 0.5
        t = unwrap_ls(torch.angle(rec[mine]).detach().cpu().numpy(), mask).astype(np.float32)
        for k, v in zip(mine, t):
            ctx.targets[idx[k]] = torch.from_numpy(v)
    target = torch.stack([ctx.targets[i] for i in idx]).to(phi.device)
    ap = ctx.pib.ap
    d = (phi - target) * ap
    d = (d - d.sum(dim=(-2, -1), keepdim=True) / ap.sum()) * ap
    return ((d ** 2).sum(dim=(-2, -1)) / ap.sum()).mean(), None
