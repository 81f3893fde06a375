"""Stage 1: the RCWA unit-cell library (rectangular pillars, both polarisations), and the supercell surrogate
protocol with its resolver (the models themselves: :mod:`metadesign.library.surrogates`)."""

from __future__ import annotations

import importlib

#: each name -> the submodule that defines it (imported on first use, PEP 562)
_EXPORTS = {
    "CellResult": "rcwa", "Factorization": "rcwa", "SolverSettings": "rcwa", "Stack": "rcwa", "Truncation": "rcwa",
    "fabry_perot_t": "rcwa", "solve_cell": "rcwa", "UnitCellLibrary": "store", "export_csv": "store",
    "load_library": "store", "save_library": "store",
    # every supercell model behind one protocol, chosen by name or model file
    "SupercellSurrogate": "surrogates.base", "surrogate": "surrogates.registry",
}
#: the supercell models' kernels, exported here before they moved to :mod:`metadesign.library.surrogates`:
#: still resolved (``metadesign.library.lpa_t``), no longer listed
_MOVED = ("CouplingConfig", "lpa_t", "relative_error", "save_coupling", "tuple_t", "coupling_card", "is_coupling",
          "transpose_supercells", "Coupling", "build_coupling", "coupling_t", "find_coupling", "fit_coupling",
          "load_coupling", "pair_tables", "pillar_terms", "PedsModel", "certified_t", "fit_peds", "find_peds",
          "load_peds", "save_peds", "low_fidelity_couplings", "peds_t", "peds_t_torch", "couplings_torch",
          "solve_symmetric_t")
__all__ = list(_EXPORTS)


def __getattr__(name: str):
    if name in _EXPORTS:
        return getattr(importlib.import_module(f"{__name__}.{_EXPORTS[name]}"), name)
    if name in _MOVED:
        return getattr(importlib.import_module(f"{__name__}.surrogates"), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__():
    return sorted(_EXPORTS)
