"""The evaluation's figures of merit, defined once.

NPiB is the power in the turbulence stage's bucket (the beacon-plane Airy core) of the corrected beam,
normalised by that of the ideal beam through vacuum (:class:`~.losses.PiB`): 1 is a perfect correction
of a beam that kept its power; the complex conjugate (which also restores the amplitude the turbulence
scattered) can exceed the phase conjugate.  The **captured fraction** is how much of the gain the phase
conjugate makes over no correction an estimate makes, ``(<est> - <none>) / (<pc> - <none>)`` of the means;
the **gain** is per sample, ``est / none``."""

from __future__ import annotations

import numpy as np

__all__ = ["EVAL_NOISE_SEED", "captured_fraction", "captured_fraction_ci", "gain", "npib_rows"]

#: the seed of the sensor noise of every evaluation (evaluate, compare): the same draws for every estimator
EVAL_NOISE_SEED = 12345

_EPS = 1e-12


def captured_fraction(none, est, pc) -> float:
    """``(mean(est) - mean(none)) / (mean(pc) - mean(none))``: the share of the phase conjugate's gain an
    estimate captures (1: all of it; 0: none)."""
    return float((np.mean(est) - np.mean(none)) / max(np.mean(pc) - np.mean(none), _EPS))


def captured_fraction_ci(none, est, pc, n_boot: int = 2000, level: float = 0.95, seed: int = 0) -> tuple[float, float]:
    """Bootstrap interval of :func:`captured_fraction` (percentile, ``n_boot`` resamplings of the samples with
    replacement, seeded): how well the test set pins the captured fraction down."""
    none, est, pc = (np.asarray(x, np.float64) for x in (none, est, pc))
    rng = np.random.default_rng(seed)
    idx = rng.integers(0, len(none), size=(n_boot, len(none)))
    mn, me, mp = none[idx].mean(1), est[idx].mean(1), pc[idx].mean(1)
    cf = (me - mn) / np.maximum(mp - mn, _EPS)
    a = (1 - level) / 2
    return float(np.quantile(cf, a)), float(np.quantile(cf, 1 - a))


def gain(none, est) -> np.ndarray:
    """Per-sample NPiB gain of an estimate over no correction."""
    return np.asarray(est) / np.maximum(np.asarray(none), _EPS)


def npib_rows(pib, phi, screens, received, complex_conjugate: bool = False, mirror=None) -> dict:
    """Per-sample NPiB (torch tensors on the PiB's device) of an estimate ``phi``, of no correction and of
    the phase (and optionally the complex) conjugate of the true received field, through ``screens``.
    ``mirror`` (B, A, A): a closed-loop residual's mirror phase (``received`` is the field seen through it):
    every correction is the mirror's plus its own, "none" is the mirror alone."""
    import torch

    if mirror is not None:
        mirror = mirror.to(phi.device)
        received = received * torch.polar(torch.ones_like(mirror), mirror)  # the beacon before the mirror
        out = npib_rows(pib, phi + mirror, screens, received, complex_conjugate)
        with torch.no_grad():
            out["none"] = pib.npib_phase(mirror * pib.ap, screens)
        return out
    with torch.no_grad():
        out = {"estimate": pib.npib_phase(phi, screens), "none": pib.npib_phase(torch.zeros_like(phi), screens),
               "phase_conjugate": pib.npib_phase(torch.angle(received) * pib.ap, screens)}
        if complex_conjugate:
            out["complex_conjugate"] = pib.npib_complex(received, screens)
    return out
