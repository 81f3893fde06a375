"""The certified surrogate (PEDS) as a supercell surrogate: the LPA plus calibrated couplings measured by
cheap supercell solves (:mod:`metadesign.library.peds`: :func:`~metadesign.library.peds.certified_t`; torch
twin :func:`~metadesign.library.peds_torch.peds_t_torch`).  Its ``t`` costs RCWA solves (0.1-0.2 core-s per
supercell): it certifies single supercells and samples of a device, not a device's millions of supercells."""

from __future__ import annotations

import tempfile
from pathlib import Path

import numpy as np

from ...execution import SERIAL, Execution
from ...validation import ValidationError
from .. import surrogates as kernels
from ..peds import PEDS_FORMAT, PedsModel, certified_t, find_peds, load_peds
from ..rcwa import Stack
from ..store import UnitCellLibrary
from .base import Surrogate, check_widths

__all__ = ["PEDS"]


class PEDS(Surrogate):
    """The PEDS model of library ``lib``: ``model`` (a :class:`~metadesign.library.peds.PedsModel`), else
    the model file at ``path``, else the one calibrated against ``lib`` in ``library/``.

    ``partial``: the folder its low-fidelity solves are kept in (resumable chunks; the caller removes it),
    None: a temporary folder per call, removed after it; ``run``: how the solves run (workers, scheduler,
    progress); ``stack`` / ``taper``: the low-fidelity solves' pillar stack and ``(sidewall_deg, slices)``
    when not the library's vertical pillars (:func:`~metadesign.library.peds.certified_t`)."""

    name = "peds"
    description = ("certified surrogate (PEDS): the LPA plus calibrated couplings t_super(nG_k) - mean_i "
                   "t_unit,i(nG_k) measured by cheap supercell solves at low truncations")
    formats = (PEDS_FORMAT,)

    def __init__(self, lib: UnitCellLibrary, path: str | Path | None = None, *, model: PedsModel | None = None,
                 partial: str | Path | None = None, run: Execution = SERIAL, stack: Stack | None = None,
                 taper: tuple[float, int] | None = None):
        super().__init__(lib)
        if model is None:
            path = Path(path) if path is not None else find_peds(lib)
            model = load_peds(path, lib)
        self.model, self.path = model, None if path is None else Path(path)
        self.partial = None if partial is None else Path(partial)
        self.run, self.stack, self.taper = run, stack, taper

    def t(self, widths: np.ndarray, t_units: np.ndarray | None = None) -> np.ndarray:
        """(n, 2) complex: :func:`~metadesign.library.peds.certified_t` (solves each supercell at the model's
        levels; ``t_units``: the LPA part's unit cells, default the library's)."""
        w = check_widths(widths, "peds")
        if self.partial is not None:
            return self._t(w, self.partial, t_units)
        with tempfile.TemporaryDirectory(prefix="metadesign-peds-") as tmp:
            return self._t(w, Path(tmp) / "peds", t_units)

    def _t(self, w, partial: Path, t_units):
        r = self.run
        return certified_t(self.lib, w, partial, self.model, workers=r.workers, scheduler=r.scheduler,
                           progress=r.progress, stack=self.stack, t_unit=t_units, taper=self.taper)

    def pillar_terms(self, widths: np.ndarray, t_units: np.ndarray | None = None) -> np.ndarray:
        raise ValidationError("the peds supercell model has no per-pillar terms (its correction belongs to the "
                              "supercell; a device under it is sampled: metadesign library coupling-check --certified)")

    def t_torch(self, widths):
        """(n, 2) complex128 tensor: :func:`~metadesign.library.peds_torch.peds_t_torch` (vertical pillars of
        the library's stack only)."""
        if self.stack is not None or self.taper is not None:
            raise ValidationError("peds: the torch twin solves the library's vertical pillars only (no stack / taper)")
        return kernels.peds_t_torch(self.model, self.lib, widths)  # torch: imported on first use

    def certification(self) -> dict | None:
        return self.model.card.get("certification")

    def inputs(self) -> dict:
        c = self.model.card
        return {"library_sha256": self.model.library_sha256 or self.lib.identity,
                "model": {"path": None if self.path is None else str(self.path), "format": PEDS_FORMAT,
                          "harmonics": list(self.model.harmonics),
                          "coef": [[float(complex(a).real), float(complex(a).imag)] for a in self.model.coef],
                          "trained_on": c.get("trained_on", c.get("table"))}}
