"""The supercell surrogate protocol: one interface for every model of a 2 x 2 supercell's transmission.

Convention (stated once, every implementation follows it):

* ``widths``: (n, 2, 2, 2) metres, ``widths[k, r, c] = (wx, wy)`` of the pillar at row ``r``, column ``c`` of
  supercell ``k`` (the layout of :func:`~metadesign.library.coupling.transpose_supercells` and every table);
* ``t(widths)``: (n, 2) complex, the supercell's zeroth-order transmission per polarisation (x, y), what
  the sensor sees of it (only the 0th order propagates at this pitch);
* ``t_units`` (optional, (n, 2, 2, 2 pol) complex): the four pillars' unit-cell ``t`` when they are not the
  library's (an as-fabricated look-up: etch depth, sidewall), else the library's bilinear look-up;
* ``pillar_terms(widths, t_units)``: (n, 2, 2, 2 pol) complex, each pillar's coupling term where the model
  attributes one (its effective ``t`` is ``t_units + term``, and ``t`` is the mean of those): what the
  device's pupil needs, pillar by pillar.  The LPA's are zero; the coupling network's are its learned terms;
  PEDS has none (its correction belongs to the supercell, not to a pillar): it refuses, one line;
* ``t_torch(widths)``: the same ``t`` over torch tensors, differentiable in the widths (complex);
* ``card()``: what the model is, the identities of its inputs (the library's sha256, the model file's) and
  its certification (as recorded when it was fitted, or None);
* ``certify(widths, t_ref)``: its error against reference solves ``t_ref`` (n, 2) in the project's metric
  (:func:`~metadesign.library.coupling.relative_error`: ``|t - t_ref|`` over the four pillars' rms library
  ``|t|``): mean, median, p90 and max per polarisation, and both polarisations' mean and p90.

Implementations: :class:`~metadesign.library.surrogates.lpa.LPA`,
:class:`~metadesign.library.surrogates.net.CouplingNet`, :class:`~metadesign.library.surrogates.peds.PEDS`;
the resolver :func:`~metadesign.library.surrogates.registry.surrogate` picks one by name or model file.
Numpy only here (the torch twins import torch when called)."""

from __future__ import annotations

from typing import Protocol, runtime_checkable

import numpy as np

from ...validation import ValidationError
from ..coupling import relative_error
from ..store import UnitCellLibrary, interpolate_t

__all__ = ["SupercellSurrogate", "Surrogate", "METRIC", "error_stats", "check_widths"]

METRIC = "|t_model - t_ref| / rms_i |t_i| (the four pillars' rms library |t|), per polarisation"


@runtime_checkable
class SupercellSurrogate(Protocol):
    """What every supercell model offers (see the module's docstring for the array conventions)."""

    name: str
    lib: UnitCellLibrary

    def t(self, widths: np.ndarray, t_units: np.ndarray | None = None) -> np.ndarray: ...

    def pillar_terms(self, widths: np.ndarray, t_units: np.ndarray | None = None) -> np.ndarray: ...

    def t_torch(self, widths): ...

    def card(self) -> dict: ...

    def certify(self, widths: np.ndarray, t_ref: np.ndarray) -> dict: ...


def check_widths(widths, who: str) -> np.ndarray:
    """``widths`` as (n, 2, 2, 2) float metres, else one line."""
    w = np.asarray(widths, float)
    if w.ndim != 4 or w.shape[1:] != (2, 2, 2):
        raise ValidationError(f"{who}: widths must be (n, 2, 2, 2) metres, got {w.shape}")
    return w


def error_stats(e: np.ndarray) -> dict:
    """Mean, median, p90 and max per polarisation of errors (n, 2), and both polarisations' mean and p90 (the
    figures every certification quotes)."""
    e = np.asarray(e, float)
    return {"mean": e.mean(0).tolist(), "median": np.median(e, 0).tolist(), "p90": np.percentile(e, 90, 0).tolist(),
            "max": e.max(0).tolist(), "mean_both": float(e.mean()), "p90_both": float(np.percentile(e, 90))}


class Surrogate:
    """The shared part of the implementations: the library look-up, :meth:`certify`, the card's frame."""

    name = ""
    description = ""

    def __init__(self, lib: UnitCellLibrary):
        self.lib = lib

    def unit_t(self, widths: np.ndarray) -> np.ndarray:
        """(n, 2, 2, 2 pol) complex64: the pillars' library ``t`` (bilinear, clamped)."""
        w = np.asarray(widths, float)
        return interpolate_t(self.lib, w[..., 0], w[..., 1])[0]

    def t(self, widths: np.ndarray, t_units: np.ndarray | None = None) -> np.ndarray:  # pragma: no cover
        raise NotImplementedError

    def pillar_terms(self, widths: np.ndarray, t_units: np.ndarray | None = None) -> np.ndarray:
        raise ValidationError(f"the {self.name} supercell model has no per-pillar coupling terms")

    def t_torch(self, widths):
        raise ValidationError(f"the {self.name} supercell model has no torch twin")

    def certification(self) -> dict | None:
        """The certification recorded with the model (None: none recorded)."""
        return None

    def inputs(self) -> dict:
        """The identities of what the model rests on (the library; the model file)."""
        return {"library_sha256": self.lib.identity}

    def card(self) -> dict:
        return {"surrogate": self.name, "description": self.description, **self.inputs(),
                "certification": self.certification()}

    def certify(self, widths: np.ndarray, t_ref: np.ndarray, t_units: np.ndarray | None = None) -> dict:
        """This model's error on supercells ``widths`` against reference solves ``t_ref`` (n, 2) complex, in
        units of the four pillars' rms library ``|t|`` (``t_units``: the pillars' unit-cell ``t``, passed to
        :meth:`t` too; default the library's)."""
        w = check_widths(widths, f"{self.name}.certify")
        ref = np.asarray(t_ref)
        if ref.shape != (len(w), 2):
            raise ValidationError(f"{self.name}.certify: t_ref must be ({len(w)}, 2) complex, got {ref.shape}")
        tu = self.unit_t(w) if t_units is None else np.asarray(t_units)
        e = relative_error(self.t(w, t_units), ref, tu)
        return {"surrogate": self.name, "metric": METRIC, "supercells": len(w), **error_stats(e)}

    def __repr__(self) -> str:
        return f"{type(self).__name__}(library {self.lib.identity[:12]})"
