"""Point-source split-step propagation through the screens (numpy and torch).

One grid spacing ``dx`` from source to receiver (unscaled split step), the
band-limited angular-spectrum step of :mod:`metadesign.optics.propagation`
between screens, a super-Gaussian absorbing boundary at every screen.  The
torch version runs the same arithmetic (complex64, batched, differentiable):
the reconstruction stage back-propagates corrected fields through the same
screens, regenerated from their seeds.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.fft as sfft

from ..conventions import fft_centered
from ..optics.propagation import asm_transfer, cexp
from ..validation import ValidationError
from .path import PathModel, Scenario, check_sampling, solve_path
from .screens import ScreenGrid, screens

__all__ = ["SplitStep", "Turbulence", "point_source", "split_step", "split_step_torch", "Sample"]


def point_source(sc: Scenario) -> np.ndarray:
    """Schmidt's sinc-Gaussian point source (Listing 9.5) illuminating a region
    ``DROI = roi_factor * D2`` at the receiver."""
    n, dx = sc.n_grid, sc.dx
    x = fft_centered(n, dx)
    d1 = sc.wavelength * sc.length / (sc.roi_factor * sc.receiver_aperture)
    r2 = x[None, :] ** 2 + x[:, None] ** 2
    env = (np.sinc(x / d1)[None, :] * np.sinc(x / d1)[:, None] * np.exp(-r2 / (4 * d1) ** 2)) / d1**2
    return (env * cexp(-sc.k * r2 / (2 * sc.length))).astype(np.complex64)


def _absorber(sc: Scenario) -> np.ndarray:
    n, dx = sc.n_grid, sc.dx
    x = fft_centered(n, dx)
    r = np.sqrt(x[None, :] ** 2 + x[:, None] ** 2)
    return np.exp(-((r / (0.47 * n * dx)) ** sc.absorber_order)).astype(np.float32)


def split_step(u: np.ndarray, phases: np.ndarray, H: np.ndarray, absorber: np.ndarray,
               reverse: bool = False, active=None) -> np.ndarray:
    """Apply screen 0, propagate, screen 1, ... (``reverse``: the last screen
    first).  ``active[i] = False`` marks a screen known to be zero (skipped)."""
    n_s = len(phases)
    order = range(n_s) if not reverse else range(n_s - 1, -1, -1)
    u = np.array(u, np.complex64)  # a private copy, updated in place
    t = np.empty(u.shape, np.complex64)
    for j, i in enumerate(order):
        if active is None or active[i]:
            np.multiply(np.cos(phases[i]), absorber, out=t.real)  # screen and absorber in one factor
            np.multiply(np.sin(phases[i]), absorber, out=t.imag)
            u *= t
        else:
            u *= absorber
        if j < n_s - 1:
            f = sfft.fft2(u, overwrite_x=True)
            f *= H
            u = sfft.ifft2(f, overwrite_x=True)
    return u


def split_step_torch(u, phases, H, absorber, reverse: bool = False):
    """Torch twin of :func:`split_step` (``u``: (..., n, n) complex tensor; ``phases``: (n_screens, n, n)
    float tensor shared by the batch, or (B, n_screens, n, n), one set per sample of ``u`` (B, n, n);
    ``H`` complex tensor).  The training loss, the stored bucket operators and the tests all propagate
    through this one function."""
    import torch

    per_sample = phases.dim() == 4
    n_s = phases.shape[1] if per_sample else phases.shape[0]
    order = range(n_s) if not reverse else range(n_s - 1, -1, -1)
    for j, i in enumerate(order):
        ph = phases[:, i] if per_sample else phases[i]
        u = u * torch.polar(absorber.expand_as(ph), ph)  # absorber * exp(i phase) in one factor
        if j < n_s - 1:
            u = torch.fft.ifft2(torch.fft.fft2(u) * H)
    return u


@dataclass(frozen=True)
class SplitStep:
    """The turbulent path as one optical element (hcipy's ``OpticalElement`` protocol): ``forward``
    propagates a field from the beacon's plane through the screens in order (screen 0 first, an
    angular-spectrum step ``H`` between consecutive screens, the ``absorber`` at every screen),
    ``backward`` from the receiver's plane through them in reverse.  numpy arrays go through
    :func:`split_step` (scipy FFTs, complex64), torch tensors through :func:`split_step_torch` (autograd,
    GPU); the two agree to float32 rounding (test).  ``active``: the screens known to be non-zero (numpy
    skips the others' phase; None: all).  :class:`Turbulence` holds its path as one (``element``)."""

    H: object
    absorber: object
    active: object = None

    def _run(self, u, phases, reverse: bool):
        if isinstance(u, np.ndarray):
            return split_step(u, phases, self.H, self.absorber, reverse=reverse, active=self.active)
        return split_step_torch(u, phases, self.H, self.absorber, reverse=reverse)

    def forward(self, u, phases):
        return self._run(u, phases, False)

    def backward(self, u, phases):
        return self._run(u, phases, True)


@dataclass
class Sample:
    seed: int
    screens: np.ndarray  # (n_screens, n, n) rad
    field: np.ndarray  # received field on the grid (after the last screen)
    vacuum: np.ndarray  # the same source through vacuum


class Turbulence:
    """A scenario ready to draw samples: path model, screen templates, source, propagator."""

    def __init__(self, sc: Scenario, check: bool = True):
        self.sc = sc
        self.path: PathModel = solve_path(sc)
        self.sampling = check_sampling(sc, self.path)
        if check and not self.sampling.ok:
            raise ValidationError("infeasible turbulence sampling: " + "; ".join(self.sampling.failures))
        self.grid = ScreenGrid(sc.n_grid, sc.dx, sc.inner_scale, sc.outer_scale, sc.subharmonics)
        self.H = asm_transfer((sc.n_grid, sc.n_grid), sc.dx, sc.wavelength, sc.dz)
        self.absorber = _absorber(sc)
        self.source = point_source(sc)
        self.vacuum = split_step(self.source, np.zeros((sc.n_screens, 1, 1), np.float32), self.H, self.absorber,
                                 active=[False] * sc.n_screens)
        self.active = np.isfinite(self.path.r0_screens)
        x = fft_centered(sc.n_grid, sc.dx)
        self.x = x
        self.aperture = (x[None, :] ** 2 + x[:, None] ** 2) <= (sc.receiver_aperture / 2) ** 2

    @property
    def element(self) -> SplitStep:
        """The turbulent path as one optical element (forward: beacon -> receiver; backward: the reverse)."""
        return SplitStep(self.H, self.absorber, self.active)

    def at_rytov(self, rytov: float, check: bool = True) -> "Turbulence":
        """The same scenario at another Rytov number, sharing the grid, source, vacuum field and propagator
        (only the path model is solved again: ~1 ms instead of a vacuum split step)."""
        import copy
        from dataclasses import replace

        if rytov == self.sc.rytov:
            return self
        tb = copy.copy(self)
        tb.sc = replace(self.sc, rytov=rytov)
        tb.path = solve_path(tb.sc)
        tb.sampling = check_sampling(tb.sc, tb.path)
        if check and not tb.sampling.ok:
            raise ValidationError(f"infeasible turbulence sampling at Rytov {rytov:g}: "
                                  + "; ".join(tb.sampling.failures))
        tb.active = np.isfinite(tb.path.r0_screens)
        return tb

    def screens(self, seed: int) -> np.ndarray:
        return screens(self.grid, self.path.r0_screens, seed)

    def sample(self, seed: int) -> Sample:
        ph = self.screens(seed)
        return Sample(seed, ph, self.element.forward(self.source, ph), self.vacuum)

    def collimated(self, field: np.ndarray, mask: bool = True) -> np.ndarray:
        """Received field with the vacuum wavefront removed and the vacuum
        amplitude normalised out (zero outside the receiver aperture if ``mask``)."""
        v = self.vacuum
        out = (field * np.conj(v) / np.maximum(np.abs(v) ** 2, 1e-30)).astype(np.complex64)
        return np.where(self.aperture, out, 0).astype(np.complex64) if mask else out

    def to_metasurface(self, field: np.ndarray, n_out: int) -> np.ndarray:
        """Collimated aperture field demagnified onto the metasurface: the D2
        square resampled (cubic, real and imaginary parts) to ``n_out x n_out``
        samples over the metasurface aperture, zero outside the inscribed circle."""
        from scipy.ndimage import map_coordinates

        sc = self.sc
        c = self.collimated(field, mask=False)  # interpolate first, then cut the pupil
        u = (np.arange(n_out) + 0.5) / n_out - 0.5  # metasurface coordinates / aperture
        pos = u * sc.receiver_aperture / sc.dx + sc.n_grid / 2  # grid index (x = (i - n/2) dx)
        yy, xx = np.meshgrid(pos, pos, indexing="ij")
        re = map_coordinates(c.real, [yy, xx], order=3)
        im = map_coordinates(c.imag, [yy, xx], order=3)
        mask = (u[None, :] ** 2 + u[:, None] ** 2) <= 0.25
        return np.where(mask, re + 1j * im, 0).astype(np.complex64)

    def power_in_bucket(self, received: np.ndarray, mode: str, screens_: np.ndarray) -> float:
        """Normalised PiB at the source after back-propagating a correction of
        the received field through the same screens in reverse order.

        ``mode``: ``"complex"`` (complex-conjugate field), ``"phase"`` (phase
        conjugate, flat amplitude), ``"none"`` (flat, uncorrected).  The bucket
        is the FWHM of the diffraction-limited Airy disk (1.029 lambda L / D2);
        normalised by the same flat beam back-propagated through vacuum."""
        ap = self.aperture
        if mode == "complex":
            u = np.conj(received)
        elif mode == "phase":
            u = np.exp(-1j * np.angle(received))
        elif mode == "none":
            u = np.exp(-1j * np.angle(self.vacuum))
        else:
            raise ValueError(mode)
        u = np.where(ap, u, 0).astype(np.complex64)
        u = u / np.sqrt(np.sum(np.abs(u) ** 2))
        back = self.element.backward(u, screens_)
        bucket, ideal_pib = self._vacuum_bucket()
        return float(np.sum(np.abs(back[bucket]) ** 2) / ideal_pib)

    def _vacuum_bucket(self) -> tuple[np.ndarray, float]:
        """The bucket mask and the PiB of the flat beam back-propagated through
        vacuum: the same for every sample, computed once."""
        if getattr(self, "_bucket", None) is None:
            sc = self.sc
            ideal = np.where(self.aperture, np.exp(-1j * np.angle(self.vacuum)), 0).astype(np.complex64)
            ideal = ideal / np.sqrt(np.sum(np.abs(ideal) ** 2))
            back0 = split_step(ideal, np.zeros((sc.n_screens, 1, 1), np.float32), self.H, self.absorber,
                               reverse=True, active=[False] * sc.n_screens)
            r = np.sqrt(self.x[None, :] ** 2 + self.x[:, None] ** 2)
            bucket = r <= 1.029 * sc.wavelength * sc.length / sc.receiver_aperture / 2
            self._bucket = (bucket, float(np.sum(np.abs(back0[bucket]) ** 2)))
        return self._bucket
