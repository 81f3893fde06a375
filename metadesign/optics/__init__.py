"""Shared scalar optics: band-limited angular spectrum, matrix Fourier transform, Fresnel integral."""

from .propagation import (
           SamplingError,
           angular_spectrum,
           asm_transfer,
           cexp,
           check_asm_sampling,
           fresnel_points,
           grid,
           mft,
)

__all__ = ["SamplingError", "angular_spectrum", "asm_transfer", "cexp", "check_asm_sampling", "fresnel_points",
           "grid", "mft"]
