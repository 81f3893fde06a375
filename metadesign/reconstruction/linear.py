"""A linear wavefront reconstructor around the flat wavefront (issue #51): the classic fast one.

The interaction matrix is measured by push-pull on the device itself: for each mode ``j`` of a basis
``(M, A, A)`` on the received crop (e.g. unit-rms Zernikes, :meth:`metadesign.optics.dm.ModalDM.for_crop`),
the noise-free PSF tensors of the crop fields ``exp(+/- i a Z_j)``, each normalised as the datasets are
(:func:`~metadesign.reconstruction.dataset.normalise_psf`), binned ``bin x bin`` (sum) and flattened;
column ``j = (I+ - I-) / (2 a)``.  The reference is the flat wavefront's binned tensor.  The reconstructor
is the Tikhonov-regularised least-squares inverse ``R = (M^T M + alpha I)^-1 M^T`` (``alpha =
regularisation x mean diag(M^T M)``), float32.  One frame: one binning (reshape-sum) and one matvec.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..validation import InputError
from .dataset import normalise_psf

__all__ = ["LinearReconstructor", "LinearEstimator", "TipTiltSplitEstimator", "bin_tensor", "render_phase"]


def render_phase(device, phase: np.ndarray) -> np.ndarray:
    """The noise-free PSF tensor (float64, normalised as the datasets are) of the crop field ``exp(i phase)``
    on ``device``: what a push-pull calibration measures."""
    psf, _ = normalise_psf(device.psfs(device.pupil_field(np.exp(1j * phase).astype(np.complex64))))
    return np.asarray(psf, np.float64)


def bin_tensor(psf: np.ndarray, b: int) -> np.ndarray:
    """``(..., C, S, S)`` -> ``(..., C * (S/b)^2)``: each channel summed over ``b x b`` pixel blocks, flattened."""
    p = np.asarray(psf)
    *lead, c, s, s2 = p.shape
    if s != s2 or s % b:
        raise InputError(f"psf: expected (..., C, S, S) with S a multiple of bin {b}, got {p.shape}")
    n = s // b
    return p.reshape(*lead, c, n, b, n, b).sum(axis=(-3, -1)).reshape(*lead, c * n * n)


@dataclass
class LinearReconstructor:
    """``estimate(psf) = R @ (bin(psf) - reference)`` (modal coefficients, rad rms of each basis mode);
    ``phase(psf) = coefficients @ basis`` (rad, on the crop)."""

    R: np.ndarray            # (M, P) float32
    reference: np.ndarray    # (P,) float32
    basis: np.ndarray        # (M, A, A) float32
    bin: int
    interaction: np.ndarray  # (P, M) float32: the measured interaction matrix
    amplitude: float
    regularisation: float

    @classmethod
    def build(cls, device, basis: np.ndarray, amplitude: float = 0.2, bin: int = 8,
              regularisation: float = 1e-2) -> LinearReconstructor:
        """Push-pull interaction matrix of ``basis`` (M, A, A) on ``device`` (a
        :class:`~metadesign.sensing.device.Device` with a receiver crop) around the flat wavefront."""
        basis = np.asarray(basis, np.float64)
        if basis.ndim != 3 or basis.shape[1:] != (device.crop.size, device.crop.size):
            raise InputError(f"basis: expected (M, {device.crop.size}, {device.crop.size}) modes on the crop, "
                                      f"got {basis.shape}")
        if not (amplitude > 0 and regularisation >= 0 and int(bin) >= 1):
            raise InputError(f"linear: expected amplitude > 0, regularisation >= 0, bin >= 1, got "
                                       f"{amplitude!r}, {regularisation!r}, {bin!r}")
        b = int(bin)

        def measure(phase):
            return bin_tensor(render_phase(device, phase).astype(np.float32), b).astype(np.float64)

        ref = measure(np.zeros(basis.shape[1:]))
        cols = [(measure(amplitude * z) - measure(-amplitude * z)) / (2 * amplitude) for z in basis]
        Mx = np.stack(cols, axis=1)  # (P, M)
        mtm = Mx.T @ Mx
        alpha = regularisation * float(np.mean(np.diag(mtm)))
        R = np.linalg.solve(mtm + alpha * np.eye(len(basis)), Mx.T)
        return cls(R.astype(np.float32), ref.astype(np.float32), basis.astype(np.float32), b,
                   Mx.astype(np.float32), float(amplitude), float(regularisation))

    @property
    def n_modes(self) -> int:
        return self.R.shape[0]

    def estimate(self, psf: np.ndarray) -> np.ndarray:
        """Modal coefficients ``(M,)`` (or ``(B, M)``) of a normalised PSF tensor ``(8, S, S)`` (or a batch)."""
        d = bin_tensor(psf, self.bin) - self.reference
        return d @ self.R.T

    def phase(self, psf: np.ndarray) -> np.ndarray:
        """The phase estimate (rad, on the crop) ``(A, A)`` (or ``(B, A, A)``) of a normalised PSF tensor."""
        c = self.estimate(psf)
        M, A, _ = self.basis.shape
        return (c @ self.basis.reshape(M, A * A)).reshape(*c.shape[:-1], A, A)


class LinearEstimator:
    """The reconstructor as an estimator of the loop's frames (what
    :class:`~metadesign.studies.loop.MetasurfaceSensor` calls): ``estimate({"psf": (B, 8, S, S)}) -> (B, A, A)``."""

    name = "linear"

    def __init__(self, reconstructor: LinearReconstructor):
        self.reconstructor = reconstructor

    def estimate(self, batch: dict) -> np.ndarray:
        return self.reconstructor.phase(np.asarray(batch["psf"], np.float32))


class TipTiltSplitEstimator:
    """Another estimator's phase with its tip and tilt read by a separate reader instead (issue #50):
    ``estimate(batch) = main - P(main) + tiptilt.estimate(psf) @ tiptilt.basis``, ``P`` the least-squares
    projection onto the reader's basis (its modes, e.g. the unit-rms Noll 2 and 3 on the crop, fitted over
    the samples where any of them is non-zero).  The reader: anything with ``estimate(psf) -> (B, M)`` and
    ``basis`` (M, A, A): the push-pull :class:`LinearReconstructor` of Noll 2, 3 (the loop's
    ``realtime_tt``) or :class:`~metadesign.reconstruction.peak_tilt.PeakTipTilt`, the in-focus channel's
    far-field peak (``realtime_peak``).  ``estimate({"psf": (B, 8, S, S)}) -> (B, A, A)`` rad."""

    def __init__(self, main, tiptilt):
        self.main, self.tiptilt = main, tiptilt
        self.name = f"{getattr(main, 'name', 'estimator')}+tiptilt"
        B = np.asarray(tiptilt.basis, np.float64)
        M, A, _ = B.shape
        self._support = np.any(B != 0, axis=0).ravel()
        flat = B.reshape(M, A * A)[:, self._support]
        self._fit = np.linalg.pinv(flat.T)  # (M, n_support): coefficients of a phase's support samples
        self._basis = B.reshape(M, A * A)

    def estimate(self, batch: dict) -> np.ndarray:
        phase = np.asarray(self.main.estimate(batch), np.float64)
        shape = phase.shape
        flat = phase.reshape(shape[0], -1)
        own = flat[:, self._support] @ self._fit.T  # (B, M): the main estimate's tip and tilt
        tt = np.asarray(self.tiptilt.estimate(np.asarray(batch["psf"], np.float32)), np.float64).reshape(shape[0], -1)
        return (flat + (tt - own) @ self._basis).reshape(shape).astype(np.float32)
