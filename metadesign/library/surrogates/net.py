"""The supercell coupling network as a supercell surrogate: the LPA plus learned two-body terms
(:mod:`metadesign.library.coupling`; the network is :class:`~metadesign.library.coupling_net.Coupling`,
evaluated by :func:`~metadesign.library.coupling_net.coupling_t`).  Importing this module needs no torch;
making a :class:`CouplingNet` loads the network (torch)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .. import surrogates as kernels  # the network's kernels (torch) are imported on first use
from ..coupling import CARD_FORMAT
from ..store import UnitCellLibrary
from .base import Surrogate, check_widths

__all__ = ["CouplingNet"]


class CouplingNet(Surrogate):
    """The coupling network of library ``lib``: the model file at ``path`` (weights + card), else the one
    fitted against ``lib`` in ``library/`` (:func:`~metadesign.library.coupling_net.find_coupling`); or an
    already loaded ``model`` with its file's ``file_card``.

    ``model``: the network (what the device's pupil and the pair tables run); ``file_card``: its file's card
    as written (the device records its ``weights_sha256``); ``path``: the weights."""

    name = "coupling"
    description = ("supercell coupling network: the LPA plus learned two-body terms of each pillar and its row, "
                   "column and diagonal neighbours (torch, differentiable)")
    formats = (CARD_FORMAT,)

    def __init__(self, lib: UnitCellLibrary, path: str | Path | None = None, *, model=None,
                 file_card: dict | None = None):
        super().__init__(lib)
        if model is None:
            model, file_card, path = kernels.find_coupling(lib, path)
        self.model, self.file_card = model, dict(file_card or {})
        self.path = None if path is None else Path(path)

    def t(self, widths: np.ndarray, t_units: np.ndarray | None = None) -> np.ndarray:
        """(n, 2) complex64: :func:`~metadesign.library.coupling_net.coupling_t` (``t_units`` None: the
        network's own float32 look-up of the library, as ``coupling_t``)."""
        return kernels.coupling_t(self.model, check_widths(widths, "coupling"), t_units)

    def pillar_terms(self, widths: np.ndarray, t_units: np.ndarray | None = None) -> np.ndarray:
        """(n, 2, 2, 2 pol) complex64: :func:`~metadesign.library.coupling_net.pillar_terms`."""
        w = check_widths(widths, "coupling")
        return kernels.pillar_terms(self.model, w, self.unit_t(w) if t_units is None else t_units)

    def t_torch(self, widths, t_units=None):
        """(n, 2) complex64 tensor: the network's forward pass (differentiable in the widths); ``t_units``
        a (n, 2, 2, 2 pol) complex tensor or None (the network's own look-up)."""
        import torch

        tu = None if t_units is None else torch.stack([t_units.real, t_units.imag], -1).to(torch.float32)
        r = self.model(widths, tu)
        return torch.complex(r[..., 0], r[..., 1])

    def certification(self) -> dict | None:
        return self.file_card.get("certification")

    def inputs(self) -> dict:
        fc = self.file_card
        return {"library_sha256": (fc.get("library") or {}).get("sha256", self.lib.identity),
                "model": {"path": None if self.path is None else str(self.path), "format": fc.get("format"),
                          "weights_sha256": fc.get("weights_sha256"), "config": fc.get("config"),
                          "trained_on": fc.get("trained_on", fc.get("table"))}}
