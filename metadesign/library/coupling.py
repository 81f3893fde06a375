"""The supercell coupling model: a 2 x 2 supercell's 0th-order transmission beyond the local-periodic
approximation, fitted to supercell RCWA (:mod:`metadesign.library.supercells`) and differentiable (torch).
This module is the model's numpy side (configuration, cards, the LPA, errors, table look-ups; no torch);
the network, its fit and its evaluation are :mod:`metadesign.library.coupling_net` (torch).

Structure (stated once).  In the periodic 2 x 2 lattice every pillar ``i`` has one environment: its row
neighbour ``H(i)`` (both of them: left and right are the same pillar), its column neighbour ``V(i)`` and
its diagonal neighbour ``D(i)``.  The model is

    t_pol = mean_i t_lib,pol(w_i) + 1/4 sum_i [ G(f_i, f_H(i), f_V(i), f_D(i)) - G(f_i, f_i, f_i, f_i) ]

with ``f`` a pillar's features (its widths and its library transmissions in both polarisations) and ``G``
a small network (complex output as two reals).  Hence, by construction:

* four identical pillars give the unit cell (the library) exactly: the bracket vanishes;
* swapping the two rows or the two columns (a translation of the lattice by one pitch, which leaves the
  normally incident 0th order unchanged) permutes the terms of the sum: ``t`` is invariant;
* the mirror ``x <-> y`` maps x-polarised light on a supercell to y-polarised light on its transpose
  (pillar ``(r, c) -> (c, r)``, ``wx <-> wy``): ``t_y(w) = t_x(w^T)``, so one ``G`` serves both
  polarisations (and each solved row teaches it twice).

``G`` sees the library's ``t`` of each pillar because the near-field coupling follows the pillars' own
resonances, which the library resolves; fab perturbations that the library models (etch depth, sidewall)
enter through those ``t``, width perturbations through both.  Widths are normalised as
``(w - 0.3 um) / 0.2 um``.  Weights ship as safetensors with a JSON card (:func:`save_coupling`)."""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from ..cards import find_card, has_format, save_card_model
from ..paths import repo_root
from ..validation import ValidationError
from .locate import file_sha256, find_fitted
from .store import UnitCellLibrary

__all__ = ["CouplingConfig", "CARD_FORMAT", "W0", "WS", "transpose_supercells", "lpa_t", "save_coupling",
           "is_coupling", "unit_rms", "relative_error", "coupling_card", "tuple_t"]

CARD_FORMAT = "metadesign.coupling/1"
W0, WS = 0.3e-6, 0.2e-6


@dataclass(frozen=True)
class CouplingConfig:
    hidden: int = 96
    layers: int = 3
    ensemble: int = 1
    #: "environment": G sees a pillar and its three neighbours at once; "pair": a sum of two-body terms
    #: G(f_i, f_j, kind) over the row, column and diagonal neighbour (fewer inputs, less data needed)
    interaction: str = "environment"


def transpose_supercells(widths: np.ndarray) -> np.ndarray:
    """The x <-> y mirror image of supercells (n, 2, 2, 2): pillar (r, c) -> (c, r), (wx, wy) -> (wy, wx)."""
    return np.asarray(widths)[:, :, :, ::-1].transpose(0, 2, 1, 3)


def lpa_t(t_units: np.ndarray) -> np.ndarray:
    """The LPA's supercell ``t``: the mean of its four pillars' (n, 2, 2, 2 pol) complex -> (n, 2)."""
    return np.asarray(t_units).mean((1, 2))


def save_coupling(path: str | Path, model, lib_path: str | Path, card: dict) -> Path:
    """Weights (safetensors) at ``path`` and the card beside it (``PATH.json``, :mod:`metadesign.cards`): the
    config, the library it was fitted against (name + sha256), the table it was fitted on
    (``card["table"]``: what it was trained on) and whatever ``card`` adds (certification, learning curve)."""
    path = Path(path)
    save_card_model(path, model.state_dict(), CARD_FORMAT,
                    {"config": asdict(model.cfg),
                     "library": {"path": Path(lib_path).name, "sha256": file_sha256(lib_path)}, **card},
                    trained_on=card.get("table"))
    return path


def is_coupling(path: str | Path) -> bool:
    return has_format(path, CARD_FORMAT)


def unit_rms(t_units: np.ndarray) -> np.ndarray:
    """(n, 2) the four pillars' rms |t| per polarisation: the scale every coupling error is quoted in."""
    return np.sqrt((np.abs(np.asarray(t_units)) ** 2).mean((1, 2)))


def relative_error(t_model: np.ndarray, t_ref: np.ndarray, t_units: np.ndarray) -> np.ndarray:
    """(n, 2) ``|t_model - t_ref| / rms_i |t_i|`` (the certification metric of issue #25)."""
    return np.abs(np.asarray(t_model) - np.asarray(t_ref)) / unit_rms(t_units)


def coupling_card(lib: UnitCellLibrary, path: str | Path | None = None) -> Path:
    """The weights of the coupling model at ``path``, else of the one fitted against ``lib`` (its sha256)
    among the cards in the products' ``library/`` folder and the working directory (no torch needed)."""
    if path is not None:
        return Path(path)
    found = find_fitted(lib.identity, CARD_FORMAT, (repo_root() / "library", Path.cwd()))
    if found is not None:
        return found[0].with_name(found[1]["weights"])
    raise ValidationError(f"no supercell coupling model fitted against this library (sha256 {lib.identity[:12]}) "
                          "was found in library/; fit one (metadesign library coupling) or pass its path")


def tuple_t(tables: np.ndarray, t_atoms: np.ndarray, a: np.ndarray) -> np.ndarray:
    """(n, 2) supercell ``t`` of atom 4-tuples ``a`` (n, 2, 2) int (``a[:, r, c]``) from :func:`pair_tables`."""
    a = np.asarray(a)
    a00, a01, a10, a11 = a[:, 0, 0], a[:, 0, 1], a[:, 1, 0], a[:, 1, 1]
    out = (t_atoms[a00] + t_atoms[a01] + t_atoms[a10] + t_atoms[a11]).astype(np.complex64)
    for i, h, v, d in ((a00, a01, a10, a11), (a01, a00, a11, a10), (a10, a11, a00, a01), (a11, a10, a01, a00)):
        for p in (0, 1):
            out[:, p] += tables[0, p, i, h] + tables[1, p, i, v] + tables[2, p, i, d]
    return out / 4
