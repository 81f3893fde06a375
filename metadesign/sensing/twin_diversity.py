"""The torch twin with a learnable diversity (issue #33): received crops -> the eight PSFs of the device
whose channels carry the diversity of :mod:`metadesign.sensing.diversity`, differentiable in the
diversity's parameters (and in the field), on CPU or CUDA.

At its initial point (``defocus_waves = 0``, ``zernike_rad = 0``) it is the device as built and gives
the tensors of :class:`~metadesign.sensing.twin.TorchTwin` (test: to float32 rounding); its gradients
with respect to the diversity match finite differences (test, float64).
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn as nn

from .diversity import DiversityOperators, defocus_to_power, lens_delta
from .twin import render_tensor

__all__ = ["DiversityTwin"]


class DiversityTwin(nn.Module):
    """A torch backend of the forward-model contract (:mod:`metadesign.sensing.device`: :meth:`psfs`,
    :meth:`pupil_field`, :meth:`from_crop`) whose diversity is learnable.  Parameters: ``defocus_waves`` (2, 4) and ``zernike_rad`` (2, 4, J) of each channel (``[p, k-1]``).
    ``double``: float64 / complex128 throughout (for gradient checks); ``persistent=False`` keeps the
    device's operators out of the state dict (a checkpoint holds the diversity, the dataset the device)."""

    def __init__(self, ops: DiversityOperators, double: bool = False, learn_defocus: bool = True,
                 learn_zernike: bool = True, persistent: bool = True):
        super().__init__()
        cd, rd = (torch.complex128, torch.float64) if double else (torch.complex64, torch.float32)
        self.cdtype, self.rdtype = cd, rd
        self.k0 = 2 * np.pi / ops.wavelength
        self.wavelength, self.radius, self.modes = ops.wavelength, ops.radius, ops.modes
        for name, a, dt in (("G", ops.G, cd), ("P", ops.P, cd), ("Ay", ops.Ay, cd), ("Ax", ops.Ax, cd),
                            ("w", ops.w, rd), ("Ry", ops.Ry, rd), ("Rx", ops.Rx, rd), ("W", ops.W, cd),
                            ("r2", ops.r2, torch.float64), ("Z", ops.Z, torch.float64),
                            ("f0", ops.f0, torch.float64)):
            self.register_buffer(name, torch.tensor(np.asarray(a), dtype=dt), persistent=persistent)
        self.register_buffer("inside", torch.from_numpy(np.asarray(ops.inside, bool)), persistent=False)
        self.defocus_waves = nn.Parameter(torch.zeros(2, 4, dtype=torch.float64), requires_grad=learn_defocus)
        self.zernike_rad = nn.Parameter(torch.zeros(2, 4, len(ops.modes), dtype=torch.float64),
                                        requires_grad=learn_zernike)

    def focal_lengths(self):
        """(2, 4) float64: each channel's focal length (m) at the current diversity."""
        return 1.0 / (1.0 / self.f0 + defocus_to_power(self.defocus_waves, self.wavelength, self.radius))

    def phases(self):
        """(2, 4, N, N) float64: each channel's diversity phase (rad) at the block centres."""
        f = self.focal_lengths()[..., None, None]
        psi = lens_delta(self.r2, self.f0[..., None, None], f, self.k0)
        if self.Z.shape[0]:
            psi = psi + torch.einsum("pkj,jyx->pkyx", self.zernike_rad, self.Z)
        return psi

    def pupils(self):
        """(2, N, N) complex: each polarisation's pupil, its four channels with their diversity summed."""
        psi = self.phases().to(self.rdtype)
        d = torch.complex(torch.cos(psi), torch.sin(psi))
        return (self.G * d).sum(dim=1)

    def psfs(self, e_in):
        """Pupil fields (B, N, N) complex -> (B, 8, S, S) PSF tensors (power, unit incident intensity)."""
        g = self.pupils()
        K = torch.cat([g[0:1].expand(4, -1, -1), g[1:2].expand(4, -1, -1)]) * self.P  # (8, N, N)
        return render_tensor(K, e_in.to(self.cdtype), self.Ay, self.Ax, self.w, self.Ry, self.Rx)

    tensor = psfs  # the name before the contract (metadesign.sensing.device)

    def pupil_field(self, crop):
        """Received crops (B, A, A) -> pupil fields (B, N, N)."""
        return self.W @ crop.to(self.cdtype) @ self.W.transpose(-1, -2)

    def from_crop(self, crop):
        """Received crops (B, A, A) complex -> (B, 8, S, S) PSF tensors."""
        return self.psfs(self.pupil_field(crop))

    def forward(self, crop):
        return self.from_crop(crop)

    def describe(self) -> dict:
        """The diversity as numbers: focal lengths (mm) and Zernike coefficients (rad) per channel."""
        f = self.focal_lengths().detach().cpu().numpy()
        a = self.zernike_rad.detach().cpu().numpy()
        return {"focal_length_mm": (f * 1e3).round(6).tolist(), "defocus_waves":
                self.defocus_waves.detach().cpu().numpy().round(6).tolist(),
                "zernike_noll": list(self.modes), "zernike_rad": a.round(6).tolist()}
