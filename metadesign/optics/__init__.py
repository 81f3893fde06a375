"""Shared scalar optics: band-limited angular spectrum, matrix Fourier transform, Fresnel integral; wrapped
phases (branch points, the irrotational part)."""

from ..lazy import lazy_exports

#: each name -> the submodule that defines it (imported on first use, PEP 562)
_EXPORTS = {
    "SamplingError": "propagation", "angular_spectrum": "propagation", "asm_transfer": "propagation",
    "cexp": "propagation", "check_asm_sampling": "propagation", "fresnel_points": "propagation",
    "grid": "propagation", "mft": "propagation",
    "wrap": "phase", "branch_points": "phase", "irrotational_phase": "phase",
}
__all__ = list(_EXPORTS)
__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)
