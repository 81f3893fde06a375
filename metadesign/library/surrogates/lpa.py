"""The local-periodic approximation as a supercell surrogate: each pillar as in an infinite array of itself,
the supercell's ``t`` the mean of its four pillars' library ``t`` (:func:`~metadesign.library.coupling.lpa_t`,
torch twin :func:`~metadesign.library.peds_torch.lpa_torch`)."""

from __future__ import annotations

import numpy as np

from .. import surrogates as kernels
from ..coupling import lpa_t
from .base import Surrogate, check_widths

__all__ = ["LPA"]


class LPA(Surrogate):
    """The LPA of library ``lib`` (no coupling between pillars)."""

    name = "lpa"
    description = "local-periodic approximation: the mean of the four pillars' unit-cell t (no coupling)"

    def t(self, widths: np.ndarray, t_units: np.ndarray | None = None) -> np.ndarray:
        """(n, 2) complex: the mean of the four pillars' ``t`` (``t_units``, default the library's)."""
        w = check_widths(widths, "lpa")
        return lpa_t(self.unit_t(w) if t_units is None else t_units)

    def pillar_terms(self, widths: np.ndarray, t_units: np.ndarray | None = None) -> np.ndarray:
        """Zero: the LPA attributes no coupling to any pillar."""
        return np.zeros((len(check_widths(widths, "lpa")), 2, 2, 2), np.complex64)

    def t_torch(self, widths):
        """(n, 2) complex128 tensor: :func:`~metadesign.library.peds_torch.lpa_torch` (float64 look-up)."""
        return kernels.lpa_torch(self.lib, widths)  # torch: its module is imported on first use
