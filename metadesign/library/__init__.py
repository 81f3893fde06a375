"""Stage 1: the RCWA unit-cell library (rectangular pillars, both polarisations)."""

from ..lazy import lazy_exports

#: each name -> the submodule that defines it (imported on first use, PEP 562)
_EXPORTS = {
    "CellResult": "rcwa", "Factorization": "rcwa", "SolverSettings": "rcwa", "Stack": "rcwa", "Truncation": "rcwa",
    "fabry_perot_t": "rcwa", "solve_cell": "rcwa", "UnitCellLibrary": "store", "export_csv": "store",
    "load_library": "store", "save_library": "store",
    # the supercell coupling model: numpy side (no torch) and the network (torch)
    "CouplingConfig": "coupling", "lpa_t": "coupling", "relative_error": "coupling", "save_coupling": "coupling",
    "tuple_t": "coupling", "coupling_card": "coupling", "is_coupling": "coupling", "transpose_supercells": "coupling", "Coupling": "coupling_net", "build_coupling": "coupling_net",
    "coupling_t": "coupling_net", "find_coupling": "coupling_net", "fit_coupling": "coupling_net",
    "load_coupling": "coupling_net", "pair_tables": "coupling_net", "pillar_terms": "coupling_net",
    # the certified supercell surrogate (cheap solves, calibrated; numpy)
    "PedsModel": "peds", "certified_t": "peds", "fit_peds": "peds", "find_peds": "peds", "load_peds": "peds",
    "save_peds": "peds", "low_fidelity_couplings": "peds", "peds_t": "peds",
    # its differentiable, batched torch twin
    "peds_t_torch": "peds_torch", "couplings_torch": "peds_torch", "solve_symmetric_t": "peds_torch",
}
__all__ = list(_EXPORTS)
__getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)
