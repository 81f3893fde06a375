"""The forward model's real-arithmetic torch backend: the twin of :mod:`metadesign.sensing.twin` (the same
operators, :func:`~metadesign.sensing.twin.twin_operators`) with real and imaginary parts apart and an
explicit adjoint of the amplitude misfit, so the learned refinement runs (and exports to ONNX) without
complex tensors or autograd.  The forward model has three backends and one set of operators: numpy
(:func:`metadesign.sensing.forward.sensor_frames` + :func:`~metadesign.sensing.sensor.psf_tensor`),
complex torch (:class:`~metadesign.sensing.twin.TorchTwin`) and this one; they agree to float32 rounding
(test)."""

from __future__ import annotations

import numpy as np
import torch
import torch.nn as nn

from .twin import TwinOperators

__all__ = ["RealTwin", "real_buffers"]


def real_buffers(ops: TwinOperators) -> dict[str, np.ndarray]:
    """The twin's operators as real arrays (real and imaginary parts apart): :class:`RealTwin`'s buffers."""
    out = {}
    for k in ("K", "Ay", "Ax"):
        a = getattr(ops, k)
        out[k + "r"], out[k + "i"] = a.real.astype(np.float32), a.imag.astype(np.float32)
    out["w"], out["Ry"], out["Rx"] = ops.w, ops.Ry, ops.Rx
    out["W"] = ops.W.astype(np.float32)  # real: the cubic interpolation
    return out


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
