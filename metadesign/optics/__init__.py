"""Shared scalar optics: band-limited angular spectrum, matrix Fourier transform, Fresnel integral; wrapped
phases (branch points, the irrotational part); the closed loop's correctors (deformable, tip-tilt and modal
mirrors) and controller (leaky integrator, delay line, transfer functions)."""

from ..lazy import lazy_exports

#: each name -> the submodule that defines it (imported on first use, PEP 562)
_EXPORTS = {
    "SamplingError": "propagation", "angular_spectrum": "propagation", "asm_transfer": "propagation",
    "cexp": "propagation", "check_asm_sampling": "propagation", "fresnel_points": "propagation",
    "grid": "propagation", "mft": "propagation",
    "wrap": "phase", "branch_points": "phase", "irrotational_phase": "phase",
    "LinearCorrector": "dm", "DeformableMirror": "dm", "TipTiltMirror": "dm", "ModalDM": "dm",
    "gaussian_influence": "dm",
    "LeakyIntegrator": "control", "DelayLine": "control", "Controller": "control", "pseudo_open_loop": "control",
    "open_loop_tf": "control", "rejection_tf": "control", "closed_loop_tf": "control",
    "closed_loop_stable": "control", "closed_loop_bandwidth": "control", "characteristic_polynomial": "control",
}
__all__ = list(_EXPORTS)
__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)
