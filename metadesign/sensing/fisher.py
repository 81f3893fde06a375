"""Fisher information of the sensor frame (issue #33): how much the eight spots say about the received
wavefront, whatever estimator reads them.

For a frame whose expected photo-electron counts are ``mu(theta)`` (``theta``: the wavefront's
parameters, here Zernike coefficients in rad) with shot noise and Gaussian read noise ``sigma`` (e-),
the Fisher matrix is

    F_ij = sum_pixels d mu / d theta_i  d mu / d theta_j / (mu + sigma^2)

(exact for shot noise alone; with read noise the usual Gaussian approximation of the Poisson-Gaussian
likelihood).  Its inverse bounds the covariance of any unbiased estimator (Cramer-Rao): ``crb(F)`` is the
smallest achievable variance of each mode (rad^2).  ``photons`` is the frame's total count for the
unperturbed wavefront (``theta = 0``); light that a perturbation moves off the sensor is lost, so flux
changes carry information too.

:func:`fisher_information` takes any differentiable model (the closed-form test uses a Gaussian pupil);
:func:`zernike_fisher` applies it to the sensor twin and a set of received fields (the expected
information over turbulence is their mean).
"""

from __future__ import annotations

from typing import Callable

import numpy as np
import torch

from ..optics.zernike import zernike

__all__ = ["fisher_information", "crb", "crop_zernike_basis", "zernike_fisher"]


def fisher_information(model: Callable, theta0, photons: float, read_noise_e: float = 0.0) -> np.ndarray:
    """(M, M) Fisher matrix of ``model`` (``theta`` (M,) float64 -> non-negative intensities, any shape)
    at ``theta0``, the intensities scaled so that ``model(theta0)`` holds ``photons`` counts.  The
    Jacobian is forward-mode (M passes, whatever the frame size)."""
    from torch.func import jacfwd

    t0 = torch.as_tensor(theta0, dtype=torch.float64)

    def f(t):
        out = model(t).reshape(-1).to(torch.float64)
        return out, out.detach()

    J, i0 = jacfwd(f, has_aux=True)(t0)  # (P, M) and the intensities, from one forward pass per mode
    scale = float(photons) / float(i0.sum())
    J, mu = J * scale, i0 * scale
    var = mu + float(read_noise_e) ** 2
    keep = var > 0
    Jw = J[keep] / torch.sqrt(var[keep])[:, None]
    return (Jw.T @ Jw).detach().cpu().numpy()


def crb(F: np.ndarray, rcond: float = 1e-10) -> np.ndarray:
    """The Cramer-Rao bound of each parameter (rad^2): the diagonal of ``F``'s inverse on the subspace the
    frame sees (eigenvalues above ``rcond`` x the largest); a parameter with a component in the unseen
    subspace (piston; defocus for an in-focus symmetric pupil) has an infinite bound."""
    F = np.asarray(F, np.float64)
    lam, V = np.linalg.eigh(0.5 * (F + F.T))
    seen = lam > rcond * max(lam.max(), 0.0)
    out = (V[:, seen] ** 2 / lam[seen]).sum(axis=1)
    out[(V[:, ~seen] ** 2).sum(axis=1) > 1e-6] = np.inf
    return out


def crop_zernike_basis(modes, crop_start: int, crop_size: int, n_grid: int, dx: float,
                       receiver_aperture: float) -> np.ndarray:
    """(len(modes), A, A) float64 Zernike terms (Noll ``modes``) on the received crop: the turbulence grid
    ``x = (i - n/2) dx`` (FFT-centred), unit disk = the receiver aperture, 0 outside."""
    x = (crop_start + np.arange(crop_size) - n_grid / 2) * dx
    rho = np.hypot(x[None, :], x[:, None]) / (receiver_aperture / 2)
    th = np.arctan2(np.broadcast_to(x[:, None], rho.shape), np.broadcast_to(x[None, :], rho.shape))
    return np.stack([np.where(rho <= 1, zernike(int(j), rho, th), 0.0) for j in modes])


def zernike_fisher(render: Callable, fields, basis: np.ndarray, photons: float, read_noise_e: float = 0.0,
                   normalise_sum: bool = False) -> np.ndarray:
    """(B, M, M) Fisher matrices of the frame ``render(field)`` ((1, A, A) complex -> (1, 8, S, S)) for the
    Zernike terms ``basis`` (M, A, A) of the phase added to each received field of ``fields`` (B, A, A),
    at ``photons`` counts per frame.  ``normalise_sum``: the model sees the frame normalised to a fixed
    sum (as the network does), so total flux carries no information."""
    Z = torch.as_tensor(np.asarray(basis), dtype=torch.float64)
    out = []
    for f in np.asarray(fields):
        f0 = torch.as_tensor(f).to(torch.complex128)

        def model(theta, f0=f0):
            ph = torch.einsum("m,myx->yx", theta, Z)
            field = f0 * torch.complex(torch.cos(ph), torch.sin(ph))
            t = render(field[None])[0]
            return t / t.sum() if normalise_sum else t

        out.append(fisher_information(model, np.zeros(len(Z)), photons, read_noise_e))
    return np.stack(out)
